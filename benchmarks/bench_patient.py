"""Issue 3 benchmark: a scaffold in a 20 mm femoral shaft segment (jigsaw_femur.stl).

    python benchmarks/bench_patient.py [--runs 1] [--warmup 0] [--voxel 0.05] [--no-figure]
                                       [--max-memory 4G] [--skin T] [--smooth-cut K]

Two osteotomy planes at z = 210 and 230 mm keep a 20 mm segment of the shaft; pore size
0.6 mm, porosity 0.7, voxel 0.05 mm (about 10^8 voxels). Prints the wall time and the
peak resident memory of every stage (loading the mesh included), the median of --runs
runs each in a fresh process, and saves a picture of the scaffold to
benchmarks/figures/femur_shaft.png (drawn from every third voxel of its field, after
the timings). Needs ../shared/data (see its README) and about 12 GB of free memory.

With --max-memory the run is bounded (tiled in slabs when the whole grid does not fit; no
figure then, the field having been streamed) and the peak of the whole process tree
(the run and its mesh workers, their proportional set sizes summed every 0.1 s) is
printed too; --ext writes another format (a volume: .nii.gz, .tif, ...).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import DATA, FEMUR_SHAFT, median_runs, table  # noqa: E402

FIGURE = Path(__file__).resolve().parent / "figures" / "femur_shaft.png"

RUN = FEMUR_SHAFT + """
tree = {{'peak': 0, 'rss_peak': 0, 'stage': 'load', 'stages': {{}}}}
def sample_tree():
    # the run and its mesh worker processes together, overall and per stage. The workers are
    # forked: the pages they share with the run count in each one's resident set, so the sum of
    # the resident sets counts them twice; the proportional set sizes (PSS) add up to what the
    # tree holds
    while True:
        try:
            procs = [proc] + proc.children(recursive=True)
            pss = sum(p.memory_full_info().pss for p in procs)
            rss = sum(p.memory_info().rss for p in procs)
        except psutil.Error:
            continue
        tree['peak'] = max(tree['peak'], pss)
        tree['rss_peak'] = max(tree['rss_peak'], rss)
        tree['stages'][tree['stage']] = max(tree['stages'].get(tree['stage'], 0), pss / 2**20)
        time.sleep(0.1)
sampled_stage = progress.Progress.stage
@contextmanager
def tree_stage(self, name, detail=''):
    tree['stage'] = name
    with sampled_stage(self, name, detail):
        yield
progress.Progress.stage = tree_stage
threading.Thread(target=sample_tree, daemon=True).start()
t0 = time.perf_counter()
out = out[:-len('.stl')] + {ext!r}
r = implicit_scaffold.generate(patient=patient, pore_size=0.6, porosity=0.7, voxel={voxel}, output=out,
                               verbose=True, max_memory={max_memory!r}, skin={skin}, smooth_cut={smooth_cut})
total = time.perf_counter() - t0 + patient.load_seconds
rep = r.report
_out = {{'total_s': total, 'stages': rep['timings_s'], 'peak_mb': peaks,
        'grid': 'x'.join(map(str, rep['grid_shape'])), 'mvoxels': r.grid.size / 1e6,
        'patient_volume_mm3': rep['patient_volume_mm3'], 'box_volume_mm3': rep['box_volume_mm3'],
        'seeds': rep['seeds'], 'cells_in_scaffold': rep['cells_in_scaffold'],
        'porosity_voxel': rep['porosity_voxel'], 'porosity_mesh': rep.get('porosity_mesh', float('nan')),
        'triangles': rep.get('triangles', 0), 'bodies': rep.get('bodies', rep.get('bodies_voxels')),
        'watertight': rep.get('watertight'),
        'slabs': rep.get('tiled', {{}}).get('slabs', 1), 'tree_peak_mb': tree['peak'] / 2**20,
        'tree_rss_sum_mb': tree['rss_peak'] / 2**20, 'output_bytes': os.path.getsize(out),
        'tree_mb': tree['stages']}}
