"""Inverse design (issue 16): targets in, parameters out, checked by rebuilding and measuring here.

The oracles do not use design.py's measures: each test rebuilds the scaffold with ``generate`` and
the written parameters, counts the porosity from the field itself, and takes the 1st percentile of
:func:`implicit_scaffold.morphometry.local_thickness` (plus one voxel: to the voxel boundaries, as
the print certificate counts) over the solid farther than the written margin from the cube's faces,
the margin found from voxel coordinates rather than from the patient's field.

The stiffness search solves voxel FE and takes about a minute: its test runs only with
``IMPLICIT_SCAFFOLD_SLOW=1``.
"""
import json
import os

import numpy as np
import pytest

from implicit_scaffold.cli import main

TARGETS = {"porosity": 0.7, "pore_size": 0.5, "min_strut": 0.3}


@pytest.fixture(scope="module")
def feasible(tmp_path_factory):
    out = tmp_path_factory.mktemp("design") / "design.json"
    code = main(["design", "--porosity", "0.7", "--pore-size", "0.5", "--min-strut", "0.3", "--seeds", "2",
                 "-o", str(out), "-q"])
    return code, json.loads(out.read_text()), out


def _rebuild(d: dict, seed: int):
    """The written parameters built on the written cube, and the three targets measured here."""
    from implicit_scaffold import generate
    from implicit_scaffold.morphometry import local_thickness

    rve = d["representative_volume"]
    r = generate(size=rve["size"], mesh=False, morphometry=False, seed=seed, **d["parameters"])
    h = float(r.grid.spacing)
    solid = r.field < 0
    box = r.patient_sdf < 0
    porosity = 1.0 - np.count_nonzero(solid & box) / np.count_nonzero(box)
    # voxel centres farther than the margin from every face of the cube [0, size]^3
    idx = np.indices(solid.shape).reshape(3, -1).T
    centres = np.asarray(r.grid.origin) + idx * h
    core_pts = np.all((centres > rve["margin"]) & (centres < rve["size"] - rve["margin"]), axis=1)
    core = core_pts.reshape(solid.shape)
    thick = local_thickness(solid, h)
    p1 = float(np.percentile(thick[solid & core], 1)) + h
    return porosity, r.report["pore_size_mm"]["mean"], p1, r


def test_feasible_targets_are_met_measured_independently(feasible):
    code, d, _ = feasible
    assert code == 0 and d["feasible"] is True
    assert set(d) >= {"parameters", "targets", "achieved", "feasible"}
    for key in ("porosity", "pore_size", "min_strut"):
        a = d["achieved"][key]
        assert a["min"] <= a["mean"] <= a["max"] and len(a["values"]) == 2
    for seed in (0, 1):
        porosity, pore, p1, _ = _rebuild(d, seed)
        assert abs(porosity - TARGETS["porosity"]) <= 0.005  # the 0.5 points
        assert abs(pore / TARGETS["pore_size"] - 1) <= 0.05  # the 5 %
        assert p1 >= TARGETS["min_strut"]  # the issue: at or above the target


def test_generate_design_reproduces_the_parameters(feasible, tmp_path):
    _, d, path = feasible
    out = tmp_path / "s.npy"
    assert main(["generate", "--design", str(path), "--size", "2", "-o", str(out), "-q"]) == 0
    rep = json.loads((tmp_path / "s.json").read_text())
    p = d["parameters"]
    assert rep["style"] == p["style"] and rep["sf"] == p["sf"] and rep["sv"] == p["sv"]
    assert rep["porosity_target"] == p["porosity"] and rep["pore_size_target_mm"] == p["pore_size"]
    assert rep["voxel_mm"] == pytest.approx(p["voxel"])
    assert rep["box_volume_mm3"] == pytest.approx(8.0)  # --size given here applies
    # an option given on the command line wins over the design's
    assert main(["generate", "--design", str(path), "--size", "2", "--voxel", "0.08", "--sv", "0.6",
                 "-o", str(out), "-q"]) == 0
    rep = json.loads((tmp_path / "s.json").read_text())
    assert rep["voxel_mm"] == pytest.approx(0.08) and rep["sv"] == 0.6 and rep["style"] == p["style"]


def test_infeasible_strut_exit_3_names_the_conflict(tmp_path, capsys):
    out = tmp_path / "d.json"
    # 0.6 mm struts at 70 % porosity and 0.5 mm pores: thicker than the lowest Sv's struts
    code = main(["design", "--porosity", "0.7", "--pore-size", "0.5", "--min-strut", "0.6", "--seeds", "2",
                 "-o", str(out)])
    text = capsys.readouterr().out
    assert code == 3
    d = json.loads(out.read_text())
    assert d["feasible"] is False and "min_strut" in d["conflicts"] and "porosity" in d["conflicts"]
    trade = d["tradeoff"]["min_strut"]
    assert trade["thickest_reachable_mm"] < 0.6
    assert 0 < trade["porosity_for_target_estimate"] < 0.7  # less porous allows thicker struts
    assert "infeasible" in text and "min_strut" in text and "thickest minimum strut" in text
    assert d["representative_volume"]["builds"] <= 10


