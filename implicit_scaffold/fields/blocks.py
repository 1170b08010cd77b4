"""Bin geometric primitives into blocks of voxels, so a kernel visits only what matters.

A grid is cut into cubic blocks of ``block`` voxels a side, aligned on voxel 0 of
the *whole* grid whatever tile is being computed, so that the lists, and hence
the values, do not depend on how the work is tiled. Each primitive (segment,
quad, triangle, convex piece) is given by its bounding box; it is listed in every
block that its box, grown by a cut-off distance, meets. The lists are stored
compressed (CSR): ``offsets[b] .. offsets[b + 1]`` index into ``items``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..run.grid import Grid


@dataclass(frozen=True)
class BlockLists:
    """Primitives listed per block of voxels.

    Attributes
    ----------
    block : int
        Block edge, voxels.
    counts : (3,) tuple of int
        Blocks along x, y, z (the grid rounded up to whole blocks).
    offsets : (nblocks + 1,) int32 ndarray
    items : (nitems,) int32 ndarray
        Primitive indices, ascending within each block.
    """

    block: int
    counts: tuple[int, int, int]
    offsets: np.ndarray
    items: np.ndarray

    def lengths(self) -> np.ndarray:
        """Number of primitives listed in each block."""
        return np.diff(self.offsets)


def block_counts(grid: Grid, block: int) -> tuple[int, int, int]:
    """Blocks along each axis needed to cover `grid`."""
    return tuple(int(-(-n // block)) for n in grid.shape)


def bin_boxes(lo, hi, grid: Grid, *, block: int, cutoff: float, block_range=None) -> BlockLists:
    """List each box ``[lo_i, hi_i]``, grown by `cutoff`, in every block of voxel centres it meets.

    Parameters
    ----------
    lo, hi : (m, 3) float ndarray, mm
        Bounding boxes of the primitives.
    grid : Grid
    block : int
        Block edge, voxels.
    cutoff : float, mm
        Distance beyond which a primitive cannot change a voxel's value.
    block_range : (b0, b1), optional
        Only the blocks ``b0 <= bx < b1`` along x (a slab of a tiled run), numbered
        from ``b0``; their lists are those of the whole grid.

    Returns
    -------
    BlockLists
    """
    lo = np.asarray(lo, dtype=np.float64).reshape(-1, 3)
    hi = np.asarray(hi, dtype=np.float64).reshape(-1, 3)
    counts = np.array(block_counts(grid, block))
    b0, b1 = (0, int(counts[0])) if block_range is None else (int(v) for v in block_range)
    whole = counts.copy()
    counts[0] = b1 - b0
    nblocks = int(np.prod(counts))
    if len(lo) == 0:
        return BlockLists(block, tuple(int(c) for c in counts),
                          np.zeros(nblocks + 1, np.int32), np.zeros(0, np.int32))
    origin = np.asarray(grid.origin)
    h = grid.spacing
    # block b along an axis holds voxel centres origin + [b*block, (b+1)*block - 1] * h
    first = np.floor((lo - cutoff - origin) / h / block - 1e-9 / block).astype(np.int64)
    last = np.floor((hi + cutoff - origin) / h / block + 1e-9 / block).astype(np.int64)
    first = np.clip(first, 0, whole - 1)
    last = np.clip(last, -1, whole - 1)
    # a box entirely beyond the grid on some axis gets an empty range
    outside = np.any((hi + cutoff - origin) < -h * 1e-6, axis=1) | np.any(
        (lo - cutoff - origin) > (whole * block - 1) * h + h * 1e-6, axis=1)
    # then the slab's blocks only, numbered from its first
    first[:, 0] = np.maximum(first[:, 0], b0) - b0
    last[:, 0] = np.minimum(last[:, 0], b1 - 1) - b0
    span = np.where(outside[:, None], 0, np.maximum(last - first + 1, 0))
    per = np.prod(span, axis=1)
    total = int(per.sum())
    prim = np.repeat(np.arange(len(lo), dtype=np.int64), per)
    # position of each emitted pair inside its primitive's sub-box of blocks
    start = np.repeat(np.cumsum(per) - per, per)
    local = np.arange(total, dtype=np.int64) - start
    sy, sz = span[prim, 1], span[prim, 2]
    bx = first[prim, 0] + local // (sy * sz)
    by = first[prim, 1] + (local // sz) % sy
    bz = first[prim, 2] + local % sz
    bid = (bx * counts[1] + by) * counts[2] + bz
    # pairs come out grouped by primitive, in ascending order: a stable sort by
    # block keeps each block's primitives ascending
    order = np.argsort(bid, kind="stable")
    items = prim[order].astype(np.int32)
    offsets = np.zeros(nblocks + 1, np.int64)
    np.cumsum(np.bincount(bid, minlength=nblocks), out=offsets[1:])
    return BlockLists(block, tuple(int(c) for c in counts), offsets.astype(np.int32), items)
