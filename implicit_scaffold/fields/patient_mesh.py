"""A patient given as a triangle surface mesh: its signed distance on a grid and its volume.

Sign. Inside/outside comes from ray parity along grid lines in x, y and z with a
vote. A grid line crossing the surface an odd number of times passes through a hole
and abstains; the others vote, each for its own parity. A small hole thus spoils only
voxels whose three lines all pass through holes; duplicate faces are removed first;
flipped normals do not matter (parity counts crossings, not their direction). A line
that grazes an edge or a vertex is decided by simulation of simplicity on canonical
edges (the same edge gives the same 2D cross product in both its triangles), so a
crossing there is counted exactly once.

Distance. Within a band of a few voxels the exact point-to-triangle distance is the
OpenCL kernel ``kernels/patient.cl`` over triangles binned into blocks of voxels
(:func:`implicit_scaffold.fields.blocks.bin_boxes`, as the lattice kernels). Farther away,
a Euclidean feature transform (``scipy.ndimage.distance_transform_edt``) names each
voxel's nearest band voxel; the exact distance to *that* voxel's nearest triangle is
the value (exact except near the medial axis, where it is a tight upper bound).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .. import opencl
from .blocks import bin_boxes, block_counts
from ..errors import ScaffoldError
from ..run.grid import Grid

#: block edge, voxels (a work-group computes one block)
BLOCK = 8
#: the distance kernels' block edge (voxels) for a dense mesh: one of at least :data:`DENSE_TRIANGLES_PER_VOXEL`
#: triangles a voxel of the grid. Each voxel tests the triangles near its block, so their count goes with the
#: block and its cut-off grown edge cubed: a scaffold's STL measured on its own grid (the default cube's, 5.2 M
#: triangles on 7.4 M voxels) took 24.2 s in triangle_distance with blocks of 8, 14.8 s with blocks of 4, the
#: same bits; a patient's mesh (some 10^-3 triangles a voxel) keeps blocks of 8, its lists 8 times fewer
DENSE_BLOCK = 4
DENSE_TRIANGLES_PER_VOXEL = 0.1
#: exact band half-width, voxels: every voxel touching the surface is inside it
BAND_VOXELS = 3.0
#: (triangle, grid line) candidate pairs handled at once in the parity pass
_PAIR_CHUNK = 1_000_000
#: grid lines used to integrate a clipped volume (the error is at the silhouette only)
VOLUME_COLUMNS = 1_000_000
#: share of odd grid lines (through holes) beyond which inside/outside is undefined
MAX_ODD_SHARE = 0.2


def _axes_uv(axis: int) -> tuple[int, int]:
    return ((1, 2), (0, 2), (0, 1))[axis]


def _edge_signs(V2, F, pu, pv, fid):
    """Signs (+1/-1/0) of the three edges of faces `fid` at points (pu, pv), canonical and perturbed.

    Each edge is evaluated from its lower vertex index to its higher one, so the two
    triangles sharing it see exactly opposite values; an exact zero is resolved by
    perturbing the point by (eps, eps^2) (simulation of simplicity).
    """
    signs, weights = [], []
    for e in range(3):
        a = F[fid, e]
        b = F[fid, (e + 1) % 3]
        flip = a > b
        lo = np.where(flip, b, a)
        hi = np.where(flip, a, b)
        du = V2[hi, 0] - V2[lo, 0]
        dv = V2[hi, 1] - V2[lo, 1]
        w = du * (pv - V2[lo, 1]) - dv * (pu - V2[lo, 0])
        s = np.sign(w)
        tie = s == 0
        if np.any(tie):
            s[tie] = np.where(dv[tie] != 0, -np.sign(dv[tie]), np.sign(du[tie]))
        sgn = np.where(flip, -1.0, 1.0)
        signs.append(s * sgn)
        weights.append(w * sgn)
    return signs, weights


def crossings(V, F, axis: int, u0: float, hu: float, nu: int, v0: float, hv: float, nv: int, *,
              first_u: int = 0):
    """Where the lines along `axis` through a 2D lattice of points cross the triangles.

    Lines pass through ``(u0 + i hu, v0 + j hv)`` in the two other axes (in
    increasing order), ``first_u <= i < first_u + nu``, ``0 <= j < nv``. A slab of a
    grid passes the whole grid's `u0` and its first plane as `first_u`, so that its
    lines' coordinates are computed exactly as the whole grid's.

    Every (face, line) pair within the face's box is tested in one compiled pass on every
    core, with :func:`crossings_reference`'s arithmetic: the same crossings, bit for bit.

    Parameters
    ----------
    V : (nv, 3) float64 ndarray, mm
    F : (m, 3) int ndarray
    axis : int

    Returns
    -------
    column : (k,) int64 ndarray
        ``(i - first_u) * nv + j`` of each crossing's line.
    t : (k,) float64 ndarray, mm
        Coordinate of the crossing along `axis`.
    """
    from ..run.threads import over_rows

    ua, va = _axes_uv(axis)
    V = np.ascontiguousarray(V, np.float64)
    F = np.ascontiguousarray(F, np.int64)
    V2 = np.ascontiguousarray(V[:, [ua, va]])
    tri = V2[F]                                    # (m, 3, 2)
    tmin, tmax = tri.min(axis=1), tri.max(axis=1)
    del tri
    i0 = np.maximum(np.ceil((tmin[:, 0] - u0) / hu), first_u).astype(np.int64)
    i1 = np.minimum(np.floor((tmax[:, 0] - u0) / hu), first_u + nu - 1).astype(np.int64)
    j0 = np.maximum(np.ceil((tmin[:, 1] - v0) / hv), 0).astype(np.int64)
    j1 = np.minimum(np.floor((tmax[:, 1] - v0) / hv), nv - 1).astype(np.int64)
    nj = np.maximum(j1 - j0 + 1, 0)
    per = np.maximum(i1 - i0 + 1, 0) * nj
    faces = np.flatnonzero(per)
    if not len(faces):
        return np.zeros(0, np.int64), np.zeros(0)
    cum = np.cumsum(per[faces])
    cols, ts = [], []
    first = 0
    while first < len(faces):
        # whole faces per chunk, about 4 _PAIR_CHUNK pairs each (17 bytes a pair)
        base = cum[first - 1] if first else 0
        stop = max(int(np.searchsorted(cum, base + 4 * _PAIR_CHUNK, side="right")), first + 1)
        start = np.concatenate([[0], cum[first:stop] - base])
        col = np.empty(int(start[-1]), np.int64)
        t = np.empty(int(start[-1]), np.float64)
        hit = np.zeros(int(start[-1]), np.bool_)
        over_rows(_crossings_kernel(), stop - first, V, V2, F, axis, faces[first:stop], start, i0, j0, nj, per,
                  float(u0), float(hu), float(v0), float(hv), int(first_u), int(nv), col, t, hit)
        cols.append(col[hit])
        ts.append(t[hit])
        del col, t, hit
        first = stop
    return np.concatenate(cols), np.concatenate(ts)


_CROSSINGS = None


def _crossings_kernel():
    global _CROSSINGS
    if _CROSSINGS is None:
        import numba as nb

        @nb.njit(cache=True, nogil=True, boundscheck=False)
        def crossings_rows(V, V2, F, axis, faces, start, i0, j0, nj, per, u0, hu, v0, hv, first_u, nv, col, t, hit,
                           lo, hi):  # pragma: no cover - compiled
            # _edge_signs and crossings_reference's arithmetic, pair by pair: each edge from its
            # lower vertex index to its higher, an exact zero resolved by perturbation
            s = np.zeros(3)
            w = np.zeros(3)
            for q in range(lo, hi):
                f = faces[q]
                out = start[q]
                for local in range(per[f]):
                    ii = i0[f] + local // nj[f]
                    jj = j0[f] + local % nj[f]
                    pu = u0 + ii * hu
                    pv = v0 + jj * hv
                    for e in range(3):
                        a = F[f, e]
                        b = F[f, (e + 1) % 3]
                        flip = a > b
                        lo_v = b if flip else a
                        hi_v = a if flip else b
                        du = V2[hi_v, 0] - V2[lo_v, 0]
                        dv = V2[hi_v, 1] - V2[lo_v, 1]
                        we = du * (pv - V2[lo_v, 1]) - dv * (pu - V2[lo_v, 0])
                        se = np.sign(we)
                        if se == 0:
                            se = -np.sign(dv) if dv != 0 else np.sign(du)
                        sgn = -1.0 if flip else 1.0
                        s[e] = se * sgn
                        w[e] = we * sgn
                    if s[0] == s[1] and s[1] == s[2] and s[0] != 0:
                        total = w[0] + w[1] + w[2]
                        va_ = V[F[f, 0], axis]
                        vb_ = V[F[f, 1], axis]
                        vc_ = V[F[f, 2], axis]
                        t[out + local] = (w[1] * va_ + w[2] * vb_ + w[0] * vc_) / (total if total != 0 else 1.0)
                        col[out + local] = (ii - first_u) * nv + jj
                        hit[out + local] = True

        _CROSSINGS = crossings_rows
    return _CROSSINGS


def crossings_reference(V, F, axis: int, u0: float, hu: float, nu: int, v0: float, hv: float, nv: int, *,
                        first_u: int = 0):
    """:func:`crossings` in NumPy, chunk by chunk of (face, line) pairs (the oracle of the
    compiled pass).

    Where the lines along `axis` through a 2D lattice of points cross the triangles.

    Lines pass through ``(u0 + i hu, v0 + j hv)`` in the two other axes (in
    increasing order), ``first_u <= i < first_u + nu``, ``0 <= j < nv``. A slab of a
    grid passes the whole grid's `u0` and its first plane as `first_u`, so that its
    lines' coordinates are computed exactly as the whole grid's.

    Parameters
    ----------
    V : (nv, 3) float64 ndarray, mm
    F : (m, 3) int ndarray
    axis : int

    Returns
    -------
    column : (k,) int64 ndarray
        ``(i - first_u) * nv + j`` of each crossing's line.
    t : (k,) float64 ndarray, mm
        Coordinate of the crossing along `axis`.
    """
    ua, va = _axes_uv(axis)
    V2 = np.ascontiguousarray(V[:, [ua, va]])
    tri = V2[F]                                    # (m, 3, 2)
    tmin, tmax = tri.min(axis=1), tri.max(axis=1)
    i0 = np.maximum(np.ceil((tmin[:, 0] - u0) / hu), first_u).astype(np.int64)
    i1 = np.minimum(np.floor((tmax[:, 0] - u0) / hu), first_u + nu - 1).astype(np.int64)
    j0 = np.maximum(np.ceil((tmin[:, 1] - v0) / hv), 0).astype(np.int64)
    j1 = np.minimum(np.floor((tmax[:, 1] - v0) / hv), nv - 1).astype(np.int64)
    ni = np.maximum(i1 - i0 + 1, 0)
    nj = np.maximum(j1 - j0 + 1, 0)
    per = ni * nj
    faces = np.flatnonzero(per)
    cols, ts = [], []
    cum = np.cumsum(per[faces])
    start = 0
    while start < len(faces):
        # whole faces per chunk, about _PAIR_CHUNK pairs each
        base = cum[start - 1] if start else 0
        stop = max(int(np.searchsorted(cum, base + _PAIR_CHUNK, side="right")), start + 1)
        fc = faces[start:stop]
        count = per[fc]
        fid = np.repeat(fc, count)
        local = np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count)
        ii = i0[fid] + local // nj[fid]
        jj = j0[fid] + local % nj[fid]
        pu = u0 + ii * hu
        pv = v0 + jj * hv
        s, w = _edge_signs(V2, F, pu, pv, fid)
        hit = (s[0] == s[1]) & (s[1] == s[2]) & (s[0] != 0)
        fid, ii, jj = fid[hit], ii[hit], jj[hit]
        w = [x[hit] for x in w]
        total = w[0] + w[1] + w[2]
        # barycentric weights: the edge opposite a vertex weighs that vertex
        va_, vb_, vc_ = (V[F[fid, k], axis] for k in range(3))
        t = (w[1] * va_ + w[2] * vb_ + w[0] * vc_) / np.where(total != 0, total, 1.0)
        cols.append((ii - first_u) * nv + jj)
        ts.append(t)
        start = stop
    if not cols:
        return np.zeros(0, np.int64), np.zeros(0)
    return np.concatenate(cols), np.concatenate(ts)


def inside_votes(V, F, grid: Grid, x_range=None) -> tuple[np.ndarray, float]:
    """Inside/outside of every voxel by ray parity along x, y and z with a vote.

    The parity decomposes by slab: a line along x is intersected whole (its crossings
    before the slab flip its first plane, those after it only count in its total), and
    lines along y and z lie in one plane each. So the planes `x_range` alone get the
    whole grid's answer, bit for bit.

    Each axis's crossings mark the first voxel beyond them; one compiled pass per axis then
    carries the parity along the lines and adds its vote (:func:`inside_votes_reference` does
    the same in NumPy, in about eight passes over the slab per axis).

    Parameters
    ----------
    V : (nv, 3) float64 ndarray, mm
    F : (m, 3) int ndarray
    grid : Grid
    x_range : (x0, x1), optional
        The planes to decide; all of them by default.

    Returns
    -------
    inside : (x1 - x0, ny, nz) bool ndarray
    odd_share : float
        Share of the grid lines (of the slab) that meet the surface and cross it an odd
        number of times (0 for a closed surface).
    """
    from ..run.threads import over_rows

    x0, x1 = (0, grid.shape[0]) if x_range is None else (int(x_range[0]), int(x_range[1]))
    shape = (x1 - x0,) + tuple(grid.shape[1:])
    score = np.zeros(shape, np.int8)
    raw = np.zeros(shape, np.uint8)
    marks = np.zeros(shape, np.uint8)  # the passes leave it zero for the next axis
    odd = hit = 0
    kernels = _vote_kernels()
    for axis in range(3):
        ua, va = _axes_uv(axis)
        nu, nv = shape[ua], shape[va]
        col, t = crossings(V, F, axis, grid.origin[ua], grid.spacing, nu, grid.origin[va], grid.spacing, nv,
                           first_u=x0 if ua == 0 else 0)
        per_col = np.bincount(col, minlength=nu * nv)
        even = (per_col % 2 == 0).reshape(nu, nv)
        odd += int(np.count_nonzero(per_col % 2))
        hit += int(np.count_nonzero(per_col))
        # first voxel beyond each crossing; crossings past the grid only count in the totals
        k = np.ceil((t - grid.origin[axis]) / grid.spacing).astype(np.int64)
        if axis == 0:
            k -= x0  # in the whole grid's frame, then the slab's: crossings before it flip its first plane
        keep = k < shape[axis]
        k = np.maximum(k[keep], 0)
        ci, cj = np.divmod(col[keep], nv)
        idx = [None, None, None]
        idx[axis], idx[ua], idx[va] = k, ci, cj
        kernels[0](marks.reshape(-1), np.ravel_multi_index(tuple(idx), shape))
        del col, t, k, keep, ci, cj, idx
        # lines along x run across the planes: the pieces split y; the others split x
        over_rows(kernels[1 + axis], shape[1] if axis == 0 else shape[0], marks, even, score, raw)
    inside = score > 0
    tie = score == 0
    if np.any(tie):
        # every line through these voxels passes a hole: the plain majority decides
        inside[tie] = raw[tie] >= 2
    return inside, (odd / hit if hit else 0.0)


_VOTE_KERNELS = None


def _vote_kernels():
    """The compiled passes of :func:`inside_votes`, built on first use and cached on disk."""
    global _VOTE_KERNELS
    if _VOTE_KERNELS is not None:
        return _VOTE_KERNELS
    import numba as nb

    @nb.njit(cache=True, nogil=True, boundscheck=False)
    def mark(flat, at):  # pragma: no cover - compiled
        # two crossings at one voxel cancel: the mark is their count's parity
        for f in at:
            flat[f] ^= 1

    # each pass: the parity p so far along the line (the XOR of the marks up to here), clearing
    # the marks; raw counts the axes that say inside, score adds +1 inside and -1 outside on the
    # lines that cross the surface an even number of times (the others do not vote)
    @nb.njit(cache=True, nogil=True, boundscheck=False)
    def along_x(marks, even, score, raw, lo, hi):  # pragma: no cover - compiled
        nx, _, nz = marks.shape
        p = np.zeros((hi - lo, nz), np.uint8)
        for i in range(nx):
            for j in range(lo, hi):
                for k in range(nz):
                    q = p[j - lo, k] ^ marks[i, j, k]
                    p[j - lo, k] = q
                    marks[i, j, k] = 0
                    raw[i, j, k] += q
                    if even[j, k]:
                        score[i, j, k] += 2 * np.int8(q) - 1

    @nb.njit(cache=True, nogil=True, boundscheck=False)
    def along_y(marks, even, score, raw, lo, hi):  # pragma: no cover - compiled
        _, ny, nz = marks.shape
        p = np.zeros(nz, np.uint8)
        for i in range(lo, hi):
            p[:] = 0
            for j in range(ny):
                for k in range(nz):
                    q = p[k] ^ marks[i, j, k]
                    p[k] = q
                    marks[i, j, k] = 0
                    raw[i, j, k] += q
                    if even[i, k]:
                        score[i, j, k] += 2 * np.int8(q) - 1

    @nb.njit(cache=True, nogil=True, boundscheck=False)
    def along_z(marks, even, score, raw, lo, hi):  # pragma: no cover - compiled
        _, ny, nz = marks.shape
        for i in range(lo, hi):
            for j in range(ny):
                q = np.uint8(0)
                e = even[i, j]
                for k in range(nz):
                    q ^= marks[i, j, k]
                    marks[i, j, k] = 0
                    raw[i, j, k] += q
                    if e:
                        score[i, j, k] += 2 * np.int8(q) - 1

    _VOTE_KERNELS = (mark, along_x, along_y, along_z)
    return _VOTE_KERNELS


def inside_votes_reference(V, F, grid: Grid, x_range=None) -> tuple[np.ndarray, float]:
    """:func:`inside_votes` in NumPy: each axis's parities by an XOR accumulation of the
    crossings' marks (the oracle of the compiled passes).

    Inside/outside of every voxel by ray parity along x, y and z with a vote.

    The parity decomposes by slab: a line along x is intersected whole (its crossings
    before the slab flip its first plane, those after it only count in its total), and
    lines along y and z lie in one plane each. So the planes `x_range` alone get the
    whole grid's answer, bit for bit.

    Parameters
    ----------
    V : (nv, 3) float64 ndarray, mm
    F : (m, 3) int ndarray
    grid : Grid
    x_range : (x0, x1), optional
        The planes to decide; all of them by default.

    Returns
    -------
    inside : (x1 - x0, ny, nz) bool ndarray
    odd_share : float
        Share of the grid lines (of the slab) that meet the surface and cross it an odd
        number of times (0 for a closed surface).
    """
    x0, x1 = (0, grid.shape[0]) if x_range is None else (int(x_range[0]), int(x_range[1]))
    shape = (x1 - x0,) + tuple(grid.shape[1:])
    score = np.zeros(shape, np.int8)
    raw = np.zeros(shape, np.uint8)
    odd = hit = 0
    for axis in range(3):
        ua, va = _axes_uv(axis)
        nu, nv = shape[ua], shape[va]
        col, t = crossings_reference(V, F, axis, grid.origin[ua], grid.spacing, nu, grid.origin[va], grid.spacing, nv,
                           first_u=x0 if ua == 0 else 0)
        per_col = np.bincount(col, minlength=nu * nv)
        even = (per_col % 2 == 0).reshape(nu, nv)
        odd += int(np.count_nonzero(per_col % 2))
        hit += int(np.count_nonzero(per_col))
        # first voxel beyond each crossing; crossings past the grid only count in the totals
        k = np.ceil((t - grid.origin[axis]) / grid.spacing).astype(np.int64)
        if axis == 0:
            k -= x0  # in the whole grid's frame, then the slab's: crossings before it flip its first plane
        keep = k < shape[axis]
        k = np.maximum(k[keep], 0)
        ci, cj = np.divmod(col[keep], nv)
        idx = [None, None, None]
        idx[axis], idx[ua], idx[va] = k, ci, cj
        flat = np.ravel_multi_index(tuple(idx), shape)
        u, c = np.unique(flat, return_counts=True)
        par = np.zeros(shape, np.uint8)
        par.reshape(-1)[u[c % 2 == 1]] = 1
        np.bitwise_xor.accumulate(par, axis=axis, out=par)
        raw += par
        vote = par.view(np.int8)
        vote *= 2
        vote -= 1
        vote *= np.expand_dims(even, axis).view(np.int8)
        score += vote
        del par, vote
    inside = score > 0
    tie = score == 0
    if np.any(tie):
        # every line through these voxels passes a hole: the plain majority decides
        inside[tie] = raw[tie] >= 2
    return inside, (odd / hit if hit else 0.0)


#: triangles packed at a time by :func:`_pack_triangles` (its float64 temporaries, some 400 bytes a triangle)
PACK_CHUNK = 1 << 18


def _pack_triangles(V, F, origin) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangles relative to `origin` as 6 float4 each (v0, v1, v2, (n, n.v0), lo, hi), and their boxes.

    A chunk of :data:`PACK_CHUNK` triangles at a time (each triangle's values are its own: the same bits as all at
    once): the whole mesh's float64 corners, normals and their temporaries held 1.4 GB for the default cube's STL
    (5.2 M triangles)."""
    V = np.asarray(V, np.float64)
    F = np.asarray(F)
    origin = np.asarray(origin, np.float64)
    m = len(F)
    # float32 boxes grown by a hair so rounding never makes a box test skip the nearest triangle (the largest
    # corner coordinate of any triangle, as all the corners at once would give)
    used = np.zeros(len(V), bool)
    used[F.ravel()] = True
    pad = 1e-5 * (1 + (np.abs(V[used] - origin).max() if m else 0.0))
    del used
    # read by the device in place (opencl.host_buffer): a dense mesh's copy on the device held 96 bytes a
    # triangle more (g2.3mf, 12.5 M triangles: 1.2 GB)
    data = opencl.aligned_empty((m, 6, 4), np.float32)
    data[...] = 0
    lo = np.empty((m, 3))
    hi = np.empty((m, 3))
    for a in range(0, m, PACK_CHUNK):
        b = min(m, a + PACK_CHUNK)
        tri = V[F[a:b]] - origin
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        norm = np.linalg.norm(n, axis=1)
        n /= norm[:, None]
        np.min(tri, axis=1, out=lo[a:b])
        np.max(tri, axis=1, out=hi[a:b])
        part = data[a:b]
        part[:, :3, :3] = tri
        part[:, 3, :3] = n
        part[:, 3, 3] = np.einsum("ij,ij->i", n, tri[:, 0])
        part[:, 4, :3] = lo[a:b] - pad
        part[:, 5, :3] = hi[a:b] + pad
    return data, lo, hi


