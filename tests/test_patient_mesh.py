"""Mesh patients: signed distance against analytic shapes and brute force, robust sign, cuts, scaffold inside."""
import math

import numpy as np
import pytest
import trimesh

from implicit_scaffold import generate
from implicit_scaffold.run.grid import Grid
from implicit_scaffold.fields.patient import CutPatient, Cylinder, Sphere, cut_halfspaces
from implicit_scaffold.fields import patient_mesh
from implicit_scaffold.fields.patient_mesh import (clamped_distance, inside_votes, mesh_patient_from_trimesh,
                                            triangle_distance, triangle_distance_reference)


def sphere_mesh(size=10.0, subdivisions=5):
    """The analytic Sphere(size) as a mesh: centred in [0, size]^3."""
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=size / 2)
    m.apply_translation([size / 2] * 3)
    return m


def cylinder_mesh(size=10.0, sections=256):
    """The analytic Cylinder(size) as a mesh: axis z through (size/2, size/2), z in [0, size]."""
    m = trimesh.creation.cylinder(radius=size / 2, height=size, sections=sections)
    m.apply_translation([size / 2] * 3)
    return m


def brute_distance(points, triangles):
    """Distance to the nearest triangle by trimesh's closest-point routine (an independent oracle)."""
    p = np.asarray(points, np.float64)
    best = np.full(len(p), np.inf)
    for t in np.asarray(triangles, np.float64):
        q = trimesh.triangles.closest_point(np.repeat(t[None], len(p), axis=0), p)
        best = np.minimum(best, np.linalg.norm(q - p, axis=1))
    return best


@pytest.mark.parametrize("make, analytic", [(sphere_mesh, Sphere), (cylinder_mesh, Cylinder)])
def test_mesh_sdf_matches_analytic_shape(make, analytic):
    mesh = make()
    patient = mesh_patient_from_trimesh(mesh, name="shape.stl")
    exact = analytic(10.0)
    np.testing.assert_allclose(patient.lo, exact.lo, atol=1e-9)
    np.testing.assert_allclose(patient.hi, exact.hi, atol=1e-9)
    # a closed mesh's volume is its own exact volume; the facets lose a little against the shape
    assert patient.closed and patient.volume == pytest.approx(abs(mesh.volume), rel=1e-12)
    assert patient.volume == pytest.approx(exact.volume, rel=2e-3)
    grid = Grid.covering(exact.lo, exact.hi, 0.25)
    h = grid.spacing
    got = patient.sdf_grid(grid)
    want = exact.sdf_grid(grid)
    assert got.dtype == np.float32 and got.shape == grid.shape
    assert np.max(np.abs(got - want)) < 0.5 * h


@pytest.mark.slow
@pytest.mark.parametrize("make, shape", [(sphere_mesh, "sphere"), (cylinder_mesh, "cylinder")])
def test_mesh_scaffold_porosity_matches_analytic(make, shape):
    opts = dict(seeds=60, porosity=None, voxel=0.2, seed=3, mesh=False)
    ref = generate(shape=shape, size=10.0, **opts)
    got = generate(patient=mesh_patient_from_trimesh(make(), name=f"{shape}.stl"), **opts)
    assert got.grid == ref.grid
    assert abs(got.report["porosity_voxel"] - ref.report["porosity_voxel"]) < 0.01


def test_sign_survives_holes_duplicates_and_flips():
    clean = sphere_mesh(subdivisions=4)
    rng = np.random.default_rng(5)
    faces = clean.faces.copy()
    # flip the winding of half the faces, duplicate some, punch holes by deleting others
    flip = rng.random(len(faces)) < 0.5
    faces[flip] = faces[flip][:, ::-1]
    holes = rng.choice(len(faces), 8, replace=False)
    dup = rng.choice(len(faces), 40, replace=False)
    faces = np.concatenate([np.delete(faces, holes, axis=0), faces[dup]])
    broken = trimesh.Trimesh(clean.vertices, faces, process=False)
    assert not broken.is_watertight
    grid = Grid.covering([0, 0, 0], [10, 10, 10], 0.2)
    want = mesh_patient_from_trimesh(clean, name="clean").sdf_grid(grid) < 0
    patient = mesh_patient_from_trimesh(broken, name="broken")
    assert not patient.closed
    got = patient.sdf_grid(grid) < 0
    assert np.mean(got == want) >= 0.999
    # its volume is integrated along lines instead: close to the clean one
    assert patient.volume == pytest.approx(abs(clean.volume), rel=0.01)


