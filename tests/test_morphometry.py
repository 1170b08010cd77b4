"""Voxel morphometry against shapes whose answers are known, and against brute force."""
import itertools
import math
import re

import numpy as np
import pytest
from scipy import ndimage

from implicit_scaffold.measure import morphometry as M
from implicit_scaffold.errors import ScaffoldError
from implicit_scaffold.run.grid import Grid


def _coords(n):
    return np.meshgrid(*(np.arange(n, dtype=float),) * 3, indexing="ij")


def ball(n, r, centre=None):
    c = (n - 1) / 2 if centre is None else centre
    x, y, z = _coords(n)
    return (x - c) ** 2 + (y - c) ** 2 + (z - c) ** 2 <= r * r


def torus(n, big, small):
    x, y, z = _coords(n)
    c = (n - 1) / 2
    rho = np.hypot(x - c, y - c)
    return (rho - big) ** 2 + (z - c) ** 2 <= small * small


def brute_local_thickness(phase):
    """Every phase voxel's largest inscribed sphere, painted by brute force (the definition)."""
    pts = np.argwhere(phase)
    bg = np.argwhere(~np.pad(phase, 1)) - 1
    out = np.zeros(phase.shape)
    grid = np.argwhere(np.ones(phase.shape, bool))
    for p in pts:
        r2 = ((bg - p) ** 2).sum(axis=1).min()  # squared distance to the nearest non-phase centre
        inside = ((grid - p) ** 2).sum(axis=1) < r2
        idx = tuple(grid[inside].T)
        out[idx] = np.maximum(out[idx], 2 * math.sqrt(r2))
    return out


@pytest.mark.parametrize("seed, shape", [(0, (18, 16, 14)), (1, (18, 16, 14)), (2, (11, 13, 140))])
def test_local_thickness_matches_brute_force(seed, shape):
    rng = np.random.default_rng(seed)
    from scipy import ndimage

    # a random blobby phase with thick and thin parts; the last one's rows span three 64-voxel
    # words and its 13 rows two bricks of 8
    phase = ndimage.gaussian_filter(rng.normal(size=shape), 2.0) > 0
    got = M.local_thickness(phase, 0.5)
    want = brute_local_thickness(phase) * 0.5
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("radius", [4.0, 7.5, 11.0])
def test_ball_thickness_is_its_diameter(radius):
    n = int(2 * radius) + 5
    phase = ball(n + (n + 1) % 2, radius)  # odd size: the centre is a voxel centre
    t = M.local_thickness(phase, 0.1)
    # the largest inscribed sphere is the ball itself: 2R within one voxel, at every voxel
    assert abs(t.max() - 2 * radius * 0.1) <= 0.1
    assert np.all(np.abs(t[phase] - 2 * radius * 0.1) <= 0.1 + 1e-6)


@pytest.mark.parametrize("thick", [3, 6, 9])
def test_slab_thickness_is_its_thickness(thick):
    phase = np.zeros((30, 30, 24), bool)
    phase[:, :, 5:5 + thick] = True
    h = 0.02
    t = M.local_thickness(phase, h)
    # the slab touches the array's sides, beyond which is no phase: look away from them
    core = t[thick + 2:-thick - 2, thick + 2:-thick - 2][phase[thick + 2:-thick - 2, thick + 2:-thick - 2]]
    assert np.all(np.abs(core - thick * h) <= h + 1e-9)


def test_thickness_stats_histogram_counts_every_voxel():
    phase = ball(25, 8, 9.0) | ball(25, 4, 18.0)  # two sizes of sphere
    t = M.local_thickness(phase, 0.05)
    st = M.thickness_stats(t, phase, 0.05)
    hist = st["histogram"]
    assert sum(hist["counts"]) == phase.sum()
    assert len(hist["edges_mm"]) == len(hist["counts"]) + 1
    assert hist["edges_mm"][0] == 0 and hist["edges_mm"][-1] > st["max"]
    vals = t[phase].astype(np.float64)
    assert st["mean"] == pytest.approx(vals.mean(), rel=1e-9) and st["sd"] == pytest.approx(vals.std(), rel=1e-9)
    assert st["sd"] > 0 and st["max"] == pytest.approx(vals.max())


def test_thickness_tally_counts_each_squared_radius_as_numpy_does():
    """The compiled count per squared radius against NumPy's over the gathered values (rounded
    half to even in float64): a local-thickness map, a slab of it (a view), and arbitrary float32
    values that are not of the 2 h sqrt(v) form."""
    rng = np.random.default_rng(11)
    phase = ndimage.gaussian_filter(rng.random((31, 27, 29)), 1.5) > 0.5
    h = 0.05
    t = M.local_thickness(phase, h)
    noise = (rng.random(phase.shape) * 3.0).astype(np.float32)
    for tmap, ph in ((t, phase), (t[7:19], phase[7:19]), (noise, phase), (t, ~phase)):
        want = np.bincount(np.rint((tmap[ph].astype(np.float64) / (2 * h)) ** 2).astype(np.int64))
        got = M.ThicknessTally(h).add(tmap, ph).counts
        n = max(len(want), len(got))
        assert np.array_equal(np.pad(got, (0, n - len(got))), np.pad(want, (0, n - len(want))))
        assert got.sum() == np.count_nonzero(ph)


@pytest.mark.parametrize("shape, chi", [
    (lambda: ball(15, 6), 1),
    (lambda: torus(30, 9, 4), 0),
    (lambda: ball(21, 9) & ~ball(21, 5), 2),  # a hollow ball: one body, one cavity
    (lambda: ball(21, 4, 5.0) | ball(21, 4, 15.0), 2),  # two separate balls
])
def test_euler_characteristic_of_known_shapes(shape, chi):
    assert M.euler_characteristic(shape()) == chi


def test_euler_of_two_tori_and_a_corner_contact():
    a = torus(30, 9, 3)
    both = np.concatenate([a, a], axis=0)
    assert M.euler_characteristic(both) == 0
    corner = np.zeros((4, 4, 4), bool)
    corner[1, 1, 1] = corner[2, 2, 2] = True  # 26-connected: one body
    assert M.euler_characteristic(corner) == 1


@pytest.mark.parametrize("seed", range(3))
def test_euler_matches_scikit_image(seed):
    from skimage.measure import euler_number

    vol = np.random.default_rng(seed).random((12, 11, 10)) < 0.45
    assert M.euler_characteristic(vol) == euler_number(np.pad(vol, 1), connectivity=3)


def test_connectivity_density_of_a_torus():
    t = torus(30, 9, 4)
    h = 0.1
    # one tunnel: (1 - chi) = 1 over the volume measured
    assert M.connectivity_density(t, h) == pytest.approx(1 / (t.size * h ** 3))


