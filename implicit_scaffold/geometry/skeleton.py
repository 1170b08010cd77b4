"""Scaled skeleton, pores and channels (stage 4, paper §2.2).

For cell ``c`` (centroid ``g_c``) and its face ``f`` (area centroid ``g_f``):

- window rim ``f' = g_f + Sf (f - g_f)``: the face scaled about its own centroid,
  the same for both cells that share ``f``;
- pore cage face ``f'' = g_c + Sv (f - g_c)``: the face of the cell scaled about
  the cell's centroid;
- rails: vertex ``k`` of ``f''`` to vertex ``k`` of ``f'``.

The pore of ``c`` is the cell scaled by Sv; the channel through ``f`` is the
frustum between ``f''`` and ``f'``. Their union is the void; its boundary, the
lattice surface, is exactly the channels' side quads (the paper's quad meshes).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .cells import Cells, polygon_properties
from ..errors import ScaffoldError


def closed_form_porosity(sf: float, sv: float) -> float:
    """Porosity of the unsmoothed lattice, independent of the seeds.

    ``P0 = Sv³ + (1 - Sv)(Sf² + Sf·Sv + Sv²)``: the pores hold ``Sv³`` of every cell,
    and the channel of face ``f`` is a frustum of height ``(1 - Sv) h_f`` with end
    areas ``Sv² A_f`` and ``Sf² A_f``, while ``Σ_f A_f h_f = 3 V``.
    """
    return sv ** 3 + (1 - sv) * (sf ** 2 + sf * sv + sv ** 2)


def check_scale(name: str, value: float) -> float:
    """Validate a scale factor: a number strictly between 0 and 1."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ScaffoldError(f"--{name} must be a number between 0 and 1 (exclusive), got {value!r}") from None
    if not (0.0 < v < 1.0):
        raise ScaffoldError(f"--{name} must lie strictly between 0 and 1, got {v:g}; try --{name} 0.75")
    return v


@dataclass(frozen=True)
class Skeleton:
    """The scaled skeleton of a tessellation and the void's convex pieces.

    Attributes
    ----------
    cells : Cells
    sf, sv : float
    rims : (m, 3) float64 ndarray, mm
        Window rim vertices, laid out like ``cells.face_vertices``.
    cages : (m, 3) float64 ndarray, mm
        Pore cage vertices, laid out like ``cells.face_vertices``.
    quads : (nq, 4, 3) float64 ndarray, mm
        Side quads of the channels, ``(cage k, cage k+1, rim k+1, rim k)`` reordered
        so that they wind counter-clockwise about the normal pointing into the solid.
    quad_normals : (nq, 3) float64 ndarray
    quad_face : (nq,) int64 ndarray
        Face whose channel each quad bounds.
    piece_start : (npieces + 1,) int64 ndarray
        Pieces are the ``n`` pores, then one channel per face. Piece ``i`` is the
        intersection of half-spaces ``planes[piece_start[i]:piece_start[i + 1]]``.
    planes : (npl, 4) float64 ndarray
        ``(nx, ny, nz, d)``: inside where ``n · x <= d``.
    piece_lo, piece_hi : (npieces, 3) float64 ndarray, mm
        Bounding boxes of the pieces.
    """

    cells: Cells
    sf: float
    sv: float
    rims: np.ndarray
    cages: np.ndarray
    quads: np.ndarray
    quad_normals: np.ndarray
    quad_face: np.ndarray
    piece_start: np.ndarray
    planes: np.ndarray
    piece_lo: np.ndarray
    piece_hi: np.ndarray

    @property
    def porosity_closed_form(self) -> float:
        return closed_form_porosity(self.sf, self.sv)

    @property
    def rails(self) -> np.ndarray:
        """Rails, ``(m, 2, 3)`` mm: cage vertex to rim vertex."""
        return np.stack([self.cages, self.rims], axis=1)

    @property
    def n_pores(self) -> int:
        return self.cells.n


