"""Issue 5 benchmarks: fine and large grids in bounded memory (tiled runs).

    python benchmarks/bench_tiled.py [--only b2,b2-plain,b5,scaling,femur,femur-fine,femur-fine-slices,femur-graded,ct]
                                     [--runs 3]
                                     [--warmup 0] [--no-figure] [--write]

- B2 "fine pores": the 10 mm cube, pore size 0.5 mm, porosity 0.8 (12,223 seeds), voxel
  0.02 mm (502^3 voxels with the outer layer), written as STL with ``max_memory="4G"``:
  end-to-end seconds and peak memory (targets 60 s and 4 GB). b2-plain: the same without the
  voxel morphometry (``morphometry=False``), the work issue 12's 37.0 s tiled B2 run did.
- B5 "large": the default cube (pore size 0.6 mm) at 0.01 mm (1002^3 voxels), streamed
  once to STL and once to a PNG stack, each within ``max_memory="4G"``: seconds, seconds
  per billion voxels, peak memory.
- scaling: time and peak memory against the voxel count (500 seeds at 0.04, 0.02 and
  0.01 mm) and against the seed count (500, 12,223 and 100,000 seeds at 0.02 mm), STL
  out, ``max_memory="4G"`` except where the seeds alone need more (the 100,000 seeds'
  cells); a log-log plot goes to benchmarks/figures/scaling.png.

- femur, femur-fine, ct (issue 12, need ../shared/data): the 20 mm femoral shaft of
  ``jigsaw_femur.stl`` at 0.05 mm with the defaults (the default budget, 4 GiB), at 0.02 mm
  (about 1.7 G voxels) to STL (femur-fine) and to a PNG stack (femur-fine-slices), graded
  (``--grade 0:0.3,2:0.8``) with a 0.3 mm skin at 0.03 mm to STL (femur-graded), and the CT label of
  ``totalseg_example_seg.nii.gz`` (label 31, L1) at 0.1 mm with the voxel morphometry.

Every run is a fresh process (its peak resident memory is its own), on this machine's
OpenCL device; the figures are medians of --runs runs. Outputs go to a temporary folder
and are removed after each run. With --write, benchmarks/scaling.md gets this run's table
(with the date, the command and the load average) above the earlier runs' tables, and at its
top the whole table: every run's newest row, with when and by which command it was measured.
``--only '' --write`` measures nothing and writes the whole table again from the runs there.
"""
from __future__ import annotations

import argparse
import re
import shlex
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import DATA, median_runs, table  # noqa: E402

FIGURE = Path(__file__).resolve().parent / "figures" / "scaling.png"
SCALING = Path(__file__).resolve().parent / "scaling.md"
TITLE = "How time and memory grow (issues 5 and 12)"
#: the heading above the runs' own tables, newest first
RUNS = "## Every run's table, newest first"

RUN = """
import os, shutil, tempfile, threading, time
import psutil
import implicit_scaffold
from implicit_scaffold import opencl
# the mesh stage may fork two workers: their memory counts too, each page once (PSS)
proc = psutil.Process()
tree = {{'peak': 0}}
def sample():
    while True:
        total = 0
        for p in [proc] + proc.children(recursive=True):
            try:
                total += p.memory_full_info().pss
            except psutil.Error:
                pass
        tree['peak'] = max(tree['peak'], total)
        time.sleep(0.25)
threading.Thread(target=sample, daemon=True).start()
opencl.context()
folder = tempfile.mkdtemp(dir={folder!r})
kind = {kind!r}
patient_file, patient_options = {patient!r}
t0 = time.perf_counter()
if patient_file is not None:
    from implicit_scaffold.io.patient_io import load_patient
    options = dict({options!r}, patient=load_patient(patient_file, **patient_options))
else:
    options = {options!r}
try:
    if kind == 'slices':
        r = implicit_scaffold.generate(mesh=False, morphometry=False, slices={{'out_dir': os.path.join(folder, 'stack')}},
                                       **options)
    else:
        r = implicit_scaffold.generate(output=os.path.join(folder, 'scaffold.stl'), **options)
    seconds = time.perf_counter() - t0
    size = sum(f.stat().st_size for f in __import__('pathlib').Path(folder).rglob('*') if f.is_file())
finally:
    shutil.rmtree(folder, ignore_errors=True)
rep = r.report
_out = {{'seconds': seconds, 'voxels': int(__import__('numpy').prod(rep['grid_shape'])), 'seeds': rep['seeds'],
        'triangles': rep.get('triangles', 0), 'porosity_voxel': rep['porosity_voxel'],
        'porosity_mesh': rep.get('porosity_mesh', float('nan')), 'watertight': rep.get('watertight'),
        'porosity_printed': rep.get('porosity_printed', float('nan')),
        'slabs': (rep.get('tiled') or {{}}).get('slabs', 1), 'output_mb': size / 2**20,
        'peak_tree_mb': tree['peak'] / 2**20, 'mesh_workers': rep.get('mesh_workers', 1),
        'stages': rep['timings_s'], 'strut_mean_mm': (rep.get('strut_thickness_mm') or {{}}).get('mean'),
        'pore_diameter_mean_mm': (rep.get('pore_diameter_mm') or {{}}).get('mean'),
        'interconnected_porosity': rep.get('interconnected_porosity'),
        'conn_d_per_mm3': rep.get('connectivity_density_per_mm3')}}
"""


