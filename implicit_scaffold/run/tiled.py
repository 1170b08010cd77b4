"""The one driver of the scaffold's field: slab by slab, in bounded memory, on one machine or a cluster.

Every run's field comes from :func:`tiled_scaffold`. A grid whose run fits in
``--max-memory`` is one slab, held in memory (:class:`~implicit_scaffold.run.tiles.ArraySlabs`); a larger one
is cut into slabs along x (:func:`~implicit_scaffold.run.tiles.plan_slabs`). Each slab's lattice field is computed
for its own planes plus the halo the blend reads, in the whole grid's frame, so every
value is the one the whole-grid run computes, bit for bit. The passes:

1. lattice, blend and patient field of each slab (the heavy part; in local worker
   processes or on Dask workers when asked: :mod:`~implicit_scaffold.run.executor`), kept in two raw files on disk (:class:`~implicit_scaffold.run.tiles.FieldFile`) or arrays,
   while the patient's voxels are counted and their lattice values histogrammed;
2. the exact order statistics that give the surface offset (:class:`~implicit_scaffold.run.tiles.StreamQuantile`);
3. the scaffold field ``max(lattice - level, patient)`` of each slab, with its solid
   pieces labelled and joined across slabs (:class:`~implicit_scaffold.run.tiles.SlabComponents`);
4. the solid fragments turned into void;
5. the sealed void pieces (joined across slabs the same way) turned into solid.

The finished field stays on disk for the outputs (streamed mesh, printer slices, .npy),
which read it slab by slab too.
"""
from __future__ import annotations

import contextlib
import shutil
import tempfile
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from ..errors import ScaffoldError
from .executor import InProcess, Processes
from ..fields.field import level_between, scaffold_field, solid_voxels, void_mask
from .grid import Grid
from .memory import release
from .tiles import ArraySlabs, FieldFile, Slab, SlabComponents, StreamQuantile, blend_halo, level_ranks, \
    plan_slabs

#: bytes per voxel of a slab at the peak of pass 1 (lattice and blended planes, the
#: blend's own temporary, the patient planes, masks and quantile keys), rounded up
SLAB_BYTES_PER_VOXEL = 48
#: bytes a tiled run holds beside its slabs, cells, skeleton and packed primitives: the
#: OpenCL runtime's own buffers, the libraries the later stages load, the calibration
#: prism (measured: 190 MiB from the skeleton to the mesh stage of a 400-seed cube at
#: 0.04 mm with the freed heap returned between stages), rounded up
STAGE_RESERVE = 256 * 2**20
#: bytes each worker process of the lattice pass (``--workers``) holds beside its slab and its
#: packed primitives: a fresh interpreter (the workers are spawned, not forked: an OpenCL runtime's
#: threads do not survive a fork) with NumPy, PyOpenCL, its context and the compiled kernels.
#: Measured as the workers' PSS: 166.5 MiB at most for slabs of 32 planes of 161 x 161 (0.8 M
#: voxels, 40 MB at SLAB_BYTES_PER_VOXEL) of a 4 mm cube at 0.025 mm, so about 127 MiB; rounded up
WORKER_RESERVE = 160 * 2**20
#: bytes on disk per voxel while a tiled run goes: the scaffold and patient fields
DISK_BYTES_PER_VOXEL = 8


def check_disk(grid: Grid, folder=None) -> None:
    """Raise before the run if the temporary folder cannot hold the tiled run's fields."""
    folder = folder or tempfile.gettempdir()
    need = DISK_BYTES_PER_VOXEL * grid.size
    free = shutil.disk_usage(folder).free
    if need > free:
        raise ScaffoldError(f"a tiled run over {grid.shape[0]}x{grid.shape[1]}x{grid.shape[2]} voxels keeps its "
                            f"fields on disk: it needs {need / 2**30:.1f} GiB but only {free / 2**30:.1f} GiB is "
                            f"free in {folder}; set TMPDIR to a larger disk or use a larger --voxel")


@dataclass(frozen=True)
class SlabWork:
    """What every slab of pass 1 needs; sent once to each worker.

    Attributes
    ----------
    style : str
        ``"paper"`` (``skeleton``) or ``"struts"`` (``edges``).
    skeleton, edges : the lattice's primitives
    patient : object with ``sdf_grid(grid, x_range=)``
    grid : Grid
    cutoff : float, mm
    k : float, mm
        Blend width (paper: Gaussian support; struts: smooth-minimum width).
    smooth_cut : float, mm
        The smooth cut's width: with the cut-off, how far outside the patient the lattice
        still counts (:func:`~implicit_scaffold.fields.lattice.blocks_beyond`).
    """

    style: str
    skeleton: Any
    edges: Any
    patient: Any
    grid: Grid
    cutoff: float
    k: float
    smooth_cut: float = 0.0

    @property
    def halo(self) -> int:
        """Planes the blend reads on either side of a slab."""
        return blend_halo(self.grid.spacing, self.k) if self.style == "paper" else 0


