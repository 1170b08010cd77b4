import re
import numpy as np
import pytest

from implicit_scaffold.geometry.cells import voronoi_cells
from implicit_scaffold.errors import ScaffoldError


def test_cells_tile_the_box(cube_cells):
    # voro++ volumes and our own pyramid volumes both sum to the box: 1e-9 relative
    assert cube_cells.volumes.sum() == pytest.approx(1000.0, rel=1e-9)
    assert np.all(cube_cells.volumes > 0)


def test_shared_faces_are_identical(cube_cells):
    c = cube_cells
    owner = {(int(o), int(n)): f for f, (o, n) in enumerate(zip(c.face_cell, c.face_neighbor)) if n >= 0}
    checked = 0
    for (o, n), f in owner.items():
        g = owner.get((n, o))
        if g is None:
            continue
        a, b = c.face(f), c.face(g)
        # same polygon, opposite winding (each is outward for its own cell)
        assert np.array_equal(a, b[::-1])
        np.testing.assert_allclose(c.face_normals[f], -c.face_normals[g], atol=1e-12)
        checked += 1
    assert checked > 0.95 * sum(1 for n in c.face_neighbor if n >= 0)


def test_regular_seeds_give_cubes():
    # seeds at the centres of a 4 x 4 x 4 lattice of 2.5 mm cubes
    g = (np.arange(4) + 0.5) * 2.5
    seeds = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    cells = voronoi_cells(seeds, [0, 0, 0], [10, 10, 10])
    assert np.all(cells.faces_per_cell(walls=True) == 6)
    np.testing.assert_allclose(cells.volumes, 2.5 ** 3, rtol=1e-6)
    np.testing.assert_allclose(cells.centroids, seeds, atol=1e-6)
    np.testing.assert_allclose(cells.face_areas, 2.5 ** 2, rtol=1e-6)


def test_poisson_voronoi_mean_faces(cube_cells):
    # far from walls, mean faces per cell of a Poisson-Voronoi tessellation is 2 + 48 pi^2 / 35;
    # 500 cells give only a rough estimate (the 20,000-seed check lives in test_metrics)
    inner = cube_cells.interior_cells(2.0)
    assert abs(cube_cells.faces_per_cell()[inner].mean() - (2 + 48 * np.pi ** 2 / 35)) < 0.6


def test_too_few_seeds():
    with pytest.raises(ScaffoldError, match="at least 2 seeds"):
        voronoi_cells(np.zeros((1, 3)), [0, 0, 0], [1, 1, 1])


def test_too_many_seeds_for_memory_fail_before_the_work():
    from implicit_scaffold.geometry.cells import (BYTES_PER_SEED, CELLS_BYTES_PER_SEED, CELLS_PEAK_BYTES_PER_SEED, CHUNK_SEEDS,
                                         check_seed_memory)

    # 2 M seeds on a machine with 8 GiB free: refused, with a pore size that would fit
    with pytest.raises(ScaffoldError, match=r"2,000,000 seeds need about .* GiB .* --pore-size \(e\.g\. "):
        check_seed_memory(2_000_000, pore_size=0.6, available=8 * 2**30)
    with pytest.raises(ScaffoldError, match="fewer --seeds"):
        check_seed_memory(2_000_000, available=8 * 2**30)
    # the count it suggests fits, chunked (seeds in a box) or not (seeds in a patient)
    for chunked in (True, False):
        with pytest.raises(ScaffoldError, match=r"at most ([\d,]+)\)") as exc:
            check_seed_memory(2_000_000, available=2**30, chunked=chunked)
        most = int(re.search(r"at most ([\d,]+)\)", str(exc.value)).group(1).replace(",", ""))
        assert check_seed_memory(most, available=2**30, chunked=chunked) <= 2**30
        with pytest.raises(ScaffoldError):
            check_seed_memory(most + 1, available=2**30, chunked=chunked)
    # the pore size it suggests holds the seeds counted at it, by the count's own law (a thin
    # patient's margin: here pore**-2), with a tenth of the memory spare; 2 % smaller does not
    law = lambda pore: 3_000_000 * (0.6 / pore) ** 2  # noqa: E731
    with pytest.raises(ScaffoldError, match=r"--pore-size \(e\.g\. ([0-9.]+) mm\)") as exc:
        check_seed_memory(3_000_000, pore_size=0.6, available=2**30, count_at=law)
    pore = float(re.search(r"--pore-size \(e\.g\. ([0-9.]+) mm\)", str(exc.value)).group(1))
    assert check_seed_memory(int(np.ceil(law(pore))), available=2**30) <= 2**30
    with pytest.raises(ScaffoldError):
        check_seed_memory(int(np.ceil(law(0.98 * pore))), available=int(0.9 * 2**30))
    # a graded run's count is not the user's: it is told what budget would do
    with pytest.raises(ScaffoldError, match=r"pass --max-memory \S+ or more, or use larger pores"):
        check_seed_memory(100_000, available=2**30, chunked=False, seeds_given=False)
    assert check_seed_memory(1000, available=8 * 2**30) == 1000 * (BYTES_PER_SEED + CELLS_BYTES_PER_SEED)
    # beyond a chunk, voro++'s peak stays that of two chunks, and the arrays' copies then take
    # CELLS_PEAK_BYTES_PER_SEED: 8 M seeds fit in 64 GiB
    assert check_seed_memory(8 * 10**6, available=64 * 2**30) == max(
        8 * 10**6 * CELLS_PEAK_BYTES_PER_SEED, 8 * 10**6 * CELLS_BYTES_PER_SEED + 2 * CHUNK_SEEDS * BYTES_PER_SEED)


