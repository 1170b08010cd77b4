"""Repair for a printer (issue 15): thin struts thickened, narrow throats opened, porosity kept."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from implicit_scaffold.measure.printability import printer_profile
from implicit_scaffold.fields.repair import repair

H = 0.05  # mm


def _grid(n):
    ax = (np.arange(n) + 0.5) * H
    return np.meshgrid(ax, ax, ax, indexing="ij")


def _box(X, Y, Z, lo, hi):
    q = [np.abs(v - (a + b) / 2) - (b - a) / 2 for v, a, b in zip((X, Y, Z), lo, hi)]
    return np.sqrt(sum(np.maximum(v, 0) ** 2 for v in q)) + np.minimum(np.max(q, axis=0), 0)


def _noise(shape):
    # breaks the exact ties of analytic fields on a voxel grid (whole planes of equal values),
    # which no level can split; a lattice's field has none
    return np.random.default_rng(0).uniform(-1e-4, 1e-4, shape)


def test_a_thin_rod_is_thickened_to_the_minimum_and_the_porosity_kept():
    X, Y, Z = _grid(60)
    rod = np.sqrt((X - 1.0) ** 2 + (Y - 0.8) ** 2) - 0.1          # 0.2 mm across, along z
    wall = np.abs(Y - 2.013) - 0.4                                 # 0.8 mm: material to give back
    box = _box(X, Y, Z, [0.25] * 3, [2.75] * 3)
    field = (np.maximum(np.minimum(rod, wall), box) + _noise(X.shape)).astype(np.float32)
    patient = box.astype(np.float32)
    out, info = repair(field, patient, H, printer_profile("custom:min_strut=0.4,min_throat=0.5,drain=0"),
                       porosity=None)
    region = patient < 0
    before = 1 - np.count_nonzero((field < 0) & region) / np.count_nonzero(region)
    after = 1 - np.count_nonzero((out < 0) & region) / np.count_nonzero(region)
    assert after == pytest.approx(before, abs=1e-3) and info["holds"]["porosity"]
    # the rod's cross-section (a plane across it, away from the wall) against a disc's area
    section = out[:, : int(1.5 / H), 30] < 0
    diameter = 2 * np.sqrt(np.count_nonzero(section) * H * H / np.pi)
    assert diameter >= 0.4 - H
    assert info["holds"]["min_strut"] and info["grown_mm3"] > 0 and info["opened_mm3"] > 0
    # what the rod took, the wall gave: it is thinner, and still above the minimum
    assert 0.4 <= np.count_nonzero(out[30, int(1.5 / H):, 30] < 0) * H < 0.8


def test_a_hole_narrower_than_the_drain_is_opened_until_a_drain_sized_ball_passes():
    X, Y, Z = _grid(72)
    block = _box(X, Y, Z, [0.3] * 3, [3.3] * 3)
    cavity = _box(X, Y, Z, [1.3] * 3, [2.3] * 3)                                   # a pore inside the block
    hole = np.maximum(np.sqrt((X - 1.8) ** 2 + (Y - 1.8) ** 2) - 0.15, 2.2 - Z)   # its only way out: 0.3 mm
    groove = _box(X, Y, Z, [0.0, 0.0, 1.0], [0.9, 3.6, 3.6])                      # open void to give back from
    field = (np.max([block, -cavity, -hole, -groove], axis=0) + _noise(X.shape)).astype(np.float32)
    patient = (block + 1e-3).astype(np.float32)
    profile = printer_profile("custom:min_strut=0.3,min_throat=0.5,drain=0.5")
    out, info = repair(field, patient, H, profile, porosity=None)
    assert info["holds"] == {"min_strut": True, "drain": True, "porosity": True}
    assert info["undrained_pore_share"]["before"] > 0.1 and info["undrained_pore_share"]["after"] == 0
    # independent of the repair's own measure: in every plane along the hole, the void's 2-D
    # distance map holds a disc of the drain's diameter (to the voxels' boundaries)
    for k in range(int(2.35 / H), int(3.3 / H)):
        void = out[20:52, 20:52, k] >= 0
        radius = ndimage.distance_transform_edt(void).max() * H + H / 2
        assert radius >= 0.25 - 1e-9, (k, radius)
    region = patient < 0
    porosity = [1 - np.count_nonzero((f < 0) & region) / np.count_nonzero(region) for f in (field, out)]
    assert porosity[1] == pytest.approx(porosity[0], abs=1e-3)


def test_a_repair_that_would_do_harm_is_not_made_and_says_why():
    # a lattice of thin rods only: nothing thick to give material back at this porosity
    X, Y, Z = _grid(48)
    rods = np.min([np.sqrt((Y - c1) ** 2 + (Z - c2) ** 2) for c1 in (0.6, 1.2, 1.8) for c2 in (0.6, 1.2, 1.8)],
                  axis=0) - 0.08
    box = _box(X, Y, Z, [0.2] * 3, [2.2] * 3)
    field = (np.maximum(rods, box) + _noise(X.shape)).astype(np.float32)
    out, info = repair(field, box.astype(np.float32), H, printer_profile("custom:min_strut=0.4,min_throat=0.5,drain=0"),
                       porosity=None)
    assert np.array_equal(out, field) and info["rounds"] == 0
    assert not info["holds"]["min_strut"] and any("too thin" in w for w in info["why"])


def test_generate_repair_reports_what_changed_and_needs_a_printer(tmp_path):
    from implicit_scaffold.errors import ScaffoldError
    from implicit_scaffold.pipeline import generate

    with pytest.raises(ScaffoldError, match="add --printer"):
        generate(size=2, seeds=20, repair=True, mesh=False)
    kw = dict(size=4, pore_size=0.8, porosity=0.75, printer="custom:min_strut=0.18,min_throat=0.3,drain=0.4",
              mesh=False, morphometry=False)
    plain, r = generate(**kw), generate(repair=True, **kw)
    rep = r.report["repair"]
    assert set(rep) >= {"rounds", "porosity", "volume_moved_mm3", "grown_mm3", "opened_mm3", "holds", "why",
                        "thin_strut_share", "undrained_pore_share"}
    assert rep["rounds"] >= 1 and rep["undrained_pore_share"]["before"] > 0
    assert rep["undrained_pore_share"]["after"] < rep["undrained_pore_share"]["before"]
    assert rep["holds"]["porosity"] and not rep["why"]
    # the report's porosity is the repaired field's, and still the target's
    inside = r.patient_sdf < 0
    assert r.report["porosity_voxel"] == pytest.approx(1 - np.count_nonzero((r.field < 0) & inside)
                                                       / np.count_nonzero(inside))
    assert abs(r.report["porosity_voxel"] - 0.75) < 2e-3
    # the certificate, measured on its own after the repair, finds more of the void drained
    assert (r.report["print_check"]["void_reached_by_drain_share"]
            > plain.report["print_check"]["void_reached_by_drain_share"])


def _hole_case():
    """The field of the test of the hole narrower than the drain."""
    X, Y, Z = _grid(72)
    block = _box(X, Y, Z, [0.3] * 3, [3.3] * 3)
    cavity = _box(X, Y, Z, [1.3] * 3, [2.3] * 3)
    hole = np.maximum(np.sqrt((X - 1.8) ** 2 + (Y - 1.8) ** 2) - 0.15, 2.2 - Z)
    groove = _box(X, Y, Z, [0.0, 0.0, 1.0], [0.9, 3.6, 3.6])
    field = (np.max([block, -cavity, -hole, -groove], axis=0) + _noise(X.shape)).astype(np.float32)
    return field, (block + 1e-3).astype(np.float32), printer_profile("custom:min_strut=0.3,min_throat=0.5,drain=0.5")


def _rod_case():
    """The field of the test of the thin rod."""
    X, Y, Z = _grid(60)
    rod = np.sqrt((X - 1.0) ** 2 + (Y - 0.8) ** 2) - 0.1
    wall = np.abs(Y - 2.013) - 0.4
    box = _box(X, Y, Z, [0.25] * 3, [2.75] * 3)
    field = (np.maximum(np.minimum(rod, wall), box) + _noise(X.shape)).astype(np.float32)
    return field, box.astype(np.float32), printer_profile("custom:min_strut=0.4,min_throat=0.5,drain=0")


@pytest.mark.parametrize("case", [_hole_case, _rod_case])
@pytest.mark.parametrize("planes", [1, 12, 40])
def test_a_repair_in_slabs_is_the_whole_grids_bit_for_bit(case, planes):
    """repair_by_slabs against repair on the whole arrays: the same field (every bit) and the
    same info, whatever the slabs (one owned plane each, a few, and about two slabs)."""
    from implicit_scaffold.fields.repair import repair_by_slabs
    from implicit_scaffold.run.grid import Grid
    from implicit_scaffold.run.tiles import ArraySlabs

    field, patient, profile = case()
    out, info = repair(field, patient, H, profile, porosity=None)
    assert info["rounds"] >= 1  # the case repairs something
    n = field.shape[0]
    grid = Grid((0.0, 0.0, 0.0), H, field.shape)
    source = ArraySlabs(field.copy(), grid)
    slab_info = repair_by_slabs(source, ArraySlabs(patient, grid), H, profile, porosity=None,
                                max_voxels=planes * n * n)
    assert np.array_equal(source.field.view(np.uint32), out.view(np.uint32))
    assert slab_info == info


def test_a_run_in_slabs_repairs_as_the_whole_grid_does(tmp_path):
    """generate --repair in slabs (tiled=<voxels>): it writes the field of the run in memory,
    byte for byte, and the report's repair and clean-up figures are the same."""
    from implicit_scaffold.pipeline import generate

    kw = dict(size=4, pore_size=0.8, porosity=0.75, voxel=0.05, seed=2, mesh=False, morphometry=False,
              printer="custom:min_strut=0.18,min_throat=0.3,drain=0.4", repair=True)
    whole = generate(output=tmp_path / "whole.npy", tiled=False, **kw)
    assert whole.report["repair"]["rounds"] >= 1
    plane = whole.field.shape[1] * whole.field.shape[2]
    slabs = generate(output=tmp_path / "slabs.npy", tiled=20 * plane, **kw)
    assert slabs.report["tiled"]["slabs"] > 1
    assert (tmp_path / "slabs.npy").read_bytes() == (tmp_path / "whole.npy").read_bytes()
    assert slabs.report["repair"] == whole.report["repair"]
    for key in ("porosity_voxel", "bodies_voxels", "fragments_removed", "sealed_voids"):
        assert slabs.report[key] == whole.report[key], key


