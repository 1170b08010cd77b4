"""Fused vector updates of the voxel solver's conjugate gradients and V-cycle (issue 14).

The solver's vectors cover the whole node grid for a block of load cases, ``(m, 3, N)``, and
NumPy makes one pass over memory (often with a temporary) per operation: on the 128^3 scaffold
of the benchmark the CG's and the fine level's vector arithmetic took some 1.6 s of a 5.6 s
iteration. Each function here is one compiled pass (numba, serial loops on the rows of
:func:`~implicit_scaffold.run.threads.over_rows`, so both cores share it), in place, with no
temporary. A sum is kept per piece of the node axis and the pieces are added in order, so the
result does not depend on the number of threads.

Every vector is C-contiguous ``(m, 3, N)``; a weight ``w`` is ``(1, N)`` or ``(3, N)``
(per node, or per node and component), as the solver's masks and inverse diagonals are.
"""
from __future__ import annotations

import functools

import numpy as np

#: the node axis is cut into this many pieces (the rows handed to the threads)
PIECES = 64
#: the compiled passes' "no array" arguments (their types fixed, so that one compiled version serves every call)
_NONE2 = np.zeros((0, 0))
_NONE3 = np.zeros((0, 0, 0))


@functools.lru_cache(maxsize=None)
def _kernels():
    # the helper _own is a module global, not a closure cell: numba keys its disk cache on a
    # closure's cells, and a dispatcher pickles differently in every process (a fresh compile each run)
    global _own
    import numba as nb

    # each inner loop runs over one contiguous row piece (1-D slices, no branch inside), which
    # LLVM vectorizes
    @nb.njit(cache=True, nogil=True, boundscheck=False)
    def wdot_rows(a, b, w, out, lo, hi):  # pragma: no cover - compiled
        m, _, n = a.shape
        for piece in range(lo, hi):
            n0, n1 = piece * n // out.shape[0], (piece + 1) * n // out.shape[0]
            for c in range(m):
                s = 0.0
                for d in range(3):
                    ad, bd = a[c, d, n0:n1], b[c, d, n0:n1]
                    wd = w[d if w.shape[0] == 3 else 0, n0:n1]
                    for i in range(n1 - n0):
                        # in double whatever the floats: a float32 a times a float32 b is exact there, as
                        # when either comes in double (the CG's p.q with q in the float product's float)
                        s += np.float64(ad[i]) * bd[i] * wd[i]
                out[piece, c] = s

    @nb.njit(cache=True, nogil=True, boundscheck=False)
    def cg_rows(x, p, r, q, w, alpha, out, lo, hi):  # pragma: no cover - compiled
        m, _, n = x.shape
        for piece in range(lo, hi):
            n0, n1 = piece * n // out.shape[0], (piece + 1) * n // out.shape[0]
            for c in range(m):
                a = alpha[c]
                s = 0.0
                for d in range(3):
                    xd, pd, rd, qd = x[c, d, n0:n1], p[c, d, n0:n1], r[c, d, n0:n1], q[c, d, n0:n1]
                    wd = w[d if w.shape[0] == 3 else 0, n0:n1]
                    for i in range(n1 - n0):
                        xd[i] += a * pd[i]
                        v = rd[i] - a * (qd[i] * wd[i])
                        rd[i] = v
                        s += v * v
                out[piece, c] = s

    @nb.njit(cache=True, nogil=True, boundscheck=False)
    def xpby_rows(z, p, beta, pieces, lo, hi):  # pragma: no cover - compiled
        m, _, n = p.shape
        for piece in range(lo, hi):
            n0, n1 = piece * n // pieces, (piece + 1) * n // pieces
            for c in range(m):
                bc = beta[c]
                for d in range(3):
                    zd, pd = z[c, d, n0:n1], p[c, d, n0:n1]
                    for i in range(n1 - n0):
                        pd[i] = zd[i] + bc * pd[i]

    @nb.njit(cache=True, nogil=True, boundscheck=False)
    def weighted_rows(out, b, y, w, s, k, accumulate, pieces, lo, hi):  # pragma: no cover - compiled
        # out = s w (b - k y), or out += that; out may be y itself (k is 0 or 1)
        m, _, n = out.shape
        for piece in range(lo, hi):
            n0, n1 = piece * n // pieces, (piece + 1) * n // pieces
            for c in range(m):
                for d in range(3):
                    od, bd, yd = out[c, d, n0:n1], b[c, d, n0:n1], y[c, d, n0:n1]
                    wd = w[d if w.shape[0] == 3 else 0, n0:n1]
                    if accumulate:
                        for i in range(n1 - n0):
                            od[i] += s * wd[i] * (bd[i] - k * yd[i])
                    else:  # out may hold anything (an empty array): never read
                        for i in range(n1 - n0):
                            od[i] = s * wd[i] * (bd[i] - k * yd[i])

    @nb.njit(cache=True, nogil=True, boundscheck=False)
    def _own(idx, n0, n1, piece, pieces, n):  # pragma: no cover - compiled
        # the grid nodes a piece of idx spreads onto: from the one after its previous piece's last
        # live node to its own last (the last piece: to the grid's end; idx is increasing)
        start = idx[n0 - 1] + 1 if n0 > 0 else 0
        stop = n if piece == pieces - 1 else (idx[n1 - 1] + 1 if n1 > n0 else start)
        return slice(start, stop)

    # a vector on the live nodes only, (m, 3, len(idx)), from the whole grid's (m, 3, N), or
    # spread back onto it; each piece reads or writes its own entries of idx (distinct nodes), so
    # no two pieces race. Spread, a piece first zeroes its own stretch of the grid (_own), so
    # that `out` need not be zeroed by a pass of its own: in cache for the scatter after, and on
    # both cores (128^3 benchmark scaffold, one case in float: put 2.7 against 3.5 ms with the
    # zeroing pass first, put_smoothed 3.7 against 4.3; a zeroing of each gap between live nodes
    # as the scatter met it took 5.4 and 6.8)
    # taking, with dots.shape[0] > 0 also each case's sum of dv * out * dw over the piece (wdot's, in its order)
    @nb.njit(cache=True, nogil=True, boundscheck=False)
    def move_rows(src, idx, w, out, spread, dv, dw, dots, pieces, lo, hi):  # pragma: no cover - compiled
        m, n = src.shape[0], idx.shape[0]
        for piece in range(lo, hi):
            n0, n1 = piece * n // pieces, (piece + 1) * n // pieces
            for c in range(m):
                acc = 0.0
                for d in range(3):
                    wd = w[d if w.shape[0] == 3 else 0]
                    if spread:
                        od = out[c, d]
                        od[_own(idx, n0, n1, piece, pieces, od.shape[0])] = 0
                        for i in range(n0, n1):
                            od[idx[i]] = wd[i] * src[c, d, i]
                    elif dots.shape[0] > 0:
                        dd = dw[d if dw.shape[0] == 3 else 0]
                        for i in range(n0, n1):
                            out[c, d, i] = wd[i] * src[c, d, idx[i]]
                            acc += np.float64(dv[c, d, i]) * out[c, d, i] * dd[i]  # in double, as wdot
                    else:
                        for i in range(n0, n1):
                            out[c, d, i] = wd[i] * src[c, d, idx[i]]
                if dots.shape[0] > 0:
                    dots[piece, c] = acc

    # the fine level of the V-cycle on live-node residuals src: mode 0, the pre-smoothed
    # x = s g (w src) spread onto the grid vector out (g the inverse diagonal on the live nodes,
    # as src); mode 1, w src added onto out (mode 3: subtracted); mode 2, the post-smoothed result's live nodes
    # out = w (x + s g (w src - ax)) taken back (x, ax whole grids). Each piece writes its own
    # entries of idx (distinct nodes); mode 0 zeroes the other nodes as move_rows spreads
    # mode 2 with dots.shape[0] > 0: also each case's sum of src * out over the piece (wdot's with a weight of
    # ones, in its order)
    @nb.njit(cache=True, nogil=True, boundscheck=False)
    def live_rows(src, idx, w, g, s, out, x, ax, mode, dots, pieces, lo, hi):  # pragma: no cover - compiled
        m, n = src.shape[0], idx.shape[0]
        for piece in range(lo, hi):
            n0, n1 = piece * n // pieces, (piece + 1) * n // pieces
            for c in range(m):
                acc = 0.0
                for d in range(3):
                    wd, gd = w[d if w.shape[0] == 3 else 0], g[d if g.shape[0] == 3 else 0]
                    if mode == 0 or mode == 5:
                        od = out[c, d]
                        if mode == 0:  # 5: the other nodes are left as they are
                            od[_own(idx, n0, n1, piece, pieces, od.shape[0])] = 0
                        for i in range(n0, n1):
                            j = idx[i]
                            od[j] = wd[i] * src[c, d, i]
                            od[j] = s * gd[i] * od[j]
                    elif mode == 1:
                        for i in range(n0, n1):
                            out[c, d, idx[i]] += wd[i] * src[c, d, i]
                    elif mode == 3:
                        for i in range(n0, n1):
                            out[c, d, idx[i]] -= wd[i] * src[c, d, i]
                    elif mode == 4:
                        # mode 0's value (rounded to out's float as mode 0 stores it) plus w times out's own,
                        # in the order mode 0 then prolong_add's w P e would give it
                        for i in range(n0, n1):
                            j = idx[i]
                            pe = out[c, d, j]
                            out[c, d, j] = wd[i] * src[c, d, i]
                            v = s * gd[i] * out[c, d, j]
                            out[c, d, j] = v + wd[i] * pe
                    elif dots.shape[0] > 0:
                        for i in range(n0, n1):
                            j = idx[i]
                            out[c, d, i] = wd[i] * (x[c, d, j] + s * gd[i] * (wd[i] * src[c, d, i] - ax[c, d, j]))
                            acc += np.float64(src[c, d, i]) * out[c, d, i]
                    else:
                        for i in range(n0, n1):
                            j = idx[i]
                            out[c, d, i] = wd[i] * (x[c, d, j] + s * gd[i] * (wd[i] * src[c, d, i] - ax[c, d, j]))
                if dots.shape[0] > 0:
                    dots[piece, c] = acc

    # a Chebyshev smoothing step of a coarse level (multigrid._chebyshev), a = A d (or A x) given:
    # mode 0, r -= a; d = c1 d + c2 g r; x += d. Mode 1 (the first step from an iterate x): r = b - a;
    # d = c2 g r; x += d. Mode 2 (the first step from 0, a not read): r = b; d = c2 g b; x = d. Each product rounded to the vectors' float as NumPy's in-place operations round it
    @nb.njit(cache=True, nogil=True, boundscheck=False)
    def chebyshev_rows(r, a, b, dv, x, g, c1, c2, mode, pieces, lo, hi):  # pragma: no cover - compiled
        m, _, n = r.shape
        for piece in range(lo, hi):
            n0, n1 = piece * n // pieces, (piece + 1) * n // pieces
            for c in range(m):
                for d in range(3):
                    rd, ad, bd, dd, xd = r[c, d, n0:n1], a[c, d, n0:n1], b[c, d, n0:n1], dv[c, d, n0:n1], x[c, d, n0:n1]
                    gd = g[d if g.shape[0] == 3 else 0, n0:n1]
                    if mode == 0:
                        for i in range(n1 - n0):
                            v = rd[i] - ad[i]
                            rd[i] = v
                            u = dd[i] * c1
                            t = gd[i] * v
                            t = t * c2
                            u = u + t
                            dd[i] = u
                            xd[i] += u
                    elif mode == 1:
                        for i in range(n1 - n0):
                            v = bd[i] - ad[i]
                            rd[i] = v
                            t = gd[i] * v
                            t = t * c2
                            dd[i] = t
                            xd[i] += t
                    else:
                        for i in range(n1 - n0):
                            v = bd[i]
                            rd[i] = v
                            t = gd[i] * v
                            t = t * c2
                            dd[i] = t
                            xd[i] = t

    # each case's and component's sum over a piece (in double), then that component's mean taken off (center);
    # a value of a table per node by the node's code (lookup: table (m, 3, codes), out (m, 3, len(code)))
    @nb.njit(cache=True, nogil=True, boundscheck=False)
    def sums_rows(a, out, lo, hi):  # pragma: no cover - compiled
        m, _, n = a.shape
        for piece in range(lo, hi):
            n0, n1 = piece * n // out.shape[0], (piece + 1) * n // out.shape[0]
            for c in range(m):
                for d in range(3):
                    ad = a[c, d, n0:n1]
                    s = 0.0
                    for i in range(n1 - n0):
                        s += np.float64(ad[i])
                    out[piece, c, d] = s

    @nb.njit(cache=True, nogil=True, boundscheck=False)
    def shift_rows(a, mu, pieces, lo, hi):  # pragma: no cover - compiled
        m, _, n = a.shape
        for piece in range(lo, hi):
            n0, n1 = piece * n // pieces, (piece + 1) * n // pieces
            for c in range(m):
                for d in range(3):
                    ad = a[c, d, n0:n1]
                    v = mu[c, d]
                    for i in range(n1 - n0):
                        ad[i] -= v

    @nb.njit(cache=True, nogil=True, boundscheck=False)
    def lookup_rows(table, code, out, pieces, lo, hi):  # pragma: no cover - compiled
        m, _, n = out.shape
        for piece in range(lo, hi):
            n0, n1 = piece * n // pieces, (piece + 1) * n // pieces
            for c in range(m):
                for d in range(3):
                    td, od = table[c, d], out[c, d]
                    for i in range(n0, n1):
                        od[i] = td[code[i]]

    # a Lanczos step of multigrid._largest_eigenvalue on w = A (g v): mode 0, w *= g and each piece's v.w; mode 1,
    # w -= alpha v, then w -= beta prev (prev given), and each piece's w.w; mode 2, w /= beta and t = g w (the
    # next product's input). Each product rounded to the vectors' float as NumPy's in-place operations round it,
    # the sums in double
    @nb.njit(cache=True, nogil=True, boundscheck=False)
    def lanczos_rows(w, v, prev, g, t, alpha, beta, mode, out, lo, hi):  # pragma: no cover - compiled
        m, _, n = w.shape
        pieces = out.shape[0]
        for piece in range(lo, hi):
            n0, n1 = piece * n // pieces, (piece + 1) * n // pieces
            acc = 0.0
            for c in range(m):
                for d in range(3):
                    wd, vd = w[c, d, n0:n1], v[c, d, n0:n1]
                    gd = g[d if g.shape[0] == 3 else 0, n0:n1]
                    if mode == 0:
                        for i in range(n1 - n0):
                            x = wd[i] * gd[i]
                            wd[i] = x
                            acc += np.float64(vd[i]) * x
                    elif mode == 1:
                        if prev.shape[2] == n:
                            pd = prev[c, d, n0:n1]
                            for i in range(n1 - n0):
                                x = wd[i] - alpha * vd[i]
                                x = x - beta * pd[i]
                                wd[i] = x
                                acc += np.float64(x) * x
                        else:
                            for i in range(n1 - n0):
                                x = wd[i] - alpha * vd[i]
                                wd[i] = x
                                acc += np.float64(x) * x
                    else:
                        td = t[c, d, n0:n1]
                        for i in range(n1 - n0):
                            x = wd[i] / beta
                            wd[i] = x
                            td[i] = x * gd[i]
            out[piece] = acc

    return wdot_rows, cg_rows, xpby_rows, weighted_rows, move_rows, live_rows, chebyshev_rows, sums_rows, shift_rows, \
        lookup_rows, lanczos_rows


