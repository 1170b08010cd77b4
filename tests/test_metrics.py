"""The paper's cell metrics against closed forms and brute-force NumPy/SciPy oracles."""
from __future__ import annotations

import math

import numpy as np
import pytest

from implicit_scaffold.geometry.cells import voronoi_cells
from implicit_scaffold.measure.metrics import (cell_metrics, interior_face_pairs, pore_size_histogram, pore_sizes,
                                       trabecular_thicknesses)


def grid_cells(counts, a):
    """Seeds at the centres of a regular grid of cubes of side `a`: the cells are those cubes."""
    axes = [(np.arange(m) + 0.5) * a for m in counts]
    seeds = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    return voronoi_cells(seeds, [0, 0, 0], np.asarray(counts, float) * a)


# a box that is not a cube, so that no symmetry of the box hides an axis mix-up
GRID = (3, 4, 2)
SIDE = 1.25


@pytest.fixture(scope="module")
def cubes():
    return grid_cells(GRID, SIDE)


@pytest.mark.parametrize("sf, sv", [(0.75, 0.75), (0.3, 0.6)])
def test_regular_grid_gives_cubes_with_closed_form_metrics(cubes, sf, sv):
    a = SIDE
    # every cell is a cube: six faces, walls included
    assert np.all(cubes.faces_per_cell(walls=True) == 6)
    m = cell_metrics(cubes, sf, sv)
    d_cube = sv * (6 * a ** 3 / np.pi) ** (1 / 3)
    assert m["pore_size_mm"]["mean"] == pytest.approx(d_cube, rel=1e-12)
    assert m["pore_size_mm"]["min"] == pytest.approx(d_cube, rel=1e-12)
    assert m["pore_size_mm"]["max"] == pytest.approx(d_cube, rel=1e-12)
    assert m["pore_size_mm"]["sd"] == pytest.approx(0, abs=1e-12)
    assert m["interconnection_faces_with_walls_mean"] == 6
    # face neighbours of a grid cell: one per side that is not on the box wall (counted by loops)
    neighbours = [sum((idx[ax] > 0) + (idx[ax] < GRID[ax] - 1) for ax in range(3))
                  for idx in np.ndindex(*GRID)]
    assert m["interconnection_faces_mean"] == pytest.approx(np.mean(neighbours), rel=1e-12)
    assert m["trabecular_thickness_mm_mean"] == pytest.approx((1 - sv) * a, rel=1e-12)
    assert m["channel_area_mm2_mean"] == pytest.approx(a ** 2, rel=1e-12)
    assert m["window_area_mm2_mean"] == pytest.approx(sf ** 2 * a ** 2, rel=1e-12)


def test_regular_grid_of_the_paper_cube():
    # 4 x 4 x 4 cubes of 2.5 mm fill the paper's 10 mm cube
    cells = grid_cells((4, 4, 4), 2.5)
    assert np.all(cells.faces_per_cell(walls=True) == 6)
    d = pore_sizes(cells, 0.75)
    np.testing.assert_allclose(d, 0.75 * (6 * 2.5 ** 3 / np.pi) ** (1 / 3), rtol=1e-12)


@pytest.mark.parametrize("sv", [0.25, 0.5, 0.75])
def test_pore_volumes_sum_to_sv_cubed_of_the_box(cube_cells, sv):
    # the polyhedron spheres hold Sv³ of every cell, and the cells tile the box:
    # the paper's 1000 mm³ x 0.75³ = 421.875 mm³ at Sv = 0.75
    d = pore_sizes(cube_cells, sv)
    assert np.sum(np.pi * d ** 3 / 6) == pytest.approx(1000.0 * sv ** 3, rel=1e-9)
    assert cell_metrics(cube_cells, 0.5, sv)["pore_volume_mm3_sum"] == pytest.approx(1000.0 * sv ** 3, rel=1e-9)
    if sv == 0.75:
        assert np.sum(np.pi * d ** 3 / 6) == pytest.approx(421.875, rel=1e-9)


@pytest.mark.slow
def test_poisson_voronoi_mean_faces():
    # 20,000 uniform seeds in the 10 mm cube: mean spacing 0.37 mm; a cell whose seed
    # lies 1.5 mm (4 spacings) from every wall never reaches a wall, so it is an
    # unbounded Poisson-Voronoi cell; their mean face count tends to 2 + 48 π² / 35
    rng = np.random.default_rng(20_000)
    cells = voronoi_cells(rng.uniform(0, 10, (20_000, 3)), [0, 0, 0], [10, 10, 10])
    inner = cells.interior_cells(1.5)
    assert inner.sum() > 6000
    faces = cells.faces_per_cell(walls=True)[inner]
    assert np.array_equal(faces, cells.faces_per_cell(walls=False)[inner])
    # ~6,800 cells, face-count sd ~3.3: standard error ~0.04, so 0.1 is 2.5 standard errors
    assert faces.mean() == pytest.approx(2 + 48 * math.pi ** 2 / 35, abs=0.1)


