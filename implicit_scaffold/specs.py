"""Typed specs of a run: what lattice to build, on what grid, and what to write.

:func:`~implicit_scaffold.pipeline.generate` takes them (``generate(lattice=LatticeSpec(...),
grid=GridSpec(...), outputs=Outputs(...), patient=...)``) or the same options as flat keywords.
Each spec is a frozen dataclass checked when it is built: a bad value raises a
:class:`~implicit_scaffold.errors.ScaffoldError` whose one line says what is wrong and how to
fix it, so a spec that exists is a valid one, and the values it holds are the normalised ones
(``porosity="none"`` is None, a ``grade`` string is a :class:`~implicit_scaffold.geometry.grade.GradeProfile`,
a ``max_memory`` size is bytes, a printer name is its profile). ``dataclasses.replace`` checks
the new spec again. Units are mm.

This module imports no stage: building a spec is cheap, and a script can check its options
before the OpenCL device or the pipeline's libraries load.
"""
from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from .errors import ScaffoldError, positive_mm
from .io.formats import FIELD_WRITERS, MESH_WRITERS, match

#: the lattice styles: the paper's pores and channels, or capsules on the Voronoi edges
STYLES = ("paper", "struts")


def output_format(path) -> str | None:
    """The mesh or field format that `path`'s name ends with (``.nii.gz`` as a whole), or None."""
    return match(path, MESH_WRITERS + FIELD_WRITERS)


def _set(spec, name: str, value) -> None:
    # a frozen dataclass stores its normalised values in __post_init__ this way (as the
    # dataclasses documentation shows); the spec is immutable once built
    object.__setattr__(spec, name, value)


def check_flag(name: str, value) -> bool:
    """`value` as a bool (True, False, 0, 1 or None for False), else a :class:`ScaffoldError`."""
    if value not in (True, False, None, 0, 1):
        raise ScaffoldError(f"{name} must be True or False, got {value!r}")
    return bool(value)


def check_width(name: str, value, *, hint: str = "") -> float:
    """`value` as a width >= 0 in mm (None is 0), else a :class:`ScaffoldError` naming ``--name``
    (`hint`, e.g. ``" (0 for sharp creases)"``, follows "a width in mm")."""
    try:
        v = float(value or 0.0)
    except (TypeError, ValueError):
        raise ScaffoldError(f"--{name} must be a width in mm{hint}, got {value!r}") from None
    if not (math.isfinite(v) and v >= 0):
        raise ScaffoldError(f"--{name} must be a width >= 0 mm, got {value!r}")
    return v


def _whole(name: str, value, what: str = "") -> int:
    """`value` as an int, else a :class:`ScaffoldError`: ``--name must be a whole number{what}``."""
    try:
        return int(value)
    except (TypeError, ValueError):
        raise ScaffoldError(f"--{name} must be a whole number{what}, got {value!r}") from None