def _cells_box(skeleton):
    """The box of the skeleton's cells, mm: ``((3,), (3,))`` tuples."""
    cells = skeleton.cells
    return tuple(map(float, cells.lo)), tuple(map(float, cells.hi))


def slab_fields(work: SlabWork, slab: Slab) -> tuple[Slab, np.ndarray, np.ndarray]:
    """Pass 1 for one slab: its blended lattice field and its patient field, owned planes only.

    Returns
    -------
    slab : Slab
    lattice : (x1 - x0, ny, nz) float32 ndarray, mm
    patient : (x1 - x0, ny, nz) float32 ndarray, mm
    """
    from ..fields.lattice import blocks_beyond
    from ..fields.nodes import Blend, PaperLattice, Patient, Struts
    from ..fields.patient import far_clamp

    grid = work.grid
    # the lattice and the level lie within the cut-off: beyond twice it (and the smooth cut)
    # outside the patient the scaffold is the patient's distance, so those blocks are skipped.
    # A mesh's clamped far field is only a sign there: from its clamp on, the scaffold is void
    # whatever the lattice (its values there, all at or above the clamp, are read by no stage)
    clamp = far_clamp(work.patient, grid)
    reach = min(2 * work.cutoff + work.smooth_cut + 2 * grid.spacing, clamp)
    if work.style == "paper":
        skeleton = work.skeleton
        if hasattr(skeleton, "near"):
            skeleton = skeleton.near(*_band(grid, (slab.h0, slab.h1), work.cutoff))
        lattice = Blend(PaperLattice(skeleton, work.cutoff), work.k, mirror=_cells_box(work.skeleton))
        del skeleton
    else:
        lattice = Struts(work.edges, work.cutoff, work.k)
    # the patient on the planes the lattice reads (the blend's halo: the slab's h0..h1, as the
    # slabs were planned with work.halo), which decide the lattice's skipped blocks
    reads = lattice.reads(grid, (slab.x0, slab.x1))
    s_p = Patient(work.patient).evaluate(grid, reads)
    skip = blocks_beyond(s_p, grid, reads, reach=reach, halo=work.halo)
    s_p = np.ascontiguousarray(s_p[slab.x0 - reads[0]:slab.x1 - reads[0]])
    base = lattice.evaluate(grid, (slab.x0, slab.x1), skip=skip)
    del lattice
    if np.isfinite(clamp):
        # from the clamp on, the lattice is one value below any level (the scaffold there is the
        # clamp, exactly): the same bits whichever blocks a slab or the whole grid skipped
        np.putmask(base, s_p >= np.float32(clamp), np.float32(-work.cutoff))
    return slab, base, s_p


def _band(grid: Grid, x_range, cutoff: float) -> tuple[float, float]:
    """The x band (mm) whose primitives can reach the blocks of planes `x_range` within `cutoff`."""
    from ..fields.lattice import BLOCK

    b0, b1 = int(x_range[0]) // BLOCK * BLOCK, -(-int(x_range[1]) // BLOCK) * BLOCK
    margin = float(cutoff) + 2 * grid.spacing
    x0 = float(grid.origin[0])
    return x0 + b0 * grid.spacing - margin, x0 + b1 * grid.spacing + margin