def test_sign_counts_a_line_through_a_vertex_once():
    # a box whose vertices and edges sit exactly on grid lines: every line grazes edges
    box = trimesh.creation.box(extents=[2, 2, 2])
    box.apply_translation([1, 1, 1])
    grid = Grid((0.0, 0.0, 0.0), 0.5, (5, 5, 5))
    inside, odd = inside_votes(np.asarray(box.vertices), np.asarray(box.faces), grid)
    assert odd == 0
    want = Grid.points(grid).reshape(5, 5, 5, 3)
    strict = np.all((want > 0) & (want < 2), axis=-1)
    # voxels strictly inside are inside and those strictly outside are outside
    assert inside[strict].all()
    assert not inside[np.any((want < 0) | (want > 2), axis=-1)].any()


@pytest.mark.parametrize("dense", [False, True])
def test_kernel_distance_equals_brute_force(dense, monkeypatch):
    # dense: the blocks of a mesh of many triangles a voxel (patient_mesh.DENSE_BLOCK), asked for here
    if dense:
        monkeypatch.setattr(patient_mesh, "DENSE_TRIANGLES_PER_VOXEL", 0.0)
    rng = np.random.default_rng(11)
    centres = rng.uniform(0.5, 2.5, (25, 1, 3))
    triangles = centres + rng.normal(0, 0.5, (25, 3, 3))
    V = triangles.reshape(-1, 3)
    F = np.arange(len(V)).reshape(-1, 3)
    grid = Grid((-0.37, -0.41, -0.29), 0.13, (29, 31, 27))  # odd sizes: partial blocks and tiles
    assert patient_mesh.block_for(len(F), grid) == (patient_mesh.DENSE_BLOCK if dense else patient_mesh.BLOCK)
    got = triangle_distance(V, F, grid)
    points = grid.points()
    want = brute_distance(points, triangles)
    # the two oracles agree with each other
    sel = slice(None, None, 97)
    np.testing.assert_allclose(triangle_distance_reference(points[sel], triangles), want[sel], atol=1e-9)
    got = got.reshape(-1)
    band = want <= 3 * grid.spacing
    assert band.sum() > 1000 and (~band).sum() > 1000
    # exact within the band (float32 coordinates relative to the grid origin)
    assert np.max(np.abs(got[band] - want[band])) < 1e-4
    # far from it: the distance to one real triangle, so never below the true one, and within a voxel
    # of it (a feature transform's nearest band voxel may see another nearest triangle near a medial axis)
    assert np.all(got[~band] >= want[~band] - 1e-4)
    assert np.max(got[~band] - want[~band]) < grid.spacing


@pytest.mark.parametrize("dense", [False, True])
def test_clamped_distance_is_exact_within_reach_and_slab_by_slab(dense, monkeypatch):
    if dense:
        monkeypatch.setattr(patient_mesh, "DENSE_TRIANGLES_PER_VOXEL", 0.0)
    rng = np.random.default_rng(11)
    centres = rng.uniform(0.5, 2.5, (25, 1, 3))
    triangles = centres + rng.normal(0, 0.5, (25, 3, 3))
    V = triangles.reshape(-1, 3)
    F = np.arange(len(V)).reshape(-1, 3)
    grid = Grid((-0.37, -0.41, -0.29), 0.13, (29, 31, 27))  # odd sizes: partial blocks and tiles
    reach = 0.61  # several voxels, past the exact band of 3 voxels
    got = clamped_distance(V, F, grid, reach=reach)
    want = brute_distance(grid.points(), triangles).reshape(grid.shape)
    near = want < reach - 1e-4
    assert near.sum() > 1000 and (~near).sum() > 1000
    # exact (float32 coordinates relative to the grid origin) within reach, the reach beyond it
    assert np.max(np.abs(got[near] - want[near])) < 1e-4
    assert np.all(got[want > reach + 1e-4] == np.float32(reach))
    # any slab (crossing block and tile boundaries) gets the whole grid's bits
    for x0, x1 in ((0, 5), (5, 13), (13, 29), (7, 8)):
        assert clamped_distance(V, F, grid, reach=reach, x_range=(x0, x1)).tobytes() == got[x0:x1].tobytes()