@dataclass(frozen=True)
class LatticeSpec:
    """What lattice to build: its style, cells, scale factors, porosity target and grading.

    Parameters
    ----------
    style : {"paper", "struts"}
        ``paper``: pores (cells scaled by `sv`) and channels (faces scaled by `sf`);
        ``struts``: capsules on the Voronoi edges, their radius solved from `porosity`.
    seeds : int, optional
        The number of seeds (Voronoi cells), at least 2; by default it follows `pore_size`.
    pore_size : float, mm
        Target pore size (see `seed_rule`); ignored when `seeds` is given.
    seed_rule : {"pore-size", "paper"}
        ``pore-size``: the seed count is solved so that the measured mean pore size
        (polyhedron-sphere) is `pore_size`; ``paper``: the paper's ``n = V P / (pi Dp^3 / 6)``.
    seeds_in : {"box", "patient"}, optional
        Where the seeds are drawn: the bounding box (the paper), or the patient plus one
        cell. None: the patient when one is given to ``generate``, the box for a built-in shape.
    porosity : float or None
        Target porosity in (0, 1), met by offsetting the surface; None (or ``"none"``) keeps
        the lattice as `sf` and `sv` make it (not with ``style="struts"``).
    sf, sv : float
        Face and cell scale factors, each in (0, 1).
    blend : float, mm, optional
        Width over which creases are rounded; 0 keeps them sharp; None: from the walls.
    seed : int
        Random seed, >= 0: the same spec and seed give the same bytes.
    remove_fragments : bool
        Drop solid pieces not attached to the main body.
    fill_sealed_voids : bool
        Fill void pieces that do not reach the outside (closed cavities in the print).
    grade : str or callable, optional
        Graded pore size: ``"0:0.3,2:0.8"`` (depth below the patient surface : pore size,
        mm) or ``f(x, y, z) -> pore size`` (mm); the seed count then follows it.
    calibration : (slope, intercept), optional
        Grade from the patient's CT: density g/cm³ = slope * HU + intercept (needs ``ct``).
    relax : int
        Lloyd iterations on graded seeds (needs `grade` or `calibration`).
    weighted : bool
        Power (Laguerre) cells weighted by the local pore size (needs `grade` or `calibration`).

    Raises
    ------
    ScaffoldError
        A value out of range or options that contradict each other, in one line with its fix.

    Examples
    --------
    >>> LatticeSpec(pore_size=0.5, porosity=0.7).sv
    0.75
    """

    style: str = "paper"
    seeds: int | None = None
    pore_size: float = 0.6
    seed_rule: str = "pore-size"
    seeds_in: str | None = None
    porosity: float | None = 0.8
    sf: float = 0.75
    sv: float = 0.75
    blend: float | None = None
    seed: int = 0
    remove_fragments: bool = True
    fill_sealed_voids: bool = True
    grade: Any = None
    calibration: Any = None
    relax: int = 0
    weighted: bool = False

    def __post_init__(self):
        from .fields.field import check_porosity
        from .geometry.seeds import SEED_RULES
        from .geometry.skeleton import check_scale

        style = str(self.style).lower()
        if style not in STYLES:
            raise ScaffoldError(f"unknown --style {self.style!r}; use paper or struts")
        seeds = None if self.seeds is None else _whole("seeds", self.seeds)
        if seeds is not None and seeds < 2:
            raise ScaffoldError(f"a Voronoi lattice needs at least 2 seeds, got {seeds}; pass --seeds 2 or more")
        porosity = check_porosity(self.porosity)
        if style == "struts" and porosity is None:
            raise ScaffoldError("--style struts solves the strut radius from --porosity; give a target such as 0.8")
        # None: from the walls
        blend = None if self.blend is None else check_width("blend", self.blend, hint=" (0 for sharp creases)")
        seed = _whole("seed", self.seed)
        if seed < 0:
            raise ScaffoldError(f"--seed must be >= 0, got {seed}")
        seeds_in = None if self.seeds_in is None else str(self.seeds_in).lower()
        if seeds_in not in (None, "box", "patient"):
            raise ScaffoldError(f"--seeds-in takes box or patient, got {self.seeds_in!r}")
        seed_rule = str(self.seed_rule).lower()
        if seed_rule not in SEED_RULES:
            raise ScaffoldError(f"--seed-rule takes {' or '.join(SEED_RULES)}, got {self.seed_rule!r}")
        values = dict(style=style, seeds=seeds, pore_size=positive_mm("pore-size", self.pore_size, example="0.6"),
                      seed_rule=seed_rule, seeds_in=seeds_in, porosity=porosity, sf=check_scale("sf", self.sf),
                      sv=check_scale("sv", self.sv), blend=blend, seed=seed,
                      remove_fragments=check_flag("remove_fragments", self.remove_fragments),
                      fill_sealed_voids=check_flag("fill_sealed_voids", self.fill_sealed_voids),
                      **self._graded(seeds))
        for name, value in values.items():
            _set(self, name, value)

    def _graded(self, seeds) -> dict:
        """The graded options (``grade``, ``calibration``, ``relax``, ``weighted``) checked, or a ScaffoldError."""
        from .geometry.grade import check_grade, parse_calibration

        grade = check_grade(self.grade)
        calibration = parse_calibration(self.calibration)
        relax = _whole("relax", self.relax or 0, " of Lloyd iterations")
        if relax < 0:
            raise ScaffoldError(f"--relax must be >= 0 Lloyd iterations, got {relax}")
        weighted = check_flag("weighted", self.weighted)
        if grade is not None and calibration is not None:
            raise ScaffoldError("give --grade (pore size by depth) or --calibration (from the CT), not both")
        if grade is None and calibration is None:
            if relax:
                raise ScaffoldError("--relax relaxes graded seeds; add --grade (e.g. --grade 0:0.6 for even pores) "
                                    "or --calibration")
            if weighted:
                raise ScaffoldError("--weighted weights the cells by the graded pore size; add --grade (e.g. --grade "
                                    "0:0.3,2:0.8) or --calibration")
            return {"grade": None, "calibration": None, "relax": 0, "weighted": False}
        if seeds is not None:
            raise ScaffoldError("a graded scaffold takes its seed count from the pore-size field; drop --seeds")
        return {"grade": grade, "calibration": calibration, "relax": relax, "weighted": weighted}