@dataclass
class TiledField:
    """The finished scaffold field, in its slab store, and what its passes counted.

    Attributes
    ----------
    field : FieldFile or ArraySlabs
        The scaffold's signed distance (negative in the solid), mm: on disk, or in memory
        for a run of one slab (``field.field`` is then the array).
    patient : FieldFile or ArraySlabs
        The patient's signed distance, mm.
    level : float, mm
    cutoff : float, mm
    n_inside : int
        Voxels inside the patient.
    solid : int
        Solid voxels of the scaffold.
    fragments : int or None
        Solid pieces removed (None when kept).
    pieces : int
        Solid pieces left (6-connected).
    slabs : list of Slab
    sealed : (int, int)
        Sealed void pieces and their voxels, counted before any filling.
    patient_pieces : int
        The patient's 6-connected pieces on the grid.
    level_plan, level_field : LevelPlan, LevelField or None
        A graded run's offset bins and offset field (:mod:`~implicit_scaffold.geometry.grade`).
    fragments_voxels : int
        Voxels of the solid fragments removed.
    inside_box : ((3,) int ndarray, (3,) int ndarray) or None
        The bounds of the patient's voxels (indices, inclusive).
    solid_inside : int or None
        Solid voxels inside the patient, when counted (fragments removed, a sharp cut).
    """

    field: FieldFile
    patient: FieldFile
    level: float
    cutoff: float
    n_inside: int
    solid: int
    fragments: int | None
    pieces: int
    slabs: list
    sealed: tuple = (0, 0)
    patient_pieces: int = 1
    level_plan: Any = None
    level_field: Any = None
    fragments_voxels: int = 0
    inside_box: Any = None
    solid_inside: int | None = None

    def close(self) -> None:
        """Remove the files (or let the arrays go)."""
        self.field.close()
        self.patient.close()


@dataclass(frozen=True)
class _Stores:
    """Where a worker process writes its slab's fields: the two field files, by path."""

    field: str
    patient: str


@dataclass
class _SlabCounts:
    """What pass 1 counts on one slab (small: sent back by a worker in place of its fields).

    Attributes
    ----------
    slab : Slab
    fields : (lattice, patient) float32 ndarrays, or None once written to the stores
    n_inside : int
        The patient's voxels.
    high : (65536,) int64 ndarray or None
        The quantile's pass-1 histogram of the lattice over them (:meth:`~implicit_scaffold.run.tiles.StreamQuantile.merge`).
    lo, hi : float, mm
        The lattice's range over them.
    box : ((3,) int ndarray, (3,) int ndarray) or None
        The bounds of the patient's voxels (indices, inclusive).
    """

    slab: Slab
    fields: tuple | None
    n_inside: int
    high: np.ndarray | None
    lo: float
    hi: float
    box: Any


def _lattice_slab(job: tuple, slab: Slab) -> _SlabCounts:
    """Pass 1 on one slab, wherever it runs: its fields and counts. `job` is ``(work, count,
    stores)``; with `stores` (a local worker process) the fields are written there, else sent back."""
    work, count, stores = job
    slab, base, s_p = slab_fields(work, slab)
    inside = s_p < 0
    n_inside, high, lo, hi = int(np.count_nonzero(inside)), None, np.inf, -np.inf
    if count and n_inside:
        part = StreamQuantile()
        part.count(base, inside)
        high, n_inside = part.high, part.n
        lo = float(np.min(base, where=inside, initial=np.inf))
        hi = float(np.max(base, where=inside, initial=-np.inf))
    box = _union_box(None, inside, slab.x0)
    del inside
    fields = (base, s_p)
    if stores is not None:
        for path, planes in zip((stores.field, stores.patient), fields):
            with FieldFile.attach(path, work.grid, write=True) as store:
                store.write(slab.x0, planes)
        del base, s_p, fields
        fields = None
        release()  # what the slab's kernels and temporaries left in the worker's heap
    return _SlabCounts(slab, fields, n_inside, high, lo, hi, box)


def _pass_lattice(work: SlabWork, slabs, executor, field: FieldFile, patient: FieldFile, progress, count=True):
    """Pass 1; returns the quantile's first pass, the patient's voxel count, its values' range
    (with `count` False, for one slab held in memory, only the voxel count: the level is then
    found on the arrays themselves), and the bounds ``(lo, hi)`` of the patient's voxels (indices,
    inclusive; None without any).

    The slabs run on `executor` and are taken as they finish: every count is a sum, a
    minimum or a maximum, the same in any order. Local worker processes write their slabs'
    fields into the files themselves; this process, or a cluster's workers, hand them back.
    """
    quantile = StreamQuantile()
    n_inside, lo, hi = 0, np.inf, -np.inf
    box = None
    stores = _Stores(field.path, patient.path) if isinstance(executor, Processes) else None
    with contextlib.closing(executor.map(_lattice_slab, slabs, (work, count, stores), ordered=False)) as results:
        for done, got in enumerate(results, 1):
            n_inside += got.n_inside
            if got.high is not None:
                quantile.merge(got.high, got.n_inside)
            lo, hi = min(lo, got.lo), max(hi, got.hi)
            if got.box is not None:
                box = got.box if box is None else (np.minimum(box[0], got.box[0]), np.maximum(box[1], got.box[1]))
            if got.fields is not None:
                field.write(got.slab.x0, got.fields[0])
                patient.write(got.slab.x0, got.fields[1])
            del got
            if len(slabs) > 1:
                release()  # what the slab's kernels and temporaries left in the heap, before the next
            if progress is not None:
                progress(done, len(slabs))
    return quantile, n_inside, lo, hi, box