# --- power (Laguerre) cells ----------------------------------------------------------

def _power_labels(points, seeds, radii, chunk=50_000):
    """Brute force: the seed minimising |x - s_i|^2 - r_i^2 for each point."""
    out = np.empty(len(points), np.int64)
    for i in range(0, len(points), chunk):
        x = points[i:i + chunk]
        out[i:i + chunk] = np.argmin(((x[:, None, :] - seeds[None]) ** 2).sum(-1) - radii ** 2, axis=1)
    return out


def _face_areas_by_pair(c):
    return {(int(o), int(n)): a for o, n, a in zip(c.face_cell, c.face_neighbor, c.face_areas) if n >= 0}


def test_equal_radii_give_the_voronoi_cells():
    # equal weights cancel in every power plane: the same tessellation, to rounding
    rng = np.random.default_rng(11)
    hi = np.array([4.0, 3.0, 3.5])
    seeds = rng.uniform(0, 1, (150, 3)) * hi
    plain = voronoi_cells(seeds, [0, 0, 0], hi)
    power = voronoi_cells(seeds, [0, 0, 0], hi, radii=np.full(150, 0.7))
    assert plain.radii is None and plain.seed_index is None
    assert power.n == 150 and np.array_equal(power.seed_index, np.arange(150))
    np.testing.assert_allclose(power.volumes, plain.volumes, rtol=0, atol=1e-9)
    np.testing.assert_allclose(power.centroids, plain.centroids, rtol=0, atol=1e-9)
    a, b = _face_areas_by_pair(plain), _face_areas_by_pair(power)
    # faces of (near) zero area may come and go with rounding; every other face is in both
    big = {k for k, v in a.items() if v > 1e-9} | {k for k, v in b.items() if v > 1e-9}
    for k in big:
        assert abs(a.get(k, 0.0) - b.get(k, 0.0)) < 1e-9


def test_power_cells_match_a_brute_force_assignment():
    rng = np.random.default_rng(7)
    hi = np.array([3.0, 2.5, 2.0])
    box = float(np.prod(hi))
    seeds = rng.uniform(0, 1, (40, 3)) * hi
    radii = rng.uniform(0, 0.45, 40)
    cells = voronoi_cells(seeds, [0, 0, 0], hi, radii=radii)
    # the power cells tile the box
    assert cells.volumes.sum() == pytest.approx(box, rel=1e-9)
    npts = 400_000
    x = np.random.default_rng(1).uniform(0, 1, (npts, 3)) * hi
    label = _power_labels(x, seeds, radii)
    # the case the vertex mean is for: some seeds lie outside their own power cell
    assert np.count_nonzero(_power_labels(seeds, seeds, radii) != np.arange(40)) >= 1
    count = np.bincount(label, minlength=40)
    assert set(np.nonzero(count)[0]) <= set(cells.seed_index.tolist())
    np.testing.assert_array_equal(cells.seeds, seeds[cells.seed_index])
    np.testing.assert_array_equal(cells.radii, radii[cells.seed_index])
    est = count[cells.seed_index] / npts * box
    # binomial counts: each estimate within 5 standard errors, big cells within 3 %
    p = cells.volumes / box
    assert np.all(np.abs(est - cells.volumes) <= 5 * box * np.sqrt(p * (1 - p) / npts))
    big = cells.volumes > 0.1
    assert big.sum() > 20
    assert np.all(np.abs(est[big] / cells.volumes[big] - 1) < 0.03)
    # centroids from the pyramids agree with the points' means (within 0.03 mm for >= 2000 points)
    mean = np.stack([np.bincount(label, weights=x[:, a], minlength=40) for a in range(3)], 1)
    mean = mean[cells.seed_index] / np.maximum(count[cells.seed_index], 1)[:, None]
    many = count[cells.seed_index] >= 2000
    assert np.all(np.linalg.norm(mean[many] - cells.centroids[many], axis=1) < 0.03)
    # every face is oriented outward from its (convex) cell
    out = np.einsum("ij,ij->i", cells.face_normals, cells.face_centroids - cells.centroids[cells.face_cell])
    assert np.all(out > 0)


