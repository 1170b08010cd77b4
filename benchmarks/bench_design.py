"""Issue 16 benchmark: inverse design, targets in and parameters out.

    PYTHONPATH=. python benchmarks/bench_design.py [--seeds 5] [--quick] [--ct] [--no-maps]
    PYTHONPATH=. python benchmarks/bench_design.py --accuracy 20 [--seeds 5] [--stiffness-sets K]

Runs a few designs through :func:`implicit_scaffold.design.design` (without and with a stiffness
target, one infeasible on purpose) and prints, for each: the wall time, the forward builds of the
search (the issue allows 10 of a 128³ cube), the representative cube's grid, the parameters found
(with the verification's modulus cube), and every target beside its achieved mean and range over
the seeds. The issue's budgets: 2 min without --stiffness, 5 min with it, on 2 cores. Timings on a shared 2-core machine are noisy.

``--no-maps`` starts the searches without the shipped design maps (the builds they save). ``--ct``
runs the design graded from a CT instead (``design --stiffness-from-ct``): a synthetic CT of two
densities (0.5 and 0.9 g/cm3 by the calibration 0.001 HU), the pooled law of Morgan et al. 2003,
Ti-6Al-4V; it prints the fitted modulus-porosity law, the porosity per target bin, and each half's
core modulus measured by voxel FE (every voxel, CG to 1e-5) beside Morgan's modulus of its density.

``--accuracy 20`` runs the issue's accuracy study: 20 target sets drawn with a fixed rng inside the
feasible range (porosity 0.6-0.85, pore size 0.3-0.8 mm, the minimum strut 0.3-0.8 of the thickest the
maps give there, the modulus within 3 % of the maps' at that porosity), each designed and checked over
``--seeds`` seeds; it prints one row per set and the share meeting all its targets within the issue's
tolerances, on every seed and on the means over the seeds (the thinnest strut of all seeds either way). ``--stiffness-sets K`` gives a modulus target to the first K only (the FE
solves are most of the time).
"""
from __future__ import annotations

import argparse
import time

from implicit_scaffold.design import Targets, conflict_message, design

CASES = [
    Targets(porosity=0.7, pore_size=0.5, min_strut=0.3),
    Targets(porosity=0.6, pore_size=0.4, min_strut=0.2),
    Targets(porosity=0.8, pore_size=0.6, min_strut=0.1),
    Targets(porosity=0.7, pore_size=0.5, min_strut=0.6),  # infeasible on purpose
    Targets(porosity=0.7, pore_size=0.5, min_strut=0.25, stiffness=9.5, material="ti64"),
    # strut-limited on the search's cube; on the modulus cube, with the porosity shift, within 10 % on the mean
    Targets(porosity=0.7, pore_size=0.5, min_strut=0.25, stiffness=8.0, material="ti64"),
    Targets(porosity=0.7, pore_size=0.5, min_strut=0.2, stiffness=3.0, material="ti64"),  # infeasible on purpose
]


def ct_case() -> None:
    """The CT-graded design on a synthetic two-density CT, checked by voxel FE on each half's core."""
    import tempfile
    from pathlib import Path

    import numpy as np
    import SimpleITK as sitk

    from implicit_scaffold.design import design_from_ct
    from implicit_scaffold.geometry.grade import load_ct
    from implicit_scaffold.measure.mechanics import compress, density_modulus, material
    from implicit_scaffold.io.patient_io import load_patient

    h, size, hu_values = 0.1, (6.0, 2.8, 2.8), (500, 900)
    n = [int(round(s / h)) for s in size]
    x = (np.arange(n[0]) + 0.5) * h
    hu = np.broadcast_to(np.where(x < size[0] / 2, *hu_values)[:, None, None], n).astype(np.int16)
    with tempfile.TemporaryDirectory() as tmp:
        path, out = Path(tmp) / "two.nrrd", Path(tmp) / "graded.npy"
        img = sitk.GetImageFromArray(np.ascontiguousarray(hu.T))
        img.SetSpacing((h, h, h))
        sitk.WriteImage(img, str(path))
        t0 = time.perf_counter()
        d = design_from_ct(load_ct(path), load_patient(path, threshold=0), calibration=(0.001, 0.0),
                           pore_size=0.5, output=str(out))
        dt = time.perf_counter() - t0
        rel = d.representative_volume["modulus_porosity"]
        print(f"CT design: {'feasible' if d.feasible else 'INFEASIBLE'}; {dt:.1f} s; "
              f"{d.representative_volume['builds']} forward builds; law E = {rel['solid_gpa']:g} * {rel['c']:.4g} "
              f"(1 - P)^{rel['n']:.4f} GPa over {rel['porosity_range'][0]:.4f}..{rel['porosity_range'][1]:.4f}, "
              f"largest miss at its builds {100 * d.representative_volume['fit_residual_max']:.1f} %")
        for row in d.achieved["porosity_by_target"]:
            print(f"  target porosity {row['porosity_target_mean']:.4f}: measured {row['porosity']:.4f} "
                  f"({row['voxels']} voxels)")
        f = np.load(out)
        grid_h = d.parameters["voxel"]
        import json
        o = np.asarray(json.loads(out.with_suffix(".json").read_text())["grid_origin_mm"]) + h / 2
        ax = [o[a] + np.arange(f.shape[a]) * grid_h for a in range(3)]
        ys, zs = ((ax[a] > 0.25) & (ax[a] < size[a] - 0.25) for a in (1, 2))
        law = density_modulus("pooled")
        for (lo, hi), v in zip(((0.25, 2.6), (3.3, 5.75)), hu_values):
            core = f[np.ix_((ax[0] > lo) & (ax[0] < hi), ys, zs)] < 0
            t1 = time.perf_counter()
            e = compress(core, grid_h, material("ti64"), axis=2, tol=1e-5, backend="opencl").apparent_modulus_gpa
            target = float(law.modulus_gpa(0.001 * v))
            print(f"  {v} HU half, core {core.shape}: porosity {1 - core.mean():.4f}, modulus {e:.4g} GPa against "
                  f"Morgan's {target:.4g} GPa ({100 * (e / target - 1):+.1f} %), FE {time.perf_counter() - t1:.1f} s")


