"""Mesh simplification within a tolerance (implicit_scaffold.mesh.simplify) and its measure.

Oracles, none of them manifold3d's own: closed-form ball volumes; closedness, winding and
bodies counted here over the faces (union-find on shared edges); self-intersection by a
triangle-triangle test written here (orientation signs) on every pair whose bounding
spheres meet; distances by trimesh's closest point on every triangle (no spatial index).
"""
from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from implicit_scaffold.errors import ScaffoldError
from implicit_scaffold.run.grid import Grid
from implicit_scaffold.mesh.marching import mesh_field
from implicit_scaffold.mesh.simplify import (check_tolerance, euler_characteristic, simplification_error, simplify_mesh,
                                        surface_deviation)


# ----------------------------------------------------------------------------- oracles


def ball_mesh(r=2.0, h=0.1, centre=(0.13, -0.07, 0.21)):
    centre = np.asarray(centre)
    grid = Grid.covering(centre - r - 0.3, centre + r + 0.3, h)
    x, y, z = np.meshgrid(*grid.axes(), indexing="ij", sparse=True)
    field = np.sqrt((x - centre[0]) ** 2 + (y - centre[1]) ** 2 + (z - centre[2]) ** 2) - r
    return mesh_field(field, grid), centre, r


def brute_distance(points, mesh):
    """Distance from each point to the mesh: trimesh's closest point on every triangle, the least."""
    from trimesh.triangles import closest_point

    tri = np.asarray(mesh.vertices)[np.asarray(mesh.faces)]
    out = np.empty(len(points))
    for i, p in enumerate(points):
        cp = closest_point(tri, np.repeat(p[None], len(tri), axis=0))
        out[i] = np.sqrt(((cp - p) ** 2).sum(axis=1).min())
    return out


def edges_closed_and_consistent(faces):
    """Every undirected edge used exactly twice, once in each direction (counted here)."""
    d = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    und, counts = np.unique(np.sort(d, axis=1), axis=0, return_counts=True)
    directed = np.unique(d, axis=0)
    return bool(np.all(counts == 2)) and len(directed) == len(d)


def bodies(faces):
    """Components of the faces joined across shared edges (union-find written here)."""
    parent = np.arange(len(faces))

    def find(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    owner = {}
    for f, tri in enumerate(faces):
        for a, b in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0])):
            key = (min(a, b), max(a, b))
            if key in owner:
                ra, rb = find(owner[key]), find(f)
                parent[ra] = rb
            else:
                owner[key] = f
    return len({find(f) for f in range(len(faces))})


def _orient(a, b, c, d):
    """Signed volume (times 6) of the tetrahedra (a, b, c, d), row by row."""
    return np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a)


def _segment_crosses(p, q, a, b, c, eps):
    """Segment pq crosses the interior of triangle abc (strictly, not in its plane)."""
    sp, sq = _orient(a, b, c, p), _orient(a, b, c, q)
    through = sp * sq < -eps * eps
    s1, s2, s3 = _orient(p, q, a, b), _orient(p, q, b, c), _orient(p, q, c, a)
    inside = ((s1 > eps) & (s2 > eps) & (s3 > eps)) | ((s1 < -eps) & (s2 < -eps) & (s3 < -eps))
    return through & inside