def test_interconnected_porosity_closed_and_open():
    n = 40
    solid = np.ones((n, n, n), bool)
    # closed cells: isolated spherical cavities inside a solid block
    x, y, z = _coords(n)
    for cx, cy, cz in itertools.product((10, 29), repeat=3):
        solid &= (x - cx) ** 2 + (y - cy) ** 2 + (z - cz) ** 2 > 36
    assert M.interconnected_porosity(solid) == 0.0
    # open cells: a channel along x through each row of cavities reaches the outside
    chan = solid.copy()
    for cy, cz in itertools.product((10, 29), repeat=2):
        chan[:, cy - 2:cy + 2, cz - 2:cz + 2] = False
    assert M.interconnected_porosity(chan) == 1.0
    # with a patient region: a cavity drilled to the region's outside (x < 3) counts as reached
    region = np.ones_like(solid)
    region[:3] = False  # the cavities start at x = 4
    cav = solid.copy()
    drill = np.zeros_like(solid)
    drill[1:12, 10, 10] = True
    cav &= ~drill
    reached = region & (drill | ((x - 10) ** 2 + (y - 10) ** 2 + (z - 10) ** 2 <= 36))
    void = region & ~cav
    assert M.interconnected_porosity(cav, region) == pytest.approx(reached.sum() / void.sum())


def test_fragments_of_two_balls():
    two = ball(30, 6, 8.0) | ball(30, 6, 21.0)
    assert M.count_fragments(two) == 1
    assert M.count_fragments(ball(30, 6)) == 0


def test_morphometry_keys_and_region():
    n = 30
    solid = ~(torus(n, 9, 4) | ball(n, 3))
    region = ball(n, 14)
    solid &= region
    r = M.morphometry(solid, 0.05, region=region)
    for key in ("strut_thickness_mm", "pore_diameter_mm", "connectivity_density_per_mm3",
                "interconnected_porosity", "fragments", "surface_area_mm2", "bs_bv_per_mm"):
        assert key in r
    assert r["porosity_voxel"] == pytest.approx(1 - solid.sum() / region.sum())
    assert r["fragments"] == 0


def test_surface_of_a_voxel_box():
    solid = np.zeros((12, 12, 12), bool)
    solid[2:8, 3:9, 4:10] = True  # 6 x 6 x 6 voxels
    area, vol = M.surface_from_volume(solid, 0.5)
    # the mesh runs halfway between centres: a 3 mm cube with its 12 edges and 8 corners
    # bevelled by marching cubes (half a voxel); bounded by the cube's measures
    assert 0.85 * 54 < area <= 54 and 0.9 * 27 < vol <= 27


def test_bad_inputs():
    with pytest.raises(ScaffoldError, match="3-D"):
        M.morphometry(np.zeros((4, 4)), 0.1)
    with pytest.raises(ScaffoldError, match="voxel size"):
        M.morphometry(np.zeros((4, 4, 4)), -1)
    with pytest.raises(ScaffoldError, match="shape"):
        M.morphometry(np.zeros((4, 4, 4)), 0.1, region=np.ones((3, 4, 4)))


def box_with_hole(a=4.0, s=2.0, c=1.5):
    """An a x a x c box with an s x s square hole through z, as a closed mesh."""
    import trimesh

    b = (a - s) / 2
    outer = [(0, 0), (a, 0), (a, a), (0, a)]
    inner = [(b, b), (b + s, b), (b + s, b + s), (b, b + s)]
    v = [(x, y, z) for z in (0.0, c) for x, y in outer + inner]
    O0, I0, O1, I1 = 0, 4, 8, 12  # bottom outer/inner, top outer/inner
    f = []
    for k in range(4):
        n = (k + 1) % 4
        f += [(O0 + k, I0 + n, O0 + n), (O0 + k, I0 + k, I0 + n)]  # bottom ring, facing -z
        f += [(O1 + k, O1 + n, I1 + n), (O1 + k, I1 + n, I1 + k)]  # top ring, facing +z
        f += [(O0 + k, O0 + n, O1 + n), (O0 + k, O1 + n, O1 + k)]  # outer wall
        f += [(I0 + k, I1 + n, I0 + n), (I0 + k, I1 + k, I1 + n)]  # inner wall
    m = trimesh.Trimesh(np.array(v), np.array(f), process=True)
    return m


def test_box_with_hole_mesh_is_closed_and_outward():
    m = box_with_hole()
    assert m.is_watertight and m.is_winding_consistent and m.volume > 0


def test_voxelize_box_with_hole():
    a, s, c = 4.0, 2.0, 1.5
    m = box_with_hole(a, s, c)
    grid = Grid.covering(m.bounds[0], m.bounds[1], 0.1)
    inside = M.voxelize(m.vertices, m.faces, grid)
    p = grid.points().reshape(*grid.shape, 3)
    b = (a - s) / 2
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    want = ((x > 0) & (x < a) & (y > 0) & (y < a) & (z > 0) & (z < c)
            & ~((x > b) & (x < a - b) & (y > b) & (y < a - b)))
    assert np.array_equal(inside, want)


def test_voxelize_open_mesh_is_refused():
    import trimesh

    m = trimesh.creation.box(extents=(1, 1, 1))
    drop = np.nonzero(np.abs(m.face_normals[:, 2]) > 0.9)[0][0]  # a triangle of the top or bottom
    m = trimesh.Trimesh(m.vertices, np.delete(m.faces, drop, axis=0), process=True)
    grid = Grid.covering(m.bounds[0], m.bounds[1], 0.1)
    with pytest.raises(ScaffoldError, match="not closed"):
        M.voxelize(m.vertices, m.faces, grid)


def test_same_result_on_one_thread_and_all():
    from implicit_scaffold.run.threads import limited

    rng = np.random.default_rng(3)
    from scipy import ndimage

    phase = ndimage.gaussian_filter(rng.normal(size=(40, 36, 30)), 2.5) > 0
    every = M.local_thickness(phase, 0.1)
    with limited(1):
        one = M.local_thickness(phase, 0.1)
    assert np.array_equal(every, one)


def test_volume_resampled_to_the_voxel_asked(tmp_path):
    import SimpleITK as sitk

    vol = torus(31, 9, 4)
    img = sitk.GetImageFromArray(np.transpose(vol, (2, 1, 0)).astype(np.uint8))
    img.SetSpacing((0.05, 0.05, 0.05))
    sitk.WriteImage(img, str(tmp_path / "t.nii.gz"))
    a = M.analyze_file(tmp_path / "t.nii.gz", voxel=0.15)
    # nearest voxel: the new centres (k + 1/2) 0.15 mm are the centres of old voxels 3k + 1
    idx = 3 * np.arange(10) + 1
    assert a.solid.shape == (10, 10, 10)
    assert np.array_equal(a.solid, vol[np.ix_(idx, idx, idx)])
    assert a.report["voxel_mm"] == 0.15 and "nearest" in a.report["resampled"]