def _polygon_centroid(p):
    """Area centroid of a planar polygon by a fan of triangles (brute force)."""
    tri_area, tri_cen = [], []
    for k in range(1, len(p) - 1):
        tri_area.append(np.linalg.norm(np.cross(p[k] - p[0], p[k + 1] - p[0])) / 2)
        tri_cen.append((p[0] + p[k] + p[k + 1]) / 3)
    w = np.asarray(tri_area)
    return (w[:, None] * np.asarray(tri_cen)).sum(0) / w.sum()


def _cell_centroid(points):
    """Volume centroid of the convex hull of `points`, by tetrahedra from an interior point."""
    from scipy.spatial import ConvexHull

    hull = ConvexHull(points)
    o = points.mean(0)
    vol, cen = 0.0, np.zeros(3)
    for s in hull.simplices:
        a, b, c = points[s]
        v = abs(np.dot(a - o, np.cross(b - o, c - o))) / 6
        vol += v
        cen += v * (o + a + b + c) / 4
    return cen / vol, vol


def test_trabecular_thickness_against_scaled_faces_brute_force(small_cells):
    # the paper's definition, built literally: scale each of the two cells by Sv about its
    # own centroid, take the centroid of the coupled face in each, measure their distance
    sv = 0.6
    c = small_cells
    cen = {}
    for i in range(c.n):
        pts = np.concatenate([c.face(f) for f in np.nonzero(c.face_cell == i)[0]])
        cen[i], vol = _cell_centroid(pts)
        assert vol == pytest.approx(c.volumes[i], rel=1e-9)
    pairs = interior_face_pairs(c)
    want = []
    for f in pairs:
        i, j = c.face_cell[f], c.face_neighbor[f]
        g = [np.nonzero((c.face_cell == i) & (c.face_neighbor == j))[0][0],
             np.nonzero((c.face_cell == j) & (c.face_neighbor == i))[0][0]]
        fi = cen[i] + sv * (c.face(g[0]) - cen[i])
        fj = cen[j] + sv * (c.face(g[1]) - cen[j])
        want.append(np.linalg.norm(_polygon_centroid(fi) - _polygon_centroid(fj)))
    np.testing.assert_allclose(trabecular_thicknesses(c, sv), want, rtol=1e-9)
    assert cell_metrics(c, 0.5, sv)["trabecular_thickness_mm_mean"] == pytest.approx(np.mean(want), rel=1e-9)


def test_channel_area_is_the_mean_face_area_of_the_polyhedra(small_cells):
    # Σ over a cell's faces of their areas is the surface of its convex hull
    from scipy.spatial import ConvexHull

    c = small_cells
    surface = sum(ConvexHull(np.concatenate([c.face(f) for f in np.nonzero(c.face_cell == i)[0]])).area
                  for i in range(c.n))
    faces = c.faces_per_cell(walls=True)
    m = cell_metrics(c, 0.4, 0.7)
    assert m["interconnection_faces_with_walls_mean"] == pytest.approx(faces.mean(), rel=1e-12)
    assert m["channel_area_mm2_mean"] == pytest.approx(surface / faces.sum(), rel=1e-9)
    assert m["window_area_mm2_mean"] == pytest.approx(0.16 * surface / faces.sum(), rel=1e-9)


def test_selection_and_histogram(small_cells):
    c = small_cells
    sel = np.zeros(c.n, bool)
    sel[::3] = True
    sv = 0.75
    # brute force: the diameter of the sphere with the scaled cell's volume
    d = np.array([(6 * sv ** 3 * c.volumes[i] / np.pi) ** (1 / 3) for i in np.nonzero(sel)[0]])
    m = cell_metrics(c, 0.5, sv, sel)
    ps = m["pore_size_mm"]
    assert ps["count"] == sel.sum()
    assert ps["mean"] == pytest.approx(d.mean(), rel=1e-12)
    assert ps["sd"] == pytest.approx(d.std(), rel=1e-9)
    assert ps["share_150_600um"] == pytest.approx(np.mean((d >= 0.15) & (d <= 0.6)))
    hist = ps["histogram"]
    assert sum(hist["counts"]) == sel.sum()
    assert len(hist["edges_mm"]) == len(hist["counts"]) + 1
    assert hist["edges_mm"][0] <= d.min() and hist["edges_mm"][-1] >= d.max()
    faces = [np.count_nonzero(c.face_cell == i) for i in np.nonzero(sel)[0]]
    assert m["interconnection_faces_with_walls_mean"] == pytest.approx(np.mean(faces))
    empty = cell_metrics(c, 0.5, sv, np.zeros(c.n, bool))
    assert empty["pore_size_mm"]["mean"] is None and empty["interconnection_faces_with_walls_mean"] is None
    assert empty["pore_size_mm"]["histogram"] is None and empty["trabecular_thickness_mm_mean"] is None


def test_histogram_of_equal_pores_is_one_bin():
    hist = pore_size_histogram(np.full(10, 0.4) * (1 + 1e-15 * np.arange(10)))
    assert sum(hist["counts"]) == 10 and max(hist["counts"]) == 10
    assert hist["edges_mm"][0] < 0.4 < hist["edges_mm"][-1]