def _union_box(box, mask: np.ndarray, x0: int):
    """`box` (``(lo, hi)`` voxel indices, inclusive, or None) grown by the voxels of `mask`,
    planes from `x0`."""
    if not mask.any():
        return box
    ends = [np.flatnonzero(mask.any(axis=tuple(a for a in range(3) if a != axis))) for axis in range(3)]
    lo = np.array([e[0] for e in ends]) + (x0, 0, 0)
    hi = np.array([e[-1] for e in ends]) + (x0, 0, 0)
    return (lo, hi) if box is None else (np.minimum(box[0], lo), np.maximum(box[1], hi))


def _solve_level(quantile: StreamQuantile, slabs, field: FieldFile, patient: FieldFile, n_inside: int,
                 lo: float, hi: float, porosity: float | None, progress=None, *, skin: float = 0.0,
                 smooth_cut: float = 0.0) -> float:
    """Pass 2: the level :func:`~implicit_scaffold.fields.field.solve_level_cut` finds on the whole grid."""
    if porosity is None:
        return 0.0
    ranks = level_ranks(n_inside, porosity)
    if ranks is None:
        level = lo - 1e-6 if solid_voxels(n_inside, porosity) <= 0 else hi + 1e-6
    else:
        _refine(quantile, ranks, slabs, field, patient, progress)
        level = level_between(*quantile.values())
    if skin <= 0 and smooth_cut <= 0:
        return level
    return _correct_level_cut(quantile, slabs, field, patient, n_inside, porosity, level, skin, smooth_cut)


def _refine(quantile: StreamQuantile, ranks, slabs, field: FieldFile, patient: FieldFile, progress=None) -> None:
    """The quantile's second pass for `ranks`, over the patient's voxels of every slab."""
    quantile.select(*ranks)
    for done, slab in enumerate(slabs, 1):
        quantile.refine(field.read(slab.x0, slab.x1), patient.read(slab.x0, slab.x1) < 0)
        if progress is not None:
            progress(done, len(slabs))


def _correct_level_cut(quantile: StreamQuantile, slabs, field: FieldFile, patient: FieldFile, n_inside: int,
                       porosity: float, level: float, skin: float, smooth_cut: float,
                       iterations: int = 8) -> float:
    """:func:`~implicit_scaffold.fields.field.solve_level_cut`'s corrections for a skin or a smooth cut,
    each an exact count over the slabs and, for the new level, two order statistics.

    Every figure is the whole grid's: the solid voxels and the patient's values below the
    level are sums over slabs, and the order statistics come from the streamed quantile.
    The arithmetic is the whole-grid function's (the comparison with the level in float64,
    as ``np.searchsorted`` makes it; the midpoint of two float32 values in float32).
    """
    from ..fields.field import scaffold_field

    target = solid_voxels(n_inside, porosity)
    for _ in range(iterations):
        solid = below = 0
        for slab in slabs:
            base, s_p = field.read(slab.x0, slab.x1), patient.read(slab.x0, slab.x1)
            s = scaffold_field(base, s_p, level=level, skin=skin, smooth_cut=smooth_cut)
            solid += int(np.count_nonzero(s < 0))
            del s
            below += int(np.count_nonzero((base < np.float64(level)) & (s_p < 0)))
        error = solid - target
        if error == 0:
            break
        rank = below - error
        if rank <= 0 or rank >= n_inside:
            from ..fields.field import unreachable_with_cut

            raise ScaffoldError(unreachable_with_cut(porosity, rank <= 0, skin, smooth_cut))
        _refine(quantile, (rank - 1, rank), slabs, field, patient)
        a, b = (np.float32(v) for v in quantile.values())
        new = float(level_between(a, b))
        if new == level:
            break
        level = new
    return level


