import numpy as np
import pytest

from implicit_scaffold.cells import voronoi_cells
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
    from implicit_scaffold.cells import BYTES_PER_SEED, check_seed_memory

    # 2 M seeds on a machine with 8 GiB free: refused, with a pore size that would fit
    with pytest.raises(ScaffoldError, match=r"2,000,000 seeds need about .* GiB .* --pore-size \(e\.g\. "):
        check_seed_memory(2_000_000, pore_size=0.6, available=8 * 2**30)
    with pytest.raises(ScaffoldError, match="fewer --seeds"):
        check_seed_memory(2_000_000, available=8 * 2**30)
    assert check_seed_memory(1000, available=8 * 2**30) == 1000 * BYTES_PER_SEED