def measure(options: dict, runs: int, warmup: int, kind: str = "stl", folder: str | None = None,
            patient=(None, {})) -> dict:
    med, _ = median_runs(RUN.format(options=options, kind=kind, folder=folder, patient=patient), runs, warmup)
    return med


def _row(name, m):
    gvox = m["voxels"] / 1e9
    return [name, f"{m['voxels']:,}", m["seeds"], m["slabs"], f"{m['seconds']:.1f}", f"{m['seconds'] / gvox:.0f}",
            f"{m['peak_rss_mb'] / 1024:.2f}", f"{max(m['peak_tree_mb'], m['peak_rss_mb']) / 1024:.2f}",
            f"{m['triangles']:,}", f"{m['output_mb']:.0f}"]


HEADER = ["run", "voxels", "seeds", "slabs", "s", "s per 10^9 voxels", "peak GiB (process)",
          "peak GiB (with mesh workers, PSS)", "triangles", "output MiB"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default="b2,b5,scaling")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--warmup", type=int, default=0)
    ap.add_argument("--no-figure", action="store_true")
    ap.add_argument("--folder", default=None, help="where the outputs are written (a temporary folder)")
    ap.add_argument("--write", action="store_true", help="write the table to benchmarks/scaling.md")
    args = ap.parse_args(argv)
    only = set(filter(None, args.only.split(",")))
    rows, cache = [], {}

    def run(name, options, kind="stl", patient=(None, {})):
        key = (kind, tuple(sorted(options.items())), str(patient))
        if key not in cache:
            cache[key] = measure(options, args.runs, args.warmup, kind=kind, folder=args.folder, patient=patient)
            rows.append(_row(name, cache[key]))
        return cache[key]

    b2 = dict(pore_size=0.5, porosity=0.8, voxel=0.02, max_memory="4G")
    if "b2" in only:
        m = run("B2 fine pores -> STL", b2)
        print(f"B2: {m['seconds']:.1f} s (target 60), peak {m['peak_rss_mb'] / 1024:.2f} GiB, with the mesh "
              f"workers {max(m['peak_tree_mb'], m['peak_rss_mb']) / 1024:.2f} GiB (target 4), "
              f"porosity voxels {m['porosity_voxel']:.4f} mesh {m['porosity_mesh']:.4f}, "
              f"watertight {m['watertight']}; stages {m['stages']}", flush=True)
    if "b2-plain" in only:
        # the work the 37.0 s B2 run did: the mesh without the voxel morphometry, which
        # the slab path then left "not measured" and every run now measures by default
        m = run("B2 fine pores -> STL, no morphometry", dict(b2, morphometry=False))
        print(f"B2 without morphometry: {m['seconds']:.1f} s (the issue's tiled run: 37.0 s), peak "
              f"{max(m['peak_tree_mb'], m['peak_rss_mb']) / 1024:.2f} GiB; stages {m['stages']}", flush=True)
    if "b5" in only:
        for kind in ("stl", "slices"):
            m = run(f"B5 large -> {'STL' if kind == 'stl' else 'PNG stack'}", dict(voxel=0.01, max_memory="4G"),
                    kind)
            print(f"B5 {kind}: {m['seconds']:.1f} s, {m['seconds'] / (m['voxels'] / 1e9):.0f} s per 10^9 voxels, "
                  f"peak {m['peak_rss_mb'] / 1024:.2f} GiB, with the mesh workers "
                  f"{max(m['peak_tree_mb'], m['peak_rss_mb']) / 1024:.2f} GiB (target 4); stages {m['stages']}",
                  flush=True)
    if "scaling" in only:
        series = {"voxels": [], "seeds": []}
        for voxel in (0.04, 0.02, 0.01):
            m = run(f"500 seeds at {voxel} mm", dict(seeds=500, voxel=voxel, max_memory="4G"))
            series["voxels"].append(m)
            print(f"scaling voxels {voxel}: {m['seconds']:.1f} s, peak {m['peak_rss_mb'] / 1024:.2f} GiB", flush=True)
        for seeds in (500, 12_223, 100_000):
            if seeds == 500:
                m = series["voxels"][1]
            elif seeds == 12_223:
                m = run("B2 fine pores -> STL", b2)  # 12,223 seeds from the 0.5 mm pore size
            else:
                # the cells of 100,000 seeds alone take about 5 GB: this run gets 8
                m = run(f"{seeds:,} seeds at 0.02 mm", dict(seeds=seeds, voxel=0.02, max_memory="8G"))
            series["seeds"].append(m)
            print(f"scaling seeds {seeds}: {m['seconds']:.1f} s, peak {m['peak_rss_mb'] / 1024:.2f} GiB", flush=True)
        if not args.no_figure:
            _plot(series)
    femur = (str(DATA / "jigsaw_femur.stl"), {"cut_planes": (0, 0, 210, 0, 0, 1, 0, 0, 230, 0, 0, 1)})
    shaft = dict(pore_size=0.6, porosity=0.7)
    if "femur" in only:
        m = run("femoral shaft at 0.05 mm, defaults (4 GiB)", dict(shaft, voxel=0.05), patient=femur)
        print(f"femur 0.05: {m['seconds']:.1f} s, peak with the mesh workers "
              f"{max(m['peak_tree_mb'], m['peak_rss_mb']) / 1024:.2f} GiB (target 4); stages {m['stages']}", flush=True)
    for kind in [k for k, part in (("stl", "femur-fine"), ("slices", "femur-fine-slices")) if part in only]:
        m = run(f"femoral shaft at 0.02 mm -> {'STL' if kind == 'stl' else 'PNG stack'}",
                dict(shaft, voxel=0.02), kind, patient=femur)
        print(f"femur 0.02 {kind}: {m['seconds']:.1f} s, {m['seconds'] / (m['voxels'] / 1e9):.0f} s per 10^9 "
              f"voxels (target 160), peak {max(m['peak_tree_mb'], m['peak_rss_mb']) / 1024:.2f} GiB (target 4), "
              f"printed porosity {m['porosity_printed']:.4f} (target 0.7); stages {m['stages']}", flush=True)
    if "femur-graded" in only:
        m = run("femoral shaft graded 0:0.3,2:0.8, skin 0.3 mm, at 0.03 mm -> STL",
                dict(grade="0:0.3,2:0.8", skin=0.3, porosity=0.7, voxel=0.03), patient=femur)
        print(f"femur graded: {m['seconds']:.1f} s, peak {max(m['peak_tree_mb'], m['peak_rss_mb']) / 1024:.2f} GiB "
              f"(target 4), {m['slabs']} slabs; stages {m['stages']}", flush=True)
    if "ct" in only:
        label = (str(DATA / "totalseg_example_seg.nii.gz"), {"label": 31})
        for name, pore in (("L1 (CT label 31) at 0.1 mm, 0.8 mm pores, morphometry", 0.8),):
            m = run(name, dict(voxel=0.1, pore_size=pore), patient=label)
            print(f"ct: {m['seconds']:.1f} s, peak {max(m['peak_tree_mb'], m['peak_rss_mb']) / 1024:.2f} GiB; strut "
                  f"{m['strut_mean_mm']}, pore {m['pore_diameter_mean_mm']}, interconnected "
                  f"{m['interconnected_porosity']}, Conn.D {m['conn_d_per_mm3']}", flush=True)
    print()
    print(table(rows, HEADER))
    if args.write:
        _write(rows, argv)
    return 0


