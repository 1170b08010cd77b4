"""Volume exports read back by independent readers (SimpleITK, PyVista) with their geometry."""
import hashlib

import numpy as np
import pytest

from implicit_scaffold.errors import ScaffoldError
from implicit_scaffold.io.export import write_volume
from implicit_scaffold.run.grid import Grid


@pytest.fixture(scope="module")
def field_grid():
    grid = Grid((1.5, -2.0, 0.25), 0.1, (13, 11, 9))   # odd sizes: axis order mistakes show
    rng = np.random.default_rng(3)
    return (rng.random(grid.shape) - 0.5).astype(np.float32), grid


@pytest.mark.parametrize("ext", [".nii.gz", ".nii", ".nrrd", ".mha"])
def test_itk_round_trip(tmp_path, field_grid, ext):
    import SimpleITK as sitk

    field, grid = field_grid
    path = write_volume(field, grid, tmp_path / f"f{ext}")
    img = sitk.ReadImage(str(path))
    back = sitk.GetArrayFromImage(img).transpose(2, 1, 0)
    assert back.shape == field.shape and np.array_equal(back, field)
    assert np.allclose(img.GetOrigin(), grid.origin) and np.allclose(img.GetSpacing(), grid.spacing)
    # the value at a physical point is the field's value at that voxel centre
    idx = img.TransformPhysicalPointToIndex(tuple(grid.indices_to_points([[4, 7, 2]])[0]))
    assert idx == (4, 7, 2)
    assert [p.name for p in tmp_path.iterdir()] == [f"f{ext}"]


def test_binary_tiff_for_bonej(tmp_path, field_grid):
    import SimpleITK as sitk

    field, grid = field_grid
    path = write_volume(field, grid, tmp_path / "s.tif")
    back = sitk.GetArrayFromImage(sitk.ReadImage(str(path))).transpose(2, 1, 0)
    assert back.dtype == np.uint8 and np.array_equal(back == 255, field < 0) and set(np.unique(back)) <= {0, 255}


def test_vti_round_trip(tmp_path, field_grid):
    import pyvista as pv

    field, grid = field_grid
    path = write_volume(field, grid, tmp_path / "f.vti", binary=True)
    img = pv.read(str(path))
    assert tuple(img.dimensions) == field.shape and np.allclose(img.origin, grid.origin)
    back = np.asarray(img.point_data["solid"]).reshape(field.shape, order="F")
    assert np.array_equal(back.astype(bool), field < 0)


@pytest.mark.parametrize("ext", [".nii.gz", ".vti", ".tif"])
def test_same_field_same_bytes(tmp_path, field_grid, ext):
    field, grid = field_grid
    a = write_volume(field, grid, tmp_path / f"a{ext}")
    b = write_volume(field, grid, tmp_path / f"b{ext}")
    assert hashlib.sha256(a.read_bytes()).digest() == hashlib.sha256(b.read_bytes()).digest()


def test_zarr_or_a_clear_message(tmp_path, field_grid):
    field, grid = field_grid
    try:
        import zarr
    except ImportError:
        with pytest.raises(ScaffoldError, match="zarr extra"):
            write_volume(field, grid, tmp_path / "f.zarr")
        return
    write_volume(field, grid, tmp_path / "f.zarr")
    g = zarr.open_group(str(tmp_path / "f.zarr"), mode="r")
    assert np.array_equal(g["sdf"][...], field) and g.attrs["spacing_mm"] == grid.spacing


def test_unknown_extension(tmp_path, field_grid):
    field, grid = field_grid
    with pytest.raises(ScaffoldError, match="use one of"):
        write_volume(field, grid, tmp_path / "f.xyz")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("name, binary", [("f.nii.gz", False), ("f.tif", True), ("f.vti", False)])
def test_generate_writes_volumes_with_their_report(tmp_path, name, binary):
    import json

    import SimpleITK as sitk

    import implicit_scaffold

    r = implicit_scaffold.generate(seeds=20, size=2.0, voxel=0.1, porosity=0.7, output=tmp_path / name, mesh=False)
    rep = json.loads((tmp_path / "f.json").read_text())
    assert rep["grid_shape"] == list(r.grid.shape)
    if name.endswith(".vti"):
        import pyvista as pv

        back = np.asarray(pv.read(str(tmp_path / name)).point_data["sdf"]).reshape(r.grid.shape, order="F")
    else:
        back = sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / name))).transpose(2, 1, 0)
    assert np.array_equal(back > 0, r.field < 0) if binary else np.array_equal(back, r.field)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([name, "f.json"])


def _sitk_write(values, grid, path, compress):
    """SimpleITK's own writer: the oracle for the streamed headers and data."""
    import SimpleITK as sitk

    image = sitk.GetImageFromArray(np.ascontiguousarray(values.transpose(2, 1, 0)))
    image.SetSpacing((grid.spacing,) * 3)
    image.SetOrigin(tuple(float(v) for v in grid.origin))
    sitk.WriteImage(image, str(path), useCompression=compress)
    return path


