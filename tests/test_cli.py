"""The command line as a user meets it: summary, outputs, and one-line errors with exit code 2."""
import json
import os
import subprocess
import sys

import pytest

from implicit_scaffold.cli import main


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
    text = capsys.readouterr().out
    for word in ("seeds 30", "surface offset", "blend 0.0000 mm", "voxel 0.1000 mm", "grid", "porosity",
                 "time:"):
        assert word in text
    import numpy as np

    field = np.load(out)
    rep = json.loads((tmp_path / "f.json").read_text())
    assert field.dtype == np.float32 and list(field.shape) == rep["grid_shape"]
    assert rep["porosity_target"] is None and rep["surface_offset_mm"] == 0.0


BAD = [
    (["--sf", "1.2"], "--sf must lie strictly between 0 and 1"),
    (["--sv", "0"], "--sv must lie strictly between 0 and 1"),
    (["--seeds", "1"], "at least 2 seeds"),
    (["--size", "-3"], "--size must be one or three positive lengths"),
    (["--size", "0"], "--size must be one or three positive lengths"),
    (["--voxel", "0"], "--voxel must be a positive number"),
    (["--voxel", "-0.1"], "--voxel must be a positive number"),
    (["--voxel", "0.0004"], "GiB but only"),
    (["--porosity", "80"], "fraction, not a percentage"),
    (["--pore-size", "0"], "--pore-size must be a positive"),
    (["--style", "struts", "--porosity", "none"], "solves the strut radius"),
]


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
    assert main(["info"]) == 0
    out = capsys.readouterr().out
    assert "OpenCL device:" in out and "kernels:" in out


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
