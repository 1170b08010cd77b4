"""Issue 15 benchmark: the print certificate's time on a 400^3 scaffold, and which printer profiles
the default cube and the femoral shaft pass, and why.

    python benchmarks/bench_printability.py [--runs 3] [--only speed,profiles,slabs]

slabs: the whole grid's certificate against the one measured slab by slab (issue 12), same figures.

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
from implicit_scaffold.measure.printability import certificate, printer_profile
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
from implicit_scaffold.measure.printability import certificate, printer_profile, profiles
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

BUILD_FIELDS = """
import numpy as np
import implicit_scaffold
r = implicit_scaffold.generate(mesh=False, morphometry=False)
np.ascontiguousarray(r.field, np.float32).tofile({folder!r} + '/field.f32')
np.ascontiguousarray(r.patient_sdf, np.float32).tofile({folder!r} + '/patient.f32')
_out = {{'origin': list(r.grid.origin), 'spacing': r.grid.spacing, 'shape': list(r.grid.shape)}}
"""

#: the certificate of the fields BUILD_FIELDS wrote, whole (planes 0) or slab by slab from files on
#: disk as a tiled run holds them; the fields are read a few planes at a time, so the process's peak
#: before the call is small and its peak RSS (ru_maxrss) is the certificate's
SLABS = """
import time
import numpy as np, psutil
from implicit_scaffold.run.grid import Grid
from implicit_scaffold.measure.printability import certificate, certificate_by_slabs, printer_profile
from implicit_scaffold.run.tiles import FieldFile
grid = Grid(tuple({origin!r}), {spacing!r}, tuple({shape!r}))
profile = printer_profile('dlp-resin')
plane = grid.shape[1] * grid.shape[2]
def planes_of(name, x0, x1):
    return np.fromfile({folder!r} + '/' + name, np.float32, count=(x1 - x0) * plane,
                       offset=4 * x0 * plane).reshape(-1, grid.shape[1], grid.shape[2])
if {planes!r}:
    files = []
    for name in ('field.f32', 'patient.f32'):
        f = FieldFile(grid)
        for x0 in range(0, grid.shape[0], 8):
            f.write(x0, planes_of(name, x0, min(x0 + 8, grid.shape[0])))
        files.append(f)
    before = psutil.Process().memory_info().rss
    t0 = time.perf_counter()
    c = certificate_by_slabs(files[0], files[1], grid.spacing, profile, max_voxels={planes!r} * plane,
                             origin=grid.origin)
else:
    field = planes_of('field.f32', 0, grid.shape[0])
    region = planes_of('patient.f32', 0, grid.shape[0]) < 0
    before = psutil.Process().memory_info().rss
    t0 = time.perf_counter()
    c = certificate(field < 0, grid.spacing, profile, field=field, region=region, origin=grid.origin)
t = time.perf_counter() - t0
c = dict(c)
c.pop('seconds')
import json, hashlib
_out = {{'seconds': t, 'before_mb': before / 2**20,
         'digest': hashlib.sha256(json.dumps(c, sort_keys=True, default=str).encode()).hexdigest()[:16]}}
"""

CUBE = "r = implicit_scaffold.generate(mesh=False, morphometry=False)"
SHAFT = """from implicit_scaffold.io.patient_io import load_patient
patient = load_patient({femur!r}, cut_planes=(0, 0, 210, 0, 0, 1, 0, 0, 230, 0, 0, 1))
r = implicit_scaffold.generate(patient=patient, pore_size=0.6, porosity=0.7, voxel=0.1, mesh=False, morphometry=False)"""


def speed(runs):
    med, _ = median_runs(SPEED, runs)
    print(f"\nCertificate of the default cube's lattice on a {med['grid']} grid (dlp-resin), median of {runs} runs "
          "after a warm-up")
    rows = [[k[5:], f"{v:.2f}"] for k, v in med.items() if k.startswith("part_")]
    rows.append(["total", f"{med['seconds']:.2f}"])
    print(table(rows, ["part", "seconds"]))
    print("(the as-built check runs beside the others, in a thread of its own: its part is the wait for it "
          "at its end, its work falls in the parts before)")
    print(f"peak RSS {med['peak_rss_mb']:.0f} MB (the run's generate included); target <= 10 s: "
          f"{'met' if med['seconds'] <= 10 else 'NOT met'}")


def slabs(runs):
    """The whole grid's certificate against certificate_by_slabs on the default cube (195^3), each
    in a fresh process; memory is the peak above what the process held before the call."""
    import shutil
    import tempfile

    folder = tempfile.mkdtemp(prefix="bench_printability_")
    g = run_isolated(BUILD_FIELDS.format(folder=folder))
    rows, digests = [], set()
    for planes in (0, 60, 20):
        med, _ = median_runs(SLABS.format(folder=folder, planes=planes, **g), runs)
        digests.add(med["digest"])
        rows.append(["whole grid" if not planes else f"slabs of {planes} planes", f"{med['seconds']:.2f}",
                     f"{med['peak_rss_mb'] - med['before_mb']:.0f}", med["digest"]])
    print(f"\nPrint certificate (dlp-resin) of the default cube, 195^3 voxels, median of {runs} runs after a warm-up")
    print(table(rows, ["certificate", "seconds", "peak MiB above the process", "figures' digest"]))
    print(f"same figures whole and in slabs: {'yes' if len(digests) == 1 else 'NO'}")
    shutil.rmtree(folder, ignore_errors=True)


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
        {"speed": speed, "profiles": profiles, "slabs": slabs}[name.strip()](args.runs)


if __name__ == "__main__":
    main()
