"""Patient geometry (stage 1): analytic primitives and the patient's signed distance.

A patient is anything with ``lo``/``hi`` bounds (mm), a ``volume`` (mm³) and a
``sdf_grid(grid)`` method that returns its signed distance on a grid, negative
inside the bone. The primitives here (box, cylinder, sphere) are also the test
fixtures; mesh and volume patients live in their own modules.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np

from ..errors import ScaffoldError
from ..run.grid import Grid, evaluate_by_slabs

#: voxels evaluated at once by the analytic primitives (bounds the work arrays)
_SLAB_VOXELS = 4_000_000


def _check_size(size) -> tuple[float, float, float]:
    try:
        vals = [float(size)] * 3 if np.isscalar(size) else [float(v) for v in size]
    except (TypeError, ValueError):
        raise ScaffoldError(f"--size takes one or three lengths in mm, got {size!r}") from None
    if len(vals) == 1:
        vals = vals * 3
    if len(vals) != 3 or not all(math.isfinite(v) and v > 0 for v in vals):
        raise ScaffoldError(f"--size must be one or three positive lengths in mm, got {size!r}; e.g. --size 10")
    return tuple(vals)


class _Analytic:
    """Shared slab-wise evaluation of an analytic signed distance on a grid."""

    def sdf(self, points) -> np.ndarray:  # pragma: no cover - every primitive defines it
        raise NotImplementedError

    def sdf_grid(self, grid: Grid, x_range=None) -> np.ndarray:
        """Signed distance on `grid` (the planes `x_range` only, if given), float32, mm, negative inside."""
        return evaluate_by_slabs(grid, self.sdf_axes, max_voxels=_SLAB_VOXELS, x_range=x_range)

    def sdf_axes(self, x, y, z) -> np.ndarray:
        """Signed distance at broadcastable coordinate arrays, mm."""
        shape = np.broadcast_shapes(np.shape(x), np.shape(y), np.shape(z))
        pts = np.stack(np.broadcast_arrays(x, y, z), axis=-1).reshape(-1, 3)
        return self.sdf(pts).reshape(shape)


@dataclass(frozen=True)
class Box(_Analytic):
    """The box ``[0, size]`` (mm); the paper's 10 mm cube by default."""

    size: tuple[float, float, float] = (10.0, 10.0, 10.0)

    def __post_init__(self):
        object.__setattr__(self, "size", _check_size(self.size))

    @property
    def lo(self):
        return np.zeros(3)

    @property
    def hi(self):
        return np.asarray(self.size, dtype=np.float64)

    @property
    def volume(self) -> float:
        return float(np.prod(self.size))

    def sdf(self, points):
        p = np.asarray(points, np.float64)
        return self.sdf_axes(p[..., 0], p[..., 1], p[..., 2])

    def sdf_grid(self, grid: Grid, x_range=None) -> np.ndarray:
        """Signed distance on `grid` (the planes `x_range` only, if given), float32, mm, negative
        inside: :meth:`sdf_axes` voxel by voxel in one compiled pass, without its float64 grids
        (the same operations in the same order, so the same values)."""
        lo, hi = (0, grid.shape[0]) if x_range is None else (int(x_range[0]), int(x_range[1]))
        half = self.hi / 2
        q = [np.abs(c - m) - m for c, m in zip(grid.axes(), half)]
        out = np.empty((hi - lo,) + tuple(grid.shape[1:]), np.float32)
        _box_planes(np.ascontiguousarray(q[0][lo:hi]), q[1], q[2], out)
        return out

    def sdf_axes(self, x, y, z):
        half = self.hi / 2
        q = [np.abs(c - m) - m for c, m in zip((x, y, z), half)]
        outside = np.sqrt(sum(np.maximum(c, 0) ** 2 for c in q))
        return outside + np.minimum(np.maximum(np.maximum(q[0], q[1]), q[2]), 0)


@nb.njit(cache=True, nogil=True, boundscheck=False)
def _box_planes(qx, qy, qz, out):  # pragma: no cover - compiled
    # Box.sdf_axes from the axes' distances to the faces, q = |c - m| - m
    for i in range(qx.size):
        ox = max(qx[i], 0.0)
        for j in range(qy.size):
            oy = max(qy[j], 0.0)
            oxy = ox * ox + oy * oy
            mxy = max(qx[i], qy[j])
            for k in range(qz.size):
                oz = max(qz[k], 0.0)
                out[i, j, k] = math.sqrt(oxy + oz * oz) + min(max(mxy, qz[k]), 0.0)


