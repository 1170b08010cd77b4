"""The patient's pieces: fragment removal and the report, piece by piece.

A patient may come in several pieces (two vertebrae in one clip, the fragments of a
broken bone, the sides of an osteotomy gap). Each piece gets its own scaffold: a solid
piece of the scaffold is debris only when it is not the main body of the patient piece
it lies in, never because another patient piece holds a larger body.

Pieces are 6-connected sets of voxels inside the patient (``s_P < 0``), as the
scaffold's solid pieces are (:func:`~implicit_scaffold.fields.field.remove_fragments`). Since the scaffold's
solid lies inside the patient, every solid piece lies in exactly one patient piece.
"""
from __future__ import annotations

import numba as nb
import numpy as np

#: pieces listed one by one in the report (the largest first); the rest are summed up
REPORT_PIECES = 20


def label_pieces(inside: np.ndarray, connectivity: int = 6) -> tuple[np.ndarray, int]:
    """The 6-connected pieces of a mask (the patient's, the solid's, the void's).

    Parameters
    ----------
    inside : bool ndarray, 2-D or 3-D
        The voxels that belong to some piece.
    connectivity : 6 or 26
        26 joins voxels across edges and corners too (3-D only; ``scipy.ndimage.label``
        with a 3x3x3 structure).

    Returns
    -------
    labels : int32 ndarray of the mask's shape
        0 outside, 1..count for the pieces, numbered in C order of their first voxel:
        ``scipy.ndimage.label``'s labels, by connected-components-3d (cc3d), 3-4x faster.
    count : int
    """
    import cc3d

    mask = np.ascontiguousarray(inside, dtype=bool)  # cc3d numbers in memory order: C order
    if mask.size == 0 or not mask.any():
        return np.zeros(mask.shape, np.int32), 0
    labels, count = cc3d.connected_components(mask, connectivity=4 if mask.ndim == 2 else connectivity,
                                              return_N=True,
                                              out_dtype=np.uint32)
    return labels.view(np.int32), int(count)


@nb.njit(cache=True, nogil=True, boundscheck=False)
def _count_labels(flat, n):  # pragma: no cover - compiled
    # by runs of one label: a label grid is mostly long runs along z, and one add per run
    # spares the store-to-load chain of adding 1 to the same count voxel after voxel (2.8x)
    out = np.zeros(n + 1, np.int64)
    if flat.size == 0:
        return out
    current, run = flat[0], 0
    for x in flat:
        if x == current:
            run += 1
        else:
            out[current] += run
            current, run = x, 1
    out[current] += run
    return out


@nb.njit(cache=True, nogil=True, boundscheck=False)
def _count_labels_where(flat, where, n):  # pragma: no cover - compiled
    out = np.zeros(n + 1, np.int64)
    for i in range(flat.size):
        out[flat[i]] += where[i]  # no branch: the mask is read, not tested
    return out


@nb.njit(cache=True, nogil=True, boundscheck=False)
def _count_labels_first(flat, n):  # pragma: no cover - compiled
    # _count_labels, and where each label's run first starts: its first voxel in C order
    out = np.zeros(n + 1, np.int64)
    first = np.full(n + 1, -1, np.int64)
    if flat.size == 0:
        return out, first
    current, run, start = flat[0], 0, 0
    for i in range(flat.size):
        x = flat[i]
        if x == current:
            run += 1
        else:
            out[current] += run
            if first[current] < 0:
                first[current] = start
            current, run, start = x, 1, i
    out[current] += run
    if first[current] < 0:
        first[current] = start
    return out, first


