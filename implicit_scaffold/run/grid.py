"""Voxel grids: an index array plus a transform (origin, spacing, shape).

Voxel ``(i, j, k)`` has its centre at ``origin + (i, j, k) * spacing``; arrays over a
grid are C-ordered with shape ``(nx, ny, nz)``, so z varies fastest. Units are mm.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ScaffoldError

#: bytes per voxel that a run that stops at the field keeps alive at its peak: lattice
#: field, blended field, patient field and scaffold field (float32 each) and masks.
PIPELINE_BYTES_PER_VOXEL = 28
#: the same with the voxel morphometry (distance transforms, local thickness): 8.2 GB
#: measured at 107.7 M voxels (a 20 mm femoral shaft at 0.05 mm), rounded up
MORPHOMETRY_BYTES_PER_VOXEL = 80
#: the same with the mesh: the stage peaks in mesh_summary at 100-123 bytes per
#: triangle over what the run holds before it (measured with /proc VmHWM around
#: mesh_field + mesh_summary at 2-16 M voxels); at the scaffolds' usual 0.66 triangles
#: per voxel (a 20 mm femoral shaft at 0.05 mm: 107.7 M voxels, 71 M triangles) that is
#: 82 bytes per voxel, plus about 20 held by the earlier stages, rounded up
MESH_BYTES_PER_VOXEL = 112
#: the same with the printer's repair held in memory (its field, offsets, weights and measures
#: for the round kept and the one tried): 1,087 MiB peak on a 202^3 grid (8.2 M voxels), from
#: 234 MiB held before the lattice, 104 bytes a voxel, rounded up; a grid that cannot hold it is
#: repaired in slabs (fields/repair.py, repair_by_slabs)
REPAIR_BYTES_PER_VOXEL = 112


def run_bytes_per_voxel(*, mesh: bool, morphometry: bool, repair: bool = False) -> int:
    """Peak bytes per voxel of a pipeline run that meshes or not, measures or not, repairs or not."""
    if mesh:
        stages = MESH_BYTES_PER_VOXEL
    else:
        stages = MORPHOMETRY_BYTES_PER_VOXEL if morphometry else PIPELINE_BYTES_PER_VOXEL
    # the repair's arrays are freed before the mesh and the measures
    return max(stages, REPAIR_BYTES_PER_VOXEL) if repair else stages


@dataclass(frozen=True)
class Grid:
    """A regular voxel grid.

    Parameters
    ----------
    origin : (3,) tuple of float, mm
        Centre of voxel ``(0, 0, 0)``.
    spacing : float, mm
        Edge length of a (cubic) voxel.
    shape : (3,) tuple of int
        Number of voxels along x, y and z.
    """

    origin: tuple[float, float, float]
    spacing: float
    shape: tuple[int, int, int]

    def __post_init__(self):
        if not (np.isfinite(self.spacing) and self.spacing > 0):
            raise ScaffoldError(f"voxel size must be a positive number of mm, got {self.spacing!r}")
        if len(self.shape) != 3 or min(self.shape) < 1:
            raise ScaffoldError(f"grid shape must be three positive counts, got {self.shape!r}")

    @classmethod
    def covering(cls, lo, hi, spacing: float, pad: int = 1) -> "Grid":
        """The grid of voxel size `spacing` whose voxels cover the box ``[lo, hi]``.

        The box is centred in the grid, and `pad` extra layers of voxels lie
        outside it on every side (marching cubes needs one "outside" layer to
        close the surface).

        Parameters
        ----------
        lo, hi : (3,) array_like of float, mm
            Corners of the box.
        spacing : float, mm
        pad : int
        """
        lo = np.asarray(lo, dtype=np.float64)
        hi = np.asarray(hi, dtype=np.float64)
        if not (np.isfinite(spacing) and spacing > 0):
            raise ScaffoldError(
                f"voxel size must be a positive number of mm, got {spacing!r}; pass e.g. --voxel 0.04")
        size = hi - lo
        inner = np.maximum(np.ceil(size / spacing - 1e-9), 1).astype(np.int64)
        shape = inner + 2 * pad
        centre = (lo + hi) / 2
        origin = centre - (shape - 1) / 2 * spacing
        return cls(tuple(float(v) for v in origin), float(spacing), tuple(int(v) for v in shape))

    @property
    def size(self) -> int:
        """Number of voxels."""
        return int(np.prod(self.shape, dtype=np.int64))

    @property
    def lo(self) -> np.ndarray:
        """Lower corner of the grid's voxel region (not of the first centre), mm."""
        return np.asarray(self.origin) - self.spacing / 2

    @property
    def hi(self) -> np.ndarray:
        """Upper corner of the grid's voxel region, mm."""
        return np.asarray(self.origin) + (np.asarray(self.shape) - 0.5) * self.spacing

    @property
    def voxel_volume(self) -> float:
        """Volume of one voxel, mm³."""
        return self.spacing ** 3

    def axes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Voxel-centre coordinates along x, y and z, mm (float64)."""
        return tuple(self.origin[a] + np.arange(self.shape[a]) * self.spacing for a in range(3))

    def points(self, index_lo=(0, 0, 0), index_hi=None) -> np.ndarray:
        """Voxel centres of the sub-block ``[index_lo, index_hi)``, as ``(m, 3)`` float64, mm."""
        index_hi = self.shape if index_hi is None else index_hi
        ax = [self.origin[a] + np.arange(index_lo[a], index_hi[a]) * self.spacing for a in range(3)]
        return np.stack(np.meshgrid(*ax, indexing="ij"), axis=-1).reshape(-1, 3)

    def points_to_indices(self, points) -> np.ndarray:
        """Nearest voxel index of each point, ``(m, 3)`` int64 (not clipped to the grid)."""
        p = np.asarray(points, dtype=np.float64)
        return np.rint((p - np.asarray(self.origin)) / self.spacing).astype(np.int64)

    def indices_to_points(self, indices) -> np.ndarray:
        """Voxel centres of integer indices, ``(m, 3)`` float64, mm."""
        return np.asarray(self.origin) + np.asarray(indices, dtype=np.float64) * self.spacing

    def memory_estimate(self, bytes_per_voxel: int = PIPELINE_BYTES_PER_VOXEL) -> int:
        """Bytes a pipeline run over this grid holds at its peak (an estimate)."""
        return self.size * int(bytes_per_voxel)


def evaluate_by_slabs(grid: Grid, fn, *, max_voxels: int, x_range=None) -> np.ndarray:
    """``fn(x, y, z)`` on the voxel centres of `grid`, slab by slab along x, as float32.

    `fn` receives broadcastable coordinate arrays, mm (``(rows, 1, 1)``, ``(1, ny, 1)``,
    ``(1, 1, nz)``), so no ``(m, 3)`` point array is built, and returns values of shape
    ``(rows, ny, nz)``; a slab holds at most about `max_voxels` voxels. The coordinates
    are the whole grid's, so the planes `x_range` alone get the same values.

    Returns
    -------
    (x1 - x0, ny, nz) float32 ndarray
        The planes ``x_range = (x0, x1)``; all of them by default.
    """
    lo, hi = (0, grid.shape[0]) if x_range is None else (int(x_range[0]), int(x_range[1]))
    out = np.empty((hi - lo,) + tuple(grid.shape[1:]), np.float32)
    ax, ay, az = grid.axes()
    rows = max(1, int(max_voxels) // (grid.shape[1] * grid.shape[2]))
    for x0 in range(lo, hi, rows):
        x1 = min(x0 + rows, hi)
        out[x0 - lo:x1 - lo] = fn(ax[x0:x1, None, None], ay[None, :, None], az[None, None, :])
    return out
