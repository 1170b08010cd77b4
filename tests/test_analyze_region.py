"""`analyze` agrees with `generate` on the scaffold generate wrote (issue 17)."""
from __future__ import annotations

import json

import pytest

from implicit_scaffold.cli import main


@pytest.fixture(scope="module")
def cylinder_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("run") / "cyl.stl"
    assert main(["generate", "--shape", "cylinder", "--size", "5", "--pore-size", "1", "--porosity", "0.75",
                 "--voxel", "0.05", "-o", str(out), "-q"]) == 0
    return out, json.loads(out.with_suffix(".json").read_text())


def test_analyze_with_the_runs_report_matches_generate(cylinder_run, tmp_path, capsys):
    out, gen = cylinder_run
    code = main(["analyze", str(out), "--region", str(out.with_suffix(".json")), "-o", str(tmp_path / "a.json")])
    text = capsys.readouterr().out
    ana = json.loads((tmp_path / "a.json").read_text())
    assert code == 0 and "the patient of cyl.json" in text
    assert abs(ana["porosity_voxel"] - gen["porosity_voxel"]) < 0.005
    # the same mesh volume over the same patient volume (the STL holds float32 vertices: 1e-6 relative)
    assert abs(ana["porosity_mesh"] - gen["porosity_mesh"]) < 1e-6
    assert ana["bodies"] == gen["bodies"]


def test_analyze_with_the_patient_mesh_matches_generate(tmp_path):
    # the patient given as a file, and the scaffold analysed at a voxel of its own (not the run's grid)
    import trimesh

    patient = tmp_path / "ball.stl"
    trimesh.creation.icosphere(subdivisions=4, radius=2.5).apply_translation([3, 3, 3]).export(patient)
    out = tmp_path / "s.stl"
    assert main(["generate", "--patient", str(patient), "--pore-size", "1", "--porosity", "0.7", "--voxel", "0.05",
                 "-o", str(out), "-q"]) == 0
    gen = json.loads(out.with_suffix(".json").read_text())
    assert main(["analyze", str(out), "--region", str(patient), "--voxel", "0.04", "-o", str(tmp_path / "a.json"),
                 "-q"]) == 0
    ana = json.loads((tmp_path / "a.json").read_text())
    assert abs(ana["porosity_voxel"] - gen["porosity_mesh"]) < 0.005 and ana["bodies"] == gen["bodies"]
    # without --voxel, the run's grid from the report beside the mesh (it asked for --voxel): generate's own
    # voxels, so its voxel porosity and fragments exactly
    assert main(["analyze", str(out), "--region", str(patient), "-o", str(tmp_path / "b.json"), "-q"]) == 0
    own = json.loads((tmp_path / "b.json").read_text())
    assert own["voxel_mm"] == 0.05 and own["grid_shape"] == gen["grid_shape"]
    assert own["porosity_voxel"] == pytest.approx(gen["porosity_voxel"], abs=1e-9)
    assert own["fragments"] == gen["fragments"]


def test_analyze_without_a_region_says_what_it_was(cylinder_run, capsys):
    out, gen = cylinder_run
    assert main(["analyze", str(out), "--voxel", "0.05"]) == 0
    text = capsys.readouterr().out
    assert "region the mesh's bounding box (give --region for the patient)" in text


def test_region_of_a_report_without_a_patient_is_one_line_exit_2(cylinder_run, tmp_path, capsys):
    out, _ = cylinder_run
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"hello": 1}))
    assert main(["analyze", str(out), "--region", str(bad)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not a report written by generate" in err