def test_empty_power_cells_are_dropped():
    # seed 0 sits 0.5 mm from seed 1, whose radius 3 mm outshines it everywhere in the box
    # (the radical plane |x - s0|^2 = |x - s1|^2 - 9 lies at z = 14.25 mm)
    seeds = np.array([[5.0, 5.0, 5.0], [5.0, 5.0, 5.5], [2.0, 2.0, 2.0], [8.0, 7.0, 2.5]])
    radii = np.array([0.0, 3.0, 3.0, 2.0])
    cells = voronoi_cells(seeds, [0, 0, 0], [10, 10, 10], radii=radii)
    x = np.random.default_rng(2).uniform(0, 10, (100_000, 3))
    assert not np.any(_power_labels(x, seeds, radii) == 0)
    assert cells.n == 3
    np.testing.assert_array_equal(cells.seed_index, [1, 2, 3])
    np.testing.assert_array_equal(cells.seeds, seeds[1:])
    assert cells.volumes.sum() == pytest.approx(1000.0, rel=1e-9)
    assert set(cells.face_cell.tolist()) == {0, 1, 2}
    assert set(cells.face_neighbor.tolist()) <= {-1, 0, 1, 2}
    assert len(cells.centroids) == len(cells.volumes) == 3


@pytest.mark.parametrize("radii, match", [
    (np.ones(3), r"one length per seed: got shape \(3,\) for 4 seeds"),
    (np.array([0.1, -0.2, 0.1, 0.1]), "power radius -0.2 of seed 1 is not a finite length >= 0 mm"),
    (np.array([0.1, 0.1, np.nan, 0.1]), "power radius nan of seed 2"),
    (np.array([0.1, 0.1, 0.1, np.inf]), "power radius inf of seed 3"),
    (["a", "b", "c", "d"], "power radii must be numbers"),
])
def test_bad_radii(radii, match):
    seeds = np.random.default_rng(0).uniform(0, 1, (4, 3))
    with pytest.raises(ScaffoldError, match=match) as err:
        voronoi_cells(seeds, [0, 0, 0], [1, 1, 1], radii=radii)
    assert "\n" not in str(err.value)


def _faces(c):
    """Every face of `c` in an order that does not depend on voro++'s: by cell, neighbour and
    (for a cell's several box-wall faces) normal; with its vertex count, area and centroid."""
    k = np.lexsort((*np.round(c.face_normals, 6).T[::-1], c.face_neighbor, c.face_cell))
    return c.face_cell[k], c.face_neighbor[k], np.diff(c.face_start)[k], c.face_areas[k], c.face_centroids[k]


def _same_cells(chunked, once, tol):
    """The same cells up to rounding: every face, neighbour and vertex count; volumes, areas and
    centroids within `tol` (mm³, mm², mm)."""
    assert chunked.n == once.n
    np.testing.assert_allclose(chunked.volumes, once.volumes, rtol=0, atol=tol)
    np.testing.assert_allclose(chunked.centroids, once.centroids, rtol=0, atol=tol)
    a, b = _faces(once), _faces(chunked)
    for x, y in zip(a[:3], b[:3]):
        np.testing.assert_array_equal(x, y)
    for x, y in zip(a[3:], b[3:]):
        np.testing.assert_allclose(x, y, rtol=0, atol=tol)


