"""The one image reader: files, DICOM folders, TIFF folders, and one-line errors."""
import math

import numpy as np
import pytest
import SimpleITK as sitk

from implicit_scaffold.errors import ScaffoldError
from implicit_scaffold.io.images import read_image


def _volume(shape=(4, 5, 6)):
    return (np.arange(np.prod(shape)).reshape(shape) % 7).astype(np.uint8)


def test_a_file_keeps_its_values_and_geometry(tmp_path):
    image = sitk.GetImageFromArray(_volume())
    image.SetSpacing((0.1, 0.2, 0.3))
    image.SetOrigin((1.0, 2.0, 3.0))
    sitk.WriteImage(image, str(tmp_path / "v.nrrd"))
    back = read_image(tmp_path / "v.nrrd")
    assert np.array_equal(sitk.GetArrayFromImage(back), _volume())
    assert back.GetSpacing() == pytest.approx((0.1, 0.2, 0.3)) and back.GetOrigin() == pytest.approx((1, 2, 3))


def test_a_folder_of_tiff_slices_reads_in_name_order(tmp_path):
    vol = _volume()
    for k, page in enumerate(vol):
        sitk.WriteImage(sitk.GetImageFromArray(page), str(tmp_path / f"s{k:03d}.tif"))
    assert np.array_equal(sitk.GetArrayFromImage(read_image(tmp_path, folder="tiff")), vol)
    # the same folder read as a CT: no DICOM series there, said in one line
    with pytest.raises(ScaffoldError, match="holds no DICOM series"):
        read_image(tmp_path, folder="dicom")


@pytest.mark.parametrize("make, words", [
    (lambda p: p / "missing.nii", "does not exist"),
    (lambda p: (p / "bad.nrrd").write_bytes(b"not an image") and p / "bad.nrrd", "cannot read bad.nrrd as a volume"),
    (lambda p: (p / "empty").mkdir() or p / "empty", "holds no .tif slices"),
])
def test_what_cannot_be_read_is_one_line(tmp_path, make, words):
    folder = "tiff" if "tif" in words else "dicom"
    with pytest.raises(ScaffoldError, match=words) as exc:
        read_image(make(tmp_path), folder=folder)
    assert "\n" not in str(exc.value)


@pytest.mark.parametrize("unit, scale", [("mm", 1.0), ("micron", 1e-3), ("\\u00B5m", 1e-3)])
def test_an_imagej_tiff_states_its_voxel_size(tmp_path, unit, scale):
    # ImageJ (and BoneJ, and this package's .tif output) keep the voxel size in the resolution tags (pixels per
    # unit, x and y) and the description's spacing= (z) in its unit=: tifffile writes them, the oracle. ITK's
    # reader gives 1 mm (or the print resolution); a TIFF without ImageJ's unit states none (its resolution is for printing)
    import tifffile

    from implicit_scaffold.io.images import header_states_spacing

    vol = _volume((3, 4, 5))
    path = tmp_path / "v.tif"
    tifffile.imwrite(path, vol, imagej=True, resolution=(1 / 20.0, 1 / 30.0), metadata={"spacing": 40.0, "unit": unit})
    assert header_states_spacing(path)
    back = read_image(path)
    assert back.GetSpacing() == pytest.approx((20 * scale, 30 * scale, 40 * scale))
    assert np.array_equal(sitk.GetArrayFromImage(back), vol)
    plain = tmp_path / "p.tif"
    tifffile.imwrite(plain, vol, resolution=(300.0, 300.0))
    assert not header_states_spacing(plain)


def _ball(shape=(40, 36, 32)):
    """A label-31 ball in a (k, j, i) array, with noise outside it so that its gzip stream is long."""
    k, j, i = np.indices(shape)
    ball = (k - 20) ** 2 + (j - 18) ** 2 + (i - 16) ** 2 <= 12 ** 2
    rng = np.random.default_rng(7)
    return np.where(ball, 31, rng.integers(0, 3, shape)).astype(np.uint8)


