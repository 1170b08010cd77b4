"""Volume patients (NIfTI, NRRD, MHA, DICOM): position, volume, smoothness and bad input.

Oracles are analytic shapes written voxel by voxel by the tests themselves (a sphere, a
cuboid) through SimpleITK with non-unit spacing, offset origins and rotated directions.
"""
from __future__ import annotations

import math
import re

import numpy as np
import pytest

sitk = pytest.importorskip("SimpleITK")

from implicit_scaffold.errors import ScaffoldError  # noqa: E402
from implicit_scaffold.run.grid import Grid  # noqa: E402
from implicit_scaffold.fields import patient_volume as pv  # noqa: E402
from implicit_scaffold.fields.patient_volume import load_volume  # noqa: E402


def _write(path, array_ijk, spacing, origin, direction=None):
    """Write `array_ijk` (indexed i, j, k) as an image; SimpleITK arrays are (k, j, i)."""
    img = sitk.GetImageFromArray(np.ascontiguousarray(np.asarray(array_ijk).T))
    img.SetSpacing(tuple(float(v) for v in spacing))
    img.SetOrigin(tuple(float(v) for v in origin))
    if direction is not None:
        img.SetDirection(tuple(float(v) for v in np.asarray(direction).ravel()))
    # the oracle's index -> physical map (_physical) is ITK's own
    corner = tuple(int(n - 1) for n in np.shape(array_ijk))
    np.testing.assert_allclose(img.TransformIndexToPhysicalPoint(corner),
                               _physical([2, 2, 2], np.asarray(spacing) * np.asarray(corner), origin,
                                         direction)[1, 1, 1], atol=1e-9)
    sitk.WriteImage(img, str(path))
    return path


def _physical(shape, spacing, origin, direction=None):
    """Physical centres ``(ni, nj, nk, 3)`` mm of every voxel, the way ITK maps indices."""
    d = np.eye(3) if direction is None else np.asarray(direction, float).reshape(3, 3)
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), axis=-1).astype(float)
    return (idx * np.asarray(spacing)) @ d.T + np.asarray(origin)


def _sphere(path, *, radius, centre, spacing, margin=4, direction=None, value=1, dtype=np.uint8):
    """A voxelised ball (voxel centres within `radius` of `centre`), written to `path`."""
    spacing = np.asarray(spacing, float)
    shape = tuple(int(v) for v in np.ceil(2 * radius / spacing) + 2 * margin)
    d = np.eye(3) if direction is None else np.asarray(direction, float).reshape(3, 3)
    # origin chosen so that the ball sits in the middle of the index box, off the voxel lattice
    origin = np.asarray(centre) - d @ ((np.asarray(shape) - 1) / 2 * spacing) + d @ (0.3 * spacing)
    p = _physical(shape, spacing, origin, d)
    mask = np.linalg.norm(p - np.asarray(centre), axis=-1) <= radius
    _write(path, (mask * value).astype(dtype), spacing, origin, d)
    return mask


def _inside_centre(patient, voxel):
    grid = Grid.covering(patient.lo, patient.hi, voxel, pad=2)
    inside = patient.sdf_grid(grid) < 0
    pts = grid.points()[inside.ravel()]
    return pts.mean(axis=0), inside.sum() * grid.voxel_volume


CENTRE = np.array([12.3, -40.7, 95.2])   # an offset, as in scanner coordinates