@pytest.mark.parametrize("weighted", [False, True])
def test_cells_built_in_chunks_are_the_cells_built_at_once(monkeypatch, weighted):
    """Beyond CHUNK_SEEDS the cells are built in chunks along x, each with the seeds within a
    margin; cells that a seed beyond it may cut are built again with the seeds that cut them:
    the same cells as one voro++ run (faces, neighbours, volumes, areas and centroids), here
    with a sparse end whose big cells are cut from beyond their chunk's margin."""
    import implicit_scaffold.geometry.cells as C

    rng = np.random.default_rng(7)
    seeds = np.concatenate([rng.uniform(0, 1, (900, 3)) * [3, 3, 3],
                            rng.uniform(0, 1, (4, 3)) * [3, 3, 3] + [3, 0, 0]])
    radii = rng.uniform(0.05, 0.1, len(seeds)) if weighted else None
    once = C.voronoi_cells(seeds, [0, 0, 0], [6, 3, 3], radii=radii)
    loose = []
    real = C._loose_cells
    monkeypatch.setattr(C, "_loose_cells", lambda *a: loose.append(real(*a)) or loose[-1])
    monkeypatch.setattr(C, "CHUNK_SEEDS", 150)
    chunked = C.voronoi_cells(seeds, [0, 0, 0], [6, 3, 3], radii=radii)
    assert len(loose) >= -(-len(seeds) // 150) and any(loose)  # 7 chunks, and some cells cut from beyond
    # volumes of about 0.05 mm³ (up to 10 near the sparse end) summed from faces: a few ulps
    _same_cells(chunked, once, 1e-12)
    np.testing.assert_allclose(chunked.volumes.sum(), 6 * 3 * 3, rtol=1e-12)


def test_polygon_properties_in_chunks_are_bit_for_bit_the_same(monkeypatch, small_cells):
    import implicit_scaffold.geometry.cells as C

    c = small_cells
    whole = C.polygon_properties(c.face_vertices, c.face_start)
    monkeypatch.setattr(C, "_PROPERTY_CHUNK", 37)
    chunked = C.polygon_properties(c.face_vertices, c.face_start)
    for a, b in zip(whole, chunked):
        np.testing.assert_array_equal(a, b)
    # and the areas are the polygons' own: a brute-force fan per face
    f = 5
    v = c.face_vertices[c.face_start[f]:c.face_start[f + 1]]
    fan = sum(np.linalg.norm(np.cross(v[i] - v[0], v[i + 1] - v[0])) / 2 for i in range(1, len(v) - 1))
    assert whole[1][f] == pytest.approx(fan, rel=1e-12)


def test_cells_of_seeds_drawn_in_a_patient_are_built_in_chunks_as_at_once(monkeypatch):
    """Seeds in a ball within a large box, as seeds drawn in a patient: the outer cells reach the
    walls, cut by seeds all around the ball, so no chunk settles them whatever its margin. They
    are built again with the seeds that cut them: the cells of one voro++ run over every seed, with
    voro++ never given more than two chunks' seeds; and the same seeds give the same bytes again."""
    import pyvoro2

    import implicit_scaffold.geometry.cells as C

    rng = np.random.default_rng(2)
    p = rng.normal(size=(2000, 3))
    seeds = 5 + 1.5 * p / np.linalg.norm(p, axis=1, keepdims=True) * rng.uniform(0, 1, (2000, 1)) ** (1 / 3)
    once = C.voronoi_cells(seeds, [0, 0, 0], [10, 10, 10], chunked=False)
    monkeypatch.setattr(C, "CHUNK_SEEDS", 100)
    sizes, settled = [], []
    real, settle = pyvoro2.compute, C._settle
    monkeypatch.setattr(pyvoro2, "compute", lambda points, **kw: sizes.append(len(points)) or real(points, **kw))
    monkeypatch.setattr(C, "_settle", lambda loose, *a: settled.append(len(loose)) or settle(loose, *a))
    chunked = C.voronoi_cells(seeds, [0, 0, 0], [10, 10, 10])
    assert sum(settled) > 100 and max(sizes) <= 2 * 100
    # coordinates of about 5 mm, cells of up to 100 mm³ reaching the walls: a few ulps
    _same_cells(chunked, once, 1e-12)
    again = C.voronoi_cells(seeds, [0, 0, 0], [10, 10, 10])
    for name in ("volumes", "centroids", "face_cell", "face_neighbor", "face_start", "face_vertices"):
        assert getattr(again, name).tobytes() == getattr(chunked, name).tobytes(), name