@dataclass(frozen=True)
class Cylinder(_Analytic):
    """A cylinder along z, of diameter ``size[0]`` and height ``size[2]``, in ``[0, size]``."""

    size: tuple[float, float, float] = (10.0, 10.0, 10.0)

    def __post_init__(self):
        s = _check_size(self.size)
        object.__setattr__(self, "size", (s[0], s[0], s[2]))

    @property
    def lo(self):
        return np.zeros(3)

    @property
    def hi(self):
        return np.asarray(self.size, dtype=np.float64)

    @property
    def volume(self) -> float:
        return math.pi * (self.size[0] / 2) ** 2 * self.size[2]

    def sdf(self, points):
        p = np.asarray(points, np.float64)
        return self.sdf_axes(p[..., 0], p[..., 1], p[..., 2])

    def sdf_axes(self, x, y, z):
        r = self.size[0] / 2
        radial = np.hypot(x - r, y - r) - r
        axial = np.abs(z - self.size[2] / 2) - self.size[2] / 2
        return np.hypot(np.maximum(radial, 0), np.maximum(axial, 0)) + np.minimum(np.maximum(radial, axial), 0)


@dataclass(frozen=True)
class Sphere(_Analytic):
    """A ball of diameter ``size[0]`` centred in ``[0, size]``."""

    size: tuple[float, float, float] = (10.0, 10.0, 10.0)

    def __post_init__(self):
        s = _check_size(self.size)
        object.__setattr__(self, "size", (s[0],) * 3)

    @property
    def lo(self):
        return np.zeros(3)

    @property
    def hi(self):
        return np.asarray(self.size, dtype=np.float64)

    @property
    def volume(self) -> float:
        return math.pi / 6 * self.size[0] ** 3

    def sdf(self, points):
        p = np.asarray(points, np.float64)
        return self.sdf_axes(p[..., 0], p[..., 1], p[..., 2])

    def sdf_axes(self, x, y, z):
        r = self.size[0] / 2
        return np.sqrt((x - r) ** 2 + (y - r) ** 2 + (z - r) ** 2) - r


SHAPES = {"box": Box, "cylinder": Cylinder, "sphere": Sphere}


def primitive(shape: str, size=10.0):
    """The analytic patient named `shape` (``box``, ``cylinder`` or ``sphere``) of `size` mm."""
    try:
        cls = SHAPES[shape]
    except KeyError:
        raise ScaffoldError(f"unknown --shape {shape!r}; use one of: {', '.join(SHAPES)}") from None
    return cls(size)


def patient_sdf(patient, grid: Grid, x_range=None) -> np.ndarray:
    """The patient's signed distance on `grid`, float32, mm, negative inside.

    Parameters
    ----------
    patient : object with ``sdf_grid(grid, x_range=None)``
    grid : Grid
    x_range : (x0, x1), optional
        Only these planes (a slab of a tiled run): the same values as those planes of
        the whole grid.

    Returns
    -------
    (x1 - x0, ny, nz) float32 ndarray, mm
        All ``(nx, ny, nz)`` planes without `x_range`.
    """
    if x_range is None:
        return np.asarray(patient.sdf_grid(grid), dtype=np.float32)
    return np.asarray(patient.sdf_grid(grid, x_range=x_range), dtype=np.float32)


# --- surgical cuts -----------------------------------------------------------------

#: voxels across the kept part when its bounds or volume are measured on a grid
_CUT_CELLS = 64


def clamp_far_field(patient, reach: float):
    """`patient`, or a copy of it whose distance may be clamped beyond `reach` mm from the
    surface (plus a few voxels) so that it can be computed slab by slab.

    Only a mesh patient (and a cut of one) has a far field that needs the whole grid;
    the others are returned as they are. The clamp changes no sign and no value a run
    reads (see :meth:`~implicit_scaffold.fields.patient_mesh.MeshPatient.clamp_far_field`).
    """
    clamp = getattr(patient, "clamp_far_field", None)
    return patient if clamp is None else clamp(reach)


def far_clamp(patient, grid: Grid) -> float:
    """The distance (mm) from which `patient`'s distance on `grid` may be clamped (a mesh's far
    field, :func:`clamp_far_field`): a voxel that far out is at least that far from the
    patient. Infinity for a patient whose distance is exact everywhere."""
    clamp = getattr(patient, "far_clamp", None)
    return float("inf") if clamp is None else float(clamp(grid))