def test_repair_of_a_grid_past_the_budget_runs_in_slabs(tmp_path):
    """--repair no longer needs the whole grid: a budget too small for any run is refused at once,
    in one line naming the smallest that works in slabs; under that budget the run repairs its
    field in slabs, finishes and writes it."""
    import json
    import re

    from implicit_scaffold.errors import ScaffoldError
    from implicit_scaffold.pipeline import generate, report_path

    kw = dict(size=3, seeds=40, voxel=0.02, porosity=0.75, printer="custom:min_strut=0.1,min_throat=0.1,drain=0.2",
              mesh=False, morphometry=False, repair=True)
    with pytest.raises(ScaffoldError, match="even in slabs") as err:
        generate(output=tmp_path / "refused.npy", max_memory="100M", **kw)
    assert "\n" not in str(err.value) and not (tmp_path / "refused.npy").exists()
    named = re.search(r"pass --max-memory (\S+) or more", str(err.value)).group(1)
    # in slabs (tiled=True): a test worker that has run others holds enough that the margin of the budget named
    # can hold the whole grid (a CI run went whole), and the budget named is the smallest for slabs
    r = generate(output=tmp_path / "slabs.npy", max_memory=named, tiled=True, **kw)
    # a run on disk (as many slabs as the budget left beside what this process holds: in a fresh
    # process 3, in a test worker that has run others maybe 1), where --repair was refused before
    assert r.report["tiled"]["slabs"] >= 1
    written = json.loads(report_path(tmp_path / "slabs.npy").read_text())
    assert written["repair"]["printer"] == "custom" and written["repair"]["porosity"]["after"] is not None
    field = np.load(tmp_path / "slabs.npy")
    assert field.shape == tuple(written["grid_shape"])