@pytest.mark.parametrize("args, message", [
    (["--porosity", "1.5", "--pore-size", "0.5"], "--porosity must lie in (0, 1)"),
    (["--porosity", "0.7", "--pore-size", "-1"], "--pore-size must lie in"),
    (["--porosity", "0.7", "--pore-size", "0.5", "--stiffness", "3kg"], "--stiffness takes a modulus"),
    (["--porosity", "0.7", "--pore-size", "0.5", "--stiffness", "3GPa", "--material", "wood"], "unknown material"),
    (["--porosity", "0.7", "--pore-size", "0.5", "--printer", "nope"], ""),
])
def test_bad_design_input_one_line_exit_2(tmp_path, capsys, args, message):
    out = tmp_path / "d.json"
    assert main(["design", *args, "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "error" in err and message in err
    assert not out.exists()


def test_bad_design_file_exit_2(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text('{"parameters": {"colour": "red"}}')
    assert main(["generate", "--design", str(bad), "-o", str(tmp_path / "s.npy")]) == 2
    assert "unknown parameters colour" in capsys.readouterr().err
    assert main(["generate", "--design", str(tmp_path / "missing.json"), "-o", str(tmp_path / "s.npy")]) == 2


@pytest.mark.skipif(not os.environ.get("IMPLICIT_SCAFFOLD_SLOW"), reason="voxel FE searches: set IMPLICIT_SCAFFOLD_SLOW=1")
def test_stiffness_target_met(tmp_path):
    from implicit_scaffold.mechanics import compress, crop, material

    out = tmp_path / "d.json"
    # 9.5 GPa: about what Ti-6Al-4V struts give at 70 % (9.3-9.9 GPa measured over Sv 0.48-0.75)
    code = main(["design", "--porosity", "0.7", "--pore-size", "0.5", "--min-strut", "0.25", "--stiffness",
                 "9.5GPa", "--seeds", "2", "-o", str(out), "-q"])
    d = json.loads(out.read_text())
    assert code == 0 and d["feasible"], d["achieved"]
    _, _, p1, r = _rebuild(d, 0)
    h = float(r.grid.spacing)
    # the documented measure (every other voxel), solved here to a tighter tolerance: within the 10 %
    e = compress(crop(r.field < 0)[::2, ::2, ::2], 2 * h, material("ti64"), axis=2, tol=1e-5).apparent_modulus_gpa
    assert abs(e / 9.5 - 1) <= 0.10 and p1 >= 0.25


@pytest.mark.skipif(not os.environ.get("IMPLICIT_SCAFFOLD_SLOW"), reason="voxel FE searches: set IMPLICIT_SCAFFOLD_SLOW=1")
def test_stiffness_out_of_reach_exit_3_and_porosity_tradeoff(tmp_path, capsys):
    out = tmp_path / "d.json"
    # 3 GPa of Ti-6Al-4V is a far more porous scaffold than 70 %
    code = main(["design", "--porosity", "0.7", "--pore-size", "0.5", "--min-strut", "0.2", "--stiffness",
                 "3GPa", "--seeds", "1", "-o", str(out)])
    d = json.loads(out.read_text())
    assert code == 3 and "stiffness" in d["conflicts"] and "porosity" in d["conflicts"]
    assert d["tradeoff"]["stiffness"]["porosity_for_target_estimate"] > 0.7
    assert "modulus reached" in capsys.readouterr().out


def test_secant_step_is_exact_on_a_power_law():
    from implicit_scaffold.design import _next_sv

    # t(Sv) = 0.1 Sv^-1.3: a secant on the logs lands on the goal in one step, wherever it starts
    def t(s):
        return 0.1 * s ** -1.3

    goal = 0.3
    s = _next_sv([(0.75, t(0.75)), (0.6, t(0.6))], goal, 0.3, 0.95)
    assert s == pytest.approx((goal / 0.1) ** (-1 / 1.3), rel=1e-9)
    # a step out of the bracket bisects it (geometric midpoint)
    assert _next_sv([(0.75, t(0.75)), (0.6, t(0.6))], 10.0, 0.3, 0.95) == pytest.approx((0.3 * 0.95) ** 0.5)


@pytest.mark.parametrize("text, gpa", [("3GPa", 3.0), ("3 GPa", 3.0), ("800MPa", 0.8), ("2.5", 2.5)])
def test_parse_stiffness(text, gpa):
    from implicit_scaffold.design import parse_stiffness

    assert parse_stiffness(text) == pytest.approx(gpa)