def label_sizes_first(labels: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`label_sizes` and each label's first voxel (its flat index in C order; -1 for a
    label absent), ``(count + 1,)`` int64 each, in the same one pass.

    The first voxel seeds :func:`flood_paint`, which repaints a piece without labelling the
    grid again.
    """
    return _count_labels_first(np.ascontiguousarray(labels).reshape(-1), int(count))


@nb.njit(cache=True, nogil=True, inline="always")
def face_neighbour(q, t, i, j, k, nx, ny, nz):  # pragma: no cover - compiled
    """The flat index of voxel `q` (indices ``i, j, k``)'s face neighbour `t` (0 to 5: -x, +x, -y,
    +y, -z, +z) in a C-ordered ``(nx, ny, nz)`` grid; -1 beyond the grid."""
    if t == 0:
        return q - ny * nz if i > 0 else -1
    if t == 1:
        return q + ny * nz if i < nx - 1 else -1
    if t == 2:
        return q - nz if j > 0 else -1
    if t == 3:
        return q + nz if j < ny - 1 else -1
    if t == 4:
        return q - 1 if k > 0 else -1
    return q + 1 if k < nz - 1 else -1


@nb.njit(cache=True, nogil=True, boundscheck=False)
def _flood(field, seeds, value, below):  # pragma: no cover - compiled
    nx, ny, nz = field.shape
    flat = field.reshape(-1)
    plane = ny * nz
    stack = np.empty(4096, np.int64)
    n = 0
    for seed in seeds:
        f = flat[seed]
        if not ((f < 0) if below else (f >= 0)):
            continue
        flat[seed] = value
        n += 1
        stack[0] = seed
        top = 1
        while top > 0:
            top -= 1
            i = stack[top]
            x, y, z = i // plane, (i // nz) % ny, i % nz
            for k in range(6):
                j = face_neighbour(i, k, x, y, z, nx, ny, nz)
                if j < 0:
                    continue
                f = flat[j]
                if (f < 0) if below else (f >= 0):
                    flat[j] = value
                    n += 1
                    if top == stack.size:
                        grown = np.empty(2 * stack.size, np.int64)
                        grown[:top] = stack
                        stack = grown
                    stack[top] = j
                    top += 1
    return n


def flood_paint(field: np.ndarray, seeds: np.ndarray, value: float, *, below: bool) -> int:
    """Write `value` into the 6-connected pieces of ``field < 0`` (`below`) or ``field >= 0``
    that hold the voxels `seeds` (flat indices in C order), in place; returns the voxels written.

    Each piece is :func:`label_pieces`' piece of the seed, painted without labelling the grid:
    `value` must lie on the other side of 0 (the painted voxels then leave the mask, which is
    what marks them visited).

    Parameters
    ----------
    field : float32 C-contiguous ndarray (3-D), mm
    seeds : int ndarray
    value : float, mm
    below : bool
    """
    if field.ndim != 3 or field.dtype != np.float32 or not field.flags.c_contiguous:
        raise ValueError("flood_paint takes a C-contiguous 3-D float32 field")
    if (np.float32(value) < 0) == bool(below) or np.isnan(value):
        raise ValueError(f"the value {value} would stay in the mask it paints")
    return int(_flood(field, np.ascontiguousarray(seeds, np.int64), np.float32(value), bool(below)))


def label_sizes(labels: np.ndarray, count: int, where: np.ndarray | None = None) -> np.ndarray:
    """Voxels per label, ``(count + 1,)`` int64 (label 0 first): ``np.bincount(labels.ravel(),
    minlength=count + 1)``, or of the voxels of `where` alone, in one pass without the 8-byte
    copy of the labels that bincount makes (9x faster on a slab of 50 M voxels).

    Parameters
    ----------
    labels : int ndarray
        Labels 0..count, as :func:`label_pieces` gives them.
    count : int
    where : bool ndarray of the labels' shape, optional
    """
    flat = np.ascontiguousarray(labels).reshape(-1)
    if where is None:
        return _count_labels(flat, int(count))
    return _count_labels_where(flat, np.ascontiguousarray(where, np.bool_).reshape(-1).view(np.uint8), int(count))


@nb.njit(cache=True, nogil=True, boundscheck=False)
def _paint(flat_labels, table, flat_field, value):  # pragma: no cover - compiled
    n = 0
    for i in range(flat_labels.size):
        if table[flat_labels[i]]:
            flat_field[i] = value
            n += 1
    return n


def paint_labels(labels: np.ndarray, table: np.ndarray, field: np.ndarray, value: float) -> int:
    """``field[table[labels]] = value`` in one pass, without the boolean mask of the grid; returns
    how many voxels were written.

    Parameters
    ----------
    labels : int32 ndarray
        Labels 0..count (:func:`label_pieces`).
    table : (count + 1,) bool ndarray
        The labels to paint.
    field : float32 ndarray of the labels' shape, mm
        Written in place.
    value : float, mm
    """
    table = np.ascontiguousarray(table, np.bool_)
    if labels.shape != field.shape:
        raise ValueError(f"labels of shape {labels.shape} for a field of {field.shape}")
    if not (field.flags.c_contiguous and labels.flags.c_contiguous and field.dtype == np.float32
            and labels.dtype == np.int32):
        drop = table[labels]
        field[drop] = value
        return int(np.count_nonzero(drop))
    return int(_paint(labels.reshape(-1), table, field.reshape(-1), np.float32(value)))


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
        label met first in C order is kept, as :func:`~implicit_scaffold.fields.field.remove_fragments` does.
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
    labels, count = label_pieces(field < 0)
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
        labels, n_solid = label_pieces(solid)
        bodies = np.bincount(solid_piece(labels, piece_labels, n_solid)[1:], minlength=count + 1)
        del labels
    if count == 1:  # one piece (every primitive): its bounds from the mask's three projections
        inside = piece_labels > 0
        lo, hi = np.zeros((1, 3), np.int64), np.zeros((1, 3), np.int64)
        for a in range(3):
            on = np.flatnonzero(inside.any(axis=tuple(b for b in range(3) if b != a)))
            lo[0, a], hi[0, a] = on[0], on[-1]
    else:
        bounds = ndimage.find_objects(piece_labels)
        lo = np.array([[s.start for s in box] for box in bounds], np.int64).reshape(-1, 3)
        hi = np.array([[s.stop - 1 for s in box] for box in bounds], np.int64).reshape(-1, 3)
    return _rows(voxels[1:], solid_voxels[1:], cells[1:], bodies[1:], lo, hi, grid)


def _rows(voxels, solid_voxels, cells, bodies, lo, hi, grid) -> list[dict]:
    """The table's rows from per-piece figures (piece i + 1 in row i; `lo`, `hi` voxel indices), largest first."""
    lo_mm, hi_mm = grid.indices_to_points(lo), grid.indices_to_points(hi)
    rows = []
    for i in range(len(voxels)):
        rows.append({"piece": i + 1, "volume_mm3": float(voxels[i] * grid.voxel_volume), "cells": int(cells[i]),
                     "porosity_voxel": float(1.0 - solid_voxels[i] / voxels[i]), "bodies": int(bodies[i]),
                     "lo_mm": [round(float(v), 4) for v in lo_mm[i]], "hi_mm": [round(float(v), 4) for v in hi_mm[i]]})
    rows.sort(key=lambda r: (-r["volume_mm3"], r["piece"]))
    return rows