def test_ray_parity_decomposes_by_slab():
    mesh = sphere_mesh(3.0, subdivisions=3)
    V, F = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    grid = Grid((-0.2, -0.13, -0.17), 0.11, (33, 31, 30))
    whole, _ = inside_votes(V, F, grid)
    parts = [inside_votes(V, F, grid, x_range=(x0, min(x0 + 7, 33)))[0] for x0 in range(0, 33, 7)]
    assert np.array_equal(np.concatenate(parts), whole)
    # the oracle: the analytic ball (voxel centres farther than the facets' sag from its sphere)
    r = np.linalg.norm(grid.points() - 1.5, axis=1).reshape(grid.shape)
    clear = np.abs(r - 1.5) > 0.05
    assert np.array_equal(whole[clear], (r < 1.5)[clear])


def test_a_clamped_mesh_patient_keeps_its_sign_and_near_field():
    patient = mesh_patient_from_trimesh(sphere_mesh(3.0, subdivisions=3), name="ball")
    grid = Grid.covering(patient.lo - 0.3, patient.hi + 0.3, 0.07)
    exact = patient.sdf_grid(grid)
    clamped = patient.clamp_far_field(0.2)
    assert patient.far_reach is None  # the original is untouched
    reach = np.float32(0.2 + 3 * 0.07)
    got = clamped.sdf_grid(grid)
    assert np.array_equal(got < 0, exact < 0)
    near = np.abs(exact) <= 3 * 0.07
    assert np.array_equal(got[near], exact[near])
    assert np.max(np.abs(got)) == reach
    part = clamped.sdf_grid(grid, x_range=(9, 30))
    assert part.tobytes() == got[9:30].tobytes()
    cut = CutPatient(patient, cut_halfspaces(cut_planes=[0, 0, 1.0, 0, 0, -1, 0, 0, 2.0, 0, 0, 1]))
    whole_cut = cut.clamp_far_field(0.2).sdf_grid(grid)
    assert cut.clamp_far_field(0.2).sdf_grid(grid, x_range=(3, 11)).tobytes() == whole_cut[3:11].tobytes()
    assert np.array_equal(whole_cut < 0, cut.sdf_grid(grid) < 0)


@pytest.mark.slow
def test_clipped_mesh_volume_and_bounds_exact():
    cube = trimesh.creation.box(extents=[2, 2, 2])
    cube.apply_translation([1, 1, 1])
    base = mesh_patient_from_trimesh(cube, name="cube")
    # the plane x + y + z = 3 through the centre halves the cube (central symmetry)
    half = CutPatient(base, [[*(np.ones(3) / math.sqrt(3)), 3 / math.sqrt(3)]])
    assert half.volume == pytest.approx(4.0, rel=1e-4)
    clip = CutPatient(base, cut_halfspaces(clip=(-1, 0.5, 0.25, 1.5, 5, 1.75)))
    assert clip.volume == pytest.approx(1.5 * 1.5 * 1.5, rel=1e-9)
    np.testing.assert_allclose(clip.lo, [0, 0.5, 0.25], atol=1e-3)
    np.testing.assert_allclose(clip.hi, [1.5, 2, 1.75], atol=1e-3)
    # two osteotomy planes, normals either way: the slab 0.5 <= z <= 1.25
    slab = CutPatient(base, cut_halfspaces(cut_planes=(0, 0, 0.5, 0, 0, 1, 0, 0, 1.25, 0, 0, 1)))
    assert slab.volume == pytest.approx(4 * 0.75, rel=1e-9)
    assert slab.lo[2] == pytest.approx(0.5) and slab.hi[2] == pytest.approx(1.25)