def _next_in_polygon(start: np.ndarray) -> np.ndarray:
    nxt = np.arange(start[-1]) + 1
    nxt[start[1:] - 1] = start[:-1]
    return nxt


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.cross`` of ``(m, 3)`` rows: the same products and differences, without its
    general axis handling (2.5x)."""
    out = np.empty(a.shape)
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def _channel_quads(cells: Cells, sf: float, sv: float):
    """Every face vertex's channel-side quad (cage, next cage, next rim, rim), before the
    skeleton orients it: ``(vert_face, rims, cages, quads, area vectors, areas)``, mm and mm²."""
    start = cells.face_start
    vert_face = np.repeat(np.arange(len(cells.face_cell)), np.diff(start))
    F = cells.face_vertices
    g_f = cells.face_centroids[vert_face]
    g_c = cells.centroids[cells.face_cell][vert_face]
    rims = g_f + sf * (F - g_f)
    cages = g_c + sv * (F - g_c)
    nxt = _next_in_polygon(start)
    quads = np.empty((len(F), 4, 3))
    quads[:, 0], quads[:, 1], quads[:, 2], quads[:, 3] = cages, cages[nxt], rims[nxt], rims
    area_vec = 0.5 * _cross(quads[:, 2] - quads[:, 0], quads[:, 3] - quads[:, 1])
    return vert_face, rims, cages, quads, area_vec, np.linalg.norm(area_vec, axis=1)


def _kept_quads(cells: Cells, area: np.ndarray) -> np.ndarray:
    """The quads the skeleton keeps: those not collapsed to a segment or a point."""
    return area > 1e-12 * float(np.max(cells.hi - cells.lo)) ** 2


def scaled_skeleton(cells: Cells, sf: float, sv: float) -> Skeleton:
    """Build rims, cages, rails, the channels' side quads and the void's pieces.

    Parameters
    ----------
    cells : Cells
    sf, sv : float
        Face and cell scale factors, each in (0, 1).

    Returns
    -------
    Skeleton
    """
    sf = check_scale("sf", sf)
    sv = check_scale("sv", sv)
    start = cells.face_start
    nf = len(cells.face_cell)
    vert_face, rims, cages, quads, area_vec, area = _channel_quads(cells, sf, sv)
    normals = area_vec / np.where(area > 0, area, 1)[:, None]
    # the channel's axis point at this quad's height: outward is away from it
    fn = cells.face_normals[vert_face]
    cage_c = cells.centroids[cells.face_cell] + sv * (cells.face_centroids - cells.centroids[cells.face_cell])
    axis_mid = 0.5 * (cage_c + cells.face_centroids)[vert_face]
    qc = quads.mean(axis=1)
    radial = (qc - axis_mid) - np.einsum("ij,ij->i", qc - axis_mid, fn)[:, None] * fn
    flip = np.einsum("ij,ij->i", normals, radial) < 0
    quads[flip] = quads[flip][:, ::-1]
    normals[flip] *= -1
    quad_face = vert_face.copy()
    good = _kept_quads(cells, area)
    if not good.all():
        quads, normals, quad_face = quads[good], normals[good], quad_face[good]

    # pieces: pores (one plane per cage face), then channels (cage end, rim end, sides)
    n = cells.n
    pore_planes = np.concatenate([cells.face_normals,
                                  np.einsum("ij,ij->i", cells.face_normals, cage_c)[:, None]], axis=1)
    order = np.argsort(cells.face_cell, kind="stable")
    pore_planes = pore_planes[order]
    pore_start = np.concatenate([[0], np.cumsum(np.bincount(cells.face_cell, minlength=n))])

    side = np.concatenate([normals, np.einsum("ij,ij->i", normals, quads[:, 0])[:, None]], axis=1)
    side_count = np.bincount(quad_face, minlength=nf)
    side_order = np.argsort(quad_face, kind="stable")
    side = side[side_order]
    side_start = np.concatenate([[0], np.cumsum(side_count)])
    cage_end = np.concatenate([-cells.face_normals,
                               -np.einsum("ij,ij->i", cells.face_normals, cage_c)[:, None]], axis=1)
    rim_end = np.concatenate([cells.face_normals,
                              np.einsum("ij,ij->i", cells.face_normals, cells.face_centroids)[:, None]], axis=1)
    ch_count = side_count + 2
    ch_start = np.concatenate([[0], np.cumsum(ch_count)])
    ch_planes = np.empty((ch_start[-1], 4))
    ch_planes[ch_start[:-1]] = cage_end
    ch_planes[ch_start[:-1] + 1] = rim_end
    pos = np.repeat(ch_start[:-1] + 2 - side_start[:-1], side_count) + np.arange(side_start[-1])
    ch_planes[pos] = side
    planes = np.concatenate([pore_planes, ch_planes])
    piece_start = np.concatenate([pore_start, pore_start[-1] + ch_start[1:]])

    # bounds of each face's vertices (a face's vertices are consecutive, three or more), then of
    # each cell's faces (grouped by a stable sort): minima and maxima, exact in any order
    first = start[:-1]
    cage_lo, cage_hi = np.minimum.reduceat(cages, first), np.maximum.reduceat(cages, first)
    ch_lo = np.minimum(cage_lo, np.minimum.reduceat(rims, first))
    ch_hi = np.maximum(cage_hi, np.maximum.reduceat(rims, first))
    pore_lo = np.full((n, 3), np.inf)
    pore_hi = np.full((n, 3), -np.inf)
    if nf:
        by_cell = cells.face_cell[order]
        group = np.flatnonzero(np.r_[True, by_cell[1:] != by_cell[:-1]])
        pore_lo[by_cell[group]] = np.minimum.reduceat(cage_lo[order], group)
        pore_hi[by_cell[group]] = np.maximum.reduceat(cage_hi[order], group)
    return Skeleton(cells=cells, sf=sf, sv=sv, rims=rims, cages=cages, quads=quads,
                    quad_normals=normals, quad_face=quad_face, piece_start=piece_start,
                    planes=planes, piece_lo=np.concatenate([pore_lo, ch_lo]),
                    piece_hi=np.concatenate([pore_hi, ch_hi]))


def piece_volumes(skeleton: Skeleton) -> tuple[np.ndarray, np.ndarray]:
    """Volumes of the pores and of the channels, from their boundary polygons.

    Divergence theorem over each piece's faces: the cage polygons for a pore; the
    cage end, rim end and side quads for a channel. Independent of the closed form.

    Returns
    -------
    pores : (n,) float64 ndarray, mm³
    channels : (nf,) float64 ndarray, mm³
    """
    cells = skeleton.cells
    start = cells.face_start
    n, nf = cells.n, len(cells.face_cell)
    cn, ca, cc = polygon_properties(skeleton.cages, start)
    flux = ca * np.einsum("ij,ij->i", cn, cc) / 3
    pores = np.bincount(cells.face_cell, weights=flux, minlength=n)
    rn, ra, rc = polygon_properties(skeleton.rims, start)
    q = skeleton.quads.reshape(-1, 3)
    qstart = np.arange(0, len(q) + 1, 4)
    qn, qa, qc = polygon_properties(q, qstart)
    side = np.bincount(skeleton.quad_face, weights=qa * np.einsum("ij,ij->i", qn, qc) / 3, minlength=nf)
    # the cage end faces into the pore (reversed), the rim end faces out
    channels = side - flux + ra * np.einsum("ij,ij->i", rn, rc) / 3
    return pores, channels


def voronoi_edges(cells: Cells, *, walls: bool = False) -> np.ndarray:
    """The unique edges of the tessellation, as ``(ne, 2, 3)`` float64 segments, mm.

    Edges that lie in a box wall (the box's own outline) are left out unless `walls`.
    """
    start = cells.face_start
    nxt = _next_in_polygon(start)
    a = cells.face_vertices
    b = cells.face_vertices[nxt]
    scale = float(np.max(cells.hi - cells.lo))
    tol = 1e-7 * scale
    ka = np.round(a / tol).astype(np.int64)
    kb = np.round(b / tol).astype(np.int64)
    # order each edge's ends lexicographically so both directions share a key
    diff = kb - ka
    first_nonzero = np.argmax(diff != 0, axis=1)
    less = diff[np.arange(len(diff)), first_nonzero] >= 0
    p = np.where(less[:, None], a, b)
    q = np.where(less[:, None], b, a)
    key = np.concatenate([np.where(less[:, None], ka, kb), np.where(less[:, None], kb, ka)], 1)
    # each distinct key's first row: a stable sort of the rows by all six columns (the rows
    # np.unique(axis=0, return_index=True) gives, without its sort of a structured view: 8x)
    order = np.lexsort(key.T[::-1])
    sk = key[order]
    first = np.ones(len(order), bool)
    first[1:] = np.any(sk[1:] != sk[:-1], axis=1)
    idx = np.sort(order[first])
    seg = np.stack([p[idx], q[idx]], axis=1)
    if not walls:
        on_wall = np.zeros(len(seg), bool)
        for axis in range(3):
            for bound in (cells.lo[axis], cells.hi[axis]):
                on_wall |= np.all(np.abs(seg[:, :, axis] - bound) < tol, axis=1)
        seg = seg[~on_wall]
    length = np.linalg.norm(seg[:, 1] - seg[:, 0], axis=1)
    return seg[length > tol]


#: bytes a Skeleton holds per channel-side quad (rims, cages, quads, normals, owning face)
#: and per plane of the void's pieces, and per piece (boxes)
SKELETON_BYTES_PER_QUAD = 24 + 24 + 96 + 24 + 8
SKELETON_BYTES_PER_PLANE = 32
SKELETON_BYTES_PER_PIECE = 56


def skeleton_bytes(cells: Cells) -> int:
    """Bytes :func:`scaled_skeleton` of `cells` holds (a close upper estimate, from the cells alone).

    A face of ``k`` vertices gives ``k`` quads, a channel of ``k + 2`` planes and a pore plane.
    """
    m, nf = len(cells.face_vertices), len(cells.face_cell)
    return (m * SKELETON_BYTES_PER_QUAD + (m + 3 * nf) * SKELETON_BYTES_PER_PLANE
            + (cells.n + nf) * SKELETON_BYTES_PER_PIECE)


class SkeletonSource:
    """The scaled skeleton of a tessellation, built on demand for the cells near a band of x.

    A tiled run holds the cells only; each slab builds the skeleton of the cells that can
    reach its voxels (:meth:`near`). The skeleton is built face by face, so a subset's
    quads and pieces are the whole skeleton's, value for value and in the same relative
    order, and a slab's field is bit for bit the one the whole skeleton gives.

    Parameters
    ----------
    cells : Cells
    sf, sv : float
    """

    #: a slab's skeleton peaks at about this many times what it holds once built (measured:
    #: 2.86 for 40,000 cells), and the lattice then holds it with its packed quads beside
    BUILD_FACTOR = 3.0

    def __init__(self, cells: Cells, sf: float, sv: float):
        self.cells = cells
        self.sf = check_scale("sf", sf)
        self.sv = check_scale("sv", sv)
        self.x_lo, self.x_hi = cells.x_extents()
        # each cell's skeleton bytes, summed over cells sorted by either end of their x extent
        counts = np.diff(cells.face_start)
        m = np.bincount(cells.face_cell, weights=counts, minlength=cells.n)
        nf = np.bincount(cells.face_cell, minlength=cells.n)
        per_cell = (m * SKELETON_BYTES_PER_QUAD + (m + 3 * nf) * SKELETON_BYTES_PER_PLANE
                    + (1 + nf) * SKELETON_BYTES_PER_PIECE)
        self._lo_sorted = np.sort(self.x_lo)
        self._hi_sorted = np.sort(self.x_hi)
        self._lo_sum = np.concatenate([[0.0], np.cumsum(per_cell[np.argsort(self.x_lo)])])
        self._hi_sum = np.concatenate([[0.0], np.cumsum(per_cell[np.argsort(self.x_hi)])])

    def bytes_near(self, x_lo: float, x_hi: float) -> int:
        """The peak bytes of :meth:`near` for this band and of the lattice that reads it
        (:data:`BUILD_FACTOR` times the skeleton's own bytes)."""
        # cells that start at or before x_hi, less those that end before x_lo (they start before too)
        started = self._lo_sum[np.searchsorted(self._lo_sorted, x_hi, side="right")]
        ended = self._hi_sum[np.searchsorted(self._hi_sorted, x_lo, side="left")]
        return int(self.BUILD_FACTOR * max(0.0, started - ended))

    def near(self, x_lo: float, x_hi: float) -> Skeleton:
        """The skeleton of the cells whose x extent meets ``[x_lo, x_hi]`` (mm); every quad and
        piece of the others lies outside that band."""
        return scaled_skeleton(self.cells.subset((self.x_hi >= x_lo) & (self.x_lo <= x_hi)), self.sf, self.sv)

    def quad_areas(self, chunk: int = 20000) -> np.ndarray:
        """Area of every quad of the whole skeleton, mm², in its order, built `chunk` cells at a time."""
        out = []
        n = self.cells.n
        for c0 in range(0, n, chunk):
            keep = np.zeros(n, bool)
            keep[c0:c0 + chunk] = True
            # only the quads: the areas quad_areas gives on the whole skeleton, bit for bit (an
            # orientation flip negates the cross product, a halving is exact), for a fifth of the work
            part = self.cells.subset(keep)
            area = _channel_quads(part, self.sf, self.sv)[5]
            out.append(area[_kept_quads(part, area)])
        return np.concatenate(out) if out else np.zeros(0)


def quad_areas(skeleton: Skeleton) -> np.ndarray:
    """Area of each channel-side quad, mm² (half the cross product of its diagonals)."""
    q = skeleton.quads
    return np.linalg.norm(np.cross(q[:, 2] - q[:, 0], q[:, 3] - q[:, 1]), axis=1) / 2