def test_nifti_sphere_anisotropic_volume_and_position(tmp_path):
    spacing, radius = (0.4, 0.5, 0.7), 6.0
    _sphere(tmp_path / "ball.nii.gz", radius=radius, centre=CENTRE, spacing=spacing)
    patient = load_volume(tmp_path / "ball.nii.gz")
    true_volume = 4 / 3 * math.pi * radius ** 3
    assert patient.volume == pytest.approx(true_volume, rel=0.02)
    centre, voxel_volume = _inside_centre(patient, 0.25)
    # the inside region's centre: within half a CT voxel (the smallest spacing) of the ball's
    assert np.linalg.norm(centre - CENTRE) < 0.5 * min(spacing)
    # the voxel count on the scaffold grid agrees with the reported volume (same surface)
    assert voxel_volume == pytest.approx(patient.volume, rel=0.01)
    assert float(patient.sdf(CENTRE[None])[0]) == pytest.approx(-radius, abs=0.5)
    # tight bounds: the ball's, within one CT voxel
    assert np.all(np.abs(patient.lo - (CENTRE - radius)) < max(spacing))
    assert np.all(np.abs(patient.hi - (CENTRE + radius)) < max(spacing))
    assert patient.spacing == pytest.approx(spacing)
    assert "ball.nii.gz" in patient.describe()


@pytest.mark.parametrize("direction", [
    [[0, -1, 0], [1, 0, 0], [0, 0, 1]],            # 90 degrees about z
    [[1, 0, 0], [0, -1, 0], [0, 0, -1]],           # 180 degrees about x (two flips)
    [[0, 0, 1], [-1, 0, 0], [0, -1, 0]],           # an axis permutation with flips
])
def test_direction_puts_the_bone_in_place(tmp_path, direction):
    """A cuboid 4 x 8 x 12 mm along physical x, y, z keeps those extents under any direction."""
    d = np.asarray(direction, float)
    spacing = np.array([0.5, 0.6, 0.4])
    half = np.array([2.0, 4.0, 6.0])
    shape = (50, 50, 50)
    origin = CENTRE - d @ ((np.asarray(shape) - 1) / 2 * spacing) + d @ (0.27 * spacing)
    p = _physical(shape, spacing, origin, d)
    mask = np.all(np.abs(p - CENTRE) <= half, axis=-1)
    _write(tmp_path / "box.nii.gz", mask.astype(np.uint8), spacing, origin, d)
    patient = load_volume(tmp_path / "box.nii.gz")
    # bounds: the cuboid's, within one voxel (the surface lies between voxel centres)
    assert np.all(np.abs(patient.lo - (CENTRE - half)) < spacing.max())
    assert np.all(np.abs(patient.hi - (CENTRE + half)) < spacing.max())
    centre, _ = _inside_centre(patient, 0.3)
    # the voxelised cuboid's centre (mean of its voxel centres) within a tenth of a voxel,
    # the true centre within half a voxel along each axis
    assert np.linalg.norm(centre - p[mask].mean(axis=0)) < 0.1 * spacing.min()
    assert np.all(np.abs(centre - CENTRE) < 0.5 * spacing.max())
    # the surface encloses the voxels' volume (the count, by the brute-force mask above)
    assert patient.volume == pytest.approx(mask.sum() * np.prod(spacing), rel=2e-3)


def test_nrrd_and_mha_round_trips_give_the_same_patient(tmp_path):
    _sphere(tmp_path / "ball.nii.gz", radius=4.0, centre=CENTRE, spacing=(0.5, 0.4, 0.6))
    img = sitk.ReadImage(str(tmp_path / "ball.nii.gz"))
    patients = [load_volume(tmp_path / "ball.nii.gz")]
    for name in ("ball.nrrd", "ball.mha", "ball.mhd"):
        sitk.WriteImage(img, str(tmp_path / name))
        patients.append(load_volume(tmp_path / name))
    grid = Grid.covering(patients[0].lo, patients[0].hi, 0.3)
    ref = patients[0].sdf_grid(grid)
    for p in patients[1:]:
        assert p.volume == pytest.approx(patients[0].volume, rel=1e-5)
        np.testing.assert_allclose(p.lo, patients[0].lo, atol=1e-4)
        np.testing.assert_allclose(p.sdf_grid(grid), ref, atol=1e-4)


