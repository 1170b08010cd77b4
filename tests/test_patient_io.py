"""Reading patients from files: every mesh format, units, surgical cuts, bad input, a real femur."""
import math
import warnings

import numpy as np
import pytest
import trimesh

from implicit_scaffold.cli import main
from implicit_scaffold.errors import ScaffoldError, ScaffoldWarning
from implicit_scaffold.io.patient_io import load_patient


def cylinder(scale=1.0):
    """A cylinder of radius 5 and height 10 (mm), axis z, in [0, 10]^3, times `scale`."""
    m = trimesh.creation.cylinder(radius=5, height=10, sections=96)
    m.apply_translation([5, 5, 5])
    m.apply_scale(scale)
    return m


@pytest.fixture()
def cyl_stl(tmp_path):
    path = tmp_path / "cyl.stl"
    cylinder().export(path)
    return path


@pytest.mark.parametrize("name, file_type", [("c.stl", "stl"), ("c.stl", "stl_ascii"), ("c.obj", "obj"),
                                             ("c.ply", "ply"), ("c.off", "off"), ("c.3mf", "3mf")])
def test_every_mesh_format_gives_the_same_patient(tmp_path, name, file_type):
    mesh = cylinder()
    path = tmp_path / name
    data = mesh.export(file_type=file_type)
    path.write_bytes(data.encode() if isinstance(data, str) else data)
    p = load_patient(path)
    # a closed mesh keeps its exact volume (ascii STL rounds coordinates to a few digits)
    assert p.volume == pytest.approx(mesh.volume, rel=1e-5)
    np.testing.assert_allclose(p.lo, [0, 0, 0], atol=1e-5)
    np.testing.assert_allclose(p.hi, [10, 10, 10], atol=1e-5)
    assert p.load_seconds >= 0 and name in p.describe()


@pytest.mark.parametrize("scale, units", [(1e-3, "m"), (1e3, "um")])
def test_units_warning_and_fix(tmp_path, scale, units):
    path = tmp_path / "bone.stl"
    cylinder(scale).export(path)
    with pytest.warns(ScaffoldWarning, match=f"pass --units {units}"):
        load_patient(path)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        p = load_patient(path, units=units)
    # back in mm: the same cylinder
    np.testing.assert_allclose(p.hi, [10, 10, 10], rtol=1e-6)
    assert p.volume == pytest.approx(cylinder().volume, rel=1e-6)


def test_cm_scales_a_mesh(tmp_path):
    path = tmp_path / "bone.stl"
    cylinder(0.1).export(path)  # 1 cm across, given in cm
    p = load_patient(path, units="cm")
    np.testing.assert_allclose(p.hi, [10, 10, 10], rtol=1e-6)


def _3mf_in_unit(path, mesh, unit):
    """Write `mesh` (coordinates already in `unit`) as a 3MF whose ``<model unit=...>`` says `unit`
    (trimesh's writer always says millimeter)."""
    import io
    import re
    import zipfile

    src = zipfile.ZipFile(io.BytesIO(mesh.export(file_type="3mf")))
    with zipfile.ZipFile(path, "w") as out:
        for name in src.namelist():
            data = src.read(name)
            if name.endswith(".model"):
                data = re.sub(rb'unit="[a-z]+"', f'unit="{unit}"'.encode(), data, count=1)
            out.writestr(name, data)


@pytest.mark.parametrize("unit, mm_per_unit", [("inch", 25.4), ("centimeter", 10.0), ("meter", 1000.0),
                                               ("micron", 1e-3)])
def test_a_3mf_declared_unit_is_converted_to_mm(tmp_path, unit, mm_per_unit):
    path = tmp_path / f"bone_{unit}.3mf"
    _3mf_in_unit(path, cylinder(1 / mm_per_unit), unit)
    # independent oracle: trimesh reads the unit and converts the mesh itself
    ref = trimesh.load(path, force="mesh")
    assert ref.units == unit
    ref.convert_units("millimeters")
    with pytest.warns(ScaffoldWarning, match=f"declares its unit as {unit}"):
        p = load_patient(path)
    np.testing.assert_allclose(p.hi, ref.bounds[1], rtol=1e-9)
    np.testing.assert_allclose(p.hi, [10, 10, 10], rtol=1e-6)
    assert p.volume == pytest.approx(abs(ref.volume), rel=1e-9)
    assert p.volume == pytest.approx(cylinder().volume, rel=1e-6)


def test_units_given_override_a_3mf_declared_unit_with_a_warning(tmp_path):
    path = tmp_path / "bone.3mf"
    _3mf_in_unit(path, cylinder(1 / 25.4), "inch")
    with warnings.catch_warnings():
        # the unit asked agrees with the file's: nothing to say
        warnings.simplefilter("error")
        agree = load_patient(path, units="in")
    np.testing.assert_allclose(agree.hi, [10, 10, 10], rtol=1e-6)
    with pytest.warns(ScaffoldWarning, match="declares its unit as inch.*--units mm overrides"):
        raw = load_patient(path, units="mm")
    np.testing.assert_allclose(raw.hi, np.full(3, 10 / 25.4), rtol=1e-6)