def self_intersections(mesh) -> int:
    """Pairs of triangles that cross each other, by orientation signs (a test written here).

    Candidates: every pair whose bounding spheres (centroid, farthest corner) meet. A pair
    sharing no vertex crosses when an edge of one passes through the other's interior; a
    pair sharing one vertex when the edge opposite it in one passes through the other; a
    pair sharing an edge when it is folded flat onto itself (normals opposite). Coplanar
    pairs sharing no vertex are checked in the plane: a corner strictly inside the other.
    """
    v = np.asarray(mesh.vertices, np.float64)
    f = np.asarray(mesh.faces)
    tri = v[f]
    cen = tri.mean(axis=1)
    rad = np.linalg.norm(tri - cen[:, None], axis=2).max(axis=1)
    pairs = cKDTree(cen).query_pairs(2 * rad.max(), output_type="ndarray")
    i, j = pairs[:, 0], pairs[:, 1]
    keep = np.linalg.norm(cen[i] - cen[j], axis=1) <= rad[i] + rad[j]
    i, j = i[keep], j[keep]
    shared = (f[i][:, :, None] == f[j][:, None, :]).sum(axis=(1, 2))
    scale = np.median(np.linalg.norm(tri[:, 1] - tri[:, 0], axis=1))
    eps = 1e-9 * scale ** 3
    bad = 0
    # no shared vertex: any of the six edges through the other triangle
    a, b = i[shared == 0], j[shared == 0]
    hit = np.zeros(len(a), bool)
    for s, t in ((a, b), (b, a)):
        for k in range(3):
            p, q = tri[s, k], tri[s, (k + 1) % 3]
            hit |= _segment_crosses(p, q, tri[t, 0], tri[t, 1], tri[t, 2], eps)
    # coplanar pairs: a corner of one strictly inside the other, in the plane
    n = np.cross(tri[a, 1] - tri[a, 0], tri[a, 2] - tri[a, 0])
    coplanar = np.all(np.abs(np.stack([_orient(tri[a, 0], tri[a, 1], tri[a, 2], tri[b, k]) for k in range(3)]))
                      <= eps, axis=0)
    for idx in np.flatnonzero(coplanar):
        axis = int(np.argmax(np.abs(n[idx])))
        keep2 = [d for d in range(3) if d != axis]
        A, B = tri[a[idx]][:, keep2], tri[b[idx]][:, keep2]
        for P, Q in ((A, B), (B, A)):
            for pt in Q:
                w = [np.cross(P[(k + 1) % 3] - P[k], pt - P[k]) for k in range(3)]
                if all(x > 1e-12 for x in w) or all(x < -1e-12 for x in w):
                    hit[idx] = True
    bad += int(hit.sum())
    # one shared vertex: the edge opposite it, in either triangle, through the other
    a, b = i[shared == 1], j[shared == 1]
    for s, t in ((a, b), (b, a)):
        common = (f[s][:, :, None] == f[t][:, None, :]).any(axis=2)  # which corner of s is shared
        k = np.argmax(common, axis=1)
        rows = np.arange(len(s))
        p, q = tri[s, (k + 1) % 3][rows], tri[s, (k + 2) % 3][rows]
        bad += int(_segment_crosses(p, q, tri[t, 0], tri[t, 1], tri[t, 2], eps).sum())
    # a shared edge: folded onto itself
    a, b = i[shared == 2], j[shared == 2]
    na = np.cross(tri[a, 1] - tri[a, 0], tri[a, 2] - tri[a, 0])
    nb = np.cross(tri[b, 1] - tri[b, 0], tri[b, 2] - tri[b, 0])
    cos = np.einsum("ij,ij->i", na, nb) / (np.linalg.norm(na, axis=1) * np.linalg.norm(nb, axis=1))
    bad += int(np.count_nonzero(cos < -0.999999))
    return bad


# ----------------------------------------------------------------------------- the oracles themselves


def test_self_intersection_oracle_finds_two_crossing_boxes():
    one = trimesh.creation.box(extents=(1, 1, 1))
    other = trimesh.creation.box(extents=(1, 1, 1))
    other.apply_translation((0.5, 0.3, 0.2))
    both = trimesh.util.concatenate([one, other])
    assert self_intersections(one) == 0
    assert self_intersections(both) > 0
    apart = trimesh.creation.box(extents=(1, 1, 1))
    apart.apply_translation((1.5, 0, 0))
    assert self_intersections(trimesh.util.concatenate([one, apart])) == 0
    assert bodies(np.asarray(trimesh.util.concatenate([one, apart]).faces)) == 2


# ----------------------------------------------------------------------------- surface_deviation


