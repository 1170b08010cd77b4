"""The print certificate: will this scaffold print, drain and let bone in, on this printer?

Checks a scaffold's voxels against a printer profile (``printers.json``, or inline
``custom:min_strut=0.3,...``), all lengths in mm:

- thinnest solid: local thickness (maximal spheres) of the solid, its minimum and 1st
  percentile, and the share of solid volume thinner than the profile's minimum strut;
- throats: the largest sphere that can travel from outside the scaffold to each place
  of the void through void only. With ``d`` the void's distance to the solid, that is
  the best path's narrowest ``d``: a morphological reconstruction by dilation of ``d``
  from the grid's faces (a max-min path). A sphere of radius ``r`` reaches the void
  within ``r`` of a centre whose path allows ``r``;
- sealed voids (void that no path joins to the outside) and floating solid (pieces
  besides the largest);
- overhangs: the share of downward-facing surface flatter than the profile's limit,
  for the build direction and for the best of the six axis directions;
- as built: porosity and throat again after the profile's typical deviation is applied
  as an offset of the solid (of a field, to first order in the deviation: :func:`grown_solid`).

Every check gives pass, warn or fail; the certificate's verdict is the worst of them.
:func:`certificate` measures a whole grid; :func:`certificate_by_slabs` the same figures
from fields read plane range by plane range (a tiled run's files), in bounded memory.
"""
from __future__ import annotations

import functools
import json
import math
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from ..errors import ScaffoldError
from ..run.pieces import face_neighbour, label_pieces, label_sizes

#: cells need windows of about 100 um to grow in (the issue's figure; Karageorgiou & Kaplan 2005)
INFILTRATION_MM = 0.1
#: the throat reported: the narrowest on the way to the pores that hold this share of the pore
#: volume (each pore weighted by its largest inscribed sphere)
THROAT_PORE_SHARE = 0.9
#: the overhang check's marching cubes runs on at most about this many voxels a side
OVERHANG_CELLS = 160
AXES = {"+x": (1, 0, 0), "-x": (-1, 0, 0), "+y": (0, 1, 0), "-y": (0, -1, 0), "+z": (0, 0, 1), "-z": (0, 0, -1)}
_KEYS = {"min_strut": "min_strut_mm", "min_throat": "min_throat_mm", "layer": "layer_mm",
         "overhang": "overhang_deg", "drain": "drain_mm", "deviation": "deviation_mm", "axis": "build_axis"}


@dataclass(frozen=True)
class PrinterProfile:
    """A printing process's limits (mm, degrees from the build plate)."""

    name: str
    process: str
    min_strut_mm: float
    min_throat_mm: float
    layer_mm: float
    overhang_deg: float
    build_axis: str
    drain_mm: float
    deviation_mm: float
    source: str


def profiles() -> dict[str, PrinterProfile]:
    """The shipped printer profiles, by name (``printers.json`` beside this module)."""
    table = json.loads((Path(__file__).with_name("printers.json")).read_text())
    return {name: PrinterProfile(name=name, **spec) for name, spec in table.items() if not name.startswith("_")}


def _check_profile(p: PrinterProfile) -> PrinterProfile:
    for key in ("min_strut_mm", "min_throat_mm", "layer_mm"):
        v = getattr(p, key)
        if not (math.isfinite(v) and v > 0):
            raise ScaffoldError(f"printer profile {p.name}: {key[:-3]} must be a positive length in mm, got {v!r}")
    for key in ("drain_mm",):
        if not (math.isfinite(getattr(p, key)) and getattr(p, key) >= 0):
            raise ScaffoldError(f"printer profile {p.name}: drain must be 0 or a positive length in mm")
    if not 0 < p.overhang_deg < 90:
        raise ScaffoldError(f"printer profile {p.name}: overhang must be an angle in (0, 90) degrees "
                            f"from the build plate, got {p.overhang_deg!r}")
    if p.build_axis not in AXES:
        raise ScaffoldError(f"printer profile {p.name}: axis must be one of {', '.join(AXES)}, got {p.build_axis!r}")
    return p


def printer_profile(text: str) -> PrinterProfile:
    """A profile by name, or ``custom:min_strut=0.3,min_throat=0.5,...`` (the rest as ``dlp-resin``).

    Raises
    ------
    ScaffoldError
        An unknown name or key, or a value out of range, in one line.
    """
    table = profiles()
    text = str(text).strip()
    if text.lower().startswith("custom:"):
        base = replace(table["dlp-resin"], name="custom", process="custom", source="given on the command line")
        changes = {}
        for item in filter(None, text[7:].split(",")):
            key, sep, value = item.partition("=")
            key = key.strip().replace("-", "_")
            if not sep or key not in _KEYS:
                raise ScaffoldError(f"--printer custom: takes key=value pairs with keys {', '.join(_KEYS)}; "
                                    f"got {item!r}")
            if key == "axis":
                changes[_KEYS[key]] = value.strip()
                continue
            try:
                changes[_KEYS[key]] = float(value)
            except ValueError:
                raise ScaffoldError(f"--printer custom: {key} must be a number, got {value!r}") from None
        if not changes:
            # custom: alone would be dlp-resin's limits under another name, which the user did not ask for
            raise ScaffoldError(f"--printer custom: needs at least one key=value (keys {', '.join(_KEYS)}), "
                                "e.g. custom:min_strut=0.3,min_throat=0.5; or name a printer: "
                                f"{', '.join(table)}")
        return _check_profile(replace(base, **changes))
    if text not in table:
        raise ScaffoldError(f"unknown printer {text!r}; use one of {', '.join(table)} "
                            "or custom:min_strut=MM,min_throat=MM,...")
    return _check_profile(table[text])


# ----------------------------------------------------------------------------- the measures


