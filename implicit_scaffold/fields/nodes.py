"""Field nodes: signed distances that evaluate themselves on any planes of a grid.

A node is anything with ``evaluate(grid, x_range, skip=None)`` returning the float32 planes
``x0 <= i < x1`` of its field on `grid` (mm, negative in the solid), and
``reads(grid, x_range)``, the planes its leaves are evaluated on (wider than `x_range` when a
node such as :class:`Blend` reads a halo). A node's planes are the same bits as those planes
of its whole-grid field, so any driver may cut the grid into slabs as it likes:
:func:`evaluate` is the simplest one, and the pipeline's driver (:func:`~implicit_scaffold.run.tiled.slab_fields`)
evaluates the lattice and patient nodes slab by slab the same way, skipping blocks whose
lattice values cannot matter (fogleman/sdf's ``generate`` is the model).

Nodes hold plain data (a skeleton, edges, a patient, a function) and call the stage
functions (:func:`~implicit_scaffold.fields.lattice.lattice_sdf`, :func:`~implicit_scaffold.fields.lattice.struts_field`, :func:`~implicit_scaffold.fields.field.blend_field`,
:func:`~implicit_scaffold.fields.field.scaffold_field`); they add no arithmetic of their own, so a field built from
nodes has the bytes of the stage functions called by hand. Units are mm.

Examples
--------
The paper's lattice, blended, cut by your own ball at a level for 70 % porosity::

    lattice = Blend(PaperLattice(skeleton, cutoff=1.0), k=0.1)
    ball = SDF(lambda x, y, z: np.sqrt((x - 3) ** 2 + (y - 3) ** 2 + (z - 3) ** 2) - 2.8)
    level = solve_level(evaluate(lattice, grid), evaluate(ball, grid) < 0, porosity=0.7)
    s = evaluate(Cut(lattice, ball, level=level), grid, max_voxels=2_000_000)
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Protocol, runtime_checkable

import numpy as np

from ..run.grid import Grid

#: voxels an :class:`SDF` node evaluates its function on at once (its temporaries stay small)
SDF_SLAB_VOXELS = 4_000_000


@runtime_checkable
class FieldNode(Protocol):
    """A signed distance (mm, negative in the solid) that can be evaluated plane range by plane range."""

    def evaluate(self, grid: Grid, x_range: tuple[int, int], skip: np.ndarray | None = None) -> np.ndarray:
        """The planes ``x0 <= i < x1`` of the field on `grid`, ``(x1 - x0, ny, nz)`` float32, mm.

        `skip` (optional) marks blocks of the lattice kernels (:func:`~implicit_scaffold.fields.lattice.blocks_beyond`) over
        the planes ``reads(grid, x_range)`` whose values cannot change the scaffold; a lattice leaf
        leaves them at its cut-off, other nodes pass it to their children or ignore it.
        """

    def reads(self, grid: Grid, x_range: tuple[int, int]) -> tuple[int, int]:
        """The planes this node's leaves are evaluated on to give the planes `x_range`."""


def _planes(grid: Grid, x_range) -> tuple[int, int]:
    return (0, grid.shape[0]) if x_range is None else (int(x_range[0]), int(x_range[1]))


class _Leaf:
    """A node that reads exactly the planes it gives."""

    def reads(self, grid: Grid, x_range) -> tuple[int, int]:
        return _planes(grid, x_range)


@dataclass(frozen=True)
class PaperLattice(_Leaf):
    """The paper's lattice (pores and channels): its exact signed distance, clamped at `cutoff`.

    Parameters
    ----------
    skeleton : Skeleton or SkeletonSource
        From :func:`~implicit_scaffold.geometry.skeleton.scaled_skeleton` (or a tiled run's source, which builds the part
        near each slab).
    cutoff : float, mm
        Distances beyond it are clamped to it (with their sign).
    """

    skeleton: Any
    cutoff: float

    def evaluate(self, grid: Grid, x_range=None, skip=None) -> np.ndarray:
        from .lattice import lattice_sdf

        return lattice_sdf(self.skeleton, grid, cutoff=self.cutoff, x_range=_planes(grid, x_range), skip=skip)