def _weight(w, n: int, dtype) -> np.ndarray:
    """`w` as (rows, n), in `dtype` where it is wider (or not a float): a float32 mask beside float64
    vectors is read as it is (each value widens exactly), not copied a call (8 bytes a live node)."""
    w = np.ascontiguousarray(w).reshape(-1, n)
    dtype = np.dtype(dtype)
    if w.dtype.kind != "f" or w.dtype.itemsize > dtype.itemsize:
        w = w.astype(dtype)
    return w


def _pieces(n: int) -> int:
    return max(1, min(PIECES, n))


def wdot(a: np.ndarray, b: np.ndarray, w) -> np.ndarray:
    """(m,) ``sum a * b * w`` per load case."""
    from ..run.threads import over_rows

    kernel = _kernels()[0]
    n = a.shape[2]
    out = np.zeros((_pieces(n), a.shape[0]))
    over_rows(kernel, out.shape[0], a, b, _weight(w, n, a.dtype), out)
    return out.sum(axis=0)


def cg_update(x: np.ndarray, p: np.ndarray, r: np.ndarray, q: np.ndarray, w, alpha) -> np.ndarray:
    """``x += alpha p``, ``r -= alpha w q`` per load case, in place; returns (m,) ``|r|^2``."""
    from ..run.threads import over_rows

    kernel = _kernels()[1]
    n = x.shape[2]
    out = np.zeros((_pieces(n), x.shape[0]))
    over_rows(kernel, out.shape[0], x, p, r, q, _weight(w, n, x.dtype),
              np.asarray(alpha, x.dtype), out)
    return out.sum(axis=0)


