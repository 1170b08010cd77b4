"""The command line as a user meets it: summary, outputs, and one-line errors with exit code 2."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from implicit_scaffold.cli import main
from implicit_scaffold.errors import ScaffoldError


def test_generate_writes_mesh_and_report(tmp_path, capsys):
    out = tmp_path / "s.stl"
    code = main(["generate", "-o", str(out), "--seeds", "40", "--size", "4", "--voxel", "0.1", "-q"])
    assert code == 0 and out.stat().st_size > 84
    rep = json.loads((tmp_path / "s.json").read_text())
    assert rep["seeds"] == 40 and rep["watertight"] is True
    assert capsys.readouterr().out == ""


def test_summary_lines(tmp_path, capsys):
    out = tmp_path / "f.npy"
    assert main(["generate", "-o", str(out), "--seeds", "30", "--size", "3", "--voxel", "0.1",
                 "--porosity", "none", "--blend", "0"]) == 0
    captured = capsys.readouterr()
    text = captured.out
    for word in ("seeds 30 (drawn in the box)", "surface offset", "blend 0.0000 mm", "voxel 0.1000 mm", "grid",
                 "porosity", "time:", "cells (paper, means over the 30 cells in the scaffold): pore size",
                 "interconnection", "voxels (spheres): strut thickness", "Conn.D"):
        assert word in text
    # the progress line counts what the summary counts
    assert "30 seeds drawn in the box" in captured.err
    import numpy as np

    field = np.load(out)
    rep = json.loads((tmp_path / "f.json").read_text())
    assert field.dtype == np.float32 and list(field.shape) == rep["grid_shape"]
    assert rep["porosity_target"] is None and rep["surface_offset_mm"] == 0.0


@pytest.mark.parametrize("name", ["f.nii.gz", "F.NII.GZ", "f.nrrd"])
def test_a_volume_output_is_written_and_its_report_gives_its_size(tmp_path, name):
    # .nii.gz was written under a temporary name ending .gz, whose format no writer knew (exit 2 after the build);
    # the report's file size is the file's as it lies in place (SimpleITK reads the geometry back: the oracle)
    import SimpleITK as sitk

    out = tmp_path / name
    assert main(["generate", "-o", str(out), "--size", "1", "--voxel", "0.1", "--pore-size", "0.5", "-q"]) == 0
    rep = json.loads(next(tmp_path.glob("*.json")).read_text())
    assert rep["file_size_bytes"] == out.stat().st_size > 0
    image = sitk.ReadImage(str(out))
    assert list(image.GetSize()) == rep["grid_shape"] and image.GetSpacing()[0] == pytest.approx(0.1)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([name, Path(name).name.split(".")[0] + ".json"])


def test_a_zarr_output_of_a_whole_grid_run_is_written(tmp_path):
    # the whole-grid run wrote into a temporary file of the name where the zarr writer makes its folder, and the
    # writer refused it ("already exists", exit 2 after the whole build)
    zarr = pytest.importorskip("zarr")
    out = tmp_path / "f.zarr"
    assert main(["generate", "-o", str(out), "--size", "1", "--voxel", "0.1", "--pore-size", "0.5", "-q"]) == 0
    rep = json.loads((tmp_path / "f.json").read_text())
    assert list(zarr.open_group(str(out), mode="r")["sdf"].shape) == rep["grid_shape"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.json", "f.zarr"]


BAD = [
    (["--sf", "1.2"], "--sf must lie strictly between 0 and 1"),
    (["--sv", "0"], "--sv must lie strictly between 0 and 1"),
    (["--seeds", "1"], "at least 2 seeds"),
    (["--size", "-3"], "--size must be one or three positive lengths"),
    (["--size", "0"], "--size must be one or three positive lengths"),
    (["--voxel", "0"], "--voxel must be a positive number"),
    (["--voxel", "-0.1"], "--voxel must be a positive number"),
    (["--voxel", "0.0004"], "or use a larger --voxel"),
    (["--porosity", "80"], "fraction, not a percentage"),
    (["--porosity", "1"], "got 1 (all void); a fraction such as 0.8 is 80 %"),
    (["--pore-size", "0"], "--pore-size must be a positive"),
    (["--style", "struts", "--porosity", "none"], "solves the strut radius"),
    (["--repair"], "--repair repairs for a printer's limits; add --printer NAME"),
    # options a graded build replaces were dropped without a word (the same bytes as without them)
    (["--grade", "0:0.5,1:0.8", "--pore-size", "2"], "--grade sets the pore sizes by depth"),
    (["--calibration", "0.001", "0", "--porosity", "0.6"], "--calibration sets the porosity and the pore sizes"),
    (["--calibration", "0.001", "0", "--pore-size", "2", "--porosity", "0.7"], "drop --porosity and --pore-size"),
    # the mechanics options without --mechanics: a typo (--nu 0.7) was taken without a word
    (["--nu", "0.7"], "--nu sets --mechanics' solve; add --mechanics or drop it"),
    (["--material", "foo"], "--material sets --mechanics' solve"),
    (["--axis", "x"], "--axis sets --mechanics' solve"),
    (["--mechanics-tol", "1e-4"], "--mechanics-tol sets --mechanics' solve"),
]
# the output is the field: a simplified mesh nobody got was described in the report
BAD_FIELD = [(["--tolerance", "0.01"], "--tolerance simplifies a mesh output; s.npy is the field")]


@pytest.mark.parametrize("args, message", BAD)
def test_bad_input_one_line_exit_2_no_output(tmp_path, capsys, args, message):
    out = tmp_path / "s.stl"
    code = main(["generate", "-o", str(out), "--seeds", "20", "--size", "3"] + args
                if "--seeds" not in args and "--pore-size" not in args
                else ["generate", "-o", str(out), "--size", "3"] + args)
    err = capsys.readouterr().err
    assert code == 2
    assert message in err and err.count("\n") == 1 and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("args, message", BAD_FIELD)
def test_bad_input_for_a_field_output_one_line_exit_2_no_output(tmp_path, capsys, args, message):
    code = main(["generate", "-o", str(tmp_path / "s.npy"), "--seeds", "20", "--size", "3"] + args)
    err = capsys.readouterr().err
    assert code == 2 and message in err and err.count("\n") == 1 and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []


def test_a_porosity_a_skin_puts_out_of_reach_names_the_way_out(tmp_path, capsys):
    # a solid skin caps the porosity from above: the way out is a lower target (it said to raise it, and named --skin
    # for a smooth cut)
    code = main(["generate", "-o", str(tmp_path / "s.stl"), "--seeds", "20", "--size", "3", "--skin", "0.8",
                 "--porosity", "0.7", "-q"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "Traceback" not in err
    assert "cannot be reached with --skin: the solid it adds alone leaves less void; lower --porosity" in err
    assert list(tmp_path.iterdir()) == []


def test_unwritable_folder(tmp_path, capsys):
    code = main(["generate", "-o", str(tmp_path / "missing" / "s.stl"), "--seeds", "20", "--size", "3"])
    err = capsys.readouterr().err
    assert code == 2 and "missing" in err and err.count("\n") == 1
    assert list(tmp_path.iterdir()) == []


def test_unknown_extension(tmp_path, capsys):
    assert main(["generate", "-o", str(tmp_path / "s.xyz"), "--seeds", "20"]) == 2
    assert ".stl" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def _run(args, env_extra, cwd):
    env = dict(os.environ, **env_extra)
    return subprocess.run([sys.executable, "-m", "implicit_scaffold"] + args, capture_output=True, text=True,
                          env=env, cwd=cwd, timeout=300)


def test_no_opencl_device(tmp_path):
    # a device that does not exist stands for a machine with no OpenCL driver
    p = _run(["generate", "-o", "s.stl", "--seeds", "20", "--size", "3"],
             {"IMPLICIT_SCAFFOLD_DEVICE": "no-such-platform"}, tmp_path)
    assert p.returncode == 2
    assert "OpenCL" in p.stderr and "Traceback" not in p.stderr and p.stderr.count("\n") == 1
    assert list(tmp_path.iterdir()) == []


def test_argparse_errors_exit_2(capsys):
    assert_exit = pytest.raises(SystemExit)
    with assert_exit as e:
        main(["generate", "-o", "x.stl", "--shape", "cube"])
    assert e.value.code == 2
    assert "Traceback" not in capsys.readouterr().err


def test_info(capsys):
    from implicit_scaffold import opencl

    assert main(["info"]) == 0
    out = capsys.readouterr().out
    assert "OpenCL device:" in out and "kernels:" in out and "kernel build now:" in out
    # every device found, with its verdict, and which one was chosen
    for c in opencl.device_checks():
        line = next(ln for ln in out.splitlines() if c.label in ln and ln.startswith("  ["))
        assert ("kernels OK" in line) == c.ok
    assert f"chosen: {opencl.chosen().label}" in out


def test_generate_with_report(tmp_path):
    out, page = tmp_path / "s.stl", tmp_path / "r.html"
    assert main(["generate", "-o", str(out), "--seeds", "30", "--size", "3", "--voxel", "0.1", "-q",
                 "--report", str(page)]) == 0
    text = page.read_text()
    assert text.count("data:image/png;base64,") >= 4 and "porosity" in text


def test_report_needs_html_name(tmp_path, capsys):
    assert main(["generate", "-o", str(tmp_path / "s.stl"), "--seeds", "20", "--report",
                 str(tmp_path / "r.pdf")]) == 2
    assert "HTML" in capsys.readouterr().err and list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- analyze


def _box_with_hole_stl(folder, a=4.0, s=2.0, c=1.5):
    from test_morphometry import box_with_hole

    path = folder / "boxhole.stl"
    box_with_hole(a, s, c).export(path)
    return path


def test_analyze_box_with_hole_against_closed_form(tmp_path, capsys):
    a, s, c = 4.0, 2.0, 1.5
    stl = _box_with_hole_stl(tmp_path, a, s, c)
    out = tmp_path / "m.json"
    assert main(["analyze", str(stl), "--voxel", "0.1", "-o", str(out)]) == 0
    rep = json.loads(out.read_text())
    area = 2 * (a * a - s * s) + 4 * a * c + 4 * s * c
    volume = (a * a - s * s) * c
    assert rep["surface_area_mm2"] == pytest.approx(area, rel=1e-9)
    assert rep["bs_bv_per_mm"] == pytest.approx(area / volume, rel=1e-9)
    # the region is the bounding box: the hole is the void, open at both ends
    assert rep["porosity_voxel"] == pytest.approx(s * s / (a * a), abs=1e-9)
    assert rep["interconnected_porosity"] == 1.0 and rep["fragments"] == 0
    assert rep["euler_characteristic"] == 0  # one tunnel
    # the walls are w = (a - s) / 2 = 1 mm thick and 1.5 mm tall; the thickest sphere sits in a corner,
    # touching both outer faces and the hole's edge: diameter 2 w sqrt(2) / (1 + sqrt(2)), within a voxel
    w = (a - s) / 2
    assert abs(rep["strut_thickness_mm"]["max"] - 2 * w * 2 ** 0.5 / (1 + 2 ** 0.5)) <= 0.1 + 1e-9
    text = capsys.readouterr().out
    assert "BS/BV" in text and "connectivity density" in text and str(out) in text


def test_analyze_volume_nrrd_and_tiff(tmp_path, capsys):
    import numpy as np
    import SimpleITK as sitk

    from test_morphometry import torus

    vol = torus(30, 9, 4)
    img = sitk.GetImageFromArray(np.transpose(vol, (2, 1, 0)).astype(np.uint8) * 255)
    img.SetSpacing((0.05, 0.05, 0.05))
    sitk.WriteImage(img, str(tmp_path / "t.nrrd"))
    out = tmp_path / "t.json"
    assert main(["analyze", str(tmp_path / "t.nrrd"), "-o", str(out), "-q"]) == 0
    rep = json.loads(out.read_text())
    assert rep["euler_characteristic"] == 0 and rep["voxel_mm"] == pytest.approx(0.05)
    assert rep["connectivity_density_per_mm3"] == pytest.approx(1 / (vol.size * 0.05 ** 3))
    assert rep["porosity_voxel"] == pytest.approx(1 - vol.mean())
    # a TIFF stack states no spacing: refused without --spacing, measured with it
    sitk.WriteImage(sitk.GetImageFromArray(np.transpose(vol, (2, 1, 0)).astype(np.uint8)), str(tmp_path / "t.tif"))
    assert main(["analyze", str(tmp_path / "t.tif"), "-q"]) == 2
    err = capsys.readouterr().err
    assert "--spacing" in err and err.count("\n") == 1
    out2 = tmp_path / "t2.json"
    assert main(["analyze", str(tmp_path / "t.tif"), "--spacing", "0.05", "-o", str(out2), "-q"]) == 0
    rep2 = json.loads(out2.read_text())
    assert rep2["euler_characteristic"] == 0
    assert rep2["strut_thickness_mm"]["mean"] == pytest.approx(rep["strut_thickness_mm"]["mean"])


def test_analyze_with_report(tmp_path):
    stl = _box_with_hole_stl(tmp_path)
    page = tmp_path / "r.html"
    assert main(["analyze", str(stl), "--voxel", "0.1", "--report", str(page), "-q"]) == 0
    text = page.read_text()
    # picture, cut-away, section and the two sphere histograms
    assert text.count("data:image/png;base64,") == 5 and "BS/BV" in text


def _analyze_bad(tmp_path):
    import numpy as np
    import SimpleITK as sitk
    import trimesh

    stl = _box_with_hole_stl(tmp_path)
    open_mesh = trimesh.creation.box(extents=(1, 1, 1))
    open_mesh = trimesh.Trimesh(open_mesh.vertices, open_mesh.faces[2:])
    open_mesh.export(tmp_path / "open.stl")
    grey = np.arange(1000, dtype=np.uint8).reshape(10, 10, 10)
    img = sitk.GetImageFromArray(grey)
    img.SetSpacing((0.1, 0.1, 0.1))
    sitk.WriteImage(img, str(tmp_path / "grey.nrrd"))
    (tmp_path / "notes.txt").write_text("not a scaffold")
    return [
        ([str(tmp_path / "missing.stl"), "--voxel", "0.1"], "does not exist"),
        ([str(stl)], "--voxel"),
        ([str(stl), "--voxel", "0"], "--voxel must be a positive"),
        ([str(stl), "--voxel", "0.1", "--spacing", "0.1"], "--spacing applies to a volume"),
        ([str(tmp_path / "open.stl"), "--voxel", "0.1"], "not a closed surface"),
        ([str(tmp_path / "grey.nrrd")], "not a binary volume"),
        ([str(tmp_path / "notes.txt"), "--voxel", "0.1"], "cannot analyse notes.txt"),
        ([str(stl), "--voxel", "0.1", "-o", str(tmp_path / "m.csv")], ".json"),
        ([str(stl), "--voxel", "0.1", "-o", str(tmp_path / "nowhere" / "m.json")], "nowhere"),
        ([str(stl), "--voxel", "0.1", "--report", str(tmp_path / "r.pdf")], "HTML"),
        # the option that names the file, in the fix
        ([str(stl), "--voxel", "0.1", "--report", str(tmp_path / "nowhere" / "r.html")],
         "pick an existing folder with --report"),
        # refused by the run's budget (--max-memory's default) before anything is read or allocated
        ([str(stl), "--voxel", "0.0001"], "over --max-memory"),
    ]


def test_analyze_bad_inputs_one_line_exit_2(tmp_path, capsys):
    cases = _analyze_bad(tmp_path)
    before = sorted(p.name for p in tmp_path.iterdir())
    for args, message in cases:
        code = main(["analyze"] + args)
        err = capsys.readouterr().err
        assert code == 2, (args, err)
        assert message in err and err.count("\n") == 1 and "Traceback" not in err, (args, err)
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # nothing written


def test_analyze_bad_spacing_is_an_argparse_error(capsys):
    with pytest.raises(SystemExit) as e:
        main(["analyze", "x.nrrd", "--spacing", "1 2"])
    assert e.value.code == 2 and "--spacing" in capsys.readouterr().err


def test_fragments_flags(tmp_path):
    common = ["generate", "--seeds", "30", "--size", "3", "--voxel", "0.1", "-q"]
    assert main(common + ["-o", str(tmp_path / "k.npy"), "--keep-fragments"]) == 0
    assert main(common + ["-o", str(tmp_path / "r.npy"), "--remove-fragments"]) == 0
    kept = json.loads((tmp_path / "k.json").read_text())
    removed = json.loads((tmp_path / "r.json").read_text())
    assert kept["fragments_removed"] is None and isinstance(removed["fragments_removed"], int)
    # what was built: no fragment is left after removal; kept ones are all still there
    assert removed["fragments"] == 0 and kept["fragments"] == removed["fragments_removed"]
    with pytest.raises(SystemExit):
        main(common + ["-o", str(tmp_path / "x.npy"), "--keep-fragments", "--remove-fragments"])


def test_analyze_of_a_generated_mesh_finds_what_generate_measured(tmp_path):
    # the mesh's bounding box is the patient box and the voxels are the same size, so the
    # inside test on the voxel centres gives back the solid that was meshed
    out = tmp_path / "s.stl"
    assert main(["generate", "-o", str(out), "--seeds", "30", "--size", "3", "--voxel", "0.1", "-q"]) == 0
    built = json.loads((tmp_path / "s.json").read_text())
    assert main(["analyze", str(out), "--voxel", "0.1", "-o", str(tmp_path / "a.json"), "-q"]) == 0
    found = json.loads((tmp_path / "a.json").read_text())
    assert found["grid_shape"] == built["grid_shape"]
    assert found["porosity_voxel"] == pytest.approx(built["porosity_voxel"], abs=1e-12)
    assert found["euler_characteristic"] == built["euler_characteristic"]
    for key in ("strut_thickness_mm", "pore_diameter_mm"):
        assert found[key]["mean"] == pytest.approx(built[key]["mean"], rel=1e-9)
    assert found["bs_bv_per_mm"] == pytest.approx(built["bs_bv_per_mm"], rel=1e-6)


def test_slice_writes_a_stack_that_matches_the_field(tmp_path, capsys):
    import numpy as np
    from PIL import Image

    out = tmp_path / "layers"
    assert main(["slice", "-o", str(out), "--seeds", "30", "--size", "3", "--voxel", "0.1", "-q"]) == 0
    meta = json.loads((out / "stack.json").read_text())
    images = sorted(out.glob("layer_*.png"))
    assert len(images) == meta["layers"] and capsys.readouterr().out == ""
    # pixels = voxels, layers = voxel planes: the field's solid, plane by plane
    import implicit_scaffold

    r = implicit_scaffold.generate(seeds=30, size=3.0, voxel=0.1, mesh=False)
    for k in (5, meta["layers"] // 2):
        img = np.asarray(Image.open(images[k]))
        solid = (r.field[:, :, k] < 0).T[::-1]      # rows are y, top row the largest y
        assert np.mean((img >= 128) == solid) > 0.99


def test_slice_writes_the_runs_report_beside_the_stack(tmp_path, capsys):
    # slice --printer certified what it built and wrote the verdict nowhere (stack.json holds the layers' geometry);
    # the run's report lies beside the stack, as generate's beside its mesh, also when --require-printable fails
    out = tmp_path / "layers"
    code = main(["slice", "-o", str(out), "--size", "2", "--pore-size", "1", "--voxel", "0.1", "-q",
                 "--printer", "custom:min_strut=5,min_throat=5", "--require-printable"])
    assert code == 3
    rep = json.loads((tmp_path / "layers.json").read_text())
    assert rep["print_check"]["verdict"]["overall"] == "fail" and rep["slices"]["layers"] == len(
        list(out.glob("layer_*.png")))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["layers", "layers.json"]


@pytest.mark.parametrize("args, message", [
    (["--pixel", "0"], "--pixel must be a positive number"),
    (["--layer", "-2"], "--layer must be a positive number"),
    (["--layer", "500"], "--layer 500 mm is taller than the part (3 mm along z)"),
    (["--sf", "2"], "--sf must lie strictly between 0 and 1"),
])
def test_slice_bad_input(tmp_path, capsys, args, message):
    code = main(["slice", "-o", str(tmp_path / "s"), "--seeds", "20", "--size", "3"] + args)
    err = capsys.readouterr().err
    assert code == 2 and message in err and err.count("\n") == 1
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_sweep_quick_runs_the_quick_sweep_and_lists_its_files(tmp_path, capsys, monkeypatch):
    # what the quick sweep writes (every figure's CSV and PNG) is tests/test_sweep.py's; here the
    # command's wiring: the options it passes and the files it lists
    import implicit_scaffold.sweep as sweep

    calls = []

    def fake(out, *, quick, seed, progress):
        calls.append((str(out), quick, seed))
        if progress is not None:
            progress(1, 1)
        return {"files": ["a.csv", "a.png"], "figures": {"fig10": {"csv": "a.csv", "png": "a.png"}}}

    monkeypatch.setattr(sweep, "run_sweep", fake)
    assert main(["sweep", "-o", str(tmp_path / "sw"), "--quick", "--seed", "4"]) == 0
    assert calls == [(str(tmp_path / "sw"), True, 4)]
    out = capsys.readouterr().out
    assert "wrote 2 files" in out and "fig10: a.csv, a.png" in out


def test_too_many_seeds_refused_before_the_work(tmp_path, capsys):
    # a 200 mm cube at 0.6 mm pores asks for ~57 M seeds: refused at once, with a fix
    code = main(["generate", "-o", str(tmp_path / "s.stl"), "--size", "200"])
    err = capsys.readouterr().err
    assert code == 2 and "seeds need about" in err and "--pore-size" in err and err.count("\n") == 1
    assert list(tmp_path.iterdir()) == []


def test_warnings_are_one_line(tmp_path, capsys):
    # under-resolved struts: the run completes and says, in one line each, what missed and why
    code = main(["generate", "-o", str(tmp_path / "s.stl"), "--size", "6", "--pore-size", "2", "--voxel", "0.4",
                 "-q"])
    err = capsys.readouterr().err.splitlines()
    assert code == 0 and err and all(line.startswith("implicit-scaffold: warning: ") for line in err)
    rep = json.loads((tmp_path / "s.json").read_text())
    assert len(rep["warnings"]) == len(err)


@pytest.mark.slow
@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_interrupted_run_leaves_no_file(tmp_path, sig):
    # Ctrl-C or a kill while the run writes: exit 130, one line, no file at all (not even a temporary one)
    import signal

    p = subprocess.Popen([sys.executable, "-m", "implicit_scaffold", "generate", "-o", "s.stl", "--size", "6",
                          "--voxel", "0.03"], cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    seen = ""
    while "mesh ..." not in seen:           # the stage lines come on stderr as the run goes
        line = p.stderr.readline()
        assert line, seen
        seen += line
    p.send_signal(getattr(signal, sig))
    _, err = p.communicate(timeout=300)
    assert p.returncode == 130 and "interrupted; no output written" in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("stop", [KeyboardInterrupt, MemoryError])
def test_a_run_stopped_after_its_mesh_is_written_leaves_no_file(tmp_path, capsys, monkeypatch, stop):
    # the mesh is in place before the report is written: a kill then (or a failure) must not leave a
    # mesh without its report, where the run says no output was written
    import implicit_scaffold.io.files as files

    (tmp_path / "old.txt").write_text("a file of the user's")

    def fail(*args, **kwargs):
        # the mesh is finished, under its hidden temporary name until the run ends: a run killed outright
        # here (SIGKILL, the out-of-memory killer) leaves no mesh without its report
        assert not (tmp_path / "s.stl").exists()
        assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".s.stl.tmp-")]
        raise stop

    monkeypatch.setattr(files, "write_json", fail)
    code = main(["generate", "-o", str(tmp_path / "s.stl"), "--size", "3", "--voxel", "0.1", "-q"])
    err = capsys.readouterr().err
    last = "implicit-scaffold: interrupted; no output written" if stop is KeyboardInterrupt else \
        "implicit-scaffold: error: out of memory"
    assert code == (130 if stop is KeyboardInterrupt else 2) and "Traceback" not in err
    assert err.splitlines()[-1].startswith(last)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old.txt"]


def test_progress_and_summary_count_the_same_seeds(tmp_path, capsys):
    # seeds drawn where the patient is: the progress line and the summary give the seeds drawn
    # (patient and margin), and the summary the cells in the scaffold apart, with what each counts
    import re

    import trimesh

    patient = tmp_path / "ball.stl"
    trimesh.creation.icosphere(subdivisions=3, radius=2.0).export(patient)
    out = tmp_path / "s.npy"
    assert main(["generate", "--patient", str(patient), "--pore-size", "1", "--voxel", "0.1", "-o", str(out)]) == 0
    captured = capsys.readouterr()
    rep = json.loads((tmp_path / "s.json").read_text())
    drawn = re.findall(r"(\d+) seeds drawn in the patient and one cell's margin", captured.err)
    assert drawn and int(drawn[-1]) == rep["seeds"]
    assert f"seeds {rep['seeds']} (drawn in the patient and one cell's margin)" in captured.out
    assert f"{rep['cells_in_scaffold']} of the {rep['seeds']} cells in the scaffold" in captured.out


def test_the_summary_says_which_voxel_measures_were_not_made_and_why():
    # a slab run whose thickness halo did not fit measured the topology alone: the reason was in the
    # JSON only, and the summary's line silently lacked strut thickness and pore diameter
    from implicit_scaffold.cli import _metric_lines

    why = "strut thickness and pore diameter not measured: a slab with its halo of 40 planes needs 2.10 GiB, over what " \
          "--max-memory leaves; raise --max-memory"
    lines = _metric_lines({"connectivity_density_per_mm3": 0.049, "interconnected_porosity": 1.0, "morphometry": why})
    assert lines[-2] == "  voxels (spheres): Conn.D 0.049 /mm3, interconnected 1"
    assert lines[-1] == f"  voxels: {why}"
    assert not any(line.startswith("  voxels: ") for line in _metric_lines({"connectivity_density_per_mm3": 0.049}))


def test_a_budget_beyond_the_machines_memory_is_warned_about(tmp_path, capsys):
    import psutil

    huge = f"{psutil.virtual_memory().total * 2 // 2**30}G"
    assert main(["generate", "-o", str(tmp_path / "s.npy"), "--size", "2", "--voxel", "0.1", "--max-memory", huge,
                 "-q"]) == 0
    assert f"--max-memory {huge} is more than this machine's" in capsys.readouterr().err
    # half the machine: within it, whatever this process holds from the tests before (1G was not, in the suite)
    half = f"{psutil.virtual_memory().total // 2 // 2**30}G"
    assert main(["generate", "-o", str(tmp_path / "s.npy"), "--size", "2", "--voxel", "0.1", "--max-memory", half,
                 "-q"]) == 0
    assert "more than this machine's" not in capsys.readouterr().err


@pytest.mark.parametrize("command", [["check", "--printer", "dlp-resin"], ["analyze"]])
def test_an_output_onto_the_runs_report_beside_the_file_is_refused(tmp_path, capsys, command):
    # check c.stl -o c.json replaced generate's report, which the next check of c.stl read its grid from
    out = tmp_path / "c.stl"
    assert main(["generate", "-o", str(out), "--size", "1", "--voxel", "0.1", "--pore-size", "0.5", "-q"]) == 0
    before = (tmp_path / "c.json").read_bytes()
    capsys.readouterr()
    code = main([command[0], str(out), *command[1:], "-o", str(tmp_path / "c.json"), "-q"])
    err = capsys.readouterr().err
    assert code == 2 and "is the report generate wrote beside c.stl" in err and err.count("\n") == 1
    assert (tmp_path / "c.json").read_bytes() == before


def test_a_designs_own_parameters_are_not_refused_beside_its_calibration():
    # generate --design of a CT design (its calibration and its pore size, 1.0 mm) was refused: "drop --pore-size",
    # an option the user never typed; typed, it still is
    import argparse

    from implicit_scaffold.cli import _check_graded_options

    args = argparse.Namespace(porosity="0.8", pore_size=1.0, seed_rule="pore-size", calibration=(0.001, 0.0),
                              grade=None, from_design={"pore_size"})
    _check_graded_options(args)
    args.from_design = set()
    with pytest.raises(ScaffoldError, match="drop --pore-size"):
        _check_graded_options(args)


def test_calibration_of_a_label_map_is_refused(tmp_path, capsys):
    # --calibration read a segmentation's label numbers as Hounsfield units: label 31 became 31 HU, every pore 0.8 mm
    import numpy as np
    import SimpleITK as sitk

    labels = np.zeros((12, 12, 12), np.uint8)
    labels[3:9, 3:9, 3:9] = 31
    image = sitk.GetImageFromArray(labels)
    image.SetSpacing((0.5, 0.5, 0.5))
    sitk.WriteImage(image, str(tmp_path / "seg.nii.gz"))
    code = main(["generate", "--patient", str(tmp_path / "seg.nii.gz"), "--label", "31", "--calibration", "0.004",
                 "0", "-o", str(tmp_path / "s.stl"), "-q"])
    err = capsys.readouterr().err
    assert code == 2 and "--calibration reads a CT's intensities" in err and err.count("\n") == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["seg.nii.gz"]


@pytest.mark.parametrize("command", ["check", "analyze"])
def test_check_and_analyze_say_a_stage_that_runs_for_seconds(command, tmp_path, capsys, monkeypatch):
    # a femur's analysis at 0.3 mm ran 113 s in silence: a stage that has run 2 s says so on stderr; -q keeps quiet
    import time

    import numpy as np

    from implicit_scaffold.measure import morphometry, printability

    g = np.linspace(-1.0, 1.0, 24)
    field = (np.sqrt(g[:, None, None] ** 2 + g[None, :, None] ** 2 + g[None, None, :] ** 2) - 0.8).astype(np.float32)
    np.save(tmp_path / "ball.npy", field)
    slow = printability.certificate if command == "check" else morphometry.morphometry
    name = "certificate" if command == "check" else "morphometry"
    module = printability if command == "check" else morphometry
    monkeypatch.setattr(module, name, lambda *a, **k: time.sleep(2.6) or slow(*a, **k))
    argv = [command, str(tmp_path / "ball.npy"), "--voxel", "0.1", "-o", str(tmp_path / "r.json")]
    argv += ["--printer", "lpbf-ti64"] if command == "check" else []
    assert main(argv) == 0
    stage = "certifying" if command == "check" else "measuring"
    assert f"  {stage} (" in capsys.readouterr().err
    assert main(argv + ["-q"]) == 0
    assert capsys.readouterr().err == ""