def test_a_cut_through_a_mesh_with_a_hole_keeps_its_volume():
    """A hole in the surface leaves the lines through it an odd count of crossings: along one axis its whole
    shadow was lost (a femur shaft with a 218 mm² hole, cut to 20 mm, read 5,937 mm³ for 9,780). The oracle:
    the ball and the ball less its cap, in closed form (the mesh's facets are within 0.3 % of it)."""
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=10.0)
    centres = sphere.triangles_center
    # a cap of 15 degrees at +x: the lines along x through it are the ones that lose it
    holed = sphere.copy()
    holed.update_faces(centres[:, 0] < 10.0 * math.cos(math.radians(15)))
    holed.remove_unreferenced_vertices()
    assert not holed.is_watertight
    patient = mesh_patient_from_trimesh(holed, name="holed")
    for z in (5.0, 12.0):  # a cut, and none within the sphere
        kept = CutPatient(patient, cut_halfspaces(cut_planes=(0, 0, -20, 0, 0, 1, 0, 0, z, 0, 0, 1)))
        h = max(10.0 - z, 0.0)
        truth = 4 / 3 * math.pi * 10.0 ** 3 - math.pi * h * h * (3 * 10.0 - h) / 3
        assert kept.volume == pytest.approx(truth, rel=0.01), z


def test_cut_sdf_keeps_only_the_segment():
    base = mesh_patient_from_trimesh(cylinder_mesh(), name="cyl")
    cut = CutPatient(base, cut_halfspaces(cut_planes=(0, 0, 3, 0, 0, -1, 0, 0, 7, 0, 0, 1)))
    grid = Grid.covering(cut.lo, cut.hi, 0.25)
    assert grid.lo[2] < 3 < grid.origin[2] + grid.spacing and grid.hi[2] > 7 > grid.hi[2] - 2 * grid.spacing
    s = cut.sdf_grid(grid)
    z = grid.axes()[2]
    want = np.maximum(Cylinder(10).sdf_grid(grid), np.maximum(3 - z, z - 7)[None, None, :])
    assert np.max(np.abs(s - want)) < 0.5 * grid.spacing
    # exact cylinder segment of radius 5 and length 4, less the 256-gon's facets
    assert cut.volume == pytest.approx(math.pi * 25 * 4, rel=2e-3)


def test_cut_of_an_analytic_patient_counts_its_volume():
    # patients without volume_within (analytic, volumes) are measured on a grid
    cap = CutPatient(Sphere(10), cut_halfspaces(clip=(-1, -1, 7, 11, 11, 11)))
    # a cap of height 3 of a ball of radius 5: pi h^2 (3 r - h) / 3
    assert cap.volume == pytest.approx(math.pi * 3 ** 2 * (3 * 5 - 3) / 3, rel=0.01)
    assert cap.lo[2] == pytest.approx(7) and cap.hi[2] == pytest.approx(10, abs=0.5)


@pytest.mark.slow
def test_scaffold_lies_inside_mesh_patient():
    patient = mesh_patient_from_trimesh(cylinder_mesh(), name="cyl")
    r = generate(patient=patient, seeds=50, porosity=0.7, voxel=0.2, seed=1)
    assert r.mesh.is_watertight
    s = Cylinder(10).sdf(np.asarray(r.mesh.vertices))
    assert np.max(s) <= r.grid.spacing


def test_same_mesh_same_bytes():
    patient = mesh_patient_from_trimesh(sphere_mesh(subdivisions=3), name="s")
    grid = Grid.covering(patient.lo, patient.hi, 0.3)
    a, b = patient.sdf_grid(grid), patient.sdf_grid(grid)
    assert a.tobytes() == b.tobytes()