def tiled_scaffold(*, style: str, skeleton, edges, patient, grid: Grid, porosity: float | None, k: float,
                   cutoff: float, next_cutoff: Callable[[float, float], float | None], remove_fragments: bool,
                   max_voxels: int, executor=None, prog=None, fill_sealed_voids: bool = True,
                   printed=None, skin: float = 0.0, smooth_cut: float = 0.0,
                   patient_pieces: bool = True, grade=None, in_memory: bool = False) -> TiledField:
    """The scaffold's field on `grid`, slab by slab: the one driver of every run's field.

    A run whose whole grid fits in memory is the case of one slab held in memory
    (`in_memory`); a larger one keeps its slabs' fields on disk. Both make the same
    field, bit for bit, through the same passes.

    Parameters
    ----------
    style : str
    skeleton, edges : the lattice's primitives (paper, struts)
    patient : object with ``sdf_grid(grid, x_range=)``
    grid : Grid
    porosity : float or None
        Target void fraction of the patient; None keeps the lattice as built (level 0).
    k : float, mm
        Blend width.
    cutoff : float, mm
        First cut-off of the lattice field.
    next_cutoff : callable(level, cutoff) -> float or None
        A wider cut-off when `level` reads values the cut-off clamped, else None (the
        whole-grid run's rule, so that both take the same steps).
    remove_fragments : bool
    max_voxels : int
        Voxels a slab may hold, halo included.
    executor : InProcess, Processes or DaskCluster, optional
        Where pass 1 runs its slabs (:mod:`~implicit_scaffold.run.executor`); this process by default, and always
        for one slab held in memory. The field is the same bits wherever they run.
    prog : Progress, optional
    fill_sealed_voids : bool
        Fill the void pieces that do not reach the outside (always counted).
    printed : (bands, callable(read, level, pieces) -> level), optional
        The calibration prism's y and z bands and the search for the level of what is
        printed (:mod:`~implicit_scaffold.fields.printed`); ``read(ys, zs)`` gives the lattice and patient fields
        on a band, `pieces` the patient's pieces on the prism (:func:`prism_pieces`; None
        when fragments are kept or the patient is one piece).
    skin, smooth_cut : float, mm
        As in :func:`~implicit_scaffold.fields.field.scaffold_field`: voxel by voxel, from the
        patient's distance of the same voxel, so they need no halo.
    patient_pieces : bool
        Find the patient's pieces across slabs, each keeping its own main body; False for a
        patient known to be in one piece (a primitive), which saves a labelling pass.
    grade : GradeField, optional
        A graded run's targets: the offset is then a field solved bin by bin over the slabs
        (:func:`~implicit_scaffold.geometry.grade.solve_level_field`, the whole grid's solver), and
        `porosity` is not read.
    in_memory : bool
        One slab, the whole grid, whose fields are held in memory (`max_voxels` is then not read).

    Returns
    -------
    TiledField
        Close it (or use its files) when done: its fields live in temporary files.
    """
    from ..progress import Progress

    prog = prog or Progress(False)
    if in_memory or executor is None:
        executor = InProcess()  # one slab held in memory: nothing to share, nothing to send
    if in_memory:
        field, patient_file = ArraySlabs(None, grid, views=True), ArraySlabs(None, grid, views=True)
        max_voxels = None  # the graded passes read the arrays in their own chunks
    else:
        check_disk(grid)
        field, patient_file = FieldFile(grid), FieldFile(grid)
    plan = level_field = None
    known = None  # the patient's pieces on the prism and their count, labelled once for every cut-off
    try:
        for _ in range(6):
            work = SlabWork(style, skeleton, edges, patient, grid, float(cutoff), float(k), float(smooth_cut))
            nx = int(grid.shape[0])
            slabs = [Slab(0, nx, 0, nx)] if in_memory else plan_slabs(grid.shape, max_voxels=max_voxels,
                                                                      halo=work.halo)
            with prog.stage("lattice", f"{grid.shape[0]}x{grid.shape[1]}x{grid.shape[2]} voxels in "
                                       f"{len(slabs)} slab{'' if len(slabs) == 1 else 's'}"):
                quantile, n_inside, lo, hi, box = _pass_lattice(work, slabs, executor, field, patient_file,
                                                           prog.bar("lattice"), count=not in_memory)
            if n_inside == 0:
                raise ScaffoldError("the patient covers no voxel of the grid; use a smaller --voxel")
            if grade is not None:
                from ..geometry.grade import level_plan, solve_level_field

                if plan is None:
                    with prog.stage("grade", "offset bins"):
                        plan = level_plan(grade, patient_file, grid, max_voxels=max_voxels, skin=skin + smooth_cut)
                with prog.stage("offset", f"{len(plan.edges) - 1} bins"):
                    level_field = solve_level_field(field, patient_file, plan, max_voxels=max_voxels)
                level = level_field.reach(style)
            elif in_memory:
                from ..fields.field import solve_level_cut

                with prog.stage("offset"):
                    # one slab: the streamed quantile's order statistics are the arrays' own
                    level = 0.0 if porosity is None else solve_level_cut(
                        field.field, patient_file.field, porosity, skin=skin, smooth_cut=smooth_cut)
            else:
                with prog.stage("offset"):
                    level = _solve_level(quantile, slabs, field, patient_file, n_inside, lo, hi, porosity,
                                         prog.bar("offset"), skin=skin, smooth_cut=smooth_cut)
            if printed is not None:
                (ys, zs), search = printed
                with prog.stage("printed"):
                    from ..fields.printed import face_bands

                    # the prism and the grid's y-face bands the search reads, from one pass over each field
                    bands = [(ys, zs)] + [(band, zs) for band in face_bands(grid.shape, ys)]
                    labeller = None
                    if remove_fragments and patient_pieces and known is None:
                        # each patient piece keeps its main body on the prism, as in the scaffold pass
                        # (a primitive is one piece: its largest body is its main body); labelled as
                        # the patient's planes are read for the bands
                        labeller = _PrismPieces(patient_file, ys, zs)
                    read = dict(zip(map(_band_key, bands),
                                    zip(_read_bands(field, slabs, bands),
                                        _read_bands(patient_file, slabs, bands, labeller))))
                    if labeller is not None:
                        known = labeller.finish()
                    level = search(lambda y, z: read.pop(_band_key((y, z)), None) or (
                        read_prism(field, slabs, y, z), read_prism(patient_file, slabs, y, z)),
                        level, None if known is None else known[0])
                    del read
            wider = next_cutoff(level, cutoff)
            if wider is None:
                break
            cutoff = wider
        with prog.stage("scaffold"):
            shift = None if level_field is None else (plan, level_field)
            # a patient the printed stage found in one piece is not labelled again
            by_piece = patient_pieces and (known is None or known[1] > 1)
            del known
            solid, fragments, pieces, patient_pieces, removed, sealed, solid_inside = _pass_scaffold(
                slabs, field, patient_file, 0.0 if shift else level, grid.spacing, remove_fragments,
                prog.bar("scaffold"), skin=skin, smooth_cut=smooth_cut, patient_pieces=by_piece, shift=shift,
                fill_sealed=fill_sealed_voids, keep_interior=skin > 0,
                count_inside=remove_fragments and smooth_cut <= 0)
            if fill_sealed_voids:
                solid += sealed[1]
    except BaseException:
        field.close()
        patient_file.close()
        raise
    finally:
        from ..fields.lattice import release_packed

        release_packed()
    return TiledField(field, patient_file, float(level), float(cutoff), int(n_inside), solid, fragments,
                      pieces, slabs, sealed, patient_pieces, plan, level_field, removed, box, solid_inside)


