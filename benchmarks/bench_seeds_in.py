"""Issue 17 benchmark: seeds in the box (the paper) against seeds where the bone is (the default with a patient).

    python benchmarks/bench_seeds_in.py [--runs 1] [--voxel 0.1] [--pore-size 0.6] [--cases l3 ct]

A 20 mm clip of the mean L3 vertebra, clouthier_lumbar_L3_mean.stl (x -30..-10, y 20..40,
z -10..10 mm: a thin posterior part, about 1,100 mm3 of bone in its 8,000 mm3 box, as the
issue's iliac wing and talus clips), pore size 0.6 mm, porosity 0.7. Runs ``--seeds-in box`` and ``--seeds-in patient`` (the default), each
in a fresh process, and prints the cells built, the cells in the scaffold, the wall time and
the peak resident memory of each, and the porosity and pore size that came out. Needs
../shared/data (see its README). Timings on a shared machine are noisy.

``--cases ct`` (or ``l3 ct``) runs thin anatomy far apart in a large box: the abdominal CT slab
totalseg_example_ct_sm.nii.gz thresholded at 250 HU (ribs and vertebrae in 112 pieces, a 300 mm
box), pore size 0.8 mm, porosity 0.7, generate's seeds and cells stage alone: the seeding grid, the cell passes of the pore-size solve, the seeds drawn, those
inside the bone by its exact distance (the volume patient's own interpolated field), and the
mean pore size measured on the cells whose seed lies inside, against the 0.8 mm asked.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import DATA, STAGE_MEMORY, median_runs, table  # noqa: E402

CLIP = (-30.0, 20.0, -10.0, -10.0, 40.0, 10.0)

RUN = STAGE_MEMORY.replace("{", "{{").replace("}", "}}") + """
from implicit_scaffold.io.patient_io import load_patient
opencl.context()
t0 = time.perf_counter()
with measured('load'):
    patient = load_patient({bone!r}, clip={clip!r})
r = implicit_scaffold.generate(patient=patient, pore_size={pore}, porosity=0.7, voxel={voxel},
                               seeds_in={seeds_in!r}, output=os.path.join(tempfile.mkdtemp(), 'head.stl'))
rep = r.report
_out = {{'total_s': time.perf_counter() - t0, 'stages': rep['timings_s'],
        'patient_volume_mm3': rep['patient_volume_mm3'], 'box_volume_mm3': rep['box_volume_mm3'],
        'seeds': rep['seeds'], 'cells_in_scaffold': rep['cells_in_scaffold'],
        'porosity_voxel': rep['porosity_voxel'], 'porosity_printed': rep['porosity_printed'],
        'patient_pieces': rep['patient_pieces_count'], 'pore_size_mm': rep['pore_size_mm']['mean'],
        'triangles': rep['triangles'], 'bodies': rep['bodies'], 'cell_passes': len(rep['seed_solve'] or [1])}}
"""


CT = """
import time
from dataclasses import replace
import numpy as np
from implicit_scaffold import pipeline
from implicit_scaffold.measure.metrics import pore_sizes
from implicit_scaffold.io.patient_io import load_patient
from implicit_scaffold.progress import Progress
patient = load_patient({ct!r}, threshold=250)
# generate's stages up to the cells (the seeds' count, the seeding grid, the pore-size solve)
params = replace(pipeline.Params(), pore_size=0.8, porosity=0.7, seeds_in='patient')
prog = Progress(False)
t0 = time.perf_counter()
built = pipeline._seeds_and_cells(params, patient, pipeline._seed_count(params, patient), None, None, prog)
seconds = time.perf_counter() - t0
inside = patient.sdf(built.cells.seeds) < 0
n = built.tried[-1]['seeds_in_patient']
_, grid = pipeline._coarse_patient(patient, (patient.volume / pipeline._seed_count(params, patient)) ** (1 / 3))
_out = {{'grid': 'x'.join(map(str, grid.shape)), 'step': grid.spacing, 'passes': len(built.tried),
        'seeds': len(built.seeds), 'asked_inside': n, 'inside': int(inside.sum()),
        'pore_inside': float(pore_sizes(built.cells, 0.75)[inside].mean()), 'seconds': seconds,
        'solve': [round(t['pore_size_mm'], 4) for t in built.tried]}}
"""


def ct_case() -> None:
    """Thin anatomy far apart in a large box: the seeds inside and the pore size they give."""
    from _common import run_isolated

    ct = DATA / "totalseg_example_ct_sm.nii.gz"
    r = run_isolated(CT.format(ct=str(ct)), timeout=3600)
    print(f"abdominal CT (threshold 250 HU), pore size 0.8 mm, porosity 0.7: seeding grid {r['grid']} "
          f"(step {r['step']:.3f} mm)")
    print(table([[r["passes"], ", ".join(map(str, r["solve"])), r["seeds"], r["asked_inside"], r["inside"],
                  f"{r['pore_inside']:.4f}", f"{r['seconds']:.1f}"]],
                ["cell passes", "solve's pore sizes mm", "seeds", "seeds asked inside", "seeds inside (exact)",
                 "pore size of their cells mm", "seeds and cells s"]))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=1)
    ap.add_argument("--voxel", type=float, default=0.1)
    ap.add_argument("--pore-size", type=float, default=0.6)
    ap.add_argument("--cases", nargs="+", choices=["l3", "ct"], default=["l3"],
                    help="l3: the L3 clip, box against patient seeding; ct: the abdominal CT's ribs and vertebrae")
    args = ap.parse_args(argv)
    bone = DATA / "clouthier_lumbar_L3_mean.stl"
    if not bone.is_file():
        print(f"needs {bone} (the shared data folder); nothing measured", file=sys.stderr)
        return 1
    rows, first = [], None
    for where in ("box", "patient") if "l3" in args.cases else ():
        code = RUN.format(bone=str(bone), clip=CLIP, pore=args.pore_size, voxel=args.voxel, seeds_in=where)
        med, _ = median_runs(code, args.runs, warmup=0)
        first = first or med
        rows.append([where, f"{med['seeds']:.0f}", f"{med['cells_in_scaffold']:.0f}",
                     f"{med['stages']['cells']:.2f} ({med['cell_passes']:.0f} passes)", f"{med['stages']['lattice']:.2f}", f"{med['total_s']:.1f}",
                     f"{med['peak_rss_mb']:.0f}", f"{med['porosity_printed']:.4f}", f"{med['porosity_voxel']:.4f}",
                     f"{med['pore_size_mm']:.4f}", f"{med['triangles']:.0f}",
                     f"{med['bodies']:.0f} ({med['patient_pieces']:.0f} patient pieces)"])
    if rows:
        print(f"L3 clip {CLIP} of clouthier_lumbar_L3_mean.stl: patient {first['patient_volume_mm3']:.0f} mm3 in a "
              f"{first['box_volume_mm3']:.0f} mm3 box; pore size {args.pore_size} mm, porosity 0.7, voxel "
              f"{args.voxel} mm; median of {args.runs} (shared machine: timings noisy)")
        print(table(rows, ["seeds in", "cells", "cells in scaffold", "cells s", "lattice s", "total s",
                           "peak RSS MiB", "porosity printed (mesh)", "porosity voxels", "pore size mm",
                           "triangles", "bodies"]))
    if "ct" in args.cases:
        ct_case()
    return 0


if __name__ == "__main__":
    sys.exit(main())
