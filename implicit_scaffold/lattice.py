"""Lattice fields on a voxel grid (stage 5), by OpenCL kernels, with NumPy references.

Paper style: ``lattice_sdf`` is the signed distance to the lattice surface (the
channels' side quads), negative in the solid, clamped at ``±cutoff``. Struts
style: ``struts_field`` is the smooth-minimum distance to the Voronoi edges; the
solid is where it is below the strut radius.

Both bin their primitives into blocks of voxels (:mod:`.blocks`) and evaluate the
grid tile by tile; tiles are whole blocks aligned on the grid's voxel 0, and a
voxel's value depends only on its global index, so neither the tiling nor the
order of the primitives changes a value.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from . import opencl
from .blocks import bin_boxes, block_counts
from .grid import Grid
from .skeleton import Skeleton

#: block edge, voxels: a work-group computes one block
BLOCK = 8


@dataclass(frozen=True)
class Primitives:
    """Packed primitives for a kernel, with coordinates relative to a grid origin."""

    kind: str
    data: np.ndarray          # float32 (m, k, 4)
    lo: np.ndarray            # float64 (m, 3), mm, relative
    hi: np.ndarray


def _pack_quads(skeleton: Skeleton, origin) -> Primitives:
    q = skeleton.quads - np.asarray(origin)
    n = skeleton.quad_normals
    data = np.zeros((len(q), 5, 4), np.float32)
    data[:, :4, :3] = q
    data[:, 4, :3] = n
    data[:, 4, 3] = np.einsum("ij,ij->i", n, q[:, 0])
    return Primitives("quads", data, q.min(axis=1), q.max(axis=1))


def _pack_pieces(skeleton: Skeleton, origin):
    origin = np.asarray(origin)
    planes = skeleton.planes.copy()
    # shifting the frame by -origin shifts d by -n.origin
    planes[:, 3] -= planes[:, :3] @ origin
    lo = skeleton.piece_lo - origin
    hi = skeleton.piece_hi - origin
    boxes = np.zeros((len(lo), 2, 4), np.float32)
    # float32 boxes are grown by a hair so rounding never drops a voxel on a face
    pad = 1e-5 * (1 + np.abs(np.concatenate([lo, hi])).max())
    boxes[:, 0, :3] = lo - pad
    boxes[:, 1, :3] = hi + pad
    return boxes, planes.astype(np.float32), skeleton.piece_start.astype(np.int32), lo, hi


def _tiles(grid: Grid, tile_blocks: int):
    """Slabs along x of `tile_blocks` blocks, each ``(x0, x1)`` in voxels."""
    step = tile_blocks * BLOCK
    return [(x0, min(x0 + step, grid.shape[0])) for x0 in range(0, grid.shape[0], step)]


def _launch(kernel, grid: Grid, buffers, scalars, *, tile_blocks, progress):
    import pyopencl as cl

    ctx, queue = opencl.context()
    cy, cz = block_counts(grid, BLOCK)[1:]
    out = np.empty(grid.shape, np.float32)
    tiles = _tiles(grid, tile_blocks)
    ny, nz = grid.shape[1:]
    pad = lambda n: -(-n // BLOCK) * BLOCK  # noqa: E731
    dev_out = cl.Buffer(ctx, cl.mem_flags.WRITE_ONLY, size=4 * (tiles[0][1] - tiles[0][0]) * ny * nz)
    for i, (x0, x1) in enumerate(tiles):
        nx = x1 - x0
        kernel(queue, (pad(nz), pad(ny), pad(nx)), (BLOCK, BLOCK, BLOCK),
               dev_out, np.int32(x0), np.int32(0), np.int32(0), np.int32(nx), np.int32(ny), np.int32(nz),
               np.int32(cy), np.int32(cz), np.float32(grid.spacing), *buffers, *scalars)
        host = np.empty((nx, ny, nz), np.float32)
        cl.enqueue_copy(queue, host, dev_out, is_blocking=True)
        out[x0:x1] = host
        if progress is not None:
            progress(i + 1, len(tiles))
    return out


def lattice_sdf(skeleton: Skeleton, grid: Grid, *, cutoff: float, tile_blocks: int = 4,
                progress: Callable[[int, int], None] | None = None) -> np.ndarray:
    """Signed distance to the paper's lattice surface on `grid`, negative in the solid.

    Parameters
    ----------
    skeleton : Skeleton
    grid : Grid
    cutoff : float, mm
        Distances beyond it are clamped to it (with their sign).
    tile_blocks : int
        Thickness of a tile along x, in blocks.
    progress : callable(done, total), optional

    Returns
    -------
    (nx, ny, nz) float32 ndarray, mm
    """
    quads = _pack_quads(skeleton, grid.origin)
    boxes, planes, plane_start, lo, hi = _pack_pieces(skeleton, grid.origin)
    rel = Grid((0.0, 0.0, 0.0), grid.spacing, grid.shape)
    qlists = bin_boxes(quads.lo, quads.hi, rel, block=BLOCK, cutoff=cutoff)
    plists = bin_boxes(lo, hi, rel, block=BLOCK, cutoff=grid.spacing * 1e-3)
    kernel = opencl.kernel("lattice", "lattice_paper", BLOCK=BLOCK)
    buffers = [opencl.to_device(qlists.offsets, np.int32), opencl.to_device(qlists.items, np.int32),
               opencl.to_device(quads.data.reshape(-1, 4)),
               opencl.to_device(plists.offsets, np.int32), opencl.to_device(plists.items, np.int32),
               opencl.to_device(boxes.reshape(-1, 4)), opencl.to_device(plane_start, np.int32),
               opencl.to_device(planes)]
    return _launch(kernel, grid, buffers, [np.float32(cutoff)],
                   tile_blocks=tile_blocks, progress=progress)


def struts_field(edges: np.ndarray, grid: Grid, *, cutoff: float, blend: float, tile_blocks: int = 4,
                 progress: Callable[[int, int], None] | None = None) -> np.ndarray:
    """Smooth-minimum distance to the struts' axes on `grid`.

    ``F = -k ln Σ_i exp(-d_i / k)`` over the edges with ``d_i < cutoff`` (the plain
    minimum when ``k = 0``), clamped at `cutoff`; the solid of strut radius ``r`` is
    ``F < r``.

    Parameters
    ----------
    edges : (ne, 2, 3) float ndarray, mm
    grid : Grid
    cutoff : float, mm
    blend : float, mm
        The smoothing width ``k``.

    Returns
    -------
    (nx, ny, nz) float32 ndarray, mm
    """
    seg = np.asarray(edges, np.float64) - np.asarray(grid.origin)
    data = np.zeros((len(seg), 2, 4), np.float32)
    data[:, :, :3] = seg
    rel = Grid((0.0, 0.0, 0.0), grid.spacing, grid.shape)
    lists = bin_boxes(seg.min(axis=1), seg.max(axis=1), rel, block=BLOCK, cutoff=cutoff)
    kernel = opencl.kernel("lattice", "lattice_struts", BLOCK=BLOCK)
    buffers = [opencl.to_device(lists.offsets, np.int32), opencl.to_device(lists.items, np.int32),
               opencl.to_device(data.reshape(-1, 4))]
    return _launch(kernel, grid, buffers, [np.float32(cutoff), np.float32(blend)],
                   tile_blocks=tile_blocks, progress=progress)


# --- slow, obviously right references (the tests' oracles) -------------------------

def _segment_dist(p, a, b):
    ab = b - a
    len2 = np.einsum("...i,...i->...", ab, ab)
    t = np.clip(np.einsum("...i,...i->...", p - a, ab) / np.where(len2 > 0, len2, 1), 0, 1)
    return np.linalg.norm(p - a - t[..., None] * ab, axis=-1)


def quad_distance_reference(points, quads) -> np.ndarray:
    """Exact distance from each point to each planar convex quad, ``(m, nq)``, float64."""
    p = np.asarray(points, np.float64)[:, None, :]
    q = np.asarray(quads, np.float64)[None]
    n = np.cross(q[..., 2, :] - q[..., 0, :], q[..., 3, :] - q[..., 1, :])
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    inside = np.ones(p.shape[0:1] + q.shape[1:2], bool)
    edge = []
    for i in range(4):
        a, b = q[..., i, :], q[..., (i + 1) % 4, :]
        inside &= np.einsum("...i,...i->...", np.cross(b - a, p - a), n) >= 0
        edge.append(_segment_dist(p, a, b))
    plane = np.abs(np.einsum("...i,...i->...", p - q[..., 0, :], n))
    return np.where(inside, plane, np.min(edge, axis=0))


def lattice_sdf_reference(skeleton: Skeleton, points, *, cutoff: float = np.inf) -> np.ndarray:
    """Brute-force :func:`lattice_sdf` at `points` ``(m, 3)`` mm: every quad, every piece."""
    p = np.asarray(points, np.float64)
    dist = np.full(len(p), np.inf)
    for chunk in range(0, len(skeleton.quads), 2000):
        dist = np.minimum(dist, quad_distance_reference(p, skeleton.quads[chunk:chunk + 2000]).min(axis=1))
    in_void = np.zeros(len(p), bool)
    planes = skeleton.planes
    for i in range(len(skeleton.piece_start) - 1):
        pl = planes[skeleton.piece_start[i]:skeleton.piece_start[i + 1]]
        in_void |= np.all(p @ pl[:, :3].T - pl[:, 3] <= 0, axis=1)
    dist = np.minimum(dist, cutoff)
    return np.where(in_void, dist, -dist)


def struts_field_reference(edges, points, *, cutoff: float, blend: float) -> np.ndarray:
    """Brute-force :func:`struts_field` at `points` ``(m, 3)`` mm: every edge."""
    p = np.asarray(points, np.float64)[:, None, :]
    e = np.asarray(edges, np.float64)[None]
    d = _segment_dist(p, e[..., 0, :], e[..., 1, :])
    m = np.minimum(d.min(axis=1), cutoff)
    if blend > 0:
        w = np.where(d < cutoff, np.exp(-(d - m[:, None]) / blend), 0.0).sum(axis=1)
        near = m < cutoff
        m = np.where(near, np.minimum(m - blend * np.log(np.where(near, w, 1.0)), cutoff), m)
    return m
