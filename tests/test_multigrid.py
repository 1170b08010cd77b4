"""The multigrid preconditioner against dense products and the FFT preconditioner (issue 14)."""
import numpy as np
import pytest

from implicit_scaffold.measure import mechanics as M
from implicit_scaffold.measure import multigrid as G

MAT = M.material("ti64")


def _dense(op, shape_in, n_out=None):
    """The dense matrix of a linear map on (m, 3, N) arrays, one unit vector per column."""
    n_in = int(np.prod(shape_in))
    eye = np.eye(3 * n_in).reshape(3 * n_in, 3, n_in)
    cols = np.concatenate([op(eye[i:i + 64]) for i in range(0, 3 * n_in, 64)])
    return cols.reshape(3 * n_in, -1).T


@pytest.mark.parametrize("n", [7, 8])
def test_prolongation_interpolates_a_linear_field_exactly(n):
    # away from the periodic seam, trilinear interpolation of a linear field is the field
    cshape = G.coarse_shape((n, n, n))
    ci = np.indices(cshape) * 2.0  # coarse node I sits on fine node 2 I
    coarse = np.stack([0.5 + 1.0 * ci[0] - 2.0 * ci[1] + 0.25 * ci[2]] * 3)[None].reshape(1, 3, -1)
    fine = G.prolong(coarse, (n, n, n)).reshape(3, n, n, n)
    fi = np.indices((n, n, n)).astype(float)
    expect = 0.5 + 1.0 * fi[0] - 2.0 * fi[1] + 0.25 * fi[2]
    inner = (slice(0, 2 * (cshape[0] - 1) + 1),) * 3
    assert np.allclose(fine[0][inner], expect[inner], rtol=0, atol=1e-12)


def test_restriction_is_the_transpose_of_prolongation():
    rng = np.random.default_rng(1)
    shape = (7, 6, 5)
    r = rng.standard_normal((2, 3, int(np.prod(shape))))
    y = rng.standard_normal((2, 3, int(np.prod(G.coarse_shape(shape)))))
    assert np.vdot(G.restrict(r, shape), y) == pytest.approx(np.vdot(r, G.prolong(y, shape)), rel=1e-12)


@pytest.mark.parametrize("rows", [1, 3])
@pytest.mark.parametrize("shape", [(7, 6, 5), (8, 8, 6)])
def test_the_weighted_transfers_are_the_dense_ones(shape, rows):
    # restrict(r, w) = P^T (w r) and prolong_add(y, x, w): x + w (P y), P the dense prolongation
    # (column by column of prolong, which interpolates linear fields exactly); in float32 the
    # same bits as forming w r, or P y, in a pass of its own first (the V-cycle's claim)
    rng = np.random.default_rng(sum(shape) + rows)
    n, nc = int(np.prod(shape)), int(np.prod(G.coarse_shape(shape)))
    P = _dense(lambda v: G.prolong(v, shape), (nc,))
    w = (rng.random((rows, n)) < 0.7) * 1.0
    W = np.broadcast_to(w, (3, n)).ravel()
    r = rng.standard_normal((2, 3, n))
    y = rng.standard_normal((2, 3, nc))
    x = rng.standard_normal((2, 3, n))
    got = G.restrict(r, shape, w)
    assert np.allclose(got.reshape(2, -1), (r.reshape(2, -1) * W) @ P, rtol=0, atol=1e-12)
    added = x.copy()
    G.prolong_add(y, added, w, shape)
    assert np.allclose(added.reshape(2, -1), x.reshape(2, -1) + W * (y.reshape(2, -1) @ P.T), rtol=0, atol=1e-12)
    r32, y32, x32, w32 = (a.astype(np.float32) for a in (r, y, x, w))
    assert np.array_equal(G.restrict(r32, shape, w32), G.restrict(r32 * w32[None], shape))
    added = x32.copy()
    G.prolong_add(y32, added, w32, shape)
    assert np.array_equal(added, x32 + w32[None] * G.prolong(y32, shape))



@pytest.mark.parametrize("rows", [1, 3])
def test_the_smoothed_spread_onto_a_prolongation_is_the_two_passes_it_replaces(rows):
    # the V-cycle's post-smoothing start x = s g w r + w P e: put_smoothed_onto over prolong's P e (one pass over the
    # live nodes) against put_smoothed (spread, zeroing the grid) then prolong_add (w P e added), bit for bit on
    # the live nodes, in float32 from a float64 residual as the cycle runs them
    from implicit_scaffold.measure.fused import put_smoothed, put_smoothed_onto

    shape = (9, 8, 10)
    rng = np.random.default_rng(rows)
    n, nc = int(np.prod(shape)), int(np.prod(G.coarse_shape(shape)))
    live = np.flatnonzero(rng.random(n) < 0.45)
    w_grid = np.zeros((rows, n), np.float32)
    w_grid[:, live] = rng.random((rows, live.size)) < 0.9
    w = np.ascontiguousarray(w_grid[:, live])
    g = rng.random((rows, live.size)).astype(np.float32)
    r = rng.standard_normal((1, 3, live.size))
    y = rng.standard_normal((1, 3, nc)).astype(np.float32)
    s = 0.37
    want = put_smoothed(r, live, n, w, g, s, np.float32)
    G.prolong_add(y, want, w_grid, shape)
    got = G.prolong(y, shape)
    put_smoothed_onto(got, r, live, w, g, s)
    assert got.dtype == np.float32 and np.array_equal(got[:, :, live], want[:, :, live])
    # the other nodes keep P e (no live node's product reads them)
    rest = np.setdiff1d(np.arange(n), live)
    assert np.array_equal(got[:, :, rest], G.prolong(y, shape)[:, :, rest])
    # the pre-smoothing spread into a buffer kept across cases: without zeroing, the live nodes as spread afresh
    kept = rng.standard_normal((1, 3, n)).astype(np.float32)
    before = kept.copy()
    fresh = put_smoothed(r, live, n, w, g, s, np.float32)
    put_smoothed(r, live, n, w, g, s, np.float32, out=kept, zero=False)
    assert np.array_equal(kept[:, :, live], fresh[:, :, live]) and not fresh[:, :, rest].any()
    assert np.array_equal(kept[:, :, rest], before[:, :, rest])

@pytest.mark.parametrize("shape, periodic, fix", [((6, 5, 7), True, False), ((5, 6, 4), False, True),
                                                  ((8, 8, 8), True, False)])
