"""Printer slices: layer images against the field and against a sphere's closed-form sections."""
import json

import numpy as np
import pytest
from PIL import Image

from implicit_scaffold.errors import ScaffoldError
from implicit_scaffold.grid import Grid
from implicit_scaffold.slices import STACK_JSON, write_slices


def _sphere(radius=1.7, h=0.05, size=4.0):
    grid = Grid.covering([0, 0, 0], [size] * 3, h)
    x, y, z = np.meshgrid(*grid.axes(), indexing="ij")
    field = (np.sqrt((x - size / 2) ** 2 + (y - size / 2) ** 2 + (z - size / 2) ** 2) - radius).astype(np.float32)
    return field, grid


def _layers(folder, stack):
    return [np.asarray(Image.open(folder / stack.files.format(k))) for k in range(stack.layers)]


def test_sphere_sections_match_the_closed_form(tmp_path):
    # each layer of a ball is a disc of radius sqrt(R^2 - dz^2): its area in pixels is known
    radius, c = 1.7, 2.0
    field, grid = _sphere(radius)
    stack = write_slices(field, grid, tmp_path / "stack", pixel=0.02, layer=0.1)
    images = _layers(tmp_path / "stack", stack)
    assert len(images) == stack.layers and images[0].shape == (stack.height, stack.width)
    for k, img in enumerate(images):
        z = stack.origin_mm[2] + (k + 0.5) * stack.layer_mm
        dz2 = (z - c) ** 2
        r2 = max(radius ** 2 - dz2, 0.0)
        area = img.astype(np.float64).sum() / 255 * stack.pixel_mm ** 2
        # anti-aliasing only changes pixels whose centre lies within half a pixel of the
        # surface (|s| < pixel / 2): the area of that annulus bounds the error
        half = stack.pixel_mm / 2
        band = np.pi * (max((radius + half) ** 2 - dz2, 0) - max((radius - half) ** 2 - dz2, 0))
        assert area == pytest.approx(np.pi * r2, abs=0.5 * band + 1e-4), k


def test_image_orientation_row_zero_is_largest_y(tmp_path):
    # a solid slab in the half y > 2 shows in the top rows
    grid = Grid.covering([0, 0, 0], [4, 4, 1], 0.1)
    _, y, _ = np.meshgrid(*grid.axes(), indexing="ij")
    field = (2.0 - y).astype(np.float32)
    stack = write_slices(field, grid, tmp_path / "s")
    img = _layers(tmp_path / "s", stack)[0]
    assert img[: stack.height // 4].min() == 255 and img[-stack.height // 4:].max() == 0


@pytest.mark.slow
def test_scaffold_slices_agree_with_the_voxels(tmp_path):
    import implicit_scaffold

    r = implicit_scaffold.generate(seeds=60, size=3.0, voxel=0.05, porosity=0.75, mesh=False)
    stack = write_slices(r.field, r.grid, tmp_path / "s")
    assert stack.layers == r.grid.shape[2] and (stack.width, stack.height) == r.grid.shape[:2]
    # pixels = voxels and layers = voxel planes: each layer's solid share is its voxel share
    voxel_share = (r.field < 0).mean(axis=(0, 1))
    assert np.max(np.abs(np.array(stack.solid_share) - voxel_share)) < 0.01
    meta = json.loads((tmp_path / "s" / STACK_JSON).read_text())
    assert meta["layers"] == stack.layers and meta["units"] == "mm"


def test_same_field_same_bytes(tmp_path):
    field, grid = _sphere(h=0.1)
    write_slices(field, grid, tmp_path / "a")
    write_slices(field, grid, tmp_path / "b")
    for fa in sorted((tmp_path / "a").iterdir()):
        assert fa.read_bytes() == (tmp_path / "b" / fa.name).read_bytes()


def test_interrupted_stack_leaves_nothing(tmp_path):
    field, grid = _sphere(h=0.1)

    def stop(done, total):
        if done == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        write_slices(field, grid, tmp_path / "s", progress=stop)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("kwargs, message", [({"pixel": 0}, "--pixel must be a positive"),
                                             ({"layer": -1}, "--layer must be a positive")])
def test_bad_pitch(tmp_path, kwargs, message):
    field, grid = _sphere(h=0.2)
    with pytest.raises(ScaffoldError, match=message):
        write_slices(field, grid, tmp_path / "s", **kwargs)
    assert list(tmp_path.iterdir()) == []


def test_existing_folder_is_not_overwritten(tmp_path):
    field, grid = _sphere(h=0.2)
    (tmp_path / "s").mkdir()
    (tmp_path / "s" / "keep.txt").write_text("x")
    with pytest.raises(ScaffoldError, match="already exists"):
        write_slices(field, grid, tmp_path / "s")
    assert [p.name for p in (tmp_path / "s").iterdir()] == ["keep.txt"]