def block_for(triangles: int, grid: Grid) -> int:
    """The distance kernels' block edge (voxels) for `triangles` on `grid`: :data:`DENSE_BLOCK` for a dense mesh,
    else :data:`BLOCK` (the whole grid's, so that every slab of a run gets the same lists and values)."""
    return DENSE_BLOCK if triangles >= DENSE_TRIANGLES_PER_VOXEL * float(np.prod(grid.shape)) else BLOCK


def _binned(lo, hi, grid: Grid, **kwargs) -> tuple:
    """The boxes' :func:`~implicit_scaffold.fields.blocks.bin_boxes` as device buffers (offsets, items), and
    the host array the items' buffer reads in place (keep it while the buffers are used): a dense mesh's
    items are some 80 bytes a triangle, which a copy on the device held twice."""
    lists = bin_boxes(lo, hi, grid, empty=opencl.aligned_empty, **kwargs)
    return (opencl.to_device(lists.offsets, np.int32), opencl.host_buffer(lists.items)), lists.items


def _tiles(grid: Grid, tile_blocks: int = 8, x_range=None, block: int = BLOCK):
    step = tile_blocks * block
    x0, x1 = (0, grid.shape[0]) if x_range is None else x_range
    return [(t0, min(t0 + step, x1)) for t0 in range(x0, x1, step)]


