"""Issue 16: compute the design maps shipped in the package (implicit_scaffold/design_maps.json).

    PYTHONPATH=. python benchmarks/design_maps.py [--write] [--only paper|struts]

Builds every point of :func:`implicit_scaffold.design_maps.grid_points` (style, Sf, Sv, porosity)
once, on a cube of four cells a side, and measures the minimum strut (1st percentile local
thickness, as a share of the pore size) and the apparent modulus (platen compression along z, as
a share of the solid's). Prints the table and the wall time; ``--write`` writes the file the
package ships (tests/test_design.py rebuilds two entries and compares). Timings on a shared 2-core
machine are noisy.
"""
from __future__ import annotations

import argparse
import json
import time

from implicit_scaffold import design_maps


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--write", action="store_true", help=f"write {design_maps.MAPS_FILE}")
    ap.add_argument("--only", choices=["paper", "struts"], default=None, help="one style (not with --write)")
    args = ap.parse_args(argv)
    if args.write and args.only:
        ap.error("--write writes every entry; drop --only")
    points = [p for p in design_maps.grid_points() if args.only in (None, p[0])]
    entries = []
    t0 = time.perf_counter()
    print(f"{'style':7s} {'Sf':>5s} {'Sv':>5s} {'P':>5s} {'strut/pore':>10s} {'E/Es':>9s} {'s':>6s}")
    for style, sf, sv, p in points:
        t1 = time.perf_counter()
        e = design_maps.measure_entry(style, sf, sv, p)
        entries.append(e)
        print(f"{style:7s} {sf:5g} {sv:5g} {p:5g} {e['min_strut_rel']:10.4g} {e['modulus_rel']:9.4g} "
              f"{time.perf_counter() - t1:6.1f}", flush=True)
    print(f"{len(entries)} entries in {time.perf_counter() - t0:.1f} s")
    if args.write:
        text = json.dumps({**design_maps.header(), "entries": entries}, separators=(",", ":"))
        design_maps.MAPS_FILE.write_text(text + "\n")
        print(f"wrote {design_maps.MAPS_FILE} ({len(text) + 1} bytes)")


if __name__ == "__main__":
    main()