@dataclass(frozen=True)
class GridSpec:
    """The voxel grid and how the run is laid out on this machine (or a cluster).

    None of these change the field's bytes except `voxel`: a run in slabs, in worker
    processes or on a cluster gives the same field as one slab held in memory.

    Parameters
    ----------
    voxel : float, mm, optional
        Voxel size; by default from the walls (several voxels across the median wall).
    max_memory : int or str, optional
        What the run may hold: bytes, or a size such as ``"4G"`` or ``"800M"`` (held as
        bytes); by default 4 GiB, or 80 % of the free memory when that is less.
    tiled : bool or int, optional
        Force (True) or forbid (False) slabs kept on disk; an int forces them with at most
        that many voxels per slab (halo included); None chooses by memory.
    workers : int
        Local worker processes for the slabs' lattice passes (1: this process).
    scheduler : str or distributed.Client, optional
        A dask.distributed scheduler to run the slabs on (not with ``workers > 1``).

    Raises
    ------
    ScaffoldError
        A value out of range, in one line with its fix.
    """

    voxel: float | None = None
    max_memory: int | str | None = None
    tiled: bool | int | None = None
    workers: int = 1
    scheduler: Any = None

    def __post_init__(self):
        from .run.memory import parse_memory

        if self.voxel is not None:
            _set(self, "voxel", positive_mm("voxel", self.voxel, example="0.04"))
        m = self.max_memory
        if isinstance(m, str):
            _set(self, "max_memory", parse_memory(m))
        elif m is not None:
            if isinstance(m, bool) or not isinstance(m, numbers.Real) or not (math.isfinite(m) and m > 0):
                raise ScaffoldError(f"--max-memory must be a positive size such as 4G (or bytes), got {m!r}")
            _set(self, "max_memory", int(m))
        t = self.tiled
        if not (t is None or isinstance(t, bool)):
            if not isinstance(t, numbers.Integral) or t < 1:
                raise ScaffoldError(f"tiled must be True, False, None or the voxels of a slab (a whole number "
                                    f">= 1), got {t!r}")
        from .run.executor import check_workers

        _set(self, "workers", check_workers(self.workers, self.scheduler))