#: the accuracy study's ranges (issue 16: target sets inside the feasible range, drawn with a fixed rng)
STUDY_SEED = 16
STUDY_POROSITY = (0.6, 0.85)
STUDY_PORE = (0.3, 0.8)
#: the minimum strut: this share of the thickest the maps give at the set's porosity and pore size
#: (the struts style at the lowest Sv searched)
STUDY_STRUT_SHARE = (0.3, 0.8)
#: the modulus: the maps' modulus of the struts style at the set's porosity times this (Sv hardly
#: moves it at a fixed porosity: a target far from it is infeasible, not a test of accuracy)
STUDY_STIFFNESS_SHARE = (0.97, 1.03)


def study_targets(count: int, stiffness_sets: int) -> list[Targets]:
    """`count` target sets drawn with a fixed rng; the first `stiffness_sets` carry a modulus too."""
    import numpy as np

    from implicit_scaffold.design import SV_RANGE
    from implicit_scaffold.design_maps import load_maps
    from implicit_scaffold.measure.mechanics import material

    rng = np.random.default_rng(STUDY_SEED)
    maps = load_maps()
    out = []
    for i in range(count):
        p = float(rng.uniform(*STUDY_POROSITY))
        d = float(rng.uniform(*STUDY_PORE))
        thickest = maps.value("min_strut_rel", "struts", 0.75, SV_RANGE[0], p) * d
        strut = float(rng.uniform(*STUDY_STRUT_SHARE)) * thickest
        e_share = float(rng.uniform(*STUDY_STIFFNESS_SHARE))
        e = None
        if i < stiffness_sets:
            e = e_share * maps.value("modulus_rel", "struts", 0.75, 0.5, p) * material("ti64").E_gpa
        out.append(Targets(porosity=round(p, 4), pore_size=round(d, 4), min_strut=round(strut, 4),
                           stiffness=None if e is None else round(e, 3), material="ti64"))
    return out


def seeds_meet(d, *, every: bool = True) -> dict:
    """Each target met (the issue's tolerances) by every seed's build, or (`every` False) by the mean
    over the seeds (the thinnest strut of all seeds either way)."""
    from implicit_scaffold.design import PORE_SIZE_RELATIVE, POROSITY_POINTS, STIFFNESS_RELATIVE

    t, a = d.targets, d.achieved

    def values(key):
        return a[key]["values"] if every else [a[key]["mean"]]

    met = {"porosity": all(abs(v - t["porosity"]) <= POROSITY_POINTS for v in values("porosity")),
           "pore_size": all(abs(v / t["pore_size"] - 1) <= PORE_SIZE_RELATIVE for v in values("pore_size")),
           "min_strut": a["min_strut"]["min"] >= t["min_strut"]}
    if "stiffness" in t:
        met["stiffness"] = all(abs(v / t["stiffness"] - 1) <= STIFFNESS_RELATIVE for v in values("stiffness"))
    return met


def modulus_cube(d) -> str:
    """The verification's modulus cube of a design, as text (empty without a modulus target)."""
    cube = d.representative_volume.get("modulus")
    if not cube:
        return ""
    cells = cube["size"] * d.parameters["sv"] / d.targets["pore_size"]
    return (f", modulus cube {cube['size']:.3g} mm ({cells:.1f} cells) solved at {cube['solve_voxel']:.3g} mm "
            f"({cube['size'] / cube['solve_voxel']:.0f} voxels a side)")


