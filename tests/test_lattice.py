"""The OpenCL lattice kernels against brute-force NumPy over every primitive."""
import numpy as np
import pytest

from implicit_scaffold.grid import Grid
from implicit_scaffold.lattice import (lattice_sdf, lattice_sdf_reference, struts_field,
                                       struts_field_reference)
from implicit_scaffold.skeleton import scaled_skeleton, voronoi_edges

# float32 coordinates of a few mm carry ~1e-6 mm of rounding; 1e-4 mm is the bound
TOL = 1e-4


def _grid(cells, h, shape=None):
    if shape is None:
        return Grid.covering(cells.lo, cells.hi, h)
    return Grid(tuple(cells.lo - h / 3), h, shape)


def _sample(grid, n, rng):
    idx = np.stack([rng.integers(0, s, n) for s in grid.shape], 1)
    return idx, grid.indices_to_points(idx)


@pytest.mark.parametrize("sf, sv", [(0.75, 0.75), (0.4, 0.6)])
def test_paper_kernel_matches_reference(small_cells, sf, sv):
    sk = scaled_skeleton(small_cells, sf, sv)
    # odd sizes that do not divide into 8^3 work-groups
    grid = _grid(small_cells, 0.05, shape=(61, 53, 43))
    cutoff = 0.15
    field = lattice_sdf(sk, grid, cutoff=cutoff)
    rng = np.random.default_rng(3)
    idx, pts = _sample(grid, 3000, rng)
    # and the last planes of the grid, where work-groups hang over the edge
    edge_idx = np.array([[grid.shape[0] - 1, j, k] for j in range(0, 53, 4) for k in range(0, 43, 3)])
    idx = np.concatenate([idx, edge_idx, edge_idx[:, [0, 2, 1]][:, [0, 1, 2]] * 0 + [0, 52, 42]])
    pts = grid.indices_to_points(idx)
    ref = lattice_sdf_reference(sk, pts, cutoff=cutoff)
    got = field[idx[:, 0], idx[:, 1], idx[:, 2]]
    np.testing.assert_allclose(got, ref, atol=TOL)
    # the sample must hold both signs, and values both below and at the cut-off
    assert (ref > 0).any() and (ref < 0).any()
    assert (np.abs(ref) < cutoff - 0.01).mean() > 0.2 and (np.abs(ref) == cutoff).any()


def test_paper_kernel_near_the_cutoff(small_cells):
    sk = scaled_skeleton(small_cells, 0.75, 0.75)
    grid = _grid(small_cells, 0.04)
    cutoff = 0.12
    unclamped = lattice_sdf_reference(sk, grid.points()[::7], cutoff=np.inf)
    # points whose true distance is within 2 % of the cut-off, on both sides of it
    sel = np.nonzero(np.abs(np.abs(unclamped) - cutoff) < 0.02 * cutoff)[0]
    assert len(sel) > 50
    flat = lattice_sdf(sk, grid, cutoff=cutoff).reshape(-1)[::7]
    expect = np.sign(unclamped[sel]) * np.minimum(np.abs(unclamped[sel]), cutoff)
    np.testing.assert_allclose(flat[sel], expect, atol=TOL)


def test_paper_kernel_ignores_piece_order_and_tiling(small_cells):
    sk = scaled_skeleton(small_cells, 0.75, 0.75)
    grid = _grid(small_cells, 0.05, shape=(45, 37, 29))
    base = lattice_sdf(sk, grid, cutoff=0.2, tile_blocks=100)
    perm = np.random.default_rng(5).permutation(len(sk.quads))
    import dataclasses

    shuffled = dataclasses.replace(sk, quads=sk.quads[perm], quad_normals=sk.quad_normals[perm],
                                   quad_face=sk.quad_face[perm])
    # the minimum of a set does not depend on its order: bit-identical
    assert np.array_equal(lattice_sdf(shuffled, grid, cutoff=0.2), base)
    assert np.array_equal(lattice_sdf(sk, grid, cutoff=0.2, tile_blocks=1), base)


@pytest.mark.parametrize("blend", [0.0, 0.05])
def test_struts_kernel_matches_reference(small_cells, blend):
    edges = voronoi_edges(small_cells)
    grid = _grid(small_cells, 0.05, shape=(59, 51, 41))
    cutoff = 0.3
    field = struts_field(edges, grid, cutoff=cutoff, blend=blend)
    rng = np.random.default_rng(4)
    idx, pts = _sample(grid, 4000, rng)
    ref = struts_field_reference(edges, pts, cutoff=cutoff, blend=blend)
    np.testing.assert_allclose(field[idx[:, 0], idx[:, 1], idx[:, 2]], ref, atol=TOL)
    assert (ref < cutoff).mean() > 0.3 and (ref >= cutoff).any()
    perm = np.random.default_rng(6).permutation(len(edges))
    again = struts_field(edges[perm], grid, cutoff=cutoff, blend=blend)
    # a sum's rounding may depend on its order; far below the tolerance
    np.testing.assert_allclose(again, field, atol=1e-6)
    assert np.array_equal(struts_field(edges, grid, cutoff=cutoff, blend=blend, tile_blocks=1), field)