@pytest.mark.parametrize("ext", [".nii.gz", ".nrrd", ".mha", ".nhdr"])
def test_a_compressed_volume_cut_short_is_refused_in_one_line(tmp_path, ext):
    # an interrupted download: the data cut in half. ITK reads a .nii.gz with the missing half as zeros (the ball
    # loses voxels without a word), and refuses the others in messages that name no cause ("No such file or
    # directory"). The oracle is Python's gzip and zlib, on the data after the header ITK wrote
    import gzip
    import zlib

    sitk.WriteImage(sitk.GetImageFromArray(_ball()), str(tmp_path / f"v{ext}"), True)
    # whole, it reads as written (no check refuses a sound stream)
    assert np.array_equal(sitk.GetArrayFromImage(read_image(tmp_path / f"v{ext}")), _ball())
    data = tmp_path / ("v.raw.gz" if ext == ".nhdr" else f"v{ext}")
    raw = data.read_bytes()
    start = {".nii.gz": 0, ".nhdr": 0, ".nrrd": raw.find(b"\n\n") + 2,
             ".mha": raw.find(b"\n", raw.find(b"ElementDataFile = LOCAL")) + 1}[ext]
    data.write_bytes(raw[: start + (len(raw) - start) // 2])
    cut = data.read_bytes()[start:]
    if ext == ".mha":
        with pytest.raises(zlib.error, match="incomplete"):
            zlib.decompress(cut)
    else:
        with pytest.raises(EOFError):
            gzip.decompress(cut)
    with pytest.raises(ScaffoldError, match=f"v{ext}.* is cut short") as exc:
        read_image(tmp_path / f"v{ext}")
    assert "\n" not in str(exc.value)


def test_a_nifti_gz_corrupt_or_whole(tmp_path):
    sitk.WriteImage(sitk.GetImageFromArray(_ball()), str(tmp_path / "whole.nii.gz"))
    data = (tmp_path / "whole.nii.gz").read_bytes()
    # a byte flipped in the data: the CRC (or the deflate stream) fails
    bad = bytearray(data)
    bad[len(bad) // 2] ^= 0xFF
    (tmp_path / "bad.nii.gz").write_bytes(bytes(bad))
    with pytest.raises(ScaffoldError, match="bad.nii.gz is corrupt"):
        read_image(tmp_path / "bad.nii.gz")
    assert np.array_equal(sitk.GetArrayFromImage(read_image(tmp_path / "whole.nii.gz")), _ball())


def _dicom_series(folder, positions, orientation=(1, 0, 0, 0, 1, 0), names=None,
                  series="1.2.826.0.1.3680043.2.1125.1.4242", pixels=None):
    """Write one 8 x 8 DICOM slice per position (mm, LPS) with these ImagePositionPatient and
    ImageOrientationPatient tags: the oracle of the series' geometry."""
    import locale

    folder.mkdir(exist_ok=True)
    # GDCM's writer leaves the process in the C locale: text files the next tests read without an encoding were
    # then read as ASCII (a report page's 'µ' failed in whichever test came next in this worker)
    saved = locale.setlocale(locale.LC_ALL)
    try:
        _write_slices(folder, series, positions, orientation, names, pixels)
    finally:
        locale.setlocale(locale.LC_ALL, saved)
    # the tags are on disk as written (GDCM may take them from the image's geometry instead)
    back = sitk.ImageFileReader()
    back.SetFileName(str(folder / (names[0] if names else "s000.dcm")))
    back.ReadImageInformation()
    assert np.allclose([float(v) for v in back.GetMetaData("0020|0032").split("\\")], positions[0], atol=1e-5)
    assert np.allclose([float(v) for v in back.GetMetaData("0020|0037").split("\\")], orientation, atol=1e-6)
    return folder


def _write_slices(folder, series, positions, orientation, names, pixels=None):
    for n, pos in enumerate(positions):
        img = sitk.GetImageFromArray(np.full((1, 8, 8), 100 + n, np.int16) if pixels is None else pixels[n][None])
        img.SetSpacing((0.5, 0.5, 1.0))
        tags = {"0008|0060": "CT", "0020|000d": "1.2.826.0.1.3680043.2.1125.1.4241", "0020|000e": series,
                "0008|0018": f"{series}.{n + 1}", "0020|0013": str(n + 1),
                "0020|0032": "\\".join(f"{v:.6f}" for v in pos),
                "0020|0037": "\\".join(f"{v:.9f}" for v in orientation)}
        for key, value in tags.items():
            img.SetMetaData(key, value)
        writer = sitk.ImageFileWriter()
        writer.KeepOriginalImageUIDOn()
        writer.SetFileName(str(folder / (names[n] if names else f"s{n:03d}.dcm")))
        writer.Execute(img)


def test_an_even_dicom_series_reads_without_a_word(tmp_path):
    import warnings

    folder = _dicom_series(tmp_path / "even", [(1.0, 2.0, 3.0 + 2 * k) for k in range(6)])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        image = read_image(folder)
    assert image.GetSize() == (8, 8, 6) and image.GetSpacing() == pytest.approx((0.5, 0.5, 2.0))


def test_a_gantry_tilted_dicom_series_is_put_where_its_tags_place_it(tmp_path):
    # rows along x, columns tilted 20 degrees about x, the table (the slices' positions) moving along z: ITK
    # stacks the slices along the tilted normal, up to 13 mm from where the tags put them in the sweep's CT (it
    # was refused, naming dcm2niix). Oracle: a ball drawn into each slice where its tags place its pixels
    from implicit_scaffold.errors import ScaffoldWarning

    tilt = math.radians(20)
    row, col = np.array([1.0, 0.0, 0.0]), np.array([0.0, math.cos(tilt), math.sin(tilt)])
    positions = [(0.0, 0.0, 1.0 * k) for k in range(16)]
    centre, radius, n, h = np.array([8.0, 6.0, 9.0]), 3.5, 32, 0.5
    ij = np.stack(np.meshgrid(np.arange(n), np.arange(n), indexing="xy"), axis=-1) * h  # [j, i] -> (i h, j h)
    pixels = []
    for pos in positions:
        world = np.asarray(pos) + ij[..., :1] * row + ij[..., 1:] * col
        pixels.append(np.where(np.linalg.norm(world - centre, axis=-1) < radius, 1000, -1000).astype(np.int16))
    folder = _dicom_series(tmp_path / "tilt", positions, (*row, *col), pixels=pixels)
    with pytest.warns(ScaffoldWarning, match=r"not stacked along their normal.*\b20 degrees.*shifted in its plane "
                      f"to where its tags put it, up to {15 * math.sin(tilt):.3g} mm"):
        image = read_image(folder)
    arr = np.transpose(sitk.GetArrayFromImage(image), (2, 1, 0))
    idx = np.argwhere(np.ones(arr.shape, bool))
    world = np.array([image.TransformIndexToPhysicalPoint(tuple(int(v) for v in p)) for p in idx])
    dist = np.linalg.norm(world - centre, axis=1).reshape(arr.shape)
    # the bone where the tags put it: every voxel well inside the ball reads it, every one well outside does not
    # (a pixel and a slice step of slack for the interpolation)
    assert (arr[dist < radius - 1.2] > 0).all() and (arr[dist > radius + 1.2] < 0).all()
    assert image.GetSpacing()[2] == pytest.approx(math.cos(tilt))  # the step along the normal


def test_a_dicom_series_with_a_duplicated_slice_is_refused(tmp_path):
    # a copied slice, as the sweep's cp made it: GDCM cannot sort two slices at one position, and leaves the
    # files in name order, the copy after c.dcm; the two named are the pair at one position, by the tags
    names = ["a.dcm", "b.dcm", "c.dcm", "copy_b.dcm"]
    folder = _dicom_series(tmp_path / "dup", [(0.0, 0.0, 0.0), (0.0, 0.0, 2.0), (0.0, 0.0, 4.0), (0.0, 0.0, 2.0)],
                           names=names)
    with pytest.raises(ScaffoldError, match="1 slice.* lie at the position of another") as exc:
        read_image(folder)
    assert "b.dcm and copy_b.dcm at (0 0 2) mm" in str(exc.value) and "\n" not in str(exc.value)


@pytest.mark.parametrize("z, gap", [([0, 2, 4, 8, 10, 12], 4.0), ([0, 2, 4, 6, 8, 11, 13], 3.0)])
def test_an_unevenly_spaced_dicom_series_is_warned_about(tmp_path, z, gap):
    # a missing slice (4 mm where the others are 2 mm), a step of 3: ITK reads one mean step and says nothing
    from implicit_scaffold.errors import ScaffoldWarning

    folder = _dicom_series(tmp_path / "gap", [(0.0, 0.0, float(v)) for v in z])
    mean = (z[-1] - z[0]) / (len(z) - 1)
    off = max(abs(v - k * mean) for k, v in enumerate(z))     # where ITK puts each slice, against its tag
    with pytest.warns(ScaffoldWarning, match="not evenly spaced") as record:
        image = read_image(folder)
    message = str(record[0].message)
    assert f"are {gap:.4g} mm apart, the others 2 mm" in message and f"up to {off:.3g} mm" in message
    assert image.GetSpacing()[2] == pytest.approx(mean, rel=1e-4)


@pytest.mark.parametrize("units, scale", [('"microns" "microns" "microns"', 1e-3), ('"mm" "mm" "mm"', 1.0),
                                          ('"m" "m" "m"', 1000.0), ('"" "" ""', 1.0), (None, 1.0)])
def test_nrrd_space_units_are_honoured(tmp_path, units, scale):
    # a micro-CT exporter's header: 51.3 micron voxels at an origin of (100, 200, 300) microns; ITK reads the
    # numbers as mm. The header is written here by hand (NRRD0004), the oracle
    vol = _volume((3, 4, 5))
    lines = ["NRRD0004", "type: uint8", "dimension: 3", "sizes: 5 4 3", "encoding: raw",
             "space: left-posterior-superior", "space directions: (51.3,0,0) (0,51.3,0) (0,0,51.3)",
             "space origin: (100,200,300)"] + ([f"space units: {units}"] if units else [])
    path = tmp_path / "crop.nrrd"
    path.write_bytes(("\n".join(lines) + "\n\n").encode() + vol.tobytes())
    image = read_image(path)
    assert image.GetSpacing() == pytest.approx((51.3 * scale,) * 3)
    assert image.GetOrigin() == pytest.approx((100 * scale, 200 * scale, 300 * scale))
    assert np.array_equal(sitk.GetArrayFromImage(image), vol)


def test_nrrd_space_units_not_a_length_are_refused(tmp_path):
    path = tmp_path / "odd.nrrd"
    path.write_bytes(b"NRRD0004\ntype: uint8\ndimension: 3\nsizes: 2 2 2\nencoding: raw\nspace dimension: 3\n"
                     b"space directions: (1,0,0) (0,1,0) (0,0,1)\nspace units: \"furlong\" \"furlong\" \"furlong\"\n\n"
                     + bytes(8))
    with pytest.raises(ScaffoldError, match="odd.nrrd states space units .*furlong"):
        read_image(path)


@pytest.mark.parametrize("shift, warned", [(50.0, True), (0.0, False)])
def test_a_nifti_whose_sform_disagrees_with_its_qform_is_warned_about(tmp_path, shift, warned):
    # the sweep's seg_q_vs_s: qform code 1, sform code 2 moved 50 mm. ITK places it by the qform, nibabel and FSL
    # by the sform. The header's bytes (NIfTI-1: sform_code at 254, srow_x at 280) are written here, the oracle
    import gzip
    import struct
    import warnings

    from implicit_scaffold.errors import ScaffoldWarning

    image = sitk.GetImageFromArray(_volume((6, 5, 4)))
    image.SetSpacing((0.8, 0.9, 1.1))
    image.SetOrigin((10.0, -20.0, 30.0))
    sitk.WriteImage(image, str(tmp_path / "v.nii"))
    head = bytearray((tmp_path / "v.nii").read_bytes())
    assert struct.unpack("<h", head[252:254])[0] > 0       # ITK wrote a qform
    srow_x = struct.unpack("<4f", head[280:296])
    head[254:256] = struct.pack("<h", 2)
    head[280:296] = struct.pack("<4f", *srow_x[:3], srow_x[3] + shift)
    path = tmp_path / "qs.nii.gz"
    path.write_bytes(gzip.compress(bytes(head)))
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        back = read_image(path)
    said = [str(w.message) for w in record if issubclass(w.category, ScaffoldWarning)]
    assert back.GetOrigin() == pytest.approx((10.0, -20.0, 30.0))    # the qform's, as ITK reads it
    if warned:
        assert len(said) == 1 and "sform (code 2) puts the volume up to 50 mm from where ITK reads it" in said[0]
    else:
        assert not said


def test_a_folder_of_two_dicom_series_reads_the_larger_and_says_so(tmp_path):
    """Two series in one folder: the one of more slices is read, with a warning of the tool's kind that counts
    both (it was a plain UserWarning naming an empty series ID)."""
    from implicit_scaffold.errors import ScaffoldWarning

    folder = _dicom_series(tmp_path / "two", [(0.0, 0.0, 2.0 * k) for k in range(6)])
    _dicom_series(folder, [(50.0, 0.0, 2.0 * k) for k in range(3)], names=[f"b{k}.dcm" for k in range(3)],
                  series="1.2.826.0.1.3680043.2.1125.1.4343")
    with pytest.warns(ScaffoldWarning, match=r"holds 2 DICOM series; using .*\(6 slices; the others have 3\)"):
        image = read_image(folder)
    assert image.GetSize()[2] == 6
