"""The one image reader: files, DICOM folders, TIFF folders, and one-line errors."""
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
