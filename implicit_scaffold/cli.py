"""Command line: ``implicit-scaffold generate``, ``implicit-scaffold info``.

A thin layer over the public API. Bad input prints one line on stderr and exits
with code 2; nothing is written then.
"""
from __future__ import annotations

import argparse
import sys
import time

from . import __version__
from .errors import ScaffoldError


def _size(text: str):
    parts = text.replace(",", " ").split()
    try:
        vals = [float(v) for v in parts]
    except ValueError:
        raise argparse.ArgumentTypeError(f"--size takes one or three lengths in mm, got {text!r}") from None
    return vals[0] if len(vals) == 1 else tuple(vals)


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, exit 2, as every other bad input
        self.exit(2, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="implicit-scaffold",
                     description="Porous, patient-shaped Voronoi bone scaffolds (units: mm).")
    parser.add_argument("--version", action="version", version=f"implicit_scaffold {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    g = sub.add_parser("generate", help="build a scaffold and write its mesh (or field) and JSON report")
    g.add_argument("-o", "--output", required=True,
                   help="output file: .stl .ply .obj .3mf (mesh) or .npy (signed distance); "
                        "the JSON report is written beside it")
    g.add_argument("--shape", default="box", choices=["box", "cylinder", "sphere"],
                   help="built-in patient shape (default: box)")
    g.add_argument("--size", type=_size, default=10.0,
                   help="shape size in mm: one length or three (x y z in quotes); default 10")
    pg = g.add_argument_group("patient geometry (instead of --shape)")
    pg.add_argument("--patient", metavar="FILE", default=None,
                    help="bone geometry: a mesh (.stl .obj .ply .off .3mf) or a volume (.nii .nii.gz .nrrd "
                         ".mha .mhd, or a folder holding a DICOM series)")
    pg.add_argument("--label", type=int, default=None, help="volume: keep this segmentation label")
    pg.add_argument("--threshold", type=float, default=None, help="volume: keep intensities >= HU")
    pg.add_argument("--units", choices=["mm", "cm", "m", "um"], default=None,
                    help="units of a mesh file (default mm; a warning says when the size suggests others)")
    pg.add_argument("--clip", type=float, nargs=6, metavar=("XMIN", "YMIN", "ZMIN", "XMAX", "YMAX", "ZMAX"),
                    default=None, help="keep the part of the bone inside this box (mm)")
    pg.add_argument("--cut-planes", type=float, nargs=12, default=None,
                    metavar=("PX", "PY", "PZ", "NX", "NY", "NZ", "QX", "QY", "QZ", "MX", "MY", "MZ"),
                    help="two osteotomy planes, point and normal each (mm); the segment between them is kept")
    pg.add_argument("--seeds-in", choices=["box", "patient"], default="box",
                    help="box: uniform in the bounding box (the paper); patient: only where the patient is, "
                         "plus one cell, with the seed count from the patient's volume (default box)")
    pg.add_argument("--skin", type=float, default=0.0, help="solid shell this thick at the patient surface (mm)")
    pg.add_argument("--smooth-cut", type=float, default=0.0,
                    help="width of a smooth instead of sharp intersection with the patient (mm)")
    n = g.add_mutually_exclusive_group()
    n.add_argument("--seeds", type=int, default=None, help="number of seeds (Voronoi cells)")
    n.add_argument("--pore-size", type=float, default=0.6,
                   help="target pore diameter Dp in mm; the seed count follows the paper's formula (default 0.6)")
    g.add_argument("--porosity", default="0.8",
                   help="target porosity in (0, 1), met by offsetting the surface, or 'none' to keep the "
                        "lattice as Sf and Sv make it (default 0.8)")
    g.add_argument("--sf", type=float, default=0.75, help="face scale factor Sf in (0, 1) (default 0.75)")
    g.add_argument("--sv", type=float, default=0.75, help="cell scale factor Sv in (0, 1) (default 0.75)")
    g.add_argument("--style", default="paper", choices=["paper", "struts"],
                   help="paper: pores and channels; struts: capsules on the Voronoi edges (default paper)")
    g.add_argument("--blend", type=float, default=None,
                   help="smoothing width k in mm; 0 keeps creases sharp (default: half the thin walls)")
    g.add_argument("--voxel", type=float, default=None, help="voxel size in mm (default: from the walls)")
    g.add_argument("--keep-fragments", action="store_true",
                   help="keep solid pieces not attached to the main body (removed by default)")
    g.add_argument("--seed", type=int, default=0, help="random seed; same inputs and seed, same bytes (default 0)")
    g.add_argument("--report", metavar="HTML", default=None,
                   help="also write a visual report: pictures, histograms, targets against measured values")
    g.add_argument("-q", "--quiet", action="store_true", help="print nothing but errors")

    sub.add_parser("info", help="versions and the OpenCL device")
    return parser


def _generate(args) -> int:
    from .pipeline import generate

    t0 = time.perf_counter()
    if args.report is not None:
        from .mesh import check_writable

        if not args.report.lower().endswith((".html", ".htm")):
            raise ScaffoldError(f"--report writes an HTML page; name it like report.html, not {args.report!r}")
        check_writable(args.report, formats=(".html", ".htm"))
    porosity = None if str(args.porosity).strip().lower() == "none" else args.porosity
    patient = None
    if args.patient is not None:
        from .mesh import check_writable

        check_writable(args.output)  # before a long load, not after
        from .patient_io import load_patient

        patient = load_patient(args.patient, label=args.label, threshold=args.threshold, units=args.units,
                               clip=args.clip, cut_planes=args.cut_planes)
    elif args.label is not None or args.threshold is not None or args.clip or args.cut_planes or args.units:
        raise ScaffoldError("--label, --threshold, --units, --clip and --cut-planes apply to a --patient FILE; "
                            "give one or drop them")
    result = generate(output=args.output, verbose=not args.quiet, patient=patient, shape=args.shape,
                      size=args.size, seeds_in=args.seeds_in, skin=args.skin, smooth_cut=args.smooth_cut,
                      seeds=args.seeds, pore_size=args.pore_size, porosity=porosity, sf=args.sf, sv=args.sv,
                      style=args.style, blend=args.blend, voxel=args.voxel, seed=args.seed,
                      remove_fragments=not args.keep_fragments)
    if args.report is not None:
        from .report import write_run_report

        write_run_report(result, args.report)
    if not args.quiet:
        r = result.report
        offset = (f"surface offset {r['surface_offset_mm']:+.4f} mm" if "surface_offset_mm" in r
                  else f"strut radius {r['strut_radius_mm']:.4f} mm")
        target = "none" if r["porosity_target"] is None else f"{r['porosity_target']:.3f}"
        lines = [
            f"wrote {args.output} and {result_json(args.output)}"
            + (f" and {args.report}" if args.report else ""),
            f"  seeds {r['seeds']}, Sf {r['sf']:g}, Sv {r['sv']:g}, style {r['style']}",
            f"  {offset}, blend {r['blend_mm']:.4f} mm",
            f"  voxel {r['voxel_mm']:.4f} mm, grid {'x'.join(str(v) for v in r['grid_shape'])}",
            f"  porosity: target {target}, closed form {r['porosity_closed_form']:.4f}, "
            f"voxels {r['porosity_voxel']:.4f}"
            + (f", mesh {r['porosity_mesh']:.4f}" if "porosity_mesh" in r else ""),
        ]
        if "triangles" in r:
            lines.append(f"  triangles {r['triangles']}, bodies {r['bodies']}, watertight {r['watertight']}")
        lines.append("  time: " + ", ".join(f"{k} {v:.2f} s" for k, v in r["timings_s"].items())
                     + f"; total {time.perf_counter() - t0:.1f} s")
        print("\n".join(lines))
    return 0


def result_json(output) -> str:
    from pathlib import Path

    return str(Path(output).with_suffix(".json"))


def _info(args) -> int:
    import numpy
    import pyopencl

    from . import opencl

    print(f"implicit_scaffold {__version__}")
    print(f"numpy {numpy.__version__}, pyopencl {pyopencl.VERSION_TEXT}")
    print(f"OpenCL device: {opencl.device().describe()}")
    print(f"kernels: {opencl.kernels_dir()}")
    return 0


def main(argv=None) -> int:
    """Entry point; returns the exit code (0, or 2 for bad input)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        if args.command == "generate":
            return _generate(args)
        return _info(args)
    except ScaffoldError as exc:
        print(f"implicit-scaffold: error: {exc}", file=sys.stderr)
        return 2
    except MemoryError:
        print("implicit-scaffold: error: out of memory; use a larger --voxel", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("implicit-scaffold: interrupted; no output written", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