def _run(kernel, grid, out, tile_inputs, buffers, scalars, x_range=None, block: int = BLOCK):
    """Launch `kernel` (built with ``BLOCK=block``) over the planes `x_range` of `grid` (all by default) tile by
    tile into `out` (host array over those planes), in the whole grid's frame."""
    cy, cz = block_counts(grid, block)[1:]
    ny, nz = grid.shape[1:]
    pad = lambda n: -(-n // block) * block  # noqa: E731

    def args(x0, nx):
        extra = [opencl.to_device(f(x0, x0 + nx), np.int32) for f in tile_inputs]
        return (np.int32(x0), np.int32(0), np.int32(0), np.int32(nx), np.int32(ny), np.int32(nz),
                np.int32(cy), np.int32(cz), np.float32(grid.spacing), *extra, *buffers, *scalars)

    opencl.launch_tiles(kernel, _tiles(grid, x_range=x_range, block=block), out,
                        first=0 if x_range is None else int(x_range[0]),
                        sizes=lambda nx: ((pad(nz), pad(ny), pad(nx)), (block, block, block)), args=args)


def triangle_distance(V, F, grid: Grid, *, band: float | None = None) -> np.ndarray:
    """Unsigned distance from every voxel centre to the triangles, ``(nx, ny, nz)`` float32, mm.

    Exact (to float32) within `band` of the surface (kernel), and far from it the exact
    distance to the nearest triangle of the nearest band voxel (feature transform).

    Parameters
    ----------
    V : (nv, 3) float ndarray, mm
    F : (m, 3) int ndarray
        Non-degenerate triangles.
    grid : Grid
    band : float, mm, optional
        Half-width of the exact band; ``BAND_VOXELS`` voxels by default.
    """
    from scipy import ndimage

    V = np.asarray(V, np.float64)
    h = grid.spacing
    band = BAND_VOXELS * h if band is None else float(band)
    data, lo, hi = _pack_triangles(V, F, grid.origin)
    rel = Grid((0.0, 0.0, 0.0), h, grid.shape)
    tris = opencl.host_buffer(data.reshape(-1, 4))  # `data` read in place: kept to the end
    block = block_for(len(F), grid)
    nearest = np.empty(grid.shape, np.int32)
    cutoff = band
    for _ in range(2):
        lists, held = _binned(lo, hi, rel, block=block, cutoff=cutoff)
        _run(opencl.kernel("patient", "triangle_nearest", BLOCK=block), grid, nearest, [], [*lists, tris],
             [np.float32(cutoff), np.int32(0)], block=block)
        del lists, held
        far = nearest < 0
        if not far.all():
            break
        # no surface near the grid at all: widen the cut-off to reach the nearest triangle
        centre = (grid.lo + grid.hi) / 2
        cutoff = float(np.min(np.linalg.norm(V - centre, axis=1))
                       + np.linalg.norm(grid.hi - grid.lo)) + band
    if far.any():
        feature = ndimage.distance_transform_edt(far, return_distances=False, return_indices=True)
        del far
        flat_near = nearest.reshape(-1)

        def which(x0, x1):
            idx = np.ravel_multi_index(tuple(feature[a, x0:x1] for a in range(3)), grid.shape)
            return flat_near[idx]
    else:
        del far

        def which(x0, x1):
            return nearest[x0:x1]

    del lo, hi
    out = np.empty(grid.shape, np.float32)
    _run(opencl.kernel("patient", "triangle_distance", BLOCK=BLOCK), grid, out, [which], [tris], [])
    del tris, data
    return out


def clamped_distance(V, F, grid: Grid, *, reach: float, x_range=None) -> np.ndarray:
    """Unsigned distance from the voxel centres of the planes `x_range` to the triangles,
    exact (to float32) up to `reach` and `reach` beyond, ``(x1 - x0, ny, nz)`` float32, mm.

    Every voxel is decided by the triangles within `reach` of its block alone, in the
    whole grid's frame, so a slab gets the whole grid's values bit for bit; nothing
    global (such as :func:`triangle_distance`'s feature transform) is needed.

    Parameters
    ----------
    V : (nv, 3) float ndarray, mm
    F : (m, 3) int ndarray
        Non-degenerate triangles.
    grid : Grid
    reach : float, mm
        The widest distance that matters; farther values are clamped to it.
    x_range : (x0, x1), optional
        The planes to compute; all of them by default.
    """
    V = np.asarray(V, np.float64)
    x0, x1 = (0, grid.shape[0]) if x_range is None else (int(x_range[0]), int(x_range[1]))
    data, lo, hi = _pack_triangles(V, F, grid.origin)
    rel = Grid((0.0, 0.0, 0.0), grid.spacing, grid.shape)
    block = block_for(len(F), grid)
    b0, b1 = x0 // block, -(-x1 // block)
    lists, held = _binned(lo, hi, rel, block=block, cutoff=reach, block_range=(b0, b1))
    del lo, hi
    cy, cz = block_counts(grid, block)[1:]
    tris = opencl.host_buffer(data.reshape(-1, 4))  # `data` read in place: kept to the end
    out = np.empty((x1 - x0,) + tuple(grid.shape[1:]), np.float32)
    # one pass (triangle_clamped): the nearest triangle's distance, or `reach` where none is within it
    _run(opencl.kernel("patient", "triangle_clamped", BLOCK=block), grid, out, [], [*lists, tris],
         [np.float32(reach), np.int32(b0 * cy * cz)], x_range=(x0, x1), block=block)
    del lists, held, tris, data
    return out


def triangle_distance_reference(points, triangles) -> np.ndarray:
    """Brute-force distance from each point to the nearest triangle, ``(m,)`` float64, mm.

    Closest point by the Voronoi regions of the triangle (vertex, edge or face),
    every point against every triangle: slow, for tests on small inputs.
    """
    p = np.asarray(points, np.float64)[:, None, :]
    t = np.asarray(triangles, np.float64)[None]
    a, b, c = t[..., 0, :], t[..., 1, :], t[..., 2, :]
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    plane = np.einsum("...i,...i->...", p - a, n)
    proj = p - plane[..., None] * n
    inside = np.ones(plane.shape, bool)
    for u, v in ((a, b), (b, c), (c, a)):
        inside &= np.einsum("...i,...i->...", np.cross(v - u, proj - u), n) >= 0
    edge = np.inf
    for u, v in ((a, b), (b, c), (c, a)):
        uv = v - u
        s = np.clip(np.einsum("...i,...i->...", p - u, uv) / np.einsum("...i,...i->...", uv, uv), 0, 1)
        edge = np.minimum(edge, np.linalg.norm(p - u - s[..., None] * uv, axis=-1))
    return np.where(inside, np.abs(plane), edge).min(axis=1)


class MeshPatient:
    """A patient bounded by a triangle mesh (mm).

    Parameters
    ----------
    vertices : (nv, 3) float ndarray, mm
    faces : (m, 3) int ndarray
    name : str
        For the report (usually the file name).
    watertight_volume : float, optional
        The mesh's exact volume when it is closed, mm³; otherwise the volume is
        integrated along grid lines.

    Attributes
    ----------
    lo, hi : (3,) float64 ndarray, mm
        Bounds of the vertices.
    closed : bool
        Watertight and consistently wound (the volume is then exact).
    solid_faces : (k, 3) int64 ndarray
        The faces of non-zero area (the distance kernel's triangles).
    """

    def __init__(self, vertices, faces, *, name: str = "mesh", watertight_volume: float | None = None):
        self.vertices = np.ascontiguousarray(vertices, np.float64)
        self.faces = np.ascontiguousarray(faces, np.int64)
        self.name = name
        area = np.linalg.norm(np.cross(self.vertices[self.faces[:, 1]] - self.vertices[self.faces[:, 0]],
                                       self.vertices[self.faces[:, 2]] - self.vertices[self.faces[:, 0]]), axis=1)
        scale = float(np.max(self.vertices.max(axis=0) - self.vertices.min(axis=0)))
        # zero-area triangles carry no surface: their edges belong to their neighbours
        self.solid_faces = self.faces[area > (1e-12 * scale) ** 2]
        self.lo = self.vertices.min(axis=0)
        self.hi = self.vertices.max(axis=0)
        self._volume = watertight_volume
        #: closed and consistently wound (its volume is then exact)
        self.closed = watertight_volume is not None

    @property
    def volume(self) -> float:
        """Volume enclosed, mm³ (exact for a closed mesh)."""
        if self._volume is None:
            self._volume = self.volume_within(np.zeros((0, 4)), self.lo, self.hi)[0]
        return float(self._volume)

    def describe(self) -> str:
        return f"mesh {self.name} ({len(self.faces)} triangles)"

    def odd_share(self, cells_across: int = 48) -> float:
        """Share of grid lines crossing the surface an odd number of times (holes) on a coarse grid."""
        h = float(np.max(self.hi - self.lo)) / cells_across
        grid = Grid.covering(self.lo, self.hi, h)
        share = 0.0
        for axis in range(3):
            ua, va = _axes_uv(axis)
            col, _ = crossings(self.vertices, self.faces, axis, grid.origin[ua], h, grid.shape[ua],
                               grid.origin[va], h, grid.shape[va])
            per = np.bincount(col)
            hit = np.count_nonzero(per)
            share = max(share, np.count_nonzero(per % 2) / hit if hit else 1.0)
        return float(share)

    def clamp_far_field(self, reach: float) -> "MeshPatient":
        """This patient with its distance exact up to `reach` mm beyond the exact band and
        clamped farther out (the same mesh, shared): its field is then computed slab by slab.

        A run reads the patient's distance only up to its skin and smooth-cut widths
        (and a few voxels for marching cubes and sampling, the band); beyond them
        only the sign matters.
        """
        import copy

        out = copy.copy(self)
        out.far_reach = float(reach)
        return out

    def far_clamp(self, grid: Grid) -> float:
        """The distance (mm) at which :meth:`sdf_grid` on `grid` clamps the far field (as the
        float32 it writes); infinity without a clamp."""
        if self.far_reach is None:
            return float("inf")
        return float(np.float32(self.far_reach + BAND_VOXELS * grid.spacing))

    #: mm beyond the exact band up to which the distance is exact and clamped beyond
    #: (:meth:`clamp_far_field`); None: exact near the surface and a feature transform
    #: of the whole grid farther out
    far_reach: float | None = None

    def sdf_grid(self, grid: Grid, x_range=None) -> np.ndarray:
        """Signed distance on `grid` (the planes `x_range` only, if given), float32, mm,
        negative inside.

        With :attr:`far_reach` set, the distance is clamped at ``far_reach`` plus the
        exact band, and any slab gets the whole grid's values bit for bit. Without it,
        far from the surface the distance comes from a transform of the whole grid, so
        `x_range` must cover the whole grid.
        """
        x0, x1 = (0, grid.shape[0]) if x_range is None else (int(x_range[0]), int(x_range[1]))
        if self.far_reach is None and (x0, x1) != (0, grid.shape[0]):
            raise ScaffoldError(
                f"a mesh patient ({self.name}) without a clamped far field is evaluated on the whole grid, "
                "so this run cannot be tiled: raise --max-memory or use a larger --voxel")
        inside, _ = inside_votes(self.vertices, self.faces, grid, x_range=(x0, x1))
        if self.far_reach is None:
            out = triangle_distance(self.vertices, self.solid_faces, grid)
        else:
            out = clamped_distance(self.vertices, self.solid_faces, grid, x_range=(x0, x1),
                                   reach=self.far_reach + BAND_VOXELS * grid.spacing)
        np.negative(out, out=out, where=inside)
        return out

    def volume_within(self, halfspaces, lo, hi, columns: int = VOLUME_COLUMNS):
        """Volume of the mesh's inside that satisfies ``n . x <= d`` for every half-space, and its bounds.

        Integrated along grid lines: each line's inside intervals (from its crossings)
        are cut exactly by the half-spaces, so the only error is the quadrature across
        the lines at the silhouette of what is kept. A line through a hole in the surface
        crosses it an odd number of times and has no inside intervals to pair: it is left
        out, and the lines run along the axis where the fewest do so (the cheapest first,
        the others only when it has any). Along one axis a hole's whole shadow was lost: a
        femur whose shaft lost 30 triangles (a 218 mm² hole, 0.37 % of its surface), cut
        to the 20 mm around it, read 5,937 mm³ for 9,780 along x, where its lines along
        the shaft pass the hole edge-on.

        Parameters
        ----------
        halfspaces : (k, 4) float ndarray
            Rows ``(nx, ny, nz, d)``, unit normals, mm.
        lo, hi : (3,) float, mm
            A box known to hold everything kept.
        columns : int
            Number of lines.

        Returns
        -------
        volume : float, mm³
        lo, hi : (3,) float64 ndarray or None, mm
            Bounds of what is kept (None when nothing is).
        """
        hs = np.asarray(halfspaces, np.float64).reshape(-1, 4)
        lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
        best = None
        for axis in self._axes_by_cost(lo, hi):
            out, odd = self._volume_along(axis, hs, lo, hi, columns)
            if best is None or odd < best[1]:
                best = (out, odd)
            if odd == 0:
                break
        return best[0]

    def _volume_along(self, axis: int, hs: np.ndarray, lo: np.ndarray, hi: np.ndarray, columns: int):
        """:meth:`volume_within` by lines along `axis`: ``((volume, lo, hi), odd)``, `odd` the area (mm²) of the
        lines that cross the surface an odd number of times within the box's shadow (left out)."""
        size = np.maximum(hi - lo, 1e-9)
        ua, va = _axes_uv(axis)
        hc = math.sqrt(size[ua] * size[va] / columns)
        nu, nv = (max(int(math.ceil(size[a] / hc)), 1) for a in (ua, va))
        hu, hv = size[ua] / nu, size[va] / nv
        u0, v0 = lo[ua] + hu / 2, lo[va] + hv / 2
        col, t = crossings(self.vertices, self.faces, axis, u0, hu, nu, v0, hv, nv)
        order = np.lexsort((t, col))
        col, t = col[order], t[order]
        per_col = np.bincount(col, minlength=nu * nv)
        odd_lines = per_col % 2 == 1
        odd = float(np.count_nonzero(odd_lines)) * hu * hv
        first = np.searchsorted(col, col, side="left")
        rank = np.arange(len(col)) - first
        # entries pair with the next crossing on the same line; a line of an odd count has none to trust
        entry = np.flatnonzero((rank % 2 == 0)[:-1] & (col[1:] == col[:-1]) & ~odd_lines[col[:-1]])
        c, t0, t1 = col[entry], t[entry], t[entry + 1]
        ci, cj = np.divmod(c, nv)
        pu, pv = u0 + ci * hu, v0 + cj * hv
        a = np.full(len(c), lo[axis])
        b = np.full(len(c), hi[axis])
        for nx_, ny_, nz_, d in hs:
            n = np.array([nx_, ny_, nz_])
            rhs = d - n[ua] * pu - n[va] * pv
            if abs(n[axis]) < 1e-12:
                b = np.where(rhs < 0, -np.inf, b)
            elif n[axis] > 0:
                b = np.minimum(b, rhs / n[axis])
            else:
                a = np.maximum(a, rhs / n[axis])
        s0, s1 = np.maximum(t0, a), np.minimum(t1, b)
        keep = s1 > s0
        volume = float(np.sum(s1[keep] - s0[keep]) * hu * hv)
        if not keep.any():
            return (0.0, None, None), odd
        klo, khi = np.empty(3), np.empty(3)
        klo[axis], khi[axis] = s0[keep].min(), s1[keep].max()
        for a_, p_, h_ in ((ua, pu, hu), (va, pv, hv)):
            # a line stands for a cell of width h_: the kept part may reach half a cell beyond it
            klo[a_] = max(p_[keep].min() - h_ / 2, lo[a_])
            khi[a_] = min(p_[keep].max() + h_ / 2, hi[a_])
        return (volume, klo, khi), odd

    def _axes_by_cost(self, lo, hi) -> list[int]:
        """The line directions, those that meet the fewest (triangle, line) pairs in the box ``[lo, hi]`` first."""
        tri = self.vertices[self.faces]
        tmin, tmax = tri.min(axis=1), tri.max(axis=1)
        cost = []
        for axis in range(3):
            ua, va = _axes_uv(axis)
            over = np.all((tmax[:, [ua, va]] >= lo[[ua, va]]) & (tmin[:, [ua, va]] <= hi[[ua, va]]), axis=1)
            ext = np.minimum(tmax[over][:, [ua, va]], hi[[ua, va]]) - np.maximum(tmin[over][:, [ua, va]],
                                                                                  lo[[ua, va]])
            cost.append(float(np.sum(np.prod(np.maximum(ext, 0), axis=1)) / ((hi[ua] - lo[ua]) * (hi[va] - lo[va])
                                                                             + 1e-30)))
        return [int(a) for a in np.argsort(cost, kind="stable")]


def mesh_patient_from_trimesh(mesh, *, name: str, scale: float = 1.0) -> MeshPatient:
    """A :class:`MeshPatient` from a loaded ``trimesh.Trimesh``, cleaned (no NaN check: do it first).

    Vertices are merged and duplicate faces removed (a duplicate would cross a line
    twice at one point and spoil its parity). A closed mesh's surfaces nested one in another
    are wound by their depth (:func:`orient_nested_shells`: a cavity wound outward no longer
    counts as solid); surfaces that cross are joined (:func:`union_of_overlapping_shells`).
    Either warns.
    """
    import trimesh

    v = np.asarray(mesh.vertices, np.float64) * scale
    f = np.asarray(mesh.faces, np.int64)
    m = trimesh.Trimesh(v, f, process=False)
    m.merge_vertices(merge_tex=True, merge_norm=True)
    faces = np.asarray(m.faces)
    key = np.sort(faces, axis=1)
    _, first = np.unique(key, axis=0, return_index=True)
    faces = faces[np.sort(first)]
    # faces with a repeated vertex are points or segments, not surface
    faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])]
    m = trimesh.Trimesh(m.vertices, faces, process=False)
    volume = None
    if len(faces) and m.is_watertight and m.is_winding_consistent:
        import warnings

        from ..errors import ScaffoldWarning

        shells = closed_shells(m)
        nested = orient_nested_shells(m, shells)
        if nested is not None:
            m, cavities, solids = nested
            faces = np.asarray(m.faces, np.int64)
            said = []
            if cavities:
                said.append(f"{cavities} closed surface{'s' if cavities > 1 else ''} inside another "
                            f"{'are' if cavities > 1 else 'is'} wound outward; read as "
                            f"{'cavities' if cavities > 1 else 'a cavity'}")
            if solids:
                said.append(f"{solids} closed surface{'s' if solids > 1 else ''} enclosing solid "
                            f"{'are' if solids > 1 else 'is'} wound inward; read as solid")
            warnings.warn(f"{Path(name).name}: {'; '.join(said)} (the even-odd rule of nested surfaces: the patient "
                          f"{abs(float(m.volume)):.6g} mm3)", ScaffoldWarning, stacklevel=3)
        else:
            union = union_of_overlapping_shells(m, shells)
            if union is not None:
                m, count = union
                faces = np.asarray(m.faces, np.int64)
                warnings.warn(f"{Path(name).name} holds {count} closed surfaces that overlap: the patient is their "
                              f"union ({abs(float(m.volume)):.6g} mm3), not the parity of their crossings",
                              ScaffoldWarning, stacklevel=3)
        volume = abs(float(m.volume))
    return MeshPatient(np.asarray(m.vertices), faces, name=Path(name).name, watertight_volume=volume)


