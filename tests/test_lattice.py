"""The OpenCL lattice kernels against brute-force NumPy over every primitive."""
import numpy as np
import pytest

from implicit_scaffold.run.grid import Grid
from implicit_scaffold.fields.lattice import (lattice_sdf, lattice_sdf_reference, struts_field,
                                       struts_field_reference)
from implicit_scaffold.geometry.skeleton import scaled_skeleton, voronoi_edges

# float32 coordinates of a few mm carry ~1e-6 mm of rounding; 1e-4 mm is the bound
TOL = 1e-4


def _grid(cells, h, shape=None):
    if shape is None:
        return Grid.covering(cells.lo, cells.hi, h)
    return Grid(tuple(cells.lo - h / 3), h, shape)


def _sample(grid, n, rng):
    idx = np.stack([rng.integers(0, s, n) for s in grid.shape], 1)
    return idx, grid.indices_to_points(idx)


@pytest.mark.slow
@pytest.mark.parametrize("sf, sv", [(0.75, 0.75), (0.4, 0.6)])
def test_paper_kernel_matches_reference(small_cells, sf, sv):
    sk = scaled_skeleton(small_cells, sf, sv)
    # odd sizes that do not divide into 8^3 work-groups
    grid = _grid(small_cells, 0.05, shape=(61, 53, 43))
    cutoff = 0.15
    field = lattice_sdf(sk, grid, cutoff=cutoff)
    rng = np.random.default_rng(3)
    idx, pts = _sample(grid, 3000, rng)
    # and the last planes of the grid along x, y and z, where work-groups (8 voxels
    # along z in 2 rows along y, 8 along x) hang over the edge
    nx, ny, nz = grid.shape
    edge_idx = np.concatenate([
        [[nx - 1, j, k] for j in range(0, ny, 4) for k in range(0, nz, 3)],
        [[i, ny - 1, k] for i in range(0, nx, 4) for k in range(0, nz, 3)],
        [[i, j, nz - 1] for i in range(0, nx, 4) for j in range(0, ny, 3)],
        [[nx - 1, ny - 1, nz - 1]]])
    idx = np.concatenate([idx, edge_idx])
    pts = grid.indices_to_points(idx)
    ref = lattice_sdf_reference(sk, pts, cutoff=cutoff)
    got = field[idx[:, 0], idx[:, 1], idx[:, 2]]
    np.testing.assert_allclose(got, ref, atol=TOL)
    # the sample must hold both signs, and values both below and at the cut-off
    assert (ref > 0).any() and (ref < 0).any()
    assert (np.abs(ref) < cutoff - 0.01).mean() > 0.2 and (np.abs(ref) == cutoff).any()


@pytest.mark.slow
def test_paper_kernel_near_the_cutoff(small_cells):
    sk = scaled_skeleton(small_cells, 0.75, 0.75)
    grid = _grid(small_cells, 0.04)
    cutoff = 0.12
    flat = lattice_sdf(sk, grid, cutoff=cutoff).reshape(-1)
    # candidates from a run with a wider cut-off (only to pick points; the oracle judges them)
    wide = lattice_sdf(sk, grid, cutoff=2 * cutoff).reshape(-1)
    cand = np.nonzero(np.abs(np.abs(wide) - cutoff) < 0.05 * cutoff)[0][::3]
    unclamped = lattice_sdf_reference(sk, grid.points()[cand], cutoff=np.inf)
    # points whose true distance is within 2 % of the cut-off, on both sides of it
    sel = np.abs(np.abs(unclamped) - cutoff) < 0.02 * cutoff
    assert sel.sum() > 50
    assert (np.abs(unclamped[sel]) < cutoff).any() and (np.abs(unclamped[sel]) > cutoff).any()
    expect = np.sign(unclamped[sel]) * np.minimum(np.abs(unclamped[sel]), cutoff)
    np.testing.assert_allclose(flat[cand[sel]], expect, atol=TOL)