def shift_level(tf: TiledField, step: float, *, remove_fragments: bool, fill_sealed_voids: bool,
                keep_interior: bool = False, patient_pieces: bool = True, progress=None) -> tuple[int, int, int]:
    """Move a finished field's surface by `step` mm, slab by slab, as the whole-grid run does
    after measuring its mesh: ``s = max(s - step, s_P)`` (the new level's field, exactly, for
    a step far below a voxel), then the fragments and sealed voids again.

    Returns
    -------
    (fragments, sealed void pieces, sealed voxels) found by this pass; `tf`'s counts are updated.
    """
    # the patient's field is the same: one found in one piece is not labelled again
    # s = max(s - step, s_P): the solid lies inside the patient, and its voxels there are counted again
    solid, fragments, pieces, _, removed, sealed, tf.solid_inside = _pass_scaffold(
        tf.slabs, tf.field, tf.patient, float(step), tf.field.grid.spacing, remove_fragments, progress,
        patient_pieces=patient_pieces and tf.patient_pieces > 1, fill_sealed=fill_sealed_voids,
        keep_interior=keep_interior, count_inside=tf.solid_inside is not None)
    if fill_sealed_voids:
        solid += sealed[1]
    tf.solid, tf.pieces = solid, pieces
    tf.level = float(tf.level + step)
    if tf.fragments is not None:
        tf.fragments += fragments or 0
        tf.fragments_voxels += removed
    tf.sealed = (tf.sealed[0] + sealed[0], tf.sealed[1] + sealed[1])
    return fragments or 0, sealed[0], sealed[1]


