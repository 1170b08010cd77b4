"""Issue 17 benchmark: loading a volume patient (a mask of a few million voxels) as a signed distance.

    python benchmarks/bench_load.py [--runs 3] [--no-reference] [--full]

Cases, each written to a temporary folder before the clock starts:

- **trabecular µCT**: the first 154³ voxels of bonejheadless_lumbar_trabecular_ROI_1_06219.nrrd
  at its source's 0.0513 mm (a crop of 170³ = 4.91 Mvoxels with the margin): bone surface
  in nearly every voxel's neighbourhood, the hardest case per voxel;
- **vertebra at 0.5 mm**: clouthier_lumbar_L3_mean.stl voxelised at 0.5 mm (196 x 202 x 117
  = 4.63 Mvoxels cropped), what a CT segmentation of a vertebra gives;
- **L1 label**: label 31 of totalseg_example_seg.nii.gz (3 mm voxels, a few thousand);
- with ``--full``: the whole 300³ trabecular ROI (31.6 Mvoxels cropped), the compiled path only.

Each figure is the median of --runs runs, each in a fresh process (after one discarded warm-up
run that fills numba's cache): **fresh** is ``load_patient``'s own ``load_seconds`` (the load as
a run reports it: reading, the compiled kernels' start-up in a new process, every step);
**warm** a second load in the same process; **reference** the NumPy/SciPy path the kernels
replaced (``load_volume(..., reference=True)``, the code before this change), whose ratio to
fresh is printed. The check compares the two fields on the crop: near the surface (where the
reference field is within one voxel of 0) and everywhere. Needs ../shared/data.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import DATA, median_runs, table  # noqa: E402

FRESH = """
import time
from implicit_scaffold.io.patient_io import load_patient
p = load_patient({path!r}, label={label!r})
fresh = p.load_seconds
t = time.perf_counter()
p = load_patient({path!r}, label={label!r})
warm = time.perf_counter() - t
import numpy as np
_out = {{'fresh_s': fresh, 'warm_s': warm, 'crop_mvoxels': float(np.prod(p._field.shape)) / 1e6,
        'volume_mm3': p.volume, 'target_mm3': p.mask_voxels * float(np.prod(p.spacing))}}
"""

REFERENCE = """
import time
import numpy as np
from implicit_scaffold.fields.patient_volume import load_volume
t = time.perf_counter()
ref = load_volume({path!r}, label={label!r}, reference=True)
seconds = time.perf_counter() - t
new = load_volume({path!r}, label={label!r})
d = np.abs(new._field - ref._field)
near = np.abs(ref._field) < ref.spacing.max()
_out = {{'reference_s': seconds, 'reference_volume_mm3': ref.volume,
        'near_max_mm': float(d[near].max()), 'near_mean_mm': float(d[near].mean()),
        'all_max_mm': float(d.max()), 'sign_share': float(np.mean((new._field < 0) != (ref._field < 0))),
        'bounds_mm': float(max(np.abs(new.lo - ref.lo).max(), np.abs(new.hi - ref.hi).max())),
        'voxel_mm': float(ref.spacing.max())}}
"""


def _write_cases(folder: Path, full: bool) -> list[tuple[str, str, int | None]]:
    import numpy as np
    import SimpleITK as sitk

    from implicit_scaffold.run.grid import Grid
    from implicit_scaffold.io.patient_io import load_patient

    cases = []
    roi = sitk.GetArrayFromImage(sitk.ReadImage(str(DATA / "bonejheadless_lumbar_trabecular_ROI_1_06219.nrrd")))
    for n, name in ((154, "trabecular µCT 154³ at 0.0513 mm"),) + (((300, "trabecular µCT 300³ (whole ROI)"),)
                                                                   if full else ()):
        img = sitk.GetImageFromArray(np.ascontiguousarray(roi[:n, :n, :n]))
        img.SetSpacing((0.0513,) * 3)
        path = folder / f"trabecular_{n}.nrrd"
        sitk.WriteImage(img, str(path), True)
        cases.append((name, str(path), None))
    mesh = load_patient(DATA / "clouthier_lumbar_L3_mean.stl")
    h = 0.5
    grid = Grid.covering(mesh.lo, mesh.hi, h, pad=2)
    mask = (mesh.sdf_grid(grid) < 0).astype(np.uint8)
    img = sitk.GetImageFromArray(np.ascontiguousarray(mask.T))
    img.SetSpacing((h,) * 3)
    img.SetOrigin(tuple(float(v) for v in grid.origin))
    path = folder / "l3_0.5mm.nrrd"
    sitk.WriteImage(img, str(path), True)
    cases.insert(1, ("vertebra (L3 mesh) at 0.5 mm", str(path), None))
    cases.insert(2, ("L1 label, 3 mm CT", str(DATA / "totalseg_example_seg.nii.gz"), 31))
    return cases


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--no-reference", action="store_true", help="time the compiled path only")
    ap.add_argument("--full", action="store_true", help="add the whole 300³ ROI (compiled path only)")
    args = ap.parse_args(argv)
    if not DATA.is_dir():
        print(f"needs {DATA} (the shared data folder); nothing measured", file=sys.stderr)
        return 1
    print(f"load average at start (1, 5, 15 min): {' '.join(f'{x:.2f}' for x in os.getloadavg())} "
          f"on {os.cpu_count()} CPUs")
    rows, checks = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for name, path, label in _write_cases(Path(tmp), args.full):
            fresh, _ = median_runs(FRESH.format(path=path, label=label), args.runs, warmup=1)
            row = [name, f"{fresh['crop_mvoxels']:.2f}", f"{fresh['fresh_s']:.2f}", f"{fresh['warm_s']:.2f}"]
            whole = "300" in name
            if args.no_reference or whole:
                row += ["-", "-"]
            else:
                ref, _ = median_runs(REFERENCE.format(path=path, label=label), args.runs, warmup=0)
                row += [f"{ref['reference_s']:.2f}", f"{ref['reference_s'] / fresh['fresh_s']:.1f}x"]
                checks.append([name, f"{ref['voxel_mm']:.4g}", f"{ref['near_max_mm']:.2g} / {ref['near_mean_mm']:.2g}",
                               f"{ref['all_max_mm']:.2g}", f"{ref['sign_share']:.1e}", f"{ref['bounds_mm']:.2g}",
                               f"{(ref['reference_volume_mm3'] / fresh['target_mm3'] - 1):+.1e}"])
            row.append(f"{(fresh['volume_mm3'] / fresh['target_mm3'] - 1):+.1e}")
            rows.append(row)
            print(f"  {name}: done", flush=True)
    print(f"median of {args.runs} runs, each in a fresh process")
    print(table(rows, ["case", "crop Mvoxels", "fresh s", "warm s", "reference s", "reference / fresh",
                       "volume - mask's (rel)"]))
    if checks:
        print("compiled field against the reference's, on the crop:")
        print(table(checks, ["case", "voxel mm", "|diff| near surface max / mean mm", "|diff| max mm",
                             "sign differs (share)", "bounds |diff| mm", "reference volume - mask's (rel)"]))
    print(f"load average at end (1, 5, 15 min): {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
