"""End to end: porosity against the closed form, targets, mesh checks, reproducibility."""
import hashlib

import numpy as np
import pytest

import implicit_scaffold
from implicit_scaffold.fields.patient import Box, Cylinder, Sphere
from implicit_scaffold.geometry.skeleton import closed_form_porosity


@pytest.mark.slow
# the two ends of the paper's range and an unequal pair (0.5 and 0.75 lie between; the default
# 0.75 is held to the target by the printed-porosity tests): 250^3 grids are the suite's slowest
@pytest.mark.parametrize("sf, sv", [(0.25, 0.25), (0.6, 0.35)])
def test_voxel_porosity_equals_closed_form(sf, sv):
    # the oracle: 500 seeds, 250^3 voxels, sharp creases, no offset
    r = implicit_scaffold.generate(seeds=500, sf=sf, sv=sv, blend=0, porosity=None, voxel=0.04, mesh=False)
    assert r.grid.shape == (252, 252, 252)   # 250 inside the cube plus one outside layer each side
    assert abs(r.report["porosity_voxel"] - closed_form_porosity(sf, sv)) < 0.01
    assert r.report["surface_offset_mm"] == 0.0


@pytest.fixture(scope="module")
def default_like(tmp_path_factory):
    out = tmp_path_factory.mktemp("gen") / "s.stl"
    r = implicit_scaffold.generate(seeds=300, voxel=0.08, porosity=0.7, output=out)
    return r, out


def printed(r, volume):
    """Porosity of the built mesh by trimesh's own volume, against the shape's closed-form volume."""
    return 1.0 - r.mesh.volume / volume


def test_target_porosity_met(default_like):
    r, _ = default_like
    # what is printed (the mesh) meets the target within the 0.3 points
    assert abs(printed(r, 1000.0) - 0.7) < 0.003
    assert r.report["warnings"] == []
    assert r.report["porosity_printed"] == pytest.approx(printed(r, 1000.0), abs=1e-9)


def test_mesh_is_a_closed_solid_inside_the_patient(default_like):
    r, _ = default_like
    m = r.mesh
    assert m.is_watertight and m.is_winding_consistent and m.volume > 0
    assert r.report["bodies"] == 1
    # inside the patient: no vertex more than one voxel outside the 10 mm cube
    h = r.grid.spacing
    assert np.all(m.vertices >= -h) and np.all(m.vertices <= 10 + h)
    assert Box(10).sdf(m.vertices).max() <= h


def test_report_keys(default_like):
    r, out = default_like
    import json

    rep = json.loads(out.with_suffix(".json").read_text())
    for key in ("seeds", "sf", "sv", "style", "porosity_closed_form", "surface_offset_mm", "blend_mm",
                "voxel_mm", "grid_shape", "porosity_target", "porosity_voxel", "porosity_mesh",
                "triangles", "bodies", "watertight", "timings_s", "version", "rng_seed"):
        assert key in rep, key
    assert rep["seeds"] == 300 and rep["porosity_target"] == 0.7 and rep["watertight"] is True


