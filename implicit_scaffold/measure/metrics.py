"""The paper's metrics, computed from the cells that were built (stage 8, paper §3).

Every metric here needs only the Voronoi cells and the scale factors, never the
field: it is what the paper measured on its polyhedra, in its words.

- pore size, the *polyhedron-sphere method*: the diameter of the sphere with the
  volume of the cell scaled by Sv;
- pore interconnection: the mean number of faces of the polyhedra that open into a
  neighbouring pore (box walls excluded, as DESIGN.md defines it); the paper's own
  count, walls included (its 8 cubes of Fig. 16a have six channels each, three of
  them through the walls), is reported beside it;
- channel size: the mean area of the faces of the polyhedra, and of the windows
  (the faces scaled by Sf);
- trabecular thickness: the mean distance between the centroids of the coupled
  faces of two neighbouring cells scaled by Sv.
"""
from __future__ import annotations

import numpy as np

from ..geometry.cells import Cells

#: the pore-size window that bone ingrowth favours (the paper's 150-600 µm), mm
BONE_PORE_RANGE_MM = (0.150, 0.600)
#: bins of the pore-size histogram in the report
HISTOGRAM_BINS = 20


def _stats(values: np.ndarray) -> dict:
    """Mean, population standard deviation, min, max and count of `values` (None when empty)."""
    v = np.asarray(values, dtype=np.float64)
    if v.size == 0:
        return {"mean": None, "sd": None, "min": None, "max": None, "count": 0}
    return {"mean": float(v.mean()), "sd": float(v.std()), "min": float(v.min()),
            "max": float(v.max()), "count": int(v.size)}


def pore_sizes(cells: Cells, sv: float) -> np.ndarray:
    """Polyhedron-sphere pore diameters, one per cell.

    The sphere has the volume of the cell scaled by `sv` about its centroid,
    ``Sv³ V_i``, so ``D_i = Sv (6 V_i / π)^(1/3)``.

    Parameters
    ----------
    cells : Cells
    sv : float
        Cell scale factor, 0 < Sv < 1.

    Returns
    -------
    (n,) float64 ndarray, mm
    """
    return sv * np.cbrt(6.0 * cells.volumes / np.pi)


def pore_size_histogram(diameters, bins: int = HISTOGRAM_BINS) -> dict | None:
    """Counts of pore diameters in equal bins from the smallest to the largest.

    Parameters
    ----------
    diameters : (n,) float array_like, mm
    bins : int

    Returns
    -------
    dict or None
        ``{"edges_mm": [bins + 1 floats], "counts": [bins ints]}`` (the layout of the
        voxel morphometry's histograms); one bin when all pores are equal; None when
        there is no pore.
    """
    d = np.asarray(diameters, dtype=np.float64)
    if d.size == 0:
        return None
    lo, hi = float(d.min()), float(d.max())
    if hi - lo <= 1e-6 * hi:
        # equal pores (a regular grid): one bin around them, not bins of a rounding error
        lo, hi, bins = lo * 0.995, hi * 1.005, 1
    counts, edges = np.histogram(d, bins=bins, range=(lo, hi))
    return {"edges_mm": [float(e) for e in edges], "counts": [int(c) for c in counts]}


def interior_face_pairs(cells: Cells) -> np.ndarray:
    """Indices of the interior faces counted once (owner < neighbour).

    Returns
    -------
    (k,) int64 ndarray
        Indices into the ``face_*`` arrays of `cells`.
    """
    return np.nonzero((cells.face_neighbor >= 0) & (cells.face_cell < cells.face_neighbor))[0]


def trabecular_thicknesses(cells: Cells, sv: float) -> np.ndarray:
    """Distance between the centroids of coupled faces of Sv-scaled neighbours, one per interior face.

    Face ``f`` of cell ``i`` scaled about ``g_i`` lands at ``g_i + Sv (g_f - g_i)``, the
    same face of ``j`` at ``g_j + Sv (g_f - g_j)``; their distance is ``(1 - Sv) |g_i - g_j|``.

    Parameters
    ----------
    cells : Cells
    sv : float

    Returns
    -------
    (k,) float64 ndarray, mm
        In the order of :func:`interior_face_pairs`.
    """
    f = interior_face_pairs(cells)
    gi = cells.centroids[cells.face_cell[f]]
    gj = cells.centroids[cells.face_neighbor[f]]
    return (1.0 - sv) * np.linalg.norm(gi - gj, axis=1)


def cell_metrics(cells: Cells, sf: float, sv: float, cells_in: np.ndarray | None = None) -> dict:
    """Pore size, interconnection, channel size and trabecular thickness of the cells (paper §3).

    Parameters
    ----------
    cells : Cells
    sf, sv : float
        Face and cell scale factors.
    cells_in : (n,) bool ndarray, optional
        The cells that lie in the scaffold (all by default).

    Returns
    -------
    dict
        - ``pore_size_mm``: mean, sd (population), min, max, count of the polyhedron-sphere
          diameters, ``share_150_600um`` (fraction of pores with 0.15 <= D <= 0.6 mm) and
          ``histogram`` (``edges_mm``, ``counts``);
        - ``pore_volume_mm3_sum``: the spheres' total volume, ``Sv³ Σ V_i``;
        - ``interconnection_faces_mean``: mean faces per cell that open into a neighbouring
          cell (box walls excluded, as DESIGN.md defines pore interconnection);
        - ``interconnection_faces_with_walls_mean``: mean faces per cell, box walls included
          (the paper's count: a channel leaves through every face);
        - ``channel_area_mm2_mean``: mean area of the cells' faces (each cell's copy, walls
          included), mm²; ``window_area_mm2_mean``: the same scaled by ``Sf²``;
        - ``trabecular_thickness_mm_mean`` and ``_sd``: over the interior faces with at least
          one cell in the scaffold, mm.
        Values are None when no cell is selected.
    """
    sel = np.ones(cells.n, bool) if cells_in is None else np.asarray(cells_in, bool)
    d = pore_sizes(cells, sv)[sel]
    stats = _stats(d)
    lo, hi = BONE_PORE_RANGE_MM
    stats["share_150_600um"] = float(np.mean((d >= lo) & (d <= hi))) if d.size else None
    stats["histogram"] = pore_size_histogram(d)

    # every face of every selected polyhedron: a channel departs from each one
    own = sel[cells.face_cell]
    areas = cells.face_areas[own]
    faces = cells.faces_per_cell(walls=True)[sel]
    neighbours = cells.faces_per_cell(walls=False)[sel]

    pairs = interior_face_pairs(cells)
    touch = sel[cells.face_cell[pairs]] | sel[cells.face_neighbor[pairs]]
    thick = trabecular_thicknesses(cells, sv)[touch]
    return {
        "pore_size_mm": stats,
        "pore_volume_mm3_sum": float(np.sum(np.pi / 6.0 * d ** 3)),
        "interconnection_faces_with_walls_mean": float(faces.mean()) if faces.size else None,
        "interconnection_faces_mean": float(neighbours.mean()) if neighbours.size else None,
        "channel_area_mm2_mean": float(areas.mean()) if areas.size else None,
        "window_area_mm2_mean": float(sf ** 2 * areas.mean()) if areas.size else None,
        "trabecular_thickness_mm_mean": float(thick.mean()) if thick.size else None,
        "trabecular_thickness_mm_sd": float(thick.std()) if thick.size else None,
    }