def test_euler_characteristic_is_additive_over_slabs_with_a_one_plane_halo():
    from implicit_scaffold.run.tiles import ArraySlabs

    rng = np.random.default_rng(5)
    # a random solid: many components, tunnels and cavities crossing every slab boundary
    solid = rng.random((23, 17, 19)) < 0.45
    field = np.where(solid, -1.0, 1.0).astype(np.float32)
    source = ArraySlabs(field, Grid((0.0, 0.0, 0.0), 1.0, field.shape))
    whole = M.euler_characteristic(solid)
    for cuts in ([0, 23], [0, 1, 23], [0, 5, 6, 14, 22, 23], list(range(24))):
        assert M.euler_characteristic_by_slabs(source, zip(cuts[:-1], cuts[1:])) == whole, cuts
    # the oracles for the whole: a solid torus 0, a hollow ball 2 (test above), here two balls 2
    two = np.zeros((12, 5, 5), bool)
    two[1:4, 1:4, 1:4] = two[7:10, 1:4, 1:4] = True
    src = ArraySlabs(np.where(two, -1.0, 1.0).astype(np.float32), Grid((0.0, 0.0, 0.0), 1.0, two.shape))
    assert M.euler_characteristic_by_slabs(src, [(0, 3), (3, 8), (8, 12)]) == 2


@pytest.mark.parametrize("planes,halo", [(9, 1), (16, 3), (400, 40)])
def test_morphometry_by_slabs_gives_the_whole_grid_figures(planes, halo):
    """Slabs of a scaffold's field, with a halo too narrow at first (widened by the check),
    give the whole grid's morphometry, bit for bit."""
    from implicit_scaffold import generate
    from implicit_scaffold.run.tiles import ArraySlabs

    r = generate(size=2.0, pore_size=0.6, porosity=0.7, voxel=0.04, seed=5, mesh=False, morphometry=False)
    s, s_p, grid = r.field, r.patient_sdf, r.grid
    # a sealed void kept, and a piece of void cut off by solid: the interconnection is not 1
    s = s.copy()
    deepest = np.unravel_index(np.argmin(s), s.shape)
    assert s[deepest] < -1.5 * grid.spacing  # its six neighbours are solid
    s[deepest] = 0.02
    whole = M.morphometry(s < 0, grid.spacing, region=s_p < 0, surface=False)
    plane = grid.shape[1] * grid.shape[2]
    got = M.morphometry_by_slabs(ArraySlabs(s, grid), ArraySlabs(s_p, grid), grid.spacing,
                                 max_voxels=planes * plane, halo=halo, planes=planes)
    halo_used = got.pop("morphometry_halo_planes")
    whole.pop("porosity_voxel")
    # twice the widest sphere's radius, in planes, whatever the halo it started from
    assert halo_used >= whole["pore_diameter_mm"]["max"] / grid.spacing - 1e-9 or planes >= grid.shape[0]
    assert whole["interconnected_porosity"] < 1
    assert got == whole
    # the solid's pieces given (a run's passes counted them): the same figures without labelling it
    pieces = whole["fragments"] + 1
    known = M.morphometry_by_slabs(ArraySlabs(s, grid), ArraySlabs(s_p, grid), grid.spacing,
                                   max_voxels=planes * plane, halo=halo, planes=planes, solid_pieces=pieces)
    known.pop("morphometry_halo_planes")
    assert known == whole


def _write_volume(path, array, spacing=(0.1, 0.1, 0.1)):
    """`array` (x, y, z) written as a volume file (SimpleITK's arrays are (z, y, x))."""
    import SimpleITK as sitk

    img = sitk.GetImageFromArray(np.ascontiguousarray(np.transpose(array, (2, 1, 0))))
    img.SetSpacing(spacing)
    sitk.WriteImage(img, str(path))
    return path


def test_a_label_map_and_a_ct_are_measured_by_the_solid_chosen(tmp_path):
    # a label map: label 2 a 4 x 5 x 6 box, label 7 elsewhere; a CT in HU: bone 1200 in air -1000
    labels = np.zeros((10, 12, 14), np.uint8)
    labels[1:5, 2:7, 3:9] = 2
    labels[6:9, 8:11, 1:3] = 7
    ct = np.where(labels == 2, 1200, -1000).astype(np.int16)
    ct[6:9, 8:11, 1:3] = 150  # soft tissue: under the threshold
    a = M.analyze_file(_write_volume(tmp_path / "seg.nii.gz", labels), label=2)
    b = M.read_scaffold(_write_volume(tmp_path / "ct.nrrd", ct), threshold=200)
    box = labels == 2
    # the solid is exactly the box: its voxel count, against the whole volume's
    assert np.array_equal(a.solid, box) and np.array_equal(b.solid, box)
    assert a.report["porosity_voxel"] == pytest.approx(1 - 4 * 5 * 6 / labels.size, abs=1e-12)
    assert a.report["selection"] == "label 2" and b.selection == "intensity >= 200"
    # two labels at once (a bone in pieces)
    both = M.read_scaffold(tmp_path / "seg.nii.gz", label="2,7")
    assert np.array_equal(both.solid, labels > 0) and both.selection == "labels 2, 7"
    # a binary volume keeps every non-zero voxel, as before
    c = M.read_scaffold(_write_volume(tmp_path / "bin.nii.gz", (labels > 0).astype(np.uint8)))
    assert np.array_equal(c.solid, labels > 0) and c.selection == "non-zero voxels"


@pytest.mark.parametrize("kind, options, words", [
    ("labels", {}, "is a label map (labels 2, 7); pass --label N"),
    ("ct", {}, "holds intensities (-1000 to 1200); pass --threshold"),
    ("labels", {"label": 3}, "label 3 has no voxel"),
    ("ct", {"threshold": 5000}, "reaches the threshold 5000"),
    ("ct", {"label": 2, "threshold": 200}, "not both"),
    ("mesh", {"label": 2}, "is not a volume"),
    ("mesh", {"spacing": 0.1}, "--spacing applies to a volume; m.stl is a mesh"),
])
def test_a_volume_needs_its_solid_chosen_in_one_line(tmp_path, kind, options, words):
    import trimesh

    labels = np.zeros((6, 6, 6), np.uint8)
    labels[1:3] = 2
    labels[4:] = 7
    ct = np.where(labels == 2, 1200, -1000).astype(np.int16)
    if kind == "mesh":
        trimesh.creation.box(extents=(1, 1, 1)).export(tmp_path / "m.stl")
        path, options = tmp_path / "m.stl", {"voxel": 0.1, **options}
    else:
        path = _write_volume(tmp_path / f"{kind}.nii.gz", labels if kind == "labels" else ct)
    with pytest.raises(ScaffoldError) as exc:
        M.read_scaffold(path, **options)
    assert words in str(exc.value) and "\n" not in str(exc.value)


def test_a_mesh_read_on_its_runs_grid_gives_back_the_runs_solid(tmp_path):
    # marching cubes' surface passes between voxel centres of opposite signs: voxelised again on the
    # grid of the run that wrote it (the JSON beside it), the mesh is that run's solid, voxel for voxel;
    # placed from the mesh's bounds, thin walls broke (an L3 scaffold: 410 floating pieces, 63 sealed voids)
    from implicit_scaffold import generate
    from implicit_scaffold.measure.morphometry import analyze_file, read_scaffold

    r = generate(output=tmp_path / "s.stl", size=3, voxel=0.06, seed=2)
    built = np.asarray(r.field) < 0
    for voxel in (None, 0.06):
        assert np.array_equal(read_scaffold(tmp_path / "s.stl", voxel=voxel).solid, built)
    assert np.array_equal(analyze_file(tmp_path / "s.stl").solid, built)
    assert analyze_file(tmp_path / "s.stl").report["fragments"] == r.report["fragments"]
    # another voxel is the user's own grid, placed from the mesh's bounds
    assert read_scaffold(tmp_path / "s.stl", voxel=0.05).solid.shape != built.shape