@dataclass(frozen=True)
class MechanicsSpec:
    """The stiffness a run measures on what it builds (voxel finite elements, :mod:`~implicit_scaffold.measure.mechanics`).

    Its memory is checked when the run has planned its grid, before the lattice: a solve that
    cannot fit is refused then, not after the scaffold is built and written.

    Parameters
    ----------
    material : str or Material
        A :data:`~implicit_scaffold.measure.mechanics.MATERIALS` key (``ti64 pcl pla peek ha tcp cocr ta bone``) or a
        :class:`~implicit_scaffold.measure.mechanics.Material`; held as the Material.
    E : float, GPa, optional
        Young's modulus (instead of, or overriding, the material's).
    nu : float, optional
        Poisson's ratio, in (-1, 0.5).
    voxel : float, mm, optional
        The solve's voxel; by default the run's own when its solve fits the budget, else the
        finest that fits (:func:`~implicit_scaffold.measure.mechanics.plan_voxel`).
    boundary : {"auto", "periodic", "kinematic"}
        The homogenization's boundary conditions (auto: periodic for a box patient).
    axis : {"x", "y", "z"}
        The platen compression's axis.
    tol : float, optional
        The CG's relative residual, the solves' only stop; None (the default): the default stop of
        :func:`~implicit_scaffold.measure.mechanics.measure`.

    Raises
    ------
    ScaffoldError
        An unknown material or boundary, a bad modulus, nu, voxel or tol, in one line.
    """

    material: Any = "ti64"
    E: float | None = None
    nu: float | None = None
    voxel: float | None = None
    boundary: str = "auto"
    axis: str = "z"
    tol: float | None = None

    def __post_init__(self):
        from .measure.mechanics import Material, check_tol, material

        mat = self.material
        if not isinstance(mat, Material):
            mat = material(mat, E=self.E, nu=self.nu)
        elif self.E is not None or self.nu is not None:
            mat = material(None, E=self.E if self.E is not None else mat.E_gpa, nu=self.nu if self.nu is not None
                           else mat.nu)
        if self.boundary not in ("auto", "periodic", "kinematic"):
            raise ScaffoldError(f"mechanics boundary must be auto, periodic or kinematic, got {self.boundary!r}")
        if self.axis not in ("x", "y", "z"):
            raise ScaffoldError(f"mechanics axis must be x, y or z, got {self.axis!r}")
        voxel = None if self.voxel is None else positive_mm("mechanics-voxel", self.voxel, example="0.05")
        _set(self, "material", mat)
        _set(self, "voxel", voxel)
        _set(self, "tol", check_tol(self.tol))


