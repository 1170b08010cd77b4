"""The patient's pieces: fragment removal and the report, piece by piece.

A patient may come in several pieces (two vertebrae in one clip, the fragments of a
broken bone, the sides of an osteotomy gap). Each piece gets its own scaffold: a solid
piece of the scaffold is debris only when it is not the main body of the patient piece
it lies in, never because another patient piece holds a larger body.

Pieces are 6-connected sets of voxels inside the patient (``s_P < 0``), as the
scaffold's solid pieces are (:func:`.field.remove_fragments`). Since the scaffold's
solid lies inside the patient, every solid piece lies in exactly one patient piece.
"""
from __future__ import annotations

import numpy as np

#: pieces listed one by one in the report (the largest first); the rest are summed up
REPORT_PIECES = 20


def label_pieces(inside: np.ndarray) -> tuple[np.ndarray, int]:
    """The patient's 6-connected pieces.

    Parameters
    ----------
    inside : (nx, ny, nz) bool ndarray
        Voxels inside the patient.

    Returns
    -------
    labels : (nx, ny, nz) int32 ndarray
        0 outside, 1..count for the pieces, numbered in C order of their first voxel.
    count : int
    """
    from scipy import ndimage

    labels, count = ndimage.label(inside)
    return labels.astype(np.int32, copy=False), int(count)


def main_bodies(solid_labels: np.ndarray, sizes: np.ndarray, piece_labels: np.ndarray) -> np.ndarray:
    """The solid labels kept: the largest solid piece of each patient piece.

    Parameters
    ----------
    solid_labels : int ndarray
        Solid pieces, 0 for none (``scipy.ndimage.label``).
    sizes : (count + 1,) int ndarray
        Voxels per solid label (index 0 unused).
    piece_labels : int ndarray, same shape
        Patient pieces, 0 outside.

    Returns
    -------
    (count + 1,) bool ndarray
        True for the labels to keep (index 0 False). On a tie within a patient piece the
        label met first in C order is kept, as :func:`.field.remove_fragments` does.
    """
    count = len(sizes) - 1
    piece_of = solid_piece(solid_labels, piece_labels, count)
    keep = np.zeros(count + 1, bool)
    if count == 0:
        return keep
    ids = np.arange(1, count + 1)
    # by patient piece, then largest first, then lowest label: the first row of a piece is its body
    order = np.lexsort((ids, -sizes[1:], piece_of[1:]))
    first = np.ones(count, bool)
    first[1:] = piece_of[1:][order[1:]] != piece_of[1:][order[:-1]]
    keep[ids[order[first]]] = True
    return keep


def solid_piece(solid_labels: np.ndarray, piece_labels: np.ndarray, count: int) -> np.ndarray:
    """The patient piece each solid label lies in ((count + 1,) int64; 0 for label 0)."""
    piece_of = np.zeros(count + 1, np.int64)
    flat = solid_labels.ravel()
    where = np.flatnonzero(flat)
    # a solid piece lies in one patient piece: any of its voxels tells which
    piece_of[flat[where]] = piece_labels.ravel()[where]
    return piece_of


def remove_fragments_by_piece(field: np.ndarray, piece_labels: np.ndarray, *, outside: float) -> dict:
    """Turn into void every solid piece that is not the main body of its patient piece, in place.

    Parameters
    ----------
    field : float32 ndarray, mm
        Scaffold field, negative in the solid; modified in place.
    piece_labels : int ndarray, same shape
        From :func:`label_pieces`.
    outside : float, mm
        Value written into removed voxels (positive, e.g. one voxel).

    Returns
    -------
    dict
        ``removed`` (pieces turned into void) and ``removed_voxels``.
    """
    from scipy import ndimage

    labels, count = ndimage.label(field < 0)
    if count <= 1:
        return {"removed": 0, "removed_voxels": 0}
    sizes = np.bincount(labels.ravel(), minlength=count + 1)
    sizes[0] = 0
    keep = main_bodies(labels, sizes, piece_labels)
    drop_label = ~keep
    drop_label[0] = False
    drop = drop_label[labels]
    field[drop] = np.float32(outside)
    return {"removed": int(np.count_nonzero(drop_label)), "removed_voxels": int(sizes[drop_label].sum())}


