"""The compiled steps of a volume patient's signed distance against independent oracles.

Oracles: brute-force nearest voxels in NumPy (every pair of voxels), the analytic distance
of a ball and of a plane, the volume a plane cuts from a box, SciPy's cubic spline, and the
NumPy/SciPy path the kernels replaced (``reference=True``, itself checked against analytic
shapes in ``test_patient_volume.py``).
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import ndimage

from implicit_scaffold.fields import patient_volume as pv
from implicit_scaffold.fields import volume_kernels as vk


def _centres(shape):
    return np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), axis=-1).reshape(-1, 3)


@pytest.mark.parametrize("spacing", [(1.0, 1.0, 1.0), (0.5, 0.7, 0.3)])
def test_feature_transform_finds_a_nearest_feature(spacing):
    """Odd sizes, isotropic (many ties) and anisotropic voxels: the voxel found is a feature
    and no feature is nearer (brute force over every feature)."""
    rng = np.random.default_rng(4)
    shape = (13, 9, 11)
    features = rng.random(shape) < 0.04
    fi, fj, fk = vk.feature_transform(features, spacing)
    h = np.asarray(spacing)
    p = _centres(shape) * h
    f = np.argwhere(features) * h
    brute = np.sqrt(((p[:, None, :] - f[None, :, :]) ** 2).sum(axis=2)).min(axis=1)
    found = np.stack([fi.ravel(), fj.ravel(), fk.ravel()], axis=1)
    assert features[tuple(found.T)].all()
    np.testing.assert_allclose(np.linalg.norm(found * h - p, axis=1), brute, rtol=0, atol=1e-12)


def test_signed_box_distance_takes_the_box_of_a_nearest_voxel():
    """Outside, the distance to the box of one of the nearest mask voxels (which one, among
    equally near ones, is not fixed); inside, minus that to the nearest outside voxel's box."""
    rng = np.random.default_rng(5)
    shape, h = (12, 10, 9), np.array([0.4, 0.5, 0.3])
    mask = rng.random(shape) < 0.3
    got = pv._signed_box_distance(mask, h)
    for sign, feats, where in ((1, mask, ~mask), (-1, ~mask, mask)):
        f = np.argwhere(feats)
        for idx in np.argwhere(where)[::3]:
            d = np.sqrt((((f - idx) * h) ** 2).sum(axis=1))
            near = f[d <= d.min() + 1e-9]
            gap = np.maximum(np.abs(near - idx) * h - h / 2, 0)
            boxes = np.sqrt((gap ** 2).sum(axis=1))
            assert np.min(np.abs(sign * boxes - got[tuple(idx)])) < 1e-5
    assert np.all(got[mask] < 0) and np.all(got[~mask] > 0)


def test_band_is_scipys():
    """The compiled band is scipy.ndimage's morphology (face neighbours, the border as in
    ``_band``) on a random mask with voxels on the array's faces."""
    rng = np.random.default_rng(9)
    inside = rng.random((15, 12, 17)) < 0.5
    got = np.empty(inside.shape, bool)
    vk.band(inside, got)
    _, ref = pv._band(np.where(inside, -1.0, 1.0))
    np.testing.assert_array_equal(got, ref)


@pytest.mark.parametrize("sigma", [1.5, 0.75])
def test_unbiased_gaussian_is_scipys(sigma):
    """The compiled passes give scipy.ndimage's Gaussian minus sigma²/2 times its Laplacian
    (``_unbiased_gaussian_reference``, 12 filters), on a random field of odd sizes, one axis
    shorter than the kernel's radius (the "nearest" border on both sides at once)."""
    rng = np.random.default_rng(12)
    field = rng.normal(size=(19, 5, 23)).astype(np.float32)
    got = pv._unbiased_gaussian(field, sigma)
    ref = pv._unbiased_gaussian_reference(field, sigma)
    np.testing.assert_allclose(got, ref, rtol=0, atol=2e-6 * np.abs(ref).max())