def cut_halfspaces(clip=None, cut_planes=None) -> np.ndarray:
    """The half-spaces ``n . x <= d`` (unit ``n``) that keep what a surgeon keeps.

    Parameters
    ----------
    clip : (6,) sequence of float, mm, optional
        ``(xmin, ymin, zmin, xmax, ymax, zmax)``: keep what lies in this box.
    cut_planes : (12,) sequence of float, mm, optional
        Two osteotomy planes, point and normal each: keep the segment between them.

    Returns
    -------
    (k, 4) float64 ndarray
        Rows ``(nx, ny, nz, d)``; none when neither cut is given.
    """
    rows = []
    if clip is not None:
        c = np.asarray(clip, np.float64).ravel()
        if c.shape != (6,) or not np.all(np.isfinite(c)):
            raise ScaffoldError(f"--clip takes six numbers xmin ymin zmin xmax ymax zmax (mm), got {clip!r}")
        if np.any(c[3:] <= c[:3]):
            raise ScaffoldError(f"--clip box is empty: each max must exceed its min, got {c.tolist()}; "
                                "give xmin ymin zmin xmax ymax zmax")
        for a in range(3):
            e = np.eye(3)[a]
            rows += [[*(-e), -c[a]], [*e, c[3 + a]]]
    if cut_planes is not None:
        c = np.asarray(cut_planes, np.float64).ravel()
        if c.shape != (12,) or not np.all(np.isfinite(c)):
            raise ScaffoldError("--cut-planes takes twelve numbers: a point and a normal for each of two planes "
                                f"(mm), got {cut_planes!r}")
        p, n, q, m = c[0:3], c[3:6], c[6:9], c[9:12]
        if np.linalg.norm(n) == 0 or np.linalg.norm(m) == 0:
            raise ScaffoldError("--cut-planes normals must be non-zero vectors, e.g. 0 0 1")
        n, m = n / np.linalg.norm(n), m / np.linalg.norm(m)
        # keep the side of each plane that holds the other plane's point: the segment between them
        for point, normal, other in ((p, n, q), (q, m, p)):
            side = float(np.dot(other - point, normal))
            if side == 0:
                raise ScaffoldError("--cut-planes: each plane's point must lie off the other plane; "
                                    "give two distinct osteotomy planes")
            keep = normal if side > 0 else -normal
            rows.append([*(-keep), -float(np.dot(keep, point))])
    return np.asarray(rows, np.float64).reshape(-1, 4)


def _halfspace_box(hs: np.ndarray, lo, hi):
    """Shrink ``[lo, hi]`` by the half-spaces whose normal is along an axis (exact bounds there)."""
    lo, hi = np.array(lo, np.float64), np.array(hi, np.float64)
    for *n, d in hs:
        a = int(np.argmax(np.abs(n)))
        if abs(abs(n[a]) - 1) < 1e-12:
            if n[a] > 0:
                hi[a] = min(hi[a], d / n[a])
            else:
                lo[a] = max(lo[a], d / n[a])
    return lo, hi


@nb.njit(cache=True, nogil=True, boundscheck=False)
def _cut_rows(out, hs, ax, ay, az, lo, hi):  # pragma: no cover - compiled
    # out = max(out, max_h (n_h . x - d_h)) on the planes [lo, hi), each half-space's value summed
    # as CutPatient.cut_sdf_axes sums it, ((nx x + ny y) + nz z) - d, in float64
    for i in range(lo, hi):
        x = ax[i]
        for j in range(ay.size):
            y = ay[j]
            for k in range(az.size):
                z = az[k]
                best = ((hs[0, 0] * x + hs[0, 1] * y) + hs[0, 2] * z) - hs[0, 3]
                for h in range(1, hs.shape[0]):
                    v = ((hs[h, 0] * x + hs[h, 1] * y) + hs[h, 2] * z) - hs[h, 3]
                    if v > best:
                        best = v
                f = np.float32(best)
                if f > out[i, j, k]:
                    out[i, j, k] = f