def _pass_scaffold(slabs, field: FieldFile, patient: FieldFile, level: float, spacing: float,
                   remove: bool, progress, *, skin: float = 0.0, smooth_cut: float = 0.0,
                   patient_pieces: bool = True, shift=None, fill_sealed: bool = True,
                   keep_interior: bool = False, count_inside: bool = False) -> tuple:
    """Passes 3 to 5: the scaffold field, its solid pieces, the fragments made void, the
    sealed void pieces filled.

    Each piece of the patient keeps its own main body, as
    :func:`~implicit_scaffold.run.pieces.remove_fragments_by_piece` does on the whole grid:
    the patient's pieces are joined across slabs like the solid's, and each solid piece
    lies in one of them. `shift`, a graded run's ``(LevelPlan, LevelField)``, takes the
    offset field from the lattice first (:func:`~implicit_scaffold.geometry.grade.shift_planes`).
    The void pieces are joined across slabs the same way and the sealed ones filled, as
    :func:`~implicit_scaffold.fields.field.fill_sealed_voids` does on the whole grid (`fill_sealed`;
    with `keep_interior` the largest is kept); they are always counted.

    The void is labelled in the pass that last changes the field: the first when fragments are
    kept, else the one that drops them (which reads the slabs anyway). Fragments and sealed voids
    are repainted from their pieces' first voxels (:meth:`~implicit_scaffold.run.tiles.SlabComponents.drop_fragments`),
    and only the slabs that hold some are written again.

    `count_inside` counts the solid voxels inside the patient at the end (the piece table's): for a
    field whose solid lies inside the patient after the scaffold field (``s >= s_P``: every cut
    but the smooth one), only the sealed voids filled can lie outside it.

    Returns
    -------
    solid (without the sealed voids filled), fragments (None when not removed), bodies, patient
    pieces, voxels removed, (sealed void pieces, their voxels) counted before any filling, solid
    voxels inside the patient at the end (None unless `count_inside`)
    """
    by_piece = patient_pieces
    pieces, patient_pieces = SlabComponents(seeds=remove), SlabComponents()
    voids = SlabComponents(seeds=fill_sealed)
    where = []  # per slab: the patient label (local) of each solid label (local)
    solid = 0
    last = len(slabs) - 1
    total_steps = 2 * len(slabs) if remove else len(slabs)
    for done, slab in enumerate(slabs, 1):
        s_p = patient.read(slab.x0, slab.x1)
        base = field.read(slab.x0, slab.x1)
        if shift is not None:
            from ..geometry.grade import shift_planes

            shift_planes(base, s_p, slab.x0, *shift)
        s = scaffold_field(base, s_p, level=level, skin=skin, smooth_cut=smooth_cut, out=base)
        del base
        field.write(slab.x0, s)
        inside = s < 0
        labels = pieces.add(inside)
        if by_piece:
            patient_labels = patient_pieces.add(s_p < 0)
            piece_of = np.zeros(int(labels.max(initial=0)) + 1, np.int64)
            piece_of[labels[inside]] = patient_labels[inside]
            where.append(piece_of)
            del patient_labels
        solid += int(np.count_nonzero(inside))
        del s_p, labels, inside
        if not remove:
            # nothing more changes the field before the sealed voids: the void is labelled now
            voids.add(void_mask(s, first_x=done == 1, last_x=done - 1 == last))
        del s
        if progress is not None:
            progress(done, total_steps)
    n_patient = patient_pieces.finish() + 1 if by_piece else 1
    found = pieces.finish()
    if n_patient > 1 and found:
        group = np.full(pieces.labels, -1, np.int64)
        for i, piece_of in enumerate(where):
            group[pieces.roots_of(i, np.arange(1, len(piece_of)))] = patient_pieces.roots_of(i, piece_of[1:])
        pieces.keep_largest_per(group)
        found = pieces.fragments()
    del where, patient_pieces
    total = pieces.piece_count
    removed = 0
    if remove:
        for i, slab in enumerate(slabs):
            s = field.read(slab.x0, slab.x1)
            if found and pieces.has_fragments(i):
                removed += pieces.drop_fragments(i, s, spacing)
                field.write(slab.x0, s)
            voids.add(void_mask(s, first_x=i == 0, last_x=i == last))
            del s
            if progress is not None:
                progress(len(slabs) + i + 1, total_steps)
    del pieces
    voids.finish()
    sealed = voids.sealed(keep_interior)
    filled_outside = 0
    if fill_sealed and sealed[0]:
        for i, slab in enumerate(slabs):
            if voids.has_sealed(i):
                s = field.read(slab.x0, slab.x1)
                # the mask for when the sealed voids are too large to flood (labelled again)
                voids.fill_sealed(i, lambda s=s, i=i: void_mask(s, first_x=i == 0, last_x=i == last), s, -spacing)
                field.write(slab.x0, s)
                if count_inside:
                    # the solid lay inside the patient before: what is outside now was filled
                    filled_outside += int(np.count_nonzero((s < 0) & (patient.read(slab.x0, slab.x1) >= 0)))
                del s
    solid -= removed
    inside = solid + (sealed[1] if fill_sealed else 0) - filled_outside if count_inside else None
    if not remove:
        return solid, None, total, n_patient, 0, sealed, inside
    return solid, found, total - found, n_patient, removed, sealed, inside


