"""The paper's metrics, computed from the cells that were built (stage 8, paper §3)."""
from __future__ import annotations

import numpy as np

from .cells import Cells

#: the pore-size window that bone ingrowth favours (Cornell 1999), mm
BONE_PORE_RANGE_MM = (0.150, 0.600)


def _stats(values: np.ndarray) -> dict:
    v = np.asarray(values, dtype=np.float64)
    if v.size == 0:
        return {"mean": None, "sd": None, "min": None, "max": None, "count": 0}
    return {"mean": float(v.mean()), "sd": float(v.std()), "min": float(v.min()),
            "max": float(v.max()), "count": int(v.size)}


def pore_sizes(cells: Cells, sv: float) -> np.ndarray:
    """Polyhedron-sphere pore diameters: ``D_i = (6 Sv³ V_i / π)^(1/3)``, mm."""
    return sv * np.cbrt(6.0 * cells.volumes / np.pi)


def interior_face_pairs(cells: Cells) -> np.ndarray:
    """Indices of the interior faces counted once (owner < neighbour)."""
    return np.nonzero((cells.face_neighbor >= 0) & (cells.face_cell < cells.face_neighbor))[0]


def trabecular_thicknesses(cells: Cells, sv: float) -> np.ndarray:
    """Distance between the centroids of coupled faces of Sv-scaled neighbours, mm.

    Face ``f`` of cell ``i`` scaled about ``g_i`` lands at ``g_i + Sv (g_f - g_i)``, the
    same face of ``j`` at ``g_j + Sv (g_f - g_j)``; their distance is ``(1 - Sv) |g_i - g_j|``.
    """
    f = interior_face_pairs(cells)
    gi = cells.centroids[cells.face_cell[f]]
    gj = cells.centroids[cells.face_neighbor[f]]
    return (1.0 - sv) * np.linalg.norm(gi - gj, axis=1)


def cell_metrics(cells: Cells, sf: float, sv: float, cells_in: np.ndarray | None = None) -> dict:
    """Pore size, interconnection, channel size and trabecular thickness of the cells.

    Parameters
    ----------
    cells : Cells
    sf, sv : float
    cells_in : (n,) bool ndarray, optional
        The cells that lie in the scaffold (all by default).

    Returns
    -------
    dict
        ``pore_size_mm`` (stats and ``share_150_600um``), ``interconnection_faces_mean``,
        ``channel_area_mm2_mean``, ``window_area_mm2_mean``, ``trabecular_thickness_mm_mean``.
    """
    sel = np.ones(cells.n, bool) if cells_in is None else np.asarray(cells_in, bool)
    d = pore_sizes(cells, sv)[sel]
    stats = _stats(d)
    lo, hi = BONE_PORE_RANGE_MM
    stats["share_150_600um"] = float(np.mean((d >= lo) & (d <= hi))) if d.size else None
    interior = (cells.face_neighbor >= 0) & sel[cells.face_cell]
    areas = cells.face_areas[interior]
    pairs = interior_face_pairs(cells)
    pairs = pairs[sel[cells.face_cell[pairs]] | sel[cells.face_neighbor[pairs]]]
    f = pairs
    thick = (1.0 - sv) * np.linalg.norm(cells.centroids[cells.face_cell[f]] - cells.centroids[cells.face_neighbor[f]], axis=1)
    return {
        "pore_size_mm": stats,
        "interconnection_faces_mean": float(cells.faces_per_cell()[sel].mean()) if sel.any() else None,
        "channel_area_mm2_mean": float(areas.mean()) if areas.size else None,
        "window_area_mm2_mean": float(sf ** 2 * areas.mean()) if areas.size else None,
        "trabecular_thickness_mm_mean": float(thick.mean()) if thick.size else None,
    }