@dataclass(frozen=True)
class Struts(_Leaf):
    """Capsule struts on the Voronoi edges: the smooth minimum of the distances to their axes.

    The solid of strut radius ``r`` is the field below ``r`` (a :class:`Cut` at ``level=r``).

    Parameters
    ----------
    edges : (ne, 2, 3) float ndarray, mm
        The struts' axes (:func:`~implicit_scaffold.geometry.skeleton.voronoi_edges`).
    cutoff : float, mm
    k : float, mm
        The smooth minimum's width; 0 for the plain minimum.
    """

    edges: Any
    cutoff: float
    k: float = 0.0

    def evaluate(self, grid: Grid, x_range=None, skip=None) -> np.ndarray:
        from .lattice import struts_field

        return struts_field(self.edges, grid, cutoff=self.cutoff, blend=self.k, x_range=_planes(grid, x_range),
                            skip=skip)


@dataclass(frozen=True)
class Blend:
    """`child` with its creases rounded over a width `k` (:func:`~implicit_scaffold.fields.field.blend_field`).

    It reads the Gaussian's halo on either side (clipped at the grid), so its planes are the
    whole grid's, bit for bit.

    Parameters
    ----------
    child : FieldNode
    k : float, mm
        0 gives `child` unchanged.
    mirror : ((3,), (3,)) tuple of float, mm, optional
        The box the lattice's cells fill (``Cells.lo``, ``Cells.hi``). Beyond its walls the
        cells end and the lattice is solid; a wall that lies on the patient's surface (a cube's
        or a cylinder's faces) would then blend that solid into the windows that open there,
        and close them with a film thinner than a voxel. So the filter reads the field mirrored
        in the walls, as if the cells went on in their mirror images, and a window on a wall
        stays as open as its channel.
    """

    child: Any
    k: float
    mirror: Any = None

    def halo(self, grid: Grid) -> int:
        """Planes the blend reads on either side."""
        from ..run.tiles import blend_halo

        return blend_halo(grid.spacing, self.k)

    def _reach(self, grid: Grid) -> float:
        # beyond a wall, the planes the filter of any plane inside the box reads
        return (self.halo(grid) + 1) * grid.spacing

    def _sources(self, grid: Grid, axis: int, first: int, last: int):
        """The mirror's sources ``(j, t)`` of the planes ``first..last`` along `axis`
        (:func:`~implicit_scaffold.fields.field.mirror_sources`), or None when none is mirrored."""
        from .field import mirror_sources

        if self.mirror is None or self.halo(grid) == 0:
            return None
        lo, hi = self.mirror
        j, t, moved = mirror_sources(grid.origin[axis], grid.spacing, grid.shape[axis], lo[axis], hi[axis],
                                     self._reach(grid), first, last)
        return (j, t) if moved.any() else None

    def _plan(self, grid: Grid, x0: int, x1: int):
        """The filter's input planes ``o0..o1`` (beyond the grid where a wall is mirrored), the
        child's planes ``c0..c1`` they come from, and the mirror's sources along x (or None)."""
        r, n = self.halo(grid), grid.shape[0]
        h0, h1 = max(0, x0 - r), min(n, x1 + r)
        along_x = self._sources(grid, 0, x0 - r, x1 + r)
        if along_x is None:
            return h0, h1, h0, h1, None
        j, t = along_x
        # the halo's planes too, mirrored or not: a caller reads its other fields there
        need = np.concatenate([j, j[t > 0] + 1, [h0, h1 - 1]])
        return x0 - r, x1 + r, int(need.min()), int(need.max()) + 1, along_x

    def reads(self, grid: Grid, x_range=None) -> tuple[int, int]:
        x0, x1 = _planes(grid, x_range)
        return self.child.reads(grid, self._plan(grid, x0, x1)[2:4])

    def evaluate(self, grid: Grid, x_range=None, skip=None) -> np.ndarray:
        from .field import blend_field, mirror_along

        x0, x1 = _planes(grid, x_range)
        o0, o1, c0, c1, along_x = self._plan(grid, x0, x1)
        values = self.child.evaluate(grid, (c0, c1), skip=skip)
        if along_x is not None:
            values = mirror_along(values, 0, c0, *along_x)
        pad, r = [0, 0, 0], self.halo(grid)
        for axis in (1, 2):
            along = self._sources(grid, axis, -r, grid.shape[axis] + r)
            if along is not None:
                values, pad[axis] = mirror_along(values, axis, 0, *along), r
        out = blend_field(values, grid.spacing, self.k, planes=(x0 - o0, x1 - o0))
        ny, nz = grid.shape[1:]
        return np.ascontiguousarray(out[:, pad[1]:pad[1] + ny, pad[2]:pad[2] + nz])


