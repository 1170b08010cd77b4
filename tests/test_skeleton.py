import numpy as np
import pytest

from implicit_scaffold.errors import ScaffoldError
from implicit_scaffold.geometry.skeleton import (closed_form_porosity, piece_volumes, scaled_skeleton,
                                        voronoi_edges)


@pytest.mark.parametrize("sf, sv", [(0.25, 0.25), (0.5, 0.5), (0.75, 0.75), (0.9, 0.4), (0.3, 0.8)])
def test_piece_volumes_sum_to_closed_form(cube_cells, sf, sv):
    sk = scaled_skeleton(cube_cells, sf, sv)
    pores, channels = piece_volumes(sk)
    p0 = sv ** 3 + (1 - sv) * (sf ** 2 + sf * sv + sv ** 2)
    assert (pores.sum() + channels.sum()) / 1000.0 == pytest.approx(p0, rel=1e-9)
    np.testing.assert_allclose(pores, sv ** 3 * cube_cells.volumes, rtol=1e-9)
    assert np.all(channels > 0)


def test_closed_form_values():
    # DESIGN.md: Sf = Sv = 0.25 / 0.5 / 0.75 -> 15.6 / 50.0 / 84.4 %
    assert [round(100 * closed_form_porosity(s, s), 1) for s in (0.25, 0.5, 0.75)] == [15.6, 50.0, 84.4]


def test_rims_lie_in_their_face_and_match_across_it(cube_cells):
    c = cube_cells
    sk = scaled_skeleton(c, 0.6, 0.7)
    for f in range(0, len(c.face_cell), 7):
        rim = sk.rims[c.face_start[f]:c.face_start[f + 1]]
        # in the face's plane
        np.testing.assert_allclose((rim - c.face_centroids[f]) @ c.face_normals[f], 0, atol=1e-9)
        # the face scaled by Sf about its centroid
        np.testing.assert_allclose(rim - c.face_centroids[f], 0.6 * (c.face(f) - c.face_centroids[f]),
                                   atol=1e-12)
    key = {(int(o), int(n)): f for f, (o, n) in enumerate(zip(c.face_cell, c.face_neighbor)) if n >= 0}
    for (o, n), f in key.items():
        g = key.get((n, o))
        if g is not None:
            a = sk.rims[c.face_start[f]:c.face_start[f + 1]]
            b = sk.rims[c.face_start[g]:c.face_start[g + 1]]
            assert np.array_equal(a, b[::-1])


def test_quads_are_planar_and_point_into_the_solid(cube_cells):
    sk = scaled_skeleton(cube_cells, 0.75, 0.75)
    q = sk.quads
    # planar: all four vertices on the plane of the first
    off = np.einsum("ijk,ik->ij", q - q[:, :1], sk.quad_normals)
    assert np.abs(off).max() < 1e-9
    # a point just outside a quad (along its normal) lies in no piece of the void
    mid = q.mean(axis=1) + 1e-6 * sk.quad_normals
    inside = np.zeros(len(mid), bool)
    order = np.argsort(mid[:, 0])
    xs = mid[order, 0]
    for i in range(len(sk.piece_start) - 1):
        # only the points within the piece's x range can lie in it
        near = order[np.searchsorted(xs, sk.piece_lo[i, 0] - 1e-6):np.searchsorted(xs, sk.piece_hi[i, 0] + 1e-6)]
        pl = sk.planes[sk.piece_start[i]:sk.piece_start[i + 1]]
        inside[near] |= np.all(mid[near] @ pl[:, :3].T - pl[:, 3] <= 0, axis=1)
    assert inside.mean() < 0.001


@pytest.mark.parametrize("bad", [0.0, 1.0, -0.2, 1.5, float("nan")])
def test_scale_factors_must_lie_in_open_interval(cube_cells, bad):
    with pytest.raises(ScaffoldError, match="between 0 and 1"):
        scaled_skeleton(cube_cells, bad, 0.5)