@pytest.mark.parametrize("x_range", [None, (4, 19)])
def test_compiled_ray_parity_matches_numpy_reference(x_range):
    # a coarse rotated box and a ball: lines through vertices, edges and faces; the NumPy passes
    # (crossings_reference, inside_votes_reference) are the oracle of the compiled ones
    from scipy.spatial.transform import Rotation

    from implicit_scaffold.fields.patient_mesh import crossings, crossings_reference, inside_votes_reference

    box = trimesh.creation.box(extents=[1.7, 1.1, 1.3])
    box.apply_transform(np.vstack([np.hstack([Rotation.from_euler("xyz", [0.3, -0.5, 0.9]).as_matrix(),
                                              [[1.2], [1.1], [1.0]]]), [0, 0, 0, 1]]))
    ball = sphere_mesh(1.1, subdivisions=2)
    ball.apply_translation([0.4, 0.5, 0.6])
    both = trimesh.util.concatenate([box, ball])
    V, F = np.asarray(both.vertices), np.asarray(both.faces)
    grid = Grid((-0.2, -0.13, -0.17), 0.1, (27, 25, 24))
    for axis in range(3):
        ua, va = (1, 2) if axis == 0 else ((0, 2) if axis == 1 else (0, 1))
        first = x_range[0] if (x_range and ua == 0) else 0
        nu = (x_range[1] - x_range[0]) if (x_range and ua == 0) else grid.shape[ua]
        args = (V, F, axis, grid.origin[ua], grid.spacing, nu, grid.origin[va], grid.spacing, grid.shape[va])
        got, want = crossings(*args, first_u=first), crossings_reference(*args, first_u=first)
        assert len(want[0]) > 100
        a, b = np.lexsort(got[::-1]), np.lexsort(want[::-1])
        assert np.array_equal(got[0][a], want[0][b]) and np.array_equal(got[1][a], want[1][b])
    inside, odd = inside_votes(V, F, grid, x_range=x_range)
    ref, ref_odd = inside_votes_reference(V, F, grid, x_range=x_range)
    assert 0.05 < inside.mean() < 0.95
    assert np.array_equal(inside, ref) and odd == ref_odd


def _boxes(*placed):
    """One mesh of axis-aligned boxes ((extents, centre, inward) each), concatenated as a file would hold them."""
    parts = []
    for extents, centre, inward in placed:
        b = trimesh.creation.box(extents=extents)
        b.apply_translation(centre)
        if inward:
            b.invert()
        parts.append(b)
    return trimesh.util.concatenate(parts)


def test_overlapping_surfaces_make_their_union_and_a_cavity_stays_hollow():
    from implicit_scaffold.errors import ScaffoldWarning

    grid = Grid((-1.45, -1.45, -1.45), 0.1, (40, 30, 30))
    # two unit cubes overlapping by half: the union is 1.5 mm3, and the overlap is inside
    with pytest.warns(ScaffoldWarning, match="2 closed surfaces that overlap"):
        two = mesh_patient_from_trimesh(_boxes(((1, 1, 1), (0, 0, 0), False), ((1, 1, 1), (0.5, 0, 0), False)),
                                        name="two.stl")
    assert two.volume == pytest.approx(1.5, rel=1e-12)
    sdf = two.sdf_grid(grid)
    x = grid.origin[0] + 0.1 * np.arange(40)
    assert np.all(sdf[np.abs(x - 0.25) < 0.2, 13:17, 13:17] < 0)  # the overlap: inside (parity said outside)
    assert np.count_nonzero(sdf < 0) * 1e-3 == pytest.approx(1.5, rel=0.02)
    # apart: each its own, no warning; a cavity (an inner surface wound inwards) is not filled
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        apart = mesh_patient_from_trimesh(_boxes(((1, 1, 1), (0, 0, 0), False), ((1, 1, 1), (3, 0, 0), False)),
                                          name="apart.stl")
        hollow = mesh_patient_from_trimesh(_boxes(((2, 2, 2), (0, 0, 0), False), ((1, 1, 1), (0, 0, 0), True)),
                                           name="hollow.stl")
    assert apart.volume == pytest.approx(2.0, rel=1e-12) and hollow.volume == pytest.approx(7.0, rel=1e-12)
    assert np.all(hollow.sdf_grid(grid)[13:17, 13:17, 13:17] > 0)


