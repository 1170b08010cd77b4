"""The pipeline end to end: ``generate(...)`` builds a scaffold and its report.

Every stage is a function of its own module; this one only validates options,
chooses defaults, calls the stages in order and gathers the report.
"""
from __future__ import annotations

import contextlib
import math
from dataclasses import asdict, dataclass, field as dc_field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from . import __version__, opencl
from .errors import ScaffoldError, round_down
from .fields.field import sample
from .run.grid import Grid, run_bytes_per_voxel
from .run.memory import available_memory, check_memory
from .progress import Progress
from .geometry.skeleton import closed_form_porosity, quad_areas
from .specs import (FLAT_KEYWORDS, STYLES, GridSpec, LatticeSpec, Outputs, check_width,  # noqa: F401
                    output_format, specs_from)

from .io.formats import FIELD_WRITERS as FIELD_FORMATS, MESH_STREAMED, MESH_WRITERS as MESH_FORMATS  # noqa: E402
from .io.formats import report_path  # noqa: E402
#: default grids are capped at this many voxels so the default run stays quick;
#: a finer --voxel is always honoured (within memory)
DEFAULT_MAX_VOXELS = 24_000_000
#: printed porosity this far from the target (a fraction) is warned about
PRINTED_TOLERANCE = 0.003
#: voxel and printed porosity this far apart say the walls are under-resolved
UNRESOLVED = 0.05
#: voxels across the median wall when the voxel size is left to the tool
VOXELS_PER_WALL = 4.0
#: the default voxel is coarsened (to keep a run small) to no fewer voxels than this across the
#: median wall as printed (:func:`_printed_wall`). Measured on CT labels (porosity 0.7-0.8): at
#: 1.6 voxels the L1 label with 1.2 mm pores collapsed (below), at 1.8 (the T12 label, 0.8 mm
#: pores, 0.198 mm voxels) and 2.0 the printed porosity met the target
DEFAULT_MIN_VOXELS_PER_WALL = 2.0
#: a given voxel with fewer voxels than this across the printed median wall is refused before the
#: lattice: at 0.83-1.03 (the L1 label at 0.4-0.5 mm voxels, the DICOM CT at 0.5 mm) every wall
#: broke into fragments and the scaffold came out empty (printed porosity 0.9999 for 0.8)
MIN_VOXELS_PER_WALL = 1.25
#: ... and for a graded run, across the printed median wall of its smallest pores
#: (:func:`_smallest_pores_wall`): its offset meets the porosity in voxels, not on the print, so its
#: walls are thinner in voxels than an even run's at the same voxel, and break sooner. Measured in a
#: 5 mm cube at porosity 0.8 (share of the patient removed as fragments, exit 0 before): --grade 0:0.5
#: (0.221 mm walls) lost 1.5 % at 2.2 voxels across, 8.7 % at 1.84, 11 % at 1.70, 20 % at 1.47 (where
#: the even run at --pore-size 0.5 lost 1.6 %); --grade 0:0.3,2:0.8 (0.135 mm walls in its 0.3 mm
#: shell) 0.17 % at 2.7, 0.36 % at 2.25, 2.2 % at 1.69, 4.3 % at 1.5, 7.6 % at 1.35
GRADED_MIN_VOXELS_PER_WALL = 2.0
#: a scaffold whose porosity (as printed on the level's prism, else in voxels) misses the target by
#: more than this (a fraction) collapsed: its walls broke into fragments at the voxel size, and no
#: level brings it back. Refused before the mesh (the L1 label at 0.33 mm voxels, 1.6 across the
#: wall: the prism printed 0.9734 for 0.80, then a level step of 0.84 mm made it a solid block).
#: Runs that hold together meet it within a fraction of a point on the prism
COLLAPSED = 0.10
#: ... and only when the fragments removed hold at least this share of the solid asked for (the
#: collapsed runs: 76-100 %; a 0.65 mm voxel on 2 mm pores lost 57 % and still printed 0.8049
#: for 0.8; two small balls under a skin missed their target with 5 small fragments)
BROKEN_SHARE = 0.5


@dataclass(frozen=True)
class Params:
    """Validated options of one run (units mm), as the stages read them: a :class:`LatticeSpec`'s
    fields (whose meaning and defaults they are), the :class:`GridSpec`'s voxel, the
    :class:`Outputs`' tolerance, and the patient's built-in shape, skin and smooth cut.

    :func:`generate` builds it from the specs; the report's parameters are its fields.
    """

    shape: str = "box"
    size: Any = 10.0
    seeds: int | None = LatticeSpec.seeds
    pore_size: float = LatticeSpec.pore_size
    porosity: float | None = LatticeSpec.porosity
    sf: float = LatticeSpec.sf
    sv: float = LatticeSpec.sv
    style: str = LatticeSpec.style
    blend: float | None = LatticeSpec.blend
    voxel: float | None = GridSpec.voxel
    seed: int = LatticeSpec.seed
    remove_fragments: bool = LatticeSpec.remove_fragments
    fill_sealed_voids: bool = LatticeSpec.fill_sealed_voids
    #: None until :func:`generate` resolves it: the patient when one is given, else the box
    seeds_in: str | None = LatticeSpec.seeds_in
    seed_rule: str = LatticeSpec.seed_rule
    #: a solid shell this thick at the patient surface; a smooth intersection this wide
    skin: float = 0.0
    smooth_cut: float = 0.0
    grade: Any = LatticeSpec.grade
    calibration: Any = LatticeSpec.calibration
    relax: int = LatticeSpec.relax
    weighted: bool = LatticeSpec.weighted
    tolerance: float = Outputs.tolerance


@dataclass
class Result:
    """Everything a run built.

    Attributes
    ----------
    params : Params
    report : dict
        The same dict as the JSON report.
    cells : Cells
    skeleton : Skeleton or None
        The paper style's skeleton (a :class:`~implicit_scaffold.geometry.skeleton.SkeletonSource` in a tiled run, which builds
        it slab by slab); None for struts.
    edges : (ne, 2, 3) ndarray or None
        The struts' axes; None for the paper style.
    grid : Grid
    field : (nx, ny, nz) float32 ndarray, mm
        The scaffold's signed distance, negative in the solid. A tiled run's is a read-only
        ``numpy.memmap`` of its slab store on disk: it reads like an array, pages in only
        what is read, and its (already unlinked) file goes when the last reference does.
    patient_sdf : (nx, ny, nz) float32 ndarray, mm
        The patient's signed distance as the run read it: a mesh patient's is clamped
        beyond the skin and smooth-cut widths (and a depth grade's deepest node) plus 3
        voxels, where only its sign matters (:meth:`~implicit_scaffold.fields.patient_mesh.MeshPatient.clamp_far_field`).
        A memmap in a tiled run, as `field`.
    mesh : trimesh.Trimesh or None
        None without the mesh stage. A run in slabs streams its mesh to the output file, and
        `mesh` reads that file back on first use when it fits the run's memory budget
        (:data:`READ_BACK_BYTES_PER_TRIANGLE` a triangle beside what the process holds); when it
        does not, or no mesh file was written, None with a warning.
    mesh_file : Path or None
        The mesh file a run in slabs wrote (what `mesh` reads back).
    """

    params: Params
    report: dict
    cells: Any
    skeleton: Any
    edges: Any
    grid: Grid
    field: np.ndarray
    patient_sdf: np.ndarray
    patient: Any
    timings: dict = dc_field(default_factory=dict)
    #: the slabs of a run kept on disk (None for one slab held in memory)
    tiled: Any = None
    #: the platen compression of ``Outputs.mechanics`` (:class:`~implicit_scaffold.measure.mechanics.Compression`), else None
    compression: Any = None
    mesh_file: Any = None
    _mesh: Any = dc_field(default=None, repr=False)

    @property
    def mesh(self):
        if self._mesh is None and self.mesh_file is not None:
            self._mesh = _read_back(self.mesh_file, self.report)
            if self._mesh is None:
                self.mesh_file = None  # warned once
        return self._mesh

    @mesh.setter
    def mesh(self, value):
        self._mesh = value


#: bytes per triangle that trimesh holds at its peak while it reads a mesh file whole (an STL of
#: 2,277,628 triangles, the 4 mm cube at 0.02 mm: 470 by tracemalloc, 398 kept: its unmerged
#: float64 vertices, faces and the reader's copies)
READ_BACK_BYTES_PER_TRIANGLE = 480


def _read_back(path: Path, report: dict):
    """The mesh a run in slabs wrote to `path`, read whole when it fits the run's budget; else None,
    with a warning naming the budget it needs."""
    import warnings

    from .errors import ScaffoldWarning
    from .run.memory import format_size, process_memory

    budget = int(round(float((report.get("tiled") or {}).get("max_memory_mb", 0)) * 2**20))
    need = int(report.get("triangles", 0)) * READ_BACK_BYTES_PER_TRIANGLE
    if not Path(path).is_file() or need + process_memory() > budget:
        why = (f"{path} is gone" if not Path(path).is_file() else
               f"its {report.get('triangles', 0):,} triangles need about {format_size(need)} beside the "
               f"{format_size(process_memory())} held, over the run's --max-memory {format_size(budget)}")
        warnings.warn(f"Result.mesh: the mesh of this run in slabs is not read back ({why}); read {path} in pieces "
                      "or raise max_memory", ScaffoldWarning, stacklevel=3)
        return None
    import trimesh

    return trimesh.load(path, process=False, force="mesh")




def validate(**options) -> Params:
    """Check every option and return them as :class:`Params`; raise :class:`ScaffoldError` otherwise.

    The options are :class:`Params`' fields; each is checked by the spec it belongs to.
    """
    unknown = set(options) - set(Params.__dataclass_fields__)
    if unknown:
        raise ScaffoldError(f"unknown option(s): {', '.join(sorted(unknown))}")
    lattice = LatticeSpec(**{k: v for k, v in options.items() if k in LatticeSpec.__dataclass_fields__})
    return _params(lattice, GridSpec(voxel=options.get("voxel")),
                   Outputs(tolerance=options.get("tolerance", Params.tolerance)),
                   **{k: options.get(k, getattr(Params, k)) for k in ("shape", "size", "skin", "smooth_cut")})


def _params(lattice: LatticeSpec, grid: GridSpec, outputs: Outputs, *, shape, size, skin, smooth_cut) -> Params:
    """The run's :class:`Params` from its (checked) specs and the patient's options."""
    return Params(shape=shape, size=size, voxel=grid.voxel, tolerance=outputs.tolerance,
                  skin=check_width("skin", skin), smooth_cut=check_width("smooth-cut", smooth_cut),
                  **{f.name: getattr(lattice, f.name) for f in fields(LatticeSpec)})


def _default_voxel(wall: float, box_volume: float, printed_wall: float | None = None) -> float:
    """The voxel when none is given: :data:`VOXELS_PER_WALL` across the median wall, coarsened to
    at most :data:`DEFAULT_MAX_VOXELS` voxels, but never below :data:`DEFAULT_MIN_VOXELS_PER_WALL`
    across the wall as it is printed (`printed_wall`, :func:`_printed_wall`): a large bone from
    CT would otherwise get voxels too coarse to hold its walls (mm)."""
    h = wall / VOXELS_PER_WALL
    cap = (box_volume / DEFAULT_MAX_VOXELS) ** (1 / 3)
    if printed_wall is not None:
        cap = min(cap, printed_wall / DEFAULT_MIN_VOXELS_PER_WALL)
    return float(max(h, cap))


def _printed_wall(wall: float, params: Params) -> float | None:
    """The median wall of the paper's lattice once the surface offset meets the porosity target, mm
    (None for struts): the walls are plates, whose solid grows with their thickness, so the
    closed-form wall scales by ``(1 - P) / (1 - P0)``."""
    if params.style != "paper":
        return None
    p0 = closed_form_porosity(params.sf, params.sv)
    if params.porosity is None or p0 >= 1.0:
        return wall
    return wall * (1.0 - params.porosity) / (1.0 - p0)


def _check_resolved(printed_wall: float | None, voxel: float, pore_size_given: bool = True,
                    graded: bool = False) -> None:
    """Refuse, before the lattice, a voxel that cannot hold the printed walls (module notes). Without
    `pore_size_given` (a CT calibration sets the pore sizes) only a finer voxel is named; `graded`:
    the walls are those of the smallest pores (:func:`_smallest_pores_wall`), held by at least
    :data:`GRADED_MIN_VOXELS_PER_WALL` voxels."""
    least = GRADED_MIN_VOXELS_PER_WALL if graded else MIN_VOXELS_PER_WALL
    if printed_wall is not None and printed_wall / voxel < least:
        if not pore_size_given:
            fix = " (--calibration sets the pore sizes)"
        else:
            fix = ", or larger pore sizes in the grade" if graded else ", or a larger --pore-size"
        raise ScaffoldError.for_voxel(
            f"--voxel {voxel:.4g} mm cannot hold the lattice: "
            + ("the walls of its smallest pores" if graded else "its walls")
            + f", about {printed_wall:.3g} mm thick as "
            f"printed, would be {printed_wall / voxel:.2f} voxels across and break into fragments (at least "
            f"{least:g} are needed); use --voxel {round_down(printed_wall / 2)} or finer" + fix, printed_wall / least)


def _check_collapsed(tf, params: Params, voxel: float, printed_wall: float | None, calibration: dict) -> None:
    """Refuse, before the mesh, a scaffold whose porosity collapsed: its walls, under-resolved,
    broke into fragments (at least :data:`BROKEN_SHARE` of the solid asked for), whose removal
    left nothing the level could bring to the target (within :data:`COLLAPSED`).

    Where the level was searched for what is printed, that search's result on its prism tells
    (the voxels' count may sit several points off a target the print meets, on coarse walls);
    else the voxels' porosity.
    """
    if params.porosity is None or not tf.n_inside or params.porosity >= 1.0:
        return
    if tf.fragments_voxels < BROKEN_SHARE * tf.n_inside * (1.0 - params.porosity):
        # the walls held together: a target missed for another reason (a skin or smooth cut on a
        # small patient leaves too little room for the pores) is a warning on what was built
        return
    if calibration and calibration.get("by") and "printed_at_level" in calibration:
        got, target = calibration["printed_at_level"], calibration["prism_target"]
    else:
        got, target = 1.0 - tf.solid / tf.n_inside, params.porosity
    if abs(got - target) <= COLLAPSED:
        return
    finer = round_down((printed_wall / 2) if printed_wall is not None and printed_wall / 2 < voxel else voxel / 2)
    raise ScaffoldError(
        f"the scaffold's porosity came out {got:.4f} for a target of {target:.4g} after {tf.fragments} solid "
        f"fragments were removed: at {voxel:.4g} mm "
        f"voxels its walls are too thin to hold together; use --voxel {finer} or finer, or a larger --pore-size")