def piece_table_by_slabs(field, patient, grid, seeds: np.ndarray, *, max_voxels: int,
                         main_bodies_only: bool = False, progress=None) -> list[dict]:
    """:func:`piece_table` of a field in slabs (on disk or in memory), in one pass over them.

    The patient's pieces and the solid's are joined across slab faces
    (:class:`~implicit_scaffold.run.tiles.SlabComponents`); a piece's number is that of its
    first voxel in C order, as whole-grid labelling gives it, so the rows are the same.

    Parameters
    ----------
    field, patient : objects with ``read(x0, x1)`` (a FieldFile or ArraySlabs), mm
        The scaffold's and the patient's signed distances.
    grid : Grid
    seeds : (n, 3) float ndarray, mm
    max_voxels : int
        Voxels a slab may hold.
    main_bodies_only : bool
        As in :func:`piece_table` (the solid is not labelled).
    """
    from scipy import ndimage

    from .tiles import SlabComponents, plan_slabs

    slabs = plan_slabs(grid.shape, max_voxels=max_voxels, halo=0)
    probes = _seed_probes(grid, seeds)  # (9, n, 3): the voxels seed_pieces reads
    flat = probes.reshape(-1, 3)
    probe_local = np.zeros(len(flat), np.int64)
    probe_slab = np.searchsorted([sl.x1 for sl in slabs], flat[:, 0], side="right")
    parts, solids = SlabComponents(), None if main_bodies_only else SlabComponents()
    los, his, solid_maps = [], [], []
    for i, slab in enumerate(slabs):
        solid = field.read(slab.x0, slab.x1) < 0
        labels = parts.add(patient.read(slab.x0, slab.x1) < 0, tally=solid)
        boxes = ndimage.find_objects(labels)
        los.append(np.array([[b[0].start + slab.x0, b[1].start, b[2].start] for b in boxes], np.int64).reshape(-1, 3))
        his.append(np.array([[b[0].stop - 1 + slab.x0, b[1].stop - 1, b[2].stop - 1] for b in boxes],
                            np.int64).reshape(-1, 3))
        here = np.flatnonzero(probe_slab == i)
        probe_local[here] = labels[flat[here, 0] - slab.x0, flat[here, 1], flat[here, 2]]
        if solids is not None:
            solid_labels = solids.add(solid)
            piece_of = np.zeros(int(solid_labels.max(initial=0)) + 1, np.int64)
            piece_of[solid_labels[solid]] = labels[solid]
            solid_maps.append(piece_of)
            del solid_labels
        del solid, labels
        if progress is not None:
            progress(i + 1, len(slabs))
    parts.finish()
    sizes = parts.sizes
    roots = np.flatnonzero(sizes > 0)  # in C order of their first voxel: piece 1, 2, ...
    number = np.zeros(len(sizes) + 1, np.int64)  # root + 1 -> piece number (0 for none)
    number[roots + 1] = np.arange(1, len(roots) + 1)
    count = len(roots)
    all_roots = parts.roots_of_all()
    lo = np.full((count, 3), np.iinfo(np.int64).max, np.int64)
    hi = np.full((count, 3), -1, np.int64)
    piece_of_label = number[all_roots + 1] - 1
    np.minimum.at(lo, piece_of_label, np.concatenate(los))
    np.maximum.at(hi, piece_of_label, np.concatenate(his))
    probe_piece = np.zeros(len(flat), np.int64)
    for i in range(len(slabs)):
        here = np.flatnonzero(probe_slab == i)
        probe_piece[here] = number[parts.roots_of(i, probe_local[here]) + 1]
    probe_piece = probe_piece.reshape(probes.shape[:2])
    out = probe_piece[0]
    for corner in probe_piece[1:]:
        out = np.where(out > 0, out, corner)
    cells = np.bincount(out, minlength=count + 1)[1:]
    solid_voxels = parts.tally_by_root()[roots]
    if solids is None:
        bodies = (solid_voxels > 0).astype(np.int64)
    else:
        solids.finish()
        group = np.zeros(solids.labels, np.int64)
        for i, piece_of in enumerate(solid_maps):
            group[solids.roots_of(i, np.arange(1, len(piece_of)))] = number[parts.roots_of(i, piece_of[1:]) + 1]
        solid_roots = np.flatnonzero(solids.sizes > 0)
        bodies = np.bincount(group[solid_roots], minlength=count + 1)[1:]
    return _rows(sizes[roots], solid_voxels, cells, bodies, lo, hi, grid)