def _balls(*placed, subdivisions=4):
    """One mesh of icospheres ((radius, centre, inward) each) and the volume of each polyhedron, mm3."""
    parts = []
    for radius, centre, inward in placed:
        b = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
        b.apply_translation(centre)
        if inward:
            b.invert()
        parts.append(b)
    return trimesh.util.concatenate(parts), [abs(float(p.volume)) for p in parts]


#: 1 mm along a direction no two icosphere vertices share
_SKEW = np.array([1.0, 0.3, 0.2]) / math.sqrt(1.13)


def _ball_volume(r):
    return 4 / 3 * math.pi * r ** 3


def _read(mesh, name):
    """mesh_patient_from_trimesh, with the warnings it gave; the patient's own winding agrees with its volume
    (or is reversed throughout, as a file wound inward everywhere has always been read)."""
    import warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        patient = mesh_patient_from_trimesh(mesh, name=name)
    said = [str(w.message) for w in caught]
    wound = float(trimesh.Trimesh(patient.vertices, patient.faces, process=False).volume)
    assert abs(wound) == pytest.approx(patient.volume, rel=1e-12)  # the faces as written enclose the volume
    return patient, said


@pytest.mark.parametrize("outer_inward, inner_inward", [(False, False), (False, True), (True, False)])
def test_a_surface_inside_another_is_a_cavity_whatever_its_winding(outer_inward, inner_inward):
    # a ball of radius 2 holding a concentric ball of radius 1: 4/3 pi (8 - 1), the canal wound either way
    # (or both reversed, which the volume's magnitude read right already)
    mesh, (outer, inner) = _balls((2.0, (0, 0, 0), outer_inward), (1.0, (0, 0, 0), inner_inward))
    patient, said = _read(mesh, "canal.stl")
    assert patient.volume == pytest.approx(outer - inner, rel=1e-12)
    assert patient.volume == pytest.approx(_ball_volume(2) - _ball_volume(1), rel=5e-3)  # polyhedra of 642 vertices
    if inner_inward != outer_inward:
        assert said == []  # wound as nested already: as before, no warning (the faces as they were)
        assert np.array_equal(patient.faces, mesh_patient_from_trimesh(mesh, name="canal.stl").faces)
    else:
        assert len(said) == 1 and said[0].startswith(
            "canal.stl: 1 closed surface inside another is wound outward; read as a cavity")
    grid = Grid((-2.5, -2.5, -2.5), 0.25, (21, 21, 21))
    sdf = patient.sdf_grid(grid)
    assert sdf[10, 10, 10] > 0 and sdf[10, 10, 3] < 0  # the centre is in the cavity, the wall between the balls solid


@pytest.mark.parametrize("windings, cavities, solids", [((False, False, False), 1, 0),   # exported shell by shell
                                                        ((False, True, False), 0, 0),    # nested as it should
                                                        ((False, True, True), 0, 1)])    # the island wound inward
def test_an_island_in_a_cavity_is_solid(windings, cavities, solids):
    # radii 3, 2, 1 nested: solid, cavity, solid again: 4/3 pi (27 - 8 + 1)
    mesh, (a, b, c) = _balls(*((r, (0.1 * r, 0, 0), w) for r, w in zip((3.0, 2.0, 1.0), windings)))
    patient, said = _read(mesh, "island.stl")
    assert patient.volume == pytest.approx(a - b + c, rel=1e-12)
    assert patient.volume == pytest.approx(_ball_volume(3) - _ball_volume(2) + _ball_volume(1), rel=5e-3)
    assert len(said) == (1 if cavities or solids else 0)
    if cavities:
        assert "1 closed surface inside another is wound outward; read as a cavity" in said[0]
    if solids:
        assert "1 closed surface enclosing solid is wound inward; read as solid" in said[0]