def test_tube_clip_is_numpys():
    """The compiled bounds and clip equal the NumPy formula (numpy.gradient's differences,
    one-sided on the faces) on a smoothed random box distance with anisotropic voxels."""
    rng = np.random.default_rng(13)
    h = np.array([0.5, 0.7, 0.3])
    mask = rng.random((14, 11, 16)) < 0.4
    box = pv._signed_box_distance(mask, h)
    field = pv._unbiased_gaussian_reference(box, 1.5)
    for got, ref in zip(pv._tube_clip(field, box, mask, h), pv._tube_clip_reference(field, box, mask, h)):
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-5)
    lower, upper, _ = pv._tube_clip(field, box, mask, h)
    assert np.all(upper[mask] <= -pv.KEEP_VOXELS * h.min() + 1e-7)
    assert np.all(lower[~mask] >= pv.KEEP_VOXELS * h.min() - 1e-7)


def test_spline_coefficients_are_scipys():
    """The compiled prefilter is scipy.ndimage.spline_filter(order=3, mode="nearest") in
    float32, on odd sizes of 12 samples or more along each axis (a crop has at least 17: the
    two margins; on shorter lines the border's start value differs by O(z^2n))."""
    from scipy import ndimage

    field = np.random.default_rng(14).normal(size=(13, 17, 12)).astype(np.float32)
    ref = ndimage.spline_filter(field, order=3, output=np.float32, mode="nearest")
    np.testing.assert_allclose(vk.spline_coefficients(field), ref, rtol=0, atol=1e-5)


def test_spline_value_and_gradient_match_scipy():
    """The kernel's cubic spline is scipy's (order 3, "nearest", prefilter off) and its
    gradient the derivative of that spline (central differences of 1e-4 voxel in float64)."""
    from scipy import ndimage

    rng = np.random.default_rng(6)
    coef = ndimage.spline_filter(rng.random((11, 12, 13)), order=3, mode="nearest").astype(np.float32)
    c64 = coef.astype(np.float64)
    x = rng.random((200, 3)) * (np.array(coef.shape) + 1) - 1      # some stencils leave the grid
    got = np.empty(len(x))
    grad = np.empty((len(x), 3))
    for n, p in enumerate(x):
        got[n] = vk.spline(coef, p[0], p[1], p[2])
        value, *g = vk.spline_gradient(coef, p[0], p[1], p[2])
        assert value == pytest.approx(got[n], abs=1e-12)
        grad[n] = g
    ref = ndimage.map_coordinates(c64, x.T, order=3, mode="nearest", prefilter=False)
    np.testing.assert_allclose(got, ref, atol=1e-9)
    e = 1e-4
    num = np.stack([(ndimage.map_coordinates(c64, (x + e * np.eye(3)[a]).T, order=3, mode="nearest", prefilter=False)
                     - ndimage.map_coordinates(c64, (x - e * np.eye(3)[a]).T, order=3, mode="nearest",
                                               prefilter=False)) / (2 * e) for a in range(3)], axis=1)
    inner = np.all((x >= 1) & (x <= np.array(coef.shape) - 3), axis=1)   # away from the clamped border
    np.testing.assert_allclose(grad[inner], num[inner], atol=1e-6)


def _ball(shape, centre, radius, h):
    p = _centres(shape).reshape(shape + (3,)) * h
    return (np.linalg.norm(p - centre, axis=-1) - radius).astype(np.float32)


def test_redistance_of_a_ball_is_its_distance():
    """A ball's field scaled by 3 (not a distance) redistanced: the ball's distance, to the
    cubic spline's error near the surface and to the band's discretisation farther out."""
    h = np.array([0.5, 0.4, 0.6])
    shape = (41, 47, 37)
    centre, radius = np.array([10.1, 9.3, 10.9]), 6.3
    exact = _ball(shape, centre, radius, h)
    got = pv._redistance(3 * exact, h)
    _, band = pv._band(exact)
    # in the band: the spline of a distance sampled at 0.4-0.6 mm interpolates a ball of
    # radius 6.3 mm to about h^4/R^3: 1e-3 mm is ample
    assert np.abs(got - exact)[band].max() < 1e-3
    # farther: the distance to the closest point of the nearest band voxel, not to the
    # surface; up to half a voxel off (0.47 of 0.6 mm measured, the same as the reference's)
    assert np.abs(got - exact).max() < 0.5 * h.max()
    assert np.all((got < 0) == (exact < 0))