def test_surface_deviation_matches_brute_force():
    mesh, centre, r = ball_mesh(r=1.0, h=0.1)
    rng = np.random.default_rng(4)
    d = rng.normal(size=(300, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    # points at 0 .. 0.12 mm from the sphere, inside and out
    pts = centre + d * (r + rng.uniform(-0.12, 0.12, (300, 1)))
    fast = surface_deviation(pts, mesh.vertices, mesh.faces, reach=0.2)
    slow = brute_distance(pts, mesh)
    np.testing.assert_allclose(fast, slow, rtol=0, atol=1e-12)
    # beyond the reach: inf, never a wrong finite number
    near = surface_deviation(pts, mesh.vertices, mesh.faces, reach=0.05)
    assert np.all(np.isinf(near[slow > 0.05]))
    np.testing.assert_allclose(near[slow <= 0.05], slow[slow <= 0.05], rtol=0, atol=1e-12)


def test_surface_deviation_of_a_box_is_the_distance_to_its_faces():
    box = trimesh.creation.box(extents=(2, 2, 2))
    pts = np.array([[0, 0, 1.3], [1.2, 1.2, 0], [0.5, 0.5, 0.5], [1.1, 1.1, 1.1]])
    # closed form: above a face 0.3; past an edge sqrt(2 * 0.2^2); inside 0.5 from the nearest
    # faces; past a corner sqrt(3 * 0.1^2)
    want = [0.3, np.sqrt(0.08), 0.5, np.sqrt(0.03)]
    np.testing.assert_allclose(surface_deviation(pts, box.vertices, box.faces, reach=1.0), want, atol=1e-12)


def test_bad_reach_raises():
    box = trimesh.creation.box()
    with pytest.raises(ValueError, match="reach"):
        surface_deviation(np.zeros((1, 3)), box.vertices, box.faces, reach=0)


# ----------------------------------------------------------------------------- simplify_mesh


@pytest.fixture(scope="module")
def ball():
    mesh, centre, r = ball_mesh(r=2.0, h=0.1)
    tol = 0.02  # 0.2 voxel, the default share
    return mesh, simplify_mesh(mesh, tol), centre, r, tol


def test_simplified_ball_is_closed_one_body_and_smaller(ball):
    mesh, simple, centre, r, tol = ball
    f = np.asarray(simple.faces)
    assert len(f) < 0.8 * len(mesh.faces)
    assert edges_closed_and_consistent(f)
    assert bodies(f) == 1
    # outward: positive volume by the divergence theorem, summed here
    v = np.asarray(simple.vertices)
    assert _orient(np.zeros_like(v[f[:, 0]]), v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]).sum() > 0


def test_marching_cubes_ball_does_not_cross_itself(ball):
    assert self_intersections(ball[0]) == 0


@pytest.mark.xfail(reason="manifold3d 3.5.4 folds a sliver onto its neighbour: two coplanar triangles sharing an "
                          "edge, normals opposite (on this ball at z = -1.14); why simplification is not the default")
def test_simplified_ball_does_not_cross_itself(ball):
    assert self_intersections(ball[1]) == 0


def test_simplified_ball_keeps_its_volume_and_vertices(ball):
    mesh, simple, centre, r, tol = ball
    exact = 4 / 3 * np.pi * r ** 3
    # marching cubes of a sphere's distance at h = 0.1 is within 1 % of the closed form;
    # the simplification adds at most its measured displacement times the area
    err = simplification_error(mesh, simple, reach=0.05)
    assert abs(simple.volume - exact) / exact < 0.01
    assert abs(simple.volume - mesh.volume) <= err["max_mm"] * mesh.area
    # the vertices are a subset of the input's, the same bits
    before = {tuple(p) for p in np.asarray(mesh.vertices)}
    assert all(tuple(p) in before for p in np.asarray(simple.vertices))
    # every vertex within the tolerance of the sphere plus marching cubes' own error
    # (about h^2 / (8 r) for a chord, far below 0.01 mm here)
    dist = np.abs(np.linalg.norm(np.asarray(simple.vertices) - centre, axis=1) - r)
    assert dist.max() < 0.01


def test_measured_error_matches_brute_force(ball):
    mesh, simple, centre, r, tol = ball
    err = simplification_error(mesh, simple, reach=0.05)
    # the oracle on a sample of the input's vertices: the measure is the max, so at least those
    rng = np.random.default_rng(1)
    idx = rng.choice(len(mesh.vertices), 400, replace=False)
    pts = np.asarray(mesh.vertices)[idx]
    slow = brute_distance(pts, simple)
    fast = surface_deviation(pts, simple.vertices, simple.faces, reach=0.05)
    np.testing.assert_allclose(fast, slow, atol=1e-12)
    assert err["to_simplified_mm"] >= slow.max()
    # the worst vertex, found by the fast measure, checked by the oracle
    d = surface_deviation(mesh.vertices, simple.vertices, simple.faces, reach=0.05)
    worst = int(np.argmax(d))
    assert brute_distance(np.asarray(mesh.vertices)[[worst]], simple)[0] == pytest.approx(err["to_simplified_mm"],
                                                                                           abs=1e-12)


def test_simplification_is_deterministic(ball):
    mesh, simple, centre, r, tol = ball
    again = simplify_mesh(mesh, tol)
    assert np.array_equal(np.asarray(again.vertices), np.asarray(simple.vertices))
    assert np.array_equal(np.asarray(again.faces), np.asarray(simple.faces))


@pytest.mark.parametrize("value", [-0.01, float("nan"), float("inf"), "a lot"])
def test_bad_tolerance_is_one_line_error(value):
    with pytest.raises(ScaffoldError, match="--tolerance"):
        check_tolerance(value)


def test_tolerance_defaults():
    assert check_tolerance(None) == 0.0 and check_tolerance(0) == 0.0 and check_tolerance("0.01") == 0.01


# ----------------------------------------------------------------------------- in the pipeline


SMALL = dict(size=2.5, seeds=25, voxel=0.06, porosity=0.75, seed=5)
TOL = 0.012  # 0.2 voxel


@pytest.fixture(scope="module")
def small_runs(tmp_path_factory):
    from implicit_scaffold.pipeline import generate

    tmp = tmp_path_factory.mktemp("simplify")
    plain = generate(output=tmp / "plain.stl", morphometry=False, **SMALL)
    simple = generate(output=tmp / "simple.stl", morphometry=False, tolerance=TOL, **SMALL)
    return plain, simple, tmp


def test_simplified_run_reports_what_it_measured(small_runs):
    plain, simple, tmp = small_runs
    rep = json.loads((tmp / "simple.json").read_text())
    s = rep["simplification"]
    assert "simplification" not in plain.report
    h = rep["voxel_mm"]
    assert s["applied"] and s["tolerance_mm"] == TOL and s["tolerance_voxels"] == pytest.approx(TOL / h)
    assert s["triangles_before"] == plain.report["triangles"]
    assert s["triangles"] == rep["triangles"] < s["triangles_before"]
    # the report's file size is the file's, and the STL's record count gives it
    assert rep["file_size_bytes"] == (tmp / "simple.stl").stat().st_size == 84 + 50 * rep["triangles"]
    # the printed file read back: closed, one body, no crossing, counted here
    m = trimesh.load(tmp / "simple.stl", process=True)
    f = np.asarray(m.faces)
    assert edges_closed_and_consistent(f) and bodies(f) == 1
    # the porosity change and the distance, recomputed from the two files
    before = trimesh.load(tmp / "plain.stl", process=True)
    patient = rep["patient_volume_mm3"]
    assert s["porosity_change"] == pytest.approx((before.volume - m.volume) / patient, abs=1e-6)
    assert any("printed porosity" in w for w in rep["warnings"]) == (abs(s["porosity_change"]) > 0.001)
    d = surface_deviation(before.vertices, m.vertices, m.faces, reach=8 * h)
    assert d.max() == pytest.approx(s["original_to_simplified_mm"], abs=1e-6)  # STL's float32 vertices
    # the handles removed, from the two files' Euler characteristics (closed, one body each)
    assert s["handles_removed"] == (euler_characteristic(m) - euler_characteristic(before)) // 2
    # what the run promises is not what manifold3d promises: a warning says when it moved more
    warned = any("quarter voxel" in w for w in rep["warnings"])
    assert warned == (s["max_displacement_mm"] > 0.25 * h)


def test_by_default_every_triangle_is_kept(small_runs):
    plain, simple, tmp = small_runs
    assert plain.report["triangles"] == len(trimesh.load(tmp / "plain.stl", process=False).faces)
    assert plain.report["file_size_bytes"] == 84 + 50 * plain.report["triangles"]


def test_simplified_run_is_byte_reproducible(small_runs, tmp_path):
    from implicit_scaffold.pipeline import generate

    plain, simple, tmp = small_runs
    generate(output=tmp_path / "again.stl", morphometry=False, tolerance=TOL, **SMALL)
    assert (tmp_path / "again.stl").read_bytes() == (tmp / "simple.stl").read_bytes()
    generate(output=tmp_path / "other.stl", morphometry=False, tolerance=TOL, **{**SMALL, "seed": 6})
    assert (tmp_path / "other.stl").read_bytes() != (tmp / "simple.stl").read_bytes()


def test_cli_tolerance(tmp_path, capsys):
    from implicit_scaffold.cli import main

    assert main(["generate", "-o", str(tmp_path / "bad.stl"), "--tolerance", "-1", "-q"]) == 2
    err = capsys.readouterr().err
    assert "--tolerance" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "bad.stl").exists()
    args = ["generate", "-o", str(tmp_path / "c.3mf"), "--size", "2.5", "--seeds", "25", "--voxel", "0.06",
            "--porosity", "0.75", "--seed", "5", "--tolerance", "0.006"]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "simplified within 0.006 mm" in out
    rep = json.loads((tmp_path / "c.json").read_text())
    assert rep["simplification"]["tolerance_mm"] == 0.006


