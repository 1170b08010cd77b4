"""`--pore-size D` means the measured mean pore size (polyhedron-sphere), issue 17.

The oracle is independent of the package's cells: box-bounded Voronoi cells from SciPy
(the seeds mirrored across the six walls, which bounds every cell by the box exactly) and
their volumes by convex hulls; Poisson–Voronoi figures (mean cell volume = 1/density).
"""
from __future__ import annotations

import numpy as np
import pytest

import implicit_scaffold
from implicit_scaffold.geometry.seeds import PV_CUBE_ROOT_MEAN, seed_count


def _box_cell_volumes(seeds, lo, hi):
    """Volumes of the Voronoi cells of `seeds` within the box [lo, hi], by brute force."""
    from scipy.spatial import ConvexHull, Voronoi

    seeds = np.asarray(seeds, float)
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    mirrored = [seeds]
    for a in range(3):
        for wall in (lo[a], hi[a]):
            m = seeds.copy()
            m[:, a] = 2 * wall - m[:, a]
            mirrored.append(m)
    vor = Voronoi(np.concatenate(mirrored))
    vols = np.empty(len(seeds))
    for i in range(len(seeds)):
        region = vor.regions[vor.point_region[i]]
        vols[i] = ConvexHull(vor.vertices[region]).volume
    return vols


def test_poisson_voronoi_cube_root_mean_against_brute_force():
    # density 1 in a 16 mm cube: the cells fill the box (sum of volumes), mean volume 1/density
    # (the known figure), and the interior cells' mean cube root is the constant the rule uses
    rng = np.random.default_rng(11)
    side = 16.0
    n = rng.poisson(side ** 3)
    seeds = rng.uniform(0, side, (n, 3))
    vols = _box_cell_volumes(seeds, [0, 0, 0], [side] * 3)
    assert vols.sum() == pytest.approx(side ** 3, rel=1e-9)
    interior = np.all((seeds > 2.5) & (seeds < side - 2.5), axis=1)
    v = vols[interior]
    # ~1330 interior cells: the mean volume's standard error is ~0.42/sqrt(1330) = 1.2 %, 3 of them
    assert v.mean() == pytest.approx(1.0, abs=0.035)
    # sd of v^(1/3) is ~0.14: standard error 0.4 %, 3 of them
    assert np.mean(np.cbrt(v)) == pytest.approx(PV_CUBE_ROOT_MEAN, abs=0.012)


@pytest.mark.parametrize("sf, sv, porosity, shape", [
    (0.75, 0.75, 0.8, "box"), (0.5, 0.5, 0.5, "box"), (0.25, 0.25, None, "box"), (0.9, 0.4, 0.6, "box"),
    (0.75, 0.75, 0.7, "sphere")])
def test_pore_size_is_the_measured_mean_pore_size(sf, sv, porosity, shape):
    # the same number of cells (~300) at every Sv: the target pore size scales with Sv
    target = 0.8 * sv / 0.75
    r = implicit_scaffold.generate(shape=shape, size=6.0, pore_size=target, sf=sf, sv=sv, porosity=porosity,
                                   voxel=target / 5, mesh=False, morphometry=False)
    rep = r.report
    assert rep["seed_rule"] == "pore-size" and rep["pore_size_target_mm"] == target
    seeds = r.cells.seeds
    vols = _box_cell_volumes(seeds, r.cells.lo, r.cells.hi)
    # the cells in the scaffold: their seed inside the patient (the whole box, or the 6 mm ball)
    inside = np.ones(len(seeds), bool) if shape == "box" else np.linalg.norm(seeds - 3.0, axis=1) < 3.0
    oracle = np.mean(sv * np.cbrt(6 * vols[inside] / np.pi))
    assert oracle == pytest.approx(target, rel=0.05)
    assert rep["pore_size_mm"]["mean"] == pytest.approx(oracle, rel=0.01)


def test_paper_rule_is_the_papers_formula():
    r = implicit_scaffold.generate(size=6.0, pore_size=0.8, porosity=0.8, voxel=0.16, seed_rule="paper",
                                   mesh=False, morphometry=False)
    rep = r.report
    # n = V P / (pi Dp^3 / 6), by hand: 216 * 0.8 / (pi * 0.512 / 6) = 644.6
    assert rep["seeds"] == 645 == seed_count(216.0, 0.8, 0.8) and rep["seed_rule"] == "paper"
    # the paper's count makes pores well below Dp (the 0.47 mm for 0.6 mm)
    assert rep["pore_size_mm"]["mean"] < 0.9 * 0.8


def test_bad_seed_rule_is_one_line_exit_2(tmp_path, capsys):
    from implicit_scaffold.cli import main

    with pytest.raises(SystemExit) as exc:  # argparse's choices: the parser exits itself
        main(["generate", "-o", str(tmp_path / "s.stl"), "--seed-rule", "nope"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and err.count("\n") == 1 and "--seed-rule" in err
    with pytest.raises(implicit_scaffold.ScaffoldError, match="--seed-rule takes pore-size or paper"):
        implicit_scaffold.generate(seed_rule="nope", mesh=False)