@dataclass(frozen=True)
class Patient(_Leaf):
    """A patient's signed distance (:mod:`~implicit_scaffold.fields.patient`, :func:`~implicit_scaffold.io.patient_io.load_patient`): any
    object with ``sdf_grid(grid, x_range=None)``."""

    patient: Any

    def evaluate(self, grid: Grid, x_range=None, skip=None) -> np.ndarray:
        from .patient import patient_sdf

        return patient_sdf(self.patient, grid, _planes(grid, x_range))


@dataclass(frozen=True)
class SDF(_Leaf):
    """Your own signed distance: ``fn(x, y, z)`` of broadcastable coordinate arrays (mm), negative inside.

    `fn` gets ``(rows, 1, 1)``, ``(1, ny, 1)`` and ``(1, 1, nz)`` arrays of voxel centres and
    returns ``(rows, ny, nz)`` values, as :func:`~implicit_scaffold.run.grid.evaluate_by_slabs` calls it.
    """

    fn: Callable

    def evaluate(self, grid: Grid, x_range=None, skip=None) -> np.ndarray:
        from ..run.grid import evaluate_by_slabs

        return evaluate_by_slabs(grid, self.fn, max_voxels=SDF_SLAB_VOXELS, x_range=_planes(grid, x_range))


@dataclass(frozen=True)
class Cut:
    """The lattice cut by the patient: ``max(lattice - level, patient)`` (:func:`~implicit_scaffold.fields.field.scaffold_field`),
    with an optional solid skin and smooth cut.

    Parameters
    ----------
    lattice, patient : FieldNode
    level : float, mm
        Surface offset: the solid is ``lattice < level`` (:func:`~implicit_scaffold.fields.field.solve_level` finds the
        level for a porosity).
    skin : float, mm
        A solid shell this thick at the patient surface; 0 for none.
    smooth_cut : float, mm
        Width of a smooth instead of a sharp maximum; 0 for sharp.
    """

    lattice: Any
    patient: Any
    level: float = 0.0
    skin: float = 0.0
    smooth_cut: float = 0.0

    def reads(self, grid: Grid, x_range=None) -> tuple[int, int]:
        a, b = self.lattice.reads(grid, x_range), self.patient.reads(grid, x_range)
        return min(a[0], b[0]), max(a[1], b[1])

    def evaluate(self, grid: Grid, x_range=None, skip=None) -> np.ndarray:
        from .field import scaffold_field

        # the skip mask is the lattice's (the patient's planes are never skipped)
        lattice = self.lattice.evaluate(grid, x_range, skip=skip)
        return scaffold_field(lattice, self.patient.evaluate(grid, x_range), level=self.level, skin=self.skin,
                              smooth_cut=self.smooth_cut, out=lattice)


def evaluate(node, grid: Grid, *, max_voxels: int | None = None) -> np.ndarray:
    """`node`'s field on the whole of `grid`, slab by slab along x.

    Parameters
    ----------
    node : FieldNode
    grid : Grid
    max_voxels : int, optional
        Voxels a slab may hold, the planes its node reads included; by default one slab.
        The values do not depend on it.

    Returns
    -------
    (nx, ny, nz) float32 ndarray, mm
    """
    from ..run.tiles import plan_slabs

    nx = grid.shape[0]
    if max_voxels is None:
        return np.ascontiguousarray(node.evaluate(grid, (0, nx)), np.float32)
    # the planes a middle plane reads: the halo the slabs are sized for (each node reads its
    # own halo whatever the plan, so this sizes the slabs and changes no value)
    h0, h1 = node.reads(grid, (nx // 2, nx // 2 + 1))
    halo = max(nx // 2 - h0, h1 - nx // 2 - 1)
    out = np.empty(grid.shape, np.float32)
    for slab in plan_slabs(grid.shape, max_voxels=max_voxels, halo=halo):
        out[slab.x0:slab.x1] = node.evaluate(grid, (slab.x0, slab.x1))
    return out