def test_redistance_agrees_with_its_reference():
    """The compiled redistance and the NumPy one on an irregular field: the same closest
    points in the band; farther out, equally near band voxels may differ in whose closest
    point they lend."""
    from scipy import ndimage

    rng = np.random.default_rng(8)
    h = np.array([0.3, 0.35, 0.25])
    blobs = ndimage.gaussian_filter(rng.random((30, 28, 33)), 2.5)
    field = ((blobs - np.median(blobs)) * 40).astype(np.float32)
    fast = pv._redistance(field, h)
    ref = pv._redistance_reference(field, h)
    inside, band = pv._band(field)
    # the reference's gradient is central differences of 0.05 voxel, this one the spline's own:
    # the chord steps after the second end on the surface a little apart (3.4e-4 mm measured
    # where the blobs curve most, 2e-5 mm on a vertebra at 0.5 mm)
    assert np.abs(fast - ref)[band].max() < 1e-3
    assert np.all((fast < 0) == (ref < 0))
    assert np.median(np.abs(fast - ref)[~band]) < 1e-4


#: (shift, image shape): the crop in the middle of an image so big that its box cuts nothing
NO_IMAGE_BOX = (np.full(3, (1e9 - 1) / 2), np.full(3, 1e9))


def test_level_volume_of_a_plane_is_exact():
    """A linear field is its own trilinear interpolant: the volume below a tilted plane in
    the grid's box is the box's volume times the mean depth (the plane stays inside it)."""
    h = np.array([0.5, 0.4, 0.6])
    shape = (20, 24, 18)
    n = np.array([0.3, -0.2, 0.9]) / np.linalg.norm([0.3, -0.2, 0.9])
    p = _centres(shape).reshape(shape + (3,)) * h
    mid = (np.array(shape) - 1) * h / 2
    field = ((p - mid) @ n).astype(np.float64)
    got, der = vk.level_volume(field, 0.0, *NO_IMAGE_BOX, h, 4)
    lx, ly, lz = (np.array(shape) - 1) * h
    # the plane through the box's centre halves it, whatever its tilt (symmetry)
    assert got * np.prod(h) == pytest.approx(lx * ly * lz / 2, rel=1e-9)
    # d volume / d level: the plane's area in the box (its tilt keeps it off the x and y faces)
    assert der * np.prod(h) == pytest.approx(lx * ly / abs(n[2]), rel=1e-6)


def test_level_volume_of_a_ball_and_of_slabs():
    """A ball's distance: within the trilinear interpolant's error of 4/3 pi r^3; slabs across
    each axis: their volume to 1e-9."""
    h = np.array([0.25, 0.25, 0.25])
    shape = (61, 61, 61)
    centre, radius = np.array([7.53, 7.41, 7.62]), 5.0
    field = _ball(shape, centre, radius, h).astype(np.float64)
    got, _ = vk.level_volume(field, 0.0, *NO_IMAGE_BOX, h, 4)
    # trilinear interpolation raises a distance by up to h^2/8 x its Laplacian (2/r): the area
    # times h^2 / (4 r) bounds the volume lost
    sag = 4 * math.pi * radius ** 2 * h[0] ** 2 / (4 * radius)
    assert abs(got * np.prod(h) - 4 / 3 * math.pi * radius ** 3) < sag
    # slabs across each axis, faces between the lattice planes: flat faces parallel to two
    # of the column directions (the case columns along a fixed axis get wrong), exact
    p = _centres(shape).reshape(shape + (3,)) * h
    extent = (np.array(shape) - 1) * h
    for axis in range(3):
        slab = (np.abs(p[..., axis] - 7.37) - 2.61).astype(np.float64)
        got, _ = vk.level_volume(slab, 0.0, *NO_IMAGE_BOX, h, 4)
        assert got * np.prod(h) == pytest.approx(2 * 2.61 * np.prod(extent) / extent[axis], rel=1e-9)