def _report_stats(values) -> dict:
    v = np.asarray(values, np.float64)
    return {"mean": float(v.mean()), "p10": float(np.percentile(v, 10)), "median": float(np.median(v))}


class _Unset:
    """The default of generate's flat keywords: "not given", so that a keyword given beside the
    spec it belongs to is refused (even at the spec's default value) and one left out takes the
    spec's default."""

    def __repr__(self):
        return "<the spec's default>"


_UNSET = _Unset()


def generate(*, lattice: LatticeSpec | None = None, grid: GridSpec | None = None, outputs: Outputs | None = None,
             patient=None, shape: str = Params.shape, size=Params.size, skin: float = Params.skin,
             smooth_cut: float = Params.smooth_cut, ct=None, verbose: bool = False,
             output: str | Path | None = _UNSET, mesh: bool = _UNSET, morphometry: bool = _UNSET,
             slices: dict | None = _UNSET, printer=_UNSET, repair: bool = _UNSET, tolerance: float = _UNSET,
             voxel: float | None = _UNSET, max_memory=_UNSET, tiled: bool | int | None = _UNSET, scheduler=_UNSET,
             workers: int = _UNSET,
             style: str = _UNSET, seeds: int | None = _UNSET, pore_size: float = _UNSET, seed_rule: str = _UNSET,
             seeds_in: str | None = _UNSET, porosity: float | None = _UNSET, sf: float = _UNSET, sv: float = _UNSET,
             blend: float | None = _UNSET, seed: int = _UNSET, remove_fragments: bool = _UNSET,
             fill_sealed_voids: bool = _UNSET, grade=_UNSET, calibration=_UNSET, relax: int = _UNSET,
             weighted: bool = _UNSET, mechanics=_UNSET) -> Result:
    """Build a scaffold: seeds, cells, skeleton, lattice field, patient cut, mesh and report.

    What to build is given by three specs, or by their fields as flat keywords (the same run,
    the same bytes): ``generate(lattice=LatticeSpec(pore_size=0.5), outputs=Outputs("s.stl"))``
    is ``generate(pore_size=0.5, output="s.stl")``. A spec left out takes its defaults and the
    flat keywords given for it; a flat keyword beside its own spec is refused.

    Parameters
    ----------
    lattice : LatticeSpec, optional
        The lattice: style, seeds or pore size, porosity, Sf, Sv, blend, seed, grading
        (:class:`~implicit_scaffold.specs.LatticeSpec`, whose fields are also keywords here).
    grid : GridSpec, optional
        The voxel and the run's layout: ``voxel``, ``max_memory``, ``tiled``, ``workers``,
        ``scheduler`` (:class:`~implicit_scaffold.specs.GridSpec`; also keywords). Every run's field is made
        by one slab driver (:mod:`~implicit_scaffold.run.tiled`): a grid that fits is one slab held in memory, a
        larger one runs in slabs kept on disk, with the same field bit for bit; one that
        cannot fit even so is refused before the work starts, naming the budget that would
        do. ``report["tiled"]["workers"]`` says how many worker processes ran.
    outputs : Outputs, optional
        What is written and measured: ``path`` (the keyword ``output``), ``mesh``,
        ``morphometry``, ``slices``, ``printer``, ``repair``, ``tolerance``, ``mechanics``
        (:class:`~implicit_scaffold.specs.Outputs`; also keywords). The JSON report goes beside the path; a
        printer's certificate lands in ``report["print_check"]``, a repair's changes in
        ``report["repair"]``, the slices' geometry in ``report["slices"]``, the mesh
        simplification's measured error in ``report["simplification"]``.
    patient : object, optional
        A patient geometry (see :mod:`~implicit_scaffold.fields.patient`, :func:`~implicit_scaffold.io.patient_io.load_patient`); by
        default the built-in `shape` of `size`.
    shape : {"box", "cylinder", "sphere"}
    size : float or (3,) floats, mm
        The built-in patient when `patient` is None.
    skin : float, mm
        A solid shell this thick at the patient surface; 0 for none.
    smooth_cut : float, mm
        Width of a smooth instead of sharp intersection with the patient; 0 for sharp.
    ct : CTImage or str or Path, optional
        The patient's CT intensities, for ``calibration`` (:func:`~implicit_scaffold.geometry.grade.load_ct`).
    verbose : bool
        Print stage progress on stderr.
    output, mesh, morphometry, slices, printer, repair, tolerance, voxel, max_memory, tiled, \
    scheduler, workers, style, seeds, pore_size, seed_rule, seeds_in, porosity, sf, sv, blend, seed, \
    remove_fragments, fill_sealed_voids, grade, calibration, relax, weighted, mechanics
        The specs' fields as flat keywords (``output`` is :attr:`Outputs.path`); their
        defaults are the specs'.

    Returns
    -------
    Result

    Raises
    ------
    ScaffoldError
        A bad value, an option given both in a spec and as a keyword, or a run that cannot
        fit in `max_memory`: one line saying what is wrong and how to fix it.
    """
    # the flat keywords given (locals() holds the parameters here, before any other name)
    flat = {k: v for k, v in locals().items() if k in FLAT_KEYWORDS and v is not _UNSET}
    specs = specs_from({"lattice": lattice, "grid": grid, "outputs": outputs}, flat)
    lattice, layout, outs = specs["lattice"], specs["grid"], specs["outputs"]
    params = _params(lattice, layout, outs, shape=shape, size=size, skin=skin, smooth_cut=smooth_cut)
    # from here on the run reads `params` and these (`grid` becomes the voxel grid)
    output, mesh, morphometry, slices, printer, repair = (outs.path, outs.mesh, outs.morphometry, outs.slices,
                                                          outs.printer, outs.repair)
    max_memory, tiled, scheduler, workers = layout.max_memory, layout.tiled, layout.scheduler, layout.workers
    del shape, size, skin, smooth_cut, grid
    from .fields.patient import clamp_far_field, primitive

    if params.seeds_in is None:
        # time and memory then follow the bone's volume, not its bounding box's
        params = replace(params, seeds_in="box" if patient is None else "patient")
    out_path = _checked_output(output)
    if workers > 1:
        # the workers run slabs: a run given them goes in slabs (at least one per worker)
        if tiled is False:
            raise ScaffoldError("workers run the slabs of a tiled run; drop tiled=False or workers")
        tiled = True if tiled is None else tiled
    if patient is None:
        patient = primitive(params.shape, params.size)
    if slices is not None and slices.get("layer") is not None:
        height = float(patient.hi[2] - patient.lo[2])
        if float(slices["layer"]) > height:
            raise ScaffoldError(f"--layer {float(slices['layer']):g} mm is taller than the part ({height:.4g} mm along "
                                "z): it would print one empty layer; give a layer of the printer's, e.g. --layer 0.05")
    # everything that can be checked before the work starts is checked now
    opencl.context()
    from .run.memory import budget

    # the patient as the fine grid reads it: beyond the skin and smooth-cut widths (and a
    # depth grade's deepest node) only its sign matters, so a mesh's far field is clamped there
    # and computed slab by slab, the same on the whole grid as in slabs
    fine_patient = clamp_far_field(patient, params.skin + params.smooth_cut + _grade_reach(params.grade))
    run = _RunPlan(run_bytes_per_voxel(mesh=mesh, morphometry=morphometry, repair=bool(repair)),
                   int(budget(max_memory)), tiled, params, fine_patient, out_path, slices, workers=workers)
    prog = Progress(verbose)
    if mesh:
        # the mesh stages' libraries load while the cells and the lattice are computed (about
        # a second of a short run's time, most of it trimesh's imports)
        _Beside(_import_mesh_libraries)
    if getattr(patient, "load_seconds", None) is not None:
        # a patient read from a file (patient_io.load_patient) was loaded before this call
        prog.timings["load"] = float(patient.load_seconds)

    graded = _graded_density(params, patient, ct, prog)
    n = graded.density.count if graded else _seed_count(params, patient)
    seeding = _seeding_grid(params, patient, n, graded is not None)
    _plan_before_cells(run, params, patient, n, graded is not None, seeding)
    built = _seeds_and_cells(params, patient, n, graded, run, prog, seeding)
    # a graded lattice breaks first where its pores are smallest: the voxel is checked (and the
    # default one floored) against the walls there; an even lattice's is its median wall
    printed_wall = _printed_wall(built.wall_smallest, params)
    if params.voxel is not None:
        _check_resolved(printed_wall, params.voxel, pore_size_given=params.calibration is None,
                        graded=graded is not None)
    grid = Grid.covering(patient.lo, patient.hi, params.voxel if params.voxel is not None
                         else _default_voxel(built.wall, _box_volume(patient), printed_wall))
    # what the build will still hold when the solve starts: a grid held in memory, about all its run's bytes
    # (the default cube: 461 MiB at this check, 1,232 MiB at the solve, 104 bytes a voxel of its 195^3 grid,
    # against the plan's 112); a run in slabs, the libraries of its later stages (300 MiB here, 540 MiB at the
    # solve, under --max-memory 1G)
    in_memory = grid.memory_estimate(run.run_bytes)
    try:
        skeleton, edges, slab_voxels = _skeleton_stage(params, built, grid, run, prog, graded=graded is not None)
    except ScaffoldError as err:
        if outs.mechanics is not None and err.budget is not None:
            # the budget named must hold the solve after the build too, else it is refused again there (a 6 mm
            # cube at 0.04 mm: 650M named by the slabs, the solve then asked for 1.2G)
            try:
                _check_mechanics(outs.mechanics, params, patient, grid, built.walls, max_memory,
                                 kept=LATER_STAGES_BYTES, kept_in_memory=in_memory, whole=getattr(run, "whole_bytes", None))
            except ScaffoldError as solve:
                if solve.budget is not None and solve.budget > err.budget:
                    raise solve from None
        raise
    if outs.mechanics is not None:
        _check_mechanics(outs.mechanics, params, patient, grid, built.walls, max_memory,
                         kept=in_memory if slab_voxels is None else LATER_STAGES_BYTES,
                         kept_in_memory=in_memory, whole=run.whole_bytes if slab_voxels is not None else None)
    # the field: one driver for every size, over one slab held in memory when the whole grid
    # fits (slab_voxels None), else over slabs kept on disk; then the outputs
    return _build(run, params, patient, grid, built.cells, skeleton, edges, built.seeds, built.walls,
                  built.wall_p10, built.window_p25, slab_voxels, scheduler, prog, mesh, out_path, morphometry,
                  seed_solve=built.tried or None, printer=printer, repair=repair, printed_wall=printed_wall,
                  mechanics=(outs.mechanics, max_memory) if outs.mechanics is not None else None,
                  grade=(graded.field, graded.density, built.empty_power_cells) if graded else None)


def _box_volume(patient) -> float:
    """The patient's bounding box's volume, mm³."""
    return float(np.prod(np.asarray(patient.hi, float) - np.asarray(patient.lo, float)))


def _checked_output(output: Path | None) -> Path | None:
    """The output's path (its format checked by :class:`Outputs`), checked writable, with its
    report, before the work starts."""
    if output is None:
        return None
    from .io.files import check_writable

    out_path = Path(output)
    check_writable(out_path)
    check_writable(report_path(out_path))
    return out_path


@dataclass(frozen=True)
class _Graded:
    """A graded run's pore-size field and the seed density drawn from it (:mod:`~implicit_scaffold.geometry.grade`)."""

    field: Any
    density: Any


def _graded_density(params: Params, patient, ct, prog) -> _Graded | None:
    """Stage ``density``: the seed density of a graded run (``--grade`` or ``--calibration``), else None."""
    if params.grade is None and params.calibration is None:
        return None
    from .geometry import grade as grading

    if isinstance(ct, (str, Path)):
        ct = grading.load_ct(ct)
    p0 = closed_form_porosity(params.sf, params.sv)
    gfield = grading.grade_field(params.grade, params.calibration, ct,
                                 porosity=params.porosity if params.porosity is not None else p0,
                                 seed_rule=params.seed_rule, sv=params.sv)
    with prog.stage("density", gfield.describe()):
        density = grading.seed_density(gfield, patient, np.asarray(patient.lo, float), np.asarray(patient.hi, float))
    return _Graded(gfield, density)


def _seed_volume(params: Params, patient) -> float:
    """The volume the seeds fill, mm³: the bounding box's or the patient's."""
    return _box_volume(patient) if params.seeds_in == "box" else float(patient.volume)


def _seed_count(params: Params, patient) -> int:
    """The first seed count of an even (not graded) run: given, by the paper's formula, or for the pore size."""
    from .geometry.seeds import density_for_pore_size, seed_count

    if params.seeds is not None:
        return params.seeds
    volume = _seed_volume(params, patient)
    if params.seed_rule == "paper":
        p0 = closed_form_porosity(params.sf, params.sv)
        return seed_count(volume, params.porosity if params.porosity is not None else p0, params.pore_size)
    return max(2, int(round(density_for_pore_size(params.pore_size, params.sv) * volume)))


