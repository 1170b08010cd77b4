import numpy as np
import pytest

from implicit_scaffold.errors import ScaffoldError
from implicit_scaffold.geometry.seeds import seed_count, uniform_seeds


def test_paper_seed_counts():
    # the paper, §3: a 10 mm cube at P = 80 %: Dp = 5 mm -> 12 seeds, Dp = 0.5 mm -> 12,223
    assert seed_count(1000.0, 0.8, 5.0) == 12
    assert seed_count(1000.0, 0.8, 0.5) == 12223


def test_seeds_reproducible_and_inside():
    a = uniform_seeds([0, 0, 0], [10, 5, 2], 1000, np.random.default_rng(3))
    b = uniform_seeds([0, 0, 0], [10, 5, 2], 1000, np.random.default_rng(3))
    c = uniform_seeds([0, 0, 0], [10, 5, 2], 1000, np.random.default_rng(4))
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert np.all(a >= 0) and np.all(a <= [10, 5, 2])


@pytest.mark.parametrize("args", [(1000.0, 0.8, 0.0), (1000.0, 1.2, 0.5), (1000.0, 0.8, -1.0)])
def test_bad_seed_count_inputs(args):
    with pytest.raises(ScaffoldError):
        seed_count(*args)


def test_seeds_in_a_patient_the_grid_does_not_see_stop():
    """A patient no grid point lies in (thinner than a step) gets the seeds asked for in its margin."""
    from implicit_scaffold.run.grid import Grid
    from implicit_scaffold.geometry.seeds import seeds_in_patient

    grid = Grid.covering(np.zeros(3), np.full(3, 10.0), 1.0)
    sdf = np.full(grid.shape, 0.3, np.float32)   # 0.3 mm from a surface everywhere, inside nowhere
    seeds = seeds_in_patient(sdf, grid, np.zeros(3), np.full(3, 10.0), 50, np.random.default_rng(1), margin=0.5)
    assert len(seeds) == 50