def test_surfaces_that_cross_are_joined_not_nested():
    # two balls of radius 1 whose centres are 1 mm apart: their union, 2 (4/3 pi) minus the lens
    # pi (4r + d) (2r - d)^2 / 12 (apart along a skew direction: no vertex of one on the other)
    mesh, _ = _balls((1.0, (0, 0, 0), False), (1.0, _SKEW, False), subdivisions=5)
    patient, said = _read(mesh, "two.stl")
    lens = math.pi * (4 + 1) * (2 - 1) ** 2 / 12
    assert patient.volume == pytest.approx(2 * _ball_volume(1) - lens, rel=2e-3)
    assert len(said) == 1 and "2 closed surfaces that overlap" in said[0]
    # an L-shaped plate 1 mm thick (12 mm3) and a bar 3 x 1 x 0.5 across its inner corner at 45 degrees: the
    # bar's box lies within the L's and all its vertices inside it (parity from any says nested), yet its
    # middle crosses the L's notch, a right triangle of legs 0.5 + sqrt(2)/2, 0.5 thick, which joins
    ell = trimesh.boolean.union([trimesh.creation.box(bounds=[(0, 0, 0), (4, 2, 1)]),
                                 trimesh.creation.box(bounds=[(0, 0, 0), (2, 4, 1)])], engine="manifold")
    bar = trimesh.creation.box(extents=[3, 1, 0.5])
    bar.apply_transform(trimesh.transformations.rotation_matrix(-math.pi / 4, [0, 0, 1]))
    bar.apply_translation([2.25, 2.25, 0.5])
    x, y = bar.vertices[:, 0], bar.vertices[:, 1]
    assert np.all((x > 0) & (y > 0) & (np.minimum(x, y) < 2) & (np.maximum(x, y) < 4))  # every vertex in the L
    patient, said = _read(trimesh.util.concatenate([ell, bar]), "ell.stl")
    assert patient.volume == pytest.approx(12 + 0.5 * (0.5 + math.sqrt(0.5)) ** 2 * 0.5, rel=1e-12)
    assert len(said) == 1 and "2 closed surfaces that overlap" in said[0]


def test_two_cavities_apart_and_two_that_cross():
    # two balls of radius 1 apart inside one of radius 4, wound outward: two cavities
    mesh, (outer, a, b) = _balls((4.0, (0, 0, 0), False), (1.0, (-2, 0, 0), False), (1.0, (2, 0, 0), False))
    patient, said = _read(mesh, "two_canals.stl")
    assert patient.volume == pytest.approx(outer - a - b, rel=1e-12)
    assert len(said) == 1 and "2 closed surfaces inside another are wound outward; read as cavities" in said[0]
    # the two cross (centres 1 mm apart): not a nesting; as before, the union of all three (the outer ball)
    mesh, (outer, a, b) = _balls((4.0, (0, 0, 0), False), (1.0, -_SKEW / 2, False), (1.0, _SKEW / 2, False))
    patient, said = _read(mesh, "crossing_canals.stl")
    assert patient.volume == pytest.approx(outer, rel=1e-9)
    assert len(said) == 1 and "3 closed surfaces that overlap" in said[0]


def test_a_piece_in_anothers_box_but_outside_it_is_solid():
    # a ball in the notch of an L-shaped plate (within its box, outside it), wound inward: parity reads it
    # as solid, a piece beside the L, so the volume is the sum, not the difference
    ell = trimesh.boolean.union([trimesh.creation.box(bounds=[(0, 0, 0), (4, 2, 1)]),
                                 trimesh.creation.box(bounds=[(0, 0, 0), (2, 4, 1)])], engine="manifold")
    ball, (ball_volume,) = _balls((0.4, (3, 3, 0.5), True))
    patient, said = _read(trimesh.util.concatenate([ell, ball]), "beside.stl")
    assert patient.volume == pytest.approx(12 + ball_volume, rel=1e-12)
    assert len(said) == 1 and "1 closed surface enclosing solid is wound inward; read as solid" in said[0]