def _plan_before_cells(run: _RunPlan, params: Params, patient, n: int, graded: bool, seeding=None) -> int | None:
    """Refuse, before the cells, a run that cannot fit: the grid's plan (when the voxel is given)
    and the cells' own memory. Returns the plan's slab voxels (None: the whole grid, or no voxel given)."""
    planned = None
    if params.voxel is not None:
        from .geometry.cells import CELLS_BYTES_PER_SEED, HELD_BYTES_PER_SEED
        from .run.tiles import blend_halo

        # what the cells, the skeleton and the packed primitives will hold, and the blend's halo
        # at the widest the walls allow (half a wall; a wall is at most 1 - Sv of two cells'
        # spans), estimated
        span = (_seed_volume(params, patient) / n) ** (1 / 3)
        halo = blend_halo(params.voxel, params.blend if params.blend is not None else (1 - params.sv) * span)
        planned = run.plan(Grid.covering(patient.lo, patient.hi, params.voxel),
                           halo=halo if params.style == "paper" else 0,
                           reserve=n * HELD_BYTES_PER_SEED + (GRADE_RESERVE if graded else 0),
                           slab_share=n * (HELD_BYTES_PER_SEED - CELLS_BYTES_PER_SEED) if params.style == "paper" else 0,
                           span=span)
    count_at = None
    if seeding is not None and params.seeds is None and not graded and params.seeds_in == "patient":
        # the seeds in the patient's margin too (seeds_in_patient draws n per patient volume
        # over the patient grown by a cell): in a CT's thin bones they can outnumber the n
        count_at = _margin_count(seeding[0], n, n, params.pore_size, (float(patient.volume) / n) ** (1 / 3),
                                 inside=True)
    _check_cells_memory(run, params, int(math.ceil(count_at(params.pore_size))) if count_at else n, graded,
                        count_at=count_at)
    return planned


def _check_cells_memory(run: _RunPlan, params: Params, n: int, graded: bool, count_at=None) -> None:
    """Refuse `n` seeds whose cells cannot be built within what --max-memory leaves (:func:`~implicit_scaffold.geometry.cells.check_seed_memory`;
    `count_at`, the seed count at another pore size)."""
    from .geometry.cells import check_seed_memory
    from .run.memory import process_memory

    check_seed_memory(n, None if params.seeds is not None or graded else params.pore_size,
                      available=min(run.max_memory - process_memory(), available_memory()),
                      seeds_given=params.seeds is not None, count_at=count_at)


def _margin_count(coarse: np.ndarray, drawn: int, n: int, pore_size: float, margin: float, *, inside: bool = False):
    """The seeds that :func:`~implicit_scaffold.geometry.seeds.seeds_in_patient` draws at another
    pore size (mm), as a function: the patient's own `n` scale as ``pore**-3``, the patient grown
    by a margin of one cell (`margin` mm at `pore_size`) grows with the cell. `drawn` seeds were
    drawn at `pore_size`; with `inside`, none was yet, and they are estimated as the draw makes
    them, `n` over the share of the grown patient inside.

    The shares are those of the seeding grid's distance `coarse` (mm) at its cells' centres, the
    trilinear values that the draw samples: counted at the grid's own points, a 0.6 mm plate on a
    0.2 mm grid was grown by 23 % more than the draw grew it (3 % at the centres).
    """
    c = coarse
    centres = (c[:-1, :-1, :-1] + c[1:, :-1, :-1] + c[:-1, 1:, :-1] + c[:-1, :-1, 1:]
               + c[1:, 1:, :-1] + c[1:, :-1, 1:] + c[:-1, 1:, 1:] + c[1:, 1:, 1:]) / 8
    if centres.size == 0:
        centres = c
    region0 = max(int(np.count_nonzero(centres < margin)), 1)
    if inside:
        held = int(np.count_nonzero(centres < 0))
        drawn = n * region0 / held if held else n  # no point inside: n seeds in the margin

    def count_at(pore: float) -> float:
        r = pore / pore_size
        return drawn * r ** -3 * max(int(np.count_nonzero(centres < margin * r)), 1) / region0

    return count_at


def _seeding_grid(params: Params, patient, n: int, graded: bool):
    """The patient's distance on the seeding grid (:func:`_coarse_patient`) and that grid, where the
    seeds are drawn in the patient or their count solved for the pore size; else None."""
    solving = not graded and params.seeds is None and params.seed_rule == "pore-size"
    if params.seeds_in == "patient" or solving or graded:
        return _coarse_patient(patient, (float(patient.volume) / n) ** (1 / 3))
    return None


@dataclass(frozen=True)
class _Built:
    """The seeds, their cells and what the cells tell the later stages (walls and windows, mm)."""

    seeds: np.ndarray
    cells: Any
    tried: list
    empty_power_cells: int | None
    walls: np.ndarray
    wall: float
    wall_p10: float
    window_p25: float
    #: the median wall of the smallest pores: a graded lattice's walls scaled to its densest
    #: seeding (:func:`_smallest_pores_wall`), where it breaks first; an even lattice's median wall
    wall_smallest: float


def _seeds_and_cells(params: Params, patient, n: int, graded: _Graded | None, run: _RunPlan, prog,
                     seeding=None) -> _Built:
    """Stages ``seeds`` and ``cells``: the seeds drawn for `n` (for the pore size, the count
    corrected until the cells measure it) and their Voronoi (or power) cells; the walls and
    windows of the cells near the patient."""
    from .geometry.cells import voronoi_cells
    from .run.memory import release
    from .measure.metrics import interior_face_pairs, pore_sizes, trabecular_thicknesses
    from .geometry.seeds import PORE_SIZE_PASSES, PORE_SIZE_TOLERANCE, corrected_count, seeds_in_patient, uniform_seeds

    lo, hi = np.asarray(patient.lo, float), np.asarray(patient.hi, float)
    # solve the seed count for the measured pore size: the Poisson-Voronoi estimate, then
    # corrected for what the cells measure (cells cut by the box walls are smaller). A graded run
    # seeds the rule's density locally and corrects nothing: its cells, pooled over the patient,
    # measured within 0.3 % of their targets (a depth grade in a 6 mm cube, two CT pieces), inside
    # the tolerance that would trigger a correction; --relax 2 makes them 2 % larger
    solving = graded is None and params.seeds is None and params.seed_rule == "pore-size"
    coarse, coarse_grid = seeding if seeding is not None else (None, None)
    weighted = graded is not None and params.weighted
    if graded is not None:
        from .geometry import grade as grading
    tried = []
    for _ in range(PORE_SIZE_PASSES if solving else 1):
        # every pass draws from the same --seed: the seeds are a function of the count alone
        rng = np.random.default_rng(params.seed)
        with prog.stage("seeds", "patient, graded" if graded else f"in the {params.seeds_in}"):
            if graded is not None:
                seeds = grading.draw_seeds(graded.density, rng)
            elif params.seeds_in == "box":
                seeds = uniform_seeds(lo, hi, n, rng)
            else:
                seeds = seeds_in_patient(coarse, coarse_grid, lo, hi, n, rng,
                                         margin=(float(patient.volume) / n) ** (1 / 3),
                                         total=params.seeds is not None)
        prog.note(f"{len(seeds)} seeds drawn in the " + ("patient and one cell's margin"
                                                         if params.seeds_in == "patient" or graded else "box"))
        if len(seeds) > n:
            # a patient's margin holds seeds beyond the count checked before the work started
            # (431,627 drawn for 235,495 in the CT's thin bones): checked again before their cells
            _check_cells_memory(run, params, len(seeds), graded is not None,
                                count_at=_margin_count(coarse, len(seeds), n, params.pore_size,
                                                       (float(patient.volume) / n) ** (1 / 3)))
        if graded is not None and params.relax:
            with prog.stage("relax", f"{params.relax} Lloyd iterations"):
                seeds = grading.lloyd_relax(seeds, graded.density, params.relax)
        with prog.stage("cells", "power, weighted by the pore size" if weighted else ""):
            # in chunks beyond CHUNK_SEEDS, wherever the seeds were drawn (the memory check counted
            # them so): a patient's surface cells that no chunk settles are settled one by one
            cells = voronoi_cells(seeds, lo, hi,
                                  radii=grading.power_radii(graded.density, seeds) if weighted else None)
        if not solving:
            break
        inside = sample(coarse, coarse_grid, cells.seeds) < 0
        measured = float(np.mean(pore_sizes(cells, params.sv)[inside])) if inside.any() else params.pore_size
        tried.append({"seeds_in_patient": n, "seeds": len(seeds), "pore_size_mm": measured})
        if abs(measured / params.pore_size - 1) <= PORE_SIZE_TOLERANCE:
            break
        n = corrected_count(n, measured, params.pore_size)
    release()  # voro++'s cells as Python objects leave megabytes per thousand seeds in the heap
    empty = None
    if weighted:
        # seeds whose power cell is empty are gone: the lattice and the report count the others
        empty = len(seeds) - cells.n
        seeds = cells.seeds
    walls = trabecular_thicknesses(cells, params.sv)
    # the narrowest end of each channel: its window (Sf) or its pore face (Sv), as a disc radius
    windows = min(params.sf, params.sv) * np.sqrt(cells.face_areas[interior_face_pairs(cells)] / np.pi)
    spans = None
    if graded is not None:
        # each wall's cells' seed spacing, rho^(-1/3) of the field's local density at their seeds
        spacing = np.cbrt(1.0 / np.maximum(graded.density.at(cells.seeds), 1e-300))
        pairs = interior_face_pairs(cells)
        spans = (spacing[cells.face_cell[pairs]] + spacing[cells.face_neighbor[pairs]]) / 2
        densest = float(np.min(spacing[sample(coarse, coarse_grid, cells.seeds) < 0], initial=np.inf))
    if params.seeds_in == "patient" or graded is not None:
        near = _faces_near_patient(cells, coarse, coarse_grid)
        walls, windows = walls[near], windows[near]
        spans = None if spans is None else spans[near]
    wall = float(np.median(walls)) if walls.size else float(np.min(hi - lo)) * (1 - params.sv)
    smallest = wall if spans is None or not walls.size else _smallest_pores_wall(walls, spans, densest)
    return _Built(seeds, cells, tried, empty, walls, wall,
                  float(np.percentile(walls, 10)) if walls.size else wall,
                  float(np.percentile(windows, 25)) if windows.size else wall, smallest)


def _smallest_pores_wall(walls: np.ndarray, spans: np.ndarray, densest: float) -> float:
    """The median wall of a graded lattice's smallest pores, mm.

    A wall is ``(1 - Sv)`` times the distance of its two cells' centroids, so it scales with their
    seed spacing: each wall times ``densest / span`` is the wall it would be where the seeds are
    densest, and their median is the median wall of a lattice seeded so everywhere. The median of
    all the walls is that of whichever pores are most numerous, which a grade's small-pore shell
    may not be: there the walls break into fragments first.

    Parameters
    ----------
    walls : (k,) float ndarray, mm
    spans : (k,) float ndarray, mm
        The seed spacing at each wall's two cells (their mean; both seeds in the patient).
    densest : float, mm
        The smallest seed spacing at a seed in the patient, at most `spans` (inf: no seed in the
        patient, the median wall is kept).
    """
    if not np.isfinite(densest):
        return float(np.median(walls))
    return float(np.median(walls * (densest / spans)))


def _skeleton_stage(params: Params, built: _Built, grid: Grid, run: _RunPlan, prog, *, graded: bool):
    """Stage ``skeleton``: the lattice's primitives, and the run's plan on the grid.

    Returns
    -------
    skeleton, edges : the paper's skeleton (whole, or a SkeletonSource built slab by slab)
        or the struts' edges; the other is None.
    slab_voxels : int or None
        Voxels per slab on disk, or None for one slab held in memory (:meth:`_RunPlan.plan`).
    """
    from .fields.lattice import packed_bytes
    from .geometry.skeleton import SkeletonSource, scaled_skeleton, voronoi_edges
    from .run.tiles import blend_halo

    cells = built.cells
    reserve = GRADE_RESERVE if graded else 0
    if params.style != "paper":
        with prog.stage("skeleton"):
            edges = voronoi_edges(cells)
        # planned once the edges are held, so that the memory they take is not also given to the slabs
        return None, edges, run.plan(grid, halo=0, reserve=packed_bytes(edges=edges) + reserve)
    # planned from the cells: a whole grid holds the whole skeleton, a slab the skeleton of
    # the cells that reach it (SkeletonSource), which it counts slab by slab
    from .run.tiled import _band

    source = SkeletonSource(cells, params.sf, params.sv)
    primitives = max(packed_bytes(cells=cells), source.bytes_near(-np.inf, np.inf))
    # a skeleton that takes little of the budget is built once, whole (the slabs then
    # skip building their own); a larger one slab by slab
    whole = primitives <= WHOLE_SKELETON_SHARE * run.max_memory
    # the cut-off is not known yet: a cell's span is wider than any the lattice reads
    span = float(np.median(cells.volumes)) ** (1 / 3)
    slab_voxels = run.plan(grid, halo=blend_halo(grid.spacing, _paper_blend(params, built.wall_p10, built.window_p25)),
                           reserve=primitives + reserve, slab_share=0 if whole else primitives,
                           slab_bytes=None if whole else
                           (lambda h0, h1: source.bytes_near(*_band(grid, (h0, h1), span))))
    whole = whole or slab_voxels is None
    with prog.stage("skeleton", "whole" if whole else "slab by slab"):
        skeleton = scaled_skeleton(cells, params.sf, params.sv) if whole else source
    return skeleton, None, slab_voxels


class _Beside:
    """``fn(*args, **kw)`` in a daemon thread (a run interrupted meanwhile does not wait for
    it); :meth:`result` waits and returns its value, or raises its exception."""

    def __init__(self, fn, *args, **kw):
        import threading

        self._out = None
        self._error = None

        def run():
            try:
                self._out = fn(*args, **kw)
            except BaseException as exc:  # noqa: BLE001 - raised again in the caller's thread
                self._error = exc

        self._thread = threading.Thread(target=run, name="implicit_scaffold-metrics", daemon=True)
        self._thread.start()

    def result(self):
        self._thread.join()
        if self._error is not None:
            raise self._error
        return self._out


def _import_mesh_libraries() -> None:
    import trimesh  # noqa: F401
    from vtkmodules import vtkFiltersCore  # noqa: F401


def _metrics_fit_beside(grid: Grid, triangles: int, tolerance: float, max_memory: int) -> bool:
    """Whether the voxel measures may run beside the mesh (its second pass), its summary and
    write: their arrays and a mesh of `triangles` together within `max_memory`, and nothing else
    compiled and parallel (the simplification) in between."""
    from .run.grid import MORPHOMETRY_BYTES_PER_VOXEL
    from .run.memory import process_memory
    from .mesh.stream import MESH_BYTES_PER_TRIANGLE

    if tolerance > 0:
        return False
    need = process_memory() + MORPHOMETRY_BYTES_PER_VOXEL * grid.size + MESH_BYTES_PER_TRIANGLE * triangles
    return need <= max_memory