def test_fast_load_agrees_with_the_reference(tmp_path):
    """The same bone file through both paths: the volume fits the mask's to their tolerances,
    the bounds and the surface agree to a small share of a voxel."""
    sitk = pytest.importorskip("SimpleITK")
    from implicit_scaffold.run.grid import Grid

    h = np.array([0.5, 0.6, 0.4])
    shape = (40, 36, 44)
    p = _centres(shape).reshape(shape + (3,)) * h
    # two balls joined by a rod: convex and concave parts, and a thin part
    a, b = np.array([6.0, 10.0, 8.5]), np.array([14.0, 10.5, 9.5])
    mask = (np.linalg.norm(p - a, axis=-1) < 4.0) | (np.linalg.norm(p - b, axis=-1) < 3.2) \
        | ((np.abs(p[..., 1] - 10.2) < 0.8) & (np.abs(p[..., 2] - 9.0) < 0.8) & (p[..., 0] > a[0]) & (p[..., 0] < b[0]))
    img = sitk.GetImageFromArray(np.ascontiguousarray(mask.astype(np.uint8).T))
    img.SetSpacing(tuple(h))
    sitk.WriteImage(img, str(tmp_path / "bone.nrrd"))
    fast = pv.load_volume(tmp_path / "bone.nrrd")
    ref = pv.load_volume(tmp_path / "bone.nrrd", reference=True)
    target = mask.sum() * np.prod(h)
    assert fast.volume == pytest.approx(target, rel=pv.VOLUME_TOLERANCE)
    assert ref.volume == pytest.approx(target, rel=1e-4)
    # two volume measures of one surface (column integrals, marching cubes extrapolated):
    # the fitted offsets differ by a small share of a voxel, and so do the bounds
    assert np.abs(fast.lo - ref.lo).max() < 0.02 * h.max()
    assert np.abs(fast.hi - ref.hi).max() < 0.02 * h.max()
    grid = Grid.covering(ref.lo, ref.hi, 0.17, pad=2)
    s_fast, s_ref = fast.sdf_grid(grid), ref.sdf_grid(grid)
    near = np.abs(s_ref) < h.max()
    # near the surface: the box distances of equally near voxels and the volume measure
    # differ; a twentieth of a voxel bounds both
    assert np.abs(s_fast - s_ref)[near].max() < 0.05 * h.max()
    assert np.mean((s_fast < 0) != (s_ref < 0)) < 1e-3


@pytest.mark.parametrize("shape, share", [((13, 9, 11), 0.9), ((1, 17, 5), 0.7), ((21, 2, 19), 0.97),
                                          ((30, 31, 29), 0.999)])
def test_squared_distance_is_scipys(shape, share):
    """Exact integers, SciPy's Euclidean distance transform squared: random phases with long
    runs (a phase that fills whole rows and planes), odd and thin sizes. Beyond the array is
    phase: SciPy sees the array alone, as the kernels do."""
    rng = np.random.default_rng(len(shape) + shape[0])
    phase = rng.random(shape) < share
    phase.flat[rng.integers(phase.size)] = False
    want = np.rint(ndimage.distance_transform_edt(phase) ** 2).astype(np.int64)
    got = vk.squared_distance(phase)
    assert got.dtype == np.int32
    assert np.array_equal(got, want)
    assert want.max() > 3


def test_squared_distance_with_no_voxel_outside_the_phase():
    """No voxel to be near: int32's largest everywhere (SciPy and edt give infinities)."""
    assert (vk.squared_distance(np.ones((4, 3, 5), bool)) == np.iinfo(np.int32).max).all()
    assert (vk.squared_distance(np.zeros((4, 3, 5), bool)) == 0).all()