def test_inch_units_scale_a_mesh_by_25_4(tmp_path):
    path = tmp_path / "bone.stl"
    cylinder(1 / 25.4).export(path)  # an STL in inches: it cannot say so
    p = load_patient(path, units="in")
    np.testing.assert_allclose(p.hi, [10, 10, 10], rtol=1e-6)
    assert p.volume == pytest.approx(cylinder().volume, rel=1e-6)


def test_units_in_on_the_command_line(tmp_path):
    from implicit_scaffold.cli import build_parser

    args = build_parser().parse_args(["generate", "--patient", "x.stl", "--units", "in", "-o", "x.stl"])
    assert args.units == "in"


def test_clip_and_cut_planes_keep_the_segment(cyl_stl):
    clipped = load_patient(cyl_stl, clip=(-1, -1, 2, 11, 11, 6))
    segment = load_patient(cyl_stl, cut_planes=(0, 0, 2, 0, 0, 1, 0, 0, 6, 0, 0, -1))
    full = cylinder().volume
    for p in (clipped, segment):
        # the 96-gon prism cut at z = 2 and 6 keeps 4/10 of it, exactly
        assert p.volume == pytest.approx(0.4 * full, rel=1e-4)
        assert p.lo[2] == pytest.approx(2) and p.hi[2] == pytest.approx(6)
        assert p.load_seconds > 0
    assert "--clip -1 -1 2 11 11 6" in clipped.describe()


