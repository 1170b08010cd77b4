import numpy as np
import pytest

from implicit_scaffold.errors import ScaffoldError
from implicit_scaffold.fields.field import blend_field, check_porosity, scaffold_field, solve_level


def test_solve_level_counts_exactly():
    rng = np.random.default_rng(0)
    field = rng.normal(size=(30, 31, 29)).astype(np.float32)
    inside = rng.random(field.shape) < 0.7
    for p in (0.1, 0.5, 0.8, 0.93):
        t = solve_level(field, inside, p)
        solid = np.count_nonzero(field[inside] < t)
        assert solid == round((1 - p) * inside.sum())


@pytest.mark.parametrize("shape", [(23, 19, 17), (61, 47, 43)])
@pytest.mark.parametrize("kind", ["normal", "ties", "tiny", "zeros", "clamped", "sample misled"])
def test_solve_level_is_midway_between_the_sorted_values(kind, shape):
    # the oracle: the two order statistics around the rank, from a full sort (the small grid
    # is below the sampled bracket's size, the large one above it)
    rng = np.random.default_rng(3)
    field = {"normal": lambda: rng.normal(size=shape),
             "ties": lambda: rng.integers(-3, 3, shape) * 0.5,
             "tiny": lambda: rng.normal(size=shape) * 1e-30,
             "zeros": lambda: np.where(rng.random(shape) < 0.5, -0.0, 0.0),
             # most voxels at one value (a lattice clamped at its cut-off), the rest spread
             "clamped": lambda: np.minimum(rng.normal(size=shape), 0.3),
             "sample misled": lambda: rng.normal(size=shape)}[kind]().astype(np.float32)
    if kind == "sample misled":
        # the voxels the sample reads hold values far above the others: its bracket misses
        from implicit_scaffold.run.tiles import SAMPLE_STRIDE

        field.reshape(-1)[::SAMPLE_STRIDE] = 100.0
    inside = rng.random(shape) < 0.7
    values = np.sort(field[inside])
    for p in (0.01, 0.3, 0.8, 0.99):
        k = round((1 - p) * len(values))
        want = float(values[k - 1]) + (float(values[k]) - float(values[k - 1])) / 2
        assert solve_level(field, inside, p) == want


def test_offset_of_a_plane_moves_the_surface():
    # field = x - 5 (solid x < 5); a 0.8 porosity over x in [0, 10) puts the surface at x = 2
    x = np.arange(100) * 0.1 + 0.05
    field = np.broadcast_to((x - 5.0)[:, None, None], (100, 4, 4)).astype(np.float32)
    t = solve_level(field, np.ones(field.shape, bool), 0.8)
    assert t + 5.0 == pytest.approx(2.0, abs=0.06)


def test_blend_keeps_planes_and_rounds_corners():
    h = 0.05
    x = (np.arange(80) - 40) * h
    X, Y = np.meshgrid(x, x, indexing="ij")
    plane = np.repeat((X - 0.3)[:, :, None], 3, axis=2).astype(np.float32)
    # a Gaussian of a linear field is the same linear field (away from the grid edge)
    np.testing.assert_allclose(blend_field(plane, h, 0.3)[20:60, 20:60], plane[20:60, 20:60], atol=1e-5)
    # a convex corner of the solid (x < 0 and y < 0) is rounded: the blended field at the
    # corner is positive (the corner is cut away)
    corner = np.repeat(np.maximum(X, Y)[:, :, None], 3, axis=2).astype(np.float32)
    assert blend_field(corner, h, 0.3)[40, 40, 1] > 0.01
    assert np.array_equal(blend_field(corner, h, 0.0), corner)


def test_scaffold_field_is_the_intersection():
    a = np.array([-1.0, -1.0, 1.0, 0.5], np.float32)
    p = np.array([-2.0, 0.5, -1.0, 2.0], np.float32)
    np.testing.assert_array_equal(scaffold_field(a, p, level=0.0), np.maximum(a, p))
    # skin of 0.3 mm: the patient shell between s_P = -0.3 and 0 is solid
    s = scaffold_field(np.array([1.0, 1.0], np.float32), np.array([-0.1, -0.5], np.float32), skin=0.3)
    assert s[0] < 0 and s[1] > 0


@pytest.mark.parametrize("bad", ["80", 0, 1, -0.2, "x"])
def test_bad_porosity(bad):
    with pytest.raises(ScaffoldError):
        check_porosity(bad)
    assert check_porosity("none") is None and check_porosity(0.7) == 0.7


@pytest.mark.parametrize("shape, h, k", [((23, 19, 31), 0.05, 0.3), ((9, 40, 12), 0.02, 0.07), ((5, 6, 70), 0.1, 0.2)])
def test_blend_field_gives_scipy_gaussian_bits(shape, h, k):
    # the compiled passes against SciPy's gaussian_filter, the oracle, bit for bit (radii past the
    # array's size on the thin axes: the clamped "nearest" ends)
    from implicit_scaffold.fields.field import blend_field_reference

    field = np.random.default_rng(4).normal(size=shape).astype(np.float32)
    got = blend_field(field, h, k)
    assert not np.array_equal(got, field)
    assert got.dtype == np.float32 and got.tobytes() == blend_field_reference(field, h, k).tobytes()
    # a run of planes (a slab's own, its halo read) is those planes of the oracle, at either end too
    want = blend_field_reference(field, h, k)
    for i0, i1 in ((0, 1), (1, shape[0]), (shape[0] // 2, shape[0] // 2 + 1)):
        assert blend_field(field, h, k, planes=(i0, i1)).tobytes() == want[i0:i1].tobytes()