@dataclass(frozen=True)
class Outputs:
    """What a run writes and measures beyond the field.

    Parameters
    ----------
    path : str or Path, optional
        Where to write: a mesh (``.stl``, ``.ply``, ``.obj``, ``.3mf``) or the field
        (``.npy``, ``.vti``, ``.nii(.gz)``, ``.nrrd``, ``.mha``, ``.tif``, ``.zarr``); the JSON
        report goes beside it. None writes nothing (the :class:`~implicit_scaffold.pipeline.Result` has it all).
    mesh : bool
        False stops after the field (no marching cubes); a mesh `path` needs it.
    morphometry : bool
        Measure the built solid's voxels (local thickness, Conn.D, interconnected
        porosity, fragments, BS/BV).
    slices : dict, optional
        Printer slices: ``{"out_dir": folder, "pixel": mm or None, "layer": mm or None}``.
    printer : str or PrinterProfile, optional
        Certify what was built for this printer (a name such as ``"dlp-resin"``, or
        ``"custom:min_strut=..."``); held as its profile.
    repair : bool
        Thicken struts and open throats to the printer's limits before the mesh (needs `printer`).
    tolerance : float, mm
        Simplify the mesh within this distance (manifold3d); 0 keeps every triangle.
    mechanics : MechanicsSpec, optional
        Measure the built scaffold's stiffness (``report["mechanics"]``); its solve's memory is
        checked before the lattice.

    Raises
    ------
    ScaffoldError
        An unknown format, a mesh path without the mesh stage, a bad printer or tolerance,
        in one line with its fix. Whether the folder can be written is checked when the run
        starts.
    """

    path: str | Path | None = None
    mesh: bool = True
    morphometry: bool = True
    slices: dict | None = None
    printer: Any = None
    repair: bool = False
    tolerance: float = 0.0
    mechanics: MechanicsSpec | None = None

    def __post_init__(self):
        from .mesh.simplify import check_tolerance

        mesh = check_flag("mesh", self.mesh)
        if self.path is not None:
            path = Path(self.path)
            ext = output_format(path)
            if ext is None:
                raise ScaffoldError(f"cannot write {path.name}: use one of {', '.join(MESH_WRITERS + FIELD_WRITERS)}")
            if ext in MESH_WRITERS and not mesh:
                raise ScaffoldError("a mesh output needs the mesh stage; drop mesh=False or write .npy")
            if ext not in MESH_WRITERS and self.tolerance:
                # the field is written as built: a simplified mesh nobody gets was described in the report
                raise ScaffoldError(f"--tolerance simplifies a mesh output; {path.name} is the field, written as "
                                    "built: drop --tolerance, or write a mesh (.stl .ply .obj .3mf)")
            _set(self, "path", path)
        if self.slices is not None:
            if not isinstance(self.slices, dict) or "out_dir" not in self.slices:
                raise ScaffoldError(f'slices must be a dict such as {{"out_dir": "stack", "pixel": None, '
                                    f'"layer": None}}, got {self.slices!r}')
            for name in ("pixel", "layer"):
                if self.slices.get(name) is not None:
                    positive_mm(name, self.slices[name], example="0.05")
        printer = self.printer
        if printer is not None and not hasattr(printer, "min_strut_mm"):
            from .measure.printability import printer_profile

            printer = printer_profile(printer)
        repair = check_flag("repair", self.repair)
        if repair and printer is None:
            raise ScaffoldError("--repair repairs for a printer's limits; add --printer NAME (e.g. --printer dlp-resin)")
        if self.mechanics is not None and not isinstance(self.mechanics, MechanicsSpec):
            raise ScaffoldError(f"mechanics must be a MechanicsSpec, got {type(self.mechanics).__name__}; e.g. "
                                "mechanics=MechanicsSpec(material='ti64')")
        for name, value in dict(mesh=mesh, morphometry=check_flag("morphometry", self.morphometry), printer=printer,
                                repair=repair, tolerance=check_tolerance(self.tolerance)).items():
            _set(self, name, value)


#: generate's flat keywords that are a spec's fields, by spec; ``output`` is :attr:`Outputs.path`
SPEC_KEYWORDS = {
    "lattice": (LatticeSpec, {f.name: f.name for f in fields(LatticeSpec)}),
    "grid": (GridSpec, {f.name: f.name for f in fields(GridSpec)}),
    "outputs": (Outputs, {"output" if f.name == "path" else f.name: f.name for f in fields(Outputs)}),
}

#: every flat keyword of generate that belongs to a spec
FLAT_KEYWORDS = frozenset(k for _, names in SPEC_KEYWORDS.values() for k in names)


def specs_from(given: dict, flat: dict) -> dict:
    """The three specs of a run, from the specs `given` (``{"lattice": LatticeSpec or None, ...}``)
    and the flat keywords `flat` that were set (``{"sf": 0.5, "output": "s.stl", ...}``).

    A spec left out is built from its flat keywords (its defaults for the rest); a flat
    keyword beside the spec it belongs to is refused, since one of the two would be ignored.

    Raises
    ------
    ScaffoldError
        A spec of the wrong type, an option given both ways, or a bad value.
    """
    out = {}
    for arg, (cls, names) in SPEC_KEYWORDS.items():
        spec, mine = given.get(arg), {k: flat[k] for k in names if k in flat}
        if spec is None:
            spec = cls(**{names[k]: v for k, v in mine.items()})
        elif not isinstance(spec, cls):
            raise ScaffoldError(f"{arg} must be a {cls.__name__}, got {type(spec).__name__}; e.g. "
                                f"{arg}={cls.__name__}()")
        elif mine:
            both = ", ".join(sorted(mine))
            raise ScaffoldError(f"{both} given both in {arg}={cls.__name__}(...) and as keyword; give it in one place "
                                f"(e.g. {cls.__name__}({names[sorted(mine)[0]]}=...))")
        out[arg] = spec
    return out