def one_piece_table(voxels: int, solid_voxels: int, cells: int, bodies: int, box, grid) -> list[dict]:
    """:func:`piece_table` of a patient known to be one piece (a primitive), from counts a run
    has made already: its voxels and solid voxels, its cells (every seed the patient's
    trilinear distance puts inside has a patient voxel among the 8 around it, so all count),
    its solid bodies and the bounds ``box`` (voxel indices, inclusive) of its voxels."""
    lo, hi = (np.asarray(b, np.int64).reshape(1, 3) for b in box)
    return _rows(np.array([voxels]), np.array([solid_voxels]), np.array([cells]), np.array([bodies]), lo, hi, grid)


def seeds_in_one_piece(patient, grid, seeds: np.ndarray) -> int:
    """The cells of a patient in one piece, as :func:`piece_table_by_slabs` counts them: the seeds
    with a patient voxel among those :func:`seed_pieces` reads (its piece is then the one).

    Parameters
    ----------
    patient : FieldFile or ArraySlabs
        The patient's signed distance, mm. From a file only those voxels are read, one by one
        (not mapped: the pages a map touches would count in the process's memory).
    grid : Grid
    seeds : (n, 3) float ndarray, mm
    """
    import os

    probes = _seed_probes(grid, seeds)  # (9, n, 3)
    if getattr(patient, "path", None) is None:
        values = patient.field[probes[..., 0], probes[..., 1], probes[..., 2]]
    else:
        flat = np.ravel_multi_index(tuple(probes.reshape(-1, 3).T), tuple(grid.shape))
        where, back = np.unique(flat, return_inverse=True)
        size = np.dtype(np.float32).itemsize
        with open(patient.path, "rb", buffering=0) as f:
            got = b"".join(os.pread(f.fileno(), size, int(i) * size) for i in where)
        values = np.frombuffer(got, np.float32)[back].reshape(probes.shape[:2])
    return int(np.count_nonzero((values < 0).any(axis=0)))


