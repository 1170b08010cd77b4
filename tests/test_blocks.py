"""The block lists of fields.blocks against a brute-force oracle: each (primitive, block) pair decided alone."""
import numpy as np
import pytest

from implicit_scaffold.fields.blocks import bin_boxes, block_counts
from implicit_scaffold.run.grid import Grid


def _brute_force(lo, hi, grid, block, cutoff, block_range):
    """Block b lists primitive i when, on every axis, i's box grown by `cutoff` meets the block's cells
    ``[b, b + 1) * block * h`` from the origin (the first block reaching down without end, the last up), and
    the box reaches the grid: not wholly below its first voxel centre or above its last."""
    whole = np.array(block_counts(grid, block))
    b0, b1 = (0, whole[0]) if block_range is None else block_range
    cell = block * grid.spacing
    lists = {}
    for bx in range(b0, b1):
        for by in range(whole[1]):
            for bz in range(whole[2]):
                b = (bx, by, bz)
                listed = []
                for i in range(len(lo)):
                    meets = True
                    for a in range(3):
                        g_lo = lo[i, a] - cutoff - grid.origin[a]
                        g_hi = hi[i, a] + cutoff - grid.origin[a]
                        if g_hi < 0 or g_lo > (whole[a] * block - 1) * grid.spacing:
                            meets = False  # the box misses the grid on this axis
                        start = -np.inf if b[a] == 0 else b[a] * cell
                        stop = np.inf if b[a] == whole[a] - 1 else (b[a] + 1) * cell
                        if g_hi < start or g_lo >= stop:
                            meets = False
                    if meets:
                        listed.append(i)
                lists[((bx - b0) * whole[1] + by) * whole[2] + bz] = listed
    return lists


@pytest.mark.parametrize("seed", range(12))
def test_block_lists_are_the_brute_force_pairs_in_ascending_order(seed):
    rng = np.random.default_rng(seed)
    grid = Grid(tuple(rng.normal(size=3)), float(rng.uniform(0.05, 0.3)), tuple(int(v) for v in rng.integers(3, 20, 3)))
    m = int(rng.integers(1, 40))
    lo = rng.uniform(-2.0, 6.0, (m, 3))
    hi = lo + rng.uniform(0.0, 1.5, (m, 3))
    block = int(rng.choice([2, 4, 8]))
    cutoff = float(rng.uniform(0.0, 0.8))
    nx = block_counts(grid, block)[0]
    b0 = int(rng.integers(0, nx))
    for block_range in (None, (b0, int(rng.integers(b0 + 1, nx + 1)))):
        got = bin_boxes(lo, hi, grid, block=block, cutoff=cutoff, block_range=block_range)
        want = _brute_force(lo, hi, grid, block, cutoff, block_range)
        assert got.offsets.dtype == np.int32 and got.items.dtype == np.int32
        assert len(got.offsets) == len(want) + 1
        for b, listed in want.items():
            assert got.items[got.offsets[b]:got.offsets[b + 1]].tolist() == listed, (block_range, b)


def test_no_primitives_gives_empty_lists():
    grid = Grid((0.0, 0.0, 0.0), 0.1, (9, 5, 4))
    got = bin_boxes(np.zeros((0, 3)), np.zeros((0, 3)), grid, block=4, cutoff=0.2)
    assert got.counts == (3, 2, 1) and not got.offsets.any() and got.items.size == 0