def _junk(tmp_path):
    files = {}
    (tmp_path / "notes.txt").write_text("a femur")
    files["unknown"] = (tmp_path / "notes.txt", "neither a mesh")
    (tmp_path / "junk.ply").write_text("ply garbage\n")
    files["unreadable"] = (tmp_path / "junk.ply", "cannot read junk.ply as a PLY mesh")
    (tmp_path / "empty.stl").write_text("solid x\nendsolid x\n")
    files["empty"] = (tmp_path / "empty.stl", "holds no triangles")
    (tmp_path / "nan.stl").write_text("solid x\nfacet normal 0 0 1\nouter loop\nvertex nan 0 0\nvertex 1 0 0\n"
                                      "vertex 0 1 0\nendloop\nendfacet\nendsolid x\n")
    files["nan"] = (tmp_path / "nan.stl", "NaN or infinite coordinates")
    sphere = trimesh.creation.icosphere(3, radius=5)
    cup = trimesh.Trimesh(sphere.vertices, sphere.faces[sphere.triangles_center[:, 2] > 0], process=False)
    cup.export(tmp_path / "cup.stl")
    files["open"] = (tmp_path / "cup.stl", "too open to tell inside from outside")
    # an interrupted download: half a .nii.gz (ITK alone reads the missing half as zeros)
    import SimpleITK as sitk

    ball = np.linalg.norm(np.indices((30, 30, 30)) - 14.5, axis=0) <= 10
    noise = np.random.default_rng(3).integers(0, 3, ball.shape)
    sitk.WriteImage(sitk.GetImageFromArray(np.where(ball, 31, noise).astype(np.uint8)), str(tmp_path / "whole.nii.gz"))
    data = (tmp_path / "whole.nii.gz").read_bytes()
    (tmp_path / "half.nii.gz").write_bytes(data[: len(data) // 2])
    files["cut_short"] = (tmp_path / "half.nii.gz", "half.nii.gz is cut short")
    return files


@pytest.mark.parametrize("case", ["unknown", "unreadable", "empty", "nan", "open", "cut_short", "missing",
                                  "clip_misses", "label_on_mesh", "threshold_on_mesh", "bad_units_on_volume",
                                  "empty_clip"])
def test_bad_input_one_line_exit_2_nothing_written(tmp_path, capsys, cyl_stl, case):
    files = _junk(tmp_path)
    extra = []
    if case in files:
        path, message = files[case]
    elif case == "missing":
        path, message = tmp_path / "nope.stl", "no such file or folder"
    elif case == "clip_misses":
        path, message = cyl_stl, "keeps none of the bone"
        extra = ["--clip", "20", "20", "20", "30", "30", "30"]
    elif case == "empty_clip":
        path, message = cyl_stl, "--clip box is empty"
        extra = ["--clip", "5", "0", "0", "1", "10", "10"]
    elif case == "bad_units_on_volume":
        (tmp_path / "ct.nii.gz").write_bytes(b"")
        path, message = tmp_path / "ct.nii.gz", "--units applies to a mesh"
        extra = ["--units", "m"]
    else:
        path, message = cyl_stl, "--label and --threshold select bone in a volume"
        extra = ["--label", "3"] if case == "label_on_mesh" else ["--threshold", "200"]
    out = tmp_path / "out" / "s.stl"
    out.parent.mkdir()
    code = main(["generate", "--patient", str(path), "-o", str(out), "-q", "--voxel", "0.5", *extra])
    err = capsys.readouterr().err
    assert code == 2
    assert message in err and err.startswith("implicit-scaffold: error:")
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert not any(out.parent.iterdir())


def test_library_raises_scaffold_error(tmp_path):
    with pytest.raises(ScaffoldError, match="holds no triangles"):
        load_patient(_junk(tmp_path)["empty"][0])


def test_cli_generates_from_a_mesh_patient(tmp_path, cyl_stl):
    out = tmp_path / "s.stl"
    code = main(["generate", "--patient", str(cyl_stl), "--cut-planes", "0", "0", "2", "0", "0", "1",
                 "0", "0", "7", "0", "0", "1", "--seeds", "30", "--voxel", "0.25", "-o", str(out), "-q"])
    assert code == 0
    import json

    rep = json.loads(out.with_suffix(".json").read_text())
    assert rep["patient_volume_mm3"] == pytest.approx(0.5 * cylinder().volume, rel=1e-4)
    # the box is the kept segment's: the cylinder's 10 x 10 section, 5 long
    assert rep["box_volume_mm3"] == pytest.approx(10 * 10 * 5, rel=1e-3)
    assert rep["seeds"] == 30 and 0 < rep["cells_in_scaffold"] <= 30
    assert "load" in rep["timings_s"] and rep["watertight"]


def _inside_mesh(points, triangles):
    """Inside a closed mesh by parity of crossings of a slightly tilted ray (Moller-Trumbore)."""
    d = np.array([1.0, 0.0123, 0.0071])
    d /= np.linalg.norm(d)
    a, b, c = (triangles[:, k] for k in range(3))
    e1, e2 = b - a, c - a
    pv = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, pv)
    count = np.zeros(len(points), int)
    for i, p in enumerate(points):
        tv = p - a
        u = np.einsum("ij,ij->i", tv, pv) / det
        qv = np.cross(tv, e1)
        v = (qv @ d) / det
        t = np.einsum("ij,ij->i", e2, qv) / det
        count[i] = np.count_nonzero((u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0))
    return count % 2 == 1


@pytest.mark.data
@pytest.mark.slow
def test_femur_shaft_segment_scaffold(data_dir, tmp_path):
    from implicit_scaffold import generate
    from implicit_scaffold.fields.patient_mesh import triangle_distance_reference

    femur = data_dir / "jigsaw_femur.stl"
    # mid-shaft (the femur runs 8..474 mm along z; its shaft is ~27 mm across near z = 220)
    patient = load_patient(femur, clip=(-40, -30, 216, 30, 30, 224))
    bone = trimesh.load(femur)
    assert patient.hi[2] - patient.lo[2] == pytest.approx(8)
    assert 20 < patient.hi[0] - patient.lo[0] < 35 and 20 < patient.hi[1] - patient.lo[1] < 35
    r = generate(patient=patient, pore_size=1.2, porosity=0.7, voxel=0.12, seeds_in="patient",
                 output=tmp_path / "femur.stl")
    rep = r.report
    assert rep["watertight"] and rep["bodies"] == 1
    # what is printed meets the target: the mesh's own (trimesh) volume in the segment's
    assert abs(1.0 - r.mesh.volume / rep["patient_volume_mm3"] - 0.7) < 0.003
    # inside the bone: every vertex within one voxel of the kept segment
    v = np.asarray(r.mesh.vertices)
    h = r.grid.spacing
    assert v[:, 2].min() >= 216 - h and v[:, 2].max() <= 224 + h
    sample = v[np.random.default_rng(0).choice(len(v), 1500, replace=False)]
    near = triangle_distance_reference(sample, bone.triangles) <= h
    far = sample[~near]
    assert _inside_mesh(far, np.asarray(bone.triangles)).all()
    # the patient's volume is the bone's cross-section times 8 mm: check against the mesh's own section
    section = bone.section(plane_origin=[0, 0, 220], plane_normal=[0, 0, 1])
    loops = [np.asarray(p) for p in section.discrete]
    area = sum(abs(0.5 * np.sum(p[:-1, 0] * p[1:, 1] - p[1:, 0] * p[:-1, 1])) for p in loops)
    assert patient.volume == pytest.approx(area * 8, rel=0.02)
    assert math.isfinite(rep["patient_volume_mm3"])


def test_an_open_mesh_is_taken_with_a_warning_and_a_closed_one_without():
    # an open surface gets its sign from a vote and its volume integrated: said, not silent
    import tempfile
    from pathlib import Path

    ball = trimesh.creation.icosphere(subdivisions=3, radius=5.0)
    with tempfile.TemporaryDirectory() as folder:
        closed, holed = Path(folder) / "closed.stl", Path(folder) / "holed.stl"
        ball.export(closed)
        trimesh.Trimesh(ball.vertices, ball.faces[5:], process=False).export(holed)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            assert load_patient(closed).volume == pytest.approx(ball.volume, rel=1e-6)  # STL: float32
        with pytest.warns(ScaffoldWarning, match="holed.stl is not a closed surface"):
            patient = load_patient(holed)
        assert patient.volume == pytest.approx(4 / 3 * math.pi * 5.0 ** 3, rel=0.05)
