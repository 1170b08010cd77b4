"""Issue 14 study: why the compression's CG needs more iterations than the homogenization's, and which
multigrid would need fewer.

    pip install pyamg   # the algebraic peer of this study; not a dependency of the tool
    python benchmarks/bench_coarse_spaces.py [--size 48] [--tol 1e-7] [--only TEXT]
    python benchmarks/bench_coarse_spaces.py --products [--size 193] [--runs 15]

The default cube of ``implicit-scaffold generate`` (10 mm, P = 80 %, Dp = 0.6 mm, at its own voxel, before
the mesh's level correction) is built once. Its corner of --size^3 voxels is compressed along z between
lubricated platens (the system ``F K F`` of :func:`~implicit_scaffold.measure.mechanics.compress`, from the
homogeneous block's lifting), with its four lateral faces free (the ISO 13314 test) and, to tell what slows
it, held. Every system is
assembled (:func:`~implicit_scaffold.measure.mechanics.stiffness_matrix`) and solved by one and the same CG
(SciPy's, to the relative residual --tol) with each preconditioner:

- **ours**: the tool's V-cycle (:class:`~implicit_scaffold.measure.multigrid.Multigrid`, the NumPy operator in
  double): trilinear transfers between every other node, Galerkin coarse operators, Chebyshev-Jacobi smoothing;
- **ours + 8-colour SGS on the fine level**: the same, its fine smoothing a symmetric Gauss-Seidel sweep
  over the nodes in 8 colours of their index parities (nodes of one colour share no voxel);
- **ours assembled**: the same cycle on the assembled levels (SciPy only, no PyAMG), first as the tool runs
  it, then with one level changed at a time, to tell where it loses iterations: a level solved directly (level 1
  solved so, the cycle is a two-level one), a higher Chebyshev degree or 8-colour Gauss-Seidel on level 1
  (the first coarse level), Chebyshev degree 2 or damped Jacobi in each node's 3 x 3 block on the fine level;
- **our grids, SGS (Jacobi) on every level**: the same transfers and Galerkin operators as PyAMG levels,
  with PyAMG's symmetric Gauss-Seidel (damped Jacobi, 0.8) on each, or an 8-colour symmetric Gauss-Seidel
  (the order a device could run in parallel), or our fine Jacobi with Gauss-Seidel below;
- **node aggregates + rigid modes (smoothed)**: each 2x2x2 block of nodes one aggregate, the six rigid
  motions its coarse unknowns (PyAMG's tentative prolongator, then smoothed by a Jacobi step or not), the
  deeper levels PyAMG's own aggregates, symmetric Gauss-Seidel;
- **smoothed aggregation**: PyAMG's defaults with the six rigid motions, symmetric Gauss-Seidel (or damped
  Jacobi, or the 8-colour sweeps on the fine level and Gauss-Seidel below: what a device could run).

With ``--products``, no CG: the compression's first coarse level (the tool's own, OpenCL, float32) is applied to
one case's vector by each product the tool has for it, timed (medians of --runs) and compared (the largest
difference from the per-element product, over its largest value): the one a compression uses
(``level.device``), the level's own per-element matrices (``stiffness_apply``), and the level's assembled
node stencils (``stencil_rows``, as the levels below it run), with the bytes each holds.

Iterations are the figure; the seconds are serial SciPy and PyAMG on a small sample, for scale only.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._common import table  # noqa: E402

JACOBI_WEIGHT = 0.8

#: the rows of :func:`ours_assembled`: (what differs from the tool's cycle, its arguments)
ASSEMBLED = [("", {}),
             (", level 1 solved exactly (two levels)", {"exact_at": 1}),
             (", level 2 solved exactly", {"exact_at": 2}),
             (", Chebyshev degree 2 on level 1", {"smoothers": {1: ("chebyshev", 2)}}),
             (", Chebyshev degree 3 on level 1", {"smoothers": {1: ("chebyshev", 3)}}),
             (", Chebyshev degree 5 on level 1", {"smoothers": {1: ("chebyshev", 5)}}),
             (", 8-colour SGS on level 1", {"smoothers": {1: ("colours",)}}),
             (", Chebyshev degree 2 on the fine level", {"smoothers": {0: ("chebyshev", 2)}}),
             (", node-block Jacobi on the fine level", {"smoothers": {0: ("node blocks",)}})]


def default_cube_corner(size: int) -> tuple[np.ndarray, float]:
    """The solid of the default cube at its own voxel (generate's field before the mesh's level correction:
    some 20 % solid, where ``generate --mechanics`` solves 21 %), cut to its corner of size^3."""
    from implicit_scaffold.measure.mechanics import solid_for_solve
    from implicit_scaffold.pipeline import generate

    run = generate(output=None, mesh=False)
    sample = solid_for_solve(run.field, run.grid, boundary="periodic")
    return np.ascontiguousarray(sample.solid[:size, :size, :size]), float(sample.voxel)


def compression_system(solid: np.ndarray, h: float, *, held_sides: bool):
    """(model, free mask (3, N) float, assembled F K F, its unknowns' flat indices, right-hand side) of the
    compression along z from the homogeneous block's lifting (no lateral part: any lifting that meets the
    platens poses the same system)."""
    from implicit_scaffold.measure import mechanics as m

    model = m.voxel_model(m.load_path(solid, 2), h, m.material("ti64"), periodic=False)
    shape = model.shape
    free, _ = m.platen_unknowns(model, 2)
    if held_sides:
        sides = np.zeros(shape, bool)
        sides[0] = sides[-1] = True  # n + 1 node planes: the sample's faces are the first and the last
        sides[:, 0] = sides[:, -1] = True
        free &= ~sides.ravel()
    free = free.astype(np.float64)
    lifting = np.zeros((3,) + tuple(shape))
    m.add_strain(lifting, m.node_axes(shape, h), np.diag([0.0, 0.0, -1e-3]))
    b = -(m.apply_stiffness(model, lifting.reshape(1, 3, -1) * model.active) * free)
    K, dofs = m.stiffness_matrix(model, free)
    return model, free, K.tocsr(), dofs, b.reshape(-1)[dofs]


def cg_iterations(K, b, M, tol: float) -> tuple[int, float]:
    import scipy.sparse.linalg as sla

    count = [0]

    def step(_):
        count[0] += 1

    t0 = time.perf_counter()
    _, info = sla.cg(K, b, rtol=tol, maxiter=2000, M=M, callback=step)
    return (count[0] if info == 0 else -1), time.perf_counter() - t0


def rigid_modes(model, dofs: np.ndarray) -> np.ndarray:
    """(len(dofs), 6) the three translations and three rotations on the unknowns `dofs`, mm."""
    n = int(np.prod(model.shape))
    comp, node = np.divmod(dofs, n)
    x = np.array(np.unravel_index(node, model.shape), float) * model.h
    B = np.zeros((dofs.size, 6))
    B[np.arange(dofs.size), comp] = 1.0
    for k, (i, j) in enumerate(((1, 2), (2, 0), (0, 1))):  # the rotation about axis k moves i by -x_j, j by x_i
        B[:, 3 + k] = np.where(comp == i, -x[j], np.where(comp == j, x[i], 0.0))
    return B


def ours(model, free, dofs, fine_colours: bool, K):
    """The tool's V-cycle on the assembled unknowns; with `fine_colours` its fine smoothing an 8-colour SGS."""
    import scipy.sparse.linalg as sla

    from implicit_scaffold.measure.mechanics import apply_stiffness, make_preconditioner
    from implicit_scaffold.measure.multigrid import prolong, restrict

    n = int(np.prod(model.shape))
    mg = make_preconditioner("multigrid", model, lambda u: apply_stiffness(model, u), free, 1e-8)

    def spread(v):
        out = np.zeros(3 * n)
        out[dofs] = v
        return out.reshape(1, 3, n)

    if not fine_colours:
        return sla.LinearOperator(K.shape, lambda r: mg(spread(r)).reshape(-1)[dofs], dtype=float)
    forward, backward = colour_sweeps(K, dofs, model.shape)

    def cycle(b):
        b = np.asarray(b, float).ravel()
        x = np.zeros_like(b)
        forward(K, x, b)
        coarse = mg._cycle(1, restrict(spread(b - K @ x), mg.fine_shape))
        x += prolong(coarse, mg.fine_shape).reshape(-1)[dofs]
        backward(K, x, b)
        return x

    return sla.LinearOperator(K.shape, cycle, dtype=float)