def test_shared_positions_counts_vertices_that_an_stl_would_merge():
    from implicit_scaffold.mesh.simplify import shared_positions

    a = trimesh.creation.box(extents=(1, 1, 1))
    b = trimesh.creation.box(extents=(1, 1, 1))
    b.apply_translation((1, 1, 0))  # touching a along the edge x = y = 0.5: its 2 corners there, and a's 2
    both = trimesh.Trimesh(np.vstack([a.vertices, b.vertices]), np.vstack([a.faces, b.faces + len(a.vertices)]),
                           process=False)
    assert shared_positions(a) == 0 and shared_positions(both) == 4
    # as an STL reads it (positions merged): the edge's triangles are four, not watertight
    assert not trimesh.Trimesh(both.vertices, both.faces, process=True).is_watertight


def test_a_simplification_that_makes_the_surface_touch_itself_is_not_applied(tmp_path, monkeypatch):
    # manifold3d keeps two sheets it brought together apart by index: closed as it holds the mesh, but
    # not as an STL stores it (the femur in three pieces at --tolerance 0.05 had two edges of four triangles)
    import implicit_scaffold.mesh.simplify as simplify_module
    from implicit_scaffold.pipeline import generate

    real = simplify_module.simplify_mesh

    def touching(mesh, tolerance):
        out = real(mesh, tolerance)
        v = np.array(out.vertices)
        f = np.asarray(out.faces)
        far = np.argmax(np.linalg.norm(v - v[f[0, 0]], axis=1))
        v[f[0, 0]] = v[far]  # one vertex moved onto another's position
        return trimesh.Trimesh(v, f, process=False)

    monkeypatch.setattr(simplify_module, "simplify_mesh", touching)
    with pytest.warns(UserWarning, match="brought the surface onto itself"):
        rep = generate(output=tmp_path / "s.stl", morphometry=False, tolerance=TOL, **SMALL).report
    assert rep["simplification"]["applied"] is False
    assert trimesh.load(tmp_path / "s.stl").is_watertight