import shutil
shutil.rmtree(os.path.dirname(out))  # a few GB per run
if {figure!r} and r.field is not None:
    # the picture is 900 px across 27 mm: every third voxel of the same field draws the same scaffold
    # with a tenth of the triangles (rendering all of them takes tens of GB off screen)
    from implicit_scaffold.run.grid import Grid
    from implicit_scaffold.mesh.marching import mesh_field
    from implicit_scaffold.io.report import render_mesh
    step = max(1, int(round(0.15 / r.grid.spacing)))
    r.mesh = None
    light = mesh_field(r.field[::step, ::step, ::step], Grid(r.grid.origin, r.grid.spacing * step,
                       tuple(-(-n // step) for n in r.grid.shape)), check=False)
    del r
    os.makedirs(os.path.dirname({figure!r}), exist_ok=True)
    with open({figure!r}, 'wb') as f:
        f.write(render_mesh(light, size=(900, 900)))
"""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=1)
    ap.add_argument("--warmup", type=int, default=0)
    ap.add_argument("--voxel", type=float, default=0.05)
    ap.add_argument("--no-figure", action="store_true")
    ap.add_argument("--max-memory", default=None, help="bound the run (e.g. 4G); default: the tool's own")
    ap.add_argument("--ext", default=".stl", help="output format (.stl, .nii.gz, .tif, ...)")
    ap.add_argument("--skin", type=float, default=0.0)
    ap.add_argument("--smooth-cut", type=float, default=0.0)
    args = ap.parse_args(argv)
    femur = DATA / "jigsaw_femur.stl"
    if not femur.is_file():
        print(f"needs {femur} (the shared data folder); nothing measured", file=sys.stderr)
        return 1
    code = RUN.format(femur=str(femur), voxel=args.voxel, figure="" if args.no_figure else str(FIGURE),
                      max_memory=args.max_memory, skin=args.skin, smooth_cut=args.smooth_cut, ext=args.ext)
    med, _ = median_runs(code, args.runs, warmup=args.warmup)
    stages = med["stages"]
    rows = [[name, f"{stages[name]:.2f}", f"{med['peak_mb'].get(name, float('nan')):.0f}",
             f"{med['tree_mb'].get(name, float('nan')):.0f}"] for name in stages]
    rows.append(["total", f"{med['total_s']:.2f}", f"{med['peak_rss_mb']:.0f}", f"{med['tree_peak_mb']:.0f}"])
    print(f"femoral shaft segment z 210..230 mm of jigsaw_femur.stl: pore size 0.6 mm, porosity 0.7, "
          f"voxel {args.voxel} mm, grid {med['grid']} ({med['mvoxels']:.1f} Mvoxels); median of {args.runs}")
    print(f"--max-memory {args.max_memory or 'default'}, skin {args.skin} mm, smooth cut {args.smooth_cut} mm: "
          f"{med['slabs']:.0f} slab(s); peak of the process tree {med['tree_peak_mb']:.0f} MiB (PSS; "
          f"{med['tree_rss_sum_mb']:.0f} MiB as a sum of resident sets); {args.ext} of "
          f"{med['output_bytes'] / 2**20:.0f} MiB")
    print(table(rows, ["stage", "time s", "peak RSS MiB", "process tree PSS MiB"]))
    print(f"patient volume {med['patient_volume_mm3']:.1f} mm3, box volume {med['box_volume_mm3']:.1f} mm3, "
          f"seeds {med['seeds']:.0f}, cells in scaffold {med['cells_in_scaffold']:.0f}")
    print(f"porosity voxels {med['porosity_voxel']:.4f}, mesh {med['porosity_mesh']:.4f}; "
          f"triangles {med['triangles']:.0f}, bodies {med['bodies']:.0f}, watertight {med['watertight']}")
    if not args.no_figure:
        print(f"figure: {FIGURE}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