def _grade_reach(grade) -> float:
    """How deep (mm) a grade reads the patient's distance: a depth profile's deepest node plus
    its widest pore (the depth bins beyond are one); 0 for the others (they read positions)."""
    from .geometry.grade import GradeProfile

    if isinstance(grade, GradeProfile):
        return float(max(grade.depths)) + float(max(grade.sizes))
    return 0.0


def _grade_report(params: Params, gfield, density, plan, level_field, s, s_p, grid: Grid, cells,
                  max_voxels: int | None = None) -> dict:
    """The graded run's report keys: its field, the offset field and the profiles (:mod:`~implicit_scaffold.geometry.grade`).

    `s` and `s_p` are arrays, or a tiled run's fields on disk (read in chunks of at most `max_voxels`).
    """
    how = {"pore-size": "the density whose cells measure the local target pore size",
           "paper": "the paper's formula with the local pore size"}[params.seed_rule]
    out: dict[str, Any] = {"pore_size_target_mm": None, "seeds_in": "patient (graded)",
                           "seed_rule": f"{params.seed_rule} (graded: {how})", "seeds_paper_rule": None}
    info: dict[str, Any] = {"field": gfield.describe(), "kind": gfield.kind, "relax": params.relax,
                            "weighted": bool(params.weighted),
                            "seeding_voxel_mm": float(density.grid.spacing), "seed_margin_mm": density.margin,
                            "seeds_expected": density.count}
    if gfield.kind == "depth":
        info["profile_mm"] = {"depth": list(gfield.profile.depths), "pore_size": list(gfield.profile.sizes)}
    if level_field is not None:
        info["offset"] = {"coordinate": level_field.coordinate, "nodes": level_field.nodes.tolist(),
                          "levels_mm": level_field.levels.tolist()}
        # one figure for the summary line: the mean offset over the patient
        key = "surface_offset_mm" if params.style == "paper" else "strut_radius_mm"
        out[key] = level_field.mean_inside
        if gfield.kind == "ct":
            out["porosity_target"] = plan.porosity_mean
    info.update(_grade_profiles(params, gfield, s, s_p, grid, cells, max_voxels=max_voxels))
    out["grade"] = info
    return out


def _grade_profiles(params: Params, gfield, s, s_p, grid: Grid, cells, max_voxels: int | None = None) -> dict:
    """The graded report's ``profiles`` (and ``below_skin``), recounted from the fields (:func:`~implicit_scaffold.geometry.grade.profiles`)."""
    from .geometry.grade import profiles

    below = params.skin + params.smooth_cut
    info = {"profiles": profiles(s, grid, cells, params.sv, gfield, s_p, max_voxels=max_voxels, below=below)}
    if below > 0:
        # the skin is solid and the smooth cut takes what it takes: the grade's porosity is
        # met by the voxels below them, which the offset's bins count
        info["below_skin"] = info["profiles"].pop("below")
    return info


def _lattice_plan(params: Params, skeleton, edges, grid: Grid, box_volume: float, wall_p10: float,
                  window_p25: float):
    """Blend width, first cut-off and the rule that widens it, for the lattice field (mm).

    Returns
    -------
    k : float
    cutoff : float
    next_cutoff : callable(level, cutoff) -> float or None
        None when every value the level and the blend read lies within `cutoff`.
    """
    h = grid.spacing
    if params.style == "paper":
        p0 = closed_form_porosity(params.sf, params.sv)
        k = _paper_blend(params, wall_p10, window_p25)
        # estimate of the offset: the porosity change spread over the lattice surface
        area = float((skeleton.quad_areas() if hasattr(skeleton, "quad_areas") else quad_areas(skeleton)).sum())
        t_est = 0.0 if params.porosity is None else (p0 - params.porosity) * box_volume / max(area, 1e-12)
        cutoff = 2 * abs(t_est) + k + 3 * h

        def reach(level):
            return abs(level) + k + 2 * h
    else:
        length = float(np.linalg.norm(edges[:, 1] - edges[:, 0], axis=1).sum())
        r_est = math.sqrt((1 - params.porosity) * box_volume / (math.pi * max(length, 1e-12)))
        k = params.blend if params.blend is not None else 0.25 * r_est
        cutoff = 2 * r_est + 4 * k + 3 * h

        # the smooth minimum sums the edges nearer than the cut-off: keep it well clear
        def reach(level):
            return level + 6 * k + 2 * h

    def next_cutoff(level: float, cutoff: float):
        need = reach(level)
        return None if need <= cutoff else 2 * need

    return float(k), float(cutoff), next_cutoff


def _mesh_correction(volume: float, patient, params: Params, calibration, voxel: float,
                     area: float | None = None, tf=None) -> float | None:
    """The level step after the whole mesh was measured (:func:`~implicit_scaffold.fields.printed.correction`); noted in `calibration`.

    A graded run's level is a field of depth bins, solved in voxels, with no calibration prism;
    its target is the voxels' porosity (``calibration["target"]``) and its slope is measured on
    the finished field `tf` (:func:`_voxel_slope`) over the step that the mesh's ``-area / volume``
    asks for (a blended field's gradient is shorter than 1 at thin walls, where the surface moves
    farther than the level: the area alone undershoots the slope).
    """
    from .fields.printed import correction

    if not calibration or calibration.get("by") != "mesh" or "correction" in calibration:
        return None
    printed = 1.0 - volume / float(patient.volume)
    if calibration.get("graded"):
        if not area or tf is None:
            return None
        guess = (calibration["target"] - printed) / (-float(area) / float(patient.volume))
        calibration["slope_per_mm"] = _voxel_slope(tf, guess) or -float(area) / float(patient.volume)
    step = correction(printed, calibration.get("target", params.porosity), calibration, max_step=voxel)
    if step is not None:
        calibration.update(corrected_by_mm=float(step), printed_before_correction=printed)
    return step


def _voxel_slope(tf, step: float) -> float | None:
    """d porosity / d level (per mm) of the finished field over a level step of `step` mm, in voxels:
    the patient's voxels whose value the step carries across 0 (:func:`~implicit_scaffold.run.tiled.shift_level` makes
    ``max(s - step, s_P)``), over the patient's voxels and the step. None when none crosses."""
    d, crossing = abs(float(step)), 0
    for sl in tf.slabs:
        s, inside = tf.field.read(sl.x0, sl.x1), tf.patient.read(sl.x0, sl.x1) < 0
        band = ((s >= 0) & (s < d)) if step > 0 else ((s < 0) & (s >= -d))
        crossing += int(np.count_nonzero(band & inside))
        del s, inside, band
    return -crossing / (tf.n_inside * d) if crossing and d > 0 else None


#: the simplification may move the printed porosity by this much (a fraction) before a warning
SIMPLIFY_POROSITY = 0.001
#: and the surface by this many voxels
SIMPLIFY_VOXELS = 0.25


def _tolerance(params: Params, voxel: float) -> float:
    """The simplification tolerance of this run, mm (0: none)."""
    return float(params.tolerance)


def _simplify(mesh, tolerance: float, voxel: float, patient_volume: float, prog, max_memory: int):
    """Simplify `mesh` within `tolerance` (:mod:`~implicit_scaffold.mesh.simplify`) and measure what moved.

    Returns
    -------
    mesh : trimesh.Trimesh
        The simplified mesh, or `mesh` when it would not fit in `max_memory`.
    info : dict
        The report's ``simplification``.
    warnings : list of str
        Where the measured error exceeds what the default promises.
    """
    import manifold3d

    from .mesh.marching import mesh_volume
    from .run.memory import process_memory
    from .mesh.simplify import (SIMPLIFY_BYTES_PER_TRIANGLE, euler_characteristic, shared_positions,
                                simplification_error, simplify_mesh)

    before = len(mesh.faces)
    info = {"tolerance_mm": float(tolerance), "tolerance_voxels": float(tolerance / voxel),
            "library": f"manifold3d {getattr(manifold3d, '__version__', '')}".strip(),
            "triangles_before": int(before)}
    need = before * SIMPLIFY_BYTES_PER_TRIANGLE + process_memory()
    if need > max_memory:
        why = (f"not simplified: {before:,} triangles need about {need / 2**30:.1f} GiB to simplify, over "
               f"--max-memory {max_memory / 2**30:.1f} GiB; raise --max-memory, or pass --tolerance 0 to say so")
        return mesh, {**info, "applied": False, "why": why}, [f"the mesh was {why}"]
    volume_before = mesh_volume(mesh)
    with prog.stage("simplify", f"tolerance {tolerance:.4g} mm"):
        simple = simplify_mesh(mesh, tolerance)
    touching = shared_positions(simple) - shared_positions(mesh)
    if touching > 0:
        why = (f"not simplified: the edge collapses brought the surface onto itself ({touching} vertices share a "
               "position), which an STL file and a slicer read as edges of four triangles, not watertight; "
               "pass a smaller --tolerance, or --tolerance 0 to say so")
        return mesh, {**info, "applied": False, "why": why}, [f"the mesh was {why}"]
    with prog.stage("simplify check", "distances between the surfaces"):
        # exact up to half a voxel (and 8 times that for the few points beyond)
        error = simplification_error(mesh, simple, reach=voxel / 2)
    volume = mesh_volume(simple)
    change = (volume_before - volume) / patient_volume
    info.update({
        "applied": True,
        "triangles": int(len(simple.faces)),
        "porosity_before": 1.0 - volume_before / patient_volume,
        "porosity_change": change,
        "max_displacement_mm": error["max_mm"],
        "max_displacement_voxels": error["max_mm"] / voxel,
        "original_to_simplified_mm": error["to_simplified_mm"],
        "simplified_to_original_mm": error["to_original_mm"],
        # handles (tunnels or struts) the edge collapses removed: half the Euler characteristic's rise
        "handles_removed": (euler_characteristic(simple) - euler_characteristic(mesh)) // 2,
        "measured_by": "exact point-triangle distances: every vertex before to the surface after; the vertices, "
                       "edge midpoints and centroids of the triangles after to the surface before",
    })
    found = []
    if error["max_mm"] > SIMPLIFY_VOXELS * voxel:
        found.append(f"the simplified surface lies up to {error['max_mm']:.4g} mm ({error['max_mm'] / voxel:.2f} "
                     "voxels) from the unsimplified one, more than a quarter voxel"
                     + (f" (manifold3d removed {info['handles_removed']} handles: thin struts or small tunnels)"
                        if info["handles_removed"] else "") + "; --tolerance 0 keeps every triangle")
    if abs(change) > SIMPLIFY_POROSITY:
        found.append(f"the simplification moved the printed porosity by {100 * change:+.2f} points; pass a "
                     f"smaller --tolerance (e.g. {tolerance / 2:.3g}) or --tolerance 0")
    return simple, info, found


def _printed_kind(params: Params, mesh: bool, slices, *, graded: bool) -> str | None:
    """What the level is solved for: ``"mesh"``, ``"slices"``, or None (the voxel count).

    A mesh when one is made, else printer slices; a field written alone (``mesh=False``,
    .npy and the volume formats) keeps the voxel count, as does a graded run (its level
    is a field of depth bins, solved in voxels).
    """
    if params.porosity is None or graded:
        return None
    return "mesh" if mesh else ("slices" if slices is not None else None)


#: the patient's voxels per y row, for the calibration prism, are counted on a grid of at most this many voxels
PRISM_ROWS_VOXELS = 2**16