class CutPatient:
    """The part of a patient that a clip box and/or two osteotomy planes keep.

    Its signed distance is ``max(s_base, max_i(n_i . x - d_i))``, its bounds those of
    what is kept, and its volume that of what is kept: exact along grid lines for a
    mesh (``base.volume_within``), counted on a fine grid otherwise.

    Parameters
    ----------
    base : patient
        Anything with ``lo``, ``hi``, ``volume`` and ``sdf_grid``.
    halfspaces : (k, 4) float ndarray
        From :func:`cut_halfspaces`.
    what : str
        The cut as the user gave it, for messages and the report.
    """

    def __init__(self, base, halfspaces, *, what: str = "cut"):
        self.base = base
        self.halfspaces = np.asarray(halfspaces, np.float64).reshape(-1, 4)
        self.what = what
        blo, bhi = np.asarray(base.lo, np.float64), np.asarray(base.hi, np.float64)
        lo, hi = _halfspace_box(self.halfspaces, blo, bhi)
        if np.any(hi <= lo):
            self._miss(blo, bhi)
        if hasattr(base, "volume_within"):
            volume, klo, khi = base.volume_within(self.halfspaces, lo, hi)
            if klo is None or volume <= 0:
                self._miss(blo, bhi)
            self.lo, self.hi, self._volume = klo, khi, float(volume)
        else:
            self.lo, self.hi, self._volume = self._measure(lo, hi, blo, bhi)

    def _miss(self, blo, bhi):
        span = ", ".join(f"{a} {lo:.4g}..{hi:.4g}" for a, lo, hi in zip("xyz", blo, bhi))
        raise ScaffoldError(f"the {self.what} keeps none of the bone (it spans {span} mm); "
                            "move the cut onto the bone")

    def _measure(self, lo, hi, blo, bhi):
        """Bounds (refined twice on coarse grids) and volume (voxel count) of what is kept."""
        for _ in range(2):
            h = float(np.max(hi - lo)) / _CUT_CELLS
            grid = Grid.covering(lo, hi, h)
            kept = self._sdf_on(grid) <= 0
            if not kept.any():
                self._miss(blo, bhi)
            idx = np.argwhere(kept)
            pts_lo = grid.indices_to_points(idx.min(axis=0)[None])[0]
            pts_hi = grid.indices_to_points(idx.max(axis=0)[None])[0]
            # a voxel centre stands for its whole voxel, and one more for what lies between centres
            lo, hi = np.maximum(pts_lo - 1.5 * h, lo), np.minimum(pts_hi + 1.5 * h, hi)
        h = float(np.max(hi - lo)) / (4 * _CUT_CELLS)
        grid = Grid.covering(lo, hi, h)
        volume = float(np.count_nonzero(self._sdf_on(grid) < 0)) * grid.voxel_volume
        return lo, hi, volume

    @property
    def volume(self) -> float:
        """Volume of what is kept, mm³."""
        return self._volume

    def describe(self) -> str:
        base = getattr(self.base, "describe", lambda: type(self.base).__name__.lower())()
        return f"{base}, {self.what}"

    def cut_sdf_axes(self, x, y, z) -> np.ndarray:
        """``max_i(n_i . x - d_i)`` at broadcastable coordinates, mm (negative where kept)."""
        out = None
        for nx, ny, nz, d in self.halfspaces:
            v = nx * x + ny * y + nz * z - d
            out = v if out is None else np.maximum(out, v)
        return out

    def _sdf_on(self, grid: Grid, x_range=None) -> np.ndarray:
        from ..run.threads import over_rows

        out = patient_sdf(self.base, grid, x_range)
        if not len(self.halfspaces):
            return out
        lo = 0 if x_range is None else int(x_range[0])
        ax, ay, az = grid.axes()
        # max(out, cut_sdf_axes) in one compiled pass: the same float64 sums, in the same order,
        # rounded to float32 as evaluate_by_slabs(cut_sdf_axes) then np.maximum round them
        over_rows(_cut_rows, out.shape[0], out, np.ascontiguousarray(self.halfspaces, np.float64),
                  np.ascontiguousarray(ax[lo:lo + out.shape[0]]), np.ascontiguousarray(ay), np.ascontiguousarray(az))
        return out

    def sdf_grid(self, grid: Grid, x_range=None) -> np.ndarray:
        """Signed distance on `grid` (the planes `x_range` only, if given), float32, mm,
        negative inside what is kept."""
        return self._sdf_on(grid, x_range)

    def far_clamp(self, grid: Grid) -> float:
        """The base's (:func:`far_clamp`): the cut planes' distances are exact, and a voxel at
        least that far from the base or from the planes is that far from what is kept."""
        return far_clamp(self.base, grid)

    def clamp_far_field(self, reach: float) -> "CutPatient":
        """This cut of the base patient with the base's far field clamped (:func:`clamp_far_field`)."""
        import copy

        out = copy.copy(self)
        out.base = clamp_far_field(self.base, reach)
        return out
