import numpy as np
import pytest

from implicit_scaffold.run.grid import Grid, evaluate_by_slabs
from implicit_scaffold.fields.patient import Box


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


def test_a_cut_patient_takes_the_maximum_with_its_half_spaces_bit_for_bit():
    # the compiled pass against the NumPy expression it replaces: cut_sdf_axes on broadcast axes,
    # rounded to float32, then the maximum with the base's distance
    from implicit_scaffold.run.grid import evaluate_by_slabs
    from implicit_scaffold.fields.patient import CutPatient, Sphere

    rng = np.random.default_rng(3)
    normals = rng.normal(size=(4, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    normals[0] = (0, 0, 1)  # an osteotomy plane along z, as --cut-planes gives
    hs = np.column_stack([normals, rng.uniform(0.5, 2.0, 4)])
    cut = CutPatient(Sphere(4.0), hs)
    grid = Grid((0.013, -0.21, 0.37), 0.071, (37, 29, 41))
    got = cut.sdf_grid(grid)
    base = Sphere(4.0).sdf_grid(grid)
    want = np.maximum(base, evaluate_by_slabs(grid, cut.cut_sdf_axes, max_voxels=5000))
    assert got.dtype == np.float32 and got.tobytes() == want.tobytes()
    assert np.count_nonzero(base < want) > 1000  # the half-spaces cut something
    for x0, x1 in ((0, 7), (7, 30), (30, 37)):
        assert cut.sdf_grid(grid, x_range=(x0, x1)).tobytes() == got[x0:x1].tobytes()
