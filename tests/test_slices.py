"""Printer slices: layer images against the field and against a sphere's closed-form sections."""
import json

import numpy as np
import pytest
from PIL import Image

from implicit_scaffold.errors import ScaffoldError
from implicit_scaffold.run.grid import Grid
from implicit_scaffold.mesh.slices import STACK_JSON, write_slices


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


# --- slab by slab (a field read in x-slabs from a field source) ---------------------------

def _wavy(seed=4, shape=(23, 19, 17), h=0.09):
    """A random-ish analytic field on an odd grid: a ball rippled by seeded plane waves."""
    rng = np.random.default_rng(seed)
    grid = Grid((0.13, -0.41, 0.27), h, shape)
    x, y, z = np.meshgrid(*grid.axes(), indexing="ij")
    centre = (grid.lo + grid.hi) / 2
    field = np.sqrt((x - centre[0]) ** 2 + (y - centre[1]) ** 2 + (z - centre[2]) ** 2) - 0.35 * shape[1] * h
    for _ in range(4):
        k = rng.normal(0.0, 2.0 / h, 3)
        field = field + 0.6 * h * np.sin(k[0] * x + k[1] * y + k[2] * z + rng.uniform(0, 2 * np.pi))
    return field.astype(np.float32), grid


def _same_folders(a, b):
    names = sorted(p.name for p in a.iterdir())
    assert names == sorted(p.name for p in b.iterdir())
    for name in names:
        assert (a / name).read_bytes() == (b / name).read_bytes(), name
    return names


@pytest.mark.parametrize("make, pixel, layer", [
    (lambda: _sphere(h=0.1), None, None),
    (lambda: _sphere(h=0.1), 0.043, 0.13),
    (_wavy, None, None),
    (_wavy, 0.031, 0.05),  # pixels smaller than voxels: the first columns lie left of the first plane
    (_wavy, 0.23, 0.07),   # pixels wider than voxels: some slabs own no column
])
def test_slabs_give_the_same_bytes_as_the_array(tmp_path, make, pixel, layer):
    from implicit_scaffold.run.tiles import ArraySlabs

    field, grid = make()
    plane = grid.shape[1] * grid.shape[2]
    whole = write_slices(field, grid, tmp_path / "whole", pixel=pixel, layer=layer)
    # one plane per slab (plus one halo plane on either side), a few planes, and all of them
    for max_voxels in (3 * plane, 6 * plane + 7, field.size + 2 * plane):
        out = tmp_path / f"slabs{max_voxels}"
        stack = write_slices(ArraySlabs(field, grid), None, out, pixel=pixel, layer=layer, max_voxels=max_voxels)
        assert stack == whole
        names = _same_folders(tmp_path / "whole", out)
        assert names == sorted([STACK_JSON] + [whole.files.format(k) for k in range(whole.layers)])


def test_slabs_from_a_field_file(tmp_path):
    from implicit_scaffold.run.tiles import FieldFile

    field, grid = _wavy(seed=9, shape=(21, 16, 13))
    whole = write_slices(field, grid, tmp_path / "whole", pixel=0.05, layer=0.06)
    (tmp_path / "disk").mkdir()
    with FieldFile(grid, folder=tmp_path / "disk") as source:
        source.write(0, field[:8])
        source.write(8, field[8:])
        stack = write_slices(source, grid, tmp_path / "slabs", pixel=0.05, layer=0.06,
                             max_voxels=5 * 16 * 13)
    assert stack == whole
    _same_folders(tmp_path / "whole", tmp_path / "slabs")
    assert json.loads((tmp_path / "slabs" / STACK_JSON).read_text())["solid_share"] == list(whole.solid_share)


def test_float64_array_with_a_bound_reads_slabs_with_the_same_bytes(tmp_path):
    field, grid = _wavy(seed=6)
    field = field.astype(np.float64)
    calls = []
    whole = write_slices(field, grid, tmp_path / "whole", pixel=0.07, layer=0.05)
    stack = write_slices(field, grid, tmp_path / "slabs", pixel=0.07, layer=0.05, max_voxels=5 * 19 * 17,
                         progress=lambda done, total: calls.append(total))
    assert stack == whole and calls[0] == 8 + whole.layers  # 23 planes in slabs of 3: read by slabs
    _same_folders(tmp_path / "whole", tmp_path / "slabs")


