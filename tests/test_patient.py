import numpy as np
import pytest

from implicit_scaffold.grid import Grid, evaluate_by_slabs
from implicit_scaffold.patient import Box


@pytest.mark.parametrize("size, spacing, origin", [((10, 10, 10), 0.25, (-0.5, -0.5, -0.5)),
                                                   ((7, 3.3, 12.1), 0.37, (-1.3, -0.11, 0.2))])
def test_the_boxs_grid_is_the_distance_to_a_box(size, spacing, origin):
    box = Box(size)
    grid = Grid(origin=origin, spacing=spacing, shape=tuple(int(s / spacing) + 6 for s in size))
    got = box.sdf_grid(grid)
    # the oracle: outside, the distance to the nearest point of the box (the point clipped to
    # it); inside, minus the distance to the nearest face
    p = grid.points()
    hi = np.asarray(size, float)
    outside = np.linalg.norm(p - np.clip(p, 0, hi), axis=1)
    inside = np.minimum(p, hi - p).min(axis=1)
    want = np.where(outside > 0, outside, -inside).reshape(grid.shape)
    assert (want < 0).any() and (want > 0).any()
    np.testing.assert_allclose(got, want, atol=1e-5)
    # the compiled pass gives the bits of the broadcast formula, and any planes alone
    ref = evaluate_by_slabs(grid, box.sdf_axes, max_voxels=10_000)
    assert np.array_equal(got.view(np.uint32), ref.view(np.uint32))
    assert np.array_equal(box.sdf_grid(grid, x_range=(3, 9)).view(np.uint32), ref[3:9].view(np.uint32))