#: meshes of more closed surfaces than this are not checked for nesting or overlaps (a pair test
#: each, and unions): a bone's pieces are a few, a mesh of thousands of specks is noise
UNION_MAX_SHELLS = 64
#: nor meshes of more triangles: a bone surface holds some 10^4 to 10^6; a scaffold's mesh (``analyze``,
#: ``check``) millions, in pieces that do not overlap
UNION_MAX_TRIANGLES = 2_000_000


def closed_shells(mesh):
    """The closed surfaces of a closed, consistently wound mesh, or None: one surface, surfaces
    that meet at a vertex (left to parity), more than :data:`UNION_MAX_SHELLS`, or more than
    :data:`UNION_MAX_TRIANGLES`.

    Returns
    -------
    face_label : (m,) int64 ndarray
        The surface of each of the mesh's faces.
    parts : list of ``trimesh.Trimesh``
        Each surface on its own vertices, as wound in the file.
    """
    import trimesh

    from ..mesh.marching import compiled_kernels

    vertices = np.asarray(mesh.vertices, np.float64)
    faces = np.asarray(mesh.faces, np.int64)
    if len(faces) > UNION_MAX_TRIANGLES:
        return None
    kernels = compiled_kernels()
    # the surfaces by one compiled pass (a scaffold's mesh of millions of triangles is one or a few);
    # surfaces that meet at a vertex are left to parity, as before
    if not kernels["closed_fans"](faces, len(vertices)):
        return None
    vertex_label, count = kernels["vertex_pieces"](faces, len(vertices))
    if not 1 < count <= UNION_MAX_SHELLS:
        return None
    face_label = vertex_label[faces[:, 0]]
    parts = []
    for c in range(count):
        own = faces[face_label == c]
        used, local = np.unique(own, return_inverse=True)
        parts.append(trimesh.Trimesh(vertices[used], local.reshape(-1, 3), process=False))
    return face_label, parts