def test_slab_layers_agree_with_the_voxels(tmp_path):
    # pixels = voxels and layers = voxel planes: each layer samples its voxel plane at the voxel
    # centres, so its solid share is the plane's share of negative voxels (NumPy on the field)
    from implicit_scaffold.run.tiles import ArraySlabs

    field, grid = _wavy(seed=2, shape=(30, 27, 25), h=0.05)
    stack = write_slices(ArraySlabs(field, grid), None, tmp_path / "s", max_voxels=4 * 27 * 25)
    assert (stack.width, stack.height, stack.layers) == grid.shape
    voxel_share = (field < 0).mean(axis=(0, 1))
    assert 0.05 < voxel_share.mean() < 0.95  # a real mix of solid and void
    assert np.max(np.abs(np.array(stack.solid_share) - voxel_share)) < 0.01
    # and the images say the same as stack.json
    images = _layers(tmp_path / "s", stack)
    assert [float(np.mean(img >= 128)) for img in images] == pytest.approx(stack.solid_share, abs=1e-12)


def test_slab_progress_counts_slabs_then_layers(tmp_path):
    from implicit_scaffold.run.tiles import ArraySlabs

    field, grid = _wavy()
    calls = []
    stack = write_slices(ArraySlabs(field, grid), None, tmp_path / "s", max_voxels=3 * 19 * 17,
                         progress=lambda done, total: calls.append((done, total)))
    total = grid.shape[0] + stack.layers  # one plane per slab
    assert calls == [(i, total) for i in range(1, total + 1)]


@pytest.mark.parametrize("stop_at", [2, 30])  # while sampling the slabs, while encoding the layers
def test_interrupted_slab_run_leaves_nothing(tmp_path, stop_at):
    from implicit_scaffold.run.tiles import FieldFile

    field, grid = _wavy()
    out = tmp_path / "out"
    out.mkdir()

    def stop(done, total):
        if done == stop_at:
            raise KeyboardInterrupt

    with FieldFile(grid, folder=tmp_path) as source:
        source.write(0, field)
        with pytest.raises(KeyboardInterrupt):
            write_slices(source, None, out / "s", max_voxels=3 * 19 * 17, progress=stop)
    assert list(out.iterdir()) == []  # no stack, no temporary folder, no scratch file
    assert list(tmp_path.iterdir()) == [out]


@pytest.mark.parametrize("kwargs, message", [({"max_voxels": 2 * 19 * 17}, "one slab of the grid needs"),
                                             ({"max_voxels": 0}, "max_voxels must be a positive"),
                                             ({"max_voxels": 1.5e6}, "max_voxels must be a positive")])
def test_bad_slab_bound(tmp_path, kwargs, message):
    from implicit_scaffold.run.tiles import ArraySlabs

    field, grid = _wavy()
    with pytest.raises(ScaffoldError, match=message):
        write_slices(ArraySlabs(field, grid), None, tmp_path / "s", **kwargs)
    assert list(tmp_path.iterdir()) == []


def test_source_with_another_grid(tmp_path):
    from implicit_scaffold.run.tiles import ArraySlabs

    field, grid = _wavy()
    other = Grid(grid.origin, grid.spacing * 2, grid.shape)
    with pytest.raises(ScaffoldError, match="grid"):
        write_slices(ArraySlabs(field, grid), other, tmp_path / "s")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("pixel, layer", [(0.09, 0.09), (0.033, 0.07), (0.021, 0.013)])
def test_grey_columns_match_scipy_bilinear_samples(pixel, layer):
    # the compiled sampler against SciPy's map_coordinates on blended planes (layer_coverage)
    from implicit_scaffold.mesh.slices import _grey, _layer_planes, _pixel_indices, grey_columns, layer_coverage, \
        stack_geometry

    field, grid = _wavy(seed=7, shape=(26, 21, 19), h=0.09)
    origin, (width, height, layers) = stack_geometry(grid, pixel, layer)
    ix, iy = _pixel_indices(grid, pixel, origin, width, height)
    heights = [origin[2] + (k + 0.5) * layer for k in range(layers)]
    grey = grey_columns(field, ix, iy, [_layer_planes(grid, z) for z in heights], pixel)
    ref = np.stack([_grey(layer_coverage(field, grid, z, pixel, origin, width, height)).T for z in heights])
    assert 0 < np.count_nonzero(ref) < ref.size and np.count_nonzero((ref > 0) & (ref < 255)) > 0
    np.testing.assert_array_equal(grey, ref)