def xpby(z: np.ndarray, p: np.ndarray, beta) -> None:
    """``p = z + beta p`` per load case, in place."""
    from ..run.threads import over_rows

    kernel = _kernels()[2]
    pieces = _pieces(p.shape[2])
    over_rows(kernel, pieces, z, p, np.asarray(beta, p.dtype), pieces)


def _weighted(out, b, w, s, y, accumulate: bool) -> None:
    from ..run.threads import over_rows

    kernel = _kernels()[3]
    n = out.shape[2]
    pieces = _pieces(n)
    over_rows(kernel, pieces, out, b, b if y is None else y, _weight(w, n, out.dtype),
              out.dtype.type(s), out.dtype.type(y is not None), accumulate, pieces)


def weighted(out: np.ndarray, b: np.ndarray, w, s: float = 1.0, y: np.ndarray | None = None) -> np.ndarray:
    """``out = s w (b - y)`` (or ``s w b`` without `y`), in place (`out` may be `y`); returns `out`."""
    _weighted(out, b, w, s, y, False)
    return out


def add_weighted(x: np.ndarray, b: np.ndarray, w, s: float = 1.0, y: np.ndarray | None = None) -> None:
    """``x += s w (b - y)`` (or ``x += s w b`` without `y`), in place."""
    _weighted(x, b, w, s, y, True)


