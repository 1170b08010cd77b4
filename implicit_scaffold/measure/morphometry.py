"""Bone morphometry on the voxels of what was built (stage 8; BoneJ's and PoreSpy's measures).

Every function takes a boolean solid volume ``solid`` of shape ``(nx, ny, nz)`` on cubic
voxels of edge ``voxel`` mm and, optionally, a boolean ``region`` of the same shape: the
patient (the space the scaffold may fill). The void is ``region & ~solid``; everything
outside the region, and beyond the array, is "outside".

- Local thickness by maximal inscribed spheres (Hildebrand & Rüegsegger 1997): the
  thickness at a voxel is the diameter of the largest sphere that fits in the phase and
  holds the voxel. Computed exactly on the voxels (no radius binning): squared Euclidean
  distance transform, the centres of maximal spheres (a sphere is dropped when a
  26-neighbour's sphere holds all its voxels, tested exactly with a look-up table), then
  spheres painted from the largest down, each voxel written once: a bit per voxel marks
  what larger spheres already painted, so a sphere skips it a 64-voxel word at a time
  and the cost is about one step per row of each sphere instead of one per voxel.
- Euler characteristic of the 26-connected solid (6-connected void) from the cell counts
  of the union of closed voxel cubes, ``chi = V - E + F - C`` (exact).
- Interconnected porosity: the share of the void joined (6-connected) to the outside.
- Fragments: 6-connected solid pieces besides the largest, as the pipeline removes them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import ScaffoldError, ScaffoldWarning, positive_mm, round_down
from ..run.threads import count

#: histograms of thickness get at most this many bins (bin width a whole number of voxels)
MAX_BINS = 60


# --------------------------------------------------------------------------- checks


def check_voxel(voxel) -> float:
    """`voxel` as a positive, finite size in mm, else a :class:`ScaffoldError` saying so."""
    try:
        h = float(voxel)
    except (TypeError, ValueError):
        raise ScaffoldError(f"the voxel size must be a positive number of mm, got {voxel!r}") from None
    if not (math.isfinite(h) and h > 0):
        raise ScaffoldError(f"the voxel size must be a positive number of mm, got {voxel!r}")
    return h


def _check_volume(solid, voxel, region=None) -> tuple[np.ndarray, float, np.ndarray | None]:
    solid = np.asarray(solid)
    if solid.ndim != 3 or min(solid.shape) < 1:
        raise ScaffoldError(f"a solid volume must be a 3-D array, got shape {solid.shape}")
    solid = solid.astype(bool, copy=False)
    h = check_voxel(voxel)
    if region is not None:
        region = np.asarray(region).astype(bool, copy=False)
        if region.shape != solid.shape:
            raise ScaffoldError(f"the region's shape {region.shape} differs from the solid's {solid.shape}")
    return solid, h, region


# --------------------------------------------------------------------------- local thickness


def compiled_kernels():
    """The compiled kernels (numba), built on first use and cached on disk."""
    global _KERNELS
    if _KERNELS is not None:
        return _KERNELS
    import numba as nb

    from ..run.threads import over_rows

    @nb.njit(cache=True, nogil=True, boundscheck=False)
    def ridge_rows(d2, need, keep, lo, hi):  # pragma: no cover - compiled
        # a voxel is a centre of a maximal sphere unless a sphere centred up to two voxels away
        # holds its sphere
        nx, ny, nz = d2.shape
        for i in range(lo, hi):
            for j in range(ny):
                for k in range(nz):
                    v = d2[i, j, k]
                    if v <= 0:
                        continue
                    ok = True
                    for di in range(-1, 2):
                        ii = i + di
                        if ii < 0 or ii >= nx or not ok:
                            continue
                        for dj in range(-1, 2):
                            jj = j + dj
                            if jj < 0 or jj >= ny or not ok:
                                continue
                            for dk in range(-1, 2):
                                kk = k + dk
                                c = di * di + dj * dj + dk * dk
                                if kk < 0 or kk >= nz or c == 0:
                                    continue
                                if d2[ii, jj, kk] >= need[v, c]:
                                    ok = False
                                    break
                    if ok:
                        # the survivors (a sixth of the phase) against the shell two voxels out:
                        # a third of them are held by a sphere there, a third less to paint
                        for di in range(-2, 3):
                            ii = i + di
                            if ii < 0 or ii >= nx or not ok:
                                continue
                            for dj in range(-2, 3):
                                jj = j + dj
                                if jj < 0 or jj >= ny or not ok:
                                    continue
                                for dk in range(-2, 3):
                                    kk = k + dk
                                    if kk < 0 or kk >= nz or (di * di < 4 and dj * dj < 4 and dk * dk < 4):
                                        continue
                                    if d2[ii, jj, kk] >= need[v, di * di + dj * dj + dk * dk]:
                                        ok = False
                                        break
                    keep[i, j, k] = ok

    @nb.njit(cache=True, nogil=True, boundscheck=False)
    def paint_rows(nx, ny, nz, ci_, cj_, ck_, cv_, isq, bits, todo, out, scale, x0, x1):  # pragma: no cover
        # spheres come sorted by decreasing squared radius, so the first to reach a voxel is
        # the largest that holds it. One bit per voxel says "painted": a sphere's row is
        # skipped a 64-voxel word at a time, and the bits (nx * ny * nz / 8 bytes) stay in
        # cache where a pointer per voxel would not. `todo` counts the phase voxels not yet
        # painted in each brick of 8 rows by one word (one plane of x): the parts of a sphere
        # in bricks that larger spheres finished are skipped eight rows at a time. Each slab of
        # x [x0, x1) is one thread's, bricks included.
        nw = (nz + 63) >> 6
        nbj = (ny + 7) >> 3
        one = np.uint64(1)
        n = ci_.shape[0]
        for t in range(n):
            v = cv_[t]
            ci = ci_[t]
            r = isq[v]
            lo = max(ci - r, x0)
            hi = min(ci + r, x1 - 1)
            if lo > hi:
                continue
            cj = cj_[t]
            ck = ck_[t]
            val = np.float32(scale * np.sqrt(v))
            for i in range(lo, hi + 1):
                ri = v - (i - ci) * (i - ci)
                rj = isq[ri]
                j0 = max(cj - rj, 0)
                j1 = min(cj + rj, ny - 1)
                wa = max(ck - rj, 0) >> 6
                wb = min(ck + rj, nz - 1) >> 6
                for jb in range(j0 >> 3, (j1 >> 3) + 1):
                    for w in range(wa, wb + 1):
                        brick = (i * nbj + jb) * nw + w
                        left = todo[brick]
                        if left == 0:
                            continue
                        for j in range(max(jb << 3, j0), min((jb << 3) + 7, j1) + 1):
                            hk = isq[ri - (j - cj) * (j - cj)]
                            k0 = max(ck - hk, w << 6)
                            k1 = min(ck + hk, nz - 1, (w << 6) + 63)
                            if k0 > k1:
                                continue
                            a = k0 - (w << 6)
                            b = k1 - (w << 6)
                            if b - a == 63:
                                mask = ~np.uint64(0)
                            else:
                                mask = ((one << np.uint64(b - a + 1)) - one) << np.uint64(a)
                            word = (i * ny + j) * nw + w
                            cur = bits[word]
                            free = mask & ~cur
                            if free != 0:
                                bits[word] = cur | mask
                                # the free bits alone, lowest first: a power of two's remainder
                                # modulo 67 names its bit (_LOW_BIT)
                                while free != 0:
                                    low = free & (~free + one)
                                    out[i, j, (w << 6) + _LOW_BIT[low % np.uint64(67)]] = val
                                    left -= 1
                                    free ^= low
                        todo[brick] = left

    def ridge(d2, need):
        keep = np.zeros(d2.shape, np.bool_)
        over_rows(ridge_rows, d2.shape[0], d2, need, keep)
        return keep

    def paint(phase, ci_, cj_, ck_, cv_, isq, nslab, out, scale):
        nx, ny, nz = phase.shape
        bits = np.zeros(nx * ny * ((nz + 63) >> 6), np.uint64)
        # phase voxels per brick of 8 rows (y) by 64 voxels (z), one plane of x
        padded = np.zeros((nx, -(-ny // 8) * 8, -(-nz // 64) * 64), np.bool_)
        padded[:, :ny, :nz] = phase
        todo = np.ascontiguousarray(
            padded.reshape(nx, padded.shape[1] // 8, 8, padded.shape[2] // 64, 64).sum(axis=(2, 4), dtype=np.int32))
        del padded
        over_rows(paint_rows, nx, nx, ny, nz, ci_, cj_, ck_, cv_, isq, bits, todo.reshape(-1), out, scale,
                  pieces=nslab)
        return out

    @nb.njit(cache=True, nogil=True, boundscheck=False)
    def tally_rows(thickness, phase, two_h, piece_of, counts, lo, hi):  # pragma: no cover - compiled
        # counts[p, v]: the phase voxels of planes [lo, hi) (piece p) whose thickness is
        # 2 h sqrt(v), v recovered as ThicknessTally's NumPy formula does (float64, squared,
        # rounded half to even)
        nx, ny, nz = thickness.shape
        row = counts[piece_of[lo]]
        for i in range(lo, hi):
            for j in range(ny):
                for k in range(nz):
                    if phase[i, j, k]:
                        r = np.float64(thickness[i, j, k]) / two_h
                        row[np.int64(np.rint(r * r))] += 1

    def tally(thickness, phase, two_h, vmax):
        # one row of counts per piece of planes: integer sums, the same whatever the threads
        nx = thickness.shape[0]
        pieces = max(1, min(nx, 4 * count()))
        piece_of = np.zeros(nx, np.int64)
        for p in range(pieces):
            piece_of[nx * p // pieces] = p
        counts = np.zeros((pieces, vmax + 1), np.int64)
        over_rows(tally_rows, nx, thickness, phase, two_h, piece_of, counts, pieces=pieces)
        return counts.sum(axis=0)

    _KERNELS = (ridge, paint, tally)
    return _KERNELS


_KERNELS = None
#: ``_LOW_BIT[(1 << b) % 67] == b`` for b < 64: 67 is the least modulus under which the powers
#: of two up to 2^63 all differ
_LOW_BIT = np.zeros(67, np.int64)
_LOW_BIT[[pow(2, b, 67) for b in range(64)]] = np.arange(64)


def _squared_edt(phase: np.ndarray) -> np.ndarray:
    """Squared distance (voxels², exact integers) from each phase voxel to the nearest non-phase voxel centre.

    Voxels beyond the array count as phase (the caller pads with non-phase where the
    outside must bound the spheres). Compiled, on every core (:func:`~implicit_scaffold.fields.volume_kernels.squared_distance`).
    """
    from ..fields.volume_kernels import squared_distance

    return squared_distance(phase)


def _maximal_sphere_tables(vmax: int):
    """Look-up tables for integer squared radii ``v <= vmax``.

    ``need[v, c]``: the least squared radius a sphere centred at a neighbour ``c`` voxels²
    away (c = 1 to 12, offsets of at most two voxels along each axis) must have to hold every
    voxel of the sphere ``|x|² < v``;
    ``isq[m]``: the largest ``h`` with ``h² < m`` (-1 for m = 0).
    """
    r = math.isqrt(max(vmax, 1)) + 2
    # the farthest point from a neighbour in +x (+y, +z) lies on the -x (-y, -z) side: one
    # octant of the sphere is enough, an eighth of the points
    g = np.arange(-r, 1)
    x, y, z = np.meshgrid(g, g, g, indexing="ij", sparse=True)
    n2 = (x * x + y * y + z * z).ravel()
    order = np.argsort(n2, kind="stable")
    n2 = n2[order]
    last = np.searchsorted(n2, np.arange(vmax + 1) - 1, side="right") - 1  # points with |x|² <= v - 1
    need = np.full((vmax + 1, 13), np.iinfo(np.int64).max, dtype=np.int64)
    # offsets up to two voxels along each axis: each squared length names one offset up to
    # symmetry (7, 10 and 11 name none)
    for c, (a, b, e) in ((1, (1, 0, 0)), (2, (1, 1, 0)), (3, (1, 1, 1)), (4, (2, 0, 0)), (5, (2, 1, 0)),
                         (6, (2, 1, 1)), (8, (2, 2, 0)), (9, (2, 2, 1)), (12, (2, 2, 2))):
        far = ((x - a) ** 2 + (y - b) ** 2 + (z - e) ** 2).ravel()[order]
        reach = np.maximum.accumulate(far) + 1
        need[1:, c] = reach[last[1:]]
    m = np.arange(vmax + 2)
    isq = np.array([math.isqrt(int(v) - 1) if v > 0 else -1 for v in m], dtype=np.int64)
    return need, isq


def local_thickness(phase, voxel: float) -> np.ndarray:
    """Local thickness of a phase by maximal inscribed spheres (Hildebrand & Rüegsegger).

    Parameters
    ----------
    phase : (nx, ny, nz) bool ndarray
        The phase measured (solid for strut thickness, void for pore diameter).
        Voxels beyond the array are not phase: spheres stop at the array's faces.
    voxel : float, mm
        Edge of the cubic voxels.

    Returns
    -------
    (nx, ny, nz) float32 ndarray, mm
        At each phase voxel, the diameter ``2 r`` of the largest sphere that holds it and
        lies in the phase, ``r`` being the distance from the sphere's centre voxel to the
        nearest non-phase voxel centre; 0 outside the phase. A slab of ``T`` voxels reads
        ``T`` (even ``T``) or ``T + 1`` (odd), a ball of radius ``R`` reads ``2R`` within a voxel.

    Notes
    -----
    Exact on the voxels (no binning of radii). The work is the distance transform, one
    pass for the maximal spheres, and one step per voxel row of each maximal sphere.
    """
    phase, h, _ = _check_volume(phase, voxel)
    out = np.zeros(phase.shape, np.float32)
    if not phase.any():
        return out
    padded = np.pad(phase, 1)
    d2 = _squared_edt(padded)[1:-1, 1:-1, 1:-1]
    del padded
    vmax = int(d2.max())
    need, isq = _maximal_sphere_tables(vmax)
    ridge, paint, _ = compiled_kernels()
    keep = ridge(d2, need)
    ci, cj, ck = np.nonzero(keep)
    del keep
    v = d2[ci, cj, ck]
    del d2
    # ties in index order: same inputs, same work; squared radii under 2^15 (a radius of 181
    # voxels) sort as int16, by NumPy's radix sort, 3x faster than the merge sort of int32
    key = -v.astype(np.int16) if vmax < 2 ** 15 else -v
    order = np.argsort(key, kind="stable")
    del key
    nx, ny, nz = phase.shape
    nslab = max(1, min(nx, 4 * count()))
    paint(phase, ci[order], cj[order], ck[order], v[order], isq, nslab, out, 2.0 * h)
    return out


#: thickness maps up to this squared sphere radius (voxels², a radius of 3,162 voxels) are counted by
#: a compiled pass, one row of counts per piece of planes; beyond, by NumPy
TALLY_COMPILED_VMAX = 10_000_000


class ThicknessTally:
    """Voxel counts of local-thickness maps by the squared radius of their spheres, added slab by slab.

    :func:`local_thickness` gives every phase voxel ``2 h sqrt(v)`` for an integer squared
    radius ``v`` (voxels²), so a count per ``v`` holds the whole map's distribution: maps
    of slabs add up to the whole grid's exactly, and the statistics come from the counts
    in one order whatever the slabs.

    Parameters
    ----------
    voxel : float, mm
    """

    def __init__(self, voxel: float):
        self.voxel = float(voxel)
        self.counts = np.zeros(1, np.int64)

    def add(self, thickness, phase) -> "ThicknessTally":
        """Count the phase voxels of a local-thickness map (a slab's owned planes)."""
        thickness = np.asarray(thickness)
        phase = np.asarray(phase, bool)
        top = float(thickness.max()) if thickness.size else 0.0
        vmax = int(np.rint((top / (2 * self.voxel)) ** 2)) if math.isfinite(top) and top > 0 else 0
        if thickness.ndim != 3 or thickness.dtype != np.float32 or vmax > TALLY_COMPILED_VMAX:
            c = self._counts_numpy(thickness, phase)
        elif not thickness.size:
            c = np.zeros(0, np.int64)
        else:
            # one compiled pass on every core, without the gathered copy (0.2-0.3 s a phase on 252^3)
            c = compiled_kernels()[2](np.ascontiguousarray(thickness), np.ascontiguousarray(phase),
                                      2 * self.voxel, vmax)
        if c.size:
            if len(c) > len(self.counts):
                c[:len(self.counts)] += self.counts
                self.counts = c
            else:
                self.counts[:len(c)] += c
        return self

    def _counts_numpy(self, thickness, phase) -> np.ndarray:
        t = thickness[phase].astype(np.float64)
        if not t.size:
            return np.zeros(0, np.int64)
        return np.bincount(np.rint((t / (2 * self.voxel)) ** 2).astype(np.int64))

    @property
    def max_voxels(self) -> float:
        """The largest thickness counted, in voxels (0 when none)."""
        v = np.nonzero(self.counts)[0]
        return 2.0 * math.sqrt(int(v[-1])) if v.size else 0.0

    def stats(self) -> dict:
        """:func:`thickness_stats` of everything added."""
        v = np.nonzero(self.counts)[0]
        if v.size == 0:
            return {"mean": None, "sd": None, "max": None, "histogram": {"edges_mm": [], "counts": []}}
        # the float32 values local_thickness wrote
        values = np.float32(2.0 * self.voxel * np.sqrt(v.astype(np.float64))).astype(np.float64)
        counts = self.counts[v]
        n = int(counts.sum())
        mean = float(np.dot(values, counts) / n)
        sd = float(math.sqrt(max(0.0, float(np.dot((values - mean) ** 2, counts)) / n)))
        tmax = float(values[-1])
        h = self.voxel
        width = h * max(1, math.ceil(tmax / h / MAX_BINS))
        nbins = max(1, math.ceil(tmax / width + 1e-9))
        if nbins * width <= tmax:  # the maximum sits on the last edge: one more bin holds it
            nbins += 1
        edges = np.arange(nbins + 1) * width
        hist = np.bincount(np.minimum((values / width).astype(np.int64), nbins - 1), weights=counts,
                           minlength=nbins)
        return {"mean": mean, "sd": sd, "max": tmax,
                "histogram": {"edges_mm": [float(e) for e in edges], "counts": [int(c) for c in hist]}}


def thickness_stats(thickness, phase, voxel: float) -> dict:
    """Mean, sd and max of a local-thickness map over a phase, with its histogram.

    Parameters
    ----------
    thickness : (nx, ny, nz) float ndarray, mm
        As :func:`local_thickness` gives it.
    phase : (nx, ny, nz) bool ndarray
    voxel : float, mm

    Returns
    -------
    dict
        ``mean``, ``sd``, ``max`` (mm, voxel-weighted as BoneJ reports them; None for an
        empty phase) and ``histogram``: ``edges_mm`` (bins of a whole number of voxels from
        0, at most :data:`MAX_BINS`) and ``counts`` (voxels per bin).
    """
    return ThicknessTally(voxel).add(thickness, phase).stats()


# --------------------------------------------------------------------------- topology


def _or_pairs(a: np.ndarray, axis: int) -> np.ndarray:
    lo = [slice(None)] * 3
    hi = [slice(None)] * 3
    lo[axis] = slice(None, -1)
    hi[axis] = slice(1, None)
    return a[tuple(lo)] | a[tuple(hi)]


def euler_characteristic(solid) -> int:
    """Euler characteristic of the 26-connected solid (its void 6-connected), exact.

    Each solid voxel is a closed unit cube; the union's characteristic is
    ``V - E + F - C``, counting the vertices, edges, faces and cubes of the union.
    Nothing is assumed beyond the array: the solid is the whole object (no edge
    correction as for a sample cut from a larger bone).

    Parameters
    ----------
    solid : (nx, ny, nz) bool ndarray

    Returns
    -------
    int
        Components - tunnels + cavities: a ball 1, a solid torus 0, a hollow ball 2.
    """
    p = np.pad(np.asarray(solid, bool), 1)
    cubes = int(np.count_nonzero(p))
    fx = _or_pairs(p, 0)  # faces normal to x: either voxel on the two sides
    fy = _or_pairs(p, 1)
    faces = int(np.count_nonzero(fx)) + int(np.count_nonzero(fy)) + int(np.count_nonzero(_or_pairs(p, 2)))
    ez = _or_pairs(fx, 1)  # an edge along z belongs to the 4 voxels around it
    edges = (int(np.count_nonzero(ez)) + int(np.count_nonzero(_or_pairs(fx, 2)))
             + int(np.count_nonzero(_or_pairs(fy, 2))))
    del fx, fy
    vertices = int(np.count_nonzero(_or_pairs(ez, 2)))
    return vertices - edges + faces - cubes


def euler_characteristic_by_slabs(source, x_ranges) -> int:
    """:func:`euler_characteristic` of the solid ``field < 0`` of a field read by plane ranges, exact.

    The characteristic counts each cell (vertex, edge, face, cube) of the union of closed
    voxels once. Slab ``[x0, x1)`` is read with the plane before it, ``h``: the cells of
    ``h ∪ slab`` that are not cells of ``h`` alone are the slab's cubes and the cells
    between them, plus those of the plane ``h | slab`` that only the slab's voxels touch
    (the others were counted with the previous slab). So ``chi`` is the sum over slabs of
    ``chi(h ∪ slab) - chi(h)``: a one-plane halo, whatever the slab sizes.

    Parameters
    ----------
    source : object with ``read(x0, x1)`` giving planes ``(x1 - x0, ny, nz)`` of a field, mm
        E.g. a :class:`~implicit_scaffold.run.tiles.FieldFile` or ``ArraySlabs``.
    x_ranges : iterable of (x0, x1)
        Consecutive plane ranges covering the grid.

    Returns
    -------
    int
    """
    chi = 0
    for x0, x1 in x_ranges:
        lo = max(int(x0) - 1, 0)
        solid = source.read(lo, int(x1)) < 0
        chi += euler_characteristic(solid)
        if lo < x0:
            chi -= euler_characteristic(solid[:1])
    return chi


def connectivity_density(solid, voxel: float, region=None) -> float:
    """Connectivity density ``(1 - chi) / V``, mm⁻³, with ``V`` the region's volume (the whole array without one)."""
    solid, h, region = _check_volume(solid, voxel, region)
    n = int(np.count_nonzero(region)) if region is not None else solid.size
    if n == 0:
        raise ScaffoldError("the region holds no voxel; connectivity density needs a volume")
    return (1 - euler_characteristic(solid)) / (n * h ** 3)


def interconnected_porosity(solid, region=None) -> float | None:
    """Share of the void (``region & ~solid``) joined to the outside through void, 6-connected.

    The outside is every voxel outside the region, and the space beyond the array.
    None when there is no void.
    """
    from ..run.pieces import label_pieces, label_sizes

    solid = np.asarray(solid, bool)
    void = ~solid if region is None else (np.asarray(region, bool) & ~solid)
    total = int(np.count_nonzero(void))
    if total == 0:
        return None
    open_ = np.pad(~solid, 1, constant_values=True)  # void and outside alike, and the space beyond
    labels, count = label_pieces(open_)
    inner = labels[1:-1, 1:-1, 1:-1]
    # the pieces that reach the outside: the padding layer's (one piece), and those holding void
    # outside the region; the void voxels of each piece, summed over those
    reaches = np.zeros(count + 1, bool)
    reaches[labels[0, 0, 0]] = True
    if region is not None:
        reaches[inner[~np.asarray(region, bool) & ~solid]] = True
    reaches[0] = False
    return int(label_sizes(inner, count, where=void)[reaches].sum()) / total


def count_fragments(solid) -> int:
    """Solid pieces (6-connected, as the pipeline removes them) besides the largest one."""
    from ..run.pieces import label_pieces

    _, n = label_pieces(solid)
    return max(0, int(n) - 1)


def surface_mesh(solid, grid):
    """The solid's surface: marching cubes halfway between solid and void voxel centres.

    Parameters
    ----------
    solid : (nx, ny, nz) bool ndarray
    grid : Grid
        Where the voxels are (mm).

    Returns
    -------
    trimesh.Trimesh or None
        Closed and outward-oriented; None when there is no solid.
    """
    from ..run.grid import Grid
    from ..mesh.marching import mesh_field

    solid = np.asarray(solid, bool)
    if not solid.any():
        return None
    h = float(grid.spacing)
    # one layer of outside all round, so that solid on the array's faces closes
    field = _PaddedSolid(solid, h).read(0, solid.shape[0] + 2)
    origin = tuple(float(o) - h for o in grid.origin)
    return mesh_field(field, Grid(origin, h, field.shape), check=False)


#: voxels of :func:`surface_from_volume`'s slab (its planes read ahead included): 4 MiB of float32. Its
#: triangles are its peak: on the default cube's 195^3 scaffold, 12.4 bytes a voxel of the grid above what
#: was held (0.52 s), 38.0 with slabs four times as large (0.49 s), 9.2 a quarter as large (1.82 s: one cube
#: layer a slab, beside 17 planes read ahead)
SURFACE_SLAB_VOXELS = 1 << 20
#: ... but at least this many cube layers a slab (a CT's 512 x 512 planes)
SURFACE_SLAB_LAYERS = 8


class _PaddedSolid:
    """Planes of :func:`surface_mesh`'s field (``-h/2`` in the solid, ``+h/2`` in the void, one layer of void
    all round) made from the voxels as they are read: a field source for the streamed mesher's slabs."""

    def __init__(self, solid: np.ndarray, h: float):
        from ..run.grid import Grid

        self.solid, self.h = solid, float(h)
        self.grid = Grid((0.0, 0.0, 0.0), self.h, tuple(int(n) + 2 for n in solid.shape))

    def read(self, x0: int, x1: int) -> np.ndarray:
        out = np.full((x1 - x0,) + tuple(self.grid.shape[1:]), np.float32(0.5 * self.h))
        a, b = max(x0, 1), min(x1, self.solid.shape[0] + 1)
        if a < b:
            inner = out[a - x0:b - x0, 1:-1, 1:-1]
            inner[self.solid[a - 1:b - 1]] = np.float32(-0.5 * self.h)
        return out


def surface_from_volume(solid, voxel: float) -> tuple[float, float]:
    """Surface area (mm²) and enclosed volume (mm³) of the solid's marching-cubes mesh (level halfway,
    :func:`surface_mesh`'s), by slabs of planes: the same triangles, summed slab by slab.

    The whole mesh and its field held some 80 bytes a voxel (the default cube's 195^3 scaffold read as a
    volume: 575 MiB above the read, where the thickness maps before it took 21); a slab holds its own
    (:data:`SURFACE_SLAB_VOXELS`) and its triangles.
    """
    from ..mesh.marching import TIE_ROUNDS, face_measures
    from ..mesh.stream import _slab_surface

    solid, h, _ = _check_volume(solid, voxel)
    if not solid.any():
        return 0.0, 0.0
    source = _PaddedSolid(solid, h)
    nx, ny, nz = source.grid.shape
    # a slab's cube layers and the planes it reads ahead (the tie-breaking's rounds)
    layers = max(SURFACE_SLAB_LAYERS, SURFACE_SLAB_VOXELS // (ny * nz) - 2 - TIE_ROUNDS)
    area = volume = 0.0
    for x0 in range(0, nx - 1, layers):
        surface = _slab_surface(source, x0, min(x0 + layers, nx - 1), 0.0)
        if surface is None:
            continue
        verts, faces = surface
        verts = verts.astype(np.float64)
        verts[:, 0] += x0
        # one reference point for every slab: the tetrahedra's volumes add up to the closed mesh's
        a, v = face_measures(verts, faces, ref=np.zeros(3))
        area += float(a.sum())
        volume += float(v.sum())
    return area * h * h, volume * h ** 3


# --------------------------------------------------------------------------- all of it


def morphometry(solid, voxel: float, *, region=None, surface_area_mm2: float | None = None,
                solid_volume_mm3: float | None = None, surface: bool = True) -> dict:
    """Every voxel measure of a scaffold (or bone), as the report's keys.

    Parameters
    ----------
    solid : (nx, ny, nz) bool ndarray
        The solid, on cubic voxels.
    voxel : float, mm
    region : (nx, ny, nz) bool ndarray, optional
        The patient: the void is ``region & ~solid``, and void outside it does not count
        as pore. Default: the whole array.
    surface_area_mm2, solid_volume_mm3 : float, optional
        Area and volume of the solid's mesh, when one was built; otherwise they are
        measured on a marching-cubes mesh of the voxels (``surface=True``) or left out.
    surface : bool
        Measure the surface from the voxels when no area is given.

    Returns
    -------
    dict
        ``strut_thickness_mm`` and ``pore_diameter_mm`` (see :func:`thickness_stats`),
        ``connectivity_density_per_mm3``, ``euler_characteristic``,
        ``interconnected_porosity``, ``fragments``, ``porosity_voxel`` (``1 - solid / region``
        voxels), and when a surface is known or measured ``surface_area_mm2`` and
        ``bs_bv_per_mm`` (area over the mesh's volume, or the voxels' when none is given).

    Notes
    -----
    Conn.D is ``(1 - chi) / V`` with ``V`` the region's volume and ``chi`` that of the whole
    solid as it stands (nothing beyond the array is assumed): right for a scaffold, which
    is a whole object. A sample cut from a larger bone would want BoneJ's edge correction.
    """
    solid, h, region = _check_volume(solid, voxel, region)
    void = ~solid if region is None else (region & ~solid)
    n_region = int(np.count_nonzero(region)) if region is not None else solid.size
    if n_region == 0:
        raise ScaffoldError("the region holds no voxel; nothing to measure")
    out: dict = {}
    strut = local_thickness(solid, h)
    out["strut_thickness_mm"] = thickness_stats(strut, solid, h)
    del strut
    pore = local_thickness(void, h)
    out["pore_diameter_mm"] = thickness_stats(pore, void, h)
    del pore
    chi = euler_characteristic(solid)
    out["euler_characteristic"] = chi
    out["connectivity_density_per_mm3"] = (1 - chi) / (n_region * h ** 3)
    out["interconnected_porosity"] = interconnected_porosity(solid, region)
    out["fragments"] = count_fragments(solid)
    n_solid = int(np.count_nonzero(solid))
    out["porosity_voxel"] = 1.0 - n_solid / n_region
    if surface_area_mm2 is None and surface:
        surface_area_mm2, solid_volume_mm3 = surface_from_volume(solid, h)
    if surface_area_mm2 is not None:
        out.update(surface_measures(surface_area_mm2,
                                    solid_volume_mm3 if solid_volume_mm3 is not None else n_solid * h ** 3))
    return out


def surface_measures(surface_area_mm2: float, solid_volume_mm3: float) -> dict:
    """``surface_area_mm2`` and ``bs_bv_per_mm`` (area over solid volume, 1/mm; None for no solid)."""
    bv = float(solid_volume_mm3)
    return {"surface_area_mm2": float(surface_area_mm2),
            "bs_bv_per_mm": float(surface_area_mm2) / bv if bv > 0 else None}


#: bytes per voxel of a slab (its halo included) while :func:`morphometry_by_slabs` takes its
#: local thickness: the phase, its padded copy, the squared distances, the thickness map, labels
SLAB_MORPHOMETRY_BYTES_PER_VOXEL = 28


def morphometry_by_slabs(source, patient, voxel: float, *, max_voxels: int, halo: int, planes: int | None = None,
                         progress=None, solid_pieces: int | None = None) -> dict:
    """:func:`morphometry`'s voxel measures of the solid ``source < 0`` within the region
    ``patient < 0``, read slab by slab: the same figures as on the whole grid.

    - Local thickness (strut thickness, pore diameter): each slab is measured with `halo`
      planes on either side, the halo's outer faces standing for non-phase as the grid's
      faces do. A sphere of radius ``r`` that paints an owned voxel has its centre within
      ``r`` of it, and that centre's distance is exact when the halo is at least ``2 r``
      wide; a halo narrower than that shows, since some owned voxel then reads a thickness
      of at least the halo (the centre of the widest sphere is owned by some slab, where
      its distance is either exact or at least the halo). So the thickest owned voxel
      bounds what was needed: when it exceeds `halo`, every slab is measured again with a
      wider one. The counts per sphere radius add up to the whole grid's
      (:class:`ThicknessTally`), so the statistics are identical.
    - Euler characteristic: :func:`euler_characteristic_by_slabs` (one-plane halo).
    - Interconnected porosity and fragments: the void's and the solid's 6-connected
      pieces joined across slab faces (:class:`~implicit_scaffold.run.tiles.SlabComponents`).

    Parameters
    ----------
    source, patient : objects with ``read(x0, x1)`` giving planes ``(x1 - x0, ny, nz)``, mm
        The scaffold's and the patient's signed distances (a FieldFile or ArraySlabs).
    voxel : float, mm
    max_voxels : int
        Voxels a slab may read, its halo included.
    halo : int
        Planes of halo to start with (e.g. from the largest cell); widened as needed.
    planes : int, optional
        Planes each slab owns, whatever its halo (by default as many as `max_voxels` leaves
        beside the halo).
    progress : callable(done, total), optional
    solid_pieces : int, optional
        The solid's 6-connected pieces when the caller knows them (a run's passes counted them):
        the fragments are then those but one, and the solid is not labelled here.

    Returns
    -------
    dict
        The keys of :func:`morphometry` but ``porosity_voxel`` and the surface's, and
        ``morphometry_halo_planes``: the halo the thicknesses were measured with.
    """
    from ..run.tiles import SlabComponents

    nx, ny, nz = (int(n) for n in source.grid.shape)
    h = float(voxel)
    plane = ny * nz

    def ranges(width):
        owned = int(planes) if planes else max(1, int(max_voxels) // plane - 2 * width)
        return [(x0, min(x0 + owned, nx)) for x0 in range(0, nx, owned)]

    halo = max(1, int(halo))
    out: dict = {}
    while True:
        if not planes and (1 + 2 * halo) * plane > max_voxels and nx > 1 + 2 * halo:
            # the thinnest slab with its halo does not fit: the topology is still measured
            out["morphometry"] = (f"strut thickness and pore diameter not measured: a slab with its halo of {halo} "
                                  f"planes needs {(1 + 2 * halo) * plane * SLAB_MORPHOMETRY_BYTES_PER_VOXEL / 2**30:.2f}"
                                  " GiB, over what --max-memory leaves; raise --max-memory")
            strut = pore = None
            break
        strut, pore = ThicknessTally(h), ThicknessTally(h)
        spans = ranges(halo)
        for done, (x0, x1) in enumerate(spans, 1):
            lo, hi = max(0, x0 - halo), min(nx, x1 + halo)
            solid = source.read(lo, hi) < 0
            void = (patient.read(lo, hi) < 0) & ~solid
            own = slice(x0 - lo, x1 - lo)
            strut.add(local_thickness(solid, h)[own], solid[own])
            pore.add(local_thickness(void, h)[own], void[own])
            del solid, void
            if progress is not None:
                progress(done, len(spans))
        if max(strut.max_voxels, pore.max_voxels) <= halo or len(spans) == 1:
            break
        halo = max(2 * halo, int(math.ceil(max(strut.max_voxels, pore.max_voxels))) + 2)
    out["strut_thickness_mm"] = None if strut is None else strut.stats()
    out["pore_diameter_mm"] = None if pore is None else pore.stats()
    solids = SlabComponents() if solid_pieces is None else None
    opens = SlabComponents()
    n_region = chi = 0
    for x0, x1 in ranges(0):
        # one read serves the Euler characteristic (with the plane before the slab, as
        # euler_characteristic_by_slabs counts it) and the pieces (the owned planes)
        lo = max(x0 - 1, 0)
        both = source.read(lo, x1) < 0
        chi += euler_characteristic(both) - (euler_characteristic(both[:1]) if lo < x0 else 0)
        solid = both[x0 - lo:]
        region = patient.read(x0, x1) < 0
        n_region += int(np.count_nonzero(region))
        if solids is not None:
            solids.add(solid)
        # the void and the outside together; the outside (beyond the region) opens its piece
        opens.add(~solid, opens=~region & ~solid, tally=region & ~solid)
    if n_region == 0:
        raise ScaffoldError("the region holds no voxel; nothing to measure")
    out["euler_characteristic"] = chi
    out["connectivity_density_per_mm3"] = (1 - chi) / (n_region * h ** 3)
    opens.finish()
    reached, total = opens.open_tally()
    out["interconnected_porosity"] = reached / total if total else None
    out["fragments"] = solids.finish() if solids is not None else max(int(solid_pieces) - 1, 0)
    out["morphometry_halo_planes"] = halo
    return out


# --------------------------------------------------------------------------- meshes to voxels

#: the rays are moved off the grid by this fraction of a voxel (irrational steps), so that
#: they do not pass exactly through the vertices of meshes built on the same grid
_RAY_SHIFT = (math.sqrt(2) * 1e-6, math.sqrt(3) * 1e-6)


#: faces :func:`voxelize` hands to the crossings at a time (some 30 MiB of their arrays)
VOXELIZE_FACES = 1 << 18


def voxelize(vertices, faces, grid) -> np.ndarray:
    """Which voxel centres of `grid` lie inside a closed triangle mesh (ray parity along z).

    The crossings are the patient's (:func:`~implicit_scaffold.fields.patient_mesh.crossings`,
    whose shared-edge test counts a ray through an edge once): one voxelizer for both.

    Parameters
    ----------
    vertices : (nv, 3) float ndarray, mm
    faces : (nf, 3) int ndarray
        A closed mesh whose shared vertices are shared indices (as trimesh merges them).
    grid : Grid

    Returns
    -------
    (nx, ny, nz) bool ndarray

    Raises
    ------
    ScaffoldError
        Some ray crosses the surface an odd number of times: the mesh is not closed.
    """
    from ..fields.patient_mesh import crossings

    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    nx, ny, nz = (int(n) for n in grid.shape)
    h, o = float(grid.spacing), np.asarray(grid.origin, np.float64)
    # the rays pass a hair beside the voxel centres: a mesh marched on this very grid has its
    # vertices on the lines through the centres, where a ray would meet them exactly. A block of
    # faces at a time: crossings holds some 115 bytes a face it is given (the default cube's 5.2 M
    # faces took 580 MiB at once), and the parity below does not depend on the crossings' order
    found = [crossings(v, f[f0:f0 + VOXELIZE_FACES], 2, o[0] - _RAY_SHIFT[0] * h, h, nx,
                       o[1] - _RAY_SHIFT[1] * h, h, ny) for f0 in range(0, len(f), VOXELIZE_FACES)]
    col = np.concatenate([c for c, _ in found]) if found else np.zeros(0, np.int64)
    z = np.concatenate([t for _, t in found]) if found else np.zeros(0)
    del found
    if not len(col):
        return np.zeros(grid.shape, bool)
    odd_cols = np.count_nonzero(np.bincount(col, minlength=nx * ny) % 2)
    if odd_cols:
        raise ScaffoldError(f"the mesh is not closed: {odd_cols} of {nx * ny} rays cross its surface an odd "
                            "number of times; repair it (fill its holes) and try again")
    # the first centre above each crossing flips the parity from there up
    k = np.clip(np.ceil((z - o[2]) / h).astype(np.int64), 0, nz)
    uniq, mult = np.unique(col * (nz + 1) + k, return_counts=True)
    toggle = np.zeros((nx * ny, nz + 1), np.uint8)
    toggle.reshape(-1)[uniq[mult % 2 == 1]] = 1
    inside = np.bitwise_xor.accumulate(toggle[:, :nz], axis=1).astype(bool)
    return inside.reshape(nx, ny, nz)


# --------------------------------------------------------------------------- analysing a file

from ..io.formats import IMAGE_STACKS, MESH_READERS as MESH_SUFFIXES, VOLUME_READERS  # noqa: E402
from ..io.formats import suffix as _suffix  # noqa: E402

VOLUME_SUFFIXES = VOLUME_READERS + IMAGE_STACKS
#: bytes per voxel the measures hold at their peak (distance transform, sphere pointers,
#: thickness map, labels, masks)
ANALYSIS_BYTES_PER_VOXEL = 24


class Analysis:
    """What :func:`analyze_file` measured: ``report`` (dict), ``solid`` (bool volume),
    ``grid`` (:class:`~implicit_scaffold.run.grid.Grid`, cubic voxels) and ``mesh`` (the input
    mesh, or None for a volume)."""

    def __init__(self, report, solid, grid, mesh=None):
        self.report, self.solid, self.grid, self.mesh = report, solid, grid, mesh




def load_region(path):
    """The region that porosity is counted in: a patient file, or a run's JSON report.

    Parameters
    ----------
    path : str or Path
        A patient mesh or volume (as ``--patient`` takes), or the JSON report that
        ``generate`` wrote beside a scaffold (its patient is loaded again with the same
        options, and its grid is the run's).

    Returns
    -------
    patient
        Anything with ``lo``, ``hi``, ``volume`` and ``sdf_grid``.
    grid : Grid or None
        The run's grid (a JSON report), else None.
    what : str
        The region in words, for the report.
    """
    import json
    from pathlib import Path

    path = Path(path)
    if not path.exists():
        raise ScaffoldError(f"--region {path} does not exist; give the patient file or the run's .json report")
    if path.suffix.lower() != ".json":
        from ..io.patient_io import load_patient

        patient = load_patient(path)
        return patient, None, f"the patient {path.name}"
    try:
        run = json.loads(path.read_text())
        source = run["patient_source"]
        grid = run_grid(run)
    except (ValueError, KeyError, TypeError):
        raise ScaffoldError(f"--region {path.name} is not a report written by generate (it names no patient); "
                            "give the patient file instead") from None
    if source is None:
        raise ScaffoldError(f"--region {path.name}: that run's patient was a Python object, not a file or a "
                            "built-in shape; give the patient file instead")
    if "shape" in source:
        from ..fields.patient import primitive

        return primitive(source["shape"], source["size"]), grid, f"the patient of {path.name} ({source['shape']})"
    from ..io.patient_io import load_patient

    patient = load_patient(source["file"], label=source.get("label"), threshold=source.get("threshold"),
                           units=source.get("units"), clip=source.get("clip"), cut_planes=source.get("cut_planes"),
                           spacing=source.get("spacing"))
    return patient, grid, f"the patient of {path.name} ({Path(source['file']).name})"


def analyze_file(path, *, voxel=None, spacing=None, region=None, label=None, threshold=None,
                 max_memory: int | None = None) -> Analysis:
    """Voxel morphometry of a scaffold mesh or a volume file (binary, a label map or a CT).

    Parameters
    ----------
    path : str or Path
        A closed mesh (.stl .ply .obj .3mf .off), voxelised at `voxel` (a voxel is solid
        when its centre is inside); or a binary volume (.nrrd .nhdr .nii .nii.gz .mha .mhd,
        a multi-page .tif, or a folder of .tif slices): solid is every non-zero voxel.
    voxel : float, mm
        Needed for a mesh. For a volume, optional: it is resampled to this size (nearest
        voxel); by default the volume's own spacing is kept (an anisotropic one is
        resampled to its finest step).
    spacing : float or (3,) floats, mm, optional
        The volume's voxel spacing (x, y, z), for files that carry none (TIFF, NRRD
        without one); overrides the file's.

    label, threshold : optional
        Volume only: its solid is this segmentation label, or the intensities at or above this
        (HU, for a CT), as ``generate`` chooses a patient (:func:`_read_volume`); a volume of more
        than two values needs one of them.
    region : str or Path, optional
        Mesh only: count porosity inside this patient (a mesh or volume file, or the JSON
        report of the run that built the scaffold: its patient, on its grid), as generate
        does. By default the region is the mesh's bounding box (the report says so).
    max_memory : int, optional
        Bytes the run may hold: a binary STL's read, and the measures on the grid, are checked against it
        before the work (:data:`ANALYSIS_MEMORY`), and refused in one line that names the budget (and where
        the voxel can be chosen, the voxel) that would do.

    Returns
    -------
    Analysis
        For a mesh the region measured is `region`, else the mesh's bounding box; for a
        field generate wrote (``.npy`` or a volume format), its run's patient (:func:`run_region`,
        the report beside it), else its grid; for any other volume, the whole volume. Area and BS/BV come from the mesh itself (or a
        marching-cubes mesh of a volume); a mesh's ``bodies`` are its closed components,
        counted as generate counts them.
    """
    from pathlib import Path

    from .. import __version__
    from ..run.grid import Grid
    from ..run.memory import check_memory

    path = Path(path)
    if voxel is not None:
        voxel = positive_mm("voxel", voxel)
    if not path.exists():
        raise ScaffoldError(f"{path} does not exist; check the path")
    suffix = _suffix(path)
    if path.is_dir() or suffix in VOLUME_SUFFIXES:
        if region is not None:
            raise ScaffoldError("--region applies to a scaffold mesh; a volume is measured whole (a field generate "
                                "wrote: over its run's patient, from the report beside it)")
        if spacing is not None and suffix in MESH_SUFFIXES:
            raise ScaffoldError("--spacing applies to a volume; a mesh is voxelised at --voxel")
        # generate's own field (its report beside it) over its run's patient, as read_scaffold reads it for check
        scaffold = read_scaffold(path, voxel=voxel, spacing=spacing, label=label, threshold=threshold,
                                 max_memory=max_memory, work=ANALYSIS_MEMORY)
        solid, step = scaffold.solid, scaffold.voxel
        grid = Grid(scaffold.origin, step, solid.shape)  # where the file places its voxels (read_scaffold's)
        check_memory(grid, ANALYSIS_BYTES_PER_VOXEL)
        report = morphometry(solid, step, region=scaffold.region)
        report.update({"version": __version__, "source": path.name, "kind": "volume", "voxel_mm": step, "grid_shape": list(solid.shape),
                       "region": scaffold.region_name, "resampled": scaffold.resampled, "selection": scaffold.selection,
                       "axes": scaffold.axes})
        return Analysis(report, solid, grid)
    if suffix == ".npy":
        if region is not None:
            raise ScaffoldError("--region applies to a scaffold mesh; a .npy field is measured over its run's patient "
                                "(the report beside it), else its grid")
        if spacing is not None:
            raise ScaffoldError("--spacing applies to a volume; a .npy field's voxel comes from its report or --voxel")
        scaffold = read_scaffold(path, voxel=voxel, label=label, threshold=threshold, max_memory=max_memory,
                                 work=ANALYSIS_MEMORY)
        grid = Grid(scaffold.origin, scaffold.voxel, scaffold.solid.shape)
        check_memory(grid, ANALYSIS_BYTES_PER_VOXEL)
        # over the region read_scaffold names (its run's patient, when its report is beside it), not the grid
        report = morphometry(scaffold.solid, scaffold.voxel, region=scaffold.region)
        report.update({"version": __version__, "source": path.name, "kind": "field", "voxel_mm": scaffold.voxel,
                       "grid_shape": list(scaffold.solid.shape), "region": scaffold.region_name,
                       "selection": "the signed distance below 0"})
        return Analysis(report, scaffold.solid, grid)
    if suffix not in MESH_SUFFIXES:
        raise ScaffoldError(f"cannot analyse {path.name}: use a mesh ({' '.join(MESH_SUFFIXES)}), a .npy field or a "
                            f"volume ({' '.join(VOLUME_SUFFIXES)}, or a folder of TIFF slices)")
    if spacing is not None:
        raise ScaffoldError("--spacing applies to a volume; a mesh is voxelised at --voxel")
    _volume_only(path, label, threshold)
    patient = run_grid = None
    if region is not None:
        patient, run_grid, what = load_region(region)
    # the run's grid from the report beside the mesh, also under a patient given as a mesh or volume (its voxel was
    # asked for again, and a grid placed from the patient's bounds broke walls a voxel thick)
    beside = run_grid_beside(path, voxel) if run_grid is None else None
    # the arrays, not a trimesh: a binary STL read by numpy, and the measures and bodies from them (trimesh's mesh
    # of the default cube's 5.2 M triangles and its caches took the run to a 3.4 GB peak)
    triangles = binary_stl_triangles(path) if max_memory is not None else None
    planned = None  # the grid checked before the read
    if triangles:
        from ..run.memory import release

        held = release()
        # the grid's voxels: the report beside the mesh gives it, or (no patient's grid) the file's bounds and the
        # voxel asked for
        planned = planned_mesh_grid(path, triangles, beside, voxel if patient is None else None)
        if planned is not None:
            voxels = int(np.prod(planned.shape))
            check_measure_memory(ANALYSIS_MEMORY, path.name, planned.shape, float(planned.spacing), held,
                                 max_memory, coarser=planned is not beside,
                                 read=held + mesh_read_memory(triangles, voxels))
        else:
            check_mesh_read(path.name, triangles, 0, held, max_memory)
    mesh = SurfaceArrays(*read_mesh_arrays(path))
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    if voxel is None and run_grid is None and beside is None:
        raise ScaffoldError(_voxel_needed(lo, hi))
    if patient is None:
        grid = beside if beside is not None else Grid.covering(lo, hi, voxel)
        voxel = grid.spacing
    else:
        # the run's own grid when no other voxel is asked (the region's JSON, or the report beside the mesh): voxel
        # centres classified as generate's were
        own = beside if run_grid is None else (run_grid if voxel is None else None)
        grid = own if own is not None else Grid.covering(patient.lo, patient.hi, voxel)
        voxel = grid.spacing
    if max_memory is not None and (planned is None or planned.shape != grid.shape):
        from ..run.memory import process_memory

        read = held + mesh_read_memory(triangles, int(np.prod(grid.shape))) if triangles else 0
        check_measure_memory(ANALYSIS_MEMORY, path.name, grid.shape, float(voxel), process_memory(), max_memory,
                             coarser=grid is not beside and (patient is None or grid is not run_grid), read=read)
    check_memory(grid, ANALYSIS_BYTES_PER_VOXEL)
    solid = voxelize(mesh.vertices, mesh.faces, grid)
    if patient is None:
        inside = np.zeros(grid.shape, bool)
        inside[1:-1, 1:-1, 1:-1] = True  # the bounding box: all but the outer layer
        what, region_volume = "the mesh's bounding box (give --region for the patient)", float(np.prod(hi - lo))
    else:
        inside = np.asarray(patient.sdf_grid(grid)) < 0
        region_volume = float(patient.volume)
    if not solid.any():
        raise ScaffoldError(f"no voxel centre of {path.name} lies inside it at --voxel {voxel:g}; "
                            "use a smaller --voxel")
    from ..mesh.marching import face_measures, mesh_summary

    areas, volumes = face_measures(mesh.vertices, mesh.faces)
    area, volume = float(areas.sum()), float(volumes.sum())
    del areas, volumes
    report = morphometry(solid, voxel, region=inside, surface_area_mm2=area, solid_volume_mm3=volume)

    report.update({"version": __version__, "source": path.name, "kind": "mesh", "voxel_mm": float(voxel),
                   "grid_shape": list(grid.shape), "region": what, "region_volume_mm3": region_volume,
                   "triangles": int(len(mesh.faces)), "bodies": mesh_summary(mesh)["bodies"],
                   "mesh_volume_mm3": volume, "porosity_mesh": 1.0 - volume / region_volume})
    if patient is None:
        report["box_volume_mm3"] = region_volume
    return Analysis(report, solid, grid, mesh)



@dataclass(frozen=True, eq=False)
class SurfaceArrays:
    """A closed triangle mesh as its arrays (:func:`read_mesh_arrays`): ``vertices`` (nv, 3) float64, mm, and
    ``faces`` (nf, 3) int64, outward; what the measures, the body count and the pictures read of a mesh."""

    vertices: np.ndarray
    faces: np.ndarray


@dataclass(frozen=True)
class Scaffold:
    """A scaffold read from a file: its voxels and what they came from (lengths in mm).

    ``kind`` is ``"field"``, ``"volume"`` or ``"mesh"``; ``field`` is the signed distance of a
    ``.npy`` field (else None); ``region`` where the scaffold is (None: the whole grid);
    ``exact_distance`` whether ``field`` is a true distance near its surface (a mesh's), not a
    blended field such as generate writes."""

    kind: str
    solid: np.ndarray
    voxel: float
    origin: tuple
    field: np.ndarray | None
    region: np.ndarray | None
    region_name: str
    selection: str | None = None  # a volume's: how its solid was chosen (bone_mask's phrase)
    resampled: str | None = None  # a volume's resampling to another voxel (its note), or None
    axes: str | None = None  # a volume's index axes put on the world's x, y, z (world_axes' note), or None

    @property
    def exact_distance(self) -> bool:
        """Whether `field` is a true signed distance near its surface: a mesh's point-triangle distances."""
        return self.kind == "mesh"


def run_grid(run: dict):
    """The grid of a run from its JSON report's ``grid_origin_mm``, ``voxel_mm`` and ``grid_shape`` (KeyError,
    TypeError or ValueError where the report lacks them)."""
    from ..run.grid import Grid

    return Grid(tuple(float(v) for v in run["grid_origin_mm"]), float(run["voxel_mm"]),
                tuple(int(v) for v in run["grid_shape"]))


def report_beside(path) -> dict | None:
    """The JSON report generate wrote beside its output `path` (``f.stl`` -> ``f.json``, ``f.nii.gz`` ->
    ``f.json``), as a dict; None when there is none or it cannot be read."""
    import json

    from ..io.formats import report_path

    meta = report_path(path)
    if not meta.is_file():
        return None
    try:
        report = json.loads(meta.read_text())
    except (OSError, ValueError):
        return None
    return report if isinstance(report, dict) else None


def run_region(path, grid, otherwise: str, *, build: bool = True) -> tuple[np.ndarray | None, str]:
    """The region the run that wrote `path` measured: its patient's voxels on `grid`, and its name.

    From the JSON report beside `path` (:func:`report_beside`), whose patient is built again as
    ``analyze --region`` builds it (:func:`load_region`), when that report's grid is `grid`
    (origin, voxel and shape): generate counted porosity, drainage and the pores inside the
    patient, so a run's mesh, ``.npy`` field and volume field are measured over the same voxels.

    Parameters
    ----------
    path : str or Path
        The scaffold file (mesh, ``.npy`` or volume field) generate wrote.
    grid : Grid
        The grid the scaffold's voxels lie on (mm).
    otherwise : str
        The region's name when the run's patient is not used (the caller's region then).
    build : bool
        False: only whether the run's patient would be used, as an empty region (a reader that measures no
        region, the stiffness solve, need not build the patient again: a CT is segmented anew).

    Returns
    -------
    region : (nx, ny, nz) bool ndarray or None
        The patient's voxels (signed distance below 0); None when there is no such report, it is
        another grid's, or its patient was a Python object.
    name : str
        The region in words, for the report.

    Warns
    -----
    ScaffoldWarning
        The report names a patient file that cannot be read again: the region is then `otherwise`.
    """
    report = report_beside(path)
    if report is None or report.get("patient_source") is None:
        return None, otherwise
    try:
        own = run_grid(report)
    except (KeyError, TypeError, ValueError, ScaffoldError):
        return None, otherwise
    if (tuple(own.shape) != tuple(int(n) for n in grid.shape)
            or not math.isclose(own.spacing, float(grid.spacing), rel_tol=1e-6)  # a float32 header's spacing
            or not np.allclose(own.origin, grid.origin, rtol=0, atol=1e-6 * own.spacing)):
        # another voxel (--voxel) or another run's report: its patient would not lie on these voxels
        return None, otherwise
    if not build:
        return np.zeros(0, bool), otherwise
    from ..io.formats import report_path

    try:
        patient, _, what = load_region(report_path(path))
    except ScaffoldError as exc:
        import warnings

        warnings.warn(f"the run's patient could not be built again ({exc}); measured over {otherwise} instead",
                      ScaffoldWarning, stacklevel=3)
        return None, otherwise
    return np.asarray(patient.sdf_grid(grid)) < 0, what


def run_grid_beside(path, voxel=None):
    """The grid of the run that wrote the mesh `path`, from the JSON report generate wrote beside it
    (``<stem>.json``: ``grid_origin_mm``, ``voxel_mm``, ``grid_shape``), when there is one and `voxel` is
    None or that run's voxel; else None.

    Voxelised on its own run's grid, a mesh gives back that run's solid: marching cubes' surface
    passes between voxel centres of opposite signs, so each centre keeps its side. On a grid of the
    same voxel placed from the mesh's bounds, centres fall elsewhere and walls a voxel or two thick
    break: ``check`` of an L3 scaffold at its own 0.6 mm voxel found 410 floating pieces and 63
    sealed voids where generate's own check found none.
    """
    report = report_beside(path)
    if report is None:
        return None
    try:
        grid = run_grid(report)
    except (ValueError, KeyError, TypeError, ScaffoldError):
        return None
    if voxel is not None and not math.isclose(float(voxel), grid.spacing, rel_tol=1e-9):
        return None
    return grid


def read_scaffold(path, *, voxel=None, spacing=None, label=None, threshold=None, mesh_field: bool = False,
                  region: bool = True, max_memory: int | None = None, work: MeasureMemory | None = None) -> Scaffold:
    """Read a scaffold as voxels: a closed mesh (voxelised at `voxel`), a ``.npy`` signed distance
    written by ``generate`` (the run's JSON beside it gives the voxel, origin and patient), or a
    volume: binary (solid = non-zero), or a label map's `label` or a CT's intensities from
    `threshold` (HU) up (:func:`_read_volume`).

    The region (the void that counts) is the patient of the run that wrote the file, when its report
    beside it names one and the file lies on that run's grid (:func:`run_region`: the region generate
    measured, so that a run's mesh, ``.npy`` and volume field give the same figures); else the mesh's
    bounding box, the volume, or for a field the grid (its voxels outside the patient are then void
    that joins the outside, as they do on the printer). With `mesh_field`, a mesh's ``field`` is its
    signed distance on the grid (exact near the surface: the print check's as-built offset, a fraction
    of a voxel, and its surface normals come from it; without it a printer's deviation under a voxel
    moved nothing).

    With `max_memory` (bytes), a binary STL's read and voxels are checked against it before the work
    (:func:`check_mesh_read`): before the file is read, and once its bounds give the grid. With `work` too,
    the measure that follows is (:func:`check_measure_memory`): a mesh's with its read, once its grid is known,
    a field's or a volume's once it is read, before the measure.
    """
    from pathlib import Path

    from ..run.grid import Grid

    path = Path(path)
    if not path.exists():
        raise ScaffoldError(f"{path} does not exist; check the path")
    if voxel is not None:
        voxel = positive_mm("voxel", voxel)
    suffix = _suffix(path)
    if spacing is not None and (suffix == ".npy" or suffix in MESH_SUFFIXES):
        # taken without a word, it changed nothing
        raise ScaffoldError(f"--spacing applies to a volume; {path.name} is "
                            + ("a .npy field, whose voxel comes from its report beside it or --voxel" if suffix == ".npy"
                               else "a mesh, voxelised at --voxel"))
    if suffix == ".npy":
        _volume_only(path, label, threshold)
        try:
            field = np.load(path, mmap_mode="r")
        except ValueError as exc:
            # numpy's own words advise loading pickled objects "unsafely"
            why = ("it holds Python objects, not numbers" if "pickle" in str(exc) or "objects" in str(exc)
                   else str(exc))
            raise ScaffoldError(f"cannot read {path.name} as a .npy field: {why}; give the .npy generate wrote") \
                from None
        except OSError as exc:
            raise ScaffoldError(f"cannot read {path.name} as a .npy field: {exc}") from None
        if field.ndim != 3 or field.dtype.kind not in "fiu":
            raise ScaffoldError(f"{path.name} is not a 3-D signed distance (shape {field.shape}, {field.dtype}); "
                                "give the .npy that generate wrote")
        report = report_beside(path) or {}
        voxel = voxel or report.get("voxel_mm")
        origin = tuple(report.get("grid_origin_mm", (0.0, 0.0, 0.0)))
        if voxel is None:
            raise ScaffoldError(f"{path.name} carries no voxel size and no run report beside it; give --voxel")
        if max_memory is not None and work is not None:
            from ..run.memory import release

            check_measure_memory(work, path.name, field.shape, float(voxel), release(), max_memory, coarser=False)
        field = np.asarray(field, np.float32)
        bad = int(field.size - np.count_nonzero(np.isfinite(field)))
        if bad:
            # NaN compares as not negative: it was read as void without a word
            raise ScaffoldError(f"{path.name} holds {bad:,} non-finite values (NaN or inf); a signed distance is "
                                "finite everywhere: write the field again")
        where, name = run_region(path, Grid(origin, float(voxel), field.shape), "the grid", build=region)
        return Scaffold("field", field < 0, float(voxel), origin, field, where if region else None, name)
    if path.is_dir() or suffix in VOLUME_SUFFIXES:
        solid, step, note, selection, distance, axes, origin = _read_volume(path, spacing, voxel, label, threshold)
        where, name = None, "the whole volume"
        if max_memory is not None and work is not None:
            from ..run.memory import release

            check_measure_memory(work, path.name, solid.shape, float(step), release(), max_memory, coarser=True)
        if distance is not None:
            # generate's own field (:func:`_own_field`): its voxels are its run's grid, placed by the report
            own = tuple((report_beside(path) or {}).get("grid_origin_mm", origin))
            where, name = run_region(path, Grid(own, step, solid.shape), name, build=region)
            origin = own if where is not None else origin
        return Scaffold("volume", solid, step, origin, distance, where if region else None, name, selection, note,
                        axes=axes)
    if suffix not in MESH_SUFFIXES:
        raise ScaffoldError(f"cannot read {path.name}: use a mesh ({' '.join(MESH_SUFFIXES)}), a .npy field or a "
                            f"volume ({' '.join(VOLUME_SUFFIXES)})")
    _volume_only(path, label, threshold)
    run_grid = run_grid_beside(path, voxel)
    triangles = binary_stl_triangles(path) if max_memory is not None else None
    planned = None  # the grid checked before the read
    if triangles:
        from ..run.memory import release

        held = release()
        # the grid's voxels: the run's report gives it, or the file's bounds and the voxel asked for
        planned = planned_mesh_grid(path, triangles, run_grid, voxel)
        voxels = 0 if planned is None else int(np.prod(planned.shape))
        if work is not None and planned is not None:
            check_measure_memory(work, path.name, planned.shape, float(planned.spacing), held, max_memory,
                                 coarser=run_grid is None, read=held + mesh_read_memory(triangles, voxels, work))
        else:
            check_mesh_read(path.name, triangles, voxels, held, max_memory, work)
    vertices, faces = read_mesh_arrays(path)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    if voxel is None and run_grid is None:
        raise ScaffoldError(_voxel_needed(lo, hi))
    # its layer of outside all round: the scaffold's faces open onto free space (the run's grid has one)
    grid = run_grid if run_grid is not None else Grid.covering(lo, hi, voxel)
    voxel = grid.spacing
    # the check before the read holds where the file's bounds gave this grid
    unchecked = planned is None or planned.shape != grid.shape
    if unchecked and max_memory is not None and work is not None:
        from ..run.memory import release

        voxels = int(np.prod(grid.shape))
        if triangles:
            read, now = held + mesh_read_memory(triangles, voxels, work), held
        else:
            # a mesh of another format, its triangles counted once read: what its voxels and the measure's
            # triangles still take, beside what the process holds now (the mesh read)
            now = release()
            read = now + mesh_read_memory(len(faces), voxels, work) - MESH_READ_BYTES_PER_TRIANGLE * len(faces)
        check_measure_memory(work, path.name, grid.shape, float(voxel), now, max_memory, coarser=run_grid is None,
                             read=read)
    elif unchecked and triangles and run_grid is None:
        check_mesh_read(path.name, triangles, int(np.prod(grid.shape)), held, max_memory, work)
    solid = voxelize(vertices, faces, grid)
    if not solid.any():
        raise ScaffoldError(f"no voxel centre of {path.name} lies inside it at --voxel {voxel:g}; use a smaller --voxel")
    where = None
    if run_grid is not None and region:
        where, name = run_region(path, grid, "the mesh's bounding box")
    if where is None:
        pts = [grid.origin[a] + grid.spacing * np.arange(grid.shape[a]) for a in range(3)]
        inside = [(p >= lo[a]) & (p <= hi[a]) for a, p in enumerate(pts)]
        where = inside[0][:, None, None] & inside[1][None, :, None] & inside[2][None, None, :]
        name = "the mesh's bounding box"
    field = None
    if mesh_field:
        from ..fields.patient_mesh import MeshPatient

        field = np.asarray(MeshPatient(vertices, faces, name=path.name).sdf_grid(grid), np.float32)
    return Scaffold("mesh", solid, float(voxel), tuple(grid.origin), field, where, name)


#: the voxels along a mesh's longest side that the suggestion of :func:`_voxel_needed` gives
SUGGESTED_VOXELS_ALONG = 200


def _voxel_needed(lo, hi) -> str:
    """The one line that asks for a mesh's --voxel, with a suggestion from its size (the example was 0.04 mm
    whatever the mesh: 12,000 voxels along a femur)."""
    longest = float(np.max(np.asarray(hi, float) - np.asarray(lo, float)))
    example = round_down(longest / SUGGESTED_VOXELS_ALONG) if np.isfinite(longest) and longest > 0 else "0.04"
    return (f"a mesh is voxelised at --voxel H; give one, e.g. --voxel {example} (mm: {SUGGESTED_VOXELS_ALONG} "
            f"voxels along its longest side, {longest:.4g} mm; a scaffold's struts want 4 voxels across)")


def _volume_only(path, label, threshold) -> None:
    """A one-line error when `label` or `threshold` comes with a file that is not a volume."""
    if label is not None or threshold is not None:
        raise ScaffoldError(f"--label and --threshold choose a volume's solid; {path.name} is not a volume "
                            "(a mesh or a .npy field is solid where it is closed or negative)")


#: bytes of a binary STL's header (80) and triangle count (4), and of each triangle's record (normal, three
#: float32 corners, a 2-byte attribute)
STL_HEAD_BYTES, STL_RECORD_BYTES = 84, 50
#: triangles read from a binary STL at a time (50 MB of records)
STL_READ_CHUNK = 1 << 20


def binary_stl_triangles(path) -> int | None:
    """The triangles of a binary STL, from its header: None when `path` is not one (another format, an ASCII
    STL, or a size that its count does not give, as trimesh tells them apart)."""
    from pathlib import Path

    path = Path(path)
    if _suffix(path) != ".stl" or not path.is_file():
        return None
    size = path.stat().st_size
    if size < STL_HEAD_BYTES:
        return None
    with open(path, "rb") as fh:
        fh.seek(80)
        n = int(np.frombuffer(fh.read(4), "<u4")[0])
    return n if size == STL_HEAD_BYTES + STL_RECORD_BYTES * n else None


def binary_stl_bounds(path, n: int):
    """The lowest and highest corner (two (3,) float64 arrays, mm) of a binary STL of `n` triangles, read a chunk
    of :data:`STL_READ_CHUNK` records at a time (some 50 bytes a triangle of the chunk's): the grid a voxel
    gives, before the mesh is read. None when a corner is not finite or the file is short."""
    rec = np.dtype([("normal", "<f4", 3), ("corners", "<f4", (3, 3)), ("attr", "<u2")])
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    with open(path, "rb") as fh:
        fh.seek(STL_HEAD_BYTES)
        for f0 in range(0, n, STL_READ_CHUNK):
            k = min(STL_READ_CHUNK, n - f0)
            corners = np.fromfile(fh, rec, k)["corners"].reshape(-1, 3)
            if len(corners) != 3 * k or not np.isfinite(corners).all():
                return None
            lo, hi = np.minimum(lo, corners.min(axis=0)), np.maximum(hi, corners.max(axis=0))
    return (lo, hi) if n else None


def planned_mesh_grid(path, triangles: int, known, voxel):
    """The grid a binary STL of `triangles` will be voxelised on, known before it is read: `known` (a run's grid)
    when given, else the file's bounds (:func:`binary_stl_bounds`) covered at `voxel` (mm); None when neither
    gives one."""
    from ..run.grid import Grid

    if known is not None or voxel is None:
        return known
    bounds = binary_stl_bounds(path, triangles)
    return None if bounds is None else Grid.covering(*bounds, voxel)


def _group_rows(columns, count: int):
    """Equal rows of `columns` (1-D arrays of length `count`, one per coordinate): for each row its group
    (groups numbered in the rows' sorted order) and each group's first row (the lowest index: the sort is
    stable). Indices are int32 where `count` allows: 4 bytes a row where numpy's were 8."""
    index = np.int32 if count < 2**31 else np.int64
    order = np.lexsort(tuple(columns[::-1])).astype(index)
    new = np.zeros(count, bool)
    new[0] = True
    for c in columns:  # one column at a time: a sorted copy of all three was 12 bytes a row more
        col = c[order]
        new[1:] |= col[1:] != col[:-1]
        del col
    first = order[new]
    group = np.empty(count, index)
    group[order] = np.cumsum(new, dtype=index) - 1
    return group, first


def _read_binary_stl(path, n: int):
    """A binary STL's vertices (float64, mm) and faces (int64), merged as trimesh merges them, or None when a
    corner is not finite (trimesh then drops its faces: :func:`_read_mesh` reads it).

    trimesh held some 660 bytes a triangle at its peak while it read, merged and checked (3.2 GiB for the
    default cube's 5.2 M triangles): here the corners are 36 bytes a triangle (float32, as the file holds them),
    and the whole read and voxelisation at most :data:`MESH_READ_BYTES_PER_TRIANGLE`. trimesh's merge (``merge_vertices``): corners whose coordinates times 1e8, rounded,
    are equal are one vertex, the first of them in the file's order, and the vertices are in the order of their
    first corner. Equal float32 corners are merged first (exactly), then their distinct values by the rounded
    keys: the same vertices, in the same order, so the same voxels.
    """
    rec = np.dtype([("normal", "<f4", 3), ("corners", "<f4", (3, 3)), ("attr", "<u2")])
    pts = np.empty((3 * n, 3), np.float32)
    with open(path, "rb") as fh:
        fh.seek(STL_HEAD_BYTES)
        for f0 in range(0, n, STL_READ_CHUNK):
            k = min(STL_READ_CHUNK, n - f0)
            block = np.fromfile(fh, rec, k)
            if len(block) != k:
                return None
            pts[3 * f0:3 * (f0 + k)] = block["corners"].reshape(-1, 3)
            del block
    if not np.isfinite(pts).all():
        return None
    bits = pts.view(np.uint32)
    group, first = _group_rows([bits[:, a] for a in range(3)], len(pts))
    del bits
    exact = pts[first].astype(np.float64)
    del pts
    # the distinct corners, each at its first place in the file, merged by the rounded keys
    return _merged(exact, group.reshape(n, 3), position=first)


#: bytes of a 3MF's model XML parsed at a time (:func:`_read_3mf`): some 300,000 vertices
MODEL_CHUNK = 1 << 24
#: the XML outside a 3MF's vertex and triangle lists held at most (its head and tail: a few hundred bytes
#: as generate writes them)
MODEL_OUTSIDE_BYTES = 1 << 20


def _read_3mf(path):
    """A 3MF's one mesh, vertices (float64, mm) and faces (int64), read from its model's XML a chunk at a
    time (:data:`MODEL_CHUNK`); None when the file is anything else than one plain mesh in millimetres (several
    models, objects or build items, components, a transform, another unit, attributes in another order): trimesh
    reads those. Vertices whose coordinates times 1e8, rounded, are equal are merged, as trimesh merges them.

    trimesh parses the whole XML at once: on the 12.46 M triangles of a femur's scaffold (a 150 MB 3MF, 957 MB of
    XML) it held more than 24 GB and the process was killed; here the arrays and a chunk.
    """
    import re
    import zipfile

    try:
        archive = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError):
        return None
    vertex = re.compile(rb'<vertex\s+x="([^"]*)"\s+y="([^"]*)"\s+z="([^"]*)"\s*/>')
    triangle = re.compile(rb'<triangle\s+v1="(\d+)"\s+v2="(\d+)"\s+v3="(\d+)"\s*/>')
    lists = {b"vertices": (vertex, b"<vertex", np.float64, []), b"triangles": (triangle, b"<triangle", np.int64, [])}
    outside, inside, text = [], None, b""
    with archive:
        models = [n for n in archive.namelist() if n.lower().endswith(".model")]
        if len(models) != 1:
            return None
        with archive.open(models[0]) as fh:
            while True:
                data = fh.read(MODEL_CHUNK)
                text += data
                while True:
                    if inside is None:
                        # the XML before the next list (or the tail): the list's opening tag starts it
                        at = [(text.find(b"<" + k + b">"), k) for k in lists]
                        at = [(i, k) for i, k in at if i >= 0]
                        if not at:
                            break
                        i, inside = min(at)
                        outside.append(text[:i])
                        text = text[i + len(inside) + 2:]
                        continue
                    pattern, tag, dtype, blocks = lists[inside]
                    end = text.find(b"</" + inside + b">")
                    cut = end if end >= 0 else max(text.rfind(b"/>") + 2, 0)
                    body, text = text[:cut], text[cut:]
                    rows = pattern.findall(body)
                    if len(rows) != body.count(tag):
                        return None  # elements with other attributes, or in another order
                    if rows:
                        blocks.append(np.array(rows, "S").astype(dtype))
                    del body, rows
                    if end < 0:
                        break
                    text = text[len(inside) + 3:]
                    inside = None
                if sum(len(o) for o in outside) + (len(text) if inside is None else 0) > MODEL_OUTSIDE_BYTES:
                    return None
                if not data:
                    break
    outside = b"".join(outside) + text
    if (inside is not None or outside.count(b"<object") != 1 or outside.count(b"<item") != 1
            or b"<components" in outside or b"transform=" in outside
            or any(not lists[k][3] for k in lists)):
        return None
    unit = re.search(rb'<model[^>]*\bunit="([^"]*)"', outside)
    if unit is not None and unit.group(1) != b"millimeter":
        return None
    vertices = np.concatenate(lists[b"vertices"][3])
    faces = np.concatenate(lists[b"triangles"][3])
    del lists
    return _merged(vertices, faces)


def _merged(vertices: np.ndarray, faces: np.ndarray, position: np.ndarray | None = None):
    """An indexed mesh's vertices merged as trimesh merges them (coordinates times 1e8, rounded, equal: one
    vertex, the first in the file's order, numbered by it) and its faces renumbered; None when a coordinate is
    not finite or an index names no vertex (trimesh then reads the file, and says what is wrong).

    `position`, each vertex's place in the file (distinct), where that is not its row: the vertices are then
    numbered in its order (a binary STL's distinct corners, :func:`_read_binary_stl`)."""
    if not len(faces) or not np.isfinite(vertices).all() or faces.min() < 0 or faces.max() >= len(vertices):
        return None
    keys = np.round(vertices * 1e8).astype(np.int64)
    merged, first = _group_rows([keys[:, a] for a in range(3)], len(keys))
    del keys
    if position is None and len(first) == len(vertices):
        return vertices, faces
    place = np.arange(len(vertices)) if position is None else np.asarray(position, np.int64)
    rep = np.full(len(first), np.iinfo(np.int64).max, np.int64)
    np.minimum.at(rep, merged, place)
    # the row of each merged vertex's first place
    owner = np.empty(len(first), np.int64)
    hit = place == rep[merged]
    owner[merged[hit]] = np.flatnonzero(hit)
    rank = np.argsort(rep, kind="stable")
    number = np.empty(len(rank), np.int64)
    number[rank] = np.arange(len(rank))
    return vertices[owner[rank]], number[merged][faces]


def _read_ply(path):
    """A binary PLY as :func:`~implicit_scaffold.mesh.writers.write_mesh` writes it (float64 x y z, triangles
    as uchar/int lists), vertices and faces read by numpy and merged as trimesh merges them (:func:`_merged`);
    None for any other PLY (trimesh reads it). trimesh held some 650 bytes a triangle reading, merging and
    checking one (3.4 GB for the default cube's 5.2 M triangles)."""
    from ..mesh.writers import _PLY_FACE, _ply_layout

    try:
        head, nverts, nfaces = _ply_layout(path)
    except ScaffoldError:
        return None
    size = path.stat().st_size
    if size != head + 24 * nverts + _PLY_FACE.itemsize * nfaces:
        return None
    with open(path, "rb") as fh:
        fh.seek(head)
        vertices = np.fromfile(fh, "<f8", 3 * nverts).reshape(nverts, 3).astype(np.float64, copy=False)
        records = np.fromfile(fh, _PLY_FACE, nfaces)
    if np.any(records["n"] != 3):
        return None
    faces = records["v"].astype(np.int64)
    del records
    return _merged(vertices, faces)


#: bytes of an OBJ read at a time (:func:`_read_obj`)
OBJ_CHUNK = 1 << 24


def _read_obj(path):
    """An OBJ of vertices and triangles alone (``v x y z`` and ``f a b c`` lines, comments and blank lines
    beside them), read a chunk at a time (:data:`OBJ_CHUNK`) and merged as trimesh merges it; None for any other
    (normals, texture coordinates, faces of other polygons or with slashes, groups, materials: trimesh reads it).
    trimesh held some 580 bytes a triangle reading one (3.0 GB for the default cube's 5.2 M triangles)."""
    import re

    vertex = re.compile(rb"^v[ \t]+(\S+)[ \t]+(\S+)[ \t]+(\S+)[ \t]*\r?$", re.M)
    triangle = re.compile(rb"^f[ \t]+(\d+)[ \t]+(\d+)[ \t]+(\d+)[ \t]*\r?$", re.M)
    other = re.compile(rb"^(?:#[^\n]*|[ \t]*\r?)$", re.M)
    vblocks, fblocks, rest = [], [], b""
    with open(path, "rb") as fh:
        while True:
            data = fh.read(OBJ_CHUNK)
            text = rest + data
            cut = text.rfind(b"\n") + 1 if data else len(text)
            # the chunk's whole lines, without the last one's newline: each line then matches once at most
            body, rest = text[:cut - 1] if cut and text[cut - 1:cut] == b"\n" else text[:cut], text[cut:]
            del text
            if not body and data:
                continue
            v, f = vertex.findall(body), triangle.findall(body)
            if len(v) + len(f) + len(other.findall(body)) != body.count(b"\n") + 1:
                return None  # some line is neither a vertex, a triangle, a comment nor blank
            try:
                if v:
                    vblocks.append(np.array(v, "S").astype(np.float64))
                if f:
                    fblocks.append(np.array(f, "S").astype(np.int64) - 1)
            except ValueError:
                return None
            del body, v, f
            if not data:
                break
    if not vblocks or not fblocks:
        return None
    return _merged(np.concatenate(vblocks), np.concatenate(fblocks))


def _watertight(faces: np.ndarray, nverts: int) -> bool:
    """Whether every edge of `faces` belongs to exactly two of them (trimesh's ``is_watertight``), with one
    8-byte key an edge (trimesh's edges, sorted and grouped, held some 120 bytes a triangle)."""
    n = len(faces)
    key = np.empty(3 * n, np.int64)
    for e in range(3):
        a, b = faces[:, e], faces[:, (e + 1) % 3]
        key[e * n:(e + 1) * n] = np.minimum(a, b) * nverts + np.maximum(a, b)
    key.sort()
    if len(key) % 2:
        return False
    # in pairs, and no three alike: each pair differs from the next
    return bool(np.array_equal(key[0::2], key[1::2]) and not np.any(key[1:-1:2] == key[2::2]))


#: what reading a binary STL and voxelising it holds at most beyond what the process held before: a fixed
#: part (the crossings' compiled kernel and the imports it brings, 145 MiB of a small mesh's 147), bytes a
#: triangle (the read's sort and merge; the mesh then held), bytes a triangle of one block of the crossings
#: (:data:`VOXELIZE_FACES`: the kernel compiles while the mesh and the block are held) and bytes a voxel of the
#: grid. Measured in a fresh process (``peak_memory`` less what it held before), against these bounds: the
#: default cube's 5.2 M triangles on its run's 7.4 M voxels 514 MiB (bound 629), on 65 M voxels
#: (``--voxel 0.025``) 768 (959); a 1.3 M-triangle ball on 1.1 M voxels 260 (296), on 38 M 333 (507); the
#: 3 mm cube's 152 k triangles, 147 (190).
MESH_READ_FIXED_BYTES = 160 * 2**20
MESH_READ_BYTES_PER_TRIANGLE = 80
MESH_READ_BYTES_PER_CROSSED_FACE = 120
MESH_READ_BYTES_PER_VOXEL = 6


def mesh_read_memory(triangles: int, voxels: int, work: "MeasureMemory | None" = None) -> int:
    """Bytes reading a binary STL of `triangles` and voxelising it on `voxels` holds at most beyond what the
    process held (:data:`MESH_READ_FIXED_BYTES` and the rest: an upper bound of the peaks measured); with
    `work`, also what the measure after the read holds while the triangles are kept (its
    ``bytes_per_triangle``)."""
    n = int(triangles)
    extra = 0 if work is None else work.bytes_per_triangle * n
    return int(MESH_READ_FIXED_BYTES + MESH_READ_BYTES_PER_TRIANGLE * n + extra
               + MESH_READ_BYTES_PER_CROSSED_FACE * min(n, VOXELIZE_FACES) + MESH_READ_BYTES_PER_VOXEL * int(voxels))


@dataclass(frozen=True)
class MeasureMemory:
    """What a measure of a scaffold read by :func:`read_scaffold` holds, for its budget (:func:`check_measure_memory`).

    Attributes
    ----------
    what : str
        The measure in words ("the print check").
    fixed : int
        Bytes the process holds at the measure's peak beside its arrays (the libraries it loads).
    bytes_per_voxel : int
        Bytes a voxel of the grid at the measure's peak, once the triangles are let go.
    bytes_per_triangle : int
        Bytes a triangle of a mesh beyond its read (:func:`mesh_read_memory`) while the measure keeps it.
    """

    what: str
    fixed: int
    bytes_per_voxel: int
    bytes_per_triangle: int = 0

    def need(self, voxels: int, held: int) -> int:
        """Bytes of the measure's own peak on `voxels`, past the triangles, with `held` held before it."""
        return int(max(held, self.fixed) + self.bytes_per_voxel * int(voxels))


#: what analyze holds (:func:`check_measure_memory`): the libraries and a fixed part, and
#: :data:`ANALYSIS_BYTES_PER_VOXEL`. Measured (``/usr/bin/time``'s peak, 2026-12-07) on sheet gyroids written as
#: .npy fields of 160^3, 260^3 and 400^3 voxels: 280, 514 and 1,168 MiB (bounds 334, 642 and 1,705); on the
#: default cube's STL (5.2 M triangles) at 0.05 mm, 675 MiB, its read's bound (:func:`mesh_read_memory`) 634
#: beside the 100 the process held
ANALYSIS_MEMORY = MeasureMemory("the analysis", 240 * 2**20, ANALYSIS_BYTES_PER_VOXEL)


def check_measure_memory(work: MeasureMemory, name: str, shape, voxel: float, held: int, total: int,
                         coarser: bool, read: int = 0) -> None:
    """Refuse, before the measure, a grid of `shape` whose measure (`work`) does not fit `total` bytes: one line
    naming the ``--max-memory`` that would do and, where the voxel can be chosen (`coarser`: a mesh voxelised
    or a volume resampled at ``--voxel``), the voxel that would fit. `read`: the peak of a mesh's read on that
    grid (`held` and :func:`mesh_read_memory`), not yet done: the budget named holds both."""
    from ..run.memory import format_size
    from .mechanics import held_margin

    voxels = int(np.prod(shape))
    need = max(work.need(voxels, held), int(read))
    if need <= total:
        return
    named = need + held_margin(held)
    room = total - max(held, work.fixed) - held_margin(held)
    fit = None
    if coarser and room > 0 and read + held_margin(held) <= total:
        fit = voxel * (work.bytes_per_voxel * voxels / room) ** (1 / 3) * 1.02
    raise ScaffoldError.for_budget(
        f"{work.what} of {name} on {'x'.join(str(int(v)) for v in shape)} voxels at {voxel:.4g} mm needs about "
        f"{format_size(need)}, over --max-memory {format_size(total)}; use --max-memory {format_size(named)}"
        + (f" or --voxel {fit:.4g}" if fit is not None else ""), named)


def check_mesh_read(name: str, triangles: int, voxels: int, held: int, total: int,
                    work: MeasureMemory | None = None) -> None:
    """Refuse, before the work, a mesh whose read and voxels (:func:`mesh_read_memory`, with what `work` holds
    while the triangles are kept) do not fit `total` bytes beside the `held` ones: one line naming the
    ``--max-memory`` that would do (a coarser voxel saves little: the triangles take most)."""
    from ..run.memory import format_size
    from .mechanics import held_margin

    need = mesh_read_memory(triangles, voxels, work)
    if held + need > total:
        named = held + need + held_margin(held)
        grid = f" on {voxels:,} voxels" if voxels else ""
        raise ScaffoldError.for_budget(
            f"reading {name} ({triangles:,} triangles{grid}) needs about {format_size(need)} beside the "
            f"{format_size(held)} held, over --max-memory {format_size(total)}; use --max-memory "
            f"{format_size(named)}", named)


def read_mesh_arrays(path):
    """A closed mesh's vertices (float64, mm) and faces (int64): a binary STL read by numpy
    (:func:`_read_binary_stl`, a sixth of trimesh's memory), a 3MF, PLY or OBJ as generate writes them by
    :func:`_read_3mf`, :func:`_read_ply` and :func:`_read_obj`, any other mesh by trimesh (:func:`_read_mesh`).
    The same arrays either way; the same one-line refusals of a mesh that holds no triangles or is not closed."""
    from pathlib import Path

    path = Path(path)
    n = binary_stl_triangles(path)
    streamed = {".3mf": _read_3mf, ".ply": _read_ply, ".obj": _read_obj}.get(_suffix(path))
    read = _read_binary_stl(path, n) if n else streamed(path) if streamed is not None else None
    if read is None:
        mesh = _read_mesh(path)
        return np.asarray(mesh.vertices), np.asarray(mesh.faces)
    vertices, faces = read
    if not _watertight(faces, len(vertices)):
        raise ScaffoldError(_NOT_CLOSED.format(name=path.name))
    from ..mesh.marching import face_measures

    if face_measures(vertices, faces)[1].sum() < 0:
        faces = np.ascontiguousarray(faces[:, ::-1])  # normals pointing in: the same solid (trimesh's invert)
    return vertices, faces


_NOT_CLOSED = ("{name} is not a closed surface (some edges belong to one triangle only); repair it (fill its holes) "
               "before analysing it")


def _read_mesh(path):
    import trimesh

    try:
        mesh = trimesh.load(str(path), force="mesh")
    except Exception as exc:  # trimesh raises many types for a bad file; name it in one line
        reason = " ".join(str(exc).split())[:160] or type(exc).__name__
        raise ScaffoldError(f"cannot read {path.name} as a mesh: {reason}") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ScaffoldError(f"{path.name} holds no triangles; give a closed surface mesh")
    if not mesh.is_watertight:
        raise ScaffoldError(_NOT_CLOSED.format(name=path.name))
    if mesh.volume < 0:
        mesh.invert()  # normals pointing in: the same solid
    return mesh


def _own_field(path, zyx_shape) -> bool:
    """Whether the volume `path` is a signed distance generate wrote: its report beside it names a grid of
    the volume's shape (x, y, z)."""
    report = report_beside(path)
    try:
        return report is not None and tuple(int(v) for v in report["grid_shape"]) == tuple(zyx_shape[::-1])
    except (KeyError, TypeError, ValueError):
        return False


def _read_volume(path, spacing, voxel, label=None, threshold=None):
    """The solid of a volume on the world's axes (x, y, z; :func:`world_axes`), its voxel (mm), a note on
    its resampling (or None), how its solid was chosen, generate's own distance (or None), a note on
    its axes (or None) and the centre of its voxel [0, 0, 0] (mm, x, y, z): where the file's origin, direction
    and spacing place it, so that positions (the most strained voxels, a certificate's defects) read in the
    scanner's frame; an oblique volume, left on its index axes, starts half a voxel from 0. The solid is every
    non-zero voxel of a binary volume, a segmentation's `label`, or a CT's intensities from `threshold` (HU) up
    (:func:`~implicit_scaffold.fields.patient_volume.bone_mask`)."""
    import SimpleITK as sitk

    from ..fields.patient_volume import bone_mask, intensity_range
    from ..io.images import folder_kind, header_states_spacing, read_image, spacing_triple, warn_spacing_override

    kind = folder_kind(path)
    image = read_image(path, folder=kind)
    if image.GetDimension() != 3 or image.GetNumberOfComponentsPerPixel() != 1:
        raise ScaffoldError(f"{path.name} is not a 3-D single-channel volume; give a binary volume, a label map "
                            "or a CT")
    if spacing is not None:
        warn_spacing_override(path, image, spacing, folder=kind)
        step = np.asarray(spacing_triple(spacing))
    elif header_states_spacing(path, folder=kind):
        step = np.asarray(image.GetSpacing(), float)
    else:
        raise ScaffoldError(f"{path.name} states no voxel spacing; give it with --spacing (mm), "
                            "e.g. --spacing 0.05 or --spacing \"0.05 0.05 0.1\"")
    array = sitk.GetArrayViewFromImage(image)  # (z, y, x)
    distance = None  # generate's own field: its values, (x, y, z), for the as-built offset of check
    if label is not None or threshold is not None:
        mask, selection = bone_mask(array, path.name, label, threshold)
    elif array.dtype.kind == "f" and _own_field(path, array.shape):
        # generate's signed distance (mm, negative in the solid): no threshold of intensities selects its solid
        mask, selection = array < 0, "the signed distance below 0 (generate's field; its report beside it)"
        distance = np.ascontiguousarray(np.transpose(array, (2, 1, 0)), np.float32)
    else:
        nonzero = array[array != 0]
        if nonzero.size and nonzero.min() != nonzero.max():
            span = intensity_range(array)
            if span is not None:
                ct = " (bone is about 200 HU and above in a CT)" if span[0] < 0 else ""
                raise ScaffoldError(f"{path.name} is not a binary volume: it holds intensities ({span[0]:g} to "
                                    f"{span[1]:g}); pass --threshold with the bone's lowest intensity{ct}, e.g. "
                                    "--threshold 200 (a signed distance generate wrote is read with its JSON "
                                    "report beside it)")
            labels = np.unique(nonzero)
            shown = ", ".join(f"{v:g}" for v in labels[:12]) + (" ..." if labels.size > 12 else "")
            raise ScaffoldError(f"{path.name} is not a binary volume: it is a label map (labels {shown}); pass "
                                f"--label N to keep one, e.g. --label {labels[0]:g}")
        mask, selection = array != 0, "non-zero voxels"
    del array
    solid = np.ascontiguousarray(np.transpose(mask, (2, 1, 0)))
    del mask
    # figures per axis (moduli, overhangs) name the patient's x, y, z, as generate places it, not the
    # file's storage order: a volume stored (k, i, j) or flipped is the same bone
    direction = np.asarray(image.GetDirection(), np.float64).reshape(3, 3)
    order, flip, axes = world_axes(direction, path.name)
    solid, step = _reorient(solid, order, flip), step[list(order)]
    if np.all(np.abs(np.abs(direction[np.arange(3), list(order)]) - 1) <= AXIS_TOLERANCE):
        # world axis w is index axis order[w]: its lowest voxel centre is the origin's, or, where that axis runs
        # along -w, the far end's
        first = np.asarray(image.GetOrigin(), np.float64) - np.where(flip, (np.asarray(solid.shape) - 1) * step, 0.0)
    else:  # oblique: on its index axes, as before
        first = 0.5 * step
    if distance is not None:
        distance = _reorient(distance, order, flip)
    target = voxel if voxel is not None else float(step.min())
    note = None
    if not np.allclose(step, target, rtol=1e-6):
        # nearest voxel: each new centre takes the value of the old voxel holding it
        idx = []
        for a in range(3):
            n = max(1, int(round(solid.shape[a] * step[a] / target)))
            idx.append(np.minimum(((np.arange(n) + 0.5) * target / step[a]).astype(np.int64), solid.shape[a] - 1))
        solid = solid[np.ix_(*idx)]
        note = f"from {' x '.join(f'{v:g}' for v in step)} mm to {target:g} mm (nearest voxel)"
        distance = None  # not resampled: the solid's values only
    if not solid.any():
        raise ScaffoldError(f"{path.name} holds no solid voxel (all zero)")
    # the new voxels tile the same box: its corner is half an old voxel below the first centre
    origin = tuple(float(v) for v in first - step / 2 + target / 2)
    return solid, float(target), note, selection, distance, axes, origin


#: largest departure of a direction matrix's entries from 0 and ±1 still read as a signed permutation
#: (headers store cosines in float32 or rounded to a few digits; a real tilt is degrees, 1e-2 and more)
AXIS_TOLERANCE = 1e-3


def world_axes(direction: np.ndarray, name: str) -> tuple[tuple, tuple, str | None]:
    """How to put a volume's (x, y, z)-ordered index axes on the world axes.

    Parameters
    ----------
    direction : (3, 3) float ndarray
        The image's direction matrix (column ``a``: the world direction of index axis ``a``).
    name : str
        The file's name, for the messages.

    Returns
    -------
    order : (3,) tuple of int
        Index axis that runs along world x, y, z.
    flip : (3,) tuple of bool
        Whether that index axis runs along -x, -y, -z (so is reversed).
    note : str or None
        What was done (None for the identity). An oblique direction (not a signed permutation) is
        left on the index axes, with a :class:`ScaffoldWarning` that says so.
    """
    import warnings

    d = np.asarray(direction, np.float64)
    r = np.rint(d)
    if not (np.all(np.abs(d - r) <= AXIS_TOLERANCE) and np.array_equal(np.abs(r).sum(axis=0), np.ones(3))
            and np.array_equal(np.abs(r).sum(axis=1), np.ones(3))):
        warnings.warn(f"{name} has an oblique direction matrix (its voxel axes are not along x, y, z): its figures "
                      "per axis (x, y, z) are along the volume's index axes i, j, k, not the patient's; resample it "
                      "onto the world axes for per-axis figures of the patient", ScaffoldWarning, stacklevel=4)
        return (0, 1, 2), (False, False, False), "oblique direction: x, y, z are the volume's index axes i, j, k"
    order = tuple(int(np.flatnonzero(r[w])[0]) for w in range(3))
    flip = tuple(bool(r[w, order[w]] < 0) for w in range(3))
    if order == (0, 1, 2) and not any(flip):
        return order, flip, None
    ijk = "ijk"
    return order, flip, "x, y, z along the volume's " + ", ".join(
        ("-" if f else "+") + ijk[a] for a, f in zip(order, flip)) + " (its direction matrix)"


def _reorient(a: np.ndarray, order, flip) -> np.ndarray:
    """`a` (index axes i, j, k) with its axes put in world order and reversed where they run backwards."""
    out = np.transpose(a, order)
    flips = tuple(w for w in range(3) if flip[w])
    return np.ascontiguousarray(np.flip(out, flips) if flips else out)