def test_voronoi_edges_of_cubes():
    from implicit_scaffold.geometry.cells import voronoi_cells

    # 2 x 2 x 2 cubes in a 2 mm box: interior edges are the 3 axis-parallel crosses
    g = np.array([0.5, 1.5])
    seeds = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    cells = voronoi_cells(seeds, [0, 0, 0], [2, 2, 2])
    edges = voronoi_edges(cells)
    lengths = np.linalg.norm(edges[:, 1] - edges[:, 0], axis=1)
    # each of the 3 central lines x=1,y=1 (etc.) is cut into 2 unit edges at the centre
    assert len(edges) == 6
    np.testing.assert_allclose(lengths, 1.0, atol=1e-6)


def test_skeleton_near_a_band_is_the_whole_skeletons_part_there():
    """The skeleton a slab builds (SkeletonSource.near) holds, in the same order and with the same
    values, the whole skeleton's quads and pieces of the cells that reach the band; every quad of
    the other cells lies outside the band."""
    from implicit_scaffold.geometry.cells import voronoi_cells
    from implicit_scaffold.geometry.skeleton import SkeletonSource, quad_areas

    rng = np.random.default_rng(4)
    cells = voronoi_cells(rng.uniform(0, 3, (120, 3)), [0, 0, 0], [3, 3, 3])
    whole = scaled_skeleton(cells, 0.7, 0.8)
    source = SkeletonSource(cells, 0.7, 0.8)
    x_lo, x_hi = 1.1, 1.6
    part = source.near(x_lo, x_hi)
    # which cells reach the band, from their own vertices, face by face (independently of x_extents)
    cell_lo, cell_hi = np.full(cells.n, np.inf), np.full(cells.n, -np.inf)
    for f, c in enumerate(cells.face_cell):
        x = cells.face_vertices[cells.face_start[f]:cells.face_start[f + 1], 0]
        cell_lo[c], cell_hi[c] = min(cell_lo[c], x.min()), max(cell_hi[c], x.max())
    keep = (cell_hi >= x_lo) & (cell_lo <= x_hi)
    assert 0 < keep.sum() < cells.n
    mine = keep[cells.face_cell[whole.quad_face]]
    np.testing.assert_array_equal(part.quads, whole.quads[mine])
    np.testing.assert_array_equal(part.quad_normals, whole.quad_normals[mine])
    others = whole.quads[~mine]
    assert np.all((others[..., 0].max(axis=1) < x_lo) | (others[..., 0].min(axis=1) > x_hi))
    # pores then channels, each in the whole's order
    pores = np.nonzero(keep)[0]
    np.testing.assert_array_equal(part.piece_lo[:len(pores)], whole.piece_lo[pores])
    np.testing.assert_array_equal(source.quad_areas(chunk=7), quad_areas(whole))


def test_pieces_boxes_bound_their_vertices(cube_cells):
    # the oracle: each pore's box from its cage vertices and each channel's from its cage and
    # rim vertices, gathered one by one in a plain loop
    cells = cube_cells
    sk = scaled_skeleton(cells, 0.6, 0.8)
    start = cells.face_start
    lo = np.full((cells.n + len(cells.face_cell), 3), np.inf)
    hi = -lo
    for f in range(len(cells.face_cell)):
        for v in range(start[f], start[f + 1]):
            c = cells.face_cell[f]
            lo[c], hi[c] = np.minimum(lo[c], sk.cages[v]), np.maximum(hi[c], sk.cages[v])
            for p in (sk.cages[v], sk.rims[v]):
                lo[cells.n + f], hi[cells.n + f] = np.minimum(lo[cells.n + f], p), np.maximum(hi[cells.n + f], p)
    np.testing.assert_array_equal(sk.piece_lo, lo)
    np.testing.assert_array_equal(sk.piece_hi, hi)