def take(src: np.ndarray, idx: np.ndarray, w, dtype=None, out: np.ndarray | None = None) -> np.ndarray:
    """``w * src[:, :, idx]``: (m, 3, len(idx)) in `dtype` (default `src`'s), one pass (inside
    :func:`~implicit_scaffold.measure.mechanics_cl.reusing`, into memory an array dropped before held),
    or into `out` (an array of that shape, a view of a larger one may do)."""
    from .mechanics_cl import aligned_empty
    from ..run.threads import over_rows

    n = len(idx)
    # from the solver's pool, not np.empty: an array over glibc's 32 MiB mmap threshold is fresh
    # pages every call, which the kernel zeroes (200^3 benchmark scaffold: a case's K p on the live
    # nodes is 84 MB, taken every iteration; 15.6 s of system time in a 62 s solve)
    if out is None:
        out = aligned_empty(src.shape[:2] + (n,), src.dtype if dtype is None else dtype)
    pieces = _pieces(n)
    over_rows(_kernels()[4], pieces, src, idx, _weight(w, n, out.dtype), out, False, _NONE3, _NONE2, _NONE2, pieces)
    return out


def put(src: np.ndarray, idx: np.ndarray, n: int, w, dtype=None) -> np.ndarray:
    """The whole grid's (m, 3, n) vector, ``w * src`` on the nodes `idx` and 0 elsewhere, in
    `dtype` (default `src`'s), page-aligned (the OpenCL operator reads it in place)."""
    from .mechanics_cl import aligned_empty
    from ..run.threads import over_rows

    out = aligned_empty(src.shape[:2] + (int(n),), src.dtype if dtype is None else dtype)  # every entry written
    k = len(idx)
    pieces = _pieces(k)
    over_rows(_kernels()[4], pieces, src, idx, _weight(w, k, out.dtype), out, True, _NONE3, _NONE2, _NONE2, pieces)
    return out