@pytest.mark.parametrize("name", ["s.nrrd", "s.nii.gz", "s.mha", "s.npy"])
def test_generates_own_field_outputs_are_read_as_their_solid(tmp_path, name):
    # a float volume generate wrote is a signed distance, negative in the solid: read with its report beside
    # it, its solid is the field's (the run's own array is the oracle), where an intensity threshold selects
    # nothing of the kind (it was refused as a CT needing --threshold); without the report it is refused still
    from implicit_scaffold import generate
    from implicit_scaffold.measure.morphometry import analyze_file, read_scaffold

    r = generate(output=tmp_path / name, size=2, voxel=0.1, pore_size=0.6, seed=1)
    built = np.asarray(r.field) < 0
    assert np.array_equal(analyze_file(tmp_path / name).solid, built)
    assert np.array_equal(read_scaffold(tmp_path / name).solid, built)
    # over the run's patient (the report beside it), as generate counted it, not over the grid's outer layer:
    # the 2 mm box's voxel centres inside it, by the grid's axes
    found = analyze_file(tmp_path / name).report
    assert found["region"] == "the patient of s.json (box)"
    assert found["porosity_voxel"] == pytest.approx(r.report["porosity_voxel"], abs=1e-12)
    box = np.ones(r.grid.shape, bool)
    for a, axis in enumerate(r.grid.axes()):
        box &= np.expand_dims((axis > 0) & (axis < 2.0), [b for b in range(3) if b != a])
    assert np.array_equal(read_scaffold(tmp_path / name).region, box)
    assert found["porosity_voxel"] == pytest.approx(1 - np.count_nonzero(built & box) / np.count_nonzero(box),
                                                    abs=1e-12)
    if name != "s.npy":
        (tmp_path / "s.json").unlink()
        with pytest.raises(ScaffoldError, match="report beside it"):
            analyze_file(tmp_path / name)


def test_a_field_with_nan_is_refused_in_one_line(tmp_path):
    # NaN is not below 0: a corrupt field's NaN voxels were read as void without a word
    field = np.full((6, 6, 6), 1.0, np.float32)
    field[2:4, 2:4, 2:4] = -1.0
    field[3, 3, 3] = np.nan
    np.save(tmp_path / "f.npy", field)
    with pytest.raises(ScaffoldError, match="holds 1 non-finite values") as exc:
        M.read_scaffold(tmp_path / "f.npy", voxel=0.1)
    assert "\n" not in str(exc.value)


def test_a_npy_of_objects_is_refused_without_numpys_advice(tmp_path):
    # numpy's message advised loading pickled objects "unsafely"
    np.save(tmp_path / "o.npy", np.array([{"a": 1}] * 8, dtype=object).reshape(2, 2, 2))
    with pytest.raises(ScaffoldError, match="holds Python objects, not numbers") as exc:
        M.read_scaffold(tmp_path / "o.npy", voxel=0.1)
    assert "pickle" not in str(exc.value) and "\n" not in str(exc.value)


def test_a_mesh_without_a_voxel_is_asked_for_one_sized_to_it(tmp_path):
    # the example was 0.04 mm whatever the mesh (12,000 voxels along a 466 mm femur): now its longest side / 200
    import trimesh

    trimesh.creation.box(extents=(100.0, 20.0, 10.0)).export(tmp_path / "b.stl")
    for read in (M.read_scaffold, M.analyze_file):
        with pytest.raises(ScaffoldError, match=r"e\.g\. --voxel 0\.5 \(mm: 200 voxels along its longest side, 100 mm") \
                as exc:
            read(tmp_path / "b.stl")
        assert "\n" not in str(exc.value)


