"""Issue 6 benchmark: a graded scaffold in a 20 mm femoral shaft segment, against the uniform one.

    python benchmarks/bench_grade.py [--runs 1] [--warmup 0] [--voxel 0.05] [--grade "0:0.3,2:0.8"]

The femoral shaft of bench_patient.py (jigsaw_femur.stl between the osteotomy planes
z = 210 and 230 mm), porosity 0.7: graded with 0.3 mm pores at the surface and 0.8 mm
from 2 mm deep (--grade), against the uniform run of bench_patient.py (0.6 mm pores,
seeds in the bounding box). Depth is measured below the patient's whole surface, so the
two cut faces are cortex too. Prints the wall time and peak resident memory of every
stage of both runs (medians of --runs runs, each in a fresh process), the seed counts
(and what uniform 0.3 mm pores would need), and how well the graded run meets its
profiles: the largest porosity miss over the depth bins and the pore sizes at the surface
and in the core. Needs ../shared/data (see its README); at 0.05 mm about 14 GB of memory.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import DATA, FEMUR_SHAFT, median_runs, table  # noqa: E402


RUN = FEMUR_SHAFT + """
import numpy as np
from implicit_scaffold.geometry.seeds import seed_count
options = {options!r}
t0 = time.perf_counter()
r = implicit_scaffold.generate(patient=patient, porosity=0.7, voxel={voxel}, output=out, verbose=True, **options)
total = time.perf_counter() - t0 + patient.load_seconds
rep = r.report
_out = {{'total_s': total, 'stages': rep['timings_s'], 'peak_mb': peaks,
        'grid': 'x'.join(map(str, rep['grid_shape'])), 'mvoxels': r.grid.size / 1e6,
        'seeds': rep['seeds'], 'cells_in_scaffold': rep['cells_in_scaffold'],
        'seeds_uniform_03': seed_count(float(patient.volume), 0.7, 0.3),
        'porosity_voxel': rep['porosity_voxel'], 'porosity_mesh': rep['porosity_mesh'],
        'pore_size_mean': rep['pore_size_mm']['mean'], 'interconnected': rep.get('interconnected_porosity'),
        'triangles': rep['triangles'], 'bodies': rep['bodies'], 'watertight': rep['watertight'],
        'fragments_removed': rep['fragments_removed'] or 0}}
grade = rep.get('grade')
if grade:
    prof = grade['profiles']['depth']
    ok = [i for i, v in enumerate(prof['voxels']) if v >= 2000]
    miss = [abs(prof['porosity'][i] - prof['porosity_target'][i]) for i in ok]
    full = [i for i in ok if prof['cells'][i] >= 30]
    worst = ok[int(np.argmax(miss))]
    _out.update({{'porosity_bin_miss_max': max(miss), 'depth_bins': len(ok),
                 'worst_bin_mm': prof['edges_mm'][worst], 'worst_bin_porosity': prof['porosity'][worst],
                 'pore_surface': prof['pore_size_mm'][full[0]], 'pore_surface_expected':
                 prof['pore_size_expected_mm'][full[0]], 'pore_core': prof['pore_size_mm'][full[-1]],
                 'pore_core_expected': prof['pore_size_expected_mm'][full[-1]]}})
"""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=1)
    ap.add_argument("--warmup", type=int, default=0)
    ap.add_argument("--voxel", type=float, default=0.05)
    ap.add_argument("--grade", default="0:0.3,2:0.8")
    ap.add_argument("--relax", type=int, default=0)
    args = ap.parse_args(argv)
    femur = DATA / "jigsaw_femur.stl"
    if not femur.is_file():
        print(f"needs {femur} (the shared data folder); nothing measured", file=sys.stderr)
        return 1
    runs = {}
    for name, options in (("uniform", {"pore_size": 0.6}),
                          ("graded", {"grade": args.grade, "relax": args.relax})):
        code = RUN.format(femur=str(femur), voxel=args.voxel, options=options)
        runs[name], _ = median_runs(code, args.runs, warmup=args.warmup)
    u, g = runs["uniform"], runs["graded"]
    names = list(dict.fromkeys(list(g["stages"]) + list(u["stages"])))
    rows = []
    for name in names:
        cols = []
        for r in (u, g):
            t = r["stages"].get(name)
            m = r["peak_mb"].get(name)
            cols += ["—" if t is None else f"{t:.2f}", "—" if m is None else f"{m:.0f}"]
        rows.append([name] + cols)
    rows.append(["total", f"{u['total_s']:.2f}", f"{u['peak_rss_mb']:.0f}", f"{g['total_s']:.2f}",
                 f"{g['peak_rss_mb']:.0f}"])
    print(f"femoral shaft segment z 210..230 mm of jigsaw_femur.stl, porosity 0.7, voxel {args.voxel} mm, "
          f"grid {g['grid']} ({g['mvoxels']:.1f} Mvoxels); median of {args.runs}")
    print(f"uniform: 0.6 mm pores, seeds in the box; graded: --grade {args.grade}"
          + (f" --relax {args.relax}" if args.relax else ""))
    print(table(rows, ["stage", "uniform s", "uniform MiB", "graded s", "graded MiB"]))
    for name, r in (("uniform", u), ("graded", g)):
        print(f"{name}: seeds {r['seeds']:.0f}, cells in scaffold {r['cells_in_scaffold']:.0f}, porosity voxels "
              f"{r['porosity_voxel']:.4f}, mesh {r['porosity_mesh']:.4f}, mean pore size {r['pore_size_mean']:.3f} mm, "
              f"interconnected {r['interconnected']:.4f}, fragments removed {r['fragments_removed']:.0f}, "
              f"triangles {r['triangles']:.0f}, bodies {r['bodies']:.0f}, watertight {r['watertight']}")
    print(f"uniform 0.3 mm pores over the patient would need {g['seeds_uniform_03']:.0f} seeds")
    print(f"graded profiles: porosity within {100 * g['porosity_bin_miss_max']:.2f} points of 0.7 over "
          f"{g['depth_bins']:.0f} depth bins (worst {g['worst_bin_porosity']:.4f} at {g['worst_bin_mm']:.2f} mm "
          "deep); "
          f"polyhedron-sphere pore size {g['pore_surface']:.3f} mm at the "
          f"surface (expected {g['pore_surface_expected']:.3f}), {g['pore_core']:.3f} mm in the core "
          f"(expected {g['pore_core_expected']:.3f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