def _digest(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.mark.parametrize("ext", [".stl", ".3mf", ".npy"])
def test_same_seed_same_bytes(tmp_path, ext):
    opts = dict(seeds=60, voxel=0.1, size=4.0, porosity=0.75)
    a, b, c = tmp_path / f"a{ext}", tmp_path / f"b{ext}", tmp_path / f"c{ext}"
    implicit_scaffold.generate(output=a, seed=1, **opts)
    implicit_scaffold.generate(output=b, seed=1, **opts)
    implicit_scaffold.generate(output=c, seed=2, **opts)
    assert _digest(a) == _digest(b)
    assert _digest(a) != _digest(c)


@pytest.mark.parametrize("shape, cls", [("cylinder", Cylinder), ("sphere", Sphere)])
def test_other_shapes(shape, cls):
    r = implicit_scaffold.generate(shape=shape, size=6.0, seeds=150, voxel=0.06, porosity=0.75)
    patient = cls(6.0)
    assert abs(printed(r, patient.volume) - 0.75) < 0.003
    assert r.mesh.is_watertight and r.report["bodies"] == 1
    assert patient.sdf(r.mesh.vertices).max() <= r.grid.spacing
    # porosity is measured against the shape's own volume, not its box
    assert r.report["patient_volume_mm3"] == pytest.approx(patient.volume)


def test_struts_meet_their_porosity():
    r = implicit_scaffold.generate(style="struts", seeds=200, voxel=0.06, size=6.0, porosity=0.85)
    assert abs(printed(r, 216.0) - 0.85) < 0.003
    assert r.report["strut_radius_mm"] > 0
    assert r.mesh.is_watertight


def test_field_only():
    r = implicit_scaffold.generate(seeds=50, voxel=0.1, size=4.0, mesh=False)
    assert r.mesh is None and r.field.dtype == np.float32 and r.field.shape == r.grid.shape
    assert "triangles" not in r.report


def test_seeds_in_patient_follow_the_patient_volume():
    # a sphere holds pi/6 of its box: seeding only where it is (plus one cell) makes fewer
    # seeds than the box formula, and the formula's count (of the sphere's volume) inside it
    from implicit_scaffold.geometry.seeds import seed_count

    r = implicit_scaffold.generate(shape="sphere", size=8.0, seeds_in="patient", pore_size=1.0,
                                   voxel=0.1, porosity=0.7, seed_rule="paper")
    expected = seed_count(Sphere(8.0).volume, 0.7, 1.0)
    box_count = seed_count(512.0, 0.7, 1.0)
    assert expected < r.report["seeds"] < box_count
    # Poisson count inside the sphere: within 4 standard deviations of the expected number
    assert abs(r.report["cells_in_scaffold"] - expected) < 4 * np.sqrt(expected)
    assert abs(printed(r, Sphere(8.0).volume) - 0.7) < 0.003 and r.report["bodies"] == 1


def test_skin_is_solid_and_porosity_still_met():
    r = implicit_scaffold.generate(shape="cylinder", size=6.0, seeds=120, voxel=0.06, porosity=0.7, skin=0.3)
    assert abs(printed(r, Cylinder(6.0).volume) - 0.7) < 0.003
    # every voxel of the 0.3 mm shell (less half a voxel for the sampling) is solid
    s_p = r.patient_sdf
    shell = (s_p < -0.03) & (s_p > -0.27)
    assert np.all(r.field[shell] < 0)
    assert r.mesh.is_watertight and r.report["bodies"] == 1


def test_smooth_cut_meets_porosity_and_stays_inside():
    r = implicit_scaffold.generate(shape="sphere", size=6.0, seeds=150, voxel=0.06, porosity=0.7, smooth_cut=0.2)
    assert abs(printed(r, Sphere(6.0).volume) - 0.7) < 0.003
    assert Sphere(6.0).sdf(r.mesh.vertices).max() <= r.grid.spacing


@pytest.mark.parametrize("sf, sv", [(0.25, 0.25), (0.25, 0.1)])
def test_default_blend_keeps_narrow_channels_open(sf, sv):
    # a blend wider than the narrow windows closes them and the void collapses (it gave
    # 5 % for P0 = 15.6 %, 0 % for P0 = 8.9 %): the default blend must leave the lattice's
    # porosity at its closed form
    r = implicit_scaffold.generate(seeds=120, size=5.0, sf=sf, sv=sv, porosity=None, voxel=0.04, mesh=False)
    assert r.report["blend_mm"] > 0
    assert abs(r.report["porosity_voxel"] - closed_form_porosity(sf, sv)) < 0.01


def test_under_resolved_struts_are_reported():
    # 2 mm pores at 0.4 mm voxels: walls thinner than a voxel; the mesh meets the target,
    # but the voxels read far from it: the run must say the print is coarse, and the fix
    from implicit_scaffold.errors import ScaffoldWarning

    with pytest.warns(ScaffoldWarning, match="points from the printed .* finer --voxel"):
        r = implicit_scaffold.generate(size=6.0, pore_size=2.0, voxel=0.4)
    assert abs(printed(r, 216.0) - 0.8) < 0.003 and abs(r.report["porosity_voxel"] - 0.8) > 0.05
    assert any("points from the printed" in w for w in r.report["warnings"])


def test_a_skin_closing_the_patient_keeps_its_porous_interior():
    # the skin seals the whole interior void from the outside: that void is the scaffold asked for,
    # not a cavity to fill (filling it gave a solid ball, porosity 0)
    import implicit_scaffold

    r = implicit_scaffold.generate(shape="sphere", size=3.0, skin=0.12, porosity=0.75, voxel=0.04,
                                   pore_size=0.6, mesh=False, morphometry=False)
    assert abs(r.report["porosity_voxel"] - 0.75) < 0.02
    inside = r.patient_sdf < 0
    void = inside & (r.field >= 0)
    # the interior is one void piece (6-connected) holding nearly all of the void
    from scipy import ndimage

    labels, n = ndimage.label(void)
    assert n >= 1 and np.bincount(labels.ravel())[1:].max() > 0.95 * np.count_nonzero(void)


class _TwoPlates:
    """Two 0.6 mm plates of 10 x 10 mm at opposite corners of a 40 mm box: thin anatomy far
    apart (ribs in an abdominal CT), thinner than a 64-step grid of the box resolves."""

    lo = np.zeros(3)
    hi = np.full(3, 40.0)
    volume = 2 * 10 * 10 * 0.6

    @staticmethod
    def sdf(p):
        def box(c, half):
            q = np.abs(p - c) - half
            return np.linalg.norm(np.maximum(q, 0), axis=-1) + np.minimum(q.max(axis=-1), 0)
        half = np.array([5, 5, 0.3])
        return np.minimum(box(np.array([5, 5, 0.3]), half), box(np.array([35, 35, 39.7]), half))

    def sdf_grid(self, grid, x_range=None):
        from implicit_scaffold.run.grid import evaluate_by_slabs

        def fn(x, y, z):
            pts = np.stack(np.broadcast_arrays(x, y, z), axis=-1)
            return self.sdf(pts)
        return evaluate_by_slabs(grid, fn, max_voxels=2_000_000, x_range=x_range)


def test_seeds_fill_thin_parts_of_a_large_box():
    """Seeds drawn in the patient and one cell's margin put the count asked for inside the
    patient, by the exact distance (the oracle), and none beyond the margin, when the patient's
    parts are thinner than the box's 64th: the seeding grid follows the cell, not the box."""
    from implicit_scaffold.pipeline import _coarse_patient
    from implicit_scaffold.geometry.seeds import seeds_in_patient

    patient, n = _TwoPlates(), 500
    cell = (patient.volume / n) ** (1 / 3)
    coarse, grid = _coarse_patient(patient, cell)
    assert grid.spacing <= cell / 2 + 1e-9
    seeds = seeds_in_patient(coarse, grid, patient.lo, patient.hi, n, np.random.default_rng(3), margin=cell)
    d = patient.sdf(seeds)
    # a binomial count around n: 4 standard deviations, and the grid's own error a little more
    assert abs(np.count_nonzero(d < 0) - n) < 4 * np.sqrt(n) + 0.02 * n
    assert d.max() < cell + grid.spacing


def test_the_seeds_of_a_thin_patients_margin_are_counted_before_they_are_drawn():
    """The memory check counts the seeds seeds_in_patient will draw in the patient's margin:
    on thin plates (a CT's ribs) they outnumber those inside and grow faster than pore**-3 as
    the pores grow. The oracle is the draw itself, at the pore size asked and at 1.5 times it
    (the patient's count scaled by pore**-3, the margin by the cell)."""
    from implicit_scaffold.pipeline import _coarse_patient, _margin_count
    from implicit_scaffold.geometry.seeds import seeds_in_patient

    patient, n = _TwoPlates(), 2000
    cell = (patient.volume / n) ** (1 / 3)
    coarse, grid = _coarse_patient(patient, cell)
    count_at = _margin_count(coarse, n, n, 0.6, cell, inside=True)
    for r in (1.0, 1.5):
        n_r = int(round(n / r ** 3))
        drawn = len(seeds_in_patient(coarse, grid, patient.lo, patient.hi, n_r, np.random.default_rng(5),
                                     margin=cell * r))
        assert drawn > 1.5 * n_r  # the margin holds a third of them or more
        assert abs(count_at(0.6 * r) - drawn) < 4 * np.sqrt(drawn) + 0.03 * drawn, (r, count_at(0.6 * r), drawn)
    # pore**-3 alone (what the refusal's pore size assumed) misses the larger pores' draw by a quarter
    assert count_at(0.6) / 1.5 ** 3 < 0.85 * count_at(0.9)


def test_a_voxel_that_cannot_hold_the_walls_is_refused_before_the_lattice(monkeypatch):
    # 2 mm pores at 0.8 mm voxels: walls about 0.85 mm thick as printed, 1.06 voxels across; at
    # that resolution every wall breaks into fragments (a CT label at 0.83-1.03 voxels across came
    # out empty): refused before the lattice, naming a voxel that holds them
    import re

    from implicit_scaffold.run import tiled
    from implicit_scaffold.errors import ScaffoldError

    def no_lattice(**kwargs):
        raise AssertionError("the lattice ran")

    with monkeypatch.context() as m:
        m.setattr(tiled, "tiled_scaffold", no_lattice)
        with pytest.raises(ScaffoldError, match="cannot hold the lattice") as excinfo:
            implicit_scaffold.generate(size=6.0, pore_size=2.0, voxel=0.8, mesh=False)
    assert "\n" not in str(excinfo.value)
    finer = float(re.search(r"use --voxel ([0-9.]+) or finer", str(excinfo.value)).group(1))
    # the voxel named holds them: the mesh, measured here, meets the target
    r = implicit_scaffold.generate(size=6.0, pore_size=2.0, voxel=finer)
    assert abs(printed(r, 216.0) - 0.8) < 0.003 and r.report["bodies"] == 1


def test_a_collapsed_scaffold_is_refused_before_the_mesh(tmp_path, monkeypatch):
    # 2 mm pores at 0.55 mm voxels (1.5 voxels across the printed wall): the walls break into
    # fragments and no level brings the print to its target. The oracle: the same run with the
    # check taken out, whose mesh (measured here) misses the target by more than 10 points
    from implicit_scaffold import pipeline
    from implicit_scaffold.errors import ScaffoldError

    run = dict(size=6.0, pore_size=2.0, voxel=0.55)
    with pytest.raises(ScaffoldError, match="too thin to hold together") as excinfo:
        implicit_scaffold.generate(output=tmp_path / "s.stl", **run)
    assert "\n" not in str(excinfo.value) and "--voxel" in str(excinfo.value)
    assert list(tmp_path.iterdir()) == []
    monkeypatch.setattr(pipeline, "_check_collapsed", lambda *args: None)
    r = implicit_scaffold.generate(**run)
    assert abs(printed(r, 216.0) - 0.8) > 0.10


def test_the_default_voxel_holds_the_printed_walls():
    # coarsened to keep a run small, the default voxel keeps 2 voxels across the wall as printed
    from implicit_scaffold.pipeline import _default_voxel

    box = 5.6e6  # a CT slab's box, mm^3: the 24 M-voxel cap alone gives 0.62 mm
    assert _default_voxel(0.40, box) == pytest.approx((box / 24e6) ** (1 / 3))
    assert _default_voxel(0.40, box, printed_wall=0.51) == pytest.approx(0.255)
    # where the cap is finer than that, it holds
    assert _default_voxel(0.40, 1e3, printed_wall=0.51) == pytest.approx(0.10)


def test_a_level_step_longer_than_a_voxel_is_no_correction():
    from implicit_scaffold.fields.printed import correction

    info = {"slope_per_mm": -0.2383}
    # the prism's slope does not hold that far: 0.71 mm at 0.33 mm voxels made a solid block
    assert correction(0.9734, 0.80, dict(info)) == pytest.approx((0.80 - 0.9734) / -0.2383)
    assert correction(0.9734, 0.80, info, max_step=0.33) is None and "more than" in info["correction"]
    assert correction(0.8030, 0.80, {"slope_per_mm": -4.0}, max_step=0.05) == pytest.approx(0.00075)


def test_a_run_in_slabs_gives_its_mesh_read_back_when_it_fits(tmp_path, recwarn):
    import trimesh

    from implicit_scaffold import generate
    from implicit_scaffold.errors import ScaffoldWarning

    kw = dict(size=1.6, pore_size=0.6, porosity=0.7, voxel=0.04, seed=3, morphometry=False)
    whole = generate(**kw)
    plane = whole.grid.shape[1] * whole.grid.shape[2]
    r = generate(output=tmp_path / "s.stl", tiled=24 * plane, **kw)
    assert r.report["tiled"]["slabs"] > 1 and r.mesh_file == tmp_path / "s.stl"
    # the mesh the slabs wrote, as trimesh reads the file: the whole-grid run's triangles, to float32
    m = r.mesh
    assert isinstance(m, trimesh.Trimesh) and len(m.faces) == len(whole.mesh.faces) == r.report["triangles"]
    assert m.volume == pytest.approx(whole.mesh.volume, rel=1e-6)
    assert r.mesh is m  # read once
    # a budget the read-back does not fit: None, with a warning that names the triangles
    small = generate(output=tmp_path / "t.stl", tiled=24 * plane, **kw)
    small.report["tiled"]["max_memory_mb"] = 1
    assert small.mesh is None
    assert any(f"{small.report['triangles']:,} triangles" in str(w.message) for w in recwarn
               if issubclass(w.category, ScaffoldWarning))


def test_the_mesh_slabs_do_not_move_with_a_few_mib_of_memory():
    """The mesh's slabs (and so its bytes) are planned from what memory is left, which moves by
    some MiB between runs of the same inputs: the planes a slab may hold are rounded down to the
    ladder 1, 2, 3, 4, 6, 8, 12, ... so that nearby budgets plan the same slabs, keeping at
    least two thirds of the planes the memory allows."""
    from implicit_scaffold.pipeline import _steady_voxels

    plane = 1312 * 1247  # the femoral shaft's plane at 0.02 mm
    ladder = [1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64, 96, 128]
    for planes in range(1, 129):
        for extra in (0, plane // 3, plane - 1):  # some MiB more or less within a plane
            got = _steady_voxels(planes * plane + extra, plane)
            assert got % plane == 0
            assert got // plane == max(v for v in ladder if v <= planes)
            assert got <= planes * plane + extra and 3 * got >= 2 * planes * plane


def test_windows_stay_open_at_a_cubes_faces():
    # the cells end at the cube's faces, where the channels open in windows; the blend once read
    # the solid beyond the cells and closed most windows with a film under a voxel thick (at
    # 0.012 mm voxels 87 % of the first plane was solid against 65 % one plane in). A channel
    # runs through the face: each face's first plane inside holds no more solid than the next
    r = implicit_scaffold.generate(size=1.2, voxel=0.012, pore_size=0.6, porosity=0.7, seed=0, mesh=False,
                                   morphometry=False)
    solid, inside = r.field < 0, r.patient_sdf < 0
    idx = [np.nonzero(inside.any(axis=tuple(b for b in range(3) if b != a)))[0] for a in range(3)]
    core = tuple(slice(i[0] + 3, i[-1] - 2) for i in idx)
    for axis in range(3):
        for first, step in ((idx[axis][0], 1), (idx[axis][-1], -1)):
            def plane(i):
                sl = list(core)
                sl[axis] = i
                return solid[tuple(sl)].mean()
            assert plane(first) <= plane(first + step) + 0.02, (axis, first, plane(first), plane(first + step))


def test_a_voxel_too_coarse_for_the_walls_names_only_fixes_the_user_has():
    # a CT calibration sets the pore sizes: its refusal names a finer voxel, not a larger --pore-size
    from implicit_scaffold.errors import ScaffoldError
    from implicit_scaffold.pipeline import _check_resolved

    for given, fix in ((True, "or a larger --pore-size"), (False, "(--calibration sets the pore sizes)")):
        with pytest.raises(ScaffoldError) as err:
            _check_resolved(0.123, 0.1, pore_size_given=given)
        assert str(err.value).endswith("use --voxel 0.061 or finer" + (", " if given else " ") + fix)


def test_fragments_are_blamed_for_a_porosity_miss_only_when_they_could_make_it():
    # removing solid raises the porosity by its share of the patient: 9 fragments of 0.0018 % were named the cause of
    # a 0.35-point miss; a share under a third of the miss is not the cause
    from implicit_scaffold.pipeline import _fragments_why

    report = {"fragments_removed_mm3": 0.001125, "patient_volume_mm3": 64.0}
    assert _fragments_why(report, 9, "the struts are under-resolved", 0.0035) == ("the struts are under-resolved",
                                                                                   False)
    why, blamed = _fragments_why({**report, "fragments_removed_mm3": 0.5}, 9, "other", 0.0035)
    assert blamed and "removing 9 solid fragments (0.5 mm3, 0.78 % of the patient)" in why
    assert _fragments_why(report, 0, "other", 0.01) == ("other", False)


@pytest.mark.parametrize("name, tolerance", [("s.3mf", 0.0), ("s.obj", 0.0), ("s.stl", 0.01), ("s.ply", 0.0)])
def test_a_run_in_slabs_inside_a_commands_run_writes_every_mesh_format(tmp_path, name, tolerance):
    # a command's run (run_outputs) keeps each output under its temporary name until the run ends: the mesh
    # staged as PLY (for 3MF and OBJ, or to simplify) was read back at its final name, which did not exist yet
    # ("No such file or directory" after the mesh of a CT's scaffold in slabs). Oracle: the whole-grid run's mesh
    import trimesh

    from implicit_scaffold import generate
    from implicit_scaffold.io.files import run_outputs

    kw = dict(size=1.6, pore_size=0.6, porosity=0.7, voxel=0.04, seed=3, morphometry=False)
    whole = generate(**kw)
    plane = whole.grid.shape[1] * whole.grid.shape[2]
    with run_outputs():
        r = generate(output=tmp_path / name, tiled=24 * plane, tolerance=tolerance, **kw)
    assert r.report["tiled"]["slabs"] > 1
    # the mesh and its report, no staged or temporary file left
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([name, "s.json"])
    m = trimesh.load(str(tmp_path / name), force="mesh")
    if tolerance == 0:
        assert len(m.faces) == len(whole.mesh.faces)
    assert m.is_watertight and m.volume == pytest.approx(whole.mesh.volume, rel=1e-3 if tolerance else 1e-6)