def accuracy_study(count: int, seeds: int, stiffness_sets: int) -> None:
    """The issue's study: `count` target sets, `seeds` seeds each; a table and the share meeting all."""
    rows, t_all = [], time.perf_counter()
    print(f"accuracy study: {count} target sets (rng {STUDY_SEED}), {seeds} seeds each, the first "
          f"{stiffness_sets} with a modulus (Ti-6Al-4V); a target is met on every seed, or on the means over them")
    print(f"{'#':>2s} {'P':>6s} {'pore':>6s} {'strut':>6s} {'E GPa':>6s} | {'builds':>6s} {'s':>6s} | "
          f"{'P mean (min..max)':24s} {'pore mean':>9s} {'strut min':>9s} {'E mean':>7s} {'E min..max':>13s} | "
          f"every seed | on the means | parameters")
    for i, t in enumerate(study_targets(count, stiffness_sets)):
        t0 = time.perf_counter()
        d = design(t, seeds=seeds)
        dt = time.perf_counter() - t0
        met, on_means = seeds_meet(d), seeds_meet(d, every=False)
        a = d.achieved
        rows.append((all(met.values()), all(on_means.values())))
        e = (f"{a['stiffness']['mean']:7.3f} {a['stiffness']['min']:6.3f}..{a['stiffness']['max']:<6.3f}"
             if "stiffness" in a else f"{'-':>7s} {'-':>13s}")
        missed = [k for k, v in met.items() if not v]
        missed_means = [k for k, v in on_means.items() if not v]
        print(f"{i:2d} {t.porosity:6.4f} {t.pore_size:6.4f} {t.min_strut:6.4f} "
              f"{t.stiffness if t.stiffness else '-':>6} | {d.representative_volume['builds']:6d} {dt:6.1f} | "
              f"{a['porosity']['mean']:.4f} ({a['porosity']['min']:.4f}..{a['porosity']['max']:.4f}) "
              f"{a['pore_size']['mean']:9.4f} {a['min_strut']['min']:9.4f} {e} | "
              f"{'all' if not missed else 'missed ' + ','.join(missed)} | "
              f"{'all' if not missed_means else 'missed ' + ','.join(missed_means)} | "
              f"Sv {d.parameters['sv']:g}, generator P {d.parameters['porosity']:.4f}{modulus_cube(d)}", flush=True)
    every = sum(r[0] for r in rows)
    means = sum(r[1] for r in rows)
    print(f"{every} of {len(rows)} target sets met all their targets on every seed ({100 * every / len(rows):.0f} %), "
          f"{means} of {len(rows)} on the means over the seeds (porosity, pore size and modulus means, the "
          f"thinnest strut of all seeds; {100 * means / len(rows):.0f} %); the issue asks 90 %; "
          f"{time.perf_counter() - t_all:.1f} s in all")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--quick", action="store_true", help="the first case only")
    ap.add_argument("--no-maps", action="store_true", help="start the searches without the design maps")
    ap.add_argument("--ct", action="store_true", help="the design graded from a synthetic CT instead")
    ap.add_argument("--accuracy", type=int, default=None, metavar="SETS",
                    help="the issue's accuracy study instead: SETS random target sets (20 in the issue), --seeds each")
    ap.add_argument("--stiffness-sets", type=int, default=None, metavar="K",
                    help="with --accuracy: the first K sets carry a modulus target (default: all)")
    args = ap.parse_args(argv)
    if args.ct:
        ct_case()
        return
    if args.accuracy is not None:
        k = args.accuracy if args.stiffness_sets is None else min(args.stiffness_sets, args.accuracy)
        accuracy_study(args.accuracy, args.seeds, k)
        return
    for t in CASES[:1] if args.quick else CASES:
        t0 = time.perf_counter()
        d = design(t, seeds=args.seeds, maps=not args.no_maps)
        dt = time.perf_counter() - t0
        rve = d.representative_volume
        n = round(rve["size"] / rve["voxel"])
        asked = ", ".join(f"{k} {v:g}" for k, v in d.targets.items() if k != "material")
        print(f"targets: {asked}" + (f" ({t.material})" if t.stiffness else ""))
        p = d.parameters
        print(f"  {'feasible' if d.feasible else 'INFEASIBLE'}; {dt:.1f} s; {rve['builds']} forward builds of a "
              f"{n}^3 cube ({rve['size']:.3g} mm, voxel {rve['voxel']:.3g} mm) + {len(rve['seeds'])} seed checks; "
              f"style {p['style']}, Sf {p['sf']:g}, Sv {p['sv']:g}, generator porosity {p['porosity']:g}"
              f"{modulus_cube(d)}")
        for k, a in d.achieved.items():
            print(f"    {k:10s} target {d.targets[k]:<6g} achieved mean {a['mean']:.4g}, "
                  f"range {a['min']:.4g}..{a['max']:.4g}")
        if not d.feasible:
            print("  " + conflict_message(d))


if __name__ == "__main__":
    main()
