"""Command line: ``implicit-scaffold generate``, ``design``, ``analyze`` and ``info``.

A thin layer over the public API. Bad input prints one line on stderr and exits
with code 2; nothing is written then.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
import warnings
from pathlib import Path

from . import __version__
from .errors import ScaffoldError
from .io.formats import FIELD_WRITERS, IMAGE_STACKS, MESH_READERS, MESH_WRITERS, VOLUME_READERS, report_path


#: the build options' defaults (generate, slice): an option a graded build does not read is refused when its value
#: is not the default (:func:`_check_graded_options`)
BUILD_DEFAULTS = {"pore_size": 0.6, "seed_rule": "pore-size", "porosity": "0.8"}


def _listed(formats) -> str:
    """Extensions as the help text lists them."""
    return " ".join(formats)


def _size(text: str):
    parts = text.replace(",", " ").split()
    try:
        vals = [float(v) for v in parts]
    except ValueError:
        raise argparse.ArgumentTypeError(f"--size takes one or three lengths in mm, got {text!r}") from None
    return vals[0] if len(vals) == 1 else tuple(vals)


def _add_spacing(g) -> None:
    """--spacing, for every command that reads a volume (the patient's or a scaffold's)."""
    g.add_argument("--spacing", type=_spacing, default=None,
                   help='volume: voxel spacing of a file whose header states none: one or three mm, "x y z" '
                        "(given for a file that states one, it replaces it, with a warning)")


def _add_volume_choice(g) -> None:
    """--label, --threshold and --spacing: what of a volume is bone (a patient's, or the solid a command
    measures; :func:`~implicit_scaffold.fields.patient_volume.bone_mask`)."""
    g.add_argument("--label", default=None, metavar="N[,N...]",
                   help="volume: keep this segmentation label, or several (e.g. 30,31: a bone in pieces); other "
                        "labels are void")
    g.add_argument("--threshold", type=float, default=None,
                   help="volume: keep intensities >= this (HU, for a CT: bone is about 200 and above)")
    _add_spacing(g)


def _spacing(text: str):
    parts = text.replace(",", " ").split()
    try:
        vals = [float(v) for v in parts]
    except ValueError:
        vals = []
    if len(vals) not in (1, 3):
        raise argparse.ArgumentTypeError(f"--spacing takes one or three lengths in mm, got {text!r}")
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
                   help=f"output file: {_listed(MESH_WRITERS)} (mesh); "
                        f"{_listed(f for f in FIELD_WRITERS if f not in IMAGE_STACKS)} "
                        f"(signed distance, float32 mm) or {_listed(IMAGE_STACKS)} (binary solid, for ImageJ/BoneJ); "
                        "the JSON report is written beside it")
    g.add_argument("--report", metavar="HTML", default=None,
                   help="also write a visual report: pictures, histograms, targets against measured values")
    _add_build_options(g)
    g.add_argument("--tolerance", default=None, metavar="MM",
                   help="simplify the mesh with manifold3d within MM (e.g. 0.01): about half the triangles; the "
                        "report gives the distance between the surfaces and the porosity moved, as measured, and "
                        "warns beyond a quarter voxel or 0.1 points (default 0: every triangle kept)")
    g.add_argument("--design", metavar="JSON", default=None,
                   help="build with the parameters of a design.json (implicit-scaffold design); options given "
                        "here too override them")
    g.add_argument("--mechanics", action="store_true",
                   help="also measure the scaffold's stiffness (voxel FE): report section 'mechanics'")
    _add_mechanics_options(g)

    sl = sub.add_parser("slice", help="write the layer images a DLP/SLA printer takes (PNG stack), no mesh",
                        description="Build a scaffold (same options as generate) and write its layers as "
                                    "8-bit PNG images at the printer's pixel pitch and layer height, with "
                                    "anti-aliased edges from the field, and stack.json with the geometry.")
    sl.add_argument("-o", "--output", required=True, metavar="DIR",
                    help="a new folder for the layers (it appears only once the stack is complete)")
    sl.add_argument("--pixel", type=float, default=None, help="printer pixel pitch in mm (default: the voxel)")
    sl.add_argument("--layer", type=float, default=None, help="layer height in mm (default: the voxel)")
    _add_build_options(sl)

    sw = sub.add_parser("sweep", help="reproduce the paper's experiments (CSV + PNG per figure)",
                        description="Porosity against Sf and Sv (Fig. 10) and against the seed count (Fig. 11), "
                                    "seeds, pore size, interconnection, channel size and trabecular thickness "
                                    "against the target pore size (Fig. 13, 14, 17, 19), on the 10 mm cube.")
    sw.add_argument("-o", "--output", required=True, metavar="DIR", help="folder for the CSV and PNG files")
    sw.add_argument("--quick", action="store_true", help="a coarse version (about a minute on 2 cores)")
    sw.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    sw.add_argument("-q", "--quiet", action="store_true", help="print nothing but errors and warnings")

    a = sub.add_parser("analyze", help="voxel morphometry of any scaffold mesh or binary volume",
                       description="Measure a scaffold (from this tool or any other) or bone as bone "
                                   "morphometry does: strut thickness and pore diameter by maximal spheres, "
                                   "connectivity density, interconnected porosity, fragments, BS/BV.")
    _add_scaffold_file(a, f"a closed mesh ({_listed(MESH_READERS)}) or a volume "
                          f"({_listed(VOLUME_READERS + IMAGE_STACKS)}, a folder of .tif slices or a DICOM folder): "
                          "binary (solid = non-zero), a label map with --label or a CT with --threshold")
    a.add_argument("--region", metavar="FILE", default=None,
                   help="count porosity inside this patient, as generate does: a patient mesh or volume, or the "
                        "run's .json report (its patient, on its grid; then --voxel may be left out); default: "
                        "the mesh's bounding box")
    _add_measure_budget(a, "the measures")
    a.add_argument("-o", "--output", metavar="JSON", default=None, help="write the measures as JSON")
    a.add_argument("--report", metavar="HTML", default=None,
                   help="also write a visual report: picture, section, histograms, measures")
    a.add_argument("-q", "--quiet", action="store_true", help="print nothing but errors and warnings")

    c = sub.add_parser("check", help="print certificate: will this scaffold print, drain and let bone in?",
                       description="Check a scaffold (mesh, .npy field, or binary volume) against a printer "
                                   "profile: thinnest solid, narrowest throat, drainage, cell infiltration, "
                                   "sealed voids, floating solid, overhangs, and the same as built.")
    _add_scaffold_file(c, f"a closed mesh ({_listed(MESH_READERS)}), a .npy signed distance written by generate "
                          "(its .json beside it gives the voxel), or a volume: binary, a label map with --label or a "
                          "CT with --threshold")
    c.add_argument("--printer", required=True, metavar="NAME",
                   help=", ".join(_printer_names()) + ", or custom:min_strut=MM,min_throat=MM,...")
    _add_measure_budget(c, "the certificate")
    c.add_argument("-o", "--output", metavar="JSON", default=None, help="write the certificate as JSON")
    c.add_argument("--require-printable", action="store_true",
                   help="exit with code 3 (after writing the certificate) when it fails")
    c.add_argument("-q", "--quiet", action="store_true", help="print nothing but errors and warnings")
    me = sub.add_parser("mechanics", help="stiffness tensor, moduli and a platen compression test (voxel FE)",
                        description="The effective stiffness of a scaffold or a bone from its voxels: 6x6 tensor "
                                    "(Voigt, GPa), moduli, a compression between rigid platens, beside bone's.")
    _add_scaffold_file(me, f"a closed mesh ({_listed(MESH_READERS)}), a volume "
                           f"({_listed(VOLUME_READERS + IMAGE_STACKS)}, a folder of .tif slices or a DICOM folder: "
                           "binary, a label map with --label or a CT with --threshold) or a .npy field "
                           "(negative = solid)")
    _add_mechanics_options(me)
    me.add_argument("--max-memory", default=None, metavar="SIZE",
                    help="memory the run may hold, e.g. 4G or 800M (default: 4G, or 80%% of the free memory when "
                         "less); a binary STL's read is checked before it is read, the solve before the solve; a "
                         "refusal names the budget (and for the solve the voxel) that would do")
    me.add_argument("-o", "--output", metavar="JSON", default=None, help="write the results as JSON")
    me.add_argument("--report", metavar="HTML", default=None, help="also write a visual report")
    me.add_argument("-q", "--quiet", action="store_true", help="print nothing but errors and warnings")

    de = sub.add_parser("design", help="inverse design: targets in, generate's parameters out (design.json)",
                        description="Find the generator's parameters (style, Sf, Sv; the seed density and surface "
                                    "offset follow) that meet porosity, pore size, minimum strut and stiffness "
                                    "targets, by a few builds of a representative cube; verify them over random "
                                    "seeds. Exit code 3 when the targets conflict (the output names them and the "
                                    "nearest trade-off), or when the design built on --patient misses one. With --stiffness-from-ct: a scaffold graded so that its "
                                    "local modulus follows the bone's in the patient's CT.")
    de.add_argument("--porosity", type=float, default=None,
                    help="target porosity in (0, 1) (required, except with --stiffness-from-ct)")
    de.add_argument("--pore-size", type=float, required=True,
                    help="target mean pore size (polyhedron-sphere, as generate reports it), mm")
    de.add_argument("--min-strut", type=float, default=None,
                    help="thinnest strut allowed: the 1st percentile local thickness stays at or above it, mm")
    de.add_argument("--stiffness", default=None, metavar="MODULUS",
                    help="target apparent modulus, e.g. 3GPa or 800MPa (platen compression of the cube)")
    de.add_argument("--material", default="ti64", metavar="NAME",
                    help=f"the solid, for --stiffness: {' '.join(_material_names())} (default ti64)")
    de.add_argument("--printer", default=None, metavar="NAME",
                    help="a printer profile whose min_strut is the --min-strut (the larger of the two when both)")
    de.add_argument("--seeds", type=int, default=5,
                    help="random seeds of the verification (default 5; the CT design fits on 2 seeds a porosity)")
    dg = de.add_argument_group("the patient: the design built on it (or, with --stiffness-from-ct, graded from its "
                               "CT, the bone's modulus voxel by voxel)")
    dg.add_argument("--stiffness-from-ct", action="store_true",
                    help="target the bone's apparent modulus everywhere: the CT's density (--calibration) through the "
                         "site's density-modulus law (--site; Morgan, Bayraktar & Keaveny 2003), matched by the "
                         "porosity of the scaffold's measured modulus-porosity law; builds the graded scaffold")
    dg.add_argument("--calibration", type=float, nargs=2, default=None, metavar=("SLOPE", "INTERCEPT"),
                    help="density g/cm3 = SLOPE * HU + INTERCEPT (a phantom's linear calibration)")
    dg.add_argument("--site", default="pooled", metavar="SITE",
                    help="the density-modulus law: pooled vertebra proximal-tibia greater-trochanter femoral-neck "
                         "(Morgan et al. 2003; default pooled)")
    dg.add_argument("--patient", metavar="FILE", default=None,
                    help="the patient, as for generate: without --stiffness-from-ct the design is built on it once "
                         "more and measured (design.json's patient_check); with it, the patient's CT volume (.nii, "
                         ".nii.gz, .nrrd, .mha, .mhd or a DICOM folder)")
    _add_volume_choice(dg)
    _add_patient_cuts(dg)
    dg.add_argument("--max-memory", default=None, metavar="SIZE",
                    help="memory the build on the patient may hold, e.g. 4G or 800M (default: 4G, or 80%% of the "
                         "free memory when less)")
    dg.add_argument("--voxel", type=float, default=None,
                    help="voxel of the build on the patient, mm (default: the representative cube's, pore size / "
                         "16)")
    dg.add_argument("--scaffold", metavar="FILE", default=None,
                    help="write the scaffold built on the patient here, as generate -o does (default: built and "
                         "measured, not written)")
    de.add_argument("-o", "--output", required=True, metavar="JSON", help="where to write design.json")
    de.add_argument("-q", "--quiet", action="store_true", help="print nothing but errors and warnings")

    sub.add_parser("info", help="versions and the OpenCL device")
    return parser


def _add_scaffold_file(p, what: str) -> None:
    """The file argument of the commands that read a scaffold or bone, with its --voxel and what of a volume
    is solid (:func:`_add_volume_choice`)."""
    p.add_argument("file", help=what)
    p.add_argument("--voxel", type=float, default=None,
                   help="voxel size in mm: a mesh is voxelised at it (needed for a mesh); a volume is "
                        "resampled to it (default: the volume's own spacing)")
    _add_volume_choice(p)


def _add_mechanics_options(p) -> None:
    mg = p.add_argument_group("mechanics (voxel finite elements)")
    mg.add_argument("--material", default=None, metavar="NAME",
                    help=f"{' '.join(_material_names())} (default ti64; see implicit_scaffold.measure.mechanics.MATERIALS)")
    mg.add_argument("--E", dest="young", type=float, default=None, metavar="GPA",
                    help="the solid's Young's modulus in GPa (instead of, or overriding, --material)")
    mg.add_argument("--nu", type=float, default=None, metavar="V", help="the solid's Poisson's ratio, below 0.5")
    mg.add_argument("--boundary", choices=["auto", "periodic", "kinematic"], default="auto",
                    help="homogenization: periodic (a box sample), kinematic (a shaped one); auto tells them apart")
    mg.add_argument("--axis", choices=["x", "y", "z"], default="z", help="the compression axis (default z)")
    mg.add_argument("--mechanics-tol", dest="mechanics_tol", type=float, default=None, metavar="R",
                    help="the CG's relative residual, 1e-12 to 1e-3, the solves' only stop (default: 1e-6, or sooner "
                         "each solution's energy within 1e-5 of converged; the README's mechanics section measures "
                         "what each saves and costs)")
    mg.add_argument("--mechanics-voxel", type=float, default=None, metavar="MM",
                    help="the solve's voxel, sampled (trilinear) from the signed distance (generate's, or a .npy "
                         "field's); default: the field's own voxel when the solve fits --max-memory, else the "
                         "finest voxel that fits (the report's mechanics.voxel says which and why)")


def _mechanics_setup(args):
    """The material and the CG tolerance of a mechanics run, checked before any work."""
    from .measure.mechanics import check_tol, material

    return material(args.material, E=args.young, nu=args.nu), check_tol(args.mechanics_tol)


def _mechanics_lines(mech: dict) -> list[str]:
    from .io.report import solver_text

    E = mech["youngs_modulus_gpa"]
    G = mech["shear_modulus_gpa"]
    comp = mech["compression"]
    lines = [f"  mechanics: {mech['material']['name']} (E {mech['material']['E_gpa']:g} GPa, nu "
             f"{mech['material']['nu']:g}), solid fraction {mech['solid_fraction']:.4f}, "
             f"{mech['boundary_conditions'].split(' (')[0]} boundary conditions",
             f"  Young's moduli (GPa): x {E['x']:.4g}, y {E['y']:.4g}, z {E['z']:.4g}; shear: yz {G['yz']:.4g}, "
             f"xz {G['xz']:.4g}, xy {G['xy']:.4g}; anisotropy index "
             + ("—" if mech["anisotropy_index"] is None else f"{mech['anisotropy_index']:.3g}"),
             f"  compression along {comp['axis']}: apparent modulus {comp['apparent_modulus_gpa']:.4g} GPa",
             f"  bone: {mech['stress_shielding']}",
             f"  solver: {solver_text(mech['solver'])}"]
    lines += [f"  note: {n}" for n in mech["notes"]]
    return lines


def _only_with(options: list, what: str, needed: str) -> str:
    """The refusal of `options` given without `needed`: "--voxel applies to ...; add ... or drop it"."""
    many = len(options) > 1
    return (f"{', '.join(options)} {'apply' if many else 'applies'} to {what}; add {needed} or drop "
            f"{'them' if many else 'it'}")


def _add_measure_budget(parser, what: str) -> None:
    parser.add_argument("--max-memory", default=None, metavar="SIZE",
                        help="memory the run may hold, e.g. 4G or 800M (default: 4G, or 80%% of the free memory when "
                             f"less); a binary STL's read is checked before it is read, {what} on the grid before "
                             "they start; a refusal names the budget (and the voxel, where --voxel sets it) that "
                             "would do")


def _check_json_output(args) -> None:
    """`-o` of analyze, check and mechanics: a .json that can be written, and not the run's report beside FILE, which
    they read (its grid: the mesh voxelised on it, a field's walls): overwritten, the next read of FILE lost it."""
    if args.output is None:
        return
    from .io.files import check_writable

    check_writable(args.output, formats=(".json",))
    beside = report_path(args.file)
    if beside.is_file() and Path(args.output).resolve() == beside.resolve():
        raise ScaffoldError(f"-o {args.output} is the report generate wrote beside {Path(args.file).name}, which this "
                            "command reads; give another name, e.g. -o " + beside.with_name(beside.stem + "_"
                                                                                          + args.command + ".json").name)


def _mechanics(args) -> int:
    from .measure.mechanics import load_sample

    t0 = time.perf_counter()
    mat, tol = _mechanics_setup(args)
    _check_json_output(args)
    if args.report is not None:
        _check_report(args.report)
    from .progress import Progress

    # a whole micro-CT reads and sets up for some 40 s before the CG's first note; a quick run's lines
    # (and an error's) stay as they were
    progress = Progress(not args.quiet)
    with progress.stage("reading", Path(args.file).name, after=2.0):
        sample, kind = load_sample(args.file, voxel=args.voxel, spacing=args.spacing,
                                   mechanics_voxel=args.mechanics_voxel, max_memory=args.max_memory,
                                   boundary=args.boundary, label=args.label, threshold=args.threshold)
    solid, h = sample.solid, sample.voxel
    from .measure.mechanics import measure_sample, solve_accuracy, solve_goal

    detail = (f"{'x'.join(str(v) for v in solid.shape)} voxels of {h:.4g} mm: the platens' compression, then the "
              "homogenization's six load cases")
    with progress.stage("solving", detail, after=2.0):
        report, comp = measure_sample(sample, mat, boundary=args.boundary, axis="xyz".index(args.axis),
                                      progress=progress.solver(goal=solve_goal(tol), accuracy=solve_accuracy(tol)),
                                      tol=tol)
    report = {"version": __version__, "source": Path(args.file).name, "kind": kind, **report}
    if sample.selection is not None:
        report["selection"] = sample.selection
    if args.output is not None:
        from .io.files import write_json

        write_json(report, args.output)
    if args.report is not None:
        from .io.report import write_mechanics_report

        write_mechanics_report(report, comp, h, args.report)
    if not args.quiet:
        grid = "x".join(str(v) for v in solid.shape)
        chosen = f" ({sample.selection})" if sample.selection is not None else ""
        lines = [f"{report['source']}: {kind}{chosen}, voxel {h:.4g} mm, grid {grid}"] + _mechanics_lines(report)
        written = [p for p in (args.output, args.report) if p]
        if written:
            lines.append("wrote " + " and ".join(written))
        lines.append(f"  time {time.perf_counter() - t0:.1f} s")
        print("\n".join(lines))
    return 0


def _add_patient_cuts(pg) -> None:
    """A mesh patient's units and the part of the bone kept: generate's and design's."""
    from .io.patient_io import UNITS

    pg.add_argument("--units", choices=list(UNITS), default=None,
                    help="units of a mesh file (in: inch; default the unit the file declares (3MF) or mm; a warning "
                         "says when the size suggests others)")
    pg.add_argument("--clip", type=float, nargs=6, metavar=("XMIN", "YMIN", "ZMIN", "XMAX", "YMAX", "ZMAX"),
                    default=None, help="keep the part of the bone inside this box (mm)")
    pg.add_argument("--cut-planes", type=float, nargs=12, default=None,
                    metavar=("PX", "PY", "PZ", "NX", "NY", "NZ", "QX", "QY", "QZ", "MX", "MY", "MZ"),
                    help="two osteotomy planes, point and normal each (mm); the segment between them is kept")


def _add_build_options(g) -> None:
    """The options that say what to build, shared by generate and slice."""
    g.add_argument("--shape", default="box", choices=["box", "cylinder", "sphere"],
                   help="built-in patient shape (default: box)")
    g.add_argument("--size", type=_size, default=10.0,
                   help="shape size in mm: one length or three (x y z in quotes); default 10")
    pg = g.add_argument_group("patient geometry (instead of --shape)")
    pg.add_argument("--patient", metavar="FILE", default=None,
                    help=f"bone geometry: a mesh ({_listed(MESH_READERS)}) or a volume ({_listed(VOLUME_READERS)}, "
                         "or a folder holding a DICOM series)")
    _add_volume_choice(pg)
    _add_patient_cuts(pg)
    pg.add_argument("--seeds-in", choices=["box", "patient"], default=None,
                    help="box: uniform in the bounding box (the paper); patient: only where the patient is, "
                         "plus one cell, with the seed count from the patient's volume (default: patient with "
                         "--patient, box for --shape)")
    pg.add_argument("--skin", type=float, default=0.0, help="solid shell this thick at the patient surface (mm)")
    pg.add_argument("--smooth-cut", type=float, default=0.0,
                    help="width of a smooth instead of sharp intersection with the patient (mm)")
    n = g.add_mutually_exclusive_group()
    n.add_argument("--seeds", type=int, default=None, help="number of seeds (Voronoi cells)")
    n.add_argument("--pore-size", type=float, default=BUILD_DEFAULTS["pore_size"],
                   help="target pore size in mm: the mean polyhedron-sphere pore size that the report measures "
                        "(see --seed-rule) (default 0.6)")
    g.add_argument("--seed-rule", choices=["pore-size", "paper"], default=BUILD_DEFAULTS["seed_rule"],
                   help="pore-size: the seed count is solved so that the measured mean pore size is --pore-size; "
                        "paper: the paper's n = V P / (pi Dp^3 / 6), whose measured pores come out smaller; "
                        "a graded run (--grade, --calibration) applies the rule to the local pore size "
                        "(default pore-size)")
    g.add_argument("--porosity", default=BUILD_DEFAULTS["porosity"],
                   help="target porosity in (0, 1), met by offsetting the surface, or 'none' to keep the "
                        "lattice as Sf and Sv make it (default 0.8)")
    g.add_argument("--sf", type=float, default=0.75, help="face scale factor Sf in (0, 1) (default 0.75)")
    g.add_argument("--sv", type=float, default=0.75, help="cell scale factor Sv in (0, 1) (default 0.75)")
    g.add_argument("--style", default="paper", choices=["paper", "struts"],
                   help="paper: pores and channels; struts: capsules on the Voronoi edges (default paper)")
    g.add_argument("--blend", type=float, default=None,
                   help="smoothing width k in mm; 0 keeps creases sharp (default: half the thin walls)")
    g.add_argument("--voxel", type=float, default=None, help="voxel size in mm (default: from the walls)")
    frag = g.add_mutually_exclusive_group()
    frag.add_argument("--remove-fragments", dest="keep_fragments", action="store_false",
                      help="drop solid pieces not attached to the main body (the default)")
    frag.add_argument("--keep-fragments", dest="keep_fragments", action="store_true",
                      help="keep solid pieces not attached to the main body")
    g.set_defaults(keep_fragments=False)
    voids = g.add_mutually_exclusive_group()
    voids.add_argument("--fill-sealed-voids", dest="keep_sealed_voids", action="store_false",
                       help="fill void pieces that do not reach the outside: closed cavities where resin or "
                            "powder stays trapped (the default)")
    voids.add_argument("--keep-sealed-voids", dest="keep_sealed_voids", action="store_true",
                       help="keep them (they are counted in the report either way)")
    g.set_defaults(keep_sealed_voids=False)
    g.add_argument("--seed", type=int, default=0, help="random seed; same inputs and seed, same bytes (default 0)")
    gg = g.add_argument_group("graded scaffolds (small pores at the cortex, large in the core)")
    gg.add_argument("--grade", default=None, metavar="DEPTH:SIZE,...",
                    help='pore size against depth below the patient surface, mm, linear between: "0:0.3,2:0.8" '
                         "is 0.3 mm pores at the surface, 0.8 mm from 2 mm deep; the local seed density follows "
                         "--seed-rule (pore-size: the cells measure these sizes) and --porosity is met in every "
                         "depth bin")
    gg.add_argument("--calibration", type=float, nargs=2, default=None, metavar=("SLOPE", "INTERCEPT"),
                    help="grade from the patient's CT (--patient a CT volume): density g/cm3 = SLOPE * HU + "
                         "INTERCEPT, porosity = 1 - density / 1.8 within 0.5..0.9, pore size 0.3..0.8 mm "
                         "with it; replaces --porosity")
    gg.add_argument("--relax", type=int, default=0, metavar="N",
                    help="N Lloyd iterations on the graded seeds: a narrower pore-size spread (default 0)")
    gg.add_argument("--weighted", action="store_true",
                    help="power (Laguerre) cells weighted by the local target pore size: cells next to a "
                         "change of pore size keep their own size")
    cg = g.add_argument_group("print certificate")
    cg.add_argument("--printer", default=None, metavar="NAME",
                    help="certify what was built for a printer: " + ", ".join(_printer_names())
                         + ", or custom:min_strut=MM,min_throat=MM,layer=MM,overhang=DEG,drain=MM,deviation=MM,"
                           "axis=+z; the certificate goes in the JSON under print_check")
    cg.add_argument("--require-printable", action="store_true",
                    help="exit with code 3 (after writing everything) when the certificate fails")
    cg.add_argument("--repair", action="store_true",
                    help="before the mesh, thicken struts thinner than the printer's minimum and open throats its "
                         "drain cannot pass, by local offsets of the field, keeping the porosity; the JSON's repair "
                         "says what changed and what could not be met (needs --printer; a run in slabs repairs slab by "
                         "slab, the same field)")
    rg = g.add_argument_group("memory and cluster")
    rg.add_argument("--max-memory", default=None, metavar="SIZE",
                    help="memory the run may hold, e.g. 4G or 800M (default: 4G, or 80%% of the free memory when "
                         "less); a grid that does not fit whole is built in slabs and streamed to the output, same "
                         "bytes; a budget too small is refused before the work, naming one that would do")
    rg.add_argument("--scheduler", default=None, metavar="ADDRESS",
                    help="run the slabs on a dask.distributed scheduler (tcp://host:8786); same bytes out")
    rg.add_argument("--workers", type=int, default=1, metavar="N",
                    help="run the slabs' lattice passes in N local worker processes (the run goes in slabs, at "
                         "least one per worker); their memory counts against --max-memory; same bytes out "
                         "(default 1: this process)")
    g.add_argument("-q", "--quiet", action="store_true", help="print nothing but errors and warnings")


def _material_names() -> list[str]:
    from .measure.mechanics import MATERIALS

    return list(MATERIALS)


def _printer_names() -> list[str]:
    from .measure.printability import profiles

    return list(profiles())


def _check_report(path) -> None:
    from .io.files import check_writable

    if not path.lower().endswith((".html", ".htm")):
        raise ScaffoldError(f"--report writes an HTML page; name it like report.html, not {path!r}")
    check_writable(path, formats=(".html", ".htm"), option="--report")


def _check_graded_options(args) -> None:
    """Refuse the options a graded build replaces, where the command line changed them: --calibration sets the
    porosity and the pore sizes from the CT, --grade the pore sizes by depth; they were dropped without a word (the
    same bytes as without them). --seed-rule is not one: it turns each local pore size into a seed density."""
    designed = getattr(args, "from_design", set())  # a design.json's parameters (a CT design holds a pore size)
    changed = [o for o, key in (("--porosity", "porosity"), ("--pore-size", "pore_size"))
               if key not in designed and str(getattr(args, key)).strip().lower() != str(BUILD_DEFAULTS[key]).lower()]
    if args.calibration is not None and changed:
        raise ScaffoldError(f"--calibration sets the porosity and the pore sizes from the CT; drop {' and '.join(changed)}")
    changed = [o for o in changed if o != "--porosity"]
    if args.grade is not None and changed:
        raise ScaffoldError(f"--grade sets the pore sizes by depth (and the seed count with them); drop "
                            f"{' and '.join(changed)}")


def _build(args, *, output=None, mesh=True, morphometry=True, slices=None):
    """Run the pipeline with the build options of `args` (generate and slice share them)."""
    from .pipeline import generate
    from .specs import GridSpec, LatticeSpec, Outputs

    _check_graded_options(args)
    porosity = None if str(args.porosity).strip().lower() == "none" else args.porosity
    # the specs check every option now, before a patient or a CT is read
    lattice = LatticeSpec(style=args.style, seeds=args.seeds, pore_size=args.pore_size, seed_rule=args.seed_rule,
                          seeds_in=args.seeds_in, porosity=porosity, sf=args.sf, sv=args.sv, blend=args.blend,
                          seed=args.seed, remove_fragments=not args.keep_fragments,
                          fill_sealed_voids=not args.keep_sealed_voids, grade=args.grade,
                          calibration=args.calibration, relax=args.relax, weighted=args.weighted)
    # the slabs are what a cluster runs
    grid = GridSpec(voxel=args.voxel, max_memory=args.max_memory, tiled=True if args.scheduler is not None else None,
                    workers=args.workers, scheduler=args.scheduler)
    mechanics = None
    if getattr(args, "mechanics", False):
        from .specs import MechanicsSpec

        mechanics = MechanicsSpec(args.material, E=args.young, nu=args.nu, voxel=args.mechanics_voxel,
                                  boundary=args.boundary, axis=args.axis, tol=args.mechanics_tol)
    outputs = Outputs(output, mesh=mesh, morphometry=morphometry, slices=slices, printer=args.printer,
                      repair=getattr(args, "repair", False), tolerance=getattr(args, "tolerance", None),
                      mechanics=mechanics)
    patient = None
    if args.patient is not None:
        from .io.files import check_writable

        if output is not None:
            check_writable(output)  # before a long load, not after
        from .io.patient_io import load_patient

        patient = load_patient(args.patient, label=args.label, threshold=args.threshold, units=args.units,
                               clip=args.clip, cut_planes=args.cut_planes, spacing=args.spacing)
    elif (args.label is not None or args.threshold is not None or args.clip or args.cut_planes or args.units
          or args.spacing is not None):
        raise ScaffoldError("--label, --threshold, --spacing, --units, --clip and --cut-planes apply to a "
                            "--patient FILE; give one or drop them")
    ct = None
    if args.calibration is not None:
        from .geometry.grade import load_ct

        if args.label is not None:
            # a label map's numbers read as Hounsfield units: label 31 became 31 HU, every pore the largest
            raise ScaffoldError("--calibration reads a CT's intensities (HU); --label names a segmentation's bone, "
                                "whose label numbers are no intensities: give the CT as --patient with --threshold")
        ct = load_ct(_ct_source(args.patient, "--calibration reads the CT intensities of --patient"))
    return generate(lattice=lattice, grid=grid, outputs=outputs, patient=patient, shape=args.shape, size=args.size,
                    skin=args.skin, smooth_cut=args.smooth_cut, ct=ct, verbose=not args.quiet)


def _ct_source(source, what: str):
    """`source` when it names a CT volume (a volume file or a DICOM folder); else a ScaffoldError saying `what`."""
    from .io.patient_io import VOLUME_EXTENSIONS

    if source is None or not (Path(source).is_dir() or str(source).lower().endswith(VOLUME_EXTENSIONS)):
        raise ScaffoldError(f"{what}; give a CT volume (.nii, .nii.gz, .nrrd, .mha, .mhd or a DICOM folder)")
    return source


def _repair_lines(rep: dict) -> list[str]:
    """The summary's lines for --repair: what moved, the figures before and after, what does not hold."""
    def share(x):
        return "n/a" if x is None else f"{100 * x:.1f} %"

    s, d = rep["thin_strut_share"], rep["undrained_pore_share"]
    lines = [f"  repair ({rep['printer']}, {rep['rounds']} rounds): {rep['grown_mm3']:.4g} mm3 made solid, "
             f"{rep['opened_mm3']:.4g} mm3 opened; porosity {rep['porosity']['before']:.4f} -> "
             f"{rep['porosity']['after']:.4f}; solid in struts below the minimum {share(s['before'])} -> "
             f"{share(s['after'])}; void in pores the drain cannot reach {share(d['before'])} -> {share(d['after'])}"]
    lines += [f"    cannot: {why}" for why in rep["why"]]
    return lines


def _unresolved_text(cert: dict) -> str:
    """Where the certificate's voxels cannot tell whether thin solid meets the minimum strut, says so."""
    unresolved = cert["thinnest_mm"].get("unresolved_share") or 0.0
    if unresolved <= 0.01:
        return ""
    h, need = cert["voxel_mm"], cert["printer"]["min_strut_mm"]
    return (f" ({100 * unresolved:.1f} % of the solid is 1 to 3 voxels thick: at {h:.3g} mm voxels it cannot be "
            f"told from {need:g} mm; a voxel of {need / 4:.3g} mm or finer resolves it)")


def _certificate_lines(cert: dict) -> list[str]:
    """The certificate's summary: one line per check, its figure and its verdict."""
    v = cert["verdict"]
    p = cert["printer"]

    def share(x):
        return "n/a" if x is None else f"{100 * x:.1f} %"

    return [
        f"  print check ({p['name']}): {v['overall'].upper()}",
        f"    thinnest solid: min {cert['thinnest_mm']['min']:.3f} mm, 1st percentile {cert['thinnest_mm']['p1']:.3f} mm, "
        f"{share(cert['below_min_strut_share'])} of the solid below {p['min_strut_mm']:g} mm: {v['thinnest']}"
        + _unresolved_text(cert),
        f"    throat: {cert['throat_mm']:.3f} mm (min {p['min_throat_mm']:g} mm): {v['throat']}; void reached by the "
        f"{p['drain_mm']:g} mm drain {share(cert['void_reached_by_drain_share'])}: {v['drain']}; by 100 um cells "
        f"{share(cert['void_reached_by_100um_share'])}: {v['cell_infiltration']}",
        f"    sealed voids {cert['sealed_voids']['count']} ({cert['sealed_voids']['volume_mm3']:.4g} mm3): "
        f"{v['sealed_voids']}; floating solid {cert['floating_solid']['count']} "
        f"({cert['floating_solid']['volume_mm3']:.4g} mm3): {v['floating_solid']}",
        f"    overhangs below {p['overhang_deg']:g} deg along {cert['build_axis']}: {share(cert['overhang_share'])}: "
        f"{v['overhang']} (best axis {cert['best_build_axis']}: "
        f"{share(cert['overhang_share_by_axis'][cert['best_build_axis']])})",
        f"    as built (+{cert['as_built']['deviation_mm']:g} mm): porosity {cert['as_built']['porosity']:.4f}, "
        f"throat {cert['as_built']['throat_mm']:.3f} mm: {v['as_built']}",
    ]


def _check(args) -> int:
    from .measure.morphometry import read_scaffold
    from .measure.printability import certificate, certificate_memory, printer_profile
    from .progress import Progress
    from .run.memory import budget

    t0 = time.perf_counter()
    profile = printer_profile(args.printer)
    _check_json_output(args)
    # a stage's line once it has run 2 s (and a line every 30 s off a terminal): a femur's check at 0.2 mm runs
    # for minutes; a quick run's lines (and an error's) stay as they were
    progress = Progress(not args.quiet)
    with progress.stage("reading", Path(args.file).name, after=2.0):
        scaffold = read_scaffold(args.file, voxel=args.voxel, spacing=args.spacing, label=args.label,
                                 mesh_field=True, threshold=args.threshold, max_memory=budget(args.max_memory),
                                 work=certificate_memory())
    detail = f"{'x'.join(str(v) for v in scaffold.solid.shape)} voxels of {scaffold.voxel:.4g} mm"
    with progress.stage("certifying", detail, after=2.0):
        cert = certificate(scaffold.solid, scaffold.voxel, profile, field=scaffold.field, region=scaffold.region,
                           origin=scaffold.origin, exact_distance=scaffold.exact_distance)
    cert.update({"source": Path(args.file).name, "region": scaffold.region_name,
                 "timings_s": {"check": round(time.perf_counter() - t0, 4)}})
    if scaffold.axes:
        cert["axes"] = scaffold.axes  # a volume's index axes put on the world's x, y, z
    if args.output is not None:
        from .io.files import write_json

        write_json(cert, args.output)
    if not args.quiet:
        lines = [f"{cert['source']}: voxel {cert['voxel_mm']:.4g} mm, grid "
                 f"{'x'.join(str(v) for v in cert['grid_shape'])}, region {scaffold.region_name}, "
                 f"porosity {cert['porosity']:.4f}" + (f"; {scaffold.axes}" if scaffold.axes else "")]
        lines += _certificate_lines(cert)
        if args.output:
            lines.append(f"wrote {args.output}")
        lines.append(f"  time {time.perf_counter() - t0:.1f} s")
        print("\n".join(lines))
    return 3 if args.require_printable and cert["verdict"]["overall"] == "fail" else 0


def _apply_design(args) -> None:
    """Fill `args` from a design.json's parameters, where the command line left the default."""
    from .design import load_parameters

    params = load_parameters(args.design)
    defaults = build_parser().parse_args(["generate", "-o", "x.stl"])
    args.from_design = set()  # what the design set: not the user's to be told to drop (_check_graded_options)
    for key, value in params.items():
        if key == "porosity":
            value = str(value)
        if getattr(args, key) == getattr(defaults, key):
            setattr(args, key, value)
            args.from_design.add(key)


def _given(args, *options: str) -> list[str]:
    """Those of `options` (as typed: ``"--cut-planes"``) that the command line set."""
    return [o for o in options if getattr(args, o[2:].replace("-", "_")) is not None]


def _design_min_strut(args) -> float | None:
    """`--min-strut`, raised to `--printer`'s profile's ``min_strut`` (mm) when one is named."""
    if args.printer is None:
        return args.min_strut
    from .measure.printability import printer_profile

    floor = printer_profile(args.printer).min_strut_mm
    return floor if args.min_strut is None else max(args.min_strut, floor)


def _design(args) -> int:
    from .design import (Targets, check_on_patient, check_targets, conflict_message, design, parse_stiffness,
                         patient_check_message)
    from .errors import positive_mm
    from .progress import Progress

    t0 = time.perf_counter()
    from .io.files import check_writable, write_json

    check_writable(args.output, formats=(".json",))
    if args.stiffness_from_ct:
        return _design_from_ct(args, t0)
    ct_only = _given(args, "--calibration") + (["--site"] if args.site != "pooled" else [])
    if ct_only:
        raise ScaffoldError(_only_with(ct_only, "a design graded from the CT", "--stiffness-from-ct"))
    patient_only = _given(args, "--scaffold", "--voxel", "--max-memory", "--units", "--clip", "--cut-planes",
                          "--threshold", "--label", "--spacing")
    if patient_only and args.patient is None:
        raise ScaffoldError(_only_with(patient_only, "the build on the patient", "--patient FILE"))
    if args.porosity is None:
        raise ScaffoldError("design needs --porosity (or --stiffness-from-ct, which takes it from the CT)")
    min_strut = _design_min_strut(args)
    targets = Targets(porosity=args.porosity, pore_size=args.pore_size, min_strut=min_strut,
                      stiffness=None if args.stiffness is None else parse_stiffness(args.stiffness),
                      material=args.material)
    check_targets(targets)  # bad input refused before the stage line
    patient = None
    if args.patient is not None:
        from .io.patient_io import load_patient

        if args.voxel is not None:
            positive_mm("voxel", args.voxel, example="0.05")
        if args.scaffold is not None:
            check_writable(args.scaffold)
        if args.max_memory is not None:
            from .run.memory import budget

            budget(args.max_memory)  # a bad size refused before the design
        patient = load_patient(args.patient, label=args.label, threshold=args.threshold, units=args.units,
                               clip=args.clip, cut_planes=args.cut_planes, spacing=args.spacing)
    prog = Progress(not args.quiet)
    with prog.stage("design", "forward builds of a representative cube, then the check over seeds"):
        d = design(targets, seeds=args.seeds, progress=prog)
    check = None
    if patient is not None:
        with prog.stage("patient check", "the design built on the patient and measured"):
            check = check_on_patient(d, patient, voxel=args.voxel, output=args.scaffold, max_memory=args.max_memory,
                                     progress=prog)
    # feasible is the representative volume's; a target missed on the patient is said beside it (a design.json
    # read "feasible: true" where its run exited 3)
    met_on_patient = None if check is None else bool(all(check["met"].values()))
    out = {"version": __version__, **d.to_json(), "printer": args.printer,
           **({"patient_check": check, "met_on_patient": met_on_patient} if check is not None else {}),
           "timings_s": {"design": round(time.perf_counter() - t0, 3)}}
    write_json(out, args.output)
    if not args.quiet:
        p = d.parameters
        verdict = "feasible" if d.feasible else "INFEASIBLE"
        if met_on_patient is False:
            verdict += " on the representative volume, MISSED on the patient"
        lines = [f"wrote {args.output}: {verdict}",
                 f"  parameters: style {p['style']}, Sf {p['sf']:g}, Sv {p['sv']:g}, porosity {p['porosity']:g}, "
                 f"pore size {p['pore_size']:g} mm, voxel {p['voxel']:.4g} mm",
                 f"  {d.representative_volume['builds']} forward builds, checked over "
                 f"{len(d.representative_volume['seeds'])} seeds (mean, min..max):"]
        for k, v in d.achieved.items():
            # the thinnest strut is measured whether or not a minimum was asked
            target = f"target {d.targets[k]:g}" if d.targets.get(k) is not None else "no target"
            lines.append(f"    {k}: {target}, achieved {v['mean']:.4g} ({v['min']:.4g}..{v['max']:.4g})")
        if not d.feasible:
            lines.append("  " + conflict_message(d))
        if check is not None:
            lines.append("  " + patient_check_message(check, d.targets))
            lines += [f"    note: {n}" for n in check["notes"]]
            if args.scaffold is not None:
                lines.append(f"  wrote {args.scaffold}")
        lines.append(f"  time {time.perf_counter() - t0:.1f} s")
        print("\n".join(lines))
    return 0 if d.feasible and (check is None or all(check["met"].values())) else 3


def _design_from_ct(args, t0: float) -> int:
    """``design --stiffness-from-ct``: every input checked before the CT is read, then the design."""
    from .design import Targets, check_targets, design_from_ct
    from .io.files import check_writable, write_json
    from .geometry.grade import load_ct, parse_calibration
    from .measure.mechanics import density_modulus
    from .io.patient_io import load_patient
    from .progress import Progress

    if args.stiffness is not None:
        raise ScaffoldError("--stiffness is one modulus, --stiffness-from-ct the bone's everywhere: give one")
    not_ct = _given(args, "--units", "--clip", "--cut-planes", "--max-memory")
    if not_ct:
        raise ScaffoldError(f"{', '.join(not_ct)} are not taken with --stiffness-from-ct yet; crop the CT or drop them")
    if args.porosity is not None:
        raise ScaffoldError("--stiffness-from-ct takes the porosity from the CT (the bone's modulus); drop --porosity")
    if args.calibration is None:
        raise ScaffoldError("--stiffness-from-ct needs --calibration SLOPE INTERCEPT (density g/cm3 = SLOPE * HU + "
                            "INTERCEPT)")
    calibration = parse_calibration(args.calibration)
    density_modulus(args.site)
    source = _ct_source(args.patient, "--stiffness-from-ct reads the patient's CT (--patient)")
    min_strut = _design_min_strut(args)
    # the porosity is the CT's: 0.5 stands in for it where only the pore size, strut and material are checked
    check_targets(Targets(porosity=0.5, pore_size=args.pore_size, min_strut=min_strut, material=args.material))
    if args.scaffold is not None:
        check_writable(args.scaffold)
    patient = load_patient(source, label=args.label, threshold=args.threshold, spacing=args.spacing)
    ct = load_ct(source)
    prog = Progress(not args.quiet)
    with prog.stage("design", "forward builds of a representative cube (the modulus-porosity law), then the "
                              "graded build on the patient"):
        d = design_from_ct(ct, patient, calibration=calibration, site=args.site, pore_size=args.pore_size,
                           material=args.material, min_strut=min_strut, voxel=args.voxel,
                           output=args.scaffold, progress=prog)
    out = {"version": __version__, **d.to_json(), "printer": args.printer,
           "timings_s": {"design": round(time.perf_counter() - t0, 3)}}
    write_json(out, args.output)
    if not args.quiet:
        rel = d.representative_volume["modulus_porosity"]
        lines = [f"wrote {args.output}: {'feasible' if d.feasible else 'INFEASIBLE'}",
                 f"  bone: {d.targets['stiffness_from_ct']['law']}",
                 f"  scaffold (measured, {d.representative_volume['builds']} forward builds): E = "
                 f"{rel['solid_gpa']:g} * {rel['c']:.4g} (1 - P)^{rel['n']:.3f} GPa over porosity "
                 f"{rel['porosity_range'][0]:g}..{rel['porosity_range'][1]:g}",
                 "  graded build, per target-porosity bin: target -> measured porosity, bone -> scaffold modulus:"]
        for row in d.achieved["porosity_by_target"]:
            lines.append(f"    {row['porosity_target_mean']:.4f} -> {row['porosity']:.4f}, {row['bone_modulus_gpa']:.4g}"
                         f" -> {row['scaffold_modulus_at_porosity_gpa']:.4g} GPa ({row['voxels']} voxels)")
        for name, t in d.tradeoff.items():
            lines.append(f"  conflict {name}: " + ", ".join(f"{k} {v}" for k, v in t.items()))
        if args.scaffold is not None:
            lines.append(f"  wrote {args.scaffold}")
        lines.append(f"  time {time.perf_counter() - t0:.1f} s")
        print("\n".join(lines))
    return 0 if d.feasible else 3


def _generate(args) -> int:
    t0 = time.perf_counter()
    if args.design is not None:
        _apply_design(args)
    if args.report is not None:
        _check_report(args.report)
    if not args.mechanics:
        # the mechanics options mean nothing without the solve: taken without a word, a typo (--nu 0.7) passed
        unused = [o for o, v in (("--mechanics-voxel", args.mechanics_voxel), ("--mechanics-tol", args.mechanics_tol),
                                 ("--material", args.material), ("--E", args.young), ("--nu", args.nu),
                                 ("--boundary", None if args.boundary == "auto" else args.boundary),
                                 ("--axis", None if args.axis == "z" else args.axis)) if v is not None]
        if unused:
            raise ScaffoldError(f"{unused[0]} sets --mechanics' solve; add --mechanics or drop it")
    result = _build(args, output=args.output)
    comp = result.compression
    if args.report is not None:
        from .io.report import write_run_report

        extra = None
        if comp is not None:
            from .io.report import strain_section_image

            h = result.report["mechanics"]["voxel"]["voxel_mm"]
            extra = {"compression: von Mises strain, middle section": strain_section_image(comp, h)}
        write_run_report(result, args.report, extra_images=extra)
    if not args.quiet:
        r = result.report
        offset = (f"surface offset {r['surface_offset_mm']:+.4f} mm" if "surface_offset_mm" in r
                  else f"strut radius {r['strut_radius_mm']:.4f} mm")
        target = "none" if r["porosity_target"] is None else f"{r['porosity_target']:.3f}"
        lines = [
            f"wrote {args.output} and {report_path(args.output)}"
            + (f" and {args.report}" if args.report else ""),
            _seeds_line(r),
            f"  {offset}, blend {r['blend_mm']:.4f} mm",
            f"  voxel {r['voxel_mm']:.4f} mm, grid {'x'.join(str(v) for v in r['grid_shape'])}",
            _porosity_line(r, target),
        ]
        if "triangles" in r:
            lines.append(f"  triangles {r['triangles']}, bodies {r['bodies']}, watertight {r['watertight']}"
                         + (f", file {r['file_size_bytes'] / 1e6:.1f} MB" if "file_size_bytes" in r else ""))
        if r.get("simplification"):
            lines.append(_simplification_line(r["simplification"]))
        sealed = r.get("sealed_voids")
        if sealed and sealed["count"]:
            lines.append(f"  sealed voids {sealed['count']} ({sealed['volume_mm3']:.4g} mm3), "
                         + ("filled" if sealed["filled"] else "kept (--keep-sealed-voids)"))
        lines += _metric_lines(r)
        if r.get("grade"):
            lines.append(_grade_line(r["grade"]))
        if r.get("repair"):
            lines += _repair_lines(r["repair"])
        if isinstance(r.get("print_check"), dict):
            lines += _certificate_lines(r["print_check"])
        if "mechanics" in r:
            lines += _mechanics_lines(r["mechanics"])
        lines.append(_memory_line(r))
        lines.append("  time: " + ", ".join(f"{k} {v:.2f} s" for k, v in r["timings_s"].items())
                     + f"; total {time.perf_counter() - t0:.1f} s")
        print("\n".join(lines))
    return _printable_exit(args, result.report)


def _simplification_line(s: dict) -> str:
    if not s.get("applied"):
        return f"  simplification: {s['why']}"
    return (f"  simplified within {s['tolerance_mm']:.4g} mm ({s['tolerance_voxels']:.2f} voxel): "
            f"{s['triangles_before']} -> {s['triangles']} triangles; measured: surface moved up to "
            f"{s['max_displacement_mm']:.4g} mm ({s['max_displacement_voxels']:.2f} voxel), porosity "
            f"{100 * s['porosity_change']:+.3f} points, {s['handles_removed']} handles removed")


def _printable_exit(args, report: dict) -> int:
    """3 when --require-printable and the certificate failed (everything is written by then), else 0."""
    cert = report.get("print_check")
    return 3 if args.require_printable and isinstance(cert, dict) and cert["verdict"]["overall"] == "fail" else 0


def _seeds_line(r: dict) -> str:
    """The summary's seed line: how many were drawn, where, and by which rule."""
    where = {"box": "in the box"}.get(r["seeds_in"], "in the patient and one cell's margin")
    text = f"  seeds {r['seeds']} (drawn {where}), Sf {r['sf']:g}, Sv {r['sv']:g}, style {r['style']}"
    rule = r.get("seed_rule")
    if rule == "pore-size":
        text += (f"\n  seed rule pore-size: the count solved for a mean pore size of {r['pore_size_target_mm']:g} mm "
                 f"(the paper's formula would draw {r['seeds_paper_rule']})")
    elif rule == "paper":
        text += f"\n  seed rule paper: n = V P / (pi Dp^3 / 6) for Dp = {r['pore_size_target_mm']:g} mm"
    return text


def _porosity_line(r: dict, target: str) -> str:
    """The headline: the porosity printed (the mesh's volume or the slices' grey levels), the voxels' beside it."""
    how = (r.get("printed_level") or {}).get("by")
    printed = r.get("porosity_printed")
    head = f"  porosity: target {target}"
    if printed is not None:
        head += f", printed {printed:.4f} ({'mesh' if 'porosity_mesh' in r else 'slices'}"
        head += ", level solved for it)" if how else ")"
    head += f", voxels {r['porosity_voxel']:.4f}, closed form {r['porosity_closed_form']:.4f}"
    return head


def _metric_lines(r: dict) -> list[str]:
    """The summary's lines of measures: the patient, the paper's metrics, the voxel morphometry."""
    def stat(key):
        v = r.get(key)
        return v.get("mean") if isinstance(v, dict) else v

    lines = []
    if r.get("patient_volume_mm3") is not None and r.get("cells_in_scaffold") is not None:
        lines.append(f"  patient {r['patient_volume_mm3']:.4g} mm3 (inside its surface) in a "
                     f"{r['box_volume_mm3']:.4g} mm3 box, "
                     f"{r['cells_in_scaffold']} of the {r['seeds']} cells in the scaffold (their seed inside "
                     "the patient)")
    lines += _pieces_lines(r)
    target = r.get("pore_size_target_mm")
    paper = [(stat("pore_size_mm"), "pore size {:.4g} mm" + (f" (target {target:g})" if target else "")), (r.get("interconnection_faces_mean"),
             "interconnection {:.4g} faces"), (r.get("trabecular_thickness_mm_mean"), "trabecular thickness {:.4g} mm")]
    if any(v is not None for v, _ in paper):
        over = r.get("cells_in_scaffold")
        lines.append(f"  cells (paper{'' if over is None else f', means over the {over} cells in the scaffold'}): "
                     + ", ".join(f.format(v) for v, f in paper if v is not None))
    voxels = [(stat("strut_thickness_mm"), "strut thickness {:.4g} mm"), (stat("pore_diameter_mm"),
              "pore diameter {:.4g} mm"), (r.get("connectivity_density_per_mm3"), "Conn.D {:.4g} /mm3"),
              (r.get("interconnected_porosity"), "interconnected {:.4g}")]
    if any(v is not None for v, _ in voxels):
        lines.append("  voxels (spheres): " + ", ".join(f.format(v) for v, f in voxels if v is not None))
    if isinstance(r.get("morphometry"), str):  # what was not measured, and why (the memory it needed)
        lines.append(f"  voxels: {r['morphometry']}")
    return lines


def _pieces_lines(r: dict) -> list[str]:
    """The summary's lines for a patient in several pieces (none for one piece)."""
    count = r.get("patient_pieces_count") or 0
    if count <= 1:
        return []
    shown = r["patient_pieces"]
    lines = [f"  patient in {count} pieces (6-connected voxels), each with its own main body"
             + ("; the largest:" if count > 5 else ", largest first:")]
    lines += [f"    {p['volume_mm3']:.4g} mm3 (voxels), {p['cells']} cells (seed inside), porosity "
              f"{p['porosity_voxel']:.4f} (voxels), bodies {p['bodies']} (6-connected solid voxels)"
              for p in shown[:5]]
    if count > 5:
        lines.append(f"    and {count - 5} more (the JSON report lists the {len(shown)} largest)")
    return lines


#: rows of the analyze table: key, label, unit
_ANALYZE_ROWS = (
    ("porosity_voxel", "porosity (voxels, in the region)", ""),
    ("porosity_mesh", "porosity (mesh volume over the region's)", ""),
    ("bodies", "bodies (closed pieces of the mesh)", ""),
    ("strut_thickness_mm", "strut thickness, max spheres", "mm"),
    ("pore_diameter_mm", "pore diameter, max spheres", "mm"),
    ("connectivity_density_per_mm3", "connectivity density", "mm^-3"),
    ("euler_characteristic", "Euler characteristic", ""),
    ("interconnected_porosity", "interconnected share of the void", ""),
    ("fragments", "fragments (pieces besides the main one)", ""),
    ("surface_area_mm2", "surface area", "mm^2"),
    ("bs_bv_per_mm", "BS/BV", "mm^-1"),
)


def analyze_table(report: dict) -> str:
    """The measures as an aligned text table."""
    rows = []
    for key, label, unit in _ANALYZE_ROWS:
        if key not in report:
            continue
        v = report[key]
        if isinstance(v, dict):
            text = "—" if v.get("mean") is None else f"mean {v['mean']:.4g}, sd {v['sd']:.4g}, max {v['max']:.4g}"
        elif v is None:
            text = "—"
        elif isinstance(v, float):
            text = f"{v:.4g}"
        else:
            text = str(v)
        rows.append((label, f"{text} {unit}".rstrip()))
    width = max(len(r[0]) for r in rows)
    return "\n".join(f"  {a.ljust(width)}  {b}" for a, b in rows)


def _analyze(args) -> int:
    from .measure.morphometry import analyze_file
    from .progress import Progress
    from .run.memory import budget

    t0 = time.perf_counter()
    _check_json_output(args)
    if args.report is not None:
        _check_report(args.report)
    # its line once it has run 2 s, and a line every 30 s off a terminal (a femur at 0.3 mm: 113 s)
    with Progress(not args.quiet).stage("measuring", Path(args.file).name, after=2.0):
        result = analyze_file(args.file, voxel=args.voxel, spacing=args.spacing, region=args.region,
                              label=args.label, threshold=args.threshold, max_memory=budget(args.max_memory))
    r = result.report
    r["timings_s"] = {"analyze": round(time.perf_counter() - t0, 4)}
    if args.output is not None:
        from .io.files import write_json

        write_json(r, args.output)
    if args.report is not None:
        from .io.report import write_analysis_report

        write_analysis_report(result, args.report)
    if not args.quiet:
        grid = "x".join(str(v) for v in r["grid_shape"])
        chosen = f" ({r['selection']})" if r.get("selection") else ""
        head = f"{r['source']}: {r['kind']}{chosen}, voxel {r['voxel_mm']:.4g} mm, grid {grid}, region {r['region']}"
        if r.get("resampled"):
            head += f"; resampled {r['resampled']}"
        if r.get("axes"):
            head += f"; {r['axes']}"
        written = [p for p in (args.output, args.report) if p]
        lines = [head, analyze_table(r)]
        if written:
            lines.append("wrote " + " and ".join(written))
        lines.append(f"  time {time.perf_counter() - t0:.1f} s")
        print("\n".join(lines))
    return 0


def _slice(args) -> int:
    from .mesh.slices import check_stack_output

    from .io.files import check_writable, write_json

    t0 = time.perf_counter()
    check_stack_output(args.output, pixel=args.pixel, layer=args.layer)  # before the scaffold is built
    # the run's report beside the stack, as generate's beside its mesh: the print certificate, the repair and the
    # warnings were written nowhere (stack.json holds the layers' geometry)
    report = check_writable(report_path(Path(args.output)), formats=(".json",))
    result = _build(args, mesh=False, morphometry=False,
                    slices={"out_dir": args.output, "pixel": args.pixel, "layer": args.layer})
    write_json(result.report, report)
    if not args.quiet:
        r = result.report
        stack = r["slices"]
        solid = (1.0 - r["porosity_voxel"]) * r["patient_volume_mm3"]
        print("\n".join([
            f"wrote {stack['layers']} layer{'' if stack['layers'] == 1 else 's'} of {stack['width']}x{stack['height']} "
            f"pixels and stack.json to {args.output}, the run's report to {report}",
            f"  pixel {stack['pixel_mm']:.4g} mm, layer {stack['layer_mm']:.4g} mm, origin "
            + " ".join(f"{v:.4f}" for v in stack["origin_mm"]) + " mm",
            _porosity_line(r, 'none' if r['porosity_target'] is None else format(r['porosity_target'], '.3f'))
            + f"; solid volume: layers {stack['grey_volume_mm3']:.4g} mm3 (grey levels; pixels at least half solid "
            f"{stack['solid_volume_mm3']:.4g}), voxels {solid:.4g} mm3",
            *(_repair_lines(r["repair"]) if r.get("repair") else []),
            *(_certificate_lines(r["print_check"]) if isinstance(r.get("print_check"), dict) else []),
            _memory_line(r),
            f"  time: {time.perf_counter() - t0:.1f} s",
        ]))
    return _printable_exit(args, result.report)


def _grade_line(g: dict) -> str:
    """The summary's line for a graded run: its field and how the depth profile came out."""
    prof = g["profiles"]["depth"]
    filled = [i for i, c in enumerate(prof["cells"]) if c]
    text = f"  graded: {g['field']}"
    if filled:
        text += (f"; pore size (polyhedron-sphere) {prof['pore_size_mm'][filled[0]]:.3g} mm at the surface, "
                 f"{prof['pore_size_mm'][filled[-1]]:.3g} mm deepest")
    below = g.get("below_skin")
    skin = below["depth_mm"] if below else 0.0
    # a bin that reaches into the skin is solid there whatever the offset: it is left out
    miss = [abs(p - t) for lo, p, t in zip(prof["edges_mm"], prof["porosity"], prof["porosity_target"])
            if p is not None and lo >= skin]
    if miss and "offset" in g:
        text += (f"; porosity within {100 * max(miss):.2g} points of its target in every depth bin"
                 + (f" below the {skin:g} mm skin (there {below['porosity']:.4f})" if below else ""))
    return text


def _memory_line(r: dict) -> str:
    tiled = r.get("tiled")
    how = (f"tiled in {tiled['slabs']} slab{'s' if tiled['slabs'] != 1 else ''} of up to "
           f"{tiled['planes_per_slab']} planes within "
           f"{tiled['max_memory_mb'] / 1024:.1f} GiB" + (f" on {tiled['scheduler']}" if tiled["scheduler"] else "")
           + (f" in {tiled['workers']} worker processes" if (tiled.get("workers") or 1) > 1 else "")
           if tiled else "whole grid in memory")
    return f"  memory: {how}; peak {r['peak_memory_mb'] / 1024:.2f} GiB"


def _sweep(args) -> int:
    from .progress import Progress
    from .sweep import run_sweep

    t0 = time.perf_counter()
    prog = Progress(not args.quiet)
    with prog.stage("sweep", "quick" if args.quick else "full"):
        out = run_sweep(args.output, quick=args.quick, seed=args.seed, progress=prog.bar("runs"))
    if not args.quiet:
        print(f"wrote {len(out['files'])} files to {args.output} in {time.perf_counter() - t0:.1f} s")
        for name in sorted(out["figures"]):
            fig = out["figures"][name]
            print(f"  {name}: {fig['csv']}, {fig['png']}")
    return 0


def _show_warning(message, category, filename, lineno, file=None, line=None):
    # one line on stderr, like the errors, instead of a file name and a source line
    print(f"implicit-scaffold: warning: {message}", file=sys.stderr, flush=True)


def _info(args) -> int:
    import numpy
    import pyopencl

    from . import opencl

    print(f"implicit_scaffold {__version__}")
    print(f"numpy {numpy.__version__}, pyopencl {pyopencl.VERSION_TEXT}")
    checks = opencl.device_checks()
    pip_runtimes = ", ".join(f"{k} ({v})" for k, v in opencl.pip_runtime_libraries().items())
    print(f"OpenCL runtimes from PyPI: {pip_runtimes or 'none'}; "
          f"OCL_ICD_VENDORS={os.environ.get('OCL_ICD_VENDORS', '(unset)')}")
    print("OpenCL devices (each probed once per machine: every kernel built and checked against NumPy):")
    for c in checks:
        if c.ok:
            verdict = (f"kernels OK, built in {c.build_seconds:.2f} s, lattice {c.mvoxels_per_second:.1f} Mvoxel/s, "
                       f"max error {c.max_error_mm:.1e} mm")
        else:
            verdict = f"skipped: {c.reason}"
        print(f"  [{c.position[0]}:{max(c.position[1], 0)}] {c.label}: {verdict}")
    pick = opencl.chosen()
    how = f"named by {opencl.DEVICE_ENV}" if os.environ.get(opencl.DEVICE_ENV) else "the fastest that works"
    print(f"chosen: {pick.label} ({how})")
    t0 = time.perf_counter()
    from .fields.lattice import BLOCK

    for source in opencl.kernel_names():
        opencl.program(source, BLOCK=BLOCK)
    print(f"kernel build now: {time.perf_counter() - t0:.2f} s "
          f"({', '.join(f'{k} {v:.2f} s' for k, v in opencl.BUILD_SECONDS.items())})")
    print(f"OpenCL device: {opencl.device().describe()}")
    print(f"kernels: {opencl.kernels_dir()}")
    print(f"device cache: {opencl.cache_dir()}")
    return 0


def main(argv=None) -> int:
    """Entry point; returns the exit code (0, or 2 for bad input)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    commands = {"generate": _generate, "slice": _slice, "sweep": _sweep, "analyze": _analyze, "check": _check,
                "info": _info, "mechanics": _mechanics, "design": _design}
    # a kill (SIGTERM) ends the run as Ctrl-C does, so the writers remove their temporary files
    from . import progress

    progress.INTERRUPTED = False
    previous = _on_terminate(_interrupt)
    try:
        from .io.files import run_outputs

        with warnings.catch_warnings(), run_outputs():
            warnings.showwarning = _show_warning
            if getattr(args, "max_memory", None) is not None:
                _check_budget_fits(args.max_memory)
            return commands[args.command](args)
    except ScaffoldError as exc:
        print(f"implicit-scaffold: error: {exc}", file=sys.stderr)
        return 2
    except MemoryError:
        print("implicit-scaffold: error: out of memory; use a larger --voxel", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("implicit-scaffold: interrupted; no output written", file=sys.stderr)
        return 130
    finally:
        _on_terminate(previous)


def _check_budget_fits(size) -> None:
    """Warn when ``--max-memory`` exceeds the machine's memory: the budget is then no guard (a run that needs
    more is stopped by the system, or swaps, rather than refused before it starts)."""
    import psutil

    from .errors import ScaffoldWarning
    from .run.memory import DEFAULT_MEMORY_SHARE, available_memory, format_size, parse_memory

    total = int(psutil.virtual_memory().total)
    if parse_memory(size) > total:
        warnings.warn(f"--max-memory {size} is more than this machine's {format_size(total)} of memory: a run that needs "
                      "more is stopped by the system, not refused before it starts; give at most "
                      f"{format_size(DEFAULT_MEMORY_SHARE * available_memory())} (what is free now, less a fifth)",
                      ScaffoldWarning, stacklevel=2)


def _interrupt(signum, frame):
    from . import progress

    # remembered, since a finalizer that happens to be running would swallow the exception
    progress.INTERRUPTED = True
    raise KeyboardInterrupt


def _on_terminate(handler):
    """Set the SIGTERM and SIGINT handlers (main thread only; elsewhere nothing changes); return
    the previous ones."""
    import signal
    import threading

    if handler is None or threading.current_thread() is not threading.main_thread():
        return None
    term, intr = handler if isinstance(handler, tuple) else (handler, handler)
    # a handler not set from Python reads as None and cannot be set back: leave it
    return tuple(None if h is None else signal.signal(sig, h)
                 for sig, h in ((signal.SIGTERM, term), (signal.SIGINT, intr)))


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
