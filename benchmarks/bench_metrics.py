"""Issue 4 benchmark: all voxel morphometry of the B1 scaffold (250³) beside PoreSpy's local thickness.

    python benchmarks/bench_metrics.py [--runs 3]

B1 is ``implicit_scaffold.generate(seeds=500, porosity=0.8, voxel=0.04)``: a 252³ grid. It is
built once (not timed); then each run, in a fresh process, times on its solid and patient:

- ours, all metrics: local thickness of the solid and of the void, Euler connectivity,
  interconnected porosity, fragments (``morphometry(..., surface=False)``: the area comes
  from the pipeline's mesh, which is timed with the mesh stage); the numba kernels are
  loaded before the clock starts;
- ours, local thickness alone (solid + void);
- PoreSpy's ``porespy.filters.local_thickness`` (its defaults) on the same solid and void.

Figures are medians of --runs runs; the target is all metrics within 10 s on 2 cores.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import median_runs, run_isolated, table  # noqa: E402

BUILD = """
import numpy as np
import implicit_scaffold
r = implicit_scaffold.generate(seeds=500, porosity=0.8, voxel=0.04, mesh=False, morphometry=False)
np.save({solid!r}, r.field < 0)
np.save({inside!r}, r.patient_sdf < 0)
_out = {{'grid': 'x'.join(map(str, r.grid.shape)), 'voxel': r.grid.spacing}}
"""

OURS = """
import time
import numpy as np
from implicit_scaffold.measure import morphometry as M
solid = np.load({solid!r}); inside = np.load({inside!r})
M.local_thickness(solid[:8, :8, :8], 0.04)  # load the compiled kernels outside the clock
c0 = time.process_time(); t0 = time.perf_counter()
rep = M.morphometry(solid, 0.04, region=inside, surface=False)
total = time.perf_counter() - t0; total_cpu = time.process_time() - c0
c1 = time.process_time(); t1 = time.perf_counter()
M.local_thickness(solid, 0.04)
M.local_thickness(inside & ~solid, 0.04)
lt = time.perf_counter() - t1; lt_cpu = time.process_time() - c1
_out = {{'all_s': total, 'local_thickness_s': lt, 'all_cpu_s': total_cpu, 'local_thickness_cpu_s': lt_cpu, 'strut_mean_mm': rep['strut_thickness_mm']['mean'],
         'pore_mean_mm': rep['pore_diameter_mm']['mean'], 'conn_d': rep['connectivity_density_per_mm3'],
         'interconnected': rep['interconnected_porosity']}}
"""

PORESPY = """
import time
import numpy as np
import porespy as ps
solid = np.load({solid!r}); inside = np.load({inside!r})
void = inside & ~solid
c0 = time.process_time(); t0 = time.perf_counter()
a = ps.filters.local_thickness(solid)
ts = time.perf_counter() - t0
t1 = time.perf_counter()
b = ps.filters.local_thickness(void)
tv = time.perf_counter() - t1; cpu = time.process_time() - c0
# PoreSpy's map holds sphere radii in voxels: twice that, in mm, to set beside ours
_out = {{'solid_s': ts, 'void_s': tv, 'both_s': ts + tv, 'both_cpu_s': cpu,
         'strut_mean_mm': float(2 * a[solid].mean() * 0.04), 'pore_mean_mm': float(2 * b[void].mean() * 0.04)}}
"""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--skip-porespy", action="store_true")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as d:
        paths = {"solid": str(Path(d) / "solid.npy"), "inside": str(Path(d) / "inside.npy")}
        built = run_isolated(BUILD.format(**paths))
        print(f"B1 volume: {built['grid']} voxels of {built['voxel']:g} mm")
        ours, _ = median_runs(OURS.format(**paths), args.runs, warmup=0)
        rows = [["ours: all metrics", f"{ours['all_s']:.2f}", f"{ours['all_cpu_s']:.2f}",
                 f"{ours['peak_rss_mb']:.0f}"],
                ["ours: local thickness (solid + void)", f"{ours['local_thickness_s']:.2f}",
                 f"{ours['local_thickness_cpu_s']:.2f}", ""]]
        if not args.skip_porespy:
            peer, _ = median_runs(PORESPY.format(**paths), args.runs, warmup=0)
            rows += [["PoreSpy local_thickness (solid)", f"{peer['solid_s']:.2f}", "", ""],
                     ["PoreSpy local_thickness (void)", f"{peer['void_s']:.2f}", "", ""],
                     ["PoreSpy local_thickness (solid + void)", f"{peer['both_s']:.2f}",
                      f"{peer['both_cpu_s']:.2f}", f"{peer['peak_rss_mb']:.0f}"]]
        # CPU time (all threads) is steadier than wall time on a shared machine
        print(table(rows, ["workload (median of %d)" % args.runs, "wall (s)", "CPU (s)", "peak RSS (MB)"]))
        print(f"ours: strut thickness mean {ours['strut_mean_mm']:.4f} mm, pore diameter mean "
              f"{ours['pore_mean_mm']:.4f} mm, Conn.D {ours['conn_d']:.3f} /mm3, "
              f"interconnected {ours['interconnected']:.5f}")
        if not args.skip_porespy:
            print(f"PoreSpy: strut thickness mean {peer['strut_mean_mm']:.4f} mm, pore diameter mean "
                  f"{peer['pore_mean_mm']:.4f} mm")
            print(f"ratio PoreSpy local thickness / ours local thickness: "
                  f"{peer['both_s'] / ours['local_thickness_s']:.2f}x; "
                  f"PoreSpy local thickness / ours all metrics: {peer['both_s'] / ours['all_s']:.2f}x")
        verdict = "within" if ours["all_s"] <= 10.0 else "OVER"
        print(f"target: all metrics of B1 within 10 s: {verdict} ({ours['all_s']:.2f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