@pytest.mark.slow
@pytest.mark.parametrize("inset", [1 / 7, 0.004])
def test_paper_kernel_at_and_beyond_the_box_walls(small_cells, inset):
    """Voxels just inside and outside the cells' box, where channels open in the walls.

    A voxel plane lies `inset` voxels inside each lower wall (none exactly on a wall:
    there float64 itself cannot tell the side, and the oracle's sign is noise).
    """
    sk = scaled_skeleton(small_cells, 0.75, 0.75)
    h = 0.05
    grid = Grid(tuple(small_cells.lo - (3 - inset) * h), h, (67, 57, 47))
    field = lattice_sdf(sk, grid, cutoff=0.2)
    idx = np.concatenate([np.argwhere(np.ones((6, 57, 47), bool)) + [i0, 0, 0] for i0 in (0, 61)]
                         + [np.argwhere(np.ones((67, 6, 47), bool)) + [0, j0, 0] for j0 in (0, 51)])
    idx = idx[np.random.default_rng(8).permutation(len(idx))[:2500]]
    pts = grid.indices_to_points(idx)
    ref = lattice_sdf_reference(sk, pts, cutoff=0.2)
    np.testing.assert_allclose(field[idx[:, 0], idx[:, 1], idx[:, 2]], ref, atol=TOL)
    outside = np.any((pts < small_cells.lo) | (pts > small_cells.hi), 1)
    # outside the box is solid; just inside it, both signs occur
    assert outside.any() and (ref[outside] < 0).all()
    assert (ref[~outside] > 0).any() and (ref[~outside] < 0).any()


def _permute_pieces(sk, perm):
    import dataclasses

    start = sk.piece_start
    planes = np.concatenate([sk.planes[start[i]:start[i + 1]] for i in perm])
    counts = np.diff(start)[perm]
    return dataclasses.replace(sk, planes=planes, piece_start=np.concatenate([[0], np.cumsum(counts)]),
                               piece_lo=sk.piece_lo[perm], piece_hi=sk.piece_hi[perm])


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
    assert np.array_equal(lattice_sdf(sk, grid, cutoff=0.2, tile_blocks=3), base)
    # the pieces (which decide the sign where the quads do not) in another order
    ppieces = _permute_pieces(sk, np.random.default_rng(9).permutation(len(sk.piece_start) - 1))
    assert np.array_equal(lattice_sdf(ppieces, grid, cutoff=0.2), base)
    # and the field is the oracle's (a permutation of nothing would pass the above)
    idx, pts = _sample(grid, 1500, np.random.default_rng(10))
    np.testing.assert_allclose(base[idx[:, 0], idx[:, 1], idx[:, 2]],
                               lattice_sdf_reference(sk, pts, cutoff=0.2), atol=TOL)


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


@pytest.mark.parametrize("x_range", [(0, 9), (5, 23), (16, 17), (30, 45)])
def test_a_slab_of_the_grid_is_those_planes_of_the_whole(small_cells, x_range):
    # a tiled run evaluates each slab alone: its planes must be the whole grid's, bit for bit
    sk = scaled_skeleton(small_cells, 0.75, 0.75)
    grid = _grid(small_cells, 0.05, shape=(45, 37, 29))
    x0, x1 = x_range
    whole = lattice_sdf(sk, grid, cutoff=0.2)
    assert np.array_equal(lattice_sdf(sk, grid, cutoff=0.2, x_range=x_range), whole[x0:x1])
    edges = voronoi_edges(small_cells)
    struts = struts_field(edges, grid, cutoff=0.3, blend=0.05)
    assert np.array_equal(struts_field(edges, grid, cutoff=0.3, blend=0.05, x_range=x_range, tile_blocks=1),
                          struts[x0:x1])
    # and the slab is the oracle's
    idx, pts = _sample(Grid(grid.origin, grid.spacing, (x1 - x0,) + grid.shape[1:]), 300,
                       np.random.default_rng(x0))
    pts[:, 0] += x0 * grid.spacing
    slab = lattice_sdf(sk, grid, cutoff=0.2, x_range=x_range)
    np.testing.assert_allclose(slab[idx[:, 0], idx[:, 1], idx[:, 2]],
                               lattice_sdf_reference(sk, pts, cutoff=0.2), atol=TOL)


def test_a_slab_outside_the_grid_is_refused(small_cells):
    sk = scaled_skeleton(small_cells, 0.75, 0.75)
    grid = _grid(small_cells, 0.05, shape=(20, 20, 20))
    with pytest.raises(ValueError):
        lattice_sdf(sk, grid, cutoff=0.2, x_range=(5, 21))


def test_quads_packed_in_chunks_are_packed_the_same(monkeypatch, small_cells):
    import implicit_scaffold.fields.lattice as L
    from implicit_scaffold.geometry.skeleton import scaled_skeleton

    sk = scaled_skeleton(small_cells, 0.75, 0.75)
    whole = L._pack_quads(sk, (0.1, -0.2, 0.3))
    monkeypatch.setattr(L, "_PACK_CHUNK", 37)
    chunked = L._pack_quads(sk, (0.1, -0.2, 0.3))
    assert len(sk.quads) > 37
    for a, b in ((whole.data, chunked.data), (whole.lo, chunked.lo), (whole.hi, chunked.hi)):
        np.testing.assert_array_equal(a, b)
    # the frame's normal row is the quad's unit normal, its offset puts vertex 0 on the plane
    np.testing.assert_allclose(whole.data[:, 2, :3], sk.quad_normals, atol=1e-6)
    q0 = sk.quads[:, 0] - np.array([0.1, -0.2, 0.3])
    np.testing.assert_allclose(np.einsum("ij,ij->i", whole.data[:, 2, :3], q0) + whole.data[:, 2, 3], 0, atol=1e-5)