def test_coarse_levels_are_galerkin_products_of_the_dense_operator(shape, periodic, fix):
    rng = np.random.default_rng(sum(shape))
    solid = rng.random(shape) < 0.5
    model = M.voxel_model(solid, 0.1, MAT, periodic=periodic)
    free = np.repeat(model.active[None], 3, axis=0).astype(float)
    if fix:  # some unknowns held (a face, a platen's axial component)
        free[:, :: 7] = 0
        free[2, 1:: 5] = 0
    F = free.ravel()
    A = _dense(lambda u: M.apply_stiffness(model, u), model.shape)
    AF = F[:, None] * A * F[None, :]
    cshape = G.coarse_shape(model.shape)
    P = _dense(lambda y: G.prolong(y, model.shape), cshape)
    level = G._first_coarse(model, free)
    expect = P.T @ AF @ P
    scale = np.abs(expect).max()
    assert np.abs(_dense(level.apply, cshape) - expect).max() < 1e-12 * scale
    assert np.abs(level.matrix() - expect).max() < 1e-12 * scale
    d = np.where(level.inv_diag.ravel() > 0, 1 / np.where(level.inv_diag.ravel() > 0, level.inv_diag.ravel(), 1), 0)
    live = level.inv_diag.ravel() > 0
    assert np.allclose(d[live], np.diag(expect)[live], rtol=1e-12)
    assert np.all(np.diag(expect)[~live] < 1e-12 * scale)
    # the next level from this one
    deeper = G._next_coarse(level)
    P2 = _dense(lambda y: G.prolong(y, cshape), deeper.shape)
    expect2 = P2.T @ expect @ P2
    assert np.abs(_dense(deeper.apply, deeper.shape) - expect2).max() < 1e-12 * np.abs(expect2).max()


def _scaffold(voxel):
    from implicit_scaffold.pipeline import generate

    r = generate(mesh=False, morphometry=False, size=1.28, pore_size=0.6, porosity=0.7, voxel=voxel, seed=0)
    inside = r.patient_sdf < 0
    box = tuple(slice(i.min(), i.max() + 1) for i in np.nonzero(inside))
    return (r.field < 0)[box]


@pytest.fixture(scope="module")
def scaffolds():
    """The same 30 % solid Voronoi scaffold (struts a few voxels thick) at 0.08 and 0.04 mm."""
    return {0.08: _scaffold(0.08), 0.04: _scaffold(0.04)}


def test_the_compact_cycle_lets_the_whole_grid_inverse_diagonal_go_and_spreads_it_back(scaffolds):
    # the CG's cycle reads the inverse diagonal on its live nodes only: the whole grid's copy goes when
    # nothing is lost off them, and a whole-grid cycle after gets it back bit for bit
    solid = scaffolds[0.08]
    model = M.voxel_model(solid, 0.08, MAT, periodic=False)
    free = model.active[None].astype(np.float32)
    mg = G.Multigrid(model, lambda u: M.apply_stiffness(model, u), free, dtype=np.float32)
    whole = mg.inv_diag.copy()
    x = np.random.default_rng(4).standard_normal((1, 3, free.shape[1])) * free
    before = mg(x)
    live = np.flatnonzero(free[0])
    mg.compact(live[::2])  # nonzeros off these nodes: the whole grid's copy stays
    assert mg._inv_diag is not None
    z = mg.compact(live)(x[:, :, live])
    assert mg._inv_diag is None
    assert np.array_equal(mg.inv_diag, whole)
    assert np.array_equal(mg(x), before)
    assert np.allclose(z, before[:, :, live], rtol=0, atol=1e-5 * np.abs(before).max())