class _OnDisk:
    """A field read plane range by plane range, like a tiled run's field file."""

    def __init__(self, field, grid):
        self.field, self.grid, self.reads = field, grid, 0

    def read(self, x0, x1):
        self.reads += 1
        return np.array(self.field[x0:x1])


@pytest.mark.parametrize("binary", [False, True])
def test_streamed_nifti_is_simpleitks_file(tmp_path, field_grid, binary, monkeypatch):
    import gzip

    from implicit_scaffold.io import files

    # deflated in pieces of 2000 bytes, on the thread pool: still one gzip stream
    monkeypatch.setattr(files, "DEFLATE_PIECE", 2000)
    field, grid = field_grid
    values = (field < 0).astype(np.uint8) if binary else field
    want = _sitk_write(values, grid, tmp_path / "itk.nii", False).read_bytes()
    assert write_volume(field, grid, tmp_path / "a.nii", binary=binary).read_bytes() == want
    # compressed: zlib's deflate is not SimpleITK's (ITK 5.4 bundles zlib-ng), the stream is
    itk_gz = gzip.decompress(_sitk_write(values, grid, tmp_path / "itk.nii.gz", True).read_bytes())
    ours = (tmp_path / "a.nii.gz")
    write_volume(field, grid, ours, binary=binary)
    assert ours.read_bytes()[:10] == (tmp_path / "itk.nii.gz").read_bytes()[:10]  # gzip header: time 0, Unix
    assert gzip.decompress(ours.read_bytes()) == itk_gz == want


@pytest.mark.parametrize("ext", [".nrrd", ".mha"])
def test_streamed_nrrd_and_mha_have_simpleitks_header_and_values(tmp_path, field_grid, ext, monkeypatch):
    import SimpleITK as sitk

    from implicit_scaffold.io import files

    monkeypatch.setattr(files, "DEFLATE_PIECE", 2000)  # many pieces; ITK checks the zlib stream's Adler-32
    field, grid = field_grid
    itk = _sitk_write(field, grid, tmp_path / f"itk{ext}", True)
    ours = write_volume(field, grid, tmp_path / f"a{ext}")
    mark = b"\n\n" if ext == ".nrrd" else b"ElementDataFile = LOCAL\n"
    head = lambda p: p.read_bytes().split(mark)[0].split(b"\n")  # noqa: E731
    # the same header lines, but the compressed size (another deflate) in MetaImage's
    differ = [a for a, b in zip(head(itk), head(ours)) if a != b]
    assert len(head(itk)) == len(head(ours)) and all(a.startswith(b"CompressedDataSize") for a in differ)
    a, b = sitk.ReadImage(str(itk)), sitk.ReadImage(str(ours))
    assert np.array_equal(sitk.GetArrayFromImage(a), sitk.GetArrayFromImage(b))
    assert a.GetOrigin() == b.GetOrigin() and a.GetSpacing() == b.GetSpacing()
    assert a.GetDirection() == b.GetDirection()


@pytest.mark.parametrize("ext", [".nii", ".nii.gz", ".nrrd", ".mha", ".tif", ".vti"])
def test_a_field_on_disk_streams_to_the_same_bytes_in_small_blocks(tmp_path, field_grid, ext):
    field, grid = field_grid
    whole = write_volume(field, grid, tmp_path / f"w{ext}").read_bytes()
    source = _OnDisk(field, grid)
    # 2,000 bytes: a few z per block, two planes of x per read
    assert write_volume(source, grid, tmp_path / f"d{ext}", max_bytes=2000).read_bytes() == whole
    assert source.reads >= 2 * -(-grid.shape[0] // 2)  # two z blocks or more, each read in 7 steps


def test_streamed_tiff_and_vti_read_as_the_writers_of_record_write_them(tmp_path, field_grid):
    import pyvista as pv
    import SimpleITK as sitk
    import tifffile

    field, grid = field_grid
    pages = tifffile.imread(write_volume(field, grid, tmp_path / "s.tif"))
    assert pages.shape == field.shape[::-1] and np.array_equal(pages.transpose(2, 1, 0), (field < 0) * 255)
    with tifffile.TiffFile(tmp_path / "s.tif") as tif:
        assert tif.is_imagej and tif.imagej_metadata["spacing"] == pytest.approx(grid.spacing)
    back = sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / "s.tif")))
    assert np.array_equal(back, pages)
    # PyVista's own file of the same image is the oracle for the VTI
    ref = pv.ImageData(dimensions=field.shape, spacing=(grid.spacing,) * 3, origin=grid.origin)
    ref.point_data["sdf"] = field.ravel(order="F")
    ref.save(str(tmp_path / "ref.vti"), binary=True)
    a, b = pv.read(str(tmp_path / "ref.vti")), pv.read(str(write_volume(field, grid, tmp_path / "f.vti")))
    assert a.dimensions == b.dimensions and np.allclose(a.origin, b.origin, rtol=0, atol=0)
    assert a.spacing == b.spacing and np.array_equal(a.point_data["sdf"], b.point_data["sdf"])