def _staircase_measures(patient, centre, radius):
    """Radial error of the zero level, gradient magnitude and normal angle, along 4000 rays."""
    rng = np.random.default_rng(3)
    u = rng.normal(size=(4000, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    r = np.full(len(u), radius)
    for _ in range(30):                        # the field is a distance: r -= f converges
        r -= patient.sdf(centre + r[:, None] * u).astype(np.float64)
    x = centre + r[:, None] * u
    e = 1e-3
    g = np.stack([(patient.sdf(x + e * np.eye(3)[a]).astype(np.float64)
                   - patient.sdf(x - e * np.eye(3)[a])) / (2 * e) for a in range(3)], axis=1)
    mag = np.linalg.norm(g, axis=1)
    angle = np.degrees(np.arccos(np.clip((g * u).sum(axis=1) / mag, -1, 1)))
    return r - radius, mag, angle


def test_no_staircase_on_coarse_voxels(tmp_path, monkeypatch):
    """A ball of radius 15 mm on 3 mm voxels: the surface is smooth, within half a voxel.

    A staircase surface has axis-aligned facets: normals up to ~60 degrees off the radius,
    steps of half a voxel and more; the same measures on the unsmoothed field fail below.
    """
    h, radius = 3.0, 15.0
    _sphere(tmp_path / "coarse.nii.gz", radius=radius, centre=CENTRE, spacing=(h, h, h))
    patient = load_volume(tmp_path / "coarse.nii.gz")
    dr, mag, angle = _staircase_measures(patient, CENTRE, radius)
    assert np.abs(dr).max() < 0.5 * h
    assert np.sqrt(np.mean(dr ** 2)) < 0.15 * h
    assert np.median(mag) == pytest.approx(1.0, abs=0.1)
    assert np.percentile(np.abs(mag - 1), 95) < 0.3
    assert angle.mean() < 12.0 and np.percentile(angle, 95) < 25.0
    # fine evaluation on a scaffold grid: the sign changes where the sphere is (half a voxel)
    grid = Grid.covering(CENTRE - radius, CENTRE + radius, 0.5, pad=4)
    s = patient.sdf_grid(grid)
    dist = np.linalg.norm(grid.points() - CENTRE, axis=1).reshape(grid.shape) - radius
    assert np.all(s[dist < -0.5 * h] < 0) and np.all(s[dist > 0.5 * h] > 0)
    # the same measures on the staircase (no smoothing) fail
    monkeypatch.setattr(pv, "SMOOTH_VOXELS", 0.0)
    stair = load_volume(tmp_path / "coarse.nii.gz")
    dr, mag, angle = _staircase_measures(stair, CENTRE, radius)
    assert angle.mean() > 12.0 or np.percentile(np.abs(mag - 1), 95) > 0.3


def test_bone_outside_the_image_is_outside(tmp_path):
    """A ball cut by the image's last slice is closed at the image border."""
    spacing = np.array([0.5, 0.5, 0.5])
    shape = (40, 40, 20)
    origin = np.array([0.0, 0.0, 0.0])
    centre = np.array([10.0, 10.0, 9.75])      # the image ends at z = 9.75 (last centre + h/2)
    p = _physical(shape, spacing, origin)
    mask = np.linalg.norm(p - centre, axis=-1) <= 6.0
    _write(tmp_path / "cut.nii.gz", mask.astype(np.uint8), spacing, origin)
    patient = load_volume(tmp_path / "cut.nii.gz")
    assert patient.hi[2] == pytest.approx(9.75, abs=0.5)
    assert patient.volume == pytest.approx(2 / 3 * math.pi * 6.0 ** 3, rel=0.03)
    beyond = np.array([[10.0, 10.0, 10.5], [10.0, 10.0, 14.0], [12.0, 9.0, 11.0]])
    assert np.all(patient.sdf(beyond) > 0)
    assert patient.sdf(np.array([[10.0, 10.0, 8.0]]))[0] < 0


def test_a_bone_that_fills_the_image_keeps_a_distance_field(tmp_path):
    # every voxel bone: the image's box is the bone, whose volume the cells (rounding the box's edges) never
    # reach at any offset; the fit's secant steps ran the field off to -29,000 mm. The field stays a distance
    # within the crop (no value beyond its diagonal), and the surface is the box (closed-form distances)
    spacing = np.array([2.0, 2.0, 2.0])
    _write(tmp_path / "full.nii.gz", np.ones((5, 5, 5), np.uint8), spacing, (0.0, 0.0, 0.0))
    patient = load_volume(tmp_path / "full.nii.gz")
    diagonal = float(np.linalg.norm(np.asarray(patient._field.shape) * spacing))
    assert np.abs(patient._field).max() <= diagonal
    assert patient.sdf(np.array([[4.0, 4.0, 4.0], [0.0, 4.0, 4.0], [4.0, 4.0, 10.0]])) == \
        pytest.approx([-5.0, -1.0, 1.0], abs=1e-5)
    assert patient.volume == pytest.approx(1000.0, rel=0.06)  # the cells round the box's twelve edges


def test_label_and_threshold_select_the_bone(tmp_path):
    spacing = (0.5, 0.5, 0.5)
    shape = (60, 30, 30)
    p = _physical(shape, spacing, (0, 0, 0))
    a, b = np.array([7.0, 7.5, 7.5]), np.array([22.0, 7.5, 7.5])
    labels = np.zeros(shape, np.uint8)
    labels[np.linalg.norm(p - a, axis=-1) <= 4.0] = 3
    labels[np.linalg.norm(p - b, axis=-1) <= 5.0] = 7
    _write(tmp_path / "seg.nii.gz", labels, spacing, (0, 0, 0))
    for lab, c, r in ((3, a, 4.0), (7, b, 5.0)):
        patient = load_volume(tmp_path / "seg.nii.gz", label=lab)
        assert np.all(np.abs((patient.lo + patient.hi) / 2 - c) < 0.5)
        assert patient.volume == pytest.approx(4 / 3 * math.pi * r ** 3, rel=0.03)
    both = load_volume(tmp_path / "seg.nii.gz", label="3,7")
    assert both.volume == pytest.approx(4 / 3 * math.pi * (4.0 ** 3 + 5.0 ** 3), rel=0.03)
    # with no label, a map of several labels is refused (a whole-body map holds organs too), naming them;
    # a mask of one non-zero value is bone throughout
    with pytest.raises(ScaffoldError) as excinfo:
        load_volume(tmp_path / "seg.nii.gz")
    _one_line(excinfo, "seg.nii.gz is a label map of 2 labels (3, 7)", "--label 3,7")
    _write(tmp_path / "mask.nii.gz", (labels == 7) * np.uint8(255), spacing, (0, 0, 0))
    assert load_volume(tmp_path / "mask.nii.gz").volume == pytest.approx(4 / 3 * math.pi * 5.0 ** 3, rel=0.03)
    # a CT: soft tissue at 40 HU, bone (the second ball) at 700 HU, air -1000 elsewhere
    ct = np.full(shape, -1000, np.int16)
    ct[labels == 3] = 40
    ct[labels == 7] = 700
    _write(tmp_path / "ct.nrrd", ct, spacing, (0, 0, 0))
    bone = load_volume(tmp_path / "ct.nrrd", threshold=200)
    assert np.all(np.abs((bone.lo + bone.hi) / 2 - b) < 0.5)
    assert "intensity >= 200" in bone.describe()


def _one_line(excinfo, *words):
    msg = str(excinfo.value)
    assert "\n" not in msg
    for w in words:
        assert w in msg, msg


def test_several_labels_keep_a_bone_in_pieces():
    # four "vertebrae" of a label map, kept together as one selection, in any of the forms given
    labels = np.zeros((6, 7, 20), np.uint8)
    for z, lab in zip((1, 6, 11, 16), (30, 31, 32, 33)):
        labels[1:5, 2:6, z:z + 3] = lab
    labels[0, 0, 0] = 7  # another organ
    want = (labels >= 30) & (labels <= 33)
    for given in ("30,31,32,33", "30, 31 32,33", [30, 31, 32, 33], (33, 32, 31, 30, 30)):
        mask, selection = pv.bone_mask(labels, "seg", given, None)
        assert np.array_equal(mask, want), given
        assert selection.startswith("labels ") and all(str(v) in selection for v in (30, 31, 32, 33))
    mask, selection = pv.bone_mask(labels, "seg", "31", None)
    assert np.array_equal(mask, labels == 31) and selection == "label 31"
    # the labels that have no voxel are named, and what is there is listed
    with pytest.raises(ScaffoldError) as e:
        pv.bone_mask(labels, "seg", "30,34,35", None)
    _one_line(e, "labels 34, 35 have no voxel", "7, 30, 31, 32, 33")
    for bad in ("30,L1", "", "30.5"):
        with pytest.raises(ScaffoldError) as e:
            pv.bone_mask(labels, "seg", bad, None)
        _one_line(e, "--label must be a whole number, or several as 30,31")


def test_bad_inputs_give_one_line(tmp_path):
    spacing = (0.5, 0.5, 0.5)
    labels = np.zeros((20, 20, 20), np.uint8)
    labels[5:12, 5:12, 5:12] = 4
    labels[14:16, 14:16, 14:16] = 9
    _write(tmp_path / "seg.nii.gz", labels, spacing, (0, 0, 0))
    with pytest.raises(ScaffoldError) as e:
        load_volume(tmp_path / "seg.nii.gz", label=5)
    _one_line(e, "label 5", "4, 9")
    with pytest.raises(ScaffoldError) as e:
        load_volume(tmp_path / "seg.nii.gz", label=4, threshold=100)
    _one_line(e, "not both")
    with pytest.raises(ScaffoldError) as e:
        load_volume(tmp_path / "seg.nii.gz", threshold=100)
    _one_line(e, "threshold", "lower")
    with pytest.raises(ScaffoldError) as e:
        load_volume(tmp_path / "seg.nii.gz", label="L1")
    _one_line(e, "whole number")
    _write(tmp_path / "empty.nrrd", np.zeros((10, 10, 10), np.uint8), spacing, (0, 0, 0))
    with pytest.raises(ScaffoldError) as e:
        load_volume(tmp_path / "empty.nrrd")
    _one_line(e, "no bone")
    flat = sitk.GetImageFromArray(np.ones((10, 10), np.uint8))
    sitk.WriteImage(flat, str(tmp_path / "flat.nii.gz"))
    with pytest.raises(ScaffoldError) as e:
        load_volume(tmp_path / "flat.nii.gz")
    _one_line(e, "2-D", "not a volume")
    (tmp_path / "junk.nii").write_bytes(b"this is not an image at all\n" * 20)
    with pytest.raises(ScaffoldError) as e:
        load_volume(tmp_path / "junk.nii")
    _one_line(e, "cannot read junk.nii")
    with pytest.raises(ScaffoldError) as e:
        load_volume(tmp_path / "missing.nii.gz")
    _one_line(e, "does not exist")
    (tmp_path / "nodicom").mkdir()
    with pytest.raises(ScaffoldError) as e:
        load_volume(tmp_path / "nodicom")
    _one_line(e, "no DICOM series")
    # a MetaImage header whose spacing is not finite
    raw = np.ones((6, 6, 6), np.uint8)
    (tmp_path / "nan.raw").write_bytes(raw.tobytes())
    (tmp_path / "nan.mhd").write_text(
        "ObjectType = Image\nNDims = 3\nDimSize = 6 6 6\nElementType = MET_UCHAR\n"
        "ElementSpacing = 1 nan 1\nElementDataFile = nan.raw\n")
    with pytest.raises(ScaffoldError) as e:
        load_volume(tmp_path / "nan.mhd")
    _one_line(e, "nan.mhd", "spacing")


def test_a_ct_given_as_labels_is_refused_in_one_line(tmp_path):
    """A CT (air at -1000 HU) or a grey-level scan read with --label, or with no selection,
    would keep scattered voxels of one intensity or almost the whole box: refused, naming
    --threshold; the same CT with --threshold, and label maps, still load."""
    spacing = (0.5, 0.5, 0.5)
    shape = (24, 20, 20)
    p = _physical(shape, spacing, (0, 0, 0))
    ball = np.linalg.norm(p - np.array([6.0, 5.0, 5.0]), axis=-1) <= 3.0
    ct = np.full(shape, -1000, np.int16)
    ct[ball] = 700
    ct[0, 0, :3] = 31  # three voxels a label 31 would keep
    _write(tmp_path / "ct.nrrd", ct, spacing, (0, 0, 0))
    for label in (31, None):
        with pytest.raises(ScaffoldError) as e:
            load_volume(tmp_path / "ct.nrrd", label=label)
        _one_line(e, "ct.nrrd", "intensities", "-1000 to 700", "--threshold")
    assert load_volume(tmp_path / "ct.nrrd", threshold=200).mask_voxels == int(ball.sum())
    # grey levels with no negative value: more distinct values than any label map holds
    grey = (np.arange(np.prod(shape)).reshape(shape) % 3000).astype(np.uint16)
    _write(tmp_path / "grey.nii.gz", grey, spacing, (0, 0, 0))
    with pytest.raises(ScaffoldError) as e:
        load_volume(tmp_path / "grey.nii.gz")
    _one_line(e, "intensities", "0 to 2999")
    # a probability map: fractional values
    prob = np.where(ball, 0.9, 0.05).astype(np.float32)
    _write(tmp_path / "prob.nii.gz", prob, spacing, (0, 0, 0))
    with pytest.raises(ScaffoldError) as e:
        load_volume(tmp_path / "prob.nii.gz", label=1)
    _one_line(e, "intensities", "--label 1")
    assert load_volume(tmp_path / "prob.nii.gz", threshold=0.5).mask_voxels == int(ball.sum())
    # a label map resampled linearly: fractional values 0 to 117, no negative one. The example threshold is one
    # the image reaches (200 kept no voxel), and it loads as the message says
    lin = np.where(ball, 117.0, 0.0) + (np.arange(np.prod(shape)).reshape(shape) % 5) * 0.25
    _write(tmp_path / "lin.nii.gz", lin.astype(np.float32), spacing, (0, 0, 0))
    with pytest.raises(ScaffoldError) as e:
        load_volume(tmp_path / "lin.nii.gz", label=31)
    _one_line(e, "intensities", "--label 31", "nearest neighbour")
    example = float(re.search(r"e\.g\. --threshold (\S+),", str(e.value)).group(1))
    assert lin.min() < example <= lin.max()
    assert load_volume(tmp_path / "lin.nii.gz", threshold=example).mask_voxels == int(np.count_nonzero(lin >= example))
    # a label map of a hundred labels is a label map
    labels = (np.arange(np.prod(shape)).reshape(shape) % 100).astype(np.uint8)
    labels[ball] = 101
    _write(tmp_path / "many.nii.gz", labels, spacing, (0, 0, 0))
    assert load_volume(tmp_path / "many.nii.gz", label=101).mask_voxels == int(ball.sum())


@pytest.mark.data
@pytest.mark.slow
def test_dicom_series_with_threshold(data_dir):
    patient = load_volume(data_dir / "totalseg_example_ct_dicom", threshold=200)
    np.testing.assert_allclose(patient.spacing, [0.977, 0.977, 2.0], atol=1e-3)
    assert patient.image_shape == (512, 512, 20)
    # bone lies within the scan: 20 slices 2 mm apart, closed at the first and last slice
    assert patient.hi[2] - patient.lo[2] <= 20 * 2.0 + 1e-6
    assert patient.volume == pytest.approx(patient.mask_voxels * np.prod(patient.spacing), rel=0.01)


@pytest.mark.data
@pytest.mark.slow
def test_l1_vertebra_scaffold_is_watertight_and_inside(data_dir):
    import implicit_scaffold

    patient = load_volume(data_dir / "totalseg_example_seg.nii.gz", label=31)
    # L1 is 30 voxels of 3 mm deep at most; it is tens of mm across
    assert np.all(patient.hi - patient.lo > 30) and np.all(patient.hi - patient.lo < 120)
    voxel = 0.5
    result = implicit_scaffold.generate(patient=patient, pore_size=3.0, voxel=voxel, porosity=0.7,
                                        seeds_in="patient")
    rep = result.report
    assert rep["watertight"] and rep["bodies"] == 1
    assert rep["patient_volume_mm3"] == pytest.approx(patient.volume)
    assert float(patient.sdf(result.mesh.vertices).max()) <= voxel
    # what is printed meets the target: the mesh's own (trimesh) volume in the patient's
    assert abs(1.0 - result.mesh.volume / rep["patient_volume_mm3"] - 0.7) < 0.003


def test_a_plate_one_voxel_thin_is_kept(tmp_path):
    """On 3 mm voxels, a plate one voxel thick (which a plain Gaussian erases) stays bone."""
    h = 3.0
    mask = np.zeros((24, 24, 24), np.uint8)
    mask[4:20, 4:20, 12] = 1                       # 48 x 48 x 3 mm
    _write(tmp_path / "plate.nii.gz", mask, (h, h, h), (0, 0, 0))
    patient = load_volume(tmp_path / "plate.nii.gz")
    xs = np.linspace(15.0, 55.0, 9)
    mid = np.stack(np.meshgrid(xs, xs, [12 * h], indexing="ij"), axis=-1).reshape(-1, 3)
    assert np.all(patient.sdf(mid) < 0)
    assert patient.volume == pytest.approx(mask.sum() * h ** 3, rel=1e-3)
    assert patient.hi[2] - patient.lo[2] < 2 * h


def test_sdf_grid_does_not_depend_on_the_tiling(tmp_path, monkeypatch):
    _sphere(tmp_path / "ball.nii.gz", radius=3.0, centre=CENTRE, spacing=(0.5, 0.6, 0.7))
    patient = load_volume(tmp_path / "ball.nii.gz")
    grid = Grid.covering(patient.lo, patient.hi, 0.23, pad=3)   # odd sizes
    whole = patient.sdf_grid(grid)
    monkeypatch.setattr(pv, "_TILE_POINTS", 1000)
    np.testing.assert_array_equal(patient.sdf_grid(grid), whole)
    np.testing.assert_array_equal(patient.sdf(grid.points()).reshape(grid.shape), whole)


def test_a_sheared_direction_is_refused(tmp_path):
    img = sitk.GetImageFromArray(np.ones((6, 6, 6), np.uint8))
    img.SetDirection((1, 0.3, 0, 0, 1, 0, 0, 0, 1))
    sitk.WriteImage(img, str(tmp_path / "shear.mha"))
    with pytest.raises(ScaffoldError) as e:
        load_volume(tmp_path / "shear.mha")
    _one_line(e, "sheared", "resample")


@pytest.mark.parametrize("header", ["", "spacings: 0.1 0.1 0.1\n"])
def test_a_volume_without_spacing_needs_it_given(tmp_path, header):
    # ITK reads 1 mm voxels from a NRRD that states none: a 0.05 mm micro-CT would become a bone
    # twenty times its size (and its cells thousands of times as many); the oracle is the
    # header's own spacing, given once in the file and once with --spacing
    ball = np.zeros((24, 24, 24), np.uint8)
    i, j, k = np.ogrid[:24, :24, :24]
    ball[(i - 11.5) ** 2 + (j - 11.5) ** 2 + (k - 11.5) ** 2 <= 8.0 ** 2] = 1
    path = tmp_path / "ball.nrrd"
    path.write_bytes(f"NRRD0004\ntype: uint8\ndimension: 3\nsizes: 24 24 24\n{header}encoding: raw\n\n".encode()
                     + np.ascontiguousarray(ball.T).tobytes())
    if not header:
        with pytest.raises(ScaffoldError) as excinfo:
            load_volume(path)
        _one_line(excinfo, "states no voxel spacing", "--spacing")
        patient = load_volume(path, spacing=0.1)
    else:
        patient = load_volume(path)
    # a ball of radius 8 voxels of 0.1 mm: about 2.14 mm3, whatever the spacing's source
    assert patient.volume == pytest.approx(4 / 3 * math.pi * 0.8 ** 3, rel=0.05)
    with pytest.raises(ScaffoldError):
        load_volume(path, spacing=(0.1, -1.0, 0.1))


def test_the_cli_takes_the_spacing_of_a_volume_patient(tmp_path, capsys):
    from implicit_scaffold.cli import main

    path = tmp_path / "ball.nrrd"
    ball = np.zeros((16, 16, 16), np.uint8)
    ball[4:12, 4:12, 4:12] = 1
    path.write_bytes(b"NRRD0004\ntype: uint8\ndimension: 3\nsizes: 16 16 16\nencoding: raw\n\n"
                     + np.ascontiguousarray(ball.T).tobytes())
    assert main(["generate", "--patient", str(path), "-o", str(tmp_path / "x.stl"), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--spacing" in err[0]
    assert not (tmp_path / "x.stl").exists()


def test_nan_voxels_and_a_threshold_that_takes_everything_are_warned_about():
    # NaN voxels inside a bone read as holes without a word; a threshold every voxel reaches made the whole image bone
    from implicit_scaffold.errors import ScaffoldWarning

    ct = np.full((6, 6, 6), -1000.0, np.float32)
    ct[1:5, 1:5, 1:5] = 800.0
    ct[2, 2, 2] = np.nan
    with pytest.warns(ScaffoldWarning, match="holds 1 NaN voxels, read as no bone;"):
        mask, _ = pv.bone_mask(ct, "ct.nii", None, 200)
    assert mask.sum() == 4 ** 3 - 1
    with pytest.warns(ScaffoldWarning, match="every voxel of ct.nii reaches the threshold -2000"):
        pv.bone_mask(np.nan_to_num(ct), "ct.nii", None, -2000)


@pytest.mark.parametrize("label, threshold, inside, said", [
    (None, 200, [True, False], "+inf read as bone, -inf as no bone"),  # +inf reaches every threshold
    (800, None, [False, False], "read as no bone"),  # inf is no label
])
def test_infinite_voxels_are_warned_about_as_what_they_become(label, threshold, inside, said):
    # the warning said NaN or inf were read as no bone, where +inf over a threshold was bone
    from implicit_scaffold.errors import ScaffoldWarning

    # a CT (air at -1000 HU), or a label map (0 around the bone's label): an infinite voxel is neither's
    ct = np.full((6, 6, 6), -1000.0 if threshold is not None else 0.0, np.float32)
    ct[1:5, 1:5, 1:5] = 800.0
    ct[2, 2, 2], ct[2, 2, 3] = np.inf, -np.inf
    with pytest.warns(ScaffoldWarning, match=re.escape(f"2 infinite voxels, {said};")):
        mask, _ = pv.bone_mask(ct, "ct.nii", label, threshold)
    assert [bool(mask[2, 2, 2]), bool(mask[2, 2, 3])] == inside