@pytest.mark.parametrize("shape, periodic", [((13, 10, 12), True), ((12, 9, 11), False), ((9, 8, 8), True)])
def test_the_fine_level_by_slabs_is_the_whole_grids(shape, periodic, monkeypatch):
    # the CG's V-cycle with its fine level a slab of node planes at a time (each with its neighbours'
    # planes, wrapped round a periodic grid's ends; slabs of 1 to 5 planes, one of void): the whole-grid
    # cycle's result within float32's rounding (the restriction's sums over two slabs' planes are added
    # in another order)
    from implicit_scaffold.measure import mechanics_cl as mc

    rng = np.random.default_rng(1)
    solid = rng.random(shape) < 0.55
    solid[shape[0] // 2] = False
    model = M.voxel_model(solid, 0.1, MAT, periodic=periodic)
    free = model.active[None].astype(np.float32)
    if not periodic:  # a mask per unknown
        free = np.repeat(free, 3, axis=0)
        free[2, : free.shape[1] // 7] = 0
    mg = G.Multigrid(model, mc.StiffnessOperator(model).single(), free, dtype=np.float32)
    live = np.flatnonzero(free.any(axis=0))
    r = rng.standard_normal((2, 3, live.size))
    monkeypatch.setattr(G, "FINE_SLAB_NODES", 0)
    whole = mg.compact(live)(r)
    # handed over case by case, r.z with each as the CG sums it (wdot, weighed by ones)
    from implicit_scaffold.measure.fused import wdot

    seen = []
    mg.compact(live)(r, lambda c, z, rz: seen.append((c, z.copy(), rz)))
    assert [c for c, _, _ in seen] == [0, 1] and np.array_equal(np.concatenate([z for _, z, _ in seen]), whole)
    ones = np.ones((1, live.size), np.float32)
    assert all(rz == wdot(r[c:c + 1], z, ones)[0] for c, z, rz in seen)
    plane = model.shape[1] * model.shape[2]
    for planes in (1, 2, 3, 5):
        monkeypatch.setattr(G, "FINE_SLAB_NODES", planes * plane)
        assert mg._fine_slabs(live) is not None
        got = mg.compact(live)(r)
        assert np.abs(got - whole).max() <= 1e-6 * np.abs(whole).max(), planes
        seen = []
        mg.compact(live)(r, lambda c, z, rz: seen.append((c, z.copy(), rz)))
        assert [c for c, _, _ in seen] == [0, 1] and np.array_equal(np.concatenate([z for _, z, _ in seen]), got)


def test_the_v_cycle_is_symmetric_positive(scaffolds):
    solid = scaffolds[0.08]
    model = M.voxel_model(solid, 0.08, MAT, periodic=False)
    free = np.repeat(model.active[None], 3, axis=0).astype(float)
    free[:, : model.shape[1] * model.shape[2]] = 0  # one face held
    mg = G.Multigrid(model, lambda u: M.apply_stiffness(model, u), free)
    assert len(mg.levels) >= 2
    rng = np.random.default_rng(3)
    x, y = rng.standard_normal((2, 1, 3, free.shape[1])) * free
    mx, my = mg(x), mg(y)
    assert np.vdot(y, mx) == pytest.approx(np.vdot(x, my), rel=1e-9)
    assert np.vdot(x, mx) > 0 and np.vdot(y, my) > 0
    # the same cycle on vectors kept on the nodes with a free unknown only (the CG's own)
    live = np.flatnonzero(free.any(axis=0))
    assert not np.delete(mx, live, axis=2).any()
    assert np.allclose(mg.compact(live)(x[:, :, live]), mx[:, :, live], rtol=0, atol=1e-12 * np.abs(mx).max())
    # a block of three load cases: the compact cycle runs its fine level a case at a time; the whole-grid
    # cycle runs the block at once, and each case alone gives its own column
    xs = rng.standard_normal((3, 3, free.shape[1])) * free
    ms = mg(xs)
    for c in range(3):
        assert np.allclose(ms[c], mg(xs[c:c + 1])[0], rtol=0, atol=1e-12 * np.abs(ms).max())
    assert np.allclose(mg.compact(live)(xs[:, :, live]), ms[:, :, live], rtol=0, atol=1e-12 * np.abs(ms).max())
    # handed over in a narrower float (the CG's p's, with float products): the same values, rounded once
    z32 = mg.compact(live, np.float32)(xs[:, :, live])
    assert z32.dtype == np.float32
    assert np.array_equal(z32, mg.compact(live)(xs[:, :, live]).astype(np.float32))


def test_multigrid_and_fft_give_the_same_tensor(scaffolds):
    solid = scaffolds[0.08]
    mg = M.homogenize(solid, 0.08, MAT, tol=1e-8, preconditioner="multigrid")
    fft = M.homogenize(solid, 0.08, MAT, tol=1e-8, preconditioner="fft")
    assert np.abs(mg.stiffness - fft.stiffness).max() < 1e-6 * np.abs(fft.stiffness).max()
    assert mg.iterations < fft.iterations / 2


def test_multigrid_iterations_stay_flat_when_struts_are_refined(scaffolds):
    # the FFT preconditioner's count grows with the refinement of thin struts (the void's contrast);
    # a multigrid over the solid keeps it nearly flat
    its = {}
    for h, solid in scaffolds.items():
        hom = M.homogenize(solid, h, MAT, tol=1e-6, backend="opencl")
        comp = M.compress(solid, h, MAT, tol=1e-6, backend="opencl")
        its[h] = (hom.iterations, comp.iterations)
    assert its[0.04][0] <= 1.3 * its[0.08][0]
    assert its[0.04][1] <= 1.3 * its[0.08][1]
    assert max(its[0.04]) < 60


@pytest.mark.parametrize("cases", [1, 6])  # the solver sends the device a block of load cases, or one
def test_a_coarse_level_on_every_opencl_device_matches_the_compiled_one(cases):
    from implicit_scaffold import opencl
    from implicit_scaffold.measure.mechanics_cl import LevelOperator, has_double

    rng = np.random.default_rng(5)
    solid = rng.random((9, 10, 11)) < 0.4
    model = M.voxel_model(solid, 0.1, MAT, periodic=True)
    free = np.repeat(model.active[None], 3, axis=0).astype(float)
    devices = opencl.working_devices()
    assert devices, "no working OpenCL device"
    for dtype, tol in ((np.float32, 1e-6), (np.float64, 1e-12)):
        level = G._first_coarse(model, free, dtype)
        x = rng.standard_normal((cases, 3, int(np.prod(level.shape)))).astype(dtype)
        ref = level.apply(x.astype(np.float64))
        for check in devices:
            with opencl.using(check):
                if dtype == np.float64 and not has_double():
                    continue
                got = LevelOperator(level)(x)
                assert np.abs(got - ref).max() <= tol * np.abs(ref).max(), check.name


@pytest.mark.parametrize("vote", [True, False])
@pytest.mark.parametrize("shape, density", [((10, 12, 40), 0.3), ((9, 10, 11), 0.4), ((8, 8, 70), 0.3),
                                            ((12, 8, 70), 0.01)])
def test_a_level_on_node_stencils_is_the_dense_levels_product(shape, density, vote, monkeypatch):
    # StencilLevelOperator (the elements' matrices assembled per node by node_stencils) against the
    # level's dense matrix (np.add.at over the element matrices), for one case and six, on the first
    # and second levels: odd axes, axes of 2 and 3 nodes (a neighbour on both sides is one node),
    # rows of 33 inner nodes (vectors of 16 and one), and a sparse solid whose rows hold vectors no
    # element touches; the vote on and off
    from implicit_scaffold import opencl
    from implicit_scaffold.measure import mechanics_cl as mc

    if not vote:
        monkeypatch.setattr(mc, "has_vote", lambda: False)
    rng = np.random.default_rng(sum(shape))
    solid = rng.random(shape) < density
    model = M.voxel_model(solid, 0.1, MAT, periodic=True)
    free = np.repeat(model.active[None], 3, axis=0).astype(float)
    first = G._first_coarse(model, free, np.float64)
    for level in (first, G._next_coarse(first)):
        nc = int(np.prod(level.shape))
        A = level.matrix()
        untouched = ~A.reshape(3, nc, 3 * nc).any(axis=(0, 2))
        for dtype, tol in ((np.float32, 1e-6), (np.float64, 1e-12)):
            typed = G.Level(level.shape, level.index, level.mats.astype(dtype), level.inv_diag)
            for cases in (1, 6):
                x = rng.standard_normal((cases, 3, nc))
                ref = (x.reshape(cases, -1) @ A.T).reshape(cases, 3, nc)
                for check in opencl.working_devices():
                    with opencl.using(check):
                        if dtype == np.float64 and not mc.has_double():
                            continue
                        got = mc.StencilLevelOperator(typed)(x.astype(dtype))
                        assert got.dtype == dtype
                        assert np.abs(got - ref).max() <= tol * np.abs(ref).max(), check.name
                        assert not got[:, :, untouched].any(), check.name


@pytest.mark.parametrize("shape", [(10, 12, 9), (9, 2, 3)])
def test_the_half_node_stencils_give_back_every_block_of_the_dense_level(shape):
    # node_stencils keeps the blocks of neighbours q >= 13 only (the kernel reads the others transposed at
    # the neighbour); full_stencils' 27 blocks, summed per neighbour node, against the level's dense matrix
    # (np.add.at over the element matrices): odd axes, and axes of 2 and 3 nodes, where neighbours on both
    # sides are one node and their blocks add
    rng = np.random.default_rng(sum(shape))
    model = M.voxel_model(rng.random(shape) < 0.4, 0.1, MAT, periodic=True)
    free = np.repeat(model.active[None], 3, axis=0).astype(float)
    first = G._first_coarse(model, free, np.float64)
    for level in (first, G._next_coarse(first)):
        n1, n2, n3 = level.shape
        nc = n1 * n2 * n3
        half, live = G.node_stencils(level)
        assert half.shape == (n1 * n2, 126, n3)
        blocks = G.full_stencils(half, level.shape)
        got = np.zeros((3, nc, 3, nc))
        ijk = np.array(np.unravel_index(np.arange(nc), level.shape))
        for q in range(27):
            off = np.array([q % 3 - 1, q // 3 % 3 - 1, q // 9 - 1])[:, None]
            m = np.ravel_multi_index(tuple((ijk + off) % np.array(level.shape)[:, None]), level.shape)
            for d in range(3):
                for e in range(3):
                    np.add.at(got, (d, np.arange(nc), e, m), blocks[q, d, e])
        A = level.matrix().reshape(3, nc, 3, nc)
        assert np.abs(got - A).max() <= 1e-12 * np.abs(A).max()
        assert np.array_equal(live.astype(bool), A.any(axis=(0, 2, 3)))


def test_the_fine_inverse_diagonal_is_the_masked_inverse_in_one_row_where_its_rows_are_equal(monkeypatch):
    # oracle: the formula it replaced, free * _inverse_diagonal(d) in double, cast after; one row where the
    # rows are equal (a mask per node, an isotropic element), three where they are not. And the Lanczos
    # start drawn a chunk at a time is one whole draw, masked and cast
    rng = np.random.default_rng(4)
    model = M.voxel_model(rng.random((9, 10, 11)) < 0.4, 0.1, MAT, periodic=True)
    d = M.diagonal(model)
    node = model.active.astype(np.float32)
    other = node * (rng.random(d.shape[1]) < 0.7)
    for free in (node[None], np.stack([node, node, other]), (rng.random((3, d.shape[1])) < 0.7).astype(np.float32)):
        want = (free * G._inverse_diagonal(d)).astype(np.float32)
        got = G._fine_inverse_diagonal(d, free, np.float32)
        assert got.dtype == np.float32
        assert np.array_equal(np.broadcast_to(got, want.shape), want)
        assert len(got) == (1 if len(free) == 1 else 3)
        monkeypatch.setattr(G, "RANDOM_CHUNK", 97)
        start = G._random_start(np.random.default_rng(1), got)
        whole = (np.random.default_rng(1).standard_normal((1, 3, d.shape[1])) * (want > 0)).astype(np.float32)
        assert np.array_equal(start, whole)


def test_a_float32_level_coarsens_in_float32_as_its_float64_copy_would_without_holding_one():
    # oracle: the next level of the same matrices widened to float64 (exactly), rounded to float32 after
    import tracemalloc

    rng = np.random.default_rng(3)
    model = M.voxel_model(rng.random((24, 24, 24)) < 0.5, 0.1, MAT, periodic=True)
    free = np.repeat(model.active[None], 3, axis=0).astype(np.float32)
    level = G._first_coarse(model, free, np.float32)
    level.mats = np.asarray(rng.standard_normal(level.mats.shape), np.float32)  # one matrix per element
    level.index = np.arange(level.index.size, dtype=np.int32).reshape(level.index.shape)
    level.mats = np.resize(level.mats, (level.index.size, 24, 24))
    wide = G.Level(level.shape, level.index, level.mats.astype(np.float64), level.inv_diag)
    expect = G._next_coarse(wide).mats.astype(np.float32)
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        tracemalloc.reset_peak()
        got = G._next_coarse(level)
        peak = tracemalloc.get_traced_memory()[1] - before
    finally:
        tracemalloc.stop()
    assert got.mats.dtype == np.float32
    assert np.array_equal(got.mats, expect)
    # the new level's matrices, its diagonal and the coarsening's mask of ones: no float64 copy of the
    # level's matrices (twice their bytes), nor a float64 result beside the float32 one
    n = int(np.prod(level.shape))
    assert peak < level.mats.nbytes + 3 * got.mats.nbytes + 3 * n * 8 * 2


def test_child_matrices_are_the_interpolated_element_matrix():
    # M_c = W_c^T Ke W_c, W_c built here from its definition: fine corner q of child c = (a, b, c)
    # sits at ((a, b, c) + offset(q)) / 2 in the coarse element, where coarse corner r weighs the
    # product over the axes of t (r's bit 1) or 1 - t (bit 0)
    ke = M.voxel_model(np.ones((2, 2, 2), bool), 0.1, MAT, periodic=True).ke
    bits = np.array([[(v >> ax) & 1 for ax in range(3)] for v in range(8)])  # (8, 3)
    got = G.child_matrices(ke)
    assert got.shape == (8, 24, 24)
    for c in range(8):
        t = (bits[c][None, :] + bits) / 2  # (q, axis)
        W = np.prod(np.where(bits[None, :, :] == 1, t[:, None, :], 1 - t[:, None, :]), axis=2)  # (q, r)
        W24 = np.kron(W, np.eye(3))  # unknown 3 corner + d
        expect = W24.T @ ke @ W24
        assert np.abs(got[c] - expect).max() < 1e-12 * np.abs(expect).max()
    # a full element (all eight children) is the whole element's Galerkin product: the sum
    # over the children of W_c^T Ke W_c, whose rigid translations it keeps in its null space
    assert np.abs(got.sum(axis=0) @ np.tile(np.eye(3), (8, 1))).max() < 1e-12 * np.abs(got).max()


@pytest.mark.parametrize("shape, periodic, fix", [((10, 12, 14), True, None), ((9, 10, 11), True, None),
                                                  ((9, 12, 11), False, "kinematic"), ((8, 9, 38), False, "platens"),
                                                  ((5, 6, 4), False, "kinematic")])
@pytest.mark.parametrize("cases", [1, 2, 6])  # one case a launch: the per-element kernel alone
def test_the_first_levels_pattern_product_matches_the_dense_level(shape, periodic, fix, cases):
    # PatternLevelOperator (8 child matrices on the elements with no fixed unknown and full length,
    # a matrix per element added for the others) against the level's dense matrix and against the
    # per-element kernel, on even and odd axes (odd: short end elements), with a face's unknowns
    # held (kinematic-like) or a component of some (platens-like); 38 fine voxels along z make
    # rows of 17 inner coarse nodes (two vectors of 16), 4 none (the row ends alone)
    from implicit_scaffold import opencl
    from implicit_scaffold.measure.mechanics_cl import LevelOperator, PatternLevelOperator, has_double

    rng = np.random.default_rng(sum(shape) + cases)
    solid = rng.random(shape) < 0.4
    model = M.voxel_model(solid, 0.1, MAT, periodic=periodic)
    free = np.repeat(model.active[None], 3, axis=0).astype(float)
    if fix == "kinematic":
        free[:, : model.shape[1] * model.shape[2]] = 0
    elif fix == "platens":
        free[2, 1:: 5] = 0
    devices = opencl.working_devices()
    assert devices, "no working OpenCL device"
    for dtype, tol in ((np.float32, 1e-6), (np.float64, 1e-12)):
        level = G._first_coarse(model, free, dtype)
        pattern = level.pattern
        built = level.index >= 0
        # both kinds of element are there, except on a periodic grid of even axes (patterns only)
        assert (pattern[built] > 0).any()
        assert (pattern[built] == 0).any() == (fix is not None or any(n % 2 for n in shape))
        assert not pattern[~built].any()
        nc = int(np.prod(level.shape))
        x = rng.standard_normal((cases, 3, nc)).astype(dtype)
        ref = (x.astype(np.float64).reshape(cases, -1) @ level.matrix().T).reshape(cases, 3, nc)
        scale = np.abs(ref).max()
        children = G.child_matrices(model.ke).astype(dtype)
        for check in devices:
            with opencl.using(check):
                if dtype == np.float64 and not has_double():
                    continue
                got = PatternLevelOperator(level, pattern, children)(x)
                assert got.dtype == dtype
                assert np.abs(got - ref).max() <= tol * scale, check.name
                assert np.abs(got - LevelOperator(level)(x)).max() <= tol * scale, check.name


@pytest.mark.parametrize("vote", [True, False])
def test_the_pattern_product_skips_untouched_vectors_exactly(vote, monkeypatch):
    # pattern_rows skips the products of a vector of coarse nodes no pattern element touches (by a
    # sub-group vote where the device has one, else per work item): the dense level's product
    # either way, on a sparse solid whose coarse rows (33 inner nodes along z) hold untouched
    # vectors, a vector touched at one lane, and rows of none
    from implicit_scaffold import opencl
    from implicit_scaffold.measure import mechanics_cl as mc

    if not vote:
        monkeypatch.setattr(mc, "has_vote", lambda: False)
    solid = np.zeros((8, 9, 70), bool)
    solid[2:4, 4:6, 40:42] = True
    solid[5, 2, 0:3] = True
    model = M.voxel_model(solid, 0.1, MAT, periodic=True)
    free = np.repeat(model.active[None], 3, axis=0).astype(float)
    rng = np.random.default_rng(9)
    for dtype, tol in ((np.float32, 1e-6), (np.float64, 1e-12)):
        level = G._first_coarse(model, free, dtype)
        nc = int(np.prod(level.shape))
        x = rng.standard_normal((2, 3, nc)).astype(dtype)
        ref = (x.astype(np.float64).reshape(2, -1) @ level.matrix().T).reshape(2, 3, nc)
        untouched = ~np.abs(level.matrix()).reshape(3 * nc, 3 * nc).any(axis=1).reshape(3, nc).any(axis=0)
        assert untouched.mean() > 0.9
        for check in opencl.working_devices():
            with opencl.using(check):
                if dtype == np.float64 and not mc.has_double():
                    continue
                got = mc.PatternLevelOperator(level, level.pattern, G.child_matrices(model.ke).astype(dtype))(x)
                assert np.abs(got - ref).max() <= tol * np.abs(ref).max(), check.name
                assert not got[:, :, untouched].any(), check.name


@pytest.mark.parametrize("flag", ["FIRST_LEVEL_PATTERNS", "STENCIL_LEVELS"])
@pytest.mark.parametrize("boundary, tol", [("periodic", 1e-6), ("kinematic", 1e-6), ("periodic", 1e-8)])
def test_the_device_products_of_the_levels_leave_the_solve_as_it_was(scaffolds, monkeypatch, boundary, tol, flag):
    # the same tensor and the same iteration count with the per-element kernel on the first
    # level, or on the levels under it (the code before): the products differ by rounding only
    # (float cycle at 1e-6, double at 1e-8)
    solid = scaffolds[0.08]
    got = {}
    for on in (False, True):
        monkeypatch.setattr(G, flag, on)
        got[on] = M.homogenize(solid, 0.08, MAT, boundary=boundary, tol=tol, backend="opencl")
    assert got[True].iterations == got[False].iterations
    C = got[False].stiffness
    assert np.abs(got[True].stiffness - C).max() < tol * np.abs(C).max()


def test_the_pattern_operator_is_the_first_levels_device_product(scaffolds, monkeypatch):
    from implicit_scaffold.measure.mechanics_cl import (LevelOperator, PatternLevelOperator, StencilLevelOperator,
                                                        StiffnessOperator)

    model = M.voxel_model(scaffolds[0.08], 0.08, MAT, periodic=False)
    free = np.repeat(model.active[None], 3, axis=0).astype(np.float32)
    free[:, : model.shape[1] * model.shape[2]] = 0
    op = StiffnessOperator(model, double=False)
    mg = G.Multigrid(model, op, free, dtype=np.float32)
    assert len(mg.levels) >= 2
    # a block of cases by the pattern kernel (one case by its per-element kernel)
    first = mg.levels[0].device
    assert type(first) is PatternLevelOperator
    assert all(type(level.device) is StencilLevelOperator for level in mg.levels[1:])
    # the level keeps the one copy of its matrices the device reads (the per-element ones); a level
    # on stencils keeps none
    assert np.shares_memory(mg.levels[0].mats, first._mats_host)
    assert all(level.mats is None for level in mg.levels[1:])
    monkeypatch.setattr(G, "FIRST_LEVEL_PATTERNS", False)
    monkeypatch.setattr(G, "STENCIL_LEVELS", False)
    mg = G.Multigrid(model, op, free, dtype=np.float32)
    assert all(type(level.device) is LevelOperator for level in mg.levels)


def test_the_eigenvalue_estimate_reuses_its_products_memory():
    # a diagonal operator (D^-1 A's spectrum known: its largest entry bounds the estimate, a Ritz
    # value), with every product's output from one pool: a few buffers for the twelve products, not
    # a new one each (fresh pages, which the kernel zeroes)
    from implicit_scaffold.measure import mechanics_cl as mc

    rng = np.random.default_rng(4)
    n = mc.POOLED_BYTES // 4  # (1, 3, n) float32 products over the pool's threshold
    A = rng.random(3 * n).astype(np.float32) + 1.0
    inv_diag = (rng.random((3, n)) + 0.5).astype(np.float32)
    buffers, pooled = set(), []

    def apply(x):
        y = mc.aligned_empty(x.shape, x.dtype)
        buffers.add(y.ctypes.data)
        pooled.append(mc._pool is not None and any(np.shares_memory(y, raw) for raw in mc._pool))
        np.multiply(x, A.reshape(1, 3, n), out=y)
        return y

    got = G._largest_eigenvalue(apply, inv_diag, np.random.default_rng(0))
    top = float((A.reshape(3, n) * inv_diag).max())
    assert 0.9 * top <= got <= top * (1 + 1e-5)
    assert len(buffers) <= 3 and len(pooled) == G.LANCZOS_STEPS and all(pooled)


@pytest.mark.parametrize("n, seed, share", [(14, 0, 0.5), (16, 1, 0.4), (12, 3, 0.6)])
def test_the_largest_eigenvalue_is_found_where_its_eigenvector_is_local(n, seed, share):
    # oracle: ARPACK's largest eigenvalue of D^-1/2 K D^-1/2 (the spectrum of D^-1 K), converged to 1e-10,
    # through the NumPy operator. On random solids the top eigenvectors sit on a few voxels, which a
    # random start barely holds: twelve power iterations found 0.84 to 0.93 of it here (the smoothers'
    # intervals then end under the spectrum and the V-cycle is not positive definite, as on the L3
    # vertebra at 0.5 mm); the estimate must lie within 3 % under it, never over
    from scipy.sparse.linalg import LinearOperator, eigsh

    rng = np.random.default_rng(seed)
    model = M.voxel_model(rng.random((n, n, n)) < share, 0.1, MAT, periodic=True)
    size = int(np.prod(model.shape))
    inv_diag = G._inverse_diagonal(M.diagonal(model))
    half = np.sqrt(inv_diag)

    def product(v):
        v = v.reshape(1, 3, size) * half
        return (M.apply_stiffness(model, v) * half).ravel()

    top = eigsh(LinearOperator((3 * size, 3 * size), matvec=product, dtype=float), k=1, which="LA",
                tol=1e-10)[0][0]
    got = G._largest_eigenvalue(lambda u: M.apply_stiffness(model, u), inv_diag, np.random.default_rng(0))
    assert 0.97 * top <= got <= top * (1 + 1e-9)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("rows", [1, 3])
def test_fused_vector_passes_match_numpy(dtype, rows):
    from implicit_scaffold.measure import fused

    rng = np.random.default_rng(rows)
    m, n = 2, 1009  # odd: pieces of unequal length
    tol = 1e-12 if dtype == np.float64 else 1e-5
    x, p, r, q, z, b, y = (rng.standard_normal((m, 3, n)).astype(dtype) for _ in range(7))
    w = rng.random((rows, n)).astype(dtype)
    alpha, beta = np.array([0.3, -1.5]), np.array([0.7, 0.0])

    def close(got, want):
        return np.allclose(got, want, rtol=tol, atol=tol * np.abs(want).max())

    assert close(fused.wdot(p, q, w), (p * q * w).sum(axis=(1, 2)))
    xe, re = x + alpha[:, None, None] * p, r - alpha[:, None, None] * (w * q)
    rr = fused.cg_update(x, p, r, q, w, alpha)
    assert close(x, xe) and close(r, re) and close(rr, (re.astype(float) ** 2).sum(axis=(1, 2)))
    pe = z + beta[:, None, None] * p
    fused.xpby(z, p, beta)
    assert close(p, pe)
    out = np.full_like(b, np.nan)  # an empty output is never read
    assert close(fused.weighted(out, b, w, 0.5), 0.5 * w * b)
    assert close(fused.weighted(y.copy(), b, w, 2.0, y=y), 2.0 * w * (b - y))
    xe = x + 0.25 * w * (b - y)
    fused.add_weighted(x, b, w, 0.25, y=y)
    assert close(x, xe)
    xe = x + w * b
    fused.add_weighted(x, b, w)
    assert close(x, xe)
    # the CG's vectors on some nodes only (every other one, and the last), to and from the grid
    idx = np.r_[np.arange(0, n - 1, 2), n - 1]
    assert close(fused.take(b, idx, w[:, idx]), w[:, idx] * b[:, :, idx])
    spread = np.zeros_like(b)
    spread[:, :, idx] = w[:, idx] * b[:, :, idx]
    got = fused.put(b[:, :, idx], idx, n, w[:, idx], np.float64)
    assert got.dtype == np.float64 and close(got, spread)
    # the V-cycle's fine level on live-node vectors: a Jacobi step from zero spread, a right-hand side
    # added on the live nodes, a Jacobi step from x taken back
    g = rng.random((3, n)).astype(dtype)
    src = rng.standard_normal((m, 3, len(idx)))  # the CG's float64 residual
    want = np.zeros((m, 3, n))
    want[:, :, idx] = 0.7 * g[:, idx] * (w[:, idx] * src)
    got = fused.put_smoothed(src, idx, n, w[:, idx], g[:, idx], 0.7, dtype)
    assert got.dtype == dtype and close(got, want)
    want = y.astype(float)
    want[:, :, idx] += w[:, idx] * src
    fused.put_add(y, src, idx, w[:, idx])
    assert close(y, want)
    want[:, :, idx] -= 2 * w[:, idx] * src
    fused.put_add(y, 2 * src, idx, w[:, idx], subtract=True)
    assert close(y, want)
    want = w[:, idx] * (x[:, :, idx] + 0.7 * g[:, idx] * (w[:, idx] * src - b[:, :, idx]))
    got = fused.take_smoothed(x, b, src, idx, w[:, idx], g[:, idx], 0.7)
    assert got.dtype == np.float64 and close(got, want)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_centering_takes_each_components_mean_off_as_numpy_does(dtype):
    # the periodic CG's z off the translations: each case's and component's mean (summed in double) rounded to
    # z's float and taken off, as NumPy's mean and in-place subtraction did (its pairwise sum in another order:
    # the same to rounding); the result sums to ~0
    from implicit_scaffold.measure import fused

    rng = np.random.default_rng(5)
    z = (rng.standard_normal((2, 3, 100_003)) + np.arange(6).reshape(2, 3, 1) * 10).astype(dtype)
    mean = z.mean(axis=2, keepdims=True, dtype=np.float64)
    want = z - mean.astype(dtype)
    got = fused.center(z)
    assert got is z
    # a mean within 1e-12 of NumPy's (two sums of 1e5 terms in double), then at most an ulp apart once rounded
    step = max(1e-12, np.finfo(dtype).eps) * np.abs(mean).max()
    assert np.abs(got - want).max() <= step
    assert np.abs(got.astype(float).mean(axis=2)).max() < 4 * np.finfo(dtype).eps * np.abs(mean).max()


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("rows", [1, 3])
def test_a_lanczos_steps_passes_are_numpys_operations(dtype, rows):
    # oracle: the NumPy operations of a Lanczos step they replace (each product rounded alike; the sums, in double
    # here, within the vectors' rounding of NumPy's)
    from implicit_scaffold.measure import fused

    rng = np.random.default_rng(rows + 3)
    n = 2003
    w, v, prev = (rng.standard_normal((1, 3, n)).astype(dtype) for _ in range(3))
    g = rng.random((rows, n)).astype(dtype)
    tol = 1e-12 if dtype == np.float64 else 1e-5
    want = w * g
    dot = fused.lanczos_pass(0, w, v, g)
    assert np.array_equal(w, want) and dot == pytest.approx(float(np.vdot(v.astype(float), want)), rel=tol)
    alpha, beta = dtype(0.37), dtype(1.9)
    for before in (prev, None):
        want = w - v * alpha
        if before is not None:
            want = want - before * beta
        got = fused.lanczos_pass(1, w, v, g, alpha=float(alpha), beta=float(beta), prev=before)
        assert np.array_equal(w, want)
        assert got == pytest.approx(float((want.astype(float) ** 2).sum()), rel=tol)
    t = np.empty_like(w)
    want = w / beta
    assert fused.lanczos_pass(2, w, v, g, beta=float(beta), t=t) == 0.0
    assert np.array_equal(w, want) and np.array_equal(t, want * g)
    # a product in another float is left to NumPy
    assert fused.lanczos_pass(0, w.astype(np.float64 if dtype == np.float32 else np.float32), v, g) is None


def test_a_node_codes_table_lookup_is_numpys_take():
    # the periodic right-hand side: a value of a (case, component) table of 256 per node by its corner bits
    from implicit_scaffold.measure import fused

    rng = np.random.default_rng(6)
    table = rng.standard_normal((6, 3, 256))
    code = rng.integers(0, 256, 10_007).astype(np.uint8)
    got = fused.lookup(table, code)
    assert got.shape == (6, 3, code.size) and got.dtype == np.float64
    assert np.array_equal(got, np.take(table, code.astype(np.intp), axis=2))


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("rows", [1, 3])
def test_dots_summed_while_taking_are_wdots_bit_for_bit(dtype, rows):
    # the CG's p.Kp summed as the product's live nodes are taken, and r.z as the V-cycle takes z: the same
    # bits as wdot over the taken vectors (the CG's step lengths, and so its iterates, do not change)
    from implicit_scaffold.measure import fused

    rng = np.random.default_rng(rows + 7)
    m, n = 1, 5003
    idx = np.flatnonzero(rng.random(n) < 0.45)
    k = len(idx)
    grid = rng.standard_normal((m, 3, n)).astype(dtype)
    w = (rng.random((rows, k)) < 0.9).astype(np.float32)
    p = rng.standard_normal((m, 3, k)).astype(dtype)
    ones = np.ones((1, k), np.float32)  # as the CG takes K p: unmasked, and p.Kp weighed by the free mask
    got, dot = fused.take_dot(grid, idx, ones, p, w, np.float64)
    want = fused.take(grid, idx, ones, np.float64)
    assert np.array_equal(got, want) and np.array_equal(dot, fused.wdot(p, want, w))
    assert dot[0] == pytest.approx(float((p * want * w).sum()), rel=1e-9)  # and it is that sum
    x, ax = (rng.standard_normal((m, 3, n)).astype(dtype) for _ in range(2))
    g = rng.random((3, k)).astype(dtype)
    src = rng.standard_normal((m, 3, k))  # the CG's residual, in double
    z, rz = fused.take_smoothed(x, ax, src, idx, w, g, 0.7, np.float32, dot=True)
    assert np.array_equal(z, fused.take_smoothed(x, ax, src, idx, w, g, 0.7, np.float32))
    assert np.array_equal(rz, fused.wdot(src, z, np.ones((1, k), np.float32)))
    assert rz[0] == pytest.approx(float((src * z.astype(float)).sum()), rel=1e-9)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("rows", [1, 3])
def test_fused_chebyshev_step_is_numpys_bit_for_bit(dtype, rows):
    # the coarse levels' smoothing step in one pass must round each product as NumPy's in-place operations
    # did (the V-cycle, and so the CG's iterates, are the same bits either way)
    from implicit_scaffold.measure import fused

    rng = np.random.default_rng(11)
    m, n = 3, 1013
    r, a, b, d, x = (rng.standard_normal((m, 3, n)).astype(dtype) for _ in range(5))
    g = rng.random((rows, n)).astype(dtype)
    c1, c2 = 0.731, 1.27
    want_r, want_d, want_x = r - a, d.copy(), x.copy()
    want_d *= c1
    t = g * want_r
    t *= c2
    want_d += t
    want_x += want_d
    assert fused.chebyshev_step(r, a, d, x, g, c1, c2)
    assert np.array_equal(r, want_r) and np.array_equal(d, want_d) and np.array_equal(x, want_x)
    # the first step from an iterate: r = b - A x, d = c2 g r, x += d
    want_r = b - a
    want_d = g * want_r
    want_d *= c2
    want_x = x + want_d
    assert fused.chebyshev_step(r, a, d, x, g, 0.0, c2, b=b)
    assert np.array_equal(r, want_r) and np.array_equal(d, want_d) and np.array_equal(x, want_x)
    # the first step from 0: r = b, d = c2 g b, x = d
    want_r = b.copy()
    want_d = g * b
    want_d *= c2
    assert fused.chebyshev_step(r, b, d, x, g, 0.0, c2, b=b, start=True)
    assert np.array_equal(r, want_r) and np.array_equal(d, want_d) and np.array_equal(x, want_d)
    # arrays it cannot take are left to NumPy, untouched
    before = r.copy()
    assert not fused.chebyshev_step(r, a.astype(np.float64 if dtype == np.float32 else np.float32), d, x, g, c1, c2)
    assert np.array_equal(r, before)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_an_unweighted_prolongation_added_in_place_is_prolong_then_add(dtype):
    # a coarse level's correction x += P e in one pass: the bits of prolong then +=
    rng = np.random.default_rng(4)
    fine = (9, 8, 7)
    e = rng.standard_normal((2, 3, int(np.prod(G.coarse_shape(fine))))).astype(dtype)
    x = rng.standard_normal((2, 3, int(np.prod(fine)))).astype(dtype)
    want = x + G.prolong(e, fine)
    G.prolong_add(e, x, None, fine)
    assert np.array_equal(x, want)


def test_chebyshev_smoothing_reduces_the_error_as_its_polynomial_says():
    # _chebyshev (fused steps) against the polynomial in closed form: on A = diag(lams), D = I, b = A e, from
    # x = 0 the error after degree k is T_k((theta - lam) / delta) / T_k(theta / delta) e per eigenvalue
    from numpy.polynomial.chebyshev import chebval

    lmax = 4.0
    lams = np.linspace(0.05, lmax, 3 * 500).reshape(1, 3, 500)
    e = np.random.default_rng(2).standard_normal(lams.shape)
    lo, hi = G.LOWER * lmax, G.UPPER * lmax
    theta, delta = (hi + lo) / 2, (hi - lo) / 2
    for degree in (1, 2, 3):
        x = G._chebyshev(lambda v: lams * v, np.ones((3, 500)), lmax, lams * e, degree=degree)
        tk = chebval((theta - lams) / delta, [0] * degree + [1]) / chebval(theta / delta, [0] * degree + [1])
        assert np.allclose(e - x, tk * e, rtol=1e-9, atol=1e-9)
        # and from an iterate (the post-smoothing): one more degree's worth from x0 = the last result
        x0 = x.copy()
        x = G._chebyshev(lambda v: lams * v, np.ones((3, 500)), lmax, lams * e, x0, degree=degree)
        assert np.allclose(e - x, tk * tk * e, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("kind", ["sparse", "all"])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_spreading_onto_used_memory_zeroes_every_other_node(kind, dtype):
    # put and put_smoothed write the grid's other nodes themselves (no zeroing pass first): on
    # memory a dropped array held (the pool of reusing hands it out again, NaN-filled here) every
    # node off idx must read 0
    from implicit_scaffold.measure import fused
    from implicit_scaffold.measure.mechanics_cl import aligned_empty, reusing

    rng = np.random.default_rng(5)
    n = 300_001  # (1, 3, n) of float32 is over the pool's 1 MiB
    idx = {"sparse": np.flatnonzero(rng.random(n) < 0.3)[3:-3],  # neither end live, uneven gaps
           "all": np.arange(n)}[kind]
    src = rng.standard_normal((1, 3, len(idx)))
    w = rng.random((1, len(idx)))
    g = rng.random((3, n))
    want = np.zeros((1, 3, n))
    want[:, :, idx] = w * src
    with reusing():
        for spread, scale in ((lambda: fused.put(src, idx, n, w, dtype), 1.0),
                              (lambda: fused.put_smoothed(src, idx, n, w, g[:, idx], 0.5, dtype), 0.5 * g)):
            dirty = aligned_empty((1, 3, n), dtype)
            dirty.fill(np.nan)
            where = dirty.ctypes.data
            del dirty
            got = spread()
            assert got.ctypes.data == where  # the used memory itself
            assert np.allclose(got, scale * want, rtol=1e-6, atol=0)
            del got


@pytest.mark.parametrize("periodic", [True, False])
def test_the_first_levels_product_of_one_case_on_the_device_is_the_galerkin_product(periodic):
    # oracle: the dense P^T F A F P of the NumPy operator; one case by the level's per-element kernel, a block by
    # its child patterns' kernel: both that product within float32's rounding, and no fine product
    from implicit_scaffold import opencl
    from implicit_scaffold.measure import mechanics_cl as mc

    rng = np.random.default_rng(11)
    solid = rng.random((10, 9, 8)) < 0.6
    model = M.voxel_model(solid, 0.1, MAT, periodic=periodic)
    free = np.repeat(model.active[None], 3, axis=0)
    if not periodic:
        free[2, :: 5] = False
    A = _dense(lambda u: M.apply_stiffness(model, u), model.shape)
    F = free.ravel().astype(float)
    cshape = G.coarse_shape(model.shape)
    P = _dense(lambda y: G.prolong(y, model.shape), cshape)
    expect = P.T @ (F[:, None] * A * F[None, :]) @ P
    nc = int(np.prod(cshape))
    for check in opencl.working_devices():
        with opencl.using(check):
            op = mc.StiffnessOperator(model)
            mg = G.Multigrid(model, op.single(), free.astype(np.float32), dtype=np.float32)
            level = mg.levels[0]
            assert isinstance(level.device, mc.PatternLevelOperator), check.name
            calls = []
            fine = mg.op
            mg.op = lambda u: calls.append(u.shape) or fine(u)
            for cases in (1, 2):
                x = rng.standard_normal((cases, 3, nc))
                ref = (x.reshape(cases, -1) @ expect.T).reshape(cases, 3, nc)
                got = level.apply(x.astype(np.float32))
                assert got.shape == ref.shape and got.dtype == np.float32
                assert np.abs(got - ref).max() <= 2e-6 * np.abs(ref).max(), (check.name, cases)
            assert calls == []  # the level's own products


def test_the_coarsest_solve_is_the_pseudo_inverse_whatever_blas_threads_the_caller_allows():
    # the coarsest level's pseudo-inverse, against NumPy's own of the dense level, and bit for bit the
    # same when the caller allows BLAS one thread or two (a thread count must not change a solve's bits)
    from threadpoolctl import threadpool_limits

    rng = np.random.default_rng(7)
    model = M.voxel_model(rng.random((14, 14, 12)) < 0.6, 0.1, MAT, periodic=False)
    free = np.repeat(model.active[None], 3, axis=0).astype(float)
    free[2, :: 11] = 0
    level = G._next_coarse(G._first_coarse(model, free))  # 4 x 4 x 4 nodes: 192 unknowns
    A = level.matrix()
    live = np.flatnonzero(level.inv_diag.ravel() > 0)
    runs = []
    for threads in (1, 2):
        with threadpool_limits(threads, user_api="blas"):
            runs.append(G.Multigrid._exact(level))
    assert np.array_equal(runs[0][0], live) and np.array_equal(runs[0][1], runs[1][1])
    sub = A[np.ix_(live, live)]
    expect = np.linalg.pinv(0.5 * (sub + sub.T), rcond=1e-10, hermitian=True)
    assert np.abs(runs[0][1] - expect).max() < 1e-8 * np.abs(expect).max()