def test_a_field_whose_runs_patient_cannot_be_built_again_is_measured_over_its_grid(tmp_path):
    # the report names a patient file that is gone: the field is still measured, over its grid, with a warning
    # that says so (not a failure: the certificate of the grid is still the scaffold's); another --voxel is
    # another grid, where the run's patient does not lie, and the grid is the region without a word
    import json
    import warnings

    from implicit_scaffold import generate
    from implicit_scaffold.errors import ScaffoldWarning
    from implicit_scaffold.measure.morphometry import read_scaffold

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ScaffoldWarning)  # a coarse voxel for a quick run: not what is tested
        generate(output=tmp_path / "s.npy", size=1.5, voxel=0.1, pore_size=0.6, seed=1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert read_scaffold(tmp_path / "s.npy", voxel=0.11).region_name == "the grid"
    report = json.loads((tmp_path / "s.json").read_text())
    report["patient_source"] = {"file": str(tmp_path / "gone.stl")}
    (tmp_path / "s.json").write_text(json.dumps(report))
    with pytest.warns(ScaffoldWarning, match="could not be built again.*measured over the grid instead"):
        scaffold = read_scaffold(tmp_path / "s.npy")
    assert scaffold.region is None and scaffold.region_name == "the grid"


def _write_oriented(path, array, spacing, direction, origin=(0.0, 0.0, 0.0)):
    """`array` (the file's index axes i, j, k) written with a direction matrix (row-major, column a:
    the world direction of index axis a) and origin, mm."""
    import SimpleITK as sitk

    img = sitk.GetImageFromArray(np.ascontiguousarray(np.transpose(array, (2, 1, 0))))
    img.SetSpacing(tuple(float(v) for v in spacing))
    img.SetDirection(tuple(float(v) for v in np.asarray(direction, float).ravel()))
    img.SetOrigin(tuple(float(v) for v in origin))
    sitk.WriteImage(img, str(path))
    return path


def _world_copies(tmp_path):
    """A small solid with no symmetry between its axes, on the world axes (identity direction), and two
    copies of the same world geometry: stored (k, i, j) (index axes along +z, +x, +y) and with i reversed."""
    rng = np.random.default_rng(7)
    # odd sizes, anisotropic spacing: a mix-up of axes or of their spacing shows
    solid = (ndimage.gaussian_filter(rng.normal(size=(13, 17, 11)), 1.5) > 0.1).astype(np.uint8)
    spacing = np.array([0.1, 0.2, 0.3])
    ident = _write_oriented(tmp_path / "ident.nii.gz", solid, spacing, np.eye(3))
    # column a of the direction: the world axis index axis a runs along (+z, +x, +y)
    perm = _write_oriented(tmp_path / "perm.nii.gz", np.transpose(solid, (2, 0, 1)), spacing[[2, 0, 1]],
                           [[0, 1, 0], [0, 0, 1], [1, 0, 0]])
    flip = _write_oriented(tmp_path / "flip.nii.gz", solid[::-1], spacing, np.diag([-1.0, 1.0, 1.0]),
                           origin=((solid.shape[0] - 1) * spacing[0], 0.0, 0.0))
    return solid, ident, perm, flip


def test_a_permuted_or_flipped_volume_is_read_on_the_world_axes(tmp_path):
    import SimpleITK as sitk

    solid, ident, perm, flip = _world_copies(tmp_path)
    # independent oracle: ITK's own index-to-world map puts each copy's voxel centres where the
    # identity copy's are
    for path in (perm, flip):
        img = sitk.ReadImage(str(path))
        arr = np.transpose(sitk.GetArrayFromImage(img), (2, 1, 0))
        ijk = np.argwhere(arr)
        world = np.array([img.TransformIndexToPhysicalPoint(tuple(int(v) for v in p)) for p in ijk])
        back = np.rint(world / [0.1, 0.2, 0.3]).astype(int)
        assert sorted(map(tuple, back)) == sorted(map(tuple, np.argwhere(solid)))
    ref = M.read_scaffold(ident, voxel=0.1)
    assert ref.axes is None
    for path, words in ((perm, "+j, +k, +i"), (flip, "-i, +j, +k")):
        got = M.read_scaffold(path, voxel=0.1)
        assert got.solid.shape == ref.solid.shape and np.array_equal(got.solid, ref.solid)
        assert words in got.axes


@pytest.mark.parametrize("spacing, voxel", [((0.2, 0.2, 0.2), None), ((0.1, 0.2, 0.3), None), ((0.1, 0.2, 0.3), 0.05)])
def test_a_volume_is_placed_where_its_header_puts_it(tmp_path, spacing, voxel):
    # a volume's voxels were placed half a voxel from 0 whatever its origin: positions (the most strained voxels,
    # a certificate's) did not read in the scanner's frame. Oracle: ITK's own index-to-world map of the file (an
    # anisotropic one is resampled to its finest spacing, or to --voxel: the same box in finer voxels)
    import SimpleITK as sitk

    solid, *_ = _world_copies(tmp_path)
    spacing = np.array(spacing)
    target = spacing.min() if voxel is None else voxel
    shift = np.array([100.0, -50.0, 20.0])
    files = [_write_oriented(tmp_path / "ident.nrrd", solid, spacing, np.eye(3), origin=shift),
             _write_oriented(tmp_path / "perm.nrrd", np.transpose(solid, (2, 0, 1)), spacing[[2, 0, 1]],
                             [[0, 1, 0], [0, 0, 1], [1, 0, 0]], origin=shift),
             _write_oriented(tmp_path / "flip.nrrd", solid[::-1], spacing, np.diag([-1.0, 1.0, 1.0]), origin=shift)]
    for path in files:
        img = sitk.ReadImage(str(path))
        corners = np.array([img.TransformIndexToPhysicalPoint(tuple(int(v) for v in c))
                            for c in itertools.product(*[(0, n - 1) for n in img.GetSize()])])
        lowest = corners.min(axis=0)  # the centre of the voxel nearest -x, -y, -z
        got = M.read_scaffold(path, voxel=voxel)
        assert got.voxel == target
        want = lowest - spacing / 2 + target / 2  # the same box's corner, half a new voxel in
        assert np.allclose(got.origin, want, rtol=0, atol=1e-9), path.name


def test_mechanics_names_its_most_strained_voxels_where_the_file_has_them(tmp_path):
    # end to end: every most strained voxel of `mechanics` on a flipped volume away from the origin is the world
    # centre (ITK's index-to-world map) of a solid voxel of the file
    import json

    import SimpleITK as sitk

    from implicit_scaffold.cli import main

    solid = np.ones((13, 17, 11), np.uint8)
    solid[3:7, :, 4:8] = 0  # a channel along y off the middle of x: the strain gathers beside it, on one side
    path = _write_oriented(tmp_path / "flip.nrrd", solid[::-1], (0.2, 0.2, 0.2), np.diag([-1.0, 1.0, 1.0]),
                           origin=(100.0, -50.0, 20.0))
    out = tmp_path / "m.json"
    assert main(["mechanics", str(path), "--material", "pcl", "-o", str(out), "-q"]) == 0
    top = json.loads(out.read_text())["compression"]["most_strained_voxels"]
    img = sitk.ReadImage(str(path))
    arr = np.transpose(sitk.GetArrayFromImage(img), (2, 1, 0))
    centres = np.array([img.TransformIndexToPhysicalPoint(tuple(int(v) for v in p)) for p in np.argwhere(arr)])
    assert len(top) > 0
    for t in top:
        assert np.abs(centres - np.array(t["centre_mm"])).max(axis=1).min() <= 1e-6, t


def test_check_and_mechanics_figures_per_axis_agree_on_permuted_and_flipped_copies(tmp_path):
    import json

    from implicit_scaffold.cli import main
    from implicit_scaffold.measure.mechanics import load_sample

    _, ident, perm, flip = _world_copies(tmp_path)
    figures = {}
    for path in (ident, perm, flip):
        out = tmp_path / f"{path.name}.json"
        assert main(["check", str(path), "--printer", "dlp-resin", "--voxel", "0.1", "-o", str(out), "-q"]) == 0
        cert = json.loads(out.read_text())
        figures[path.name] = {k: v for k, v in cert.items() if k not in ("source", "timings_s", "seconds", "axes")}
        sample, _ = load_sample(path, voxel=0.1)
        figures[path.name]["solved_solid"] = sample.solid.tolist()
    assert figures["perm.nii.gz"] == figures["ident.nii.gz"]
    assert figures["flip.nii.gz"] == figures["ident.nii.gz"]


def test_an_oblique_volume_stays_on_its_index_axes_and_says_so(tmp_path):
    from implicit_scaffold.errors import ScaffoldWarning

    solid = np.zeros((9, 10, 11), np.uint8)
    solid[2:7, 3:8, 2:9] = 1
    c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
    path = _write_oriented(tmp_path / "obl.nii.gz", solid, (0.1, 0.1, 0.1), [[c, -s, 0], [s, c, 0], [0, 0, 1]])
    with pytest.warns(ScaffoldWarning, match="oblique direction"):
        got = M.read_scaffold(path)
    assert np.array_equal(got.solid, solid.astype(bool)) and "oblique" in got.axes


def _write_binary_stl(path, corners):
    """`corners` ``(n, 3, 3)`` mm as a binary STL (zero normals: the readers take the winding)."""
    rec = np.zeros(len(corners), [("normal", "<f4", 3), ("corners", "<f4", (3, 3)), ("attr", "<u2")])
    rec["corners"] = corners
    with open(path, "wb") as fh:
        fh.write(b"test".ljust(80, b" ") + np.uint32(len(corners)).tobytes())
        fh.write(rec.tobytes())
    return path


def test_a_binary_stl_is_read_as_trimesh_reads_it(tmp_path):
    # numpy's read of a binary STL (a sixth of trimesh's memory) gives trimesh's vertices and faces, array for
    # array: corners within 1e-8 mm merged (a -0.0, a 1e-9 or 2e-9 written for a 0: the same vertex, its first
    # value in the file kept), vertices in the order of their first corner, and a mesh whose normals point in turned out
    m = box_with_hole()
    corners = np.asarray(m.vertices)[np.asarray(m.faces)].astype(np.float32)
    at_origin = np.argwhere(np.all(corners == 0, axis=2))
    assert len(at_origin) >= 3
    # the origin's first corner in the file, between the others in the sort (neither the lowest nor the highest
    # float32 bits): the vertex keeps the first value, not the first or last sorted
    corners[tuple(at_origin[0])] = (1e-9, -0.0, 0.0)
    corners[tuple(at_origin[1])] = (2e-9, 0.0, -0.0)
    for name, tris in (("out.stl", corners), ("in.stl", corners[:, ::-1])):
        path = _write_binary_stl(tmp_path / name, tris)
        assert M.binary_stl_triangles(path) == len(tris)
        v, f = M.read_mesh_arrays(path)
        t = M._read_mesh(path)
        assert np.array_equal(v, t.vertices) and np.array_equal(f, t.faces), name
        assert v.dtype == np.float64 and f.dtype == np.int64 and len(v) == 16
        if name == "out.stl":
            origin = v[np.all(np.abs(v) < 1e-6, axis=1)]
            assert len(origin) == 1 and origin[0, 0] == np.float32(1e-9)
        grid = Grid.covering(v.min(axis=0), v.max(axis=0), 0.1)
        assert np.array_equal(M.voxelize(v, f, grid), M.voxelize(t.vertices, t.faces, grid))
    # an ASCII STL is not one: trimesh reads it
    m.export(tmp_path / "a.stl", file_type="stl_ascii")
    assert M.binary_stl_triangles(tmp_path / "a.stl") is None
    v, f = M.read_mesh_arrays(tmp_path / "a.stl")
    t = M._read_mesh(tmp_path / "a.stl")
    assert np.array_equal(v, t.vertices) and np.array_equal(f, t.faces)


def test_analyze_measures_a_binary_stl_from_its_arrays(tmp_path):
    # two boxes apart, the larger with a cubic cavity (its inner wall wound inward): closed-form volume, area and
    # bodies, read from the file's arrays (no trimesh mesh is made: the default cube's took analyze to 3.4 GB)
    import trimesh

    outer = trimesh.creation.box(extents=(2.0, 3.0, 4.0))
    cavity = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    cavity.invert()
    small = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    small.apply_translation((4.0, 0.0, 0.0))
    parts = [outer, cavity, small]
    tris = np.concatenate([np.asarray(p.vertices)[np.asarray(p.faces)] for p in parts]).astype(np.float32)
    path = _write_binary_stl(tmp_path / "two.stl", tris)
    analysis = M.analyze_file(path, voxel=0.1)
    r = analysis.report
    assert r["mesh_volume_mm3"] == pytest.approx(24.0 - 1.0 + 1.0, rel=1e-9)
    assert r["bs_bv_per_mm"] * r["mesh_volume_mm3"] == pytest.approx(52.0 + 6.0 + 6.0, rel=1e-9)
    assert r["bodies"] == 2 and r["triangles"] == 36
    box = (4.5 - -1.0) * 3.0 * 4.0  # the bounding box, x from -1 to 4.5
    assert r["porosity_mesh"] == pytest.approx(1.0 - 24.0 / box, rel=1e-9)
    assert not isinstance(analysis.mesh, trimesh.Trimesh) and len(analysis.mesh.faces) == 36


def test_an_open_binary_stl_is_refused_in_one_line(tmp_path):
    m = box_with_hole()
    corners = np.asarray(m.vertices)[np.asarray(m.faces)][1:]
    path = _write_binary_stl(tmp_path / "open.stl", corners)
    with pytest.raises(ScaffoldError, match="open.stl is not a closed surface") as exc:
        M.read_scaffold(path, voxel=0.1)
    assert "\n" not in str(exc.value)


def test_the_mesh_read_estimate_bounds_the_peak_measured_in_a_fresh_process(tmp_path):
    # a binary STL of 1.3 M triangles read and voxelised on 1.1 M voxels, in a fresh process (the kernels'
    # compilation counts, as in a user's run): the peak above what the process held is within
    # mesh_read_memory, and not far from it (a bound of twice the peak saves no run)
    import json
    import subprocess
    import sys
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=8, radius=5.0)
    path = _write_binary_stl(tmp_path / "ball.stl", np.asarray(s.vertices)[np.asarray(s.faces)])
    script = ("import json, sys\n"
              "from implicit_scaffold.measure import morphometry as M\n"
              "from implicit_scaffold.run.memory import peak_memory, release\n"
              "held = release()\n"
              "s = M.read_scaffold(sys.argv[1], voxel=0.1, region=False)\n"
              "print(json.dumps({'above': peak_memory() - held, 'voxels': s.solid.size}))\n")
    done = subprocess.run([sys.executable, "-c", script, str(path)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    got = json.loads(done.stdout)
    need = M.mesh_read_memory(len(s.faces), got["voxels"])
    assert got["voxels"] > 10**6
    assert got["above"] <= need <= 2 * got["above"], (got["above"] / 2**20, need / 2**20)


@pytest.mark.parametrize("slab_voxels, layers", [(1, 1), (3000, 1), (3000, 8), (1 << 22, 8)])
def test_surface_by_slabs_is_the_whole_meshs(monkeypatch, slab_voxels, layers):
    # the oracle: the whole grid's marching-cubes mesh (surface_mesh) and its summary, summed over the slabs'
    # triangles, from one cube layer a slab up to the whole grid in one
    from implicit_scaffold.mesh.marching import mesh_summary

    monkeypatch.setattr(M, "SURFACE_SLAB_VOXELS", slab_voxels)
    monkeypatch.setattr(M, "SURFACE_SLAB_LAYERS", layers)
    solid = ndimage.gaussian_filter(np.random.default_rng(3).standard_normal((37, 29, 23)), 1.5) > 0.05
    solid[0, 5:9, 5:9] = solid[-1, :, :3] = True  # solid on the array's faces: closed by the layer outside
    whole = mesh_summary(M.surface_mesh(solid, Grid((0.0, 0.0, 0.0), 0.1, solid.shape)))
    area, volume = M.surface_from_volume(solid, 0.1)
    assert area == pytest.approx(whole["surface_area_mm2"], rel=1e-12)
    assert volume == pytest.approx(whole["volume_mm3"], rel=1e-12)


def test_volume_of_a_voxel_ball_is_the_spheres():
    n, r, h = 64, 25.0, 0.1
    _, volume = M.surface_from_volume(ball(n, r), h)
    # the mesh runs halfway between solid and void centres: the ball's volume within a couple of per cent
    # (its area is not the sphere's: marching cubes on voxels is a terraced surface)
    assert volume == pytest.approx(4 / 3 * np.pi * (r * h) ** 3, rel=0.02)


def _corners(vertices, faces):
    """The triangles as sorted rows of their corners' coordinates (numbering and order left out)."""
    tri = np.round(np.asarray(vertices)[np.asarray(faces)], 6)  # (F, 3, 3)
    tri = np.sort(tri.view([("x", float), ("y", float), ("z", float)]).reshape(len(faces), 3), axis=1)
    return np.sort(tri.view(float).reshape(len(faces), 9), axis=0)


def _torus_file(path):
    import trimesh

    from implicit_scaffold.mesh.writers import write_mesh

    mesh = trimesh.creation.torus(major_radius=3.0, minor_radius=1.0, major_sections=24, minor_sections=12)
    write_mesh(mesh, path)
    return mesh


@pytest.mark.parametrize("chunk", [1 << 24, 97])
def test_a_3mf_is_read_in_chunks_as_trimesh_reads_it(tmp_path, monkeypatch, chunk):
    # the oracle: trimesh's own 3MF reader, on a torus written by generate's writer; in chunks of 97 bytes every
    # element and tag is cut somewhere
    import trimesh

    monkeypatch.setattr(M, "MODEL_CHUNK", chunk)
    path = tmp_path / "t.3mf"
    _torus_file(path)
    read = M._read_3mf(path)
    assert read is not None
    vertices, faces = read
    theirs = trimesh.load(str(path), force="mesh")
    assert len(vertices) == len(theirs.vertices) and len(faces) == len(theirs.faces)
    np.testing.assert_array_equal(_corners(vertices, faces), _corners(theirs.vertices, theirs.faces))
    v, f = M.read_mesh_arrays(path)  # closed, outward
    grid = Grid.covering(v.min(axis=0), v.max(axis=0), 0.25)
    np.testing.assert_array_equal(M.voxelize(v, f, grid), M.voxelize(theirs.vertices, theirs.faces, grid))


def test_a_3mf_with_repeated_vertices_is_merged_as_trimesh_merges_it(tmp_path):
    import zipfile

    path = tmp_path / "t.3mf"
    _torus_file(path)
    with zipfile.ZipFile(path) as z:
        xml = z.read("3D/3dmodel.model")
    # every triangle's corners written as vertices of their own: three times the vertices, each one repeated
    head, rest = xml.split(b"<vertices>\n")
    rows, rest = rest.split(b"</vertices>\n<triangles>\n")
    tris, tail = rest.split(b"</triangles>")
    verts = rows.splitlines()
    faces = [[int(w.split(b'"')[1]) for w in t.split()[1:4]] for t in tris.splitlines()]
    corners = [verts[i] for f in faces for i in f]
    own = b"".join(b'<triangle v1="%d" v2="%d" v3="%d"/>\n' % (3 * k, 3 * k + 1, 3 * k + 2) for k in range(len(faces)))
    odd = tmp_path / "odd.3mf"
    with zipfile.ZipFile(odd, "w") as z:
        z.writestr("3D/3dmodel.model", head + b"<vertices>\n" + b"\n".join(corners) + b"\n</vertices>\n<triangles>\n"
                   + own + b"</triangles>" + tail)
    v, f = M._read_3mf(odd)
    v0, f0 = M._read_3mf(path)
    assert len(v) == len(v0) and len(f) == len(f0)
    np.testing.assert_array_equal(_corners(v, f), _corners(v0, f0))


@pytest.mark.parametrize("edit", [
    lambda xml: xml.replace(b'<item objectid="1"/>', b'<item objectid="1" transform="1 0 0 0 1 0 0 0 1 5 0 0"/>'),
    lambda xml: xml.replace(b'unit="millimeter"', b'unit="inch"'),
    lambda xml: re.sub(rb'<vertex x="([^"]*)" y="([^"]*)" z="([^"]*)"/>', rb'<vertex z="\3" y="\2" x="\1"/>', xml),
])
def test_a_3mf_beyond_one_plain_mesh_is_left_to_trimesh(tmp_path, edit):
    # a transform, another unit, attributes in another order: the streamed reader declines (None), trimesh reads
    import zipfile

    path = tmp_path / "t.3mf"
    _torus_file(path)
    with zipfile.ZipFile(path) as z:
        parts = {n: z.read(n) for n in z.namelist()}
    plain = parts["3D/3dmodel.model"]
    parts["3D/3dmodel.model"] = edit(plain)
    assert parts["3D/3dmodel.model"] != plain
    other = tmp_path / "other.3mf"
    with zipfile.ZipFile(other, "w") as z:
        for n, data in parts.items():
            z.writestr(n, data)
    assert M._read_3mf(other) is None


@pytest.mark.parametrize("suffix, chunk", [(".obj", 1 << 24), (".obj", 61), (".ply", None)])
def test_an_obj_or_ply_is_read_as_trimesh_reads_it(tmp_path, monkeypatch, suffix, chunk):
    # the oracle: trimesh's readers, on a torus written by generate's writers (in 61-byte chunks every line is cut)
    import trimesh

    if chunk is not None:
        monkeypatch.setattr(M, "OBJ_CHUNK", chunk)
    path = tmp_path / f"t{suffix}"
    _torus_file(path)
    read = {".obj": M._read_obj, ".ply": M._read_ply}[suffix](path)
    assert read is not None
    vertices, faces = read
    theirs = trimesh.load(str(path), force="mesh")
    assert len(vertices) == len(theirs.vertices) and len(faces) == len(theirs.faces)
    np.testing.assert_array_equal(_corners(vertices, faces), _corners(theirs.vertices, theirs.faces))


@pytest.mark.parametrize("edit", [
    lambda text: text.replace(b"f ", b"vn 0 0 1\nf ", 1),  # normals
    lambda text: re.sub(rb"^f (\d+) (\d+) (\d+)$", rb"f \1/\1 \2/\2 \3/\3", text, count=1, flags=re.M),
    lambda text: text + b"f 1 2 3 4\n",  # a quad
    lambda text: text.replace(b"v ", b"o torus\nv ", 1),  # an object name
])
def test_an_obj_beyond_vertices_and_triangles_is_left_to_trimesh(tmp_path, edit):
    path = tmp_path / "t.obj"
    _torus_file(path)
    plain = path.read_bytes()
    assert M._read_obj(path) is not None
    path.write_bytes(edit(plain))
    assert path.read_bytes() != plain and M._read_obj(path) is None


def test_a_ply_of_another_layout_is_left_to_trimesh(tmp_path):
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=2)
    path = tmp_path / "ascii.ply"
    path.write_bytes(trimesh.exchange.ply.export_ply(mesh, encoding="ascii"))
    assert M._read_ply(path) is None
    v, f = M.read_mesh_arrays(path)  # trimesh's read, closed and outward
    assert len(f) == len(mesh.faces)


# --------------------------------------------------------------------------- the measures' memory


def test_a_measure_over_its_budget_is_refused_naming_a_budget_and_a_voxel_that_fit():
    from implicit_scaffold.measure.mechanics import held_margin
    from implicit_scaffold.run.memory import parse_memory

    mib = 2**20
    work = M.MeasureMemory("the test", 40 * mib, 32)
    extent, voxel, held, total = 10.0, 0.05, 60 * mib, 200 * mib
    shape = (200, 200, 200)
    # its need by hand: the larger of what the process holds and the fixed part, and 32 bytes a voxel
    assert work.need(200**3, held) == 60 * mib + 32 * 200**3
    with pytest.raises(ScaffoldError) as err:
        M.check_measure_memory(work, "s.stl", shape, voxel, held, total, coarser=True)
    text = str(err.value)
    named = re.search(r"use --max-memory (\S+) or --voxel (\S+)$", text)
    assert named and "\n" not in text and "200x200x200" in text, text
    assert parse_memory(named.group(1)) >= 60 * mib + 32 * 200**3 + held_margin(held)
    assert err.value.budget >= work.need(200**3, held)
    # the voxel named fits the budget on the same extent, and one a tenth finer does not
    fit = float(named.group(2))
    for h, fits in ((fit, True), (fit * 0.9, False)):
        n = math.ceil(extent / h)
        assert (work.need(n**3, held) + held_margin(held) <= total) == fits, (h, n)
    # a field's voxel is its own: only a budget is named; a grid that fits passes
    with pytest.raises(ScaffoldError, match=r"use --max-memory \S+$"):
        M.check_measure_memory(work, "s.npy", shape, voxel, held, total, coarser=False)
    M.check_measure_memory(work, "s.npy", (100, 100, 100), voxel, held, total, coarser=False)


def _gyroid_field(path, n):
    x = np.linspace(0, 2 * np.pi * 2, n, dtype=np.float32)
    X, Y, Z = np.meshgrid(x, x, x, indexing="ij", sparse=True)
    g = np.sin(X) * np.cos(Y) + np.sin(Y) * np.cos(Z) + np.sin(Z) * np.cos(X)
    np.save(path, (np.abs(g) - 0.6).astype(np.float32))
    return path


# the process's own peak: VmHWM, its memory's high-water mark (getrusage's keeps the parent's from before exec:
# a child of this test process read 446 MiB where the same command run from a shell read 311)
PEAK = ("import sys\nfrom implicit_scaffold.cli import main\ncode = main(sys.argv[1:])\n"
        "hwm = [ln for ln in open('/proc/self/status') if ln.startswith('VmHWM')][0].split()[1]\n"
        "print('PEAK', int(hwm) * 1024, code)\n")


@pytest.mark.parametrize("command", ["analyze", "check"])
def test_the_measures_peak_lies_under_its_estimate_and_a_refusal_names_what_fits(command, tmp_path, capsys,
                                                                                   monkeypatch):
    # the estimate (MeasureMemory) is the budget's word for the measure: a fresh process's own peak stays under it;
    # a budget under it is refused in one line, before the measure, naming the budget that runs it
    import subprocess
    import sys

    from implicit_scaffold.cli import main
    from implicit_scaffold.measure.printability import certificate_memory
    from implicit_scaffold.run.memory import parse_memory

    n = 200
    src = _gyroid_field(tmp_path / "g.npy", n)
    work = M.ANALYSIS_MEMORY if command == "analyze" else certificate_memory()
    extra = ["--printer", "lpbf-ti64"] if command == "check" else []
    argv = [command, str(src), "--voxel", "0.05", "-q", "-o", str(tmp_path / "r.json")] + extra
    run = subprocess.run([sys.executable, "-c", PEAK] + argv, capture_output=True, text=True, timeout=600)
    peak, code = run.stdout.split("PEAK")[-1].split()
    assert code == "0", run.stderr
    assert int(peak) <= work.need(n**3, 0), (int(peak) / 2**20, work.need(n**3, 0) / 2**20)
    measured = []
    real = M.morphometry
    monkeypatch.setattr(M, "morphometry", lambda *a, **k: measured.append(1) or real(*a, **k))
    assert main(argv + ["--max-memory", "1M"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err and not measured, err
    named = re.search(r"needs about \S+, over --max-memory \S+; use --max-memory (\S+)$", err.strip())
    assert named, err
    assert parse_memory(named.group(1)) >= work.need(n**3, 0)
    assert main(argv + ["--max-memory", named.group(1)]) == 0, capsys.readouterr().err


def test_a_mesh_of_another_format_is_counted_once_read_and_its_refusal_names_a_budget_that_runs(tmp_path, capsys,
                                                                                                monkeypatch):
    # a PLY's triangles are not known before it is read (a binary STL's header says them): once read, its grid and
    # its triangles (check's signed distance) are estimated before the voxels, and the budget named runs the check
    import trimesh

    from implicit_scaffold.cli import main
    from implicit_scaffold.measure.printability import certificate_memory
    from implicit_scaffold.run.memory import parse_memory

    mesh = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    mesh.export(tmp_path / "ball.ply")
    argv = ["check", str(tmp_path / "ball.ply"), "--voxel", "0.04", "--printer", "lpbf-ti64", "-q",
            "-o", str(tmp_path / "c.json"), "--max-memory"]
    voxelized = []
    real = M.voxelize
    monkeypatch.setattr(M, "voxelize", lambda *a, **k: voxelized.append(1) or real(*a, **k))
    assert main(argv + ["1M"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err and not voxelized, err
    named = re.search(r"the print check of ball\.ply on (\d+)x(\d+)x(\d+) voxels at 0\.04 mm needs about \S+, "
                      r"over --max-memory \S+; use --max-memory (\S+)$", err.strip())
    assert named, err
    voxels = math.prod(int(v) for v in named.groups()[:3])
    # at least the triangles' share of the signed distance and the certificate's voxels
    assert parse_memory(named.group(4)) >= certificate_memory().bytes_per_triangle * len(mesh.faces)
    assert parse_memory(named.group(4)) >= certificate_memory().need(voxels, 0)
    assert main(argv + [named.group(4)]) == 0, capsys.readouterr().err
    assert voxelized


def test_a_binary_stls_bounds_and_grid_are_known_before_it_is_read(tmp_path, capsys, monkeypatch):
    # a binary STL's corners give its grid before the read: one refusal names a budget that holds the read and the
    # measure both, and the read it refuses never starts
    import trimesh

    from implicit_scaffold.cli import main

    mesh = trimesh.creation.icosphere(subdivisions=4, radius=1.5)
    mesh.apply_translation((3.0, -2.0, 0.5))
    path = tmp_path / "ball.stl"
    mesh.export(path)
    lo, hi = M.binary_stl_bounds(path, M.binary_stl_triangles(path))
    assert np.allclose(lo, mesh.bounds[0], atol=1e-6) and np.allclose(hi, mesh.bounds[1], atol=1e-6)
    reads = []
    real = M.read_mesh_arrays
    monkeypatch.setattr(M, "read_mesh_arrays", lambda p: reads.append(p) or real(p))
    for command, extra in (("check", ["--printer", "lpbf-ti64"]), ("analyze", [])):
        argv = [command, str(path), "--voxel", "0.02", "-q", "-o", str(tmp_path / f"{command}.json")] + extra
        assert main(argv + ["--max-memory", "1M"]) == 2
        err = capsys.readouterr().err
        named = re.search(r"on (\d+)x(\d+)x(\d+) voxels at 0\.02 mm needs about \S+, over --max-memory \S+; "
                          r"use --max-memory (\S+)$", err.strip())
        assert named and not reads, err
        # the ball's 3 mm across at 0.02 mm, and a layer outside all round: 152 voxel centres a side
        assert [int(v) for v in named.groups()[:3]] == [152, 152, 152], err
        assert main(argv + ["--max-memory", named.group(4)]) == 0, capsys.readouterr().err
        assert reads
        reads.clear()