def prism_pieces(patient, slabs, ys: slice, zs: slice) -> np.ndarray:
    """The patient's 6-connected pieces on the prism ``[:, ys, zs]``, int32, 0 outside, numbered
    as whole-grid labelling (:func:`~implicit_scaffold.run.pieces.label_pieces`) numbers them: the
    pieces are joined across the slabs (:class:`~implicit_scaffold.run.tiles.SlabComponents`), each numbered by its
    first voxel in C order."""
    labeller = _PrismPieces(patient, ys, zs)
    _read_bands(patient, slabs, [], labeller)
    return labeller.finish()[0]


class _PrismPieces:
    """:func:`prism_pieces` fed the patient's planes slab by slab (:meth:`add`, in order of x), as
    another pass reads them; :meth:`finish` gives the prism's labels and the patient's piece count
    on the whole grid (found on the way)."""

    def __init__(self, patient, ys: slice, zs: slice):
        self.patient, self.ys, self.zs = patient, ys, zs
        self.parts, self.local = SlabComponents(), []

    def add(self, planes: np.ndarray) -> None:
        if not isinstance(self.patient, ArraySlabs):
            self.local.append(self.parts.add(planes < 0)[:, self.ys, self.zs].copy())

    def finish(self) -> tuple[np.ndarray, int]:
        ys, zs = self.ys, self.zs
        if isinstance(self.patient, ArraySlabs):
            from .pieces import label_pieces

            labels, count = label_pieces(self.patient.field < 0)
            return labels[:, ys, zs], count
        parts = self.parts
        parts.finish()
        roots = np.flatnonzero(parts.sizes > 0)
        number = np.zeros(len(parts.sizes) + 1, np.int32)
        number[roots + 1] = np.arange(1, len(roots) + 1)
        out = np.empty((self.patient.grid.shape[0], ys.stop - ys.start, zs.stop - zs.start), np.int32)
        x0 = 0
        for i, labels in enumerate(self.local):
            out[x0:x0 + len(labels)] = number[parts.roots_of(i, labels) + 1]
            x0 += len(labels)
        self.local = []
        return out, len(roots)


def _band_key(band) -> tuple[int, int, int, int]:
    """A ``(ys, zs)`` band as a key (slices are not hashable before Python 3.12)."""
    ys, zs = band
    return ys.start, ys.stop, zs.start, zs.stop


def read_prism(source, slabs, ys: slice, zs: slice) -> np.ndarray:
    """``source[:, ys, zs]`` of a field on disk, slab by slab, float32."""
    return _read_bands(source, slabs, [(ys, zs)])[0]


def _read_bands(source, slabs, bands, labeller: _PrismPieces | None = None) -> list[np.ndarray]:
    """``source[:, ys, zs]`` for each ``(ys, zs)`` of `bands`, float32, from one read of each slab;
    each slab's planes are given to `labeller` too."""
    nx = source.grid.shape[0]
    out = [np.empty((nx, ys.stop - ys.start, zs.stop - zs.start), np.float32) for ys, zs in bands]
    for slab in slabs:
        planes = source.read(slab.x0, slab.x1)
        for got, (ys, zs) in zip(out, bands):
            got[slab.x0:slab.x1] = planes[:, ys, zs]
        if labeller is not None:
            labeller.add(planes)
        del planes
    return out


def sample_slabs(source, grid: Grid, points) -> np.ndarray:
    """Trilinear values of a field on disk at `points` ``(m, 3)`` mm, as :func:`~implicit_scaffold.fields.field.sample` gives.

    Reads, for each group of points, only the two planes around them.
    """
    from scipy import ndimage

    idx = (np.asarray(points, np.float64) - np.asarray(grid.origin)) / grid.spacing
    out = np.empty(len(idx), np.float32)
    plane = np.clip(np.floor(idx[:, 0]), 0, grid.shape[0] - 1).astype(np.int64)
    for x in np.unique(plane):
        pick = plane == x
        x1 = min(int(x) + 2, grid.shape[0])
        local = idx[pick].copy()
        local[:, 0] -= x
        out[pick] = ndimage.map_coordinates(source.read(int(x), x1), local.T, order=1, mode="nearest")
    return out

