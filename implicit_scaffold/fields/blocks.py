"""Bin geometric primitives into blocks of voxels, so a kernel visits only what matters.

A grid is cut into cubic blocks of ``block`` voxels a side, aligned on voxel 0 of
the *whole* grid whatever tile is being computed, so that the lists, and hence
the values, do not depend on how the work is tiled. Each primitive (segment,
quad, triangle, convex piece) is given by its bounding box; it is listed in every
block that its box, grown by a cut-off distance, meets. The lists are stored
compressed (CSR): ``offsets[b] .. offsets[b + 1]`` index into ``items``.
"""
from __future__ import annotations

import functools
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


@functools.lru_cache(maxsize=None)
def _binning_kernels():
    """The two passes of :func:`bin_boxes` (numba, built on first use, cached on disk)."""
    # the helpers are module globals, not closure cells: numba keys its disk cache on a closure's cells, and a
    # dispatcher pickles differently in every process (a fresh compile each run)
    global _span, _outside
    import numba as nb

    @nb.njit(cache=True, nogil=True, boundscheck=False, inline="always")
    def _span(lo, hi, i, a, origin, h, block, cutoff, whole, b0, b1):  # pragma: no cover - compiled
        """Primitive i's first block and its blocks' count along axis a (0: none): the block holding its box's
        grown end, ``floor((lo - cutoff - origin) / h / block)``, clipped to the grid and the slab's blocks."""
        first = int(np.floor((lo[i, a] - cutoff - origin[a]) / h / block - 1e-9 / block))
        last = int(np.floor((hi[i, a] + cutoff - origin[a]) / h / block + 1e-9 / block))
        first = min(max(first, 0), whole[a] - 1)
        last = min(max(last, -1), whole[a] - 1)
        if a == 0:
            first = max(first, b0) - b0
            last = min(last, b1 - 1) - b0
        return first, max(last - first + 1, 0)

    @nb.njit(cache=True, nogil=True, boundscheck=False)
    def _outside(lo, hi, i, origin, h, cutoff, whole, block):  # pragma: no cover - compiled
        out = False
        for a in range(3):
            if (hi[i, a] + cutoff - origin[a]) < -h * 1e-6:
                out = True
            if (lo[i, a] - cutoff - origin[a]) > (whole[a] * block - 1) * h + h * 1e-6:
                out = True
        return out

    @nb.njit(cache=True, nogil=True, boundscheck=False)
    def walk(lo, hi, origin, h, block, cutoff, whole, b0, b1, counts, per_block, items, fill):  # pragma: no cover
        for i in range(lo.shape[0]):
            if _outside(lo, hi, i, origin, h, cutoff, whole, block):
                continue
            fx, sx = _span(lo, hi, i, 0, origin, h, block, cutoff, whole, b0, b1)
            fy, sy = _span(lo, hi, i, 1, origin, h, block, cutoff, whole, b0, b1)
            fz, sz = _span(lo, hi, i, 2, origin, h, block, cutoff, whole, b0, b1)
            for bx in range(fx, fx + sx):
                for by in range(fy, fy + sy):
                    for bz in range(fz, fz + sz):
                        bid = (bx * counts[1] + by) * counts[2] + bz
                        if fill:
                            items[per_block[bid]] = i
                        per_block[bid] += 1

    def count_pairs(lo, hi, origin, h, block, cutoff, whole, b0, b1, counts, per_block):
        walk(lo, hi, origin, h, block, cutoff, whole, b0, b1, counts, per_block, np.zeros(0, np.int32), False)

    def fill_pairs(lo, hi, origin, h, block, cutoff, whole, b0, b1, counts, next_free, items):
        walk(lo, hi, origin, h, block, cutoff, whole, b0, b1, counts, next_free, items, True)

    return count_pairs, fill_pairs


def block_counts(grid: Grid, block: int) -> tuple[int, int, int]:
    """Blocks along each axis needed to cover `grid`."""
    return tuple(int(-(-n // block)) for n in grid.shape)


def bin_boxes(lo, hi, grid: Grid, *, block: int, cutoff: float, block_range=None, empty=np.empty) -> BlockLists:
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
    empty : callable
        ``empty(n, dtype)``, the items' array (:func:`~implicit_scaffold.opencl.aligned_empty`: a device
        reads it in place).

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
    origin = np.asarray(grid.origin, np.float64)
    # two compiled passes over the primitives (count each block's, then fill them in the primitives' order, so
    # each block's list ascends): the (primitive, block) pairs were made whole in NumPy, some ten int64 arrays
    # of them at once (the default cube's STL, 5.2 M triangles at a 3-voxel cut-off: 4.3 GB for one check)
    count_pairs, fill_pairs = _binning_kernels()
    args = (lo, hi, origin, float(grid.spacing), int(block), float(cutoff), whole.astype(np.int64), b0, b1,
            counts.astype(np.int64))
    per_block = np.zeros(nblocks, np.int64)
    count_pairs(*args, per_block)
    offsets = np.zeros(nblocks + 1, np.int64)
    np.cumsum(per_block, out=offsets[1:])
    del per_block
    if offsets[-1] > np.iinfo(np.int32).max:
        raise OverflowError(f"{int(offsets[-1]):,} (primitive, block) pairs do not fit the kernels' int32 lists")
    items = empty(int(offsets[-1]), np.int32)
    fill_pairs(*args, offsets[:-1].copy(), items)
    return BlockLists(block, tuple(int(c) for c in counts), offsets.astype(np.int32), items)