def put_smoothed(src: np.ndarray, idx: np.ndarray, n: int, w, g: np.ndarray, s: float, dtype=None,
                 out: np.ndarray | None = None, zero: bool = True) -> np.ndarray:
    """The whole grid's (m, 3, n) vector ``s g w src`` on the nodes `idx` and 0 elsewhere: one damped
    Jacobi step from zero on the right-hand side :func:`put` would spread (`g` the inverse diagonal
    on the nodes `idx`, (1, len(idx)) or (3, len(idx))), in `dtype` (default `src`'s), page-aligned; or
    into `out` (an array of that shape, a view of a larger one may do). Without `zero`, `out`'s other nodes
    keep their values (a buffer whose other nodes no product reads, :func:`put_smoothed_onto`)."""
    from .mechanics_cl import aligned_empty
    from ..run.threads import over_rows

    if out is None:
        out = aligned_empty(src.shape[:2] + (int(n),), src.dtype if dtype is None else dtype)  # every entry written
    k = len(idx)
    pieces = _pieces(k)
    over_rows(_kernels()[5], pieces, src, idx, _weight(w, k, out.dtype),
              _weight(g, k, out.dtype), out.dtype.type(s), out, out, out, 0 if zero else 5, _NONE2, pieces)
    return out


def put_smoothed_onto(out: np.ndarray, src: np.ndarray, idx: np.ndarray, w, g: np.ndarray, s: float) -> None:
    """``out = s g w src + w out`` on the nodes `idx`, in place (`out` a whole grid's (m, 3, n), say a prolonged
    correction ``P e``): :func:`put_smoothed`'s value with ``w P e`` added (:func:`~implicit_scaffold.measure.multigrid.
    prolong_add`'s arithmetic, bit for bit on those nodes) in one pass over the live nodes, where the two made a pass
    over the whole grid each. The other nodes keep `out`'s values: a product by the fine operator reads none of them
    into a live node's (every corner of a solid voxel is live), so they need not be zeroed."""
    from ..run.threads import over_rows

    k = len(idx)
    pieces = _pieces(k)
    over_rows(_kernels()[5], pieces, src, idx, _weight(w, k, out.dtype), _weight(g, k, out.dtype),
              out.dtype.type(s), out, out, out, 4, _NONE2, pieces)