def test_long_block_lists_are_sorted_and_the_field_exact(small_cells):
    # a coarse voxel makes blocks of 2 mm, several pores wide: lists of hundreds of
    # quads, past the kernel's insertion sort, that the voxel loop's early stop
    # trusts to be in order
    import pyopencl as cl

    from implicit_scaffold import opencl
    from implicit_scaffold.fields.lattice import _pack_paper, bin_on_device

    sk = scaled_skeleton(small_cells, 0.75, 0.75)
    grid = _grid(small_cells, 0.25)
    cutoff = 0.6
    packed = _pack_paper(sk, grid)
    offsets, counts, items, keys = bin_on_device("quad", packed.quad_buffer, packed.quads.lo,
                                                 packed.quads.hi, grid, cutoff=cutoff)
    _, queue = opencl.context()
    host = {}
    for name, buf, dtype in [("offsets", offsets, np.int32), ("counts", counts, np.int32),
                             ("items", items, np.int32), ("keys", keys, np.float32)]:
        host[name] = np.empty(buf.size // 4, dtype)
        cl.enqueue_copy(queue, host[name], buf, is_blocking=True)
    lengths = host["counts"]
    assert lengths.max() > 200
    for b in np.nonzero(lengths)[0]:
        o, n = host["offsets"][b], lengths[b]
        k, q = host["keys"][o:o + n], host["items"][o:o + n]
        order = np.lexsort((q, k))
        np.testing.assert_array_equal(order, np.arange(n))
        assert len(np.unique(q)) == n
    field = lattice_sdf(sk, grid, cutoff=cutoff)
    idx = np.stack(np.meshgrid(*[np.arange(s) for s in grid.shape], indexing="ij"), -1).reshape(-1, 3)
    ref = lattice_sdf_reference(sk, grid.indices_to_points(idx), cutoff=cutoff)
    np.testing.assert_allclose(field.reshape(-1), ref, atol=TOL)


def test_skipped_blocks_leave_every_other_block_bit_for_bit(small_cells):
    # blocks skipped (a pattern over x, y and z) get no primitive: -cutoff (paper) or cutoff
    # (struts) there, and every voxel of the other blocks the bits of the full field
    sk = scaled_skeleton(small_cells, 0.75, 0.75)
    edges = voronoi_edges(small_cells)
    grid = _grid(small_cells, 0.05)
    blocks = tuple(-(-n // 8) for n in grid.shape)
    skip = np.zeros(blocks, bool)
    skip[::2, 1::2, ::3] = True
    mask = skip.repeat(8, 0).repeat(8, 1).repeat(8, 2)[:grid.shape[0], :grid.shape[1], :grid.shape[2]]
    for full, part, fill in [
            (lattice_sdf(sk, grid, cutoff=0.15), lattice_sdf(sk, grid, cutoff=0.15, skip=skip), -0.15),
            (struts_field(edges, grid, cutoff=0.3, blend=0.05),
             struts_field(edges, grid, cutoff=0.3, blend=0.05, skip=skip), 0.3)]:
        assert np.array_equal(full[~mask], part[~mask])
        assert np.all(part[mask] == np.float32(fill)) and np.any(full[mask] != np.float32(fill))


def test_what_a_slab_packed_goes_with_its_skeleton(small_cells):
    # the slabs of one skeleton pack it once; a slab's own skeleton (SkeletonSource.near) takes
    # its packed primitives with it, not beside the next slab's skeleton as that one is built
    import implicit_scaffold.fields.lattice as L

    sk = scaled_skeleton(small_cells, 0.75, 0.75)
    grid = _grid(small_cells, 0.05, shape=(45, 37, 29))
    first = lattice_sdf(sk, grid, cutoff=0.2, x_range=(0, 9))
    packed = L._PACKED[L._pack_paper][3]
    second = lattice_sdf(sk, grid, cutoff=0.2, x_range=(9, 23))
    assert L._PACKED[L._pack_paper][3] is packed
    whole = lattice_sdf(sk, grid, cutoff=0.2)
    assert np.array_equal(np.concatenate([first, second]), whole[:23])
    del sk, packed
    assert L._pack_paper not in L._PACKED