def _manifold(part, outward: bool = False):
    """`part` (a closed ``trimesh.Trimesh``) as a ``manifold3d.Manifold``, wound outward if asked,
    or None where manifold3d does not take it."""
    import manifold3d

    faces = np.ascontiguousarray(part.faces[:, ::-1] if outward and part.volume < 0 else part.faces, np.uint64)
    solid = manifold3d.Manifold(manifold3d.Mesh64(vert_properties=np.ascontiguousarray(part.vertices, np.float64),
                                                  tri_verts=faces))
    return solid if solid.status() == manifold3d.Error.NoError else None


def orient_nested_shells(mesh, shells=None):
    """A closed mesh whose surfaces are strictly nested, each wound by its nesting depth, or None
    (as wound already, or surfaces that cross, or not :func:`closed_shells`).

    A surface inside no other encloses solid, one inside one other a cavity, inside two an island
    of solid in that cavity, and so on (the even-odd rule of slicers, and what ray parity reads
    inside). The file's winding may disagree: an exporter that fixes normals surface by surface
    winds a bone's medullary canal outward, and the volume then counted the canal as solid, and
    :func:`union_of_overlapping_shells` filled it (a femur's shaft read 9,780 mm3 for 8,213).

    Depth is counted by ray parity from one vertex of each surface against every surface whose box
    holds its box, then checked by manifold3d on the surfaces wound outward: the surfaces of each
    depth enclose disjoint volumes (their union's volume is their sum) and those one deeper lie within
    them (adding them leaves the union's volume as it was). So surfaces that cross fail it, whatever
    the parity of one vertex said, and are left to :func:`union_of_overlapping_shells`. Its cost is
    one parity line per pair of nested boxes and two unions per depth.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        Closed and consistently wound (as :func:`mesh_patient_from_trimesh` checks).
    shells : tuple, optional
        :func:`closed_shells` of `mesh`, if known already.

    Returns
    -------
    mesh : trimesh.Trimesh
        The same vertices and faces in the same order, the faces of the surfaces re-wound reversed.
    cavities : int
        Surfaces at odd depth that were wound outward.
    solids : int
        Surfaces at even depth that were wound inward.
    """
    import trimesh

    shells = closed_shells(mesh) if shells is None else shells
    if shells is None:
        return None
    face_label, parts = shells
    volumes = np.array([float(p.volume) for p in parts])
    if np.any(volumes == 0):
        return None  # a surface enclosing nothing has no winding to read
    size = np.abs(volumes)
    lo = np.array([p.bounds[0] for p in parts])
    hi = np.array([p.bounds[1] for p in parts])
    # holds[j, i]: j's box holds i's box and j encloses more (a surface within another has both)
    holds = np.all((lo[:, None] <= lo[None]) & (hi[None] <= hi[:, None]), axis=2) & (size[:, None] > size[None])
    if not holds.any():
        return None
    depth = np.zeros(len(parts), np.int64)
    for j, i in zip(*np.nonzero(holds)):
        # the line along z through a vertex of i: parity of j's crossings below it. Surfaces that do
        # not cross hold no vertex of i on j, and a line through j's edges or vertices is decided by
        # simulation of simplicity (counted once)
        p = parts[i].vertices[0]
        _, t = crossings(parts[j].vertices, parts[j].faces, 2, float(p[0]), 1.0, 1, float(p[1]), 1.0, 1)
        depth[i] += int(np.count_nonzero(t < p[2])) % 2
    wrong = np.sign(volumes) != np.where(depth % 2, -1.0, 1.0)
    if not wrong.any() or wrong.all():
        # wound as nested (or every surface reversed, which the volume's magnitude reads so): as before
        return None
    import manifold3d

    solids = [_manifold(p, outward=True) for p in parts]
    if any(s is None for s in solids):
        return None

    def union_volume(which):
        chosen = [solids[k] for k in np.flatnonzero(which)]
        return chosen[0].volume() if len(chosen) == 1 else \
            manifold3d.Manifold.batch_boolean(chosen, manifold3d.OpType.Add).volume()

    own = np.array([s.volume() for s in solids])
    for d in range(int(depth.max()) + 1):
        level = depth == d
        enclosed = own[level].sum()
        # relative 1e-9: the booleans' rounding, far below any real overlap of two surfaces
        if level.sum() > 1 and union_volume(level) < enclosed * (1 - 1e-9):
            return None  # two surfaces at one depth overlap: they cross (or parity was misled)
        deeper = depth == d + 1
        if deeper.any() and union_volume(level | deeper) > enclosed * (1 + 1e-9):
            return None  # a surface one deeper reaches out of those at this depth: they cross
    faces = np.array(mesh.faces, np.int64)
    flip = wrong[face_label]
    faces[flip] = faces[flip][:, ::-1]
    odd = depth % 2 == 1
    return (trimesh.Trimesh(np.asarray(mesh.vertices), faces, process=False), int(np.count_nonzero(wrong & odd)),
            int(np.count_nonzero(wrong & ~odd)))