def put_add(out: np.ndarray, src: np.ndarray, idx: np.ndarray, w, subtract: bool = False) -> None:
    """``out[:, :, idx] += w * src`` (``-=`` with `subtract`), in place (`out` a whole grid's (m, 3, n)
    vector)."""
    from ..run.threads import over_rows

    k = len(idx)
    pieces = _pieces(k)
    wk = _weight(w, k, out.dtype)
    over_rows(_kernels()[5], pieces, src, idx, wk, wk, out.dtype.type(1), out, out, out, 3 if subtract else 1, _NONE2,
              pieces)


def take_smoothed(x: np.ndarray, ax: np.ndarray, src: np.ndarray, idx: np.ndarray, w, g: np.ndarray, s: float,
                  dtype=None, out: np.ndarray | None = None, dot: bool = False):
    """``w (x + s g (w src - ax))`` on the nodes `idx`, (m, 3, len(idx)) in `dtype` (default `src`'s):
    a damped Jacobi step on the right-hand side ``w src`` from `x` (``ax = A x``, whole grids; `g`
    the inverse diagonal on the nodes `idx`), and its live nodes taken, in one pass; or into `out` (an array
    of that shape, a view of a larger one may do). With `dot`, ``(out, (m,) src . out)`` in the same pass, the
    same bits as ``wdot(src, out, ones)`` (the CG's ``r.z``, which read both again)."""
    from .mechanics_cl import aligned_empty
    from ..run.threads import over_rows

    k = len(idx)
    if out is None:
        out = aligned_empty(src.shape[:2] + (k,), src.dtype if dtype is None else dtype)  # as take's
    pieces = _pieces(k)
    dots = np.zeros((pieces, src.shape[0])) if dot else _NONE2
    over_rows(_kernels()[5], pieces, src, idx, _weight(w, k, x.dtype),
              _weight(g, k, x.dtype), x.dtype.type(s), out, x, ax, 2, dots, pieces)
    return (out, dots.sum(axis=0)) if dot else out