def _prism(grid: Grid, patient=None):
    """The calibration prism's y and z bands (:func:`~implicit_scaffold.fields.printed.prism_bands`),
    placed by the `patient`'s voxels per y row, counted on a coarse grid (:data:`PRISM_ROWS_VOXELS`)
    over the same box."""
    from .fields.printed import prism_bands

    rows = None
    if patient is not None:
        nx, ny, nz = grid.shape
        f = max(1, math.ceil((nx * ny * nz / PRISM_ROWS_VOXELS) ** (1 / 3)))
        coarse = Grid(grid.origin, grid.spacing * f, tuple(-(-n // f) for n in grid.shape))
        counts = np.count_nonzero(patient.sdf_grid(coarse) < 0, axis=(0, 2)).astype(np.float64)
        # fine row j lies nearest coarse row j / f (the two grids share their first voxel's centre)
        rows = counts[np.minimum(np.rint(np.arange(ny) / f).astype(int), counts.size - 1)]
    return prism_bands(grid.shape, rows=rows)


def _printed_level(printed: str, read, level: float, grid: Grid, params: Params, slices, ys, zs,
                   pieces=None, whole_volume: float | None = None):
    """The level that meets the target on what is printed (:func:`~implicit_scaffold.fields.printed.printed_level`),
    from the lattice and patient fields on the calibration prism (and, for a mesh, the grid's
    y-face bands); and the report's record. ``read(ys, zs)`` gives the two fields on a band."""
    from functools import partial

    from .fields.printed import clean_prism, face_bands, face_shave, printed_level, printed_measure

    slices = slices or {}
    base, s_p = read(ys, zs)
    bands, shave = [], None
    if printed == "mesh" and whole_volume:
        # each band with the grid's face row first
        flip = (slice(None), slice(None, None, -1))
        bands = [tuple(np.ascontiguousarray(a[flip] if band.start else a, np.float32) for a in read(band, zs))
                 for band in face_bands(grid.shape, ys)]
        shave = partial(face_shave, spacing=grid.spacing, z_faces=zs.stop - zs.start == grid.shape[2])
    measure = printed_measure(printed, grid, ys, zs, pixel=slices.get("pixel"), layer=slices.get("layer"))
    cut_y, cut_z = (ys.stop - ys.start) < grid.shape[1], (zs.stop - zs.start) < grid.shape[2]
    clean = partial(clean_prism, spacing=grid.spacing, remove_fragments=params.remove_fragments,
                    fill_sealed_voids=params.fill_sealed_voids, pieces=pieces, keep_interior=params.skin > 0,
                    cut_y=cut_y, cut_z=cut_z)
    found, info = printed_level(np.ascontiguousarray(base, np.float32), np.ascontiguousarray(s_p, np.float32),
                                level, measure, spacing=grid.spacing, skin=params.skin, smooth_cut=params.smooth_cut,
                                clean=clean, open_faces=(cut_y, cut_z) if printed == "mesh" else (False, False),
                                bands=bands, shave=shave, whole_volume=whole_volume)
    return found, {"by": printed, **info}


def _paper_blend(params: Params, wall_p10: float, window_p25: float) -> float:
    """The paper style's blend width, mm."""
    # a Gaussian of support k closes a void channel narrower than about k/2: the default
    # rounds the thin walls' creases but stays below the narrow quarter of the windows
    return params.blend if params.blend is not None else min(0.5 * wall_p10, window_p25)


def _base_report(params: Params, patient, box_volume, seeds, cells, cells_in, walls, grid: Grid, k, cutoff,
                 level, porosity_voxel, fragments, sealed, seed_solve=None) -> dict:
    """The report's keys that a whole-grid and a tiled run share."""
    from .measure.metrics import cell_metrics

    report: dict[str, Any] = {
        "version": __version__,
        "rng_seed": params.seed,
        "patient": getattr(patient, "describe", lambda: type(patient).__name__.lower())(),
        "patient_volume_mm3": float(patient.volume),
        "patient_source": _patient_source(patient),
        "box_volume_mm3": box_volume,
        "seeds": int(len(seeds)),
        "seeds_in": params.seeds_in,
        "cells_in_scaffold": int(np.count_nonzero(cells_in)),
        "skin_mm": params.skin,
        "smooth_cut_mm": params.smooth_cut,
        "pore_size_target_mm": params.pore_size if params.seeds is None else None,
        # how the seed count was chosen; the paper's formula's count beside it, for comparison
        "seed_rule": None if params.seeds is not None else params.seed_rule,
        "seeds_paper_rule": None if params.seeds is not None else _paper_count(params, patient, box_volume),
        "seed_solve": seed_solve,
        "sf": params.sf,
        "sv": params.sv,
        "style": params.style,
        "porosity_closed_form": closed_form_porosity(params.sf, params.sv),
        "porosity_target": params.porosity,
        "blend_mm": float(k),
        "voxel_mm": float(grid.spacing),
        "grid_shape": list(grid.shape),
        "grid_origin_mm": list(grid.origin),
        "cutoff_mm": float(cutoff),
        "porosity_voxel": porosity_voxel,
        "fragments_removed": fragments,
        # counted before filling; a filled void is solid in the field, the mesh and the slices
        "sealed_voids": {"count": int(sealed[0]), "volume_mm3": float(sealed[1] * float(grid.spacing) ** 3),
                         "filled": bool(params.fill_sealed_voids)},
        "wall_thickness_mm": _report_stats(walls) if walls.size else None,
    }
    if params.style == "paper":
        report["surface_offset_mm"] = float(level)
    else:
        report["strut_radius_mm"] = float(level)
    report.update(cell_metrics(cells, params.sf, params.sv, cells_in))
    return report


def _patient_source(patient) -> dict | None:
    """How to build the patient again: its file and options, or the built-in shape; None for an
    object given to :func:`generate` directly."""
    from .fields.patient import SHAPES

    source = getattr(patient, "load_options", None)  # set by patient_io.load_patient
    if source is not None:
        return dict(source)
    for name, cls in SHAPES.items():
        if type(patient) is cls:
            return {"shape": name, "size": [float(v) for v in patient.size]}
    return None


def _paper_count(params: Params, patient, box_volume: float) -> int:
    """The paper's seed count n = V P / (pi Dp^3 / 6) for these options (V: where the seeds are drawn)."""
    from .geometry.seeds import seed_count

    porosity = params.porosity if params.porosity is not None else closed_form_porosity(params.sf, params.sv)
    return seed_count(box_volume if params.seeds_in == "box" else float(patient.volume), porosity,
                      params.pore_size)


#: bytes a graded run holds beside the slabs: the seeding grid, the offset's sample of
#: :data:`~implicit_scaffold.geometry.grade.LEVEL_SAMPLE_VOXELS` voxels with its sort, and the per-bin histograms of
#: :class:`~implicit_scaffold.run.tiles.GroupQuantile` (1.5 MiB a bin)
GRADE_RESERVE = 320 * 2**20
#: a tiled run builds the whole skeleton once when it (and its packed primitives) take at
#: most this share of --max-memory, else slab by slab
WHOLE_SKELETON_SHARE = 0.25
#: bytes: a slab refusal offers a larger voxel only where the budget leaves this much beside what the run holds
#: (what the process holds moves by some MiB from one run to the next)
VOXEL_ADVICE_ROOM = 32 * 2**20
#: a refusal names this much more than the estimate of the smallest budget: the estimate
#: before the cells are built is short of the one after by what the process grows
SMALLEST_MARGIN = 1.1


class _RunPlan:
    """Whole grid or slabs: decided from the memory bound, checked before the work starts."""

    def __init__(self, run_bytes: int, max_memory: int, tiled, params: Params, patient, out_path, slices,
                 workers: int = 1):
        self.run_bytes, self.max_memory, self.tiled = run_bytes, max_memory, tiled
        self.workers = int(workers)  # local processes for the lattice pass of a run in slabs
        self.params, self.patient, self.out_path, self.slices = params, patient, out_path, slices

    @property
    def forced_voxels(self) -> int | None:
        """The voxels per slab asked for by ``tiled=<int>``, else None."""
        return None if isinstance(self.tiled, bool) or not self.tiled else int(self.tiled)

    def plan(self, grid: Grid, halo: int = 0, reserve: int = 0, slab_share: int = 0,
             slab_bytes=None, span: float | None = None) -> int | None:
        """None for one slab held in memory (the whole grid), else the voxels a slab on disk may hold;
        raise if neither fits.

        `reserve` is what the stages hold beside the grid's voxels on the whole grid (the
        lattice's primitives, :func:`~implicit_scaffold.fields.lattice.packed_bytes`); of that, `slab_share` is
        built slab by slab in a tiled run, in proportion to the slab's voxels (twice, for the
        primitives that reach a slab from beyond it). Every stage's thinnest slab must fit
        beside what the process holds and the reserve, from the lattice to the mesh: a
        budget too small for that is refused now, naming the smallest that would do.
        `slab_bytes(h0, h1)`, when given, is what the lattice's primitives take for the
        slab of planes ``[h0, h1)`` (halo included), known per slab
        (:meth:`~implicit_scaffold.geometry.skeleton.SkeletonSource.bytes_near`): the slabs are then thinned until
        the most crowded one fits. Before the cells, `span` (a cell's size, mm) estimates it: the primitives
        of the cells within a span of the thinnest slab, the cells spread evenly along x.
        """
        from .run.memory import format_size, release
        from .run.tiled import SLAB_BYTES_PER_VOXEL, STAGE_RESERVE, WORKER_RESERVE, check_disk
        from .run.tiles import plan_slabs

        held = release() + STAGE_RESERVE
        whole = grid.memory_estimate(self.run_bytes) + held + int(reserve)
        self.whole_bytes = whole
        held += int(reserve) - int(slab_share)
        per_voxel = SLAB_BYTES_PER_VOXEL + 2 * int(slab_share) / grid.size
        if self.tiled is False or (self.tiled is None and whole <= self.max_memory):
            check_memory(grid, self.run_bytes)
            return None
        ext = output_format(self.out_path) if self.out_path is not None else None
        self.patient.sdf_grid(grid, x_range=(0, 1))  # a patient that cannot be tiled says so now
        # what the process holds once the patient has run (its compiled code loaded, e.g. numba's)
        held = release() + STAGE_RESERVE + int(reserve) - int(slab_share)
        # worker processes (--workers) each hold a slab of the lattice pass at once, and their own
        # runtime and packed primitives (each packs them for its device queue) beside what they
        # share with this process; this process then holds no slab (the workers write theirs to
        # disk), and the later passes run here once the workers are gone
        n = self.workers
        if n > 1:
            held += n * (WORKER_RESERVE + int(reserve) - int(slab_share))
        from .mesh.stream import MESH_HALO_PLANES, MESH_SLAB_BYTES_PER_VOXEL

        plane = grid.shape[1] * grid.shape[2]
        thinnest = int((1 + 2 * halo) * plane * per_voxel * n)
        # the primitives are not spread evenly: the most crowded slab of one plane is the thinnest
        # that must fit (a patient's surface cells reach the box's walls and crowd every slab they
        # cross), else a refusal names a budget that the slabs then refuse; a larger voxel does
        # not thin it (a plane then spans more cells)
        crowded = (n * _worst_slab(grid, halo, 1, slab_bytes)
                   if slab_bytes is not None and not self.forced_voxels else 0)
        # the budget a refusal names: before the cells (`span` given, no `slab_bytes`), enough for the
        # thinnest slab to hold every primitive, since the cells' own check after them counts the slab's
        # cells, and the cells at a patient's surface reach the box's walls and crowd every slab (a femur
        # head's 127^3 grid: 32 % of the primitives in its most crowded slab); a refusal here named 770M,
        # which that check then refused naming 920M
        named = SMALLEST_MARGIN * (held + thinnest)
        if slab_bytes is None and span is not None and slab_share and not self.forced_voxels:
            # a slab holds the primitives of the cells within a cell's `span` (mm) of it: that share of
            # them where the cells spread evenly along x, the least it needs
            reach = min(1.0, ((1 + 2 * halo) * grid.spacing + 2 * span) / (grid.shape[0] * grid.spacing))
            crowded = n * int((1 + 2 * halo) * plane * SLAB_BYTES_PER_VOXEL + reach * slab_share)
            named = max(named, held + n * ((1 + 2 * halo) * plane * SLAB_BYTES_PER_VOXEL + slab_share))
        # fewer cells where the slab's primitives outweigh its voxels, else a coarser voxel
        voxels_part = n * (1 + 2 * halo) * plane * SLAB_BYTES_PER_VOXEL
        if ext in MESH_FORMATS:
            thinnest = max(thinnest, (1 + 2 * MESH_HALO_PLANES) * plane * MESH_SLAB_BYTES_PER_VOXEL)
        # a slab's voxels go as the plane's, 1 / voxel^2; the cells' primitives and what is held do not: the voxel
        # whose thinnest slab takes half the room beside them (the mesh's slab counted: without it, 650M asked a
        # 0.04 mm cube's STL for "a larger --voxel (e.g. 0.0263 mm)"). What is held counts with the margin a named
        # budget allows for: it grows by the cells' arrays after a check before them (`span`), and moves by tens of
        # MiB from one process to the next (0.61 to 0.65 GiB for a 6 mm cube's run beside two others); no voxel is
        # offered where the room is within that
        room = self.max_memory - SMALLEST_MARGIN * held - (max(crowded - voxels_part, 0) if crowded > thinnest else 0)
        fix = (", or use a larger --pore-size (fewer cells)" if crowded > thinnest and crowded > 2 * voxels_part else
               f", or use a larger --voxel (e.g. {grid.spacing * (2 * thinnest / room) ** 0.5:.3g} mm)"
               if room >= VOXEL_ADVICE_ROOM and thinnest > room / 2 else "")
        thinnest = max(thinnest, crowded)
        smallest = held + thinnest
        named = max(named, SMALLEST_MARGIN * smallest)
        if smallest > self.max_memory and self.tiled in (None, True):
            raise ScaffoldError.for_budget(
                f"a grid of {grid.shape[0]}x{grid.shape[1]}x{grid.shape[2]} voxels needs about "
                f"{format_size(smallest)} of memory even in slabs (its thinnest slab beside "
                f"{held / 2**30:.2f} GiB of cells, skeleton and libraries"
                + (f", in each of {n} workers" if n > 1 else "") + ") but --max-memory is "
                f"{format_size(self.max_memory)}: pass --max-memory {format_size(named)} "
                "or more" + fix + (", or fewer --workers" if n > 1 else ""), named)
        voxels = self.forced_voxels or max(1, int((self.max_memory - held) // (per_voxel * n)))
        if n > 1 and not self.forced_voxels:
            # a slab for every worker at least
            voxels = min(voxels, (-(-int(grid.shape[0]) // n) + 2 * halo) * plane)
        if slab_bytes is not None and not self.forced_voxels:
            voxels = self._thin_for(grid, halo, held, slab_bytes, voxels)
        plan_slabs(grid.shape, max_voxels=max(voxels, (1 + 2 * halo) * plane), halo=halo)
        check_disk(grid)
        return voxels

    def _thin_for(self, grid: Grid, halo: int, held: int, slab_bytes, voxels: int) -> int:
        """The largest slab (voxels, halo included) whose every slab fits with its primitives."""
        from .run.memory import format_size

        plane = grid.shape[1] * grid.shape[2]
        planes = max(1, voxels // plane - 2 * halo)
        while True:
            # as many slabs at once as workers (held counts their runtimes)
            worst = self.workers * _worst_slab(grid, halo, planes, slab_bytes)
            if held + worst <= self.max_memory:
                return (planes + 2 * halo) * plane
            if planes == 1:
                named = SMALLEST_MARGIN * (held + worst)
                raise ScaffoldError.for_budget(
                    f"the lattice of the most crowded slab of {grid.shape[0]}x{grid.shape[1]}x{grid.shape[2]} voxels "
                    f"needs about {format_size(held + worst)} with what the run holds, but --max-memory is "
                    f"{format_size(self.max_memory)}: pass --max-memory {format_size(named)}"
                    " or more, or use a larger --pore-size (fewer cells)", named)
            planes = max(1, int(planes * 0.7))


def _steady_voxels(voxels: int, plane: int) -> int:
    """`voxels` rounded down to whole planes of `plane` voxels, their count to the ladder
    1, 2, 3, 4, 6, 8, 12, 16, 24, ... (a power of two, or one and a half of one).

    The mesh's bytes depend on its slabs (:func:`~implicit_scaffold.mesh.stream.write_mesh_slabs`), and its
    slabs on what memory is left, which moves by some MiB from one run to the next (the femoral
    shaft's 4 mm clip at 0.02 mm gave two STL files from the same code and seed): on the ladder
    the same inputs and budget give the same slabs, at the cost of at most a third of a slab.
    """
    planes = max(1, int(voxels) // max(1, int(plane)))
    top = 1 << (planes.bit_length() - 1)
    return (top + top // 2 if planes >= top + top // 2 and top >= 2 else top) * int(plane)


def _worst_slab(grid: Grid, halo: int, planes: int, slab_bytes) -> int:
    """The bytes of the most crowded slab of the lattice pass when slabs own `planes` planes:
    its voxels and, by `slab_bytes(h0, h1)`, its primitives."""
    from .run.tiled import SLAB_BYTES_PER_VOXEL
    from .run.tiles import plan_slabs

    plane = grid.shape[1] * grid.shape[2]
    slabs = plan_slabs(grid.shape, max_voxels=(planes + 2 * halo) * plane, halo=halo)
    return max((s.h1 - s.h0) * plane * SLAB_BYTES_PER_VOXEL + slab_bytes(s.h0, s.h1) for s in slabs)


def _slab_morphometry(tf, grid: Grid, cells, run: _RunPlan, prog) -> dict:
    """The voxel measures of a tiled run, slab by slab (:func:`~implicit_scaffold.measure.morphometry.morphometry_by_slabs`):
    the whole grid's keys, meanings and figures.

    The local thickness's halo starts at the 99th percentile of the cells' sphere diameters
    (the widest pores are about their cells' size); the measure widens it wherever a voxel
    reads a thickness above it, so the figures are exact whatever the start.
    """
    from .run.memory import release
    from .measure.morphometry import SLAB_MORPHOMETRY_BYTES_PER_VOXEL, morphometry_by_slabs

    # the widest pore is about the widest cell's sphere; a patient's surface cells run to the box's
    # walls, so the 99th percentile starts it, and the measure widens the halo where that falls short
    halo = int(math.ceil(float((6 * np.percentile(cells.volumes, 99) / math.pi) ** (1 / 3)) / grid.spacing))
    max_voxels = max(1, max(0, run.max_memory - release()) // SLAB_MORPHOMETRY_BYTES_PER_VOXEL)
    # slabs of the size asked for (tiled=<voxels>), whatever the halo
    planes = max(1, run.forced_voxels // (grid.shape[1] * grid.shape[2])) if run.forced_voxels else None
    with prog.stage("metrics", "by slabs"):
        # one solid piece left (or none) stays one when sealed voids are filled: each lies against the
        # solid all round. More are labelled again (filling may join two)
        found = morphometry_by_slabs(tf.field, tf.patient, grid.spacing, max_voxels=max_voxels, halo=halo,
                                     planes=planes, progress=prog.bar("metrics"),
                                     solid_pieces=tf.pieces if tf.pieces <= 1 else None)
    found.pop("morphometry_halo_planes", None)
    return found


def _slab_certificate(tf, grid: Grid, printer, run: _RunPlan, prog):
    """The print certificate of a tiled run, slab by slab (:func:`~implicit_scaffold.measure.printability.certificate_by_slabs`):
    the whole grid's figures and section maps, in slabs that fit what --max-memory leaves."""
    from .run.memory import release
    from .measure.printability import SLAB_CERTIFICATE_BYTES_PER_VOXEL, certificate_by_slabs

    # slabs of the size asked for (tiled=<voxels>), else as large as the budget allows
    max_voxels = run.forced_voxels or max(1, max(0, run.max_memory - release()) // SLAB_CERTIFICATE_BYTES_PER_VOXEL)
    with prog.stage("print check", printer.name):
        return certificate_by_slabs(tf.field, tf.patient, grid.spacing, printer, max_voxels=max_voxels,
                                    origin=grid.origin, progress=prog.bar("print check"))


def _build(run: _RunPlan, params: Params, patient, grid: Grid, cells, skeleton, edges, seeds, walls,
           wall_p10, window_p25, slab_voxels: int | None, scheduler, prog, mesh: bool, out_path,
           morphometry: bool = True, seed_solve=None, grade=None, printer=None, repair: bool = False,
           printed_wall: float | None = None, mechanics=None) -> Result:
    """From the cells' primitives to the outputs: the field by the one slab driver
    (:func:`~implicit_scaffold.run.tiled.tiled_scaffold`), the report, then the mesh, measures, certificate and files.

    `slab_voxels` None holds the whole grid as one slab in memory; the outputs are then made
    from the arrays (:func:`_finish_in_memory`), else slab by slab from the fields on disk
    (:func:`_finish_in_slabs`); the report's keys mean the same either way. `grade` is a
    graded run's ``(GradeField, SeedDensity, empty power cells or None)``; `printer` a
    PrinterProfile to certify what was built for; `mechanics` ``(MechanicsSpec, max_memory)``
    the stiffness to measure on what was built (:func:`_measure_mechanics`).
    """
    from .fields.patient import SHAPES
    from .run.executor import executor_for
    from .run.tiled import sample_slabs, tiled_scaffold

    in_memory = slab_voxels is None
    box_volume = float(np.prod(np.asarray(patient.hi, float) - np.asarray(patient.lo, float)))
    k, cutoff, next_cutoff = _lattice_plan(params, skeleton, edges, grid, box_volume, wall_p10, window_p25)
    # the lattice's workers launch OpenCL kernels: started afresh, not forked from this process,
    # whose OpenCL runtime already runs threads of its own
    executor = executor_for(workers=1 if in_memory else run.workers, scheduler=None if in_memory else scheduler,
                            method="spawn")
    printed, calibration = _printed_kind(params, mesh, run.slices, graded=grade is not None), {}
    search = None
    if printed is not None:
        bands = _prism(grid, run.patient)

        def level_for(read, level, pieces):
            found, info = _printed_level(printed, read, level, grid, params, run.slices, *bands, pieces=pieces,
                                         whole_volume=float(patient.volume))
            calibration.clear()
            calibration.update(info)
            return found

        search = (bands, level_for)
    one_piece = isinstance(patient, tuple(SHAPES.values()))
    try:
        tf = tiled_scaffold(style=params.style, skeleton=skeleton, edges=edges, patient=run.patient, grid=grid,
                            porosity=params.porosity, k=k, cutoff=cutoff, next_cutoff=next_cutoff,
                            remove_fragments=params.remove_fragments, max_voxels=slab_voxels, executor=executor,
                            patient_pieces=not one_piece, fill_sealed_voids=params.fill_sealed_voids,
                            printed=search, prog=prog, skin=params.skin, smooth_cut=params.smooth_cut,
                            grade=None if grade is None or (params.porosity is None and grade[0].kind != "ct")
                            else grade[0], in_memory=in_memory)
    finally:
        executor.close()
    try:
        # a depth or function grade meets one porosity everywhere: its walls too can break at the voxel (a 5 mm cube
        # of --grade 0:0.5 at 0.15 mm came out at porosity 0.9847 for 0.8, with a warning); a CT's varies with the bone
        if grade is None or grade[0].kind != "ct":
            _check_collapsed(tf, params, grid.spacing, printed_wall, calibration)
        cells_in = (sample(tf.patient.field, grid, cells.seeds) if in_memory
                    else sample_slabs(tf.patient, grid, cells.seeds)) < 0
        report = _base_report(params, patient, box_volume, seeds, cells, cells_in, walls, grid, k, tf.cutoff,
                              tf.level, 1.0 - tf.solid / tf.n_inside, tf.fragments, tf.sealed, seed_solve=seed_solve)
        report["fragments_removed_mm3"] = (None if tf.fragments is None
                                           else tf.fragments_voxels * grid.voxel_volume)
        report["printed_level"] = calibration or None
        if grade is not None:
            gfield, density, empty = grade
            if report["printed_level"] is None and params.porosity is not None:
                report["printed_level"] = {"by": None, "why": "graded: the level is solved per depth bin in voxels"}
            with prog.stage("profiles"):
                fields = (tf.field.field, tf.patient.field) if in_memory else (tf.field, tf.patient)
                report.update(_grade_report(params, gfield, density, tf.level_plan, tf.level_field, *fields,
                                            grid, cells, max_voxels=slab_voxels))
            if empty is not None:
                report["grade"]["empty_power_cells"] = empty
            tf.level_plan = tf.level_field = None  # the mesh and metrics stages need the memory
            if mesh and params.porosity is not None and (out_path is None or output_format(out_path) in MESH_FORMATS):
                # then one step on what is printed (a mesh; a field written alone keeps the voxels' count,
                # as generate(mesh=False) does, so that a design's build and its rebuild are one field):
                # the whole mesh measured and the level field shifted,
                # so that the mesh holds the porosity asked for; under a skin or a smooth cut, which take
                # what they take whatever the level, the porosity the bins met in voxels
                skinned = params.skin + params.smooth_cut > 0
                calibration.update(by="mesh", graded=True,
                                   target=float(report["porosity_voxel" if skinned else "porosity_target"]),
                                   why="graded: the level is solved per depth bin in voxels, then moved by one "
                                       "step for the whole mesh's porosity to meet "
                                       + ("the voxels'" if skinned else "the target")
                                       + ", with the slope measured on the voxels")
                report["printed_level"] = calibration
        elif params.porosity is not None and report["printed_level"] is None:
            report["printed_level"] = {"by": None, "why": "no mesh or slices: the field meets the target in voxels"}
        if not in_memory:
            report["tiled"] = {"slabs": len(tf.slabs), "planes_per_slab": max(sl.x1 - sl.x0 for sl in tf.slabs),
                               "max_memory_mb": round(run.max_memory / 2**20, 1),
                               "scheduler": None if scheduler is None else str(getattr(scheduler, "scheduler",
                                                                                         scheduler)),
                               "workers": min(run.workers, len(tf.slabs)) if scheduler is None else None}
        report["bodies_voxels"] = tf.pieces
        report["patient_pieces_count"] = tf.patient_pieces
        if repair:
            _repair(tf, report, params, printer, grid, prog, one_piece, None if in_memory else run)
            if calibration and not report["repair"]["holds"]["porosity"]:
                # a level moved for the printed porosity would undo the repair where it moved the porosity
                calibration["correction"] = "none: the repair moved the porosity (see repair.why)"
        finish = _finish_in_memory if in_memory else _finish_in_slabs
        result = finish(tf, report, run, params, patient, grid, cells, cells_in, calibration, prog, mesh,
                        out_path, morphometry, printer, one_piece=one_piece, slab_voxels=slab_voxels)
        if grade is not None and calibration.get("corrected_by_mm") is not None:
            # the printed step moved every bin's voxels: their profiles are recounted
            with prog.stage("profiles", "after the printed step"):
                fields = (tf.field.field, tf.patient.field) if in_memory else (tf.field, tf.patient)
                report["grade"].update(_grade_profiles(params, grade[0], *fields, grid, cells,
                                                       max_voxels=slab_voxels))
        result.skeleton, result.edges, result.timings = skeleton, edges, prog.timings
    finally:
        tf.close()
    if mechanics is not None:
        from .measure.mechanics import solve_accuracy, solve_goal

        tol = mechanics[0].tol
        with prog.stage("mechanics", "voxel finite elements"):
            _measure_mechanics(result, *mechanics,
                               progress=prog.solver(goal=solve_goal(tol), accuracy=solve_accuracy(tol)))
    from .run.memory import peak_memory

    if out_path is not None:
        from .io.files import written_path

        report["file_size_bytes"] = written_path(out_path).stat().st_size
    report["peak_memory_mb"] = round(peak_memory() / 2**20, 1)
    if report.get("mesh_workers", 1) > 1 or ((report.get("tiled") or {}).get("workers") or 1) > 1:
        # the lattice's or the mesh stage's worker processes: the largest one's peak
        report["peak_memory_workers_mb"] = round(peak_memory(children=True) / 2**20, 1)
    report["timings_s"] = {k2: round(v, 4) for k2, v in prog.timings.items()}
    report["peak_memory_after_stage_mb"] = {k2: round(v / 2**20, 1) for k2, v in prog.high_water.items()}
    if out_path is not None:
        from .io.files import write_json

        write_json(report, report_path(out_path))
    return result


#: what a run in slabs holds when its solve starts beyond what it held before the lattice: the
#: libraries its mesh and measure stages load (measured 240 MiB on the default cube in slabs)
LATER_STAGES_BYTES = 320 * 2**20


def _check_mechanics(spec, params: Params, patient, grid: Grid, walls, max_memory, *, kept: int,
                     kept_in_memory: int = 0, whole: int | None = None) -> None:
    """Refuse, before the lattice, a run whose stiffness solve cannot fit its budget: the decision
    :func:`_measure_mechanics` takes after the build (:func:`~implicit_scaffold.measure.mechanics.plan_voxel`), taken on the
    planned grid with the solid it will hold, ``1 - P`` of the patient's volume (the closed-form
    porosity without a target), the cells' median wall, and `kept`, the bytes the build will still
    hold then. A run in slabs (`whole`, its whole grid's estimate) that a refusal's budget would hold
    in memory is checked as one (`kept_in_memory`), so that the budget named is one that works."""
    from .measure.mechanics import plan_voxel
    from .fields.patient import Box

    boundary = spec.boundary
    if boundary == "auto":
        # as _measure_mechanics will find it: a box patient is a box sample
        boundary = "periodic" if isinstance(patient, Box) else "kinematic"
    p = params.porosity if params.porosity is not None else closed_form_porosity(params.sf, params.sv)
    solid = min(int(np.prod(grid.shape, dtype=np.int64)),
                int(math.ceil((1.0 - p) * float(patient.volume) / grid.voxel_volume)))
    if whole is not None:
        from .measure.mechanics import sample_memory
        from .run.memory import release

        # the budget the solve at the run's voxel needs beside the slabs' leftovers: one that holds the
        # whole grid runs it in memory, which leaves more behind
        if whole <= release() + kept + sample_memory(grid.shape, solid, grid.spacing, grid.spacing,
                                                     boundary=boundary):
            kept = kept_in_memory
    plan_voxel(grid.shape, solid, grid.spacing, max_memory=max_memory, voxel=spec.voxel,
               wall=float(np.median(walls)) if len(walls) else None, boundary=boundary,
               held_extra=kept)


def _measure_mechanics(result: Result, spec, max_memory, progress=None) -> None:
    """The stiffness of what was built, into ``result.report["mechanics"]`` and ``result.compression``.

    The solid comes from the field at the mechanics voxel (:func:`~implicit_scaffold.measure.mechanics.solid_for_solve`),
    a few planes at a time, so a slab run's field on disk is never held whole; the solve's memory
    is checked against the budget before it starts.
    """
    from .measure.mechanics import measure_sample, solid_box, solid_for_solve

    boundary = spec.boundary
    if boundary == "auto" and result.patient_sdf is not None:
        # a box patient is a box sample (periodic); any other shape is not (kinematic)
        lo, hi, count = solid_box(result.patient_sdf)
        boundary = "periodic" if count and count == int(np.prod(hi - lo)) else "kinematic"
    wall = (result.report.get("wall_thickness_mm") or {}).get("median")
    sample = solid_for_solve(result.field, result.grid, max_memory=max_memory, voxel=spec.voxel, wall=wall,
                             boundary=boundary)
    result.report["mechanics"], result.compression = measure_sample(sample, spec.material, boundary=boundary,
                                                                    axis="xyz".index(spec.axis), progress=progress,
                                                                    tol=spec.tol)
    mech = result.report["mechanics"]
    for warning in (sample.report["warning"], mech["solver"]["warning"], mech["compression"]["warning"]):
        if warning:
            result.report.setdefault("warnings", []).append(warning)


def _correct(tf, step: float, report: dict, params: Params, grid: Grid, prog, one_piece: bool,
             why: str | None = None) -> None:
    """Move the finished field's surface by `step` mm (:func:`~implicit_scaffold.run.tiled.shift_level`), clean its
    fragments and sealed voids again, and update the report."""
    from .run.tiled import shift_level

    with prog.stage("correct", why or f"level {step:+.3g} mm for the mesh's porosity"):
        more = shift_level(tf, step, remove_fragments=params.remove_fragments,
                           fill_sealed_voids=params.fill_sealed_voids, keep_interior=params.skin > 0,
                           patient_pieces=not one_piece, progress=prog.bar("correct"))
    report["surface_offset_mm" if params.style == "paper" else "strut_radius_mm"] = tf.level
    report["porosity_voxel"] = 1.0 - tf.solid / tf.n_inside
    if report.get("fragments_removed") is not None:
        report["fragments_removed"] += more[0]
        report["fragments_removed_mm3"] = tf.fragments_voxels * grid.voxel_volume
    report["sealed_voids"]["count"] += more[1]
    report["sealed_voids"]["volume_mm3"] += more[2] * grid.voxel_volume
    report["bodies_voxels"] = tf.pieces


def _repair(tf, report: dict, params: Params, printer, grid: Grid, prog, one_piece: bool,
            run: _RunPlan | None = None) -> None:
    """Stage ``repair``: the field repaired for the printer (:func:`~implicit_scaffold.fields.repair.repair`), cleaned of the
    fragments and sealed voids it may leave, and the report's figures updated. A run in slabs
    (`run` given) repairs its field on disk slab by slab (:func:`~implicit_scaffold.fields.repair.repair_by_slabs`),
    each slab within what --max-memory leaves: the same field, bit for bit."""
    from .fields.repair import SLAB_REPAIR_BYTES_PER_VOXEL, repair, repair_by_slabs

    with prog.stage("repair", printer.name):
        # the voxels' porosity as built is what is kept: the level met the target (or the printed
        # geometry's) already
        if run is None:
            repaired, info = repair(tf.field.field, tf.patient.field, grid.spacing, printer, porosity=None,
                                    progress=prog.bar("repair"))
            tf.field.field[...] = repaired
            del repaired
        else:
            from .run.memory import release

            max_voxels = run.forced_voxels or max(1, max(0, run.max_memory - release()) // SLAB_REPAIR_BYTES_PER_VOXEL)
            info = repair_by_slabs(tf.field, tf.patient, grid.spacing, printer, porosity=None, max_voxels=max_voxels,
                                   progress=prog.bar("repair"))
    _correct(tf, 0.0, report, params, grid, prog, one_piece, why="fragments and sealed voids after the repair")
    report["repair"] = info


def _mesh_report(report: dict, summary: dict, patient) -> None:
    """The mesh's keys of the report, from :func:`~implicit_scaffold.mesh.marching.mesh_summary` (or the streamed mesh's summary)."""
    report.update({
        "triangles": summary["triangles"],
        "watertight": summary["watertight"],
        "winding_consistent": summary["winding_consistent"],
        "bodies": summary.get("bodies", report.get("bodies_voxels")),
        "mesh_volume_mm3": summary["volume_mm3"],
        "surface_area_mm2": summary["surface_area_mm2"],
        "porosity_mesh": 1.0 - summary["volume_mm3"] / float(patient.volume),
    })
    report["porosity_printed"] = report["porosity_mesh"]


def _fragments_per_piece(report: dict) -> None:
    """The report's ``fragments``: solid pieces besides each patient piece's main body. The voxel
    measures count the pieces besides one, over the whole grid: a femur in three pieces, each a
    body, read 2."""
    if report.get("fragments") is not None and report.get("patient_pieces_with_solid", 1) > 1:
        report["fragments"] = max(0, report["fragments"] + 1 - report["patient_pieces_with_solid"])


def _pieces_report(report: dict, rows: list[dict]) -> str | None:
    """The report's patient pieces (:func:`~implicit_scaffold.run.pieces.piece_table`'s rows); a warning for the pieces
    too small to hold one pore (the target's, or the mean measured), or None."""
    from .run.pieces import REPORT_PIECES, small_pieces_warning

    report["patient_pieces_count"] = len(rows)
    report["patient_pieces"] = rows[:REPORT_PIECES]
    # each piece's main body is no fragment (the morphometry counts pieces besides one: _fragments_per_piece)
    report["patient_pieces_with_solid"] = sum(1 for r in rows if r.get("bodies"))
    pore = report["pore_size_target_mm"] or (report.get("pore_size_mm") or {}).get("mean")
    return (small_pieces_warning(rows, math.pi * pore ** 3 / 6, pore, source=report.get("patient_source"))
            if pore else None)


def _finish_in_memory(tf, report: dict, run: _RunPlan, params: Params, patient, grid: Grid, cells, cells_in,
                      calibration: dict, prog, mesh: bool, out_path, morphometry: bool, printer, *,
                      one_piece: bool, slab_voxels=None) -> Result:
    """The outputs of a run held in memory: the patient's pieces, the mesh, the voxel measures,
    the certificate, the slices and the files, from the field's arrays."""
    from .run.pieces import label_pieces, one_piece_table, piece_table

    s, s_p = tf.field.field, tf.patient.field
    h = grid.spacing
    inside = s_p < 0 if morphometry or printer is not None else None
    if one_piece and params.remove_fragments:
        # a primitive keeping its main body: its one row from what the passes counted, as in slabs
        small_pieces = _pieces_report(report, one_piece_table(
            tf.n_inside, tf.solid, int(np.count_nonzero(cells_in)), min(tf.pieces, 1), tf.inside_box, grid))
    else:
        with prog.stage("pieces"):
            pieces, n_pieces = label_pieces(s_p < 0 if inside is None else inside)
            small_pieces = _pieces_report(report, piece_table(
                pieces, n_pieces, s < 0, grid, cells.seeds[cells_in],
                main_bodies_only=params.remove_fragments and n_pieces == 1))
            del pieces

    result = Result(params=params, report=report, cells=cells, skeleton=None, edges=None, grid=grid,
                    field=s, patient_sdf=s_p, patient=patient, timings=prog.timings)
    simplify_warnings = []
    metrics_job, written = None, False
    if mesh:
        from .mesh.marching import mesh_field, mesh_summary, mesh_volume

        with prog.stage("mesh"):
            # mesh_summary below checks closure and winding; no need to check twice
            result.mesh = mesh_field(s, grid, check=False)
        # the volume alone decides on a correction; the full summary is of the final mesh
        step = _mesh_correction(mesh_volume(result.mesh), patient, params, calibration, h, area=result.mesh.area,
                                tf=tf)
        tolerance = _tolerance(params, h)

        def measure_beside(triangles):
            from .measure.morphometry import morphometry as measure

            # the voxel measures run in a second thread while the mesh is made again, summed
            # up and written (they overlap well on 2 cores: compiled loops and file writes that
            # release the interpreter); the field is final from here on
            if morphometry and _metrics_fit_beside(grid, triangles, tolerance, run.max_memory):
                return _Beside(measure, s < 0, h, region=inside, surface=False)
            return None

        if step is not None:
            triangles = len(result.mesh.faces)  # the second mesh's is about the same
            result.mesh = None  # its memory, before the second mesh
            _correct(tf, step, report, params, grid, prog, one_piece)
            metrics_job = measure_beside(triangles)
            with prog.stage("mesh", "again, at the corrected level"):
                result.mesh = mesh_field(s, grid, check=False)
        if tolerance > 0:
            result.mesh, report["simplification"], simplify_warnings = _simplify(
                result.mesh, tolerance, h, float(patient.volume), prog, run.max_memory)
        if metrics_job is None:
            metrics_job = measure_beside(len(result.mesh.faces))
        if metrics_job is not None and printer is None and run.slices is None and out_path is not None:
            from .io.files import atomic_path

            # the file does not depend on the summary: written beside it (the write is mostly
            # the kernel copying pages, the summary a compiled loop; both release the interpreter).
            # A folder (.zarr) is written under its own temporary name: a temporary file of this name
            # stood where its writer makes the folder (refused: "already exists")
            folder = output_format(out_path) == ".zarr"
            with (contextlib.nullcontext(out_path) if folder else atomic_path(out_path)) as tmp:
                write_job = _Beside(write_outputs, result, tmp)
                try:
                    with prog.stage("mesh summary"):
                        _mesh_report(report, mesh_summary(result.mesh), patient)
                finally:
                    with prog.stage("write"):
                        write_job.result()  # waited for even when interrupted: then tmp is removed
            written = True
        else:
            with prog.stage("mesh summary"):
                _mesh_report(report, mesh_summary(result.mesh), patient)
    if morphometry:
        from .measure.morphometry import morphometry as measure, surface_measures

        with prog.stage("metrics", "" if metrics_job is None else "beside the mesh summary and write"):
            # measured on what was built: fragments counts pieces left after any removal
            found = measure(s < 0, h, region=inside, surface=False) if metrics_job is None else metrics_job.result()
            if "surface_area_mm2" in report:
                found.update(surface_measures(report["surface_area_mm2"], report["mesh_volume_mm3"]))
        found.pop("porosity_voxel", None)  # the scaffold pass counted it already
        report.update(found)
        _fragments_per_piece(report)
    if printer is not None:
        from .measure.printability import certificate

        with prog.stage("print check", printer.name):
            report["print_check"] = certificate(s < 0, h, printer, field=s, region=inside, origin=grid.origin)
    if run.slices is not None:
        report["slices"] = _write_stack(s, grid, run.slices, prog)
        report.setdefault("porosity_printed", 1.0 - report["slices"]["grey_volume_mm3"] / float(patient.volume))
    precision = None
    if mesh and result.mesh is not None and out_path is not None:
        from .mesh.writers import float32_merges

        # the summary is of the float64 mesh; an STL holds float32 (exact: its vertices are here). The report
        # says what the file holds: a femur moved 10,000 mm from the origin said "watertight True" of an STL
        # whose float32 coordinates had merged 631 vertices
        merged, precision = float32_merges(out_path, grid, result.mesh.vertices,
                                           on_grid_edges="simplification" not in report)
        if merged:
            report["watertight"] = False
            report["float32_merged_vertices"] = int(merged)
    report["warnings"] = _check_built(report, params, [small_pieces, *simplify_warnings, precision])
    if out_path is not None and not written:
        with prog.stage("write"):
            write_outputs(result, out_path)
    return result


def _finish_in_slabs(tf, report: dict, run: _RunPlan, params: Params, patient, grid: Grid, cells, cells_in,
                     calibration: dict, prog, mesh: bool, out_path, morphometry: bool, printer, *,
                     one_piece: bool, slab_voxels: int) -> Result:
    """The outputs of a run in slabs on disk: each streamed from the fields slab by slab."""
    from .run.pieces import one_piece_table, piece_table_by_slabs, seeds_in_one_piece

    if one_piece and params.remove_fragments:
        # a primitive keeping its main body: its one row from what the passes counted, without
        # another pass
        small_pieces = _pieces_report(report, one_piece_table(
            tf.n_inside, tf.solid, int(np.count_nonzero(cells_in)),
            min(tf.pieces, 1), tf.inside_box, grid))
    elif params.remove_fragments and tf.patient_pieces == 1 and tf.solid_inside is not None:
        # a patient the passes found in one piece, keeping its main body: its row from their counts
        # (its voxels, its solid voxels, their bounds) and its cells from the voxels around the seeds
        # (the rows piece_table_by_slabs gives, without another pass over the slabs)
        small_pieces = _pieces_report(report, one_piece_table(
            tf.n_inside, tf.solid_inside, seeds_in_one_piece(tf.patient, grid, cells.seeds[cells_in]),
            int(tf.solid_inside > 0), tf.inside_box, grid))
    else:
        with prog.stage("pieces", "by slabs"):
            small_pieces = _pieces_report(report, piece_table_by_slabs(
                tf.field, tf.patient, grid, cells.seeds[cells_in], max_voxels=slab_voxels,
                main_bodies_only=params.remove_fragments and tf.patient_pieces == 1, progress=prog.bar("pieces")))
    simplify_warnings = []
    ext = output_format(out_path) if out_path is not None else None
    if mesh and ext in MESH_FORMATS:
        def stream():
            return _stream_mesh(tf.field, out_path, run, slab_voxels, prog,
                                tolerance=_tolerance(params, grid.spacing), voxel=grid.spacing,
                                patient_volume=float(patient.volume))

        summary, simplified, simplify_warnings = stream()
        step = _mesh_correction(summary["volume_mm3"], patient, params, calibration, grid.spacing,
                                area=summary["surface_area_mm2"], tf=tf)
        if step is not None:
            # the mesh measured, the level moved by one step, the fragments and sealed voids
            # cleaned again, and the mesh streamed once more
            _correct(tf, step, report, params, grid, prog, one_piece)
            summary, simplified, simplify_warnings = stream()
        if simplified is not None:
            report["simplification"] = simplified
        _mesh_report(report, summary, patient)
        report["mesh_workers"] = summary.get("workers", 1)
    if morphometry:
        # measured on what was built, after any correction of the level
        report.update(_slab_morphometry(tf, grid, cells, run, prog))
        _fragments_per_piece(report)
        if "mesh_volume_mm3" in report:
            # as the whole-grid morphometry takes them: the mesh's area over its volume
            report["bs_bv_per_mm"] = (report["surface_area_mm2"] / report["mesh_volume_mm3"]
                                      if report["mesh_volume_mm3"] > 0 else None)
    if printer is not None:
        report["print_check"] = _slab_certificate(tf, grid, printer, run, prog)
    if ext in FIELD_FORMATS:
        from .io.export import write_volume
        from .run.memory import process_memory

        with prog.stage("write"):
            # z blocks cut from the field on disk, within what --max-memory leaves
            write_volume(tf.field, grid, out_path, max_bytes=max((run.max_memory - process_memory()) // 2, 2**26))
    if run.slices is not None:
        report["slices"] = _write_stack(tf.field, grid, run.slices, prog, max_voxels=slab_voxels)
        report.setdefault("porosity_printed", 1.0 - report["slices"]["grey_volume_mm3"] / float(patient.volume))
    precision = None
    if mesh and ext in MESH_FORMATS:
        from .mesh.writers import float32_collapse_warning

        # streamed: no vertices held, so the bound from the grid's farthest corner
        precision = float32_collapse_warning(out_path, grid)
    report["warnings"] = _check_built(report, params, [small_pieces, *simplify_warnings, precision])
    # the API's arrays: maps of the slab store, whose files stay on disk (unlinked) while mapped
    field_map, patient_map = (np.memmap(f.path, np.float32, mode="r", shape=tuple(grid.shape))
                              for f in (tf.field, tf.patient))
    return Result(params=params, report=report, cells=cells, skeleton=None, edges=None, grid=grid,
                  field=field_map, patient_sdf=patient_map, patient=patient, timings=prog.timings, tiled=tf.slabs,
                  mesh_file=out_path if mesh and ext in MESH_FORMATS else None)


#: bytes per triangle of a whole mesh read back from the streamed PLY to simplify it (float64
#: vertices, int64 faces, about half as many vertices as triangles, and the reader's copies)
WHOLE_MESH_BYTES_PER_TRIANGLE = 96


def _stream_mesh(field, out_path: Path, run: _RunPlan, slab_voxels: int, prog, *, tolerance: float, voxel: float,
                 patient_volume: float):
    """Mesh a tiled run's field into `out_path` slab by slab, in bounded memory.

    Without simplification, STL and PLY are streamed straight to the file, and OBJ and 3MF
    are formatted a block at a time from a streamed PLY (:func:`~implicit_scaffold.mesh.writers.write_mesh_from_ply`:
    the 3MF's model XML is deflated into the zip as it is written). With a tolerance, the
    streamed PLY is read back whole and simplified when that fits in --max-memory, else
    written as it is, with a warning.

    Returns
    -------
    summary : dict
        As :func:`~implicit_scaffold.mesh.stream.write_mesh_slabs` gives it, or :func:`~implicit_scaffold.mesh.marching.mesh_summary`'s
        of the simplified mesh (with ``workers``).
    simplification : dict or None
        The report's ``simplification`` (None without a tolerance).
    warnings : list of str
    """
    from .mesh.marching import mesh_summary
    from .mesh.writers import write_mesh, write_mesh_from_ply
    from .run.memory import process_memory, release
    from .mesh.stream import MESH_HALO_PLANES, mesh_slab_bytes_per_voxel, write_mesh_slabs
    from .mesh.simplify import SIMPLIFY_BYTES_PER_TRIANGLE

    # marching cubes holds more per voxel than the field passes did, the more the denser the
    # surface (and two slabs may be in flight); the plan kept room for its thinnest slab, which
    # reads more planes than the lattice's slabs may hold (a CT at 0.25 mm: 19 planes, 18 planned)
    per_voxel = mesh_slab_bytes_per_voxel(field)
    thinnest = (1 + 2 * MESH_HALO_PLANES) * field.grid.shape[1] * field.grid.shape[2]
    slab_voxels = run.forced_voxels or max(thinnest, _steady_voxels(
        min(slab_voxels, int((run.max_memory - release()) // per_voxel)), field.grid.shape[1] * field.grid.shape[2]))
    ext = output_format(out_path)
    if tolerance <= 0 and ext in MESH_STREAMED:
        with prog.stage("mesh", "streamed to " + out_path.name):
            return write_mesh_slabs(field, out_path, max_voxels=slab_voxels, progress=prog.bar("mesh")), None, []
    from .io.files import discard, written_path

    staged = out_path.with_name(f".{out_path.name}.tmp-mesh.ply")
    try:
        with prog.stage("mesh", "streamed to " + staged.name):
            summary = write_mesh_slabs(field, staged, max_voxels=slab_voxels, progress=prog.bar("mesh"))
        # inside a command's run the staged PLY waits under its temporary name for the run's end: read it there
        # (a CT's scaffold in slabs, written as .3mf, stopped with "No such file or directory")
        readable = written_path(staged)
        info, found = None, []
        if tolerance > 0:
            import trimesh

            need = summary["triangles"] * (WHOLE_MESH_BYTES_PER_TRIANGLE + SIMPLIFY_BYTES_PER_TRIANGLE) \
                + process_memory()
            if need <= run.max_memory:
                whole = trimesh.load(readable, file_type="ply", process=False)
                simple, info, found = _simplify(whole, tolerance, voxel, patient_volume, prog, run.max_memory)
                del whole
                if info["applied"]:
                    with prog.stage("mesh summary"):
                        summary = {**mesh_summary(simple), "workers": summary.get("workers", 1)}
                    with prog.stage("write"):
                        write_mesh(simple, out_path)
                    return summary, info, found
            else:
                why = (f"not simplified: {summary['triangles']:,} triangles need about {need / 2**30:.1f} GiB to "
                       f"read back and simplify, over --max-memory {run.max_memory / 2**30:.1f} GiB; raise "
                       "--max-memory, or pass --tolerance 0 to say so")
                info = {"tolerance_mm": float(tolerance), "tolerance_voxels": float(tolerance / voxel),
                        "triangles_before": int(summary["triangles"]), "applied": False, "why": why}
                found = [f"the mesh was {why}"]
        with prog.stage("write"):
            if ext == ".ply":
                from .io.files import place

                place(staged, out_path)
                staged = None  # in place, or to be when the run ends: not removed here
            else:
                write_mesh_from_ply(readable, out_path)
        return summary, info, found
    finally:
        if staged is not None:
            discard(staged)


def _write_stack(field, grid: Grid, slices: dict, prog, **kwargs) -> dict:
    """Printer slices of the field (an array or a field on disk) and the stack's summary for the report."""
    from .mesh.slices import write_slices

    with prog.stage("slices"):
        stack = write_slices(field, grid, slices["out_dir"], pixel=slices.get("pixel"),
                             layer=slices.get("layer"), progress=prog.bar("slices"), **kwargs)
    return {"folder": str(slices["out_dir"]), "layers": stack.layers, "width": stack.width,
            "height": stack.height, "pixel_mm": stack.pixel_mm, "layer_mm": stack.layer_mm,
            "origin_mm": list(stack.origin_mm), "solid_volume_mm3": stack.solid_volume_mm3,
            "grey_volume_mm3": stack.grey_volume_mm3}


def _check_built(report: dict, params: Params, found_before=()) -> list[str]:
    """Warn (and list for the report) where what was built misses what was asked.

    Both cases come from struts thinner than a few voxels: removing the solid pieces they
    break into raises the porosity past its target, and marching cubes, which interpolates
    linearly between voxel centres, shaves them (the voxel count is the unbiased one).
    """
    import warnings

    from .errors import ScaffoldWarning

    found = []
    h = report["voxel_mm"]
    target, voxel = report["porosity_target"], report["porosity_voxel"]
    below = (report.get("grade") or {}).get("below_skin")
    if below is not None and below["porosity"] is not None and target is not None:
        # a graded skin is solid whatever the offset: the target holds below it
        if abs(below["porosity"] - below["porosity_target"]) > 0.005:
            why, _ = _fragments_why(report, report.get("fragments_removed") or 0, "the bins' voxels leave no level closer",
                                    abs(below["porosity"] - below["porosity_target"]))
            found_before = [f"the porosity below the {below['depth_mm']:g} mm skin, {below['porosity']:.4f}, misses "
                            f"its target {below['porosity_target']:.4g}: {why}; a finer --voxel (e.g. "
                            f"{report['voxel_mm'] / 2:.3g}) resolves the struts", *found_before]
        target = None
    removed = report.get("fragments_removed") or 0
    printed = report.get("porosity_printed")
    if target is not None and printed is not None and (report.get("printed_level") or {}).get("by"):
        # the level was solved for what is printed: that is what must meet the target
        if abs(printed - target) > PRINTED_TOLERANCE:
            skipped = report["printed_level"].get("skipped")
            why, blamed = (f"{skipped}, so the level is the voxels' one", False) if skipped else \
                _fragments_why(report, removed, "the struts are under-resolved", abs(printed - target))
            found.append(f"the printed porosity {printed:.4f} misses the target {target:g} by "
                         f"{100 * abs(printed - target):.1f} points: {why} at {h:.3g} mm voxels; use a finer "
                         f"--voxel (e.g. {h / 2:.3g})" + (" or --keep-fragments" if blamed else ""))
        if abs(printed - voxel) > UNRESOLVED:
            found.append(f"the voxels' porosity {voxel:.4f} is {100 * abs(printed - voxel):.1f} points from the "
                         f"printed {printed:.4f}: the walls are only a few {h:.3g} mm voxels thick, so the print "
                         f"is coarse; a finer --voxel (e.g. {h / 2:.3g}) resolves them")
    else:
        if target is not None and abs(voxel - target) > 0.005:
            why, blamed = _fragments_why(report, removed, "the patient's voxels leave no level closer",
                                         abs(voxel - target))
            found.append(f"porosity {voxel:.4f} misses the target {target:g}: {why}; the struts are "
                         f"under-resolved at {h:.3g} mm voxels: use a finer --voxel (e.g. {h / 2:.3g})"
                         + (" or --keep-fragments" if blamed else ""))
        if "porosity_mesh" in report and abs(report["porosity_mesh"] - voxel) > 0.01:
                found.append(f"the mesh's porosity {report['porosity_mesh']:.4f} differs from the voxels' {voxel:.4f} "
                         f"by {100 * abs(report['porosity_mesh'] - voxel):.1f} points: marching cubes thins struts "
                         f"only a few voxels thick; a finer --voxel (e.g. {h / 2:.3g}) brings them together")
    found += [m for m in found_before if m]
    for message in found:
        warnings.warn(message, ScaffoldWarning, stacklevel=3)
    return found


def _fragments_why(report: dict, removed: int, otherwise: str, miss: float | None = None) -> tuple[str, bool]:
    """Why the porosity moved, and whether the fragments are the cause: the fragments removed (with their volume),
    unless their share of the patient is under a third of the `miss` (a porosity difference, as a fraction), then
    `otherwise` (9 fragments of 0.0018 % of the patient were blamed for a miss of 0.35 points)."""
    if not removed:
        return otherwise, False
    volume = report.get("fragments_removed_mm3")
    patient = report.get("patient_volume_mm3")
    if miss is not None and volume is not None and patient and volume / patient < miss / 3:
        return otherwise, False
    share = "" if volume is None or not patient else (f" ({volume:.4g} mm3, {100 * volume / patient:.2g} % "
                                                       "of the patient)")
    return (f"removing {removed} solid fragments{share} not attached to the main body of their patient piece moved it",
            True)


#: the seeding grid's points at most (float32: 32 MB), so that a large box stays cheap
SEEDING_POINTS = 8_000_000


def _coarse_patient(patient, cell: float | None = None, cells_across: float = 64.0):
    """The patient's signed distance on the seeding grid, and that grid.

    Its spacing is half a `cell` (mm; the seeds' spacing) where :data:`SEEDING_POINTS` allow,
    and never coarser than `cells_across` steps across the patient's box. A grid of 64 steps
    alone misses thin anatomy in a large box: on an abdominal CT's ribs and vertebrae (a 300 mm
    box, 4.7 mm steps) it held 41,364 of the 78,620 seeds that lay in the bone, and the seed
    count solved on those cells gave pores 17 % larger than asked.
    """
    lo, hi = np.asarray(patient.lo, float), np.asarray(patient.hi, float)
    h = float(np.max(hi - lo)) / cells_across
    if cell is not None:
        h = min(h, max(cell / 2, (float(np.prod(hi - lo)) / SEEDING_POINTS) ** (1 / 3)))
    grid = Grid.covering(lo, hi, h)
    return np.asarray(patient.sdf_grid(grid), np.float32), grid


def _faces_near_patient(cells, coarse: np.ndarray, grid) -> np.ndarray:
    """Interior faces (counted once) whose two cells' seeds lie in the patient (on the seeding grid)."""
    from .measure.metrics import interior_face_pairs

    inside = sample(coarse, grid, cells.seeds) < 0
    f = interior_face_pairs(cells)
    return inside[cells.face_cell[f]] & inside[cells.face_neighbor[f]]


def write_outputs(result: Result, path: Path) -> None:
    """Write the mesh or the field to `path` (atomically); the JSON is written by :func:`generate`."""
    from .io.export import write_volume
    from .mesh.writers import write_mesh

    if output_format(path) in MESH_FORMATS:
        write_mesh(result.mesh, path)
    else:
        write_volume(result.field, result.grid, path)


def params_dict(params: Params) -> dict:
    return asdict(params)