def galerkin_levels(model, dofs, K) -> list:
    """The tool's hierarchy assembled: [(A, P, node grid, kept unknowns)] from the fine level down, with the
    tool's transfers (trilinear, every other node) and Galerkin operators ``P^T A P``; the coarsest level's P is
    None. The unknowns kept on a level are those its prolongation reaches (flat ``d N + node`` of its grid)."""
    import scipy.sparse as sp

    from implicit_scaffold.measure.multigrid import COARSEST_UNKNOWNS, _stencils, coarse_shape

    def axis(nf):
        parents, weights = _stencils(nf)[:2]
        return sp.csr_matrix((weights.ravel(), (np.repeat(np.arange(nf), 2), parents.ravel())),
                             shape=(nf, (nf + 1) // 2))

    levels, A, shape, kept = [], K.tocsr(), tuple(model.shape), dofs
    while A.shape[0] > COARSEST_UNKNOWNS and min(shape) >= 4:
        P = sp.kron(sp.kron(axis(shape[0]), axis(shape[1])), axis(shape[2])).tocsr()
        P = sp.block_diag([P] * 3).tocsr()[kept]
        coarse = np.flatnonzero(np.asarray(abs(P).sum(axis=0)).ravel() > 0)
        P = P[:, coarse].tocsr()
        levels.append((A, P, shape, kept))
        A, shape, kept = (P.T @ A @ P).tocsr(), coarse_shape(shape), coarse
    levels.append((A, None, shape, kept))
    return levels


def our_grids(model, dofs, K, smoother, fine=None):
    """PyAMG levels with the tool's transfers (trilinear, every other node) and Galerkin operators, `smoother` on
    each (`fine`, if given, on the fine level)."""
    from pyamg.multilevel import MultilevelSolver
    from pyamg.relaxation.smoothing import change_smoothers

    built, levels = galerkin_levels(model, dofs, K), []
    for A, P, _, _ in built:
        level = MultilevelSolver.Level()
        level.A = A
        if P is not None:
            level.P, level.R = P, P.T.tocsr()
        levels.append(level)
    ml = MultilevelSolver(levels, coarse_solver="pinv")
    if smoother == "colours":
        for level, (A, P, shape, kept) in zip(ml.levels, built):
            if P is not None:
                level.presmoother, level.postsmoother = colour_sweeps(A, kept, shape)
        return ml.aspreconditioner(cycle="V")
    if fine is not None:
        smoother = [fine] + [smoother] * (len(levels) - 2)
    change_smoothers(ml, presmoother=smoother, postsmoother=smoother)
    return ml.aspreconditioner(cycle="V")


def largest_eigenvalue(A, inverse) -> float:
    """The largest eigenvalue of ``B^-1 A``, `inverse` applying ``B^-1`` (ARPACK, to 1e-3)."""
    import scipy.sparse.linalg as sla

    op = sla.LinearOperator(A.shape, lambda v: inverse(A @ v), dtype=float)
    return float(abs(sla.eigs(op, k=1, which="LM", return_eigenvectors=False, tol=1e-3)[0]))


def node_blocks(A, kept: np.ndarray, n: int):
    """``B^-1`` of A's node-block diagonal (each node's coupled unknowns, up to 3 x 3) as a callable."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as sla

    node = kept % n
    coo = A.tocoo()
    same = node[coo.row] == node[coo.col]
    B = sp.csc_matrix((coo.data[same], (coo.row[same], coo.col[same])), shape=A.shape)
    return sla.splu(B).solve


def exact_solve(A):
    """A direct solve of a level (SuperLU), its rigid motions (the lubricated platens leave three free) held by a
    shift of 1e-9 times the mean diagonal."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as sla

    shift = 1e-9 * float(A.diagonal().mean())
    return sla.splu((A + shift * sp.identity(A.shape[0])).tocsc()).solve


def ours_assembled(model, dofs, K, *, exact_at: int | None = None, smoothers: dict | None = None):
    """The tool's V-cycle on :func:`galerkin_levels`: Chebyshev-Jacobi smoothing on ``[LOWER, UPPER]`` times each
    level's largest eigenvalue of ``D^-1 A``, of the tool's degrees (FINE_DEGREE, FIRST_DEGREE, DEGREE), the
    coarsest level solved by a pseudo-inverse as the tool solves it; one level changed at a time to tell where
    the cycle loses iterations: `exact_at`, a level solved directly (:func:`exact_solve`); `smoothers`,
    {level: ("chebyshev", degree) | ("colours",) | ("node blocks",)}, the 8-colour Gauss-Seidel sweeps of
    :func:`colour_sweeps` (forward before the coarse correction, backward after), or damped Jacobi in the nodes'
    3 x 3 blocks (the tool's step ``1 / theta`` on ``B^-1 A``'s largest eigenvalue)."""
    import scipy.sparse.linalg as sla

    from implicit_scaffold.measure.multigrid import DEGREE, FINE_DEGREE, FIRST_DEGREE, LOWER, UPPER, _chebyshev

    levels = galerkin_levels(model, dofs, K)
    chosen = {0: ("chebyshev", FINE_DEGREE), 1: ("chebyshev", FIRST_DEGREE)}
    chosen.update(smoothers or {})
    steps = []
    for depth, (A, P, shape, kept) in enumerate(levels):
        kind = chosen.get(depth, ("chebyshev", DEGREE))
        if P is None or depth == exact_at:
            if A.shape[0] <= 1000:
                w, v = np.linalg.eigh(A.toarray())
                keep = w > 1e-10 * w.max()
                pinv = (v[:, keep] / w[keep]) @ v[:, keep].T
                steps.append(("exact", lambda b, pinv=pinv: pinv @ b))
            else:
                steps.append(("exact", exact_solve(A)))
            break
        if kind[0] == "colours":
            steps.append(kind + (colour_sweeps(A, kept, shape),))
            continue
        if kind[0] == "node blocks":
            inverse = node_blocks(A, kept, int(np.prod(shape)))
        else:
            def inverse(v, g=1.0 / A.diagonal()):
                return g * v
        lmax = largest_eigenvalue(A, inverse)
        steps.append(kind + (inverse, lmax))

    def smooth(depth, A, b, x):
        kind = steps[depth]
        if kind[0] == "colours":
            forward, backward = kind[-1]
            if x is None:
                x = np.zeros_like(b)
                forward(A, x, b)
            else:
                backward(A, x, b)
            return x
        if kind[0] == "node blocks":
            inverse, lmax = kind[-2:]
            s = 1.0 / ((LOWER + UPPER) / 2 * lmax)
            return s * inverse(b) if x is None else x + s * inverse(b - A @ x)
        degree, inverse, lmax = kind[1], kind[-2], kind[-1]
        n = A.shape[0]

        def cases(v):  # the tool's (cases, 3, nodes) layout, padded with zeros to a multiple of 3
            out = np.zeros(3 * -(-n // 3))
            out[:n] = v.reshape(-1)[:n]
            return out.reshape(1, 3, -1)

        y = _chebyshev(lambda v: cases(A @ v.reshape(-1)[:n]), cases(inverse(np.ones(n)))[0], lmax, cases(b),
                       None if x is None else cases(x), degree=degree)
        return np.asarray(y).reshape(-1)[:n]

    def cycle(depth, b):
        A, P = levels[depth][:2]
        if steps[depth][0] == "exact":
            return steps[depth][1](b)
        x = smooth(depth, A, b, None)
        x = x + P @ cycle(depth + 1, P.T @ (b - A @ x))
        return smooth(depth, A, b, x)

    return sla.LinearOperator(K.shape, lambda r: cycle(0, np.asarray(r, float).ravel()), dtype=float)


def colour_sweeps(A, kept: np.ndarray, shape) -> tuple:
    """(forward, backward) Gauss-Seidel sweeps ``f(A, x, b)`` over the nodes of a level in 8 colours of their
    index parities (a node's three unknowns together). These grids' operators couple nodes at most one apart
    (and across an axis' ends only through the padding's void), so nodes of one colour share no entry of A:
    the order a device could run in parallel."""
    n = int(np.prod(shape))
    parity = np.array(np.unravel_index(kept % n, shape)) % 2
    colour = parity[0] * 4 + parity[1] * 2 + parity[2]
    rows = [np.flatnonzero(colour == c) for c in range(8)]
    blocks = [A[r] for r in rows]
    diag = A.diagonal()

    def sweep(order):
        def run(_, x, b):
            for c in order:
                x[rows[c]] += (b[rows[c]] - blocks[c] @ x) / diag[rows[c]]
        return run

    return sweep(range(8)), sweep(range(7, -1, -1))


def our_weight(K) -> float:
    """The tool's fine smoothing as a Jacobi weight: Chebyshev degree 1 on [LOWER, UPPER] x the largest
    eigenvalue of D^-1 K is the step 1 / theta, theta the interval's middle."""
    from implicit_scaffold.measure.multigrid import LOWER, UPPER

    g = 1.0 / K.diagonal()
    return 1.0 / (0.5 * (LOWER + UPPER) * largest_eigenvalue(K, lambda v: g * v))


def aggregation(model, dofs, K, *, geometric: bool, smooth: bool, smoother, fine_colours: bool = False):
    """PyAMG's aggregation with the six rigid motions: its own aggregates, or (`geometric`) 2x2x2 blocks of nodes
    on the fine level; `smoother` on every level, or with `fine_colours` an 8-colour SGS on the fine level."""
    import pyamg
    import scipy.sparse as sp

    kw = {}
    if geometric:
        n = int(np.prod(model.shape))
        node = np.array(np.unravel_index(dofs % n, model.shape)) // 2
        _, agg = np.unique(np.ravel_multi_index(tuple(node), tuple(-(-np.array(model.shape) // 2))),
                           return_inverse=True)
        first = sp.csr_matrix((np.ones(dofs.size), (np.arange(dofs.size), agg)), shape=(dofs.size, agg.max() + 1))
        kw["aggregate"] = [("predefined", {"AggOp": first})] + ["standard"] * 10
    ml = pyamg.smoothed_aggregation_solver(K, B=rigid_modes(model, dofs), max_coarse=1000,
                                           strength=("symmetric", {"theta": 0.0}),
                                           smooth="jacobi" if smooth else None,
                                           presmoother=smoother, postsmoother=smoother, **kw)
    if fine_colours:
        ml.levels[0].presmoother, ml.levels[0].postsmoother = colour_sweeps(K, dofs, model.shape)
    return ml.aspreconditioner(cycle="V")


def first_level_products(solid: np.ndarray, h: float, runs: int) -> list:
    """Rows (product, ms median, ms min, relative difference, MiB held) of one case's product on the first coarse
    level of the compression of `solid` along z (lateral faces free), on the tool's OpenCL operator."""
    from implicit_scaffold.measure import mechanics as m
    from implicit_scaffold.measure import mechanics_cl as mc

    from implicit_scaffold.measure import multigrid as mg

    model = m.voxel_model(m.load_path(solid, 2), h, m.material("ti64"), periodic=False)
    free, _ = m.platen_unknowns(model, 2)
    free = free.astype(np.float32)
    op = m._operator(model, "opencl")
    level = m.make_preconditioner("multigrid", model, op, free, m.TOL).levels[0]
    x = np.random.default_rng(0).standard_normal((1, 3, int(np.prod(level.shape)))).astype(np.float32)
    x *= level.inv_diag != 0
    stencils = mc.StencilLevelOperator(level)
    fine = op.single()

    def galerkin(y):
        """P^T F K F P y by the fine operator and the transfers (the tool's one-case product from 2026-12-06 to 2026-12-07)."""
        up = mg.prolong(y, model.shape)
        up *= free
        return mg.restrict(fine(up), model.shape, free)

    products = [(f"in use ({type(level.device).__name__})", level.device, 0),
                ("per element (stiffness_apply)", mc.LevelOperator(level), level.mats.nbytes + level.index.nbytes),
                ("Galerkin (fine operator, transfers)", galerkin, 0),
                ("node stencils (stencil_rows)", stencils, stencils._mats_host.nbytes)]
    reference = products[1][1](x)
    rows = []
    for name, product, held in products:
        diff = float(np.abs(product(x) - reference).max() / np.abs(reference).max())
        times = []
        for _ in range(runs):
            t0 = time.perf_counter()
            product(x)
            times.append(time.perf_counter() - t0)
        rows.append([name, f"{1e3 * np.median(times):.1f}", f"{1e3 * min(times):.1f}", f"{diff:.1e}",
                     f"{held / 2**20:.0f}" if held else "-"])
    print(f"the default cube's {solid.shape[0]}^3 corner compressed along z: its first coarse level "
          f"{'x'.join(str(v) for v in level.shape)}, {int((level.index >= 0).sum()):,} elements, one case, "
          f"medians of {runs}:")
    print(table(rows, ["product", "ms (median)", "ms (min)", "differs by", "MiB held"]))
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", type=int, default=48, help="the corner's edge, voxels")
    parser.add_argument("--tol", type=float, default=1e-7, help="the CG's relative residual")
    parser.add_argument("--only", default="", help="only the preconditioners whose name holds this text")
    parser.add_argument("--products", action="store_true",
                        help="time the first coarse level's one-case products instead (OpenCL; no CG)")
    parser.add_argument("--runs", type=int, default=15, help="--products: timed runs of each product")
    args = parser.parse_args(argv)
    if args.products:
        first_level_products(*default_cube_corner(args.size), args.runs)
        return 0
    try:
        import pyamg  # noqa: F401
    except ImportError:
        print("pyamg is not installed (pip install pyamg): only the tool's own rows are measured")
        pyamg = None
    solid, h = default_cube_corner(args.size)
    sgs = ("gauss_seidel", {"sweep": "symmetric"})
    jacobi = ("jacobi", {"omega": JACOBI_WEIGHT})
    rows = []
    for held in (False, True):
        model, free, K, dofs, b = compression_system(solid, h, held_sides=held)
        makers = [("ours", lambda: ours(model, free, dofs, False, K)),
                  ("ours + 8-colour SGS on the fine level", lambda: ours(model, free, dofs, True, K))]
        makers += [(f"ours assembled{name}", lambda kw=kw: ours_assembled(model, dofs, K, **kw))
                   for name, kw in ASSEMBLED]
        if pyamg is not None:
            makers += [
                ("our grids, SGS on every level", lambda: our_grids(model, dofs, K, sgs)),
                (f"our grids, Jacobi {JACOBI_WEIGHT} on every level", lambda: our_grids(model, dofs, K, jacobi)),
                ("our grids, 8-colour SGS on every level", lambda: our_grids(model, dofs, K, "colours")),
                ("our grids, ours' Jacobi on the fine level, SGS below",
                 lambda: our_grids(model, dofs, K, sgs, fine=("jacobi", {"omega": our_weight(K)}))),
                ("node aggregates + rigid modes, SGS", lambda: aggregation(model, dofs, K, geometric=True,
                                                                           smooth=False, smoother=sgs)),
                ("node aggregates + rigid modes, smoothed, SGS",
                 lambda: aggregation(model, dofs, K, geometric=True, smooth=True, smoother=sgs)),
                ("smoothed aggregation, SGS", lambda: aggregation(model, dofs, K, geometric=False, smooth=True,
                                                                  smoother=sgs)),
                ("smoothed aggregation, 8-colour SGS on the fine level, SGS below",
                 lambda: aggregation(model, dofs, K, geometric=False, smooth=True, smoother=sgs, fine_colours=True)),
                (f"smoothed aggregation, Jacobi {JACOBI_WEIGHT}",
                 lambda: aggregation(model, dofs, K, geometric=False, smooth=True, smoother=jacobi))]
        for name, make in makers:
            if args.only not in name:
                continue
            t0 = time.perf_counter()
            M = make()
            setup = time.perf_counter() - t0
            its, seconds = cg_iterations(K, b, M, args.tol)
            rows.append(["held" if held else "free", name, its if its >= 0 else "no convergence",
                         f"{setup:.1f}", f"{seconds:.1f}"])
            print(table(rows[-1:], ["lateral faces", "preconditioner", "CG its", "setup s", "solve s"]), flush=True)
    print(f"\nthe default cube's {args.size}^3 corner ({K.shape[0]:,} unknowns with held faces), compressed along z, "
          f"CG to {args.tol:g}:")
    print(table(rows, ["lateral faces", "preconditioner", "CG its", "setup s", "solve s"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