def _seed_probes(grid, seeds: np.ndarray) -> np.ndarray:
    """The voxels :func:`seed_pieces` reads for each seed: ``(9, n, 3)`` indices, its nearest first."""
    shape = np.asarray(grid.shape) - 1
    p = (np.asarray(seeds, np.float64).reshape(-1, 3) - np.asarray(grid.origin)) / grid.spacing
    base = np.floor(p).astype(np.int64)
    out = [np.clip(np.rint(p).astype(np.int64), 0, shape)]
    out += [np.clip(base + np.asarray(corner), 0, shape) for corner in np.ndindex(2, 2, 2)]
    return np.stack(out)


def seed_pieces(piece_labels: np.ndarray, grid, seeds: np.ndarray) -> np.ndarray:
    """The patient piece of each seed: that of its nearest voxel, else that of the first of the 8
    voxels around it inside the patient (a seed that the trilinear sample of the patient's distance
    puts inside has one of them inside).

    Returns
    -------
    (n,) int64 ndarray
        0 for a seed with no voxel of the patient around it.
    """
    probes = _seed_probes(grid, seeds)
    out = piece_labels[probes[0, :, 0], probes[0, :, 1], probes[0, :, 2]].astype(np.int64)
    for c in probes[1:]:
        out = np.where(out > 0, out, piece_labels[c[:, 0], c[:, 1], c[:, 2]])
    return out


def speck_remedy(source: dict | None, *, whole: bool = False) -> str:
    """How to remove specks from the patient, in the terms of what it was read from.

    Parameters
    ----------
    source : dict or None
        The report's ``patient_source`` (:func:`~implicit_scaffold.io.patient_io.load_patient`'s
        ``load_options``): ``file``, ``threshold``, ``label``; None for a patient given in code.
    whole : bool
        Every piece is a speck: the whole patient is smaller than one pore.
    """
    from pathlib import Path

    from ..io.patient_io import _kind

    file = (source or {}).get("file")
    if not file:
        return "remove such specks from the patient"
    if _kind(Path(file)) == "mesh":
        if whole:
            # a bone smaller than one pore is most often a mesh in metres or inches read as mm
            return "check the mesh's unit (--units m, --units in, ...)"
        # --threshold selects bone in a CT; a mesh's specks are its own small closed shells
        return "remove such specks from the mesh (e.g. MeshLab's Remove Isolated Pieces)"
    if source.get("threshold") is not None:
        return "remove such specks from the patient (e.g. a higher --threshold)"
    return "remove such specks from the segmentation (e.g. keep its largest connected components)"


def small_pieces_warning(rows: list[dict], pore_volume: float, pore_size: float, *,
                         source: dict | None = None) -> str | None:
    """A plain-words warning for the patient pieces too small to hold one pore, or None.

    Parameters
    ----------
    rows : list of dict
        From :func:`piece_table`.
    pore_volume : float, mm³
        The volume of one pore (a sphere of the pore size).
    pore_size : float, mm
    source : dict, optional
        The report's ``patient_source``: the advice fits it (:func:`speck_remedy`).
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
            f"use smaller pores, or {speck_remedy(source, whole=len(small) == len(rows))}")
