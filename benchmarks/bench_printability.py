"""Issue 15 benchmark: the print certificate's time on a 400^3 scaffold, and which printer profiles
the default cube and the femoral shaft pass, and why.

    python benchmarks/bench_printability.py [--runs 3] [--only speed,profiles]

Each figure is the median of --runs runs after a warm-up, each in a fresh process. 2-core machines
are noisy: read the medians. The femoral shaft needs ../shared/data (skipped with a note otherwise).
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import DATA, median_runs, run_isolated, table  # noqa: E402

SPEED = """
import time
import implicit_scaffold
from implicit_scaffold.printability import certificate, printer_profile
# the default cube's lattice on a 400^3 grid (10 mm at 0.025 mm)
r = implicit_scaffold.generate(voxel=0.025, mesh=False, morphometry=False)
solid = r.field < 0
t0 = time.perf_counter()
c = certificate(solid, r.grid.spacing, printer_profile('dlp-resin'), field=r.field,
                region=r.patient_sdf < 0, origin=r.grid.origin)
t = time.perf_counter() - t0
_out = {'seconds': t, 'grid': 'x'.join(map(str, r.grid.shape)), **{'part_' + k: v for k, v in c['seconds'].items()}}
"""

PROFILES = """
import implicit_scaffold
from implicit_scaffold.printability import certificate, printer_profile, profiles
{build}
solid = r.field < 0
_out = {{'grid': 'x'.join(map(str, r.grid.shape)), 'voxel': r.grid.spacing, 'porosity': r.report['porosity_voxel']}}
for name in profiles():
    c = certificate(solid, r.grid.spacing, printer_profile(name), field=r.field, region=r.patient_sdf < 0,
                    origin=r.grid.origin)
    _out[name] = {{k: c[k] for k in ('thinnest_mm', 'below_min_strut_share', 'throat_mm',
                                     'void_reached_by_drain_share', 'void_reached_by_100um_share',
                                     'sealed_voids', 'floating_solid', 'overhang_share', 'best_build_axis',
                                     'verdict')}}
"""

CUBE = "r = implicit_scaffold.generate(mesh=False, morphometry=False)"
SHAFT = """from implicit_scaffold.patient_io import load_patient
patient = load_patient({femur!r}, cut_planes=(0, 0, 210, 0, 0, 1, 0, 0, 230, 0, 0, 1))
r = implicit_scaffold.generate(patient=patient, pore_size=0.6, porosity=0.7, voxel=0.1, mesh=False, morphometry=False)"""


def speed(runs):
    med, _ = median_runs(SPEED, runs)
    print(f"\nCertificate of the default cube's lattice on a {med['grid']} grid (dlp-resin), median of {runs} runs "
          "after a warm-up")
    rows = [[k[5:], f"{v:.2f}"] for k, v in med.items() if k.startswith("part_")]
    rows.append(["total", f"{med['seconds']:.2f}"])
    print(table(rows, ["part", "seconds"]))
    print(f"peak RSS {med['peak_rss_mb']:.0f} MB (the run's generate included); target <= 10 s: "
          f"{'met' if med['seconds'] <= 10 else 'NOT met'}")


def _share(x):
    return "n/a" if x is None else f"{100 * x:.1f} %"


def profiles(runs):
    cases = [("default cube (10 mm, P 0.8, Dp 0.6 mm)", CUBE)]
    femur = DATA / "jigsaw_femur.stl"
    if femur.is_file():
        cases.append(("femoral shaft (20 mm, P 0.7, Dp 0.6 mm, voxel 0.1 mm)", SHAFT.format(femur=str(femur))))
    else:
        print(f"\n(the femoral shaft needs {femur}; not present here)")
    for label, build in cases:
        out = run_isolated(PROFILES.format(build=build))
        print(f"\n{label}: grid {out['grid']}, voxel {out['voxel']:.4g} mm, porosity {out['porosity']:.4f}")
        rows = []
        for name in [k for k in out if isinstance(out[k], dict) and "verdict" in out[k]]:
            c = out[name]
            v = c["verdict"]
            fails = [k for k, x in v.items() if k != "overall" and x != "pass"]
            rows.append([name, v["overall"], f"{c['thinnest_mm']['p1']:.3f}", _share(c["below_min_strut_share"]),
                         f"{c['throat_mm']:.3f}", _share(c["void_reached_by_drain_share"]),
                         _share(c["void_reached_by_100um_share"]), c["sealed_voids"]["count"],
                         c["floating_solid"]["count"], _share(c["overhang_share"]), c["best_build_axis"],
                         ", ".join(f"{k} {v[k]}" for k in fails) or "-"])
        print(table(rows, ["printer", "verdict", "thinnest p1 mm", "solid below min", "throat mm", "drain reach",
                           "100 um reach", "sealed voids", "floating", "overhang", "best axis", "why not pass"]))


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--only", default="speed,profiles")
    args = ap.parse_args()
    print(f"load average at start (1, 5, 15 min): {' '.join(f'{x:.2f}' for x in os.getloadavg())} "
          f"on {os.cpu_count()} CPUs")
    for name in args.only.split(","):
        {"speed": speed, "profiles": profiles}[name.strip()](args.runs)


if __name__ == "__main__":
    main()