def take_dot(src: np.ndarray, idx: np.ndarray, w, v: np.ndarray, vw, dtype=None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`take`'s ``w * src[:, :, idx]`` and, in the same pass, (m,) ``sum v * out * vw`` per case: the same
    bits as ``take`` then ``wdot(v, out, vw)`` (the CG's ``p.Kp`` on the product it takes)."""
    from .mechanics_cl import aligned_empty
    from ..run.threads import over_rows

    n = len(idx)
    out = aligned_empty(src.shape[:2] + (n,), src.dtype if dtype is None else dtype)
    pieces = _pieces(n)
    dots = np.zeros((pieces, src.shape[0]))
    over_rows(_kernels()[4], pieces, src, idx, _weight(w, n, out.dtype), out, False, v, _weight(vw, n, v.dtype),
              dots, pieces)
    return out, dots.sum(axis=0)


def chebyshev_step(r: np.ndarray, a: np.ndarray, d: np.ndarray, x: np.ndarray, g: np.ndarray, c1: float, c2: float,
                   b: np.ndarray | None = None, start: bool = False) -> bool:
    """One step of :func:`~implicit_scaffold.measure.multigrid._chebyshev` in one pass, in place: ``r -= a``,
    ``d = c1 d + c2 g r``, ``x += d`` (`a` = A d); with `b`, the first step from an iterate x (`a` = A x):
    ``r = b - a``, ``d = c2 g r``, ``x += d``; with `b` and `start`, the first step from 0 (`a` not read):
    ``r = b``, ``d = c2 g b``, ``x = d``. `g` is the level's inverse diagonal, (1, N) or (3, N). The
    same bits as those NumPy operations (each product rounded to the vectors' float). Returns False, with
    nothing done, where the arrays are not all (m, 3, N) of one float32 or float64 type (a product may come
    strided: the NumPy operator's coarse levels)."""
    from ..run.threads import over_rows

    arrays = [r, a, d, x] + ([] if b is None else [b])
    dtype = r.dtype
    if dtype.kind != "f" or any(v.dtype != dtype or v.shape != r.shape for v in arrays) \
            or g.dtype != dtype or g.ndim != 2 or g.shape[1] != r.shape[2]:
        return False
    n = r.shape[2]
    pieces = _pieces(n)
    over_rows(_kernels()[6], pieces, r, a, r if b is None else b, d, x, np.ascontiguousarray(g), dtype.type(c1),
              dtype.type(c2), 0 if b is None else (2 if start else 1), pieces)
    return True


def center(z: np.ndarray) -> np.ndarray:
    """`z` (m, 3, N) less each case's and component's mean, in place: the mean summed in double (a piece's sum at a
    time, added in order), rounded to `z`'s float and taken off, as ``z -= z.mean(axis=2, keepdims=True,
    dtype=np.float64).astype(z.dtype)`` (whose pairwise sum rounds in another order); returns `z`. Two passes on
    both cores, where NumPy's mean and subtraction were two on one (128^3 benchmark scaffold: some 0.3 s of a
    homogenization's 11 s)."""
    from ..run.threads import over_rows

    kernels = _kernels()
    n = z.shape[2]
    pieces = _pieces(n)
    sums = np.zeros((pieces, z.shape[0], 3))
    over_rows(kernels[7], pieces, z, sums)
    mu = (sums.sum(axis=0) / max(n, 1)).astype(z.dtype)
    over_rows(kernels[8], pieces, z, mu, pieces)
    return z


def lookup(table: np.ndarray, code: np.ndarray, dtype=np.float64) -> np.ndarray:
    """(m, 3, len(code)): ``table[c, d, code[i]]`` for each case c and component d (`table` (m, 3, K), `code`
    integers in ``range(K)``), in `dtype`, one pass on both cores (NumPy's take: 18 passes on one)."""
    from ..run.threads import over_rows

    table = np.ascontiguousarray(table, dtype)
    out = np.empty(table.shape[:2] + (len(code),), dtype)
    pieces = _pieces(len(code))
    over_rows(_kernels()[9], pieces, table, np.ascontiguousarray(code), out, pieces)
    return out


def lanczos_pass(mode: int, w: np.ndarray, v: np.ndarray, g: np.ndarray, *, alpha: float = 0.0, beta: float = 1.0,
                 prev: np.ndarray | None = None, t: np.ndarray | None = None) -> float | None:
    """One pass of a Lanczos step (:func:`~implicit_scaffold.measure.multigrid._largest_eigenvalue`) on the product
    ``w = A (g v)``, in place: mode 0, ``w *= g``, returns ``v . w``; mode 1, ``w -= alpha v`` and ``w -= beta prev``
    (with `prev`), returns ``w . w``; mode 2, ``w /= beta`` and ``t = g w``, returns 0. `g` is (1, N) or (3, N), the
    vectors (m, 3, N); each product rounded to their float as NumPy's in-place operations round it, the sums in
    double (NumPy's vdot and norm summed in the vectors' float). On both cores, where NumPy made some ten passes a
    step on one (128^3 benchmark scaffold: 0.19 s of the fine level's 0.33 s estimate). None, with nothing done,
    where the arrays are not all of one float32 or float64 type and shape (a product may come in another float:
    the NumPy operator's)."""
    from ..run.threads import over_rows

    arrays = [w, v] + [a for a in (prev, t) if a is not None]
    dtype = w.dtype
    if dtype.kind != "f" or any(a.dtype != dtype or a.shape != w.shape or not a.flags.c_contiguous for a in arrays) \
            or g.dtype != dtype or g.ndim != 2 or g.shape[1] != w.shape[2]:
        return None
    n = w.shape[2]
    out = np.zeros(_pieces(n))
    over_rows(_kernels()[10], out.shape[0], w, v, _NONE3.astype(dtype) if prev is None else prev,
              np.ascontiguousarray(g), _NONE3.astype(dtype) if t is None else t, dtype.type(alpha), dtype.type(beta),
              mode, out)
    return float(out.sum())
