"""Issue 16 benchmark: inverse design, targets in and parameters out.

    PYTHONPATH=. python benchmarks/bench_design.py [--seeds 5] [--quick]

Runs a few designs through :func:`implicit_scaffold.design.design` (without and with a stiffness
target, one infeasible on purpose) and prints, for each: the wall time, the forward builds of the
search (the issue allows 10 of a 128³ cube), the representative cube's grid, the parameters found,
and every target beside its achieved mean and range over the seeds. The issue's budgets: 2 min
without --stiffness, 5 min with it, on 2 cores. Timings on a shared 2-core machine are noisy.
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
    Targets(porosity=0.7, pore_size=0.5, min_strut=0.25, stiffness=8.0, material="ti64"),  # strut-limited
    Targets(porosity=0.7, pore_size=0.5, min_strut=0.2, stiffness=3.0, material="ti64"),  # infeasible on purpose
]


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--quick", action="store_true", help="the first case only")
    args = ap.parse_args(argv)
    for t in CASES[:1] if args.quick else CASES:
        t0 = time.perf_counter()
        d = design(t, seeds=args.seeds)
        dt = time.perf_counter() - t0
        rve = d.representative_volume
        n = round(rve["size"] / rve["voxel"])
        asked = ", ".join(f"{k} {v:g}" for k, v in d.targets.items() if k != "material")
        print(f"targets: {asked}" + (f" ({t.material})" if t.stiffness else ""))
        p = d.parameters
        print(f"  {'feasible' if d.feasible else 'INFEASIBLE'}; {dt:.1f} s; {rve['builds']} forward builds of a "
              f"{n}^3 cube ({rve['size']:.3g} mm, voxel {rve['voxel']:.3g} mm) + {len(rve['seeds'])} seed checks; "
              f"style {p['style']}, Sf {p['sf']:g}, Sv {p['sv']:g}")
        for k, a in d.achieved.items():
            print(f"    {k:10s} target {d.targets[k]:<6g} achieved mean {a['mean']:.4g}, "
                  f"range {a['min']:.4g}..{a['max']:.4g}")
        if not d.feasible:
            print("  " + conflict_message(d))


if __name__ == "__main__":
    main()