def union_of_overlapping_shells(mesh, shells=None):
    """(the union as a ``trimesh.Trimesh``, the number of surfaces) of a closed mesh's surfaces that
    overlap, or None: not :func:`closed_shells`, none that overlaps another, or one wound inwards (a
    cavity: a hollow bone's inner wall, whose union with the outer one would fill it; a cavity wound
    outward is :func:`orient_nested_shells`'s, to be tried first).

    Inside by ray parity, the part of the patient that two surfaces enclose is crossed twice and
    reads as outside: two copies of the L3 vertebra 20 mm apart, overlapping by 25,327 mm3, left a
    hole there in the scaffold, and the volume was their sum (126,534 mm3 against 101,207). The
    union is manifold3d's boolean (exact on the surfaces' own vertices, closed and 2-manifold).

    Parameters
    ----------
    mesh : trimesh.Trimesh
    shells : tuple, optional
        :func:`closed_shells` of `mesh`, if known already.
    """
    import trimesh

    shells = closed_shells(mesh) if shells is None else shells
    if shells is None:
        return None
    _, parts = shells
    volumes = np.array([float(p.volume) for p in parts])
    if np.any(volumes <= 0):
        return None
    lo = np.array([p.bounds[0] for p in parts])
    hi = np.array([p.bounds[1] for p in parts])
    boxes_meet = np.all((lo[:, None] <= hi[None]) & (lo[None] <= hi[:, None]), axis=2)
    np.fill_diagonal(boxes_meet, False)
    if not boxes_meet.any():
        return None
    import manifold3d

    solids = [_manifold(p) for p in parts]
    if any(s is None for s in solids):
        return None  # not a manifold manifold3d takes: parity, as before
    union = manifold3d.Manifold.batch_boolean(solids, manifold3d.OpType.Add)
    if not union.volume() < volumes.sum() * (1 - 1e-9):
        return None  # the boxes meet, the surfaces do not
    out = union.to_mesh64()
    return trimesh.Trimesh(np.array(out.vert_properties[:, :3], np.float64), np.array(out.tri_verts, np.int64),
                           process=False), len(parts)
