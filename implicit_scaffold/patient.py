"""Patient geometry (stage 1): analytic primitives and the patient's signed distance.

A patient is anything with ``lo``/``hi`` bounds (mm), a ``volume`` (mm³) and a
``sdf_grid(grid)`` method that returns its signed distance on a grid, negative
inside the bone. The primitives here (box, cylinder, sphere) are also the test
fixtures; mesh and volume patients live in their own modules.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import ScaffoldError
from .grid import Grid

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

    def sdf_grid(self, grid: Grid) -> np.ndarray:
        """Signed distance on `grid`, ``(nx, ny, nz)`` float32, mm, negative inside."""
        out = np.empty(grid.shape, np.float32)
        ax, ay, az = grid.axes()
        rows = max(1, _SLAB_VOXELS // (grid.shape[1] * grid.shape[2]))
        for x0 in range(0, grid.shape[0], rows):
            x1 = min(x0 + rows, grid.shape[0])
            # broadcast (rows, 1, 1) x (1, ny, 1) x (1, 1, nz) axes: no (m, 3) point array
            p = (ax[x0:x1, None, None], ay[None, :, None], az[None, None, :])
            out[x0:x1] = self.sdf_axes(*p)
        return out

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

    def sdf_axes(self, x, y, z):
        half = self.hi / 2
        q = [np.abs(c - m) - m for c, m in zip((x, y, z), half)]
        outside = np.sqrt(sum(np.maximum(c, 0) ** 2 for c in q))
        return outside + np.minimum(np.maximum(np.maximum(q[0], q[1]), q[2]), 0)


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


def patient_sdf(patient, grid: Grid) -> np.ndarray:
    """The patient's signed distance on `grid`, ``(nx, ny, nz)`` float32, mm, negative inside."""
    return np.asarray(patient.sdf_grid(grid), dtype=np.float32)
