"""Time and peak memory of generate --printer P --repair on the default 10 mm cube: in memory
against a run in slabs (a --max-memory small enough to force them, or ``tiled:<voxels>``); the two
fields compared byte for byte. Each run in a fresh process; its peak is its own resident set's.

    python benchmarks/bench_repair_slabs.py lpbf-ti64 700M
    python benchmarks/bench_repair_slabs.py dlp-resin tiled:306030 '{"pore_size": 1.2, "porosity": 0.6}'
"""
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUT = Path(tempfile.mkdtemp(prefix="bench_repair_"))

PRINTER = sys.argv[1] if len(sys.argv) > 1 else "lpbf-ti64"
BUDGET = sys.argv[2] if len(sys.argv) > 2 else "450M"
EXTRA = json.loads(sys.argv[3]) if len(sys.argv) > 3 else {}
CHILD = r"""
import json, resource, sys, time
sys.path.insert(0, sys.argv[2])
from implicit_scaffold.pipeline import generate
opts = json.loads(sys.argv[1])
t = time.perf_counter()
r = generate(mesh=False, morphometry=False, repair=True, **opts)
rep = r.report
print(json.dumps({"seconds": time.perf_counter() - t, "shape": list(rep.get("grid_shape") or []),
                  "tiled": rep.get("tiled"), "repair_s": rep["timings_s"].get("repair"),
                  "rounds": rep["repair"]["rounds"], "repair": rep["repair"], "peak_mb": rep["peak_memory_mb"],
                  "maxrss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}, default=lambda o: o.item()))
"""


def run(name, **opts):
    t = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", CHILD, json.dumps({**EXTRA, "printer": PRINTER, "output": str(OUT / f"{name}.npy"),
                                                                **opts}), str(ROOT)],
                          capture_output=True, text=True)
    wall = time.perf_counter() - t
    if done.returncode:
        print(name, "failed:", done.stderr.strip().splitlines()[-1])
        return None
    out = json.loads(done.stdout.strip().splitlines()[-1])
    peak = out["maxrss_mib"]
    tiled = out["tiled"]
    print(f"{name:10s} {'in memory' if tiled is None else str(tiled['slabs']) + ' slabs, ' + str(tiled['planes_per_slab']) + ' planes':>22s}"
          f"  wall {wall:6.1f} s  generate {out['seconds']:6.1f} s  repair stage {out['repair_s']:6.1f} s"
          f"  rounds {out['rounds']}  peak RSS {peak:7.1f} MiB (report {out['peak_mb']} MiB)", flush=True)
    return out


print(f"generate --printer {PRINTER} --repair {EXTRA or ''}, default 10 mm cube, -o .npy (mesh and morphometry off)")
a = run("memory", tiled=False)
b = run("slabs", **({"tiled": int(BUDGET[6:])} if BUDGET.startswith("tiled:") else {"max_memory": BUDGET}))
if a and b:
    same = (OUT / "memory.npy").read_bytes() == (OUT / "slabs.npy").read_bytes()
    print("same field bytes:", same, "| same report['repair']:", a["repair"] == b["repair"])
import shutil  # noqa: E402

shutil.rmtree(OUT, ignore_errors=True)
