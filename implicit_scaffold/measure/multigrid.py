"""A geometric multigrid preconditioner for the voxel finite-element solver (issue 14).

The FFT reference-medium preconditioner of :mod:`~implicit_scaffold.measure.mechanics` needs hundreds
of iterations on thin struts: the void's infinite contrast is what it cannot see. Multigrid
over the solid (ParOSol's approach for bone micro-FE) sees it, because every coarse operator
is built from the solid itself:

- **Grids.** Each coarse node grid keeps every other node of the finer one, on the same
  periodic node grid the solver uses (a box sample is padded by a void layer, so it never
  wraps). An axis of odd length ends in a coarse element one fine element long, so any grid
  coarsens, down to at most 1,000 unknowns, which are solved exactly (a pseudo-inverse:
  the periodic problem keeps its rigid translations).
- **Transfer.** Prolongation is trilinear interpolation from the coarse corners; restriction
  is its transpose.
- **Coarse operators** are Galerkin's, ``A_c = P^T F A F P`` with ``F`` the mask of the free
  unknowns, assembled element by element: the fine nodes inside a coarse element are
  interpolated from its eight corners only, so ``A_c`` is a sum of 24 x 24 coarse element
  matrices, each the sum over its (up to eight) children of ``W^T K_child W``. The
  first coarse level has few distinct matrices (a child pattern of 8 bits on an unmasked
  element), which are computed once and shared; deeper levels keep one matrix per element.
  Galerkin operators keep a thin strut's stiffness on the coarse grid, where re-discretising
  with averaged moduli would smear it over its neighbours' void.
- **Smoothing**: Chebyshev polynomials in ``D^-1 A`` on the upper part ``[0.05, 1.1] x`` the
  largest eigenvalue (estimated by Lanczos steps), the smoother of PETSc's GAMG (whose default
  lower end, 0.1, took more iterations here: :data:`LOWER`): degree 1
  (damped Jacobi) on the fine grid, where every product costs a pass of the OpenCL operator
  (on a 30 % Voronoi scaffold at 32^3: 23 iterations with 3 fine products each, against 25
  with 5 for degree 2 everywhere), degree 1 on the first coarse level too, whose product builds
  27 stencil blocks per node (six cases: 64.5 ms against 24.5 for one case of the fine product,
  128^3 benchmark scaffold), and degree 3 below, where it is cheap. On that scaffold, the CG's
  products in float, the first level's degree 3, 2 and 1 took 35, 37 and 41 iterations and
  50.1, 46.6 and 45.2 s (a throw-away script; 59.1, 48.1 and 45.7 s in a second round, the
  machine shared in part). A polynomial in ``D^-1 A`` is symmetric, so the V-cycle is a
  symmetric preconditioner, as conjugate gradients need; it is also positive definite only while
  no eigenvalue lies above the smoothing's interval (Jacobi's weight times the largest eigenvalue
  under 2), which is why that eigenvalue is estimated by Lanczos (:func:`_largest_eigenvalue`).
  On a block of six load cases the first level runs degree 2 (:data:`FIRST_BLOCK_DEGREE`): its product,
  by the child patterns' kernel with each node's stencil built once for the block, then costs a case
  some 3.7 ms against 11 for a fine product (128^3 benchmark scaffold), and the iterations fell from 23
  to 19 there (64^3 and 96^3 crops of it under kinematic conditions: 20 to 15 and 21 to 17; degree 3:
  18 on the 128^3, higher degrees below the first level: no fewer). One case a block keeps degree 1:
  its first level's product, by the per-element kernel, builds each node's stencil for the one case.

The fine operator is the solver's own (the OpenCL kernel or its NumPy reference). With the
OpenCL one the coarse levels run on the device too (a gather kernel of the same file, one matrix
per element, a block of load cases a launch; on the first level, the elements that are a 0/1 sum
of eight fixed child matrices by a kernel of the fine operator's kind, :func:`child_matrices`);
with the NumPy one, compiled (numba) on both cores.
Under CG to 1e-6 the cycle runs in float32. Units: mm, GPa.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

#: the coarsest level is solved exactly when it has at most this many unknowns
COARSEST_UNKNOWNS = 1000
#: Chebyshev smoothing: degree (coarse levels below the first; the fine level; the first
#: coarse level) and the share of the largest eigenvalue it targets
DEGREE = 3
FINE_DEGREE = 1
FIRST_DEGREE = 1
#: the first coarse level's degree on a block of at least :data:`FIRST_BLOCK_CASES` load cases, whose product
#: (the child patterns' kernel) builds each node's stencil once for the block: a case's share of a product is
#: then a fraction of a fine product's, and a stronger smoother there saves iterations (see the module's notes)
FIRST_BLOCK_DEGREE = 2
FIRST_BLOCK_CASES = 6
#: the smoothing's interval, ``[LOWER, UPPER] x`` each level's largest eigenvalue (degree 1: the damped Jacobi
#: step ``1 / theta``, theta its middle). A lower end of 0.05 where PETSc's GAMG takes 0.1 (throw-away scripts, the
#: CG to 1e-6 or an energy accuracy of 1e-6; iterations at 0.1, 0.05 and 0.02): the 128^3 benchmark scaffold's
#: six periodic cases 19, 18 and 18, one case a block 23, 23 and 23, its compression 44, 43 and 43; its 96^3
#: corner's six kinematic cases 18, 17 and 17; the 200^3 benchmark scaffold's six periodic cases 20, 20 and 24
#: (0.03: 24; fine products 400, 400 and 447); the lumbar micro-CT's central 96^3 (../shared/data) compressed
#: 121, 113 and 107, its six kinematic cases 23, 21 and 20
LOWER = 0.05
UPPER = 1.1
#: Lanczos steps of the estimate of each level's largest eigenvalue of ``D^-1 A`` (one product each)
LANCZOS_STEPS = 12
#: the first coarse level's device product takes its elements' child patterns (8 fixed matrices,
#: :func:`child_matrices`) where it can; False: one gathered matrix per element everywhere
FIRST_LEVEL_PATTERNS = True

#: the fine level of the CG's V-cycle (:meth:`Multigrid.compact`) runs by slabs of this many nodes' node
#: planes (whole planes, at least one) where the grid has more and the operator can
#: (:meth:`~implicit_scaffold.measure.mechanics_cl.StiffnessOperator.slab`): no whole-grid vector is made;
#: 0: over the whole grid. None: :data:`~implicit_scaffold.measure.mechanics_cl.FLOAT_SLAB_NODES` on a grid
#: of more than :data:`~implicit_scaffold.measure.mechanics_cl.FLOAT_SLABS_FROM` nodes, else the whole grid
FINE_SLAB_NODES = None

#: the levels under the first run on the device from assembled node stencils
#: (:func:`node_stencils`, ``StencilLevelOperator``); False: one gathered matrix per element
STENCIL_LEVELS = True


def fine_slab_planes(shape, slab_nodes: int | None = None) -> int:
    """The node planes (along the first axis) a slab of the V-cycle's fine level holds inside its halo on a
    node grid of `shape`, by :data:`FINE_SLAB_NODES`, or by `slab_nodes` when given (and that is None);
    ``shape[0]`` where the whole grid is one slab."""
    from .mechanics_cl import FLOAT_SLAB_NODES, FLOAT_SLABS_FROM

    n1, n2, n3 = (int(v) for v in shape)
    plane = n2 * n3
    if FINE_SLAB_NODES is None and slab_nodes is not None:
        nodes = int(slab_nodes)
    elif FINE_SLAB_NODES is None:
        nodes = FLOAT_SLAB_NODES if n1 * plane > FLOAT_SLABS_FROM else 0
    else:
        nodes = FINE_SLAB_NODES
    return min(n1, max(1, nodes // plane)) if nodes else n1


# ----------------------------------------------------------------------------- compiled kernels


def kernels_loaded() -> bool:
    """Whether this process has loaded the compiled level kernels (:func:`_kernels`) already."""
    return _kernels.cache_info().currsize > 0


@functools.lru_cache(maxsize=None)
def _kernels():
    """The compiled level kernels (numba), built on first use and cached on disk:

    - ``galerkin(fine_index, fine_mats, fine_free, elems, out)``: the coarse element
      matrices ``sum over children W^T (F K_child F) W`` of the coarse elements ``elems``;
    - ``apply(index, mats, x, y)``: ``y = A x`` of a coarse level, one node per work item,
      gathering the rows of the (up to eight) elements around it (no races);
    - ``transfer(src, out, stencils, last_first)``: a prolongation or a restriction (a separable
      stencil), in two passes.
    """
    import numba as nb

    from ..run.threads import by_rows, over_rows

    @nb.njit(cache=True, nogil=True, boundscheck=False)
    def galerkin_rows(fine_index, fine_mats, fine_free, elems, out, lo, hi):  # pragma: no cover - compiled
        f1, f2, f3 = fine_index.shape
        for e in range(lo, hi):
            ci, cj, ck = elems[e, 0], elems[e, 1], elems[e, 2]
            lx = 2 if 2 * ci + 2 <= f1 else 1
            ly = 2 if 2 * cj + 2 <= f2 else 1
            lz = 2 if 2 * ck + 2 <= f3 else 1
            acc = np.zeros((24, 24))
            w = np.empty((8, 8))
            fm = np.empty(24)
            t = np.empty((24, 24))
            for a in range(lx):
                for b in range(ly):
                    for c in range(lz):
                        fe = fine_index[2 * ci + a, 2 * cj + b, 2 * ck + c]
                        if fe < 0:
                            continue
                        K = fine_mats[fe]
                        # W[q, r]: weight of coarse corner r at this child's corner q
                        for q in range(8):
                            qx, qy, qz = q & 1, (q >> 1) & 1, (q >> 2) & 1
                            tx = (a + qx) / lx
                            ty = (b + qy) / ly
                            tz = (c + qz) / lz
                            for r in range(8):
                                wx = tx if (r & 1) else 1.0 - tx
                                wy = ty if ((r >> 1) & 1) else 1.0 - ty
                                wz = tz if ((r >> 2) & 1) else 1.0 - tz
                                w[q, r] = wx * wy * wz
                            node = ((((2 * ci + a + qx) % f1) * f2 + (2 * cj + b + qy) % f2) * f3
                                    + (2 * ck + c + qz) % f3)
                            for d in range(3):
                                fm[3 * q + d] = fine_free[d, node]
                        # t = (F K F) W, column by column of W's coarse corners
                        for i in range(24):
                            for r in range(8):
                                for d in range(3):
                                    s = 0.0
                                    for q in range(8):
                                        if w[q, r] != 0.0:
                                            s += w[q, r] * K[i, 3 * q + d] * fm[3 * q + d]
                                    t[i, 3 * r + d] = s * fm[i]
                        for r2 in range(8):
                            for d2 in range(3):
                                for j in range(24):
                                    s = 0.0
                                    for q in range(8):
                                        if w[q, r2] != 0.0:
                                            s += w[q, r2] * t[3 * q + d2, j]
                                    acc[3 * r2 + d2, j] += s
            for i in range(24):
                for j in range(24):
                    out[e, i, j] = acc[i, j]

    @nb.njit(cache=True, nogil=True, boundscheck=False)
    def apply_rows(index, mats, x, y, qtab, lo, hi):  # pragma: no cover - compiled
        # x, y: (N, 3, m), node-major, so that a node's load cases are read together. The
        # 27 neighbours are wrapped once per node and read once into U; qtab[b, a] is where
        # corner a of the element whose corner b is this node sits among them.
        n1, n2, n3 = index.shape
        m = x.shape[2]
        for i in range(lo, hi):
            I = np.empty(3, np.int64)
            J = np.empty(3, np.int64)
            K = np.empty(3, np.int64)
            U = np.empty((27, 3, m))
            acc = np.empty((3, m))
            around = np.empty(8, np.int64)
            I[0], I[1], I[2] = (i - 1) % n1, i, (i + 1) % n1
            for j in range(n2):
                J[0], J[1], J[2] = (j - 1) % n2, j, (j + 1) % n2
                for k in range(n3):
                    K[0], K[1], K[2] = (k - 1) % n3, k, (k + 1) % n3
                    node = (i * n2 + j) * n3 + k
                    live = False
                    for b in range(8):
                        mi = index[I[1 - (b & 1)], J[1 - ((b >> 1) & 1)], K[1 - ((b >> 2) & 1)]]
                        around[b] = mi
                        live = live or mi >= 0
                    if not live:
                        for d in range(3):
                            for c in range(m):
                                y[node, d, c] = 0.0
                        continue
                    for q in range(27):
                        nq = (I[q % 3] * n2 + J[(q // 3) % 3]) * n3 + K[q // 9]
                        for d in range(3):
                            for c in range(m):
                                U[q, d, c] = x[nq, d, c]
                    acc[:] = 0.0
                    for b in range(8):
                        mi = around[b]
                        if mi < 0:
                            continue
                        for a in range(8):
                            q = qtab[b, a]
                            for d in range(3):
                                r0 = mats[mi, 3 * b + d, 3 * a]
                                r1 = mats[mi, 3 * b + d, 3 * a + 1]
                                r2 = mats[mi, 3 * b + d, 3 * a + 2]
                                for c in range(m):
                                    acc[d, c] += r0 * U[q, 0, c] + r1 * U[q, 1, c] + r2 * U[q, 2, c]
                    for d in range(3):
                        for c in range(m):
                            y[node, d, c] = acc[d, c]

    # the transfers in two passes of a separable stencil: along the last axis alone (axis_rows,
    # arrays seen as (A, n, 1)), and along the first two together (plane_rows, arrays seen as
    # (A, n1, n2, B): each term a contiguous row of B words, which LLVM vectorizes). Zero weights
    # are skipped. The one intermediate grid is a quarter of the fine one. One pass of the
    # whole stencil, gathering 8 (prolongation) to 27 (restriction) words per output, took 245 and
    # 165 ms a call on the 96^3 scaffold, six cases, the machine loaded
    @nb.njit(cache=True, nogil=True, boundscheck=False)
    def axis_rows(src, out, idx, w, lo, hi):  # pragma: no cover - compiled
        n = out.shape[1]
        taps = idx.shape[1]
        for a in range(lo, hi):
            for i in range(n):
                v = 0.0
                for s in range(taps):
                    v += w[i, s] * src[a, idx[i, s]]
                out[a, i] = v

    # mode 0: out = the plane sums of src's rows; 1: those of src's rows times w's (a restriction of
    # w r, without the pass that makes w r; w on src's grid); 2: out += w times them (a prolongation
    # added onto out, without the whole-grid correction and the pass that adds it; w on out's
    # grid); 3: out += them (mode 2 without a weight). The sums are in the same order in every mode. w is (1 or 3, n1, n2, n3), a row's
    # component a % 3 (a (1, 1, 1, 1) dummy in mode 0)
    @nb.njit(cache=True, nogil=True, boundscheck=False)
    def plane_rows(src, out, ia, wa, ib, wb, w, mode, lo, hi):  # pragma: no cover - compiled
        m, _, n2, nb_ = out.shape
        row = np.empty(nb_, out.dtype)
        for i in range(lo, hi):
            for a in range(m):
                wr = w[a % 3 if w.shape[0] == 3 else 0]
                for j in range(n2):
                    o = row if mode >= 2 else out[a, i, j]
                    o[:] = 0.0
                    for s in range(ia.shape[1]):
                        for t in range(ib.shape[1]):
                            wst = wa[i, s] * wb[j, t]
                            if wst == 0.0:
                                continue
                            v = src[a, ia[i, s], ib[j, t]]
                            if mode == 1:
                                u = wr[ia[i, s], ib[j, t]]
                                for k in range(nb_):
                                    o[k] += wst * (v[k] * u[k])
                            else:
                                for k in range(nb_):
                                    o[k] += wst * v[k]
                    if mode == 2:
                        oo, u = out[a, i, j], wr[i, j]
                        for k in range(nb_):
                            oo[k] += u[k] * row[k]
                    elif mode == 3:
                        oo = out[a, i, j]
                        for k in range(nb_):
                            oo[k] += row[k]

    def galerkin(fine_index, fine_mats, fine_free, elems, out):
        over_rows(galerkin_rows, elems.shape[0], fine_index, fine_mats, fine_free, elems, out)

    def transfer(src, out, stencils, last_first, weight=None, add=False):
        from .mechanics_cl import aligned_empty

        # src (m, 3, s1, s2, s3) -> out (m, 3, n1, n2, n3) through stencils[axis] = (idx, w); the
        # last axis first (a prolongation: the intermediate is the coarse planes' fine rows) or
        # after the first two (a restriction: the fine rows of the coarse planes). With `weight` on
        # the fine grid ((1 or 3, fine nodes)): a prolongation is added onto out times it, a
        # restriction restricts src times it; with `add` and no weight, a prolongation is added onto out
        (ia, wa), (ib, wb), (ig, wg) = [(i, w.astype(src.dtype)) for i, w in stencils]
        m = src.shape[0] * 3
        s1, s2, s3 = src.shape[2:]
        n1, n2, n3 = out.shape[2:]
        if weight is None:
            mode, w = 3 if add and last_first else 0, np.ones((1, 1, 1, 1), src.dtype)
        else:  # on the fine grid: out's for a prolongation, src's for a restriction
            mode, w = (2, weight.reshape(-1, n1, n2, n3)) if last_first else (1, weight.reshape(-1, s1, s2, s3))
        if last_first:
            mid = aligned_empty((m, s1, s2, n3), src.dtype)  # from the solver's pool (reusing)
            over_rows(axis_rows, m * s1 * s2, src.reshape(m * s1 * s2, s3), mid.reshape(m * s1 * s2, n3), ig, wg)
            over_rows(plane_rows, n1, mid, out.reshape(m, n1, n2, n3), ia, wa, ib, wb, w, mode)
        else:
            mid = aligned_empty((m, n1, n2, s3), src.dtype)
            over_rows(plane_rows, n1, src.reshape(m, s1, s2, s3), mid, ia, wa, ib, wb, w, mode)
            over_rows(axis_rows, m * n1 * n2, mid.reshape(m * n1 * n2, s3), out.reshape(m * n1 * n2, n3), ig, wg)

    return galerkin, by_rows(apply_rows), transfer


#: qtab[b, a]: among a node's 27 neighbours (x fastest, offsets -1, 0, 1), corner a of the
#: element of which the node is corner b
_QTAB = np.array([[sum(3 ** ax * (1 - ((b >> ax) & 1) + ((a >> ax) & 1)) for ax in range(3)) for a in range(8)]
                  for b in range(8)], np.int64)


# ----------------------------------------------------------------------------- transfer


def coarse_shape(shape) -> tuple:
    """The coarse node grid of a periodic node grid: every other node, ``ceil(n / 2)``."""
    return tuple((int(n) + 1) // 2 for n in shape)


@functools.lru_cache(maxsize=64)
def _stencils(n: int):
    """The 1-D transfer stencils of a periodic axis of `n` fine nodes.

    Returns
    -------
    parents, weights : (n, 2) int64, (n, 2) float64
        The coarse nodes each fine node interpolates (fine ``2 I``: ``I`` alone; an odd one:
        half of each neighbour).
    children, shares : (ceil(n / 2), 3) int64, (ceil(n / 2), 3) float64
        The transpose: fine nodes ``2 I - 1, 2 I, 2 I + 1`` of coarse node ``I`` and their
        weights (0 where that node is even or missing, at an odd axis' end).
    """
    mc = (n + 1) // 2
    i = np.arange(n)
    lo = i // 2
    odd = i % 2 == 1
    parents = np.stack([lo, np.where(odd, (lo + 1) % mc, lo)], axis=1)
    weights = np.stack([np.where(odd, 0.5, 1.0), np.where(odd, 0.5, 0.0)], axis=1)
    c = np.arange(mc)
    children = np.stack([(2 * c - 1) % n, 2 * c, np.minimum(2 * c + 1, n - 1)], axis=1)
    shares = np.stack([np.where(((2 * c - 1) % n) % 2 == 1, 0.5, 0.0), np.ones(mc),
                       np.where(2 * c + 1 < n, 0.5, 0.0)], axis=1)
    return parents, weights, children, shares


def prolong(y: np.ndarray, fine_shape) -> np.ndarray:
    """Trilinear interpolation of coarse nodal values (m, 3, Nc) onto the fine grid (m, 3, N)."""
    from .mechanics_cl import aligned_empty

    m = y.shape[0]
    fine_shape = tuple(int(v) for v in fine_shape)
    out = aligned_empty((m, 3) + fine_shape, y.dtype)  # read in place by the OpenCL operator
    _kernels()[2](np.ascontiguousarray(y).reshape((m, 3) + coarse_shape(fine_shape)), out,
                  [_stencils(n)[:2] for n in fine_shape], True)
    return out.reshape(m, 3, -1)


def prolong_add(y: np.ndarray, x: np.ndarray, w: np.ndarray | None, fine_shape) -> None:
    """``x += w * prolong(y)`` in place, in one pass over x (`w` (1, N) or (3, N) on the fine grid, or None:
    ``x += prolong(y)``; the same arithmetic, without the whole-grid correction)."""
    fine_shape = tuple(int(v) for v in fine_shape)
    m = y.shape[0]
    _kernels()[2](np.ascontiguousarray(y).reshape((m, 3) + coarse_shape(fine_shape)),
                  x.reshape((m, 3) + fine_shape), [_stencils(n)[:2] for n in fine_shape], True,
                  None if w is None else np.ascontiguousarray(w, x.dtype), add=True)


def restrict(r: np.ndarray, fine_shape, w: np.ndarray | None = None) -> np.ndarray:
    """The transpose of :func:`prolong`: fine nodal values (m, 3, N) summed onto the coarse grid
    (those of ``w * r`` with `w`, (1, N) or (3, N) on the fine grid, without a pass to make them)."""
    from .mechanics_cl import aligned_empty

    m = r.shape[0]
    fine_shape = tuple(int(v) for v in fine_shape)
    cshape = coarse_shape(fine_shape)
    out = aligned_empty((m, 3) + cshape, r.dtype)  # read in place by the OpenCL operator
    _kernels()[2](np.ascontiguousarray(r).reshape((m, 3) + fine_shape), out, [_stencils(n)[2:] for n in fine_shape],
                  False, None if w is None else np.ascontiguousarray(w, r.dtype))
    return out.reshape(m, 3, -1)


def _blocks(grid: np.ndarray) -> np.ndarray:
    """(m1, m2, m3, 8) view of a fine element grid by coarse element and child (a + 2b + 4c),
    a missing child (an odd axis' last coarse element) reading as the fill value (0 or -1)."""
    pad = [(0, n % 2) for n in grid.shape]
    fill = -1 if grid.dtype.kind == "i" else 0
    g = np.pad(grid, pad, constant_values=fill)
    m1, m2, m3 = (s // 2 for s in g.shape)
    g = g.reshape(m1, 2, m2, 2, m3, 2).transpose(0, 2, 4, 5, 3, 1)  # ..., c, b, a
    return g.reshape(m1, m2, m3, 8)


# ----------------------------------------------------------------------------- levels


@dataclass
class Level:
    """One coarse level: its node grid, element matrices and smoother.

    Attributes
    ----------
    shape : (3,) ints
        Node grid (= element grid, periodic).
    index : (n1, n2, n3) int32 ndarray
        Each element's matrix in `mats`; -1 for an element with no solid below it.
    mats : (nm, 24, 24) float ndarray or None, GPa mm
        None once a :class:`~implicit_scaffold.measure.mechanics_cl.StencilLevelOperator` holds
        the level's product (its node stencils).
    inv_diag : (3, N) float ndarray
        The inverse of the operator's diagonal (0 on unknowns no solid reaches).
    lmax : float
        The largest eigenvalue of ``D^-1 A`` (estimated).
    device : callable or None
        The same product on the OpenCL device
        (:class:`~implicit_scaffold.measure.mechanics_cl.LevelOperator`), used (for one load case or a block) when set.
    pattern : (n1, n2, n3) uint8 ndarray or None
        The first level's: each element's child bits (``a + 2b + 4c``) when its matrix is
        ``sum_c solid_c M_c`` (:func:`child_matrices`: no fixed unknown, full length along every
        axis), else 0 (its matrix is its own, in `mats`).
    """

    shape: tuple
    index: np.ndarray
    mats: np.ndarray
    inv_diag: np.ndarray
    lmax: float = 2.0
    device: object = None
    pattern: np.ndarray | None = None

    def apply(self, x: np.ndarray) -> np.ndarray:
        """``A x`` for (m, 3, N) nodal values."""
        # on the device when there is one, for one case or a block (in the cycle, 64^3 scaffold:
        # the first level's product of six cases 0.020 s there against 0.037 s compiled here,
        # which also transposes the block to node-major order and back)
        if self.device is not None:
            return self.device(x)
        apply = _kernels()[1]
        xt = np.ascontiguousarray(x.transpose(2, 1, 0))
        y = np.empty_like(xt)
        apply(self.index, self.mats, xt, y, _QTAB)
        return y.transpose(2, 1, 0)

    def matrix(self) -> np.ndarray:
        """(3 N, 3 N) dense matrix of the level (unknown ``d N + node``): for the coarsest only."""
        n = int(np.prod(self.shape))
        A = np.zeros((3 * n, 3 * n))
        e = np.flatnonzero(self.index.ravel() >= 0)
        ijk = np.array(np.unravel_index(e, self.shape))  # (3, ne)
        dims = np.array(self.shape)[:, None]
        nodes = np.stack([np.ravel_multi_index(tuple((ijk + np.array(off)[:, None]) % dims), self.shape)
                          for off in ((a & 1, (a >> 1) & 1, (a >> 2) & 1) for a in range(8))])  # (8, ne)
        dof = (np.arange(3)[None, :, None] * n + nodes[:, None, :]).reshape(24, -1)  # (24, ne), corner-major
        M = self.mats[self.index.ravel()[e]]  # (ne, 24, 24)
        np.add.at(A, (dof.T[:, :, None], dof.T[:, None, :]), M)
        return A


#: the neighbours whose blocks :func:`node_stencils` stores per node: the node itself (13) and the 13 at
#: offsets after it; the others' blocks are their transposes, stored at the neighbour (the matrix is symmetric)
STENCIL_OWN = 13


def node_stencils(level: Level) -> tuple[np.ndarray, np.ndarray]:
    """A level's product as assembled node stencils, half of them (the layout of ``stencil_rows`` in
    ``kernels/mechanics.cl``).

    A level's matrix is symmetric: the 3 x 3 block of neighbour q at node n is the transpose of the
    block of neighbour ``26 - q`` at node ``n + offset(q)``. So each node keeps the blocks of the
    neighbours ``q >= 13`` (:data:`STENCIL_OWN`: itself and the 13 after it), 126 words where the 27
    blocks took 243, and the kernel reads the others, transposed, at the neighbour: on the 128^3
    benchmark scaffold the 32^3 level's stencils and those below took 58 bytes a solid voxel of the
    one-case solve's peak. :func:`full_stencils` gives the 27 blocks back.

    Built a node plane (along the first axis) at a time, into the array returned: a whole-grid build and
    then a copy to the kernel's layout held them twice.

    Returns
    -------
    stencils : (n1 n2, 126, n3) float ndarray of the level's float, page-aligned, GPa mm
        By node row, as the kernel reads them (:func:`~implicit_scaffold.measure.mechanics_cl.aligned_empty`:
        the device reads the array in place): ``[r, x, k]`` is entry x of node (r, k) (r = i n2 + j),
        entry ``9 (q - 13) + 3 d + e`` row d, column e of the 3 x 3 block that neighbour q >= 13 (offset
        ``(q % 3, q // 3 % 3, q // 9) - 1``) adds to a node's force, summed over the elements
        around the node (rows ``3 b + d`` and columns ``3 a + e`` of each one's matrix, the node
        its corner b and the neighbour its corner a).
    live : (N,) uint8 ndarray
        1 at a node some element touches.
    """
    from .mechanics import CORNERS
    from .mechanics_cl import aligned_empty

    n1, n2, n3 = level.shape
    plane = n2 * n3
    kept = 27 - STENCIL_OWN
    out = aligned_empty((n1 * n2, 9 * kept, n3), level.mats.dtype)
    live = np.zeros(n1 * plane, np.uint8)
    one = np.zeros((kept, 3, 3, plane), level.mats.dtype)
    for i in range(n1):
        one.fill(0)
        for b in range(8):
            # the element whose corner b this node is has its low corner at node - offset(b)
            o = CORNERS[b]
            e = np.roll(level.index[(i - int(o[0])) % n1], (int(o[1]), int(o[2])), axis=(0, 1)).ravel()
            has = np.flatnonzero(e >= 0)
            live[i * plane + has] = 1
            rows = level.mats[e[has], 3 * b: 3 * b + 3]  # (k, 3, 24)
            for a in range(8):
                q = int(_QTAB[b, a])
                if q >= STENCIL_OWN:
                    one[q - STENCIL_OWN][:, :, has] += rows[:, :, 3 * a: 3 * a + 3].transpose(1, 2, 0)
        out[i * n2:(i + 1) * n2] = one.reshape(9 * kept, n2, n3).transpose(1, 0, 2)
    return out, live


def full_stencils(stencils: np.ndarray, shape) -> np.ndarray:
    """All 27 blocks per node from :func:`node_stencils`' half: (27, 3, 3, N), block q of node n, those of
    ``q < 13`` the transposes of block ``26 - q`` of node ``n + offset(q)`` (periodic)."""
    n1, n2, n3 = (int(v) for v in shape)
    kept = 27 - STENCIL_OWN
    own = stencils.reshape(n1, n2, kept, 3, 3, n3).transpose(2, 3, 4, 0, 1, 5)  # (kept, 3, 3, n1, n2, n3)
    out = np.empty((27, 3, 3, n1, n2, n3), stencils.dtype)
    out[STENCIL_OWN:] = own
    for q in range(STENCIL_OWN):
        off = (q % 3 - 1, q // 3 % 3 - 1, q // 9 - 1)
        # block 26 - q of node n + off, at node n
        out[q] = np.roll(own[26 - q - STENCIL_OWN], tuple(-v for v in off), axis=(2, 3, 4)).transpose(1, 0, 2, 3, 4)
    return out.reshape(27, 3, 3, -1)


def _first_coarse(model, free3: np.ndarray, dtype=np.float64) -> Level:
    """The Galerkin level under the fine voxels of `model`, with its unknowns' mask `free3`
    (its element matrices stored in `dtype`)."""
    galerkin = _kernels()[0]
    shape = model.shape
    solid = model.solid
    child = _blocks(solid.astype(np.uint8))  # (m1, m2, m3, 8)
    code = (child.astype(np.int64) << np.arange(8)).sum(axis=-1)
    cshape = code.shape
    # the length of each coarse element per axis (1 at the end of an odd axis), in the code
    lens = [np.where(2 * np.arange(m) + 2 <= n, 0, 1) for m, n in zip(cshape, shape)]
    code = code + 256 * (lens[0][:, None, None] + 2 * lens[1][None, :, None] + 4 * lens[2][None, None, :])
    # an element touching a fixed unknown has its own matrix (F masks some of its rows)
    fixed = (model.active & (free3 == 0).any(axis=0)).reshape(shape)
    near = np.zeros(shape, bool)
    for off in range(8):
        near |= np.roll(fixed, tuple(-int(o) for o in ((off & 1), (off >> 1) & 1, (off >> 2) & 1)), axis=(0, 1, 2))
    touched = _blocks((near & solid).astype(np.uint8)).any(axis=-1)
    nonempty = child.any(axis=-1)
    code = np.where(nonempty, code, -1)
    own = touched & nonempty
    code[own] = 4096 + np.arange(int(own.sum()))
    flat = code.ravel()
    keep = np.flatnonzero(flat >= 0)
    uniq, first, inverse = np.unique(flat[keep], return_index=True, return_inverse=True)
    elems = np.array(np.unravel_index(keep[first], cshape), np.int64).T.copy()
    # the kernel runs in float64 only (one compiled signature); the matrices are then stored
    mats = np.empty((len(uniq), 24, 24))
    fine_index = np.where(solid, 0, -1).astype(np.int32)
    galerkin(fine_index, model.ke[None].astype(np.float64), np.ascontiguousarray(free3, np.float64), elems, mats)
    mats = mats.astype(dtype, copy=False)
    index = np.full(flat.shape, -1, np.int32)
    index[keep] = inverse.astype(np.int32)
    level = _level(cshape, index.reshape(cshape), mats)
    level.pattern = np.where((code >= 0) & (code < 256), code, 0).astype(np.uint8)
    return level


def child_matrices(ke: np.ndarray) -> np.ndarray:
    """The eight matrices ``M_c = W_c^T Ke W_c`` of the first coarse level (8, 24, 24) float64, GPa mm.

    ``W_c`` interpolates a full coarse element's eight corners trilinearly onto the corners of its
    child c (fine voxel ``a + 2b + 4c``), so an element with no fixed unknown has the matrix
    ``sum_c solid_c M_c``. Made by the Galerkin kernel on eight elements of one child each."""
    galerkin = _kernels()[0]
    # coarse element (e, 0, 0) has child e alone: fine voxel (2 e + a, b, c), e = a + 2b + 4c
    fine_index = np.full((16, 2, 2), -1, np.int32)
    for e in range(8):
        fine_index[2 * e + (e & 1), (e >> 1) & 1, (e >> 2) & 1] = 0
    elems = np.zeros((8, 3), np.int64)
    elems[:, 0] = np.arange(8)
    out = np.empty((8, 24, 24))
    galerkin(fine_index, np.asarray(ke, np.float64)[None], np.ones((3, fine_index.size)), elems, out)
    return out


def _next_coarse(level: Level) -> Level:
    """The Galerkin level under a coarse level (one matrix per element, in the level's float)."""
    galerkin = _kernels()[0]
    nonempty = _blocks(level.index).max(axis=-1) >= 0
    cshape = nonempty.shape
    keep = np.flatnonzero(nonempty.ravel())
    elems = np.array(np.unravel_index(keep, cshape), np.int64).T.copy()
    # in the level's own float, read and written as they are (the sums in float64, each rounded once as
    # astype would): a float64 copy of a float32 level's matrices and a float64 result beside its
    # float32 copy held 2.5 times the new level's bytes at once (128^3 benchmark scaffold, the 32^3
    # level: some 360 bytes a solid voxel, the peak of a solve of one case a block)
    mats = np.empty((len(keep), 24, 24), level.mats.dtype)
    ones = np.ones((3, int(np.prod(level.shape))))
    galerkin(level.index, level.mats, ones, elems, mats)
    index = np.full(int(np.prod(cshape)), -1, np.int32)
    index[keep] = np.arange(len(keep), dtype=np.int32)
    return _level(cshape, index.reshape(cshape), mats)


def _level(shape, index, mats) -> Level:
    # the diagonal: each node is corner b of the element at node - offset(b) (no node is two
    # corners of one element: every coarse axis keeps at least 2 nodes)
    own = mats[:, np.arange(24), np.arange(24)]  # (nm, 24)
    d = np.zeros((3,) + tuple(shape))
    for b in range(8):
        off = (b & 1, (b >> 1) & 1, (b >> 2) & 1)
        e = np.roll(index, off, axis=(0, 1, 2))
        d += np.where(e >= 0, own[e, 3 * b: 3 * b + 3].transpose(3, 0, 1, 2), 0.0)
    return Level(tuple(int(s) for s in shape), index, mats, _inverse_diagonal(d.reshape(3, -1)))


def _inverse_diagonal(d: np.ndarray) -> np.ndarray:
    # unknowns no solid reaches (or reaches with a vanishing share) have no equation
    live = d > 1e-12 * d.max() if d.size else d > 0
    return np.where(live, 1.0 / np.where(live, d, 1.0), 0.0)


def _fine_inverse_diagonal(d: np.ndarray, free: np.ndarray, dtype) -> np.ndarray:
    """``free * _inverse_diagonal(d)`` in `dtype`, bit for bit, without its whole-grid temporaries in double
    (three beside `d`: on the 128^3 benchmark scaffold the peak of the one-case solve's set-up); one row,
    (1, N), where its three rows are equal.

    The rows are equal where the mask is per node, as the solvers' are, and the element matrix's diagonal
    is one value, as an isotropic material's is (a node's diagonal is then the number of solid voxels around
    it times that value): the V-cycle's passes broadcast a row (12 against 4 bytes a node in float32, on
    that scaffold 27 bytes a solid voxel at the peak of its set-up).
    """
    # _inverse_diagonal's test and quotient, written straight into the result's float (the product by the
    # 0/1 mask, in double before, is exact either way)
    live = d > 1e-12 * d.max() if d.size else d > 0
    out = np.zeros(d.shape, dtype)
    np.divide(1.0, d, out=out, where=live)
    del live
    out *= free
    if len(out) == 3 and np.array_equal(out[0], out[1]) and np.array_equal(out[0], out[2]):
        out = out[:1].copy()
    return out


def _largest_eigenvalue(apply, inv_diag: np.ndarray, rng) -> float:
    """The largest eigenvalue of ``D^-1 A`` (`inv_diag` ``D^-1``), estimated from below by
    :data:`LANCZOS_STEPS` Lanczos steps on ``D^-1/2 A D^-1/2`` (the same spectrum), from a random start.

    Not power iterations: on anatomy the top eigenvectors are local (a few voxels at a contact or a
    thin process), which a random start barely holds, and power iterations amplify them by only the
    ratio of the eigenvalues a step. Twelve of them put the fine level of the L3 vertebra in
    ../shared/data (mesh at 0.5 mm, under platens) at 3.22 against 4.27 (300 of them), the first
    coarse level at 3.44 against 4.26: the smoothers' intervals then ended under the spectrum, the
    damped Jacobi steps amplified its top, the V-cycle was no longer positive definite (the CG's
    ``r.z`` fell below 0 at its ninth iteration) and the compression stopped with its modulus 205
    times the converged one. Lanczos's top Ritz value converges as a Chebyshev polynomial does: with
    the same twelve products it lay within 2.5 % of that figure on every level there (within 3.6 % on
    the 64^3 benchmark scaffold's levels, where power iterations were 5 to 14 % under).
    """
    import math

    from scipy.linalg import eigvalsh_tridiagonal

    from .fused import lanczos_pass
    from .mechanics_cl import aligned_empty, reusing

    # `inv_diag` (3, N), or (1, N) for three equal rows (_fine_inverse_diagonal): the vectors are (1, 3, N)
    g = np.sqrt(inv_diag)
    v = _random_start(rng, inv_diag)
    norm = float(np.linalg.norm(v))
    if norm == 0:
        return 1.0
    v /= norm
    prev, beta = None, 0.0
    alphas, betas = [], []
    # the products' outputs from one pool: fresh pages every step otherwise (a fine grid vector
    # of the 200^3 benchmark scaffold is 96 MB)
    with reusing():
        # one scratch vector for the product's input (aligned: the device reads it in place, where v * g was
        # a temporary and its aligned copy) and for the steps' alpha v and beta prev (temporaries too): on the
        # 128^3 benchmark scaffold three whole-grid vectors (120 bytes a solid voxel) at the one-case solve's peak
        t = aligned_empty(v.shape, v.dtype)
        np.multiply(v, g, out=t)
        for step in range(LANCZOS_STEPS):
            w = apply(t)
            # each step's vector arithmetic in three compiled passes on both cores (lanczos_pass), where the
            # product comes in the vectors' float; NumPy's otherwise (the same steps)
            alpha = lanczos_pass(0, w, v, g)
            fused = alpha is not None
            if not fused:
                w *= g
                alpha = float(np.vdot(v, w))
            alphas.append(alpha)
            if step == LANCZOS_STEPS - 1:
                break
            if fused:
                beta = math.sqrt(lanczos_pass(1, w, v, g, alpha=alpha, beta=beta, prev=prev))
            else:
                np.multiply(v, alpha, out=t)  # alpha v, rounded to the vectors' float as before
                w -= t
                if prev is not None:
                    np.multiply(prev, beta, out=t)
                    w -= t
                beta = float(np.linalg.norm(w))
            if not beta > 1e-12 * max(abs(alpha), 1e-300):  # an invariant subspace: its Ritz values are exact
                break
            betas.append(beta)
            if fused:
                lanczos_pass(2, w, v, g, beta=beta, t=t)  # w /= beta; t = g w, the next product's input
            else:
                w /= beta
                np.multiply(w, g, out=t)
            prev, v = v, w
    top = float(eigvalsh_tridiagonal(np.array(alphas), np.array(betas[:len(alphas) - 1]),
                                     select="i", select_range=(len(alphas) - 1, len(alphas) - 1))[0])
    return max(top, 1e-12)


#: the random start of :func:`_largest_eigenvalue` is drawn this many values at a time (in double)
RANDOM_CHUNK = 1 << 20


def _random_start(rng, inv_diag: np.ndarray) -> np.ndarray:
    """(1, 3, N) normal values of `rng` in `inv_diag`'s float, 0 where it is 0: the values a single draw of
    (1, 3, N) would give (a generator's draws run on in order), drawn a chunk at a time, without the whole
    draw and its masked copy in double (on the 128^3 benchmark scaffold 80 bytes a solid voxel each)."""
    n = inv_diag.shape[-1]
    v = np.empty((1, 3, n), inv_diag.dtype)
    for d in range(3):
        row = inv_diag[d if len(inv_diag) == 3 else 0]
        for a in range(0, n, RANDOM_CHUNK):
            b = min(n, a + RANDOM_CHUNK)
            v[0, d, a:b] = rng.standard_normal(b - a) * (row[a:b] > 0)
    return v


def _chebyshev(apply, inv_diag, lmax, b, x=None, degree=DEGREE):
    """Chebyshev smoothing of ``A x = b`` in ``D^-1 A`` on ``[LOWER, UPPER] * lmax``.

    `x` (updated in place) and the new iterate are aligned (:func:`~implicit_scaffold.measure.mechanics_cl.aligned_empty`),
    so the OpenCL operator reads them in place."""
    from .fused import chebyshev_step
    from .mechanics_cl import aligned_empty

    lo, hi = LOWER * lmax, UPPER * lmax
    theta, delta = (hi + lo) / 2, (hi - lo) / 2
    sigma = theta / delta
    rho = 1 / sigma
    d = aligned_empty(b.shape, b.dtype)
    if x is None and degree == 1:
        r = b  # read only when there is no further step
        np.multiply(inv_diag, r, out=d)
        d *= 1 / theta
        x = d
    elif x is None:
        r, x = aligned_empty(b.shape, b.dtype), aligned_empty(b.shape, b.dtype)
        if not chebyshev_step(r, b, d, x, inv_diag, 0.0, 1 / theta, b=b, start=True):
            r[...] = b
            np.multiply(inv_diag, r, out=d)
            d *= 1 / theta
            x[...] = d
    else:
        # each step one compiled pass where NumPy made five or six over the block's vectors (the same bits)
        r = apply(x)
        if not chebyshev_step(r, r, d, x, inv_diag, 0.0, 1 / theta, b=b):
            np.subtract(b, r, out=r)
            np.multiply(inv_diag, r, out=d)
            d *= 1 / theta
            x += d
    for _ in range(degree - 1):
        a = apply(d)
        rho_new = 1 / (2 * sigma - rho)
        if not chebyshev_step(r, a, d, x, inv_diag, rho_new * rho, 2 * rho_new / delta):
            r -= a
            d *= rho_new * rho
            t = inv_diag * r
            t *= 2 * rho_new / delta
            d += t
            del t
            x += d
        del a
        rho = rho_new
    return x


class Multigrid:
    """A V-cycle of the voxel operator as a conjugate-gradient preconditioner.

    Parameters
    ----------
    model : VoxelModel
        The fine voxels (:func:`~implicit_scaffold.measure.mechanics.voxel_model`).
    op : callable
        The fine operator, (m, 3, N) -> K u (OpenCL or NumPy). With the OpenCL one, the coarse
        levels run on the device too (a gather kernel of the same file, one matrix per element).
    free : (N,) or (3, N) array of 0 and 1
        The unknowns; the system solved is ``F K F``. Kept as given (not copied) when it comes in
        `dtype`.
    seed : int
        For the eigenvalue estimates' start vectors (the preconditioner is deterministic).
    dtype : numpy float type
        Of the cycle's vectors (float32 halves its time and memory; the coarse matrices and
        the coarsest solve stay float64).
    slab_nodes : int, optional
        The fine level by slabs of this many nodes' planes (:func:`fine_slab_planes`), on any grid;
        default: by :data:`FINE_SLAB_NODES`.
    """

    def __init__(self, model, op, free, *, seed: int = 0, dtype=np.float64, slab_nodes: int | None = None):
        from .mechanics import diagonal

        n = int(np.prod(model.shape))
        free = np.asarray(free)
        self.dtype = np.dtype(dtype)
        # (1, N) for a mask per node (every use broadcasts it), (3, N) per unknown; the caller's own
        # array when it comes in the cycle's float (the solver's free mask is float32: 4 bytes a node)
        self.free = free.reshape(-1, n).astype(self.dtype, copy=False)
        # the mask the result is multiplied by (the caller's own array)
        self._free_out = free.reshape(-1, n)
        self.fine_shape = tuple(model.shape)
        self.slab_nodes = slab_nodes
        # the nodes a solid voxel touches: where they are all free (periodic), a fine product reads no other
        # node into a free one's, so the cycle need not zero the rest (_fine_cases)
        self._touched = int(np.count_nonzero(model.active))
        self.op = op
        rng = np.random.default_rng(seed)
        self._inv_diag = _fine_inverse_diagonal(diagonal(model), self.free, self.dtype)
        # (live nodes, the inverse diagonal on them) once compact() has let the whole grid's go
        self._inv_diag_live = None
        self.lmax = _largest_eigenvalue(self.op, self._inv_diag, rng)
        self.levels: list[Level] = []
        shape = self.fine_shape
        if 3 * n > COARSEST_UNKNOWNS and min(shape) >= 4:
            # float32 matrices for a float32 cycle: the second level's, one per element, are
            # its largest array (about 36 bytes per fine voxel)
            level = _first_coarse(model, np.broadcast_to(self.free, (3, n)), self.dtype)
            self.levels.append(level)
            while 3 * np.prod(level.shape) > COARSEST_UNKNOWNS and min(level.shape) >= 4:
                level = _next_coarse(level)
                self.levels.append(level)
        on_device = hasattr(op, "single")
        # the coarsest level's pseudo-inverse first: a level on stencils lets go of its matrices
        self._coarsest = self._exact(self.levels[-1]) if self.levels else None
        for level in self.levels:
            level.inv_diag = level.inv_diag.astype(self.dtype)
            if on_device:
                from .mechanics_cl import LevelOperator, PatternLevelOperator, StencilLevelOperator

                if level.pattern is not None and FIRST_LEVEL_PATTERNS:
                    level.device = PatternLevelOperator(level, level.pattern,
                                                        child_matrices(model.ke).astype(level.mats.dtype))
                elif level.pattern is None and STENCIL_LEVELS:
                    level.device = StencilLevelOperator(level)
                    # every later use is the device's product (the next level is built already)
                    level.mats = None
                else:
                    level.device = LevelOperator(level)
                if isinstance(level.device, LevelOperator):
                    # the device reads the matrices in place: the level keeps that one copy
                    level.mats = level.device.host_mats(level.mats.shape)
            level.lmax = _largest_eigenvalue(level.apply, level.inv_diag, rng)

    @property
    def inv_diag(self) -> np.ndarray:
        """(3, N) the fine grid's inverse diagonal, or (1, N) where its rows are equal
        (:func:`_fine_inverse_diagonal`), 0 on the fixed unknowns, in the cycle's float (spread again from
        the live nodes' when :meth:`compact` has let the whole grid's go)."""
        if self._inv_diag is None:
            live, g = self._inv_diag_live
            whole = np.zeros((len(g), self.free.shape[1]), g.dtype)
            whole[:, live] = g
            self._inv_diag = whole
        return self._inv_diag

    def _live_inverse_diagonal(self, live: np.ndarray) -> np.ndarray:
        """(3, len(live)) the inverse diagonal on the nodes `live`. When it is 0 off them, the whole grid's
        copy is let go (12 bytes a node in float32: on the lumbar micro-CT's 192^3 crop under platens,
        44 bytes a solid voxel of the solve's peak) and this one is kept for the next call."""
        kept = self._inv_diag_live
        if kept is not None and (kept[0] is live or np.array_equal(kept[0], live)):
            self._inv_diag_live = (live, kept[1])  # the caller's array: an equal one of its last call can go
            return kept[1]
        whole = self.inv_diag
        g = np.ascontiguousarray(whole[:, live])
        if np.count_nonzero(whole.any(axis=0)) == np.count_nonzero(g.any(axis=0)):
            self._inv_diag, self._inv_diag_live = None, (live, g)
        return g

    @staticmethod
    def _exact(level: Level):
        """The pseudo-inverse of a small level (rigid motions and unreached unknowns get 0)."""
        nd = 3 * int(np.prod(level.shape))
        if nd > COARSEST_UNKNOWNS:
            return None
        A = level.matrix()
        live = np.flatnonzero(level.inv_diag.ravel() > 0)
        sub = A[np.ix_(live, live)]
        sub = 0.5 * (sub + sub.T)
        from threadpoolctl import threadpool_limits

        # one BLAS thread: at most 1,000 unknowns, 0.03 s on one thread; on two threads of a machine
        # with another job, the data folder's CT (26 pieces under platens, one such solve each) spent
        # 12.6 s in them, one of 410 unknowns 2.9 s (both threads wait on each other's time slices)
        with threadpool_limits(1, user_api="blas"):
            w, v = np.linalg.eigh(sub)
        keep = w > 1e-10 * max(w.max(), 1e-300)
        pinv = (v[:, keep] / w[keep]) @ v[:, keep].T
        return live, pinv

    def _cycle(self, depth: int, b: np.ndarray) -> np.ndarray:
        if depth == 0:
            # K x unmasked: every use of it in the cycle is masked after (by the inverse
            # diagonal, or before the restriction), so the cycle solves F K F
            apply, inv_diag, lmax, shape = self.op, self.inv_diag, self.lmax, self.fine_shape
        else:
            level = self.levels[depth - 1]
            apply, inv_diag, lmax, shape = level.apply, level.inv_diag, level.lmax, level.shape
            if depth == len(self.levels) and self._coarsest is not None:
                live, pinv = self._coarsest
                m = b.shape[0]
                x = np.zeros_like(b)
                flat = x.reshape(m, -1)
                flat[:, live] = b.reshape(m, -1)[:, live] @ pinv
                return x
        if depth == len(self.levels):
            # no exact solve (a level too large and too thin to coarsen): smooth harder
            x = None
            for _ in range(4):
                x = _chebyshev(apply, inv_diag, lmax, b, x)
            return x
        if depth == 1:
            # a block's cases are the same ones every cycle of a CG: its preconditioner stays one operator
            degree = FIRST_BLOCK_DEGREE if b.shape[0] >= FIRST_BLOCK_CASES else FIRST_DEGREE
        else:
            degree = FINE_DEGREE if depth == 0 else DEGREE
        if depth == 0 and degree == 1:
            return self._fine_jacobi(b)
        x = _chebyshev(apply, inv_diag, lmax, b, degree=degree)
        r = apply(x)
        np.subtract(b, r, out=r)
        if depth == 0:
            r *= self.free
        rc = restrict(r, shape)
        del r
        e = self._cycle(depth + 1, rc)
        del rc
        if depth == 0:
            corr = prolong(e, shape)
            corr *= self.free
            x += corr
            del corr
        else:  # x += P e in one pass (no whole-grid correction, and the same bits)
            prolong_add(e, x, None, shape)
        del e
        return _chebyshev(apply, inv_diag, lmax, b, x, degree=degree)

    def _fine_jacobi(self, b: np.ndarray) -> np.ndarray:
        """The fine level of the cycle with degree-1 smoothing (damped Jacobi, :func:`_chebyshev`'s
        degree 1), each vector update one fused pass (:mod:`~implicit_scaffold.measure.fused`)."""
        from .fused import add_weighted, weighted
        from .mechanics_cl import aligned_empty

        s = self._jacobi_step()
        x = weighted(aligned_empty(b.shape, b.dtype), b, self.inv_diag, s)
        r = self.op(x)
        weighted(r, b, self.free, y=r)  # F (b - K x): the restriction sees the free unknowns only
        rc = restrict(r, self.fine_shape)
        del r
        corr = prolong(self._cycle(1, rc), self.fine_shape)
        del rc
        add_weighted(x, corr, self.free)
        del corr
        ax = self.op(x)
        add_weighted(x, b, self.inv_diag, s, y=ax)
        return x

    def _jacobi_step(self) -> float:
        return 1 / ((LOWER + UPPER) / 2 * self.lmax)  # 1 / theta

    def compact(self, live: np.ndarray, dtype=None, weights: np.ndarray | None = None):
        """The same preconditioner on vectors kept on the nodes `live` only, (m, 3, len(live)):
        the residual is spread over the grid in the cycle's float, the result's live nodes
        taken back in `dtype` (default the residual's; one pass each, no whole-grid vector in the
        solver's float).
        ``apply(r, sink)`` hands each case's result to ``sink(case, z, rz)`` ((1, 3, len(live)), and ``r.z``
        summed as :func:`~implicit_scaffold.measure.fused.wdot` sums it, or None) as soon as it is made, and
        returns None: the caller need not hold the block's result.

        With degree-1 fine smoothing (the default) the fine level runs one load case at a time
        (:meth:`_fine_cases`): the whole-grid vectors are one case's, not the block's.

        `weights`, the caller's own copy of the free mask on `live` (the CG's), is used when it holds the
        same values in the same float: the two would otherwise keep a copy each (on the lumbar micro-CT's
        192^3 crop under platens, 16 bytes a solid voxel of the solve's peak)."""
        from .fused import put, take

        n = self.free.shape[1]
        w = np.ascontiguousarray(self._free_out[:, live])
        if weights is not None and weights.dtype == w.dtype and np.array_equal(weights, w):
            w = weights
        g = self._live_inverse_diagonal(live) if FINE_DEGREE == 1 and self.levels else None

        slabs = self._fine_slabs(live) if g is not None else None
        # every node a solid voxel touches is live (periodic: none held fixed): a product reads no other node into a
        # live one's (every corner of a solid voxel is live), so the other nodes' values need not be zero; and F 1 on
        # every live unknown (a mask per node), the product 0 off them: no mask to read. Decided once, not a cycle
        onto = live.size == self._touched
        unmasked = onto and not np.any(w != 1)

        def apply(r: np.ndarray, sink=None):
            if slabs is not None:
                return self._fine_cases_by_slabs(r, live, w, g, slabs, sink, dtype)
            if g is not None:
                return self._fine_cases(r, live, w, g, sink, dtype, onto, unmasked)
            b = put(r, live, n, w, self.dtype)
            x = self._cycle(0, b)
            del b
            z = take(x, live, w, r.dtype if dtype is None else dtype)
            if sink is None:
                return z
            for c in range(len(z)):
                sink(c, z[c:c + 1], None)

        return apply

    def _fine_cases(self, r: np.ndarray, live: np.ndarray, w: np.ndarray, g: np.ndarray, sink=None, dtype=None,
                    onto: bool = False, unmasked: bool = False):
        """:meth:`_fine_jacobi` on live-node residuals (m, 3, len(live)), the fine level one load case
        at a time and the coarse levels on the block, with the same arithmetic per case.

        The fine level of a block of six held six cases of each of its whole-grid vectors (b, x, the
        residual, the correction: 72 bytes a node each in float32); one case at a time holds one.
        The right-hand side ``b = F r`` is never spread over the grid: the pre-smoothed ``x = s D^-1 b``
        is spread from `r` at once (twice, once a pass: cheaper than keeping it), the residual is
        ``-F K x`` with ``b`` added on the live nodes, and the post-smoothing step and the taking of
        the live nodes are one pass (:mod:`~implicit_scaffold.measure.fused`); `g` is the inverse diagonal
        on the live nodes (:meth:`_live_inverse_diagonal`). With `sink`, each case's
        result goes to ``sink(case, z, r.z)`` as it is made, ``r.z`` summed in the pass that takes z (None is
        returned). The result is in `dtype` (default the residual's)."""
        from .fused import put_add, put_smoothed, put_smoothed_onto, take_smoothed
        from .mechanics_cl import aligned_empty

        n = self.free.shape[1]
        m = r.shape[0]
        s = self._jacobi_step()
        rc = None
        # with `onto` (compact's), the pre-smoothed x of each case is spread into one buffer, zeroed once (128^3
        # benchmark scaffold: the zeroing was some half of put_smoothed's 4.4 ms a case)
        spread = None
        if onto:
            spread = aligned_empty((1, 3, n), self.dtype)
            spread.fill(0)
        for c in range(m):
            x = put_smoothed(r[c:c + 1], live, n, w, g, s, self.dtype, out=spread, zero=spread is None)
            res = self.op(x)
            del x
            # K x - F b on the live nodes, restricted times F and negated: the restriction of the
            # residual F (b - K x) (F is 0 or 1: the same bits as forming it first), without a pass
            # over the grid to form it
            put_add(res, r[c:c + 1], live, w, subtract=True)
            # F is 1 on every live unknown and the product 0 off the live nodes: the same bits without reading F
            one = restrict(res, self.fine_shape, None if unmasked else self.free)
            del res
            if rc is None:
                rc = aligned_empty((m,) + one.shape[1:], one.dtype)
            np.negative(one[0], out=rc[c])
            del one
        del spread
        coarse = self._cycle(1, rc)
        del rc
        z = None
        for c in range(m):
            if onto:
                # x = s D^-1 F r + F P e on the live nodes, P e elsewhere: the prolongation written, then one pass
                # over the live nodes, where spreading x (zeroing the grid) and adding F P e were a pass over the
                # whole grid each (128^3 benchmark scaffold: 4.4 and 5.3 ms a case); the same bits on the live nodes
                x = prolong(coarse[c:c + 1], self.fine_shape)
                put_smoothed_onto(x, r[c:c + 1], live, w, g, s)
            else:  # fixed nodes (a box's faces) touch the solid: 0 there, as everywhere off the live nodes
                x = put_smoothed(r[c:c + 1], live, n, w, g, s, self.dtype)
                prolong_add(coarse[c:c + 1], x, self.free, self.fine_shape)  # x += F P e (no whole-grid P e)
            ax = self.op(x)
            if sink is not None:
                # r.z in the same pass, handed over with z: the CG's own, the same bits (it weighs r.z by ones)
                one, rz = take_smoothed(x, ax, r[c:c + 1], live, w, g, s, r.dtype if dtype is None else dtype,
                                        dot=True)
                del x, ax
                sink(c, one, float(rz[0]))
                continue
            one = take_smoothed(x, ax, r[c:c + 1], live, w, g, s, r.dtype if dtype is None else dtype)
            del x, ax
            if z is None:  # made here, beside one whole-grid vector only
                z = np.empty(r.shape, one.dtype)
            z[c] = one[0]
        return z

    def _fine_slabs(self, live: np.ndarray):
        """The slabs of the fine level's node planes (:data:`FINE_SLAB_NODES`), or None (one slab would
        hold the grid, or the operator has none). Each: (i0, i1, planes, operator, where the live nodes of
        each plane begin in `live`, the coarse planes its inner planes restrict onto and their stencil,
        the coarse planes its planes interpolate from and theirs)."""
        n1, n2, n3 = self.fine_shape
        plane = n2 * n3
        thick = fine_slab_planes(self.fine_shape, self.slab_nodes)
        if thick >= n1 or not hasattr(self.op, "slab"):
            return None
        from .mechanics_cl import plane_starts

        starts = plane_starts(live, n1, plane)
        parents, weights, children, shares = _stencils(n1)
        out = []
        for i0 in range(0, n1, thick):
            i1 = min(n1, i0 + thick)
            planes, op = self.op.slab(i0, i1)
            # restriction: the coarse planes with a child among the inner planes i0 .. i1 - 1 (the slab's
            # planes 1 .. i1 - i0), their children as the slab's planes, a weight 0 for those outside
            inside = (children >= i0) & (children < i1) & (shares > 0)
            rows = np.flatnonzero(inside.any(axis=1))
            ia = np.where(inside[rows], children[rows] - i0 + 1, 0)
            wa = np.where(inside[rows], shares[rows], 0.0)
            # prolongation: the slab's planes from their coarse parents, gathered in order of first use
            need, local = np.unique(parents[planes], return_inverse=True)
            pa = local.reshape(planes.size, 2)
            out.append((i0, i1, planes, op, rows, (ia, wa), need, (pa, weights[planes])))
        return starts, out

    def _fine_cases_by_slabs(self, r: np.ndarray, live: np.ndarray, w: np.ndarray, g: np.ndarray, slabs, sink=None,
                             dtype=None):
        """:meth:`_fine_cases` a slab of node planes at a time (:meth:`_fine_slabs`): each slab's spread
        iterate, its product, the restriction of its inner planes' residual and, after the coarse levels,
        the interpolated correction, the second product and the taking of its live nodes. The whole
        grid's float vectors (two, 12 bytes a node each in float32) are a slab's; the restriction's sums
        over the planes two slabs share are added in another order (the result is the same within
        float32's rounding)."""
        from .fused import put_add, take_smoothed
        from .mechanics_cl import aligned_empty

        starts, plan = slabs
        n1, n2, n3 = self.fine_shape
        plane = n2 * n3
        m = r.shape[0]
        s = self._jacobi_step()
        cshape = coarse_shape(self.fine_shape)
        c_plane = cshape[1] * cshape[2]
        transfer = _kernels()[2]
        along = [_stencils(n2), _stencils(n3)]
        rc = aligned_empty((m, 3, cshape[0] * c_plane), self.dtype)
        rc.fill(0)
        for c in range(m):
            for i0, i1, planes, op, coarse_rows, down, _, _ in plan:
                if starts[i1] == starts[i0]:
                    continue  # no live node: a zero residual there
                x = self._spread(r[c:c + 1], live, w, g, s, starts, planes, plane)
                res = op(x)
                del x
                k0, k1 = starts[i0], starts[i1]
                put_add(res, r[c:c + 1, :, k0:k1], live[k0:k1] - (i0 - 1) * plane, w[:, k0:k1], subtract=True)
                part = aligned_empty((1, 3, coarse_rows.size) + cshape[1:], self.dtype)
                transfer(res.reshape(1, 3, planes.size, n2, n3), part, [down] + [a[2:] for a in along], False,
                         self._slab_weight(planes, plane))
                del res
                # -(K x - F b) restricted: the coarse right-hand side
                view = rc[c].reshape(3, cshape[0], c_plane)
                view[:, coarse_rows] -= part[0].reshape(3, coarse_rows.size, c_plane)
                del part
        coarse = self._cycle(1, rc)
        del rc
        z = None
        for c in range(m):
            one = aligned_empty((1, 3, live.size), r.dtype if dtype is None else dtype)
            for i0, i1, planes, op, _, _, need, up in plan:
                k0, k1 = starts[i0], starts[i1]
                if k1 == k0:
                    continue
                x = self._spread(r[c:c + 1], live, w, g, s, starts, planes, plane)
                sub = np.ascontiguousarray(coarse[c:c + 1].reshape(1, 3, cshape[0], c_plane)[:, :, need])
                transfer(sub.reshape((1, 3, need.size) + cshape[1:]), x.reshape(1, 3, planes.size, n2, n3),
                         [up] + [a[:2] for a in along], True, self._slab_weight(planes, plane))
                del sub
                ax = op(x)
                take_smoothed(x, ax, r[c:c + 1, :, k0:k1], live[k0:k1] - (i0 - 1) * plane, w[:, k0:k1], g[:, k0:k1],
                              s, out=one[:, :, k0:k1])
                del x, ax
            if sink is not None:
                sink(c, one, None)
                continue
            if z is None:
                z = np.empty(r.shape, one.dtype)
            z[c] = one[0]
            del one
        return z

    def _spread(self, rc, live, w, g, s, starts, planes, plane):
        """The pre-smoothed iterate ``s g w r`` of one case spread over a slab's planes (0 off the live
        nodes), in the cycle's float: :func:`~implicit_scaffold.measure.fused.put_smoothed` on each run
        of consecutive planes (one, or two where the slab wraps round a periodic grid's ends)."""
        from .fused import put_smoothed
        from .mechanics_cl import aligned_empty, plane_runs

        x = aligned_empty((1, 3, planes.size * plane), self.dtype)
        for p, q in plane_runs(planes):
            k0, k1 = starts[planes[p]], starts[planes[q - 1] + 1]
            if k1 == k0:
                x[:, :, p * plane:q * plane] = 0
                continue
            # every node of the run written (0 but on its live nodes)
            put_smoothed(rc[:, :, k0:k1], live[k0:k1] - int(planes[p]) * plane, (q - p) * plane, w[:, k0:k1],
                         g[:, k0:k1], s, out=x[:, :, p * plane:q * plane])
        return x

    def _slab_weight(self, planes, plane):
        """The free mask on a slab's planes, (1 or 3, len(planes) * plane) in the cycle's float."""
        from .mechanics_cl import plane_runs

        runs = [self.free[:, int(planes[p]) * plane:(int(planes[q - 1]) + 1) * plane] for p, q in plane_runs(planes)]
        return np.ascontiguousarray(runs[0]) if len(runs) == 1 else np.concatenate(runs, axis=1)

    def __call__(self, r: np.ndarray) -> np.ndarray:
        """One V-cycle from zero: an approximation of ``(F K F)^+ r`` for (m, 3, N) residuals."""
        from .fused import weighted
        from .mechanics_cl import aligned_empty

        # each a fused pass with the cast (NumPy's casting multiply took 67 ms a call on a
        # 64^3 block of six cases, some 8 % of the solve)
        b = weighted(aligned_empty(r.shape, self.dtype), r, self.free)
        x = self._cycle(0, b)
        del b
        return weighted(aligned_empty(r.shape, r.dtype), x, self._free_out)