#: a run's table in scaling.md: the line that says when and how, then the table below it
WRITTEN = re.compile(r"^Written by `(?P<command>[^`]+)` on (?P<date>\d{4}-\d\d-\d\d \d\d:\d\d) UTC")
#: the whole table's own columns beside HEADER's
WHEN = ["measured (UTC)", "command"]


def _history(text: str) -> list[tuple[str, str, list[str]]]:
    """Every row the script wrote to scaling.md before: ``(date, command, cells)``, from each run's
    table (the one under its "Written by" line, with this script's HEADER)."""
    found, date, command = [], None, None
    for line in text.splitlines():
        m = WRITTEN.match(line)
        if m:
            date, command = m["date"], m["command"]
            continue
        if date is None or not line.startswith("|"):
            if line.startswith("#"):
                date = None  # a heading ends the run's block (the whole table has no "Written by")
            continue
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == len(HEADER) and cells != HEADER and not set("".join(cells)) <= set("-"):
            found.append((date, command, cells))
    return found


def whole_table(text: str) -> str:
    """The newest row of every run in `text` (scaling.md's runs), one table, with when and how each
    was measured; runs in the order they were first measured."""
    newest, order = {}, []
    for date, command, cells in _history(text):
        name = cells[0]
        if name not in newest:
            order.append(name)
        if name not in newest or date >= newest[name][0]:
            newest[name] = (date, command, cells)
    rows = [newest[n][2] + [newest[n][0], f"`{newest[n][1]}`"] for n in order]
    return table(rows, HEADER + WHEN)


