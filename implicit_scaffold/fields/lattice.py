"""Lattice fields on a voxel grid (stage 5), by OpenCL kernels, with NumPy references.

Paper style: ``lattice_sdf`` is the signed distance to the lattice surface (the
channels' side quads), negative in the solid, clamped at ``±cutoff``. Struts
style: ``struts_field`` is the smooth-minimum distance to the Voronoi edges; the
solid is where it is below the strut radius.

Both bin their primitives into blocks of 8^3 voxels on the device
(:func:`bin_on_device`): each block keeps the primitives that can matter to one
of its voxels, sorted by their distance from the block's centre, so that a
voxel's loop stops as soon as no later primitive can be nearer than its best.
The paper style's sign comes from the nearest quad where that quad is nearest
through its face, and from the convex pieces (binned on the host by
:mod:`~implicit_scaffold.fields.blocks`) elsewhere. The kernels compute 16 voxels per work-item (8 along z
in 2 rows along y) as one vector. The grid is evaluated tile by tile; tiles are
whole blocks aligned on the grid's voxel 0, and a voxel's value depends only on
its global index and its block's list, so neither the tiling nor the order of
the primitives changes a value.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from .. import opencl
from .blocks import bin_boxes, block_counts
from ..errors import ScaffoldError
from ..run.grid import Grid
from ..geometry.skeleton import Skeleton

#: block edge, voxels: a work-group computes one block
BLOCK = 8
#: float4 words per packed quad (kernels/lattice.cl, QUAD_WORDS)
QUAD_WORDS = 9
#: blocks per work-group of the lists' sort (``bin_sort`` in kernels/lattice.cl)
SORT_GROUP = 8


@dataclass(frozen=True)
class Primitives:
    """Packed primitives for a kernel, with coordinates relative to a grid origin."""

    kind: str
    data: np.ndarray          # float32 (m, k, 4)
    lo: np.ndarray            # float64 (m, 3), mm, relative
    hi: np.ndarray


#: quads packed at once: the frames' float64 temporaries take about 1 KB per quad
_PACK_CHUNK = 200_000


def _pack_quads(skeleton: Skeleton, origin) -> Primitives:
    """Quads in their own frames, as the row kernels read them (see ``kernels/lattice.cl``).

    Frame of quad i: origin at vertex 0, ``U`` along the in-plane part of the
    diagonal v0 -> v2, ``W = n x U``, and the unit normal ``n``; the kernel gets each
    axis with its offset (``c = A . p + A.w``), the vertices and edges in (U, W)
    coordinates, and the edges divided by their squared lengths. Packed
    :data:`_PACK_CHUNK` quads at a time (each quad's words are its own).
    """
    m = len(skeleton.quads)
    data = np.zeros((m, QUAD_WORDS, 4), np.float32)
    lo, hi = np.empty((m, 3)), np.empty((m, 3))
    origin = np.asarray(origin)
    for a in range(0, m, _PACK_CHUNK):
        b = min(a + _PACK_CHUNK, m)
        q = skeleton.quads[a:b] - origin
        n = skeleton.quad_normals[a:b]
        d1 = q[:, 2] - q[:, 0]
        u = d1 - np.einsum("ij,ij->i", d1, n)[:, None] * n
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        w = np.cross(n, u)
        rel = q - q[:, :1]
        xy = np.stack([np.einsum("ikj,ij->ik", rel, u), np.einsum("ikj,ij->ik", rel, w)], axis=-1)  # (m, 4, 2)
        e = np.roll(xy, -1, axis=1) - xy
        len2 = np.einsum("ikj,ikj->ik", e, e)
        s = e / np.where(len2 > 0, len2, np.inf)[..., None]
        for row, axis in enumerate((u, w, n)):
            data[a:b, row, :3] = axis
            data[a:b, row, 3] = -np.einsum("ij,ij->i", axis, q[:, 0])
        data[a:b, 3:5] = xy.reshape(-1, 2, 4)
        data[a:b, 5:7] = e.reshape(-1, 2, 4)
        data[a:b, 7:9] = s.reshape(-1, 2, 4)
        lo[a:b], hi[a:b] = q.min(axis=1), q.max(axis=1)
    return Primitives("quads", data, lo, hi)


def _pack_pieces(skeleton: Skeleton, origin):
    origin = np.asarray(origin)
    planes = skeleton.planes.copy()
    # shifting the frame by -origin shifts d by -n.origin
    planes[:, 3] -= planes[:, :3] @ origin
    # The two channels that meet at a window each have their own rim plane; in
    # float32 the two may leave a gap of an ulp between them, where a voxel would
    # be in neither. Every plane is widened by a few ulps: whatever that changes
    # lies within the same few ulps of the surface, or of a window rim in a wall of
    # the box (where float64 itself cannot tell which side a point is on).
    planes[:, 3] += _ulps(np.abs(planes[:, 3]).max() + np.abs(origin).max(), 8)
    lo = skeleton.piece_lo - origin
    hi = skeleton.piece_hi - origin
    boxes = np.zeros((len(lo), 2, 4), np.float32)
    # float32 boxes are grown by a hair so rounding never drops a voxel on a face
    pad = 1e-5 * (1 + np.abs(np.concatenate([lo, hi])).max())
    boxes[:, 0, :3] = lo - pad
    boxes[:, 1, :3] = hi + pad
    return boxes, planes.astype(np.float32), skeleton.piece_start.astype(np.int32), lo, hi


#: the last primitives packed for a grid, kept for the next slab of the same run:
#: (weak reference to the primitives' owner, grid, OpenCL context, packed)
_PACKED: dict = {}


def _packed(owner, grid: Grid, pack):
    """``pack(owner, grid)``, computed once per owner and grid: a tiled run's slabs share it.

    The owner (a Skeleton) is held by a weak reference, so a new owner at a recycled
    address is never mistaken for the old one; and what was packed for it goes with it.
    """
    import weakref

    ctx, _ = opencl.context()
    hit = _PACKED.get(pack)
    # the device buffers belong to one context: another device packs again
    if hit is not None and hit[0]() is owner and hit[1] == grid and hit[2] is ctx:
        return hit[3]
    _PACKED.pop(pack, None)
    packed = pack(owner, grid)

    def forget(ref):
        # a slab's own skeleton (SkeletonSource.near) dies with its slab, and no later slab can
        # ask for its primitives: kept, they sat beside the next slab's skeleton as it was built,
        # which the plan does not count (0.7 GiB over --max-memory on the L3 vertebra)
        if _PACKED.get(pack, (None,))[0] is ref:
            del _PACKED[pack]

    _PACKED[pack] = (weakref.ref(owner, forget), grid, ctx, packed)
    return packed


def release_packed() -> None:
    """Free what :func:`lattice_sdf` kept for the next slab (a tiled run calls it after its slabs)."""
    _PACKED.clear()


def _pack_paper(skeleton: Skeleton, grid: Grid):
    """Quads and pieces of `skeleton` in `grid`'s frame, on the host and the device."""
    from types import SimpleNamespace

    quads = _pack_quads(skeleton, grid.origin)
    quad_buffer = opencl.to_device(quads.data.reshape(-1, 4))
    # the device holds its own copy: only the boxes stay on the host, for binning
    quads = Primitives(quads.kind, np.zeros((0, QUAD_WORDS, 4), np.float32), quads.lo, quads.hi)
    boxes, planes, plane_start, lo, hi = _pack_pieces(skeleton, grid.origin)
    return SimpleNamespace(quads=quads, quad_buffer=quad_buffer,
                           piece_lo=lo, piece_hi=hi, piece_boxes=opencl.to_device(boxes.reshape(-1, 4)),
                           plane_start=opencl.to_device(plane_start, np.int32),
                           planes=opencl.to_device(planes))


def packed_bytes(*, cells=None, edges=None) -> int:
    """Bytes the lattice stage holds for its primitives: for the paper style (`cells`), the
    skeleton (:func:`~implicit_scaffold.geometry.skeleton.skeleton_bytes`) and its quads and pieces packed for the
    device (a CPU device's buffers are host memory too); for struts, the packed `edges`.
    """
    if cells is not None:
        from ..geometry.skeleton import skeleton_bytes

        m, nf = len(cells.face_vertices), len(cells.face_cell)
        planes, pieces = m + 3 * nf, cells.n + nf
        # device quads; quad boxes (float64 on the host, float32 to bin); pieces' boxes, planes and starts
        return skeleton_bytes(cells) + m * (QUAD_WORDS * 16 + 48 + 32) + planes * 16 + pieces * (32 + 48 + 4)
    if edges is not None:
        return len(edges) * (32 + 48 + 32)
    return 0


def _ulps(magnitude: float, n: int) -> float:
    """`n` float32 units in the last place at `magnitude` (mm)."""
    return float(n * np.spacing(np.float32(max(magnitude, 1.0))))


def _tiles(grid: Grid, tile_blocks: int, x_range=None):
    """Slabs along x of `tile_blocks` blocks within `x_range`, each ``(x0, x1)`` in voxels.

    Tiles after the first start on a block boundary of the whole grid.
    """
    lo, hi = _check_range(grid, x_range)
    step = tile_blocks * BLOCK
    cuts = [lo] + list(range((lo // step + 1) * step, hi, step)) + [hi]
    return list(zip(cuts[:-1], cuts[1:]))


def _check_range(grid: Grid, x_range) -> tuple[int, int]:
    if x_range is None:
        return 0, grid.shape[0]
    lo, hi = (int(v) for v in x_range)
    if not 0 <= lo < hi <= grid.shape[0]:
        raise ValueError(f"x_range {x_range} outside the grid's 0..{grid.shape[0]} planes")
    return lo, hi


def _block_range(grid: Grid, x_range) -> tuple[int, int]:
    """Blocks along x, ``[b0, b1)``, that hold the planes of `x_range`."""
    lo, hi = _check_range(grid, x_range)
    return lo // BLOCK, -(-hi // BLOCK)


def _default_tile_blocks(grid: Grid) -> int:
    """Tiles of about 8 M voxels: few launches, a bounded device buffer."""
    slab = BLOCK * grid.shape[1] * grid.shape[2]
    return max(1, (8 << 20) // slab)


def _launch_rows(kernel, grid: Grid, buffers, scalars, *, tile_blocks, progress, x_range=None):
    """Run a row kernel (kernels/lattice.cl, ROW_ARGS) over the planes `x_range` of `grid`, tile by tile."""
    cy, cz = block_counts(grid, BLOCK)[1:]
    lo, hi = _check_range(grid, x_range)
    b0 = _block_range(grid, x_range)[0]
    ny, nz = grid.shape[1:]
    pad = lambda n: -(-n // BLOCK) * BLOCK  # noqa: E731
    # a work-item computes 8 voxels along z in 2 rows along y; a work-group, one block
    return opencl.launch_tiles(
        kernel, _tiles(grid, tile_blocks if tile_blocks is not None else _default_tile_blocks(grid), x_range),
        np.empty((hi - lo,) + tuple(grid.shape[1:]), np.float32), first=lo, progress=progress,
        sizes=lambda nx: ((cz, pad(ny) // 2, pad(nx)), (1, BLOCK // 2, BLOCK)),
        args=lambda x0, nx: (np.int32(x0), np.int32(nx), np.int32(ny), np.int32(nz), np.int32(b0),
                             np.int32(cy), np.int32(cz), np.float32(grid.spacing), *buffers, *scalars))


def _slack(grid: Grid, *boxes) -> float:
    """Margin for float32 rounding in distances between points of `grid` and primitives, mm.

    Distances computed in float32 from coordinates of magnitude ``L`` are off by a
    few ulps of ``L``; culling bounds are loosened by many more, so that rounding
    can never drop a primitive that could be nearest.
    """
    extent = float(np.max(np.asarray(grid.shape) * grid.spacing))
    for b in boxes:
        if len(b):
            extent = max(extent, float(np.abs(b).max()))
    return 64 * _ulps(extent, 1)


def blocks_beyond(patient_planes: np.ndarray, grid: Grid, x_range, *, reach: float, halo: int = 0) -> np.ndarray:
    """The blocks of planes `x_range` whose lattice values cannot change the scaffold.

    The scaffold is ``max(lattice - level, patient)`` (smoothed within the smooth cut's
    width), and the lattice, clamped at its cut-off ``c``, lies in ``[-c, c]``, as does the
    level. Wherever the patient's distance is at least ``2 c`` plus the smooth cut, the
    scaffold is the patient's distance whatever the lattice's value, bit for bit. A block
    all of whose voxels, and every voxel within `halo` of them (the blend's reach), lie that
    far outside the patient is skipped: its lists stay empty, so the kernels make nothing
    there (a value within the cut-off).

    Parameters
    ----------
    patient_planes : (x1 - x0, ny, nz) ndarray, mm
        The patient's signed distance on the planes of `x_range`.
    grid : Grid
    x_range : (x0, x1)
    reach : float, mm
        The patient distance from which the lattice does not count.
    halo : int
        Voxels beyond a block whose values its values change (the blend's).

    Returns
    -------
    (b1 - b0, by, bz) bool ndarray
        Per block of :func:`_block_range`, True where the block can be skipped.
    """
    x0, x1 = _check_range(grid, x_range)
    b0, b1 = _block_range(grid, x_range)
    by, bz = block_counts(grid, BLOCK)[1:]
    ny, nz = grid.shape[1:]
    # voxels beyond the planes or the grid do not count: they are never stored
    near = np.zeros(((b1 - b0) * BLOCK, by * BLOCK, bz * BLOCK), bool)
    np.less(patient_planes, reach, out=near[x0 - b0 * BLOCK:x1 - b0 * BLOCK, :ny, :nz])
    near_block = near.reshape(b1 - b0, BLOCK, by, BLOCK, bz, BLOCK).any(axis=(1, 3, 5))
    del near
    grow = -(-int(halo) // BLOCK)
    if grow:
        from scipy import ndimage

        near_block = ndimage.binary_dilation(near_block, np.ones((2 * grow + 1,) * 3, bool))
    return ~near_block


def _skip_buffer(skip, n_blocks: int):
    flags = np.zeros(n_blocks, np.uint8) if skip is None else np.ascontiguousarray(skip, np.uint8).reshape(-1)
    if flags.size != n_blocks:
        raise ValueError(f"skip holds {flags.size} blocks, the planes {n_blocks}")
    return opencl.to_device(flags, np.uint8)


def bin_on_device(kind: str, buffer, lo, hi, grid: Grid, *, cutoff: float, x_range=None, skip=None):
    """Bin primitives into blocks of voxels and sort each block's list, on the device.

    ``kind`` is ``"quad"`` (lists cut to the quads that can be nearest for some
    voxel of the block) or ``"seg"`` (every segment within the cut-off); see
    ``quad_bin_*``, ``seg_bin_*`` and ``bin_sort`` in ``kernels/lattice.cl``. The
    lists depend only on the primitives and the grid, neither on the primitives'
    order nor on a tiling.

    Parameters
    ----------
    kind : str
    buffer : device buffer of the packed primitives
    lo, hi : (m, 3) float ndarray, mm, relative to the grid's origin
        Bounding boxes.
    grid : Grid
    cutoff : float, mm
    x_range : (x0, x1), optional
        Bin only the blocks that hold these planes (all by default); block ``b``
        below counts from the first of them.
    skip : (bx, by, bz) bool ndarray, optional
        Blocks that get no primitive (:func:`blocks_beyond`).

    Returns
    -------
    offsets, counts, items, keys : device buffers
        Block ``b``'s primitives are ``items[offsets[b] : offsets[b] + counts[b]]``,
        in ascending order of ``keys`` (their distance from the block's centre, mm),
        ties by index.
    """
    import pyopencl as cl

    ctx, queue = opencl.context()
    by, bz = block_counts(grid, BLOCK)[1:]
    b0, b1 = _block_range(grid, x_range)
    bx = b1 - b0
    n_blocks = bx * by * bz
    m = len(lo)
    boxes = np.zeros((max(m, 1), 2, 4), np.float32)
    boxes[:m, 0, :3] = lo
    boxes[:m, 1, :3] = hi
    common = [buffer, opencl.to_device(boxes.reshape(-1, 4)), np.int32(m), _skip_buffer(skip, n_blocks), np.int32(b0),
              np.int32(bx), np.int32(by), np.int32(bz), np.float32(grid.spacing),
              np.float32(cutoff), np.float32(_slack(grid, lo, hi))]
    rw = cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR
    counts = cl.Buffer(ctx, rw, hostbuf=np.zeros(n_blocks, np.int32))
    fill = cl.Buffer(ctx, rw, hostbuf=np.zeros(n_blocks, np.int32))
    extra = []
    if kind == "quad":
        extra = [cl.Buffer(ctx, rw, hostbuf=np.full(n_blocks, np.float32(np.inf).view(np.int32), np.int32))]
    if m:
        opencl.kernel("lattice", f"{kind}_bin_count", BLOCK=BLOCK)(queue, (m,), None, *common, counts, *extra)
    host_counts = np.empty(n_blocks, np.int32)
    cl.enqueue_copy(queue, host_counts, counts, is_blocking=True)
    offsets = np.zeros(n_blocks + 1, np.int64)
    np.cumsum(host_counts, out=offsets[1:])
    if offsets[-1] >= 2 ** 31:
        raise ScaffoldError(f"the block lists hold {offsets[-1]} entries, too many for one pass; "
                            "use a larger --voxel")
    offsets_dev = opencl.to_device(offsets, np.int32)
    items = cl.Buffer(ctx, cl.mem_flags.READ_WRITE, size=4 * max(int(offsets[-1]), 1))
    keys = cl.Buffer(ctx, cl.mem_flags.READ_WRITE, size=4 * max(int(offsets[-1]), 1))
    if m:
        opencl.kernel("lattice", f"{kind}_bin_fill", BLOCK=BLOCK)(
            queue, (m,), None, *common, *extra, offsets_dev, fill, items, keys)
    # small work-groups: left to choose, Intel's CPU runtime packs 16 blocks into one vector,
    # whose lanes then take every path of the others' heaps (the femoral shaft's 0.02 mm slab:
    # 0.38 s of CPU to sort, 0.17 s in groups of 8)
    opencl.kernel("lattice", "bin_sort", BLOCK=BLOCK)(
        queue, (-(-n_blocks // SORT_GROUP) * SORT_GROUP,), (SORT_GROUP,), offsets_dev, fill, items, keys,
        np.int32(n_blocks))
    return offsets_dev, fill, items, keys


def lattice_sdf(skeleton: Skeleton, grid: Grid, *, cutoff: float, tile_blocks: int | None = None,
                progress: Callable[[int, int], None] | None = None, x_range=None, skip=None) -> np.ndarray:
    """Signed distance to the paper's lattice surface on `grid`, negative in the solid.

    Parameters
    ----------
    skeleton : Skeleton
    grid : Grid
    cutoff : float, mm
        Distances beyond it are clamped to it (with their sign).
    tile_blocks : int, optional
        Thickness of a tile along x, in blocks; by default tiles of about 8 M voxels.
        The values do not depend on it.
    progress : callable(done, total), optional
    x_range : (x0, x1), optional
        Only the planes ``x0 <= i < x1`` of `grid` (a slab of a tiled run): the same
        bits as those planes of the whole grid, for a fraction of the memory.
    skip : (bx, by, bz) bool ndarray, optional
        Blocks of those planes left out (:func:`blocks_beyond`): their values are
        ``-cutoff``, the rest's unchanged.

    Returns
    -------
    (x1 - x0, ny, nz) float32 ndarray, mm
        ``(nx, ny, nz)`` without `x_range`.
    """
    # a slab of a tiled run reuses what the previous slab packed; a whole grid packs once
    packed = _packed(skeleton, grid, _pack_paper) if x_range is not None else _pack_paper(skeleton, grid)
    quads, lo, hi = packed.quads, packed.piece_lo, packed.piece_hi
    rel = Grid((0.0, 0.0, 0.0), grid.spacing, grid.shape)
    plists = bin_boxes(lo, hi, rel, block=BLOCK, cutoff=grid.spacing * 1e-3,
                       block_range=_block_range(grid, x_range))
    if skip is not None:
        plists = _without(plists, np.asarray(skip, bool).reshape(-1))
    qoffsets, qcounts, qitems, qkeys = bin_on_device("quad", packed.quad_buffer, quads.lo, quads.hi, grid,
                                                     cutoff=cutoff, x_range=x_range, skip=skip)
    kernel = opencl.kernel("lattice", "lattice_paper", BLOCK=BLOCK)
    buffers = [qoffsets, qcounts, qitems, qkeys, packed.quad_buffer,
               opencl.to_device(plists.offsets, np.int32), opencl.to_device(plists.items, np.int32),
               packed.piece_boxes, packed.plane_start, packed.planes]
    from pyopencl import cltypes

    slack = _slack(grid, quads.lo, quads.hi)
    # the box of the cells, shrunk by the slack: inside it a quad's side is the sign
    cells = skeleton.cells
    box_lo = np.asarray(cells.lo, np.float64) - np.asarray(grid.origin) + slack
    box_hi = np.asarray(cells.hi, np.float64) - np.asarray(grid.origin) - slack
    return _launch_rows(kernel, grid, buffers,
                        [np.float32(cutoff), np.float32(slack), cltypes.make_float4(*box_lo, 0.0),
                         cltypes.make_float4(*box_hi, 0.0)],
                        tile_blocks=tile_blocks, progress=progress, x_range=x_range)


def _without(lists, skip: np.ndarray):
    """Block lists with the `skip` blocks' emptied."""
    from .blocks import BlockLists

    lengths = lists.lengths()
    keep = np.where(skip, 0, lengths)
    offsets = np.zeros(len(lengths) + 1, np.int64)
    np.cumsum(keep, out=offsets[1:])
    items = lists.items[np.repeat(~skip, lengths)]
    return BlockLists(lists.block, lists.counts, offsets.astype(np.int32), items)


def struts_field(edges: np.ndarray, grid: Grid, *, cutoff: float, blend: float,
                 tile_blocks: int | None = None,
                 progress: Callable[[int, int], None] | None = None, x_range=None, skip=None) -> np.ndarray:
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
    tile_blocks : int, optional
        Thickness of a tile along x, in blocks; by default tiles of about 8 M voxels.
        The values do not depend on it.
    progress : callable(done, total), optional
    x_range : (x0, x1), optional
        Only these planes of `grid`, as :func:`lattice_sdf`.
    skip : (bx, by, bz) bool ndarray, optional
        Blocks left out, as :func:`lattice_sdf` (their values are ``cutoff``).

    Returns
    -------
    (x1 - x0, ny, nz) float32 ndarray, mm
        ``(nx, ny, nz)`` without `x_range`.
    """
    seg = np.asarray(edges, np.float64).reshape(-1, 2, 3) - np.asarray(grid.origin)
    ab = seg[:, 1] - seg[:, 0]
    len2 = np.einsum("ij,ij->i", ab, ab)
    data = np.zeros((len(seg), 2, 4), np.float32)
    data[:, 0, :3] = seg[:, 0]
    data[:, 0, 3] = np.where(len2 > 0, 1 / np.where(len2 > 0, len2, 1), 0)
    data[:, 1, :3] = ab
    buffer = opencl.to_device(data.reshape(-1, 4))
    offsets, counts, items, keys = bin_on_device("seg", buffer, seg.min(axis=1), seg.max(axis=1), grid,
                                                 cutoff=cutoff, x_range=x_range, skip=skip)
    kernel = opencl.kernel("lattice", "lattice_struts", BLOCK=BLOCK)
    return _launch_rows(kernel, grid, [offsets, counts, items, keys, buffer],
                        [np.float32(cutoff), np.float32(blend),
                         np.float32(_slack(grid, seg.min(axis=1), seg.max(axis=1)))],
                        tile_blocks=tile_blocks, progress=progress, x_range=x_range)


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