@functools.lru_cache(maxsize=None)
def _flood_kernels():
    """The compiled max-min floods (numba), built on first use and cached on disk:
    ``flood(d2, r2)`` from all six faces, ``flood_faces(d2, r2, low_x, high_x)`` from the
    y and z faces and only the x faces asked for (a slab's x faces inside the grid are not
    the grid's: their planes come from the neighbours, as part of the marker ``r2``)."""
    # helpers called by other kernels are module globals, not closure cells (see tiles._key_kernels)
    global _flood_spread, _flood_scan
    import numba as nb

    @nb.njit(cache=True, nogil=True, boundscheck=False)
    def _flood_spread(d2, r2, queue, qh, qt):  # pragma: no cover - compiled
        # the FIFO: each queued voxel raises its face neighbours that it can (min of its value
        # and theirs under d2), and queues those it raised; False if the ring overflowed
        nx, ny, nz = d2.shape
        fd = d2.ravel()
        fr = r2.ravel()
        sx = ny * nz
        size = queue.shape[0]
        while qh != qt:
            q = queue[qh]
            qh = qh + 1 if qh + 1 < size else 0
            k = q % nz
            j = (q // nz) % ny
            i = q // sx
            v = fr[q]
            for t in range(6):
                u = face_neighbour(q, t, i, j, k, nx, ny, nz)
                if u < 0:
                    continue
                if fr[u] < v and fr[u] < fd[u]:
                    fr[u] = min(v, fd[u])
                    queue[qt] = u
                    qt = qt + 1 if qt + 1 < size else 0
                    if qt == qh:  # more waiting than voxels: never seen; say so rather than loop
                        return False
        return True

    @nb.njit(cache=True, nogil=True, boundscheck=False)
    def settle_across(d2, r2, m):  # pragma: no cover - compiled
        # two halves flooded apart, [0, m) and [m, nx): the FIFO from both planes of the cut
        # carries what crosses it, and only that
        nx, ny, nz = d2.shape
        queue = np.empty(nx * ny * nz + 1, np.int64)
        qt = 0
        for i in (m - 1, m):
            for j in range(ny):
                for k in range(nz):
                    if d2[i, j, k] > 0:
                        queue[qt] = (i * ny + j) * nz + k
                        qt += 1
        return _flood_spread(d2, r2, queue, 0, qt)

    @nb.njit(cache=True, nogil=True, boundscheck=False)
    def _flood_scan(d2, r2, si, sj, sk, queue):  # pragma: no cover - compiled
        # one raster scan in the direction (si, sj, sk) (each +1 or -1): every void voxel takes
        # the largest of its three neighbours behind it in the scan, under its own d2. With a
        # queue, the voxels that could raise a neighbour behind them (the scan has passed it) are
        # queued, and their count returned: every other pair of neighbours is then settled
        nx, ny, nz = d2.shape
        i0, i1 = (0, nx) if si > 0 else (nx - 1, -1)
        j0, j1 = (0, ny) if sj > 0 else (ny - 1, -1)
        k0, k1 = (0, nz) if sk > 0 else (nz - 1, -1)
        seed = queue.shape[0] > 0
        qt = 0
        for i in range(i0, i1, si):
            pi = i - si
            bi = 0 <= pi < nx
            for j in range(j0, j1, sj):
                pj = j - sj
                bj = 0 <= pj < ny
                for k in range(k0, k1, sk):
                    m = d2[i, j, k]
                    if m == 0:
                        continue
                    pk = k - sk
                    bk = 0 <= pk < nz
                    v = r2[i, j, k]
                    if bi and r2[pi, j, k] > v:
                        v = r2[pi, j, k]
                    if bj and r2[i, pj, k] > v:
                        v = r2[i, pj, k]
                    if bk and r2[i, j, pk] > v:
                        v = r2[i, j, pk]
                    v = min(v, m)
                    r2[i, j, k] = v
                    if seed and ((bi and r2[pi, j, k] < v and r2[pi, j, k] < d2[pi, j, k])
                                 or (bj and r2[i, pj, k] < v and r2[i, pj, k] < d2[i, pj, k])
                                 or (bk and r2[i, j, pk] < v and r2[i, j, pk] < d2[i, j, pk])):
                        queue[qt] = (i * ny + j) * nz + k
                        qt += 1
        return qt

    @nb.njit(cache=True, nogil=True, boundscheck=False)
    def flood_faces(d2, r2, low_x, high_x):  # pragma: no cover - compiled
        # grey reconstruction by dilation of the marker r2 (raised to d2 on the seeded faces)
        # under d2, by Vincent's hybrid method: raster scans carry most values, then a FIFO
        # carries the rest (paths that turn back against every scan). 5x faster than a bucket
        # queue on a scaffold: the scans read memory in order. Four scans, the second pair with
        # x reversed against y and z, leave a FIFO a seventh of the first pair's alone (1.6 s
        # against 3.1 s on a 402^3 void, one thread). The marker must lie at or under d2; any
        # such marker works (the scans start from its values).
        nx, ny, nz = d2.shape
        for i in range(nx):
            for j in range(ny):
                for k in range(nz):
                    if ((i == 0 and low_x) or (i == nx - 1 and high_x)
                            or j == 0 or k == 0 or j == ny - 1 or k == nz - 1):
                        r2[i, j, k] = d2[i, j, k]
        none = np.empty(0, np.int64)
        _flood_scan(d2, r2, 1, 1, 1, none)
        _flood_scan(d2, r2, -1, -1, -1, none)
        _flood_scan(d2, r2, -1, 1, 1, none)
        queue = np.empty(nx * ny * nz + 1, np.int64)
        qt = _flood_scan(d2, r2, 1, -1, -1, queue)
        return _flood_spread(d2, r2, queue, 0, qt)

    def flood(d2, r2):
        # both halves along x at once, each from its own faces of the grid, then what crosses
        # the cut: the same fixpoint (the reconstruction is unique), on two cores
        from ..run.threads import count, over_rows

        nx = d2.shape[0]
        if count() < 2 or nx < 8:
            return flood_faces(d2, r2, True, True)
        ok = [True, True]

        def half(d2, r2, lo, hi):
            ok[lo > 0] = flood_faces(d2[lo:hi], r2[lo:hi], lo == 0, hi == nx)

        over_rows(half, nx, d2, r2, pieces=2)
        return ok[0] and ok[1] and settle_across(d2, r2, nx // 2)

    return flood, flood_faces


def _flood_kernel():
    """The compiled max-min flood from the grid's six faces (:func:`_flood_kernels`)."""
    return _flood_kernels()[0]


@functools.lru_cache(maxsize=None)
def _local_kernels():
    """Compiled neighbourhood tests (numba), built on first use and cached on disk, on every
    core (:func:`~implicit_scaffold.run.threads.by_rows`):
    ``peaks(d2, where, out)`` marks the voxels of `where` with ``d2 > 0`` that no voxel of their
    3x3x3 neighbourhood exceeds (the grid's faces repeated outward, as ``maximum_filter``'s
    ``mode="nearest"``); ``reach_planes(r2, c2, b, near)`` then ``reach_rows(r2, near, c2, b, out)``
    mark the voxels with ``r2 > 0`` less than ``sqrt(c2)`` from a voxel with ``r2 >= c2`` (inside
    the grid; ``b``, the window, at least the largest whole distance under it), by the squared
    distance within each plane (capped at ``c2``), then across the planes."""
    import numba as nb

    from ..run.threads import by_rows

    @nb.njit(cache=True, nogil=True, boundscheck=False)
    def peaks_rows(d2, where, out, lo, hi):  # pragma: no cover - compiled
        nx, ny, nz = d2.shape
        for i in range(lo, hi):
            for j in range(ny):
                for k in range(nz):
                    v = d2[i, j, k]
                    if v <= 0 or not where[i, j, k]:
                        continue
                    top = True
                    for a in range(max(i - 1, 0), min(i + 2, nx)):
                        for b in range(max(j - 1, 0), min(j + 2, ny)):
                            for c in range(max(k - 1, 0), min(k + 2, nz)):
                                if d2[a, b, c] > v:
                                    top = False
                                    break
                            if not top:
                                break
                        if not top:
                            break
                    out[i, j, k] = top

    @nb.njit(cache=True, nogil=True, boundscheck=False)
    def reach_planes(r2, c2, b, near, lo, hi):  # pragma: no cover - compiled
        # planes i in [lo, hi): near[i, j, k] = the least of c2 and the squared distance within
        # the plane i to a centre (r2 >= c2) no more than b voxels away along each axis: along k
        # by two sweeps of each row, then along j by a window of 2b + 1 rows added whole
        nx, ny, nz = r2.shape
        g = np.empty((ny, nz), np.int32)
        acc = np.empty(nz, np.int32)
        for i in range(lo, hi):
            for j in range(ny):
                last = -nz - b - 1
                for k in range(nz):
                    if r2[i, j, k] >= c2:
                        last = k
                    g[j, k] = k - last
                nxt = 2 * nz + b + 1
                for k in range(nz - 1, -1, -1):
                    if r2[i, j, k] >= c2:
                        nxt = k
                    a = min(g[j, k], nxt - k)
                    g[j, k] = a * a if a <= b else c2
            for j in range(ny):
                for k in range(nz):
                    acc[k] = g[j, k]
                for d in range(1, b + 1):
                    dd = d * d
                    if j - d >= 0:
                        for k in range(nz):
                            acc[k] = min(acc[k], g[j - d, k] + dd)
                    if j + d < ny:
                        for k in range(nz):
                            acc[k] = min(acc[k], g[j + d, k] + dd)
                for k in range(nz):
                    near[i, j, k] = min(acc[k], c2)

    @nb.njit(cache=True, nogil=True, boundscheck=False)
    def reach_rows(r2, near, c2, b, out, lo, hi):  # pragma: no cover - compiled
        # planes i in [lo, hi): out = void (r2 > 0) nearer than c2 to a centre, across the planes
        nx, ny, nz = r2.shape
        acc = np.empty(nz, np.int32)
        for i in range(lo, hi):
            for j in range(ny):
                for k in range(nz):
                    acc[k] = near[i, j, k]
                for d in range(1, b + 1):
                    dd = d * d
                    if i - d >= 0:
                        for k in range(nz):
                            acc[k] = min(acc[k], near[i - d, j, k] + dd)
                    if i + d < nx:
                        for k in range(nz):
                            acc[k] = min(acc[k], near[i + d, j, k] + dd)
                for k in range(nz):
                    out[i, j, k] = acc[k] < c2 and r2[i, j, k] > 0

    return by_rows(peaks_rows), by_rows(reach_planes), by_rows(reach_rows)


#: up to this radius (voxels) a sphere's reach is found by windows of 2 r + 1 rows along each axis
#: (about 4 r adds per voxel, in order in memory), beyond it by a distance transform of its centres
#: (a fixed cost, about 0.9 s on 402³ on two cores, which a window of 20 voxels costs too)
WINDOW_RHO = 20.0


def throat_radius(solid, voxel: float):
    """Squared void distance and the squared radius of the largest sphere that reaches each place.

    Parameters
    ----------
    solid : (nx, ny, nz) bool ndarray
        Beyond the array is free void (the outside of the scaffold).
    voxel : float, mm

    Returns
    -------
    d2 : (nx, ny, nz) int32 ndarray, voxels²
        Squared distance from each void voxel to the nearest solid voxel centre (0 in the solid).
    r2 : (nx, ny, nz) int32 ndarray, voxels²
        The largest squared radius of a sphere whose centre can move from outside the
        array to this voxel, face to face, through void voxels whose ``d2`` never falls
        below it: the best path's narrowest ``d2``. 0 in the solid and in sealed voids.
    """
    from .morphometry import _squared_edt

    # the outside counts as void: a sphere comes in from free space
    d2 = np.ascontiguousarray(_squared_edt(~np.asarray(solid, bool)))
    r2 = np.zeros_like(d2)
    if not _flood_kernel()(d2, r2):
        raise RuntimeError("the throat flood's queue overflowed")  # pragma: no cover
    return d2, r2


def reached_by(r2, diameter_mm: float, voxel: float) -> np.ndarray:
    """The void that a sphere of `diameter_mm` reaches from outside, as a bool mask.

    Its centre can be where ``r2`` allows its radius (to the voxels' boundaries, as the
    certificate's other lengths); it then holds the voxels nearer than that radius. A voxel
    held by a larger sphere is held by one of this size too (slid along towards it), so the
    allowed centres' reach (:func:`_reach`) answers for every sphere at least this large.
    """
    rho = 0.5 * (float(diameter_mm) / float(voxel) - 1.0)  # voxels, centre to voxel centre
    if rho <= 0:
        return r2 > 0
    return _reach(np.ascontiguousarray(r2), rho)


def _reach(r2, rho: float) -> np.ndarray:
    """Void (``r2 > 0``) nearer than `rho` voxels to a centre where ``r2 >= rho**2``: exact."""
    c2 = math.ceil(rho * rho)  # integer squared distances: d2 < rho^2 iff d2 < c2, r2 >= rho^2 iff r2 >= c2
    if r2.size == 0 or int(r2.max()) < c2:
        return np.zeros(r2.shape, bool)  # no centre
    if rho > WINDOW_RHO:
        from .morphometry import _squared_edt

        centres = r2 >= c2
        return (r2 > 0) & (_squared_edt(~centres) < c2)
    # a centre nearer than rho lies less than rho away along each axis: windows of b voxels hold it
    b = math.isqrt(c2 - 1)
    _, planes, rows = _local_kernels()
    near = np.empty(r2.shape, np.int16 if c2 + b * b < 2 ** 15 else np.int32)
    planes(r2, c2, b, near)
    out = np.empty(r2.shape, bool)
    rows(r2, near, c2, b, out)
    return out


def pore_throats(d2, r2, void_in, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """The throat of each pore (mm, a diameter) and the pore's weight.

    A pore's centre is a local maximum of the void's distance (the centre of its largest
    inscribed sphere); its throat is ``2 sqrt(r2) + 1`` voxels there (the largest sphere that
    can travel to it from outside, to the voxels' boundaries); its weight is that inscribed sphere's volume (``d2^1.5``), so that
    the crevices between struts, which are local maxima too, count for little.
    """
    centres = _pore_centres(d2, void_in)
    return voxel * (2.0 * np.sqrt(r2[centres].astype(np.float64)) + 1.0), d2[centres].astype(np.float64) ** 1.5


def _pore_centres(d2, void_in) -> np.ndarray:
    """Pore centres: void voxels of `void_in` where `d2` is a local maximum (3x3x3, the grid's
    faces repeated outward)."""
    out = np.zeros(d2.shape, bool)
    _local_kernels()[0](np.ascontiguousarray(d2), np.ascontiguousarray(void_in, bool), out)
    return out


def weighted_quantile(values, weights, q: float) -> float:
    """The `q` quantile of `values` with `weights` (the smallest value whose cumulative weight reaches q)."""
    order = np.argsort(values, kind="stable")
    cum = np.cumsum(np.asarray(weights, np.float64)[order])
    return float(np.asarray(values)[order][min(len(cum) - 1, int(np.searchsorted(cum, q * cum[-1])))])


def pieces(mask) -> tuple[int, np.ndarray]:
    """6-connected pieces of `mask`: count and the voxel count of each."""
    labels, n = label_pieces(mask)
    return int(n), label_sizes(labels, n)[1:]


def overhang_shares(field, grid, limit_deg: float, *, level: float = 0.0) -> dict:
    """Share of the downward-facing surface flatter than `limit_deg` for each of the six axis directions.

    The surface is the field's level set, measured by the co-area formula: every voxel
    within 1.5 voxels of it weighs ``δ(t)`` (``t = (f - level) / |∇f|``, its distance to the
    surface; ``δ`` a smooth delta)
    and faces the direction of ``∇f``. The grid's outer layer is left out: a part's faces on
    the grid's faces rest on the plate or open onto free space, and are no overhang.

    Parameters
    ----------
    field : (nx, ny, nz) float ndarray
        Negative in the solid (a signed distance, or a smoothed indicator).
    grid : Grid
    limit_deg : float
        The flattest overhang the process builds without support, in degrees from the plate.

    Returns
    -------
    dict
        ``{"+z": share, ...}``; a surface whose outward normal points down at an angle ``a``
        from straight down makes an angle ``a`` with the plate and needs support when ``a < limit``.
    """
    w, n = _surface_elements(np.asarray(field, np.float32) - np.float32(level), float(grid.spacing))
    return _overhang_sums(w, n, limit_deg)


def _surface_elements(f: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`overhang_shares`'s surface elements of ``f[1:-1, 1:-1, 1:-1]``: weights and unit normals.

    Every value is elementwise (central differences inside), so blocks of planes with one
    plane of halo on either side give the whole array's elements, in the same order.
    """
    gx, gy, gz = np.gradient(f, h)
    core = (slice(1, -1),) * 3
    f, gx, gy, gz = f[core], gx[core], gy[core], gz[core]
    norm = np.sqrt(gx * gx + gy * gy + gz * gz)
    eps = 1.5 * h
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.where(norm > 0, f / norm, np.inf)
    near = np.abs(t) < eps
    # t is a distance (|∇t| = 1 at the surface), so a delta in t integrates to the area
    w = (1.0 + np.cos(np.pi * t[near] / eps)) / (2.0 * eps)
    n = np.stack([gx[near], gy[near], gz[near]], 1) / norm[near][:, None]
    return w, n


def _overhang_sums(w: np.ndarray, n: np.ndarray, limit_deg: float) -> dict:
    """The shares of :func:`overhang_shares` from its surface elements (all of them, in C order)."""
    cos_limit = math.cos(math.radians(limit_deg))
    out = {}
    for name, axis in AXES.items():
        down = -(n @ np.asarray(axis, float))  # cos of the angle between the normal and straight down
        total = w[down > 1e-6].sum()
        out[name] = float(w[down > cos_limit].sum() / total) if total > 0 else 0.0
    return out


class ThroatTally:
    """Pores counted by the squared throat radius and the squared inscribed radius at their centres.

    A pore's throat is ``h (2 sqrt(r2) + 1)`` and its weight ``d2^1.5``, both functions of
    integers (voxels²), so integer counts per ``(r2, d2)`` hold everything the weighted
    quantiles read: tallies of slabs add up to the whole grid's exactly, and the quantiles
    are summed in one order (by throat, then weight) whatever the slabs.

    Parameters
    ----------
    voxel : float, mm
    """

    def __init__(self, voxel: float):
        self.voxel = float(voxel)
        self.keys = np.zeros(0, np.int64)    # r2 << 32 | d2, sorted
        self.counts = np.zeros(0, np.int64)

    def add(self, r2, d2) -> "ThroatTally":
        """Count pores with squared throat radii `r2` and squared inscribed radii `d2` (voxels², ints)."""
        r2 = np.asarray(r2, np.int64).ravel()
        if r2.size:
            keys = np.concatenate([self.keys, (r2 << 32) | np.asarray(d2, np.int64).ravel()])
            counts = np.concatenate([self.counts, np.ones(r2.size, np.int64)])
            self.keys, inverse = np.unique(keys, return_inverse=True)
            self.counts = np.zeros(len(self.keys), np.int64)
            np.add.at(self.counts, inverse.ravel(), counts)
        return self

    @property
    def pores(self) -> int:
        return int(self.counts.sum())

    def _table(self):
        throat = self.voxel * (2.0 * np.sqrt((self.keys >> 32).astype(np.float64)) + 1.0)
        weight = self.counts * (self.keys & 0xFFFFFFFF).astype(np.float64) ** 1.5
        return throat, weight

    def minimum(self) -> float | None:
        """The narrowest pore throat, mm (None without pores)."""
        return float(self._table()[0][0]) if self.keys.size else None

    def quantile(self, q: float) -> float | None:
        """The weighted `q` quantile of the throats, mm, as :func:`weighted_quantile` (None without pores)."""
        if not self.keys.size:
            return None
        throat, weight = self._table()
        cum = np.cumsum(weight)
        return float(throat[min(len(cum) - 1, int(np.searchsorted(cum, q * cum[-1])))])


def _thinnest(tally, min_strut: float) -> tuple[dict, float]:
    """Minimum and 1st percentile of the certificate's thickness map, and the share below `min_strut`,
    from a :class:`~implicit_scaffold.measure.morphometry.ThicknessTally` of :func:`~implicit_scaffold.measure.morphometry.local_thickness`'s map.

    The map's values are float32 ``2 h sqrt(v) + h`` (the voxel added in float32, as the
    certificate does), so the order statistics come from the counts per ``v``; the percentile
    interpolates as ``np.percentile`` does (linear, in float32). ``unresolved_share`` is the share
    of the solid at the map's floor (``v = 1``, 3 voxels), solid 1 to 3 voxels thick, where
    `min_strut` lies above one voxel and not above that floor: the voxels cannot tell whether it
    is thinner than `min_strut` (0 otherwise).
    """
    v = np.nonzero(tally.counts)[0]
    counts = tally.counts[v]
    h = tally.voxel
    values = np.float32(2.0 * h * np.sqrt(v.astype(np.float64))) + np.float32(h)
    n = int(counts.sum())
    cum = np.cumsum(counts)

    from ..run.tiles import percentile_1

    def order(*ranks):
        return [values[int(np.searchsorted(cum, k, side="right"))] for k in ranks]

    below = int(counts[values < min_strut].sum()) / n
    # the floor reading, 3 voxels (a sphere of one voxel's radius, plus the voxel), is what solid 1 or 2
    # voxels thick reads too (a plate of 1 voxel, a rod of 2): where 3 voxels would pass and 1 would
    # not, the voxels cannot tell whether that solid is thick enough (a 1 mm plate at 1 mm voxels read
    # 3 mm and passed a 2.5 mm minimum)
    unresolved = int(counts[v == 1].sum()) / n if h < min_strut <= values[v == 1].max(initial=0) else 0.0
    return {"min": float(values[0]), "p1": percentile_1(n, order), "unresolved_share": unresolved}, below


#: the labels of the certificate's section maps
SECTION_VOID, SECTION_SOLID, SECTION_THIN, SECTION_UNDRAINED, SECTION_SEALED, SECTION_FLOATING = range(6)
SECTION_LABELS = ("void", "solid", "solid thinner than the minimum strut", "void the drain does not reach",
                  "sealed void", "floating solid")


class Certificate(dict):
    """The certificate's keys (a dict, as the JSON report holds it) and its section maps.

    Attributes
    ----------
    sections : dict
        ``{(axis, index): (n1, n2) uint8 array}``: a plane through the middle, each voxel
        labelled by :data:`SECTION_LABELS` (a problem over what it lies in).
    """

    def __init__(self, keys: dict, sections: dict):
        super().__init__(keys)
        self.sections = sections


class _Clock:
    """Seconds of wall time from one part of the certificate's end to the next's. A part measured
    beside the others (the as-built check, from a signed distance) shows as the wait for it at its
    mark; its work falls in the parts it ran beside."""

    def __init__(self):
        import time

        self._now = time.perf_counter
        self._t = self._now()
        self.seconds = {}

    def mark(self, name: str) -> None:
        t = self._now()
        self.seconds[name] = round(t - self._t, 4)
        self._t = t


def _verdict(value, warn, fail, *, higher_is_worse=True) -> str:
    if value is None:
        return "pass"
    if higher_is_worse:
        return "fail" if value > fail else "warn" if value > warn else "pass"
    return "fail" if value < fail else "warn" if value < warn else "pass"


def certificate_memory():
    """What ``check`` holds for a scaffold read by :func:`~implicit_scaffold.measure.morphometry.read_scaffold`
    (a :class:`~implicit_scaffold.measure.morphometry.MeasureMemory`): a fixed part (numba's, the OpenCL
    runtime's), bytes a voxel of the certificate (thickness, distances, labels, the field), and bytes a
    triangle of a mesh's signed distance (its triangles' structures), held beside the read's. Bounds of the
    peaks ``/usr/bin/time`` measured (2026-12-07): sheet gyroids written as .npy fields of 160^3, 260^3 and
    400^3 voxels 416, 649 and 1,790 MiB (bounds 545, 956 and 2,373); the default cube's STL (5.2 M triangles) at
    0.08, 0.05 and 0.03 mm (2.0, 8.2 and 38 M voxels) 1,677, 1,782 and 2,086 MiB (its read's bound 2,088, 2,123
    and 2,289 beside the 100 held); the 5 mm cube's (692 k) at 0.05 and 0.025 mm 504 and 646 MiB (the read's
    bound 534, the certificate's 675)."""
    from .morphometry import MeasureMemory

    return MeasureMemory("the print check", 420 * 2**20, 32, 280)


def certificate(solid, voxel: float, profile: PrinterProfile, *, field=None, region=None, origin=(0.0, 0.0, 0.0),
                exact_distance: bool = False) -> dict:
    """The print certificate of a scaffold's voxels for `profile`.

    Parameters
    ----------
    solid : (nx, ny, nz) bool ndarray
        The scaffold's solid; everything beyond the array is outside.
    voxel : float, mm
    profile : PrinterProfile
    field : (nx, ny, nz) float ndarray, mm, optional
        The scaffold's signed distance (negative in the solid), for the surface normals of the
        overhang check and the as-built offset; by default a smoothed copy of `solid` and an
        offset by whole voxels.
    region : (nx, ny, nz) bool ndarray, optional
        Where the scaffold is (the patient): the void counted for porosity and drainage.
        By default the whole grid.
    origin : 3 floats, mm
    exact_distance : bool
        `field` is a true signed distance within the deviation of its surface (a mesh's
        point-triangle distances): the as-built solid is then ``field < deviation``, exactly.
        Otherwise (generate's blended field) it is the first-order offset of :func:`grown_solid`.

    Returns
    -------
    dict
        The keys of the issue: ``printer``, ``thinnest_mm``, ``below_min_strut_share``,
        ``throat_mm`` (the narrowest throat on the way from outside to the pores that hold 90 % of
        the pore volume), ``void_reached_by_drain_share``, ``void_reached_by_100um_share``,
        ``sealed_voids``, ``floating_solid``, ``overhang_share``, ``best_build_axis``,
        ``as_built``, ``verdict``, and what they were measured on.
    """
    from scipy import ndimage

    from ..run.grid import Grid
    from .morphometry import ThicknessTally, _check_volume, local_thickness

    solid, h, region = _check_volume(solid, voxel, region)
    if not solid.any():
        raise ScaffoldError("the scaffold holds no solid voxel; nothing to certify")
    if region is None:
        region = np.ones(solid.shape, bool)
    n_region = int(np.count_nonzero(region))
    void_in = region & ~solid
    if not void_in.any():
        raise ScaffoldError("the scaffold holds no void voxel; a solid block has no pores to certify")

    # lengths on the voxels' boundaries: a digitised phase ends half a voxel past its last voxel
    # centre on each side, where the maximal spheres (centred on voxel centres, reaching to the
    # nearest voxel centre outside) stop short; so a rod or hole of diameter D reads D within a voxel
    clock = _Clock()
    # sections through the middle, across (index 0) and along (index 1) the build axis: the
    # report's maps of where each problem lies
    planes = _section_planes(solid.shape, profile)
    maps = [np.where(np.take(solid, i, axis=a), SECTION_SOLID, SECTION_VOID).astype(np.uint8) for a, i in planes]

    # as built: the process builds the solid thicker (or thinner) by its typical deviation. From a
    # signed distance (or by shrinking) it needs nothing of the other checks, so it is measured
    # beside them: its kernels fill the time the others leave one core idle (NumPy's passes,
    # the pieces' labels, first touches of new memory), 1-1.5 s of a 402^3 grid's certificate
    sdf = None if field is None else np.asarray(field)
    beside = beside_pool = None
    if sdf is not None or profile.deviation_mm < 0:
        from concurrent.futures import ThreadPoolExecutor

        def grown_of():
            if sdf is not None and exact_distance:
                return sdf < profile.deviation_mm  # a true distance offsets by less than a voxel
            if sdf is not None:
                # a field by its own gradient (less than a voxel too), in blocks of planes
                return grown_solid(lambda lo, hi: sdf[lo:hi], sdf.shape, 0, sdf.shape[0], profile.deviation_mm, h)
            from .morphometry import _squared_edt

            return solid & ~(_squared_edt(solid) <= (profile.deviation_mm / h) ** 2)

        beside_pool = ThreadPoolExecutor(1, thread_name_prefix="as_built")
        beside = beside_pool.submit(lambda: _as_built(grown_of(), region, n_region, h, profile))

    thick = local_thickness(solid, h)
    # counted per sphere radius, as certificate_by_slabs counts its slabs: the same figures by construction
    thinnest, below = _thinnest(ThicknessTally(h).add(thick, solid), profile.min_strut_mm)
    for m, (a, i) in zip(maps, planes):
        # lengths to the voxels' boundaries, as the tally's: a voxel more than the spheres
        m[(np.take(thick, i, axis=a) + np.float32(h) < profile.min_strut_mm) & (m == SECTION_SOLID)] = SECTION_THIN
    del thick

    clock.mark("thickness")
    d2, r2 = throat_radius(solid, h)
    pores = ThroatTally(h)
    centres = _pore_centres(d2, void_in)
    pores.add(r2[centres], d2[centres])
    del centres
    throat = pores.quantile(1 - THROAT_PORE_SHARE) if pores.pores else 0.0
    n_void = np.count_nonzero(void_in)
    drain = None
    if profile.drain_mm > 0:
        drained = reached_by(r2, profile.drain_mm, h)
        drain = float(np.count_nonzero(drained & void_in) / n_void)
        for m, (a, i) in zip(maps, planes):
            m[~np.take(drained, i, axis=a) & np.take(void_in, i, axis=a)] = SECTION_UNDRAINED
        del drained
    cells = float(np.count_nonzero(reached_by(r2, INFILTRATION_MM, h) & void_in) / n_void)
    clock.mark("throats")

    sealed = void_in & (r2 == 0)
    sealed_n, sealed_sizes = pieces(sealed)
    solid_labels, solid_n = label_pieces(solid)
    solid_sizes = label_sizes(solid_labels, solid_n)[1:]
    floating = np.sort(solid_sizes)[:-1] if solid_n > 1 else np.zeros(0, np.int64)
    for m, (a, i) in zip(maps, planes):
        m[np.take(sealed, i, axis=a)] = SECTION_SEALED
        if solid_n > 1:
            lab = np.take(solid_labels, i, axis=a)
            m[(lab > 0) & (lab != 1 + int(np.argmax(solid_sizes)))] = SECTION_FLOATING
    del sealed, solid_labels

    # the surface's normals, on at most ~OVERHANG_CELLS voxels a side: their distribution is
    # what counts, and a coarser grid keeps this check's marching cubes cheap
    f = max(1, math.ceil(max(solid.shape) / OVERHANG_CELLS))
    if field is None:
        # a smoothed indicator: normals of the voxel staircase would read as flat faces
        field = ndimage.gaussian_filter(np.where(solid, -1.0, 1.0).astype(np.float32), max(1.0, 0.5 * f))
    coarse = np.ascontiguousarray(np.asarray(field)[::f, ::f, ::f])
    shares = overhang_shares(coarse, Grid(tuple(float(o) for o in origin), h * f, coarse.shape),
                             profile.overhang_deg)
    best_axis = min(shares, key=lambda k: (shares[k], k))
    clock.mark("pieces and overhangs")

    if beside is not None:
        as_built = beside.result()
        beside_pool.shutdown()
    else:
        # the solid grown by whole voxels of the void's distance
        as_built = _as_built(solid | ((d2 > 0) & (d2 <= (profile.deviation_mm / h) ** 2)), region, n_region, h,
                             profile)
    del d2, r2

    clock.mark("as built")
    return _assemble(profile, h, solid.shape, n_region, int(n_void), thinnest, below, throat, pores, drain, cells,
                     (sealed_n, int(sealed_sizes.sum())), (int(len(floating)), int(floating.sum())), shares,
                     best_axis, as_built, clock, {(a, i): m for m, (a, i) in zip(maps, planes)})


def _as_built(grown, region, n_region: int, h: float, profile: PrinterProfile) -> dict:
    """The certificate's ``as_built``: porosity, throat and drain reach of the `grown` solid."""
    void_b = region & ~grown
    as_built = {"deviation_mm": profile.deviation_mm, "porosity": float(np.count_nonzero(void_b)) / n_region,
                "throat_mm": 0.0, "void_reached_by_drain_share": None}
    if void_b.any():
        d2b, r2b = throat_radius(grown, h)
        del grown
        centres = _pore_centres(d2b, void_b)
        tb = ThroatTally(h).add(r2b[centres], d2b[centres])
        del centres, d2b
        as_built["throat_mm"] = tb.quantile(1 - THROAT_PORE_SHARE) if tb.pores else 0.0
        if profile.drain_mm > 0:
            reached = reached_by(r2b, profile.drain_mm, h) & void_b
            as_built["void_reached_by_drain_share"] = float(np.count_nonzero(reached) / np.count_nonzero(void_b))
    return as_built


#: the as-built offset works on blocks of about this many voxels: its gradient's temporaries (a few
#: arrays of the field's type) stay this small whatever the grid or the slab
OFFSET_BLOCK_VOXELS = 1 << 21


def grown_solid(read, shape, x0: int, x1: int, deviation_mm: float, voxel: float) -> np.ndarray:
    """The solid of planes ``[x0, x1)`` of a field offset outward by `deviation_mm`: ``φ < δ |∇φ|``.

    The threshold ``φ < δ`` moves a field's zero set by ``δ / |∇φ|``: right for a signed distance
    (``|∇φ| = 1``), not for generate's blended field (within a voxel of a 4 mm box's surface its central
    ``|∇φ|`` has median 0.70 and 10th percentile 0.36: 0.05 mm moved it about 0.07 mm, and the as-built
    porosity read 0.5132 where the exact offset of the run's mesh gives 0.5598). To first order in δ
    the surface offset by δ along its normal is ``φ = δ |∇φ|``, for any field whose zero set is the
    surface.

    ``|∇φ|`` is Godunov's upwind gradient of a front moving outward (Osher & Fedkiw, *Level Set
    Methods and Dynamic Implicit Surfaces*, 2003, ch. 6, motion in the normal direction; for δ < 0
    the front moves inward and the differences look the other way): along each axis the larger of
    the differences towards a lower neighbour, none at a valley. Central differences vanish on the
    void's ridges (the middle of a gap, where the front arrives from both sides), so gaps narrower
    than 2δ stayed open: the 4 mm box read porosity 0.5640 and throat 0.193 mm by central
    differences, 0.5574 and 0.275 mm upwind, 0.5598 and 0.275 mm exact. First order only: at
    δ = 0.1 mm, two voxels, the same box reads 0.3254 and 0.193 mm, exact 0.3431 and 0.225 mm. A true
    distance needs none of this (``φ < δ`` is exact; :func:`certificate`'s ``exact_distance``).

    Each plane reads one plane on either side: blocks and slabs read that halo (none beyond the
    grid's faces, where that side's difference is left out), so every plane's value is the whole
    grid's, bit for bit, however the planes are cut.

    Parameters
    ----------
    read : callable(lo, hi) -> (hi - lo, ny, nz) float ndarray, mm
        Planes of the field, negative in the solid (an array's slice, or a FieldFile's ``read``).
    shape : (3,) ints
        The whole grid's voxels.
    x0, x1 : int
        The planes wanted.
    deviation_mm : float, mm
        How much thicker the solid is built (negative: thinner).
    voxel : float, mm

    Returns
    -------
    (x1 - x0, ny, nz) bool ndarray
        True where the offset field is solid.
    """
    nx, ny, nz = (int(n) for n in shape)
    scale = float(deviation_mm) / float(voxel)  # δ |∇φ| = (δ / h) sqrt(sum of squared differences)
    out = np.empty((x1 - x0, ny, nz), bool)
    step = max(1, OFFSET_BLOCK_VOXELS // max(1, ny * nz))
    for b0 in range(x0, x1, step):
        b1 = min(b0 + step, x1)
        lo, hi = max(0, b0 - 1), min(nx, b1 + 1)
        f = np.asarray(read(lo, hi))
        # the front moves into the void (δ > 0) from lower values, into the solid (δ < 0) from higher
        g = f if scale >= 0 else -f
        norm = np.zeros(f.shape, np.result_type(f.dtype, np.float32))
        for axis in range(3):
            n = f.shape[axis]
            if n < 2:
                continue
            ahead = (slice(None),) * axis + (slice(1, None),)
            behind = (slice(None),) * axis + (slice(None, n - 1),)
            d = np.diff(g, axis=axis)  # g[i + 1] - g[i]
            up = np.zeros_like(norm)
            np.maximum(up[ahead], d, out=up[ahead])        # g[i] - g[i - 1]
            np.negative(d, out=d)
            np.maximum(up[behind], d, out=up[behind])      # g[i] - g[i + 1]
            del d
            norm += up * up
            del up
        np.sqrt(norm, out=norm)
        norm *= scale
        own = slice(b0 - lo, b1 - lo)
        out[b0 - x0:b1 - x0] = f[own] < norm[own]
        del f, g, norm
    return out


def _assemble(profile, h, shape, n_region, n_void, thinnest, below, throat, pores, drain, cells, sealed, floating,
              shares, best_axis, as_built, clock, sections) -> Certificate:
    """The certificate's verdicts and keys from its measures (`sealed`, `floating`: pieces and voxels)."""
    limit_iso = 1.0 - math.cos(math.radians(90.0 - profile.overhang_deg))
    verdict = {
        "thinnest": "fail" if below > 0.05 else "warn" if below > 0.01 or thinnest["p1"] < profile.min_strut_mm
        or thinnest["unresolved_share"] > 0.01 else "pass",
        "throat": "fail" if throat < profile.min_throat_mm - h else "warn" if throat < profile.min_throat_mm else "pass",
        "drain": _verdict(drain, 0.99, 0.9, higher_is_worse=False),
        "cell_infiltration": _verdict(cells, 0.99, 0.9, higher_is_worse=False),
        "sealed_voids": "fail" if sealed[0] else "pass",
        "floating_solid": "fail" if floating[0] else "pass",
        "overhang": _verdict(shares[profile.build_axis], 0.05, max(0.05, limit_iso)),
        "as_built": _verdict(as_built["void_reached_by_drain_share"], 0.99, 0.9, higher_is_worse=False),
    }
    verdict["overall"] = ("fail" if "fail" in verdict.values() else "warn" if "warn" in verdict.values() else "pass")
    v3 = h ** 3
    return Certificate({
        "printer": asdict(profile),
        "voxel_mm": h,
        "grid_shape": [int(n) for n in shape],
        "porosity": float(n_void) / n_region,
        "thinnest_mm": thinnest,
        "below_min_strut_share": below,
        "throat_mm": throat,
        "pore_throats_mm": {"pores": pores.pores, "min": pores.minimum(), "median": pores.quantile(0.5)},
        "void_reached_by_drain_share": drain,
        "void_reached_by_100um_share": cells,
        "sealed_voids": {"count": int(sealed[0]), "volume_mm3": float(sealed[1]) * v3},
        "floating_solid": {"count": int(floating[0]), "volume_mm3": float(floating[1]) * v3},
        "overhang_share": shares[profile.build_axis],
        "overhang_share_by_axis": shares,
        "build_axis": profile.build_axis,
        "best_build_axis": best_axis,
        "as_built": as_built,
        "verdict": verdict,
        "seconds": clock.seconds,
    }, sections=sections)



# ----------------------------------------------------------------------------- in slabs

#: bytes per voxel of a slab (its halo included) while :func:`certificate_by_slabs` works on it:
#: the local thickness, the flood (squared distances, radii, its queue) and the reads beside them; measured
#: at 33-40 bytes on the default 10 mm cube in slabs of 60 and 120 planes
SLAB_CERTIFICATE_BYTES_PER_VOXEL = 40


class _IntPlanes:
    """int32 planes over a grid on disk: a :class:`~implicit_scaffold.run.tiles.FieldFile` holding their bits
    (written and read as float32 without arithmetic, so every bit comes back)."""

    def __init__(self, grid, folder=None):
        from ..run.tiles import FieldFile

        self._file = FieldFile(grid, folder)

    def write(self, x0: int, planes: np.ndarray) -> None:
        self._file.write(x0, np.ascontiguousarray(planes, np.int32).view(np.float32))

    def read(self, x0: int, x1: int) -> np.ndarray:
        return self._file.read(x0, x1).view(np.int32)

    def close(self) -> None:
        self._file.close()


def _section_planes(shape, profile: PrinterProfile) -> list[tuple[int, int]]:
    # through the middle, across (first) and along (second) the build axis
    build = "xyz".index(profile.build_axis[1])
    return [(build, int(shape[build]) // 2), ((build + 1) % 3, int(shape[(build + 1) % 3]) // 2)]


def _paint(maps, planes, x0: int, mask: np.ndarray, label: int, only: int | None = None) -> None:
    """Label the voxels of `mask` (planes from `x0` of the grid) on the section maps they cross."""
    x1 = x0 + mask.shape[0]
    for m, (a, i) in zip(maps, planes):
        if a == 0:
            if not x0 <= i < x1:
                continue
            view, sec = m, mask[i - x0]
        else:
            view, sec = m[x0:x1], np.take(mask, i, axis=a)
        view[sec & (view == only) if only is not None else sec] = label


def _spans(nx: int, plane: int, max_voxels: int, halo: int) -> list[tuple[int, int]]:
    # as many owned planes as the budget leaves beside the halo; at least one
    owned = max(1, int(max_voxels) // plane - 2 * halo)
    return [(x0, min(x0 + owned, nx)) for x0 in range(0, nx, owned)]


def _distances_by_slabs(solid_of, region_of, grid, max_voxels: int, halo: int, folder, floor: int,
                        progress=None) -> tuple[_IntPlanes, int]:
    """The void's squared distance (:func:`throat_radius`'s ``d2``), capped where its value does not
    matter, written plane by plane.

    Every figure reads ``d2`` exactly inside the region (the patient), and elsewhere only as "at
    least as large as any value inside, and at least `floor`" (the largest squared sphere radius
    the reach checks ask of ``r2``): the flood takes minima along paths that end inside the
    region, the pore centres are inside it, and a neighbour above the cap stays above every
    value inside. So ``d2`` is capped at ``C = max(max d2 inside + 1, floor)``; the far outside
    of a bone (a clip box's corners, tens of voxels from any solid) then needs no halo that wide.

    Each slab's distance transform reads `halo` planes on either side, the planes beyond
    standing for void as the grid's outside does: the solid it misses is at least as far as the
    first unread plane (``D`` planes away), so a voxel's value is exact when it is at most
    ``D**2``, and its capped value is right whenever ``D**2 >= C``. A first pass finds the
    largest value inside the region (widening the halo until those are exact), a second writes
    the capped values (widening it until every capped value is right). Returns the planes and
    the halo used last.
    """
    from .morphometry import _squared_edt

    nx = int(grid.shape[0])
    plane = int(grid.shape[1]) * int(grid.shape[2])
    beyond = sum(int(n) ** 2 for n in grid.shape) + 1  # more than any squared distance in the grid

    def slabs(check):
        # (x0, x1, d2 of the owned planes), the halo widened until check(d2, x0, x1, lo, hi) holds
        nonlocal halo
        x0 = 0
        while x0 < nx:
            x1 = min(nx, x0 + max(1, int(max_voxels) // plane - 2 * halo))
            lo, hi = max(0, x0 - halo), min(nx, x1 + halo)
            void = ~solid_of(lo, hi)
            if void.all():
                # no solid within reach: farther than the unread planes, as far as anything in the grid
                d2 = np.full((x1 - x0,) + tuple(grid.shape[1:]), beyond, np.int32)
            else:
                d2 = _squared_edt(void)[x0 - lo:x1 - lo]
            del void
            need = check(d2, x0, x1)
            xs = np.arange(x0, x1, dtype=np.int64)
            if not ((lo == 0 or bool(np.all(need <= (xs - lo + 1) ** 2)))
                    and (hi == nx or bool(np.all(need <= (hi - xs) ** 2)))):
                halo = max(halo + 1, math.isqrt(int(need.max()) - 1) + 1)
                continue
            yield x0, x1, d2
            x0 = x1

    # pass 1: the largest value inside the region, each plane's exact where it lies inside
    inside_max = 0

    def inside_widest(d2, x0, x1):
        region = region_of(x0, x1)
        return np.where(region, d2, 0).reshape(x1 - x0, -1).max(axis=1).astype(np.int64)

    for x0, x1, d2 in slabs(inside_widest):
        region = region_of(x0, x1)
        if region.any():
            inside_max = max(inside_max, int(d2[region].max()))
    cap = max(inside_max + 1, int(floor))
    # pass 2: the capped values
    store = _IntPlanes(grid, folder)
    try:
        def capped_widest(d2, x0, x1):
            return np.minimum(d2.reshape(x1 - x0, -1).max(axis=1).astype(np.int64), cap)

        for x0, x1, d2 in slabs(capped_widest):
            store.write(x0, np.minimum(d2, np.int32(cap)))
            if progress is not None:
                progress(x1, nx)
    except BaseException:
        store.close()
        raise
    return store, halo


def _flood_by_slabs(d2s: _IntPlanes, grid, max_voxels: int, folder) -> tuple[_IntPlanes, int]:
    """:func:`throat_radius`'s ``r2`` over the whole grid, by slabs: returns the planes and the slab floods run.

    The flood of a slab reads one plane of each neighbour as part of its marker and seeds the
    grid's faces only. Values only rise, and each is the narrowest ``d2`` of a real path from
    the grid's faces, so they never pass the whole grid's. A slab is flooded again while a
    neighbour's plane beside it has changed since its last flood (forward then backward sweeps);
    when none has, every pair of face neighbours (each within some slab with its halo) satisfies
    ``r2(p) >= min(r2(q), d2(p))`` and the faces hold ``d2``: the least such field is the max-min
    path value, the whole grid's ``r2``.
    """
    _, flood_faces = _flood_kernels()
    nx = int(grid.shape[0])
    plane = int(grid.shape[1]) * int(grid.shape[2])
    spans = _spans(nx, plane, max_voxels, 1)
    r2s = _IntPlanes(grid, folder)  # a new file reads as zeros
    try:
        dirty = [True] * len(spans)
        runs = 0
        while any(dirty):
            for order in (range(len(spans)), range(len(spans) - 1, -1, -1)):
                for s in order:
                    if not dirty[s]:
                        continue
                    dirty[s] = False
                    x0, x1 = spans[s]
                    lo, hi = max(0, x0 - 1), min(nx, x1 + 1)
                    d2 = d2s.read(lo, hi)
                    r2 = r2s.read(lo, hi)
                    own = slice(x0 - lo, x1 - lo)
                    first, last = r2[own][0].copy(), r2[own][-1].copy()
                    if not flood_faces(d2, r2, lo == 0, hi == nx):
                        raise RuntimeError("the throat flood's queue overflowed")  # pragma: no cover
                    runs += 1
                    r2s.write(x0, r2[own])
                    if s > 0 and not np.array_equal(r2[own][0], first):
                        dirty[s - 1] = True
                    if s + 1 < len(spans) and not np.array_equal(r2[own][-1], last):
                        dirty[s + 1] = True
    except BaseException:
        r2s.close()
        raise
    return r2s, runs


def _pores_by_slabs(d2s, r2s, void_of, grid, h: float, max_voxels: int, diameters, visit=None, progress=None):
    """Pore throats and the void that spheres of each of `diameters` reach, slab by slab.

    The pore centres' 3x3x3 maximum (:func:`_pore_centres`) reads one plane of halo; :func:`reached_by`'s distance
    to the allowed centres matters only below ``rho``, so a halo of ``ceil(rho)`` planes
    holds every centre that counts. `visit(x0, void, r2, reached)` sees each slab's owned
    planes. Returns the :class:`ThroatTally` and, per diameter, the reached voxels of the void.
    """
    nx = int(grid.shape[0])
    plane = int(grid.shape[1]) * int(grid.shape[2])
    rhos = [0.5 * (float(d) / h - 1.0) for d in diameters]
    halo = max([1] + [math.ceil(r) for r in rhos if r > 0])
    pores = ThroatTally(h)
    counts = [0] * len(rhos)
    spans = _spans(nx, plane, max_voxels, halo)
    for done, (x0, x1) in enumerate(spans, 1):
        lo, hi = max(0, x0 - halo), min(nx, x1 + halo)
        d2w, r2w = d2s.read(lo, hi), r2s.read(lo, hi)
        own = slice(x0 - lo, x1 - lo)
        void = void_of(x0, x1)
        # the maximum filter on the owned planes and one beside: at the grid's faces the
        # window ends there too, and "nearest" repeats the same plane as on the whole grid
        a, b = max(x0 - 1, lo) - lo, min(x1 + 1, hi) - lo
        around = np.ascontiguousarray(d2w[a:b])
        peak = _pore_centres(around, around > 0)[x0 - lo - a:x1 - lo - a]
        d2, r2 = d2w[own], r2w[own]
        centres = void & peak
        del peak, around
        pores.add(r2[centres], d2[centres])
        reached = []
        for t, rho in enumerate(rhos):
            inside = r2 > 0
            if rho > 0:
                # the halo holds every centre within rho of the owned planes: the whole grid's reach there
                inside = _reach(np.ascontiguousarray(r2w), rho)[own]
            counts[t] += int(np.count_nonzero(inside & void))
            reached.append(inside)
        if visit is not None:
            visit(x0, void, r2, reached)
        if progress is not None:
            progress(done, len(spans))
    return pores, counts


def certificate_by_slabs(source, patient, voxel: float, profile: PrinterProfile, *, max_voxels: int,
                         origin=(0.0, 0.0, 0.0), halo: int | None = None, folder=None, progress=None) -> Certificate:
    """:func:`certificate` of the solid ``source < 0`` within the region ``patient < 0``, read slab by slab.

    Gives the certificate that ``certificate(s < 0, voxel, profile, field=s, region=p < 0,
    origin=origin)`` gives on the whole fields ``s`` and ``p``, every figure and both section maps
    identical, holding about `max_voxels` voxels (halo included) of each working array, beside
    the overhang check's coarse grid (at most :data:`OVERHANG_CELLS` a side, float32) and its
    near-surface elements. A slab whose distances need a wider halo than `max_voxels` leaves
    room for takes it (exactness first); `max_voxels` below one plane and its halo reads one
    plane and its halo:

    - thinnest solid: local thickness with a halo widened until it is exact (as
      :func:`~implicit_scaffold.measure.morphometry.morphometry_by_slabs`), counted per sphere radius;
    - throats: the void's squared distance, exact by halo widening, and the max-min flood,
      both kept on disk (int32 planes in `folder`, removed at the end); the flood is iterated
      over the slabs to its fixpoint, the whole grid's (:func:`_flood_by_slabs`); pores counted
      per integer radii (:class:`ThroatTally`);
    - reached void: the allowed centres with a halo of the sphere's radius;
    - sealed voids and floating solid: pieces joined across slab faces (:class:`~implicit_scaffold.run.tiles.SlabComponents`);
    - overhangs: the subsampled field assembled from its planes; as built: the same passes on
      the solid offset by the deviation (:func:`grown_solid`, each block with its plane of halo).

    Parameters
    ----------
    source, patient : objects with ``read(x0, x1)`` giving planes ``(x1 - x0, ny, nz)`` and ``grid``
        The scaffold's and the patient's signed distances, mm (a FieldFile or ArraySlabs).
    voxel : float, mm
    profile : PrinterProfile
    max_voxels : int
        Voxels a slab may read, its halo included (a slab of one plane and its halo when
        even that is more).
    origin : 3 floats, mm
    halo : int, optional
        Planes of halo the thickness and the distances start with (e.g. from the cells' size);
        widened as needed, so the figures do not depend on it.
    folder : str or Path, optional
        Where the distances and radii are kept (the system's temporary folder by default).
    progress : callable(done, total), optional
        Called after each slab of each pass.

    Returns
    -------
    Certificate
    """
    from .morphometry import ThicknessTally, check_voxel, local_thickness
    from ..run.tiles import SlabComponents

    h = check_voxel(voxel)
    grid = source.grid
    shape = tuple(int(n) for n in grid.shape)
    if tuple(int(n) for n in patient.grid.shape) != shape:
        raise ScaffoldError(f"the region's shape {tuple(patient.grid.shape)} differs from the solid's {shape}")
    nx, ny, nz = shape
    plane = ny * nz
    max_voxels = max(1, int(max_voxels))

    def stage(step: int):
        # one bar for the whole certificate: five passes (thickness, distances, pores; distances
        # and pores as built) of 1000 steps each; the flood's sweeps count with the pores
        def report(done, total):
            if progress is not None:
                progress(min(4999, 1000 * step + (1000 * done) // max(total, 1)), 5000)
        return report

    clock = _Clock()
    planes = _section_planes(shape, profile)
    maps = [np.zeros([n for a2, n in enumerate(shape) if a2 != a], np.uint8) for a, _ in planes]

    # thinnest solid: local thickness, the halo widened until the thickest owned voxel is within it
    # a start about the thinnest strut the profile allows: struts a few times thicker widen it once,
    # and a narrow start keeps thin slabs from reading many times their planes
    halo = max(1, int(halo) if halo else math.ceil(profile.min_strut_mm / h) + 1)
    while True:
        tally = ThicknessTally(h)
        n_solid = n_region = n_void = 0
        spans = _spans(nx, plane, max_voxels, halo)
        for done, (x0, x1) in enumerate(spans, 1):
            lo, hi = max(0, x0 - halo), min(nx, x1 + halo)
            solid_w = source.read(lo, hi) < 0
            own = slice(x0 - lo, x1 - lo)
            thick = local_thickness(solid_w, h)[own]
            solid = solid_w[own]
            del solid_w
            region = patient.read(x0, x1) < 0
            tally.add(thick, solid)
            thick[solid] += np.float32(h)
            n_solid += int(np.count_nonzero(solid))
            n_region += int(np.count_nonzero(region))
            n_void += int(np.count_nonzero(region & ~solid))
            _paint(maps, planes, x0, solid, SECTION_SOLID)
            _paint(maps, planes, x0, thick < profile.min_strut_mm, SECTION_THIN, only=SECTION_SOLID)
            del thick
            stage(0)(done, len(spans))
        if tally.max_voxels <= halo or len(spans) == 1:
            break
        halo = max(2 * halo, int(math.ceil(tally.max_voxels)) + 2)
        for m in maps:
            m[...] = SECTION_VOID
    if n_solid == 0:
        raise ScaffoldError("the scaffold holds no solid voxel; nothing to certify")
    if n_void == 0:
        raise ScaffoldError("the scaffold holds no void voxel; a solid block has no pores to certify")
    thinnest, below = _thinnest(tally, profile.min_strut_mm)
    clock.mark("thickness")

    def solid_of(lo, hi):
        return source.read(lo, hi) < 0

    def region_of(x0, x1):
        return patient.read(x0, x1) < 0

    diameters = [INFILTRATION_MM] + ([profile.drain_mm] if profile.drain_mm > 0 else [])
    # the reach checks ask r2 >= rho**2 of each sphere: values above stay above when capped there
    floor = max([1] + [math.ceil((0.5 * (float(d) / h - 1.0)) ** 2) + 1 for d in diameters])
    d2s, halo = _distances_by_slabs(solid_of, region_of, grid, max_voxels, halo, folder, floor, stage(1))
    r2s = None
    try:
        r2s, _ = _flood_by_slabs(d2s, grid, max_voxels, folder)
        sealed_parts, solid_parts = SlabComponents(), SlabComponents()
        f = max(1, math.ceil(max(shape) / OVERHANG_CELLS))
        coarse = np.empty(tuple(-(-n // f) for n in shape), np.float32)
        solid_sections = []  # each slab's solid labels where it crosses the section planes
        tallies = {"sealed": 0, "void_b": 0}

        def void_of(x0, x1):
            return (patient.read(x0, x1) < 0) & ~(source.read(x0, x1) < 0)

        def visit(x0, void, r2, reached):
            x1 = x0 + len(void)
            field = source.read(x0, x1)
            if profile.drain_mm > 0:
                _paint(maps, planes, x0, ~reached[1] & void, SECTION_UNDRAINED)
            sealed = void & (r2 == 0)
            sealed_parts.add(sealed)
            tallies["sealed"] += int(np.count_nonzero(sealed))
            _paint(maps, planes, x0, sealed, SECTION_SEALED)
            labels = solid_parts.add(field < 0)
            solid_sections.append((x0, [_section_of(labels, a, i, x0) for a, i in planes]))
            first = x0 + (-x0) % f
            if first < x1:
                coarse[first // f:first // f + len(range(first, x1, f))] = field[first - x0::f, ::f, ::f]
            grown = grown_solid(source.read, shape, x0, x1, profile.deviation_mm, h)
            tallies["void_b"] += int(np.count_nonzero((patient.read(x0, x1) < 0) & ~grown))

        pores, reached = _pores_by_slabs(d2s, r2s, void_of, grid, h, max_voxels, diameters, visit, stage(2))
    finally:
        d2s.close()
        if r2s is not None:
            r2s.close()
    throat = pores.quantile(1 - THROAT_PORE_SHARE) if pores.pores else 0.0
    cells = float(reached[0] / n_void)
    drain = float(reached[1] / n_void) if profile.drain_mm > 0 else None
    clock.mark("throats")

    sealed_parts.finish()
    sealed_n = sealed_parts.piece_count
    floating_n = solid_parts.finish()
    floating_voxels = n_solid - int(solid_parts.sizes[solid_parts.main])
    if floating_n:
        for index, (x0, parts) in enumerate(solid_sections):
            for m, (a, _), sec in zip(maps, planes, parts):
                if sec is not None:
                    view = m if a == 0 else m[x0:x0 + sec.shape[0]]
                    view[(sec > 0) & (solid_parts.roots_of(index, sec) != solid_parts.main)] = SECTION_FLOATING
    solid_sections = None  # released (the slab visits read it no more)
    # the surface elements by blocks of coarse planes, each with a plane of halo: the whole
    # coarse grid's elements in the same order, without its gradients held at once
    cx = coarse.shape[0]
    step = max(1, max_voxels // (coarse.shape[1] * coarse.shape[2]) - 2)
    elements = [_surface_elements(coarse[c0 - 1:min(c0 + step, cx - 1) + 1], h * f) for c0 in range(1, cx - 1, step)]
    coarse = None
    shares = _overhang_sums(np.concatenate([w for w, _ in elements] or [np.zeros(0, np.float32)]),
                            np.concatenate([n for _, n in elements] or [np.zeros((0, 3), np.float32)]),
                            profile.overhang_deg)
    del elements
    best_axis = min(shares, key=lambda k: (shares[k], k))
    clock.mark("pieces and overhangs")

    # as built: the solid grown by the process's deviation (:func:`grown_solid`: less than a voxel too)
    n_void_b = tallies["void_b"]
    as_built = {"deviation_mm": profile.deviation_mm, "porosity": float(n_void_b) / n_region,
                "throat_mm": 0.0, "void_reached_by_drain_share": None}
    if n_void_b:
        def grown_of(lo, hi):
            return grown_solid(source.read, shape, lo, hi, profile.deviation_mm, h)

        def void_b_of(x0, x1):
            return (patient.read(x0, x1) < 0) & ~grown_of(x0, x1)

        d2s, _ = _distances_by_slabs(grown_of, region_of, grid, max_voxels, halo, folder, floor, stage(3))
        r2s = None
        try:
            r2s, _ = _flood_by_slabs(d2s, grid, max_voxels, folder)
            pores_b, reached_b = _pores_by_slabs(d2s, r2s, void_b_of, grid, h, max_voxels,
                                                 [profile.drain_mm] if profile.drain_mm > 0 else [],
                                                 progress=stage(4))
        finally:
            d2s.close()
            if r2s is not None:
                r2s.close()
        as_built["throat_mm"] = pores_b.quantile(1 - THROAT_PORE_SHARE) if pores_b.pores else 0.0
        if profile.drain_mm > 0:
            as_built["void_reached_by_drain_share"] = float(reached_b[0] / n_void_b)
    clock.mark("as built")
    if progress is not None:
        progress(5000, 5000)
    return _assemble(profile, h, shape, n_region, n_void, thinnest, below, throat, pores, drain, cells,
                     (sealed_n, tallies["sealed"]), (floating_n, floating_voxels), shares, best_axis, as_built,
                     clock, {(a, i): m for m, (a, i) in zip(maps, planes)})


def _section_of(arr: np.ndarray, axis: int, index: int, x0: int):
    """The part of the section plane ``(axis, index)`` held by `arr` (planes from `x0`), or None."""
    if axis == 0:
        return arr[index - x0] if x0 <= index < x0 + arr.shape[0] else None
    return np.take(arr, index, axis=axis)