def _write(rows, argv) -> None:
    """benchmarks/scaling.md: the whole table (every run's newest row, with its date and command),
    then this run's table with its date, command and load, then the runs before it."""
    import datetime
    import os

    load = ", ".join(f"{v:.1f}" for v in os.getloadavg())
    command = shlex.join(["python", "benchmarks/bench_tiled.py", *(argv if argv is not None else sys.argv[1:])])
    old = SCALING.read_text() if SCALING.exists() else ""
    # the runs' tables as they were written (each says when and how), without the old whole table
    if RUNS in old:
        body = old[old.index(RUNS) + len(RUNS):]
    else:
        body = re.sub(r"(?m)^## Earlier runs\n+", "", re.sub(r"(?m)^# How", "### How", old))
    if rows:
        body = (f"### {TITLE}\n\nWritten by `{command}` on "
                f"{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, on this project's 2-core "
                f"machine; load average at the end {load}. Each row is the median of the runs asked for, each run "
                "a fresh process; peaks are resident memory, of the run alone and of the run with its mesh workers "
                "(proportional set sizes summed, each page once). Runs without `max_memory` use the default "
                "budget (4 GiB).\n\n" + table(rows, HEADER) + "\n\n" + body.lstrip("\n"))
    runs = RUNS + "\n\n" + body.lstrip("\n")
    text = (f"# {TITLE}\n\nWritten by `{command}` from the runs below: every run's newest row, with the "
            "time it was measured (UTC) and the command that measured it. Each run is a fresh process on this "
            "project's 2-core machine; the runs' own paragraphs say how many runs each median took and the load "
            "at the time.\n\n" + whole_table(runs) + "\n\n" + runs)
    tmp = SCALING.with_suffix(".md.tmp")
    tmp.write_text(text)
    tmp.replace(SCALING)
    print(f"wrote {SCALING}")


def _plot(series: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6))
    for ax, key, label in ((axes[0], "voxels", "voxels (500 seeds)"), (axes[1], "seeds", "seeds (502^3 voxels)")):
        x = [m[key] for m in series[key]]
        ax.loglog(x, [m["seconds"] for m in series[key]], "o-", label="time, s")
        ax.loglog(x, [m["peak_rss_mb"] / 1024 for m in series[key]], "s--", label="peak memory, GiB")
        ax.set_xlabel(label)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    fig.suptitle("implicit_scaffold: time and memory (tiled within 4 GB where it applies), 2 cores")
    fig.tight_layout()
    FIGURE.parent.mkdir(exist_ok=True)
    fig.savefig(FIGURE, dpi=110)
    print(f"figure: {FIGURE}")


if __name__ == "__main__":
    sys.exit(main())