def piece_table(piece_labels: np.ndarray, count: int, solid: np.ndarray, grid, seeds: np.ndarray, *,
                main_bodies_only: bool = False) -> list[dict]:
    """Each patient piece's volume, cells, porosity and bodies, the largest piece first.

    Parameters
    ----------
    piece_labels : int ndarray
        From :func:`label_pieces`.
    count : int
    solid : bool ndarray, same shape
        The scaffold's solid (after any fragment removal).
    grid : Grid
    seeds : (n, 3) float ndarray, mm
        The seeds of the cells in the scaffold (``cells_in_scaffold``: their seed lies in the patient).
    main_bodies_only : bool
        The patient is one piece and the solid holds only its main body
        (:func:`remove_fragments_by_piece` ran; filling sealed voids next to that body keeps it
        one): one body wherever there is solid, known without labelling the solid again.

    Returns
    -------
    list of dict
        ``volume_mm3`` (voxel count), ``cells``, ``porosity_voxel``, ``bodies`` (6-connected
        solid pieces in it), ``lo_mm``/``hi_mm`` (bounds of its voxel centres).
    """
    from scipy import ndimage

    voxels = np.bincount(piece_labels.ravel(), minlength=count + 1)
    solid_voxels = np.bincount(piece_labels[solid], minlength=count + 1)
    cells = np.bincount(seed_pieces(piece_labels, grid, seeds), minlength=count + 1)
    if main_bodies_only:
        bodies = (solid_voxels > 0).astype(np.int64)
    else:
        labels, n_solid = ndimage.label(solid)
        bodies = np.bincount(solid_piece(labels, piece_labels, n_solid)[1:], minlength=count + 1)
        del labels
    bounds = ndimage.find_objects(piece_labels)
    rows = []
    for i in range(1, count + 1):
        box = bounds[i - 1]
        lo = grid.indices_to_points(np.array([[s.start for s in box]]))[0]
        hi = grid.indices_to_points(np.array([[s.stop - 1 for s in box]]))[0]
        rows.append({"piece": i, "volume_mm3": float(voxels[i] * grid.voxel_volume), "cells": int(cells[i]),
                     "porosity_voxel": float(1.0 - solid_voxels[i] / voxels[i]), "bodies": int(bodies[i]),
                     "lo_mm": [round(float(v), 4) for v in lo], "hi_mm": [round(float(v), 4) for v in hi]})
    rows.sort(key=lambda r: (-r["volume_mm3"], r["piece"]))
    return rows


def seed_pieces(piece_labels: np.ndarray, grid, seeds: np.ndarray) -> np.ndarray:
    """The patient piece of each seed: that of its nearest voxel, else that of the first of the 8
    voxels around it inside the patient (a seed that the trilinear sample of the patient's distance
    puts inside has one of them inside).

    Returns
    -------
    (n,) int64 ndarray
        0 for a seed with no voxel of the patient around it.
    """
    shape = np.asarray(piece_labels.shape) - 1
    p = (np.asarray(seeds, np.float64) - np.asarray(grid.origin)) / grid.spacing
    near = np.clip(np.rint(p).astype(np.int64), 0, shape)
    out = piece_labels[near[:, 0], near[:, 1], near[:, 2]].astype(np.int64)
    base = np.floor(p).astype(np.int64)
    for corner in np.ndindex(2, 2, 2):
        c = np.clip(base + np.asarray(corner), 0, shape)
        out = np.where(out > 0, out, piece_labels[c[:, 0], c[:, 1], c[:, 2]])
    return out


def small_pieces_warning(rows: list[dict], pore_volume: float, pore_size: float) -> str | None:
    """A plain-words warning for the patient pieces too small to hold one pore, or None.

    Parameters
    ----------
    rows : list of dict
        From :func:`piece_table`.
    pore_volume : float, mm³
        The volume of one pore (a sphere of the pore size).
    pore_size : float, mm
    """
    small = [r for r in rows if r["volume_mm3"] < pore_volume]
    if not small:
        return None
    total = sum(r["volume_mm3"] for r in small)
    first = small[0]
    where = ", ".join(f"{a}" for a in np.round(np.add(first["lo_mm"], first["hi_mm"]) / 2, 2).tolist())
    return (f"{len(small)} of the patient's {len(rows)} pieces ({total:.4g} mm3 in all; the largest of them "
            f"{first['volume_mm3']:.4g} mm3 near {where} mm) are smaller than one {pore_size:.3g} mm pore "
            f"({pore_volume:.4g} mm3): they cannot hold a pore, so their scaffold is a solid speck or nothing; "
            "use smaller pores, or remove such specks from the patient (e.g. a higher --threshold)")
