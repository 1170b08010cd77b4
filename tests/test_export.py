"""Volume exports read back by independent readers (SimpleITK, PyVista) with their geometry."""
import hashlib

import numpy as np
import pytest

from implicit_scaffold.errors import ScaffoldError
from implicit_scaffold.export import write_volume
from implicit_scaffold.grid import Grid


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
