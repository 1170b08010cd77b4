"""Shared helpers for the benchmark scripts: isolated runs, medians, tables."""
from __future__ import annotations

import json
import statistics
import subprocess
import sys
import textwrap
from pathlib import Path

#: the shared real-bone data folder beside the repository (../shared/data)
DATA = Path(__file__).resolve().parents[2] / "shared" / "data"

#: code for a benchmark run (a format string's field): samples the resident memory every
#: 20 ms and keeps each pipeline stage's peak in ``peaks`` (MiB)
STAGE_MEMORY = """
import os, tempfile, threading, time
from contextlib import contextmanager
import psutil
import implicit_scaffold
from implicit_scaffold import opencl, progress
proc = psutil.Process()
state = {'peak': 0, 'stop': False}
def sample():
    while not state['stop']:
        state['peak'] = max(state['peak'], proc.memory_info().rss)
        time.sleep(0.02)
threading.Thread(target=sample, daemon=True).start()
peaks = {}
@contextmanager
def measured(name):
    state['peak'] = proc.memory_info().rss
    yield
    state['peak'] = max(state['peak'], proc.memory_info().rss)
    peaks[name] = max(peaks.get(name, 0), state['peak'] / 2**20)
plain_stage = progress.Progress.stage
@contextmanager
def stage(self, name, detail=''):
    with measured(name), plain_stage(self, name, detail):
        yield
progress.Progress.stage = stage
"""

#: ``STAGE_MEMORY``, then the 20 mm femoral shaft (jigsaw_femur.stl between z = 210 and 230 mm)
#: loaded as ``patient`` (stage ``load``), and ``out``, an STL path in a new temporary folder;
#: format with ``femur=`` (the file)
FEMUR_SHAFT = STAGE_MEMORY.replace("{", "{{").replace("}", "}}") + """
from implicit_scaffold.io.patient_io import load_patient
opencl.context()
with measured('load'):
    patient = load_patient({femur!r}, cut_planes=(0, 0, 210, 0, 0, 1, 0, 0, 230, 0, 0, 1))
out = os.path.join(tempfile.mkdtemp(), 'femur_shaft.stl')
"""


def run_isolated(code: str, timeout: float = 3600) -> dict:
    """Run `code` in a fresh interpreter; it must print one JSON line last. Adds ``peak_rss_mb``.

    A fresh process per run makes the peak memory (``ru_maxrss``) that run's own.
    """
    wrapper = textwrap.dedent(code) + textwrap.dedent("""
        import json as _j, resource as _r
        _out['peak_rss_mb'] = _r.getrusage(_r.RUSAGE_SELF).ru_maxrss / 1024
        print(_j.dumps(_out))
    """)
    p = subprocess.run([sys.executable, "-c", wrapper], capture_output=True, text=True, timeout=timeout)
    if p.returncode != 0:
        raise RuntimeError(p.stderr[-3000:])
    return json.loads(p.stdout.strip().splitlines()[-1])


def median_runs(code: str, runs: int, warmup: int = 1) -> tuple[dict, list[dict]]:
    """Median of each numeric figure over `runs` isolated runs after `warmup` discarded ones."""
    for _ in range(warmup):
        run_isolated(code)
    results = [run_isolated(code) for _ in range(runs)]
    med = {}
    for key in results[0]:
        vals = [r[key] for r in results]
        if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in vals):
            med[key] = statistics.median(vals)
        elif isinstance(vals[0], dict):
            med[key] = {k: statistics.median([r[key][k] for r in results]) for k in vals[0]}
        else:
            med[key] = vals[0]
    return med, results


def table(rows: list[list], header: list[str]) -> str:
    cells = [header] + [[str(c) for c in r] for r in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(header))]
    line = lambda r: "| " + " | ".join(c.ljust(w) for c, w in zip(r, widths)) + " |"  # noqa: E731
    return "\n".join([line(cells[0]), "|" + "|".join("-" * (w + 2) for w in widths) + "|"]
                     + [line(r) for r in cells[1:]])
