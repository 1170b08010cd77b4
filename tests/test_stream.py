"""Stage 7 for large grids: marching cubes slab by slab, streamed to binary STL / PLY.

Oracles: the whole-grid mesh of :func:`mesh_field` (triangle and vertex counts,
volume, and for one slab the very vertices and faces); the sphere's closed-form
volume; trimesh's loaders and its watertight / winding checks; a brute-force count
of the directed edges; the binary STL layout (84 + 50 n bytes); the folder's listing.
Two worker processes are checked against one (itself checked against the whole grid);
the compiled kernels against NumPy's formulas, np.unique and dict counts of the edges.
"""
from __future__ import annotations

import os

import numpy as np
import pytest
import trimesh

from implicit_scaffold.errors import ScaffoldError
from implicit_scaffold.run.grid import Grid
from implicit_scaffold.mesh.marching import mesh_field
from implicit_scaffold.mesh.writers import write_mesh
from implicit_scaffold.mesh.stream import write_mesh_slabs
from implicit_scaffold.run.tiles import ArraySlabs, FieldFile


def coords(grid):
    return np.meshgrid(*grid.axes(), indexing="ij", sparse=True)


def ball(grid, centre, r):
    x, y, z = coords(grid)
    return np.sqrt((x - centre[0]) ** 2 + (y - centre[1]) ** 2 + (z - centre[2]) ** 2) - r


SPHERE_R = 2.5
SPHERE_C = np.array([0.31, -0.17, 0.05])  # off the voxel lattice on purpose


@pytest.fixture(scope="module")
def sphere():
    grid = Grid.covering(SPHERE_C - SPHERE_R - 0.2, SPHERE_C + SPHERE_R + 0.2, 0.1)
    # float32, as the field sources give planes, so that the whole grid meshes the same values
    return ball(grid, SPHERE_C, SPHERE_R).astype(np.float32), grid


@pytest.fixture(scope="module")
def lattice():
    """A lattice-like solid: a gyroid sheet cut by a ball, and a few balls on seeds, on a 57x61x59 grid."""
    grid = Grid((-1.43, -1.5, -1.47), 0.05, (57, 61, 59))
    x, y, z = coords(grid)
    w = 2 * np.pi / 1.1
    gyroid = np.abs(np.sin(w * x) * np.cos(w * y) + np.sin(w * y) * np.cos(w * z)
                    + np.sin(w * z) * np.cos(w * x)) / w - 0.06
    f = np.maximum(gyroid, ball(grid, (0.0, 0.0, 0.0), 1.3))
    rng = np.random.default_rng(3)
    for c in rng.uniform(-1.1, 1.1, (5, 3)):
        f = np.minimum(f, ball(grid, c, 0.2))
    return f.astype(np.float32), grid


def whole_mesh(field, grid, level=0.0):
    return mesh_field(field, grid, level=level)


def one_layer_slabs(grid):
    """max_voxels for slabs of one cube layer (the smallest the look-ahead allows)."""
    return (2 * 9 + 1) * grid.shape[1] * grid.shape[2]


def slab_budgets(grid):
    plane = grid.shape[1] * grid.shape[2]
    # one slab; one cube layer each; 7 layers each (slab ends not aligned with anything)
    return {"one": 10 ** 9, "layers1": one_layer_slabs(grid), "layers7": (2 * 9 + 7) * plane}


def load(path):
    # STL is a triangle soup: process=True merges the coincident vertices
    return trimesh.load(path, process=True)


# ----------------------------------------------------------------------------- closed and equal to the whole grid


@pytest.mark.parametrize("ext", [".stl", ".ply"])
@pytest.mark.parametrize("budget", ["one", "layers1", "layers7"])
@pytest.mark.parametrize("name", ["sphere", "lattice"])
def test_streamed_mesh_is_closed_and_equals_the_whole_grid(request, tmp_path, name, budget, ext):
    field, grid = request.getfixturevalue(name)
    whole = whole_mesh(field, grid)
    path = tmp_path / f"m{ext}"
    s = write_mesh_slabs(ArraySlabs(field, grid), path, max_voxels=slab_budgets(grid)[budget])
    if budget == "layers1":
        assert s["slabs"] == grid.shape[0] - 1
    elif budget == "one":
        assert s["slabs"] == 1
    m = load(path)
    assert m.is_watertight and m.is_winding_consistent
    # the slabs mesh the same cubes the same way: same count (the same bytes: the test below)
    assert s["triangles"] == len(whole.faces) == len(m.faces)
    assert m.volume == pytest.approx(whole.volume, rel=1e-6)
    # the file's own measures: PLY keeps the float64 vertices, STL rounds them to float32
    rel = 1e-9 if ext == ".ply" else 1e-6
    assert s["volume_mm3"] == pytest.approx(m.volume, rel=rel)
    assert s["surface_area_mm2"] == pytest.approx(m.area, rel=rel)
    assert s["watertight"] is True and s["winding_consistent"] is True
    # vertices on the planes two slabs share are counted once, as the whole grid has them
    assert s["vertices"] == len(whole.vertices) == len(m.vertices)
    if ext == ".ply":
        raw = trimesh.load(path, process=False)  # closed as written, without merging
        assert raw.is_watertight and raw.is_winding_consistent
        assert len(raw.vertices) == len(whole.vertices)
        assert raw.volume == pytest.approx(whole.volume, rel=1e-6)
    if name == "sphere":
        # chords of an exact distance at h = 0.1 cut the sphere by h²/(8r) = 5e-4 mm; a
        # shell a tenth of a voxel thick (0.8 mm³) is a generous, independent bound
        exact = 4 / 3 * np.pi * SPHERE_R ** 3
        assert abs(s["volume_mm3"] - exact) < 4 * np.pi * SPHERE_R ** 2 * grid.spacing / 10


@pytest.mark.parametrize("ext", [".stl", ".ply"])
@pytest.mark.parametrize("budget", ["layers1", "layers7"])
def test_every_slab_plan_writes_the_whole_grids_bytes(lattice, tmp_path, budget, ext):
    # a vertex on an x edge is placed from its edge's two values, not from marching cubes' float32
    # x counted from the slab's first plane (whose rounding depended on that plane: some 7 % of the
    # vertices of a 3 mm cube in 4 slabs differed in their last bit, and the STL's bytes with them)
    field, grid = lattice
    whole = whole_mesh(field, grid)
    write_mesh_slabs(ArraySlabs(field, grid), tmp_path / f"slabs{ext}", max_voxels=slab_budgets(grid)[budget])
    if ext == ".stl":
        write_mesh(whole, tmp_path / "whole.stl")
        assert (tmp_path / "whole.stl").read_bytes() == (tmp_path / "slabs.stl").read_bytes()
    else:  # the streamed PLY numbers its vertices slab by slab: its float64 triangles are the whole grid's bits
        m = trimesh.load(tmp_path / "slabs.ply", process=False)
        assert np.array_equal(np.asarray(m.triangles), np.asarray(whole.triangles))


def test_one_slab_gives_the_whole_grid_mesh_exactly(sphere, tmp_path):
    field, grid = sphere
    whole = whole_mesh(field, grid)
    write_mesh_slabs(ArraySlabs(field, grid), tmp_path / "a.ply", max_voxels=10 ** 9)
    m = trimesh.load(tmp_path / "a.ply", process=False)
    assert np.array_equal(np.asarray(m.vertices), np.asarray(whole.vertices))
    assert np.array_equal(np.asarray(m.faces), np.asarray(whole.faces))
    # the STL records are write_mesh's, byte for byte
    write_mesh(whole, tmp_path / "whole.stl")
    write_mesh_slabs(ArraySlabs(field, grid), tmp_path / "a.stl", max_voxels=10 ** 9)
    assert (tmp_path / "a.stl").read_bytes() == (tmp_path / "whole.stl").read_bytes()


def test_many_slabs_equal_one_slab(lattice, tmp_path):
    field, grid = lattice
    one = write_mesh_slabs(ArraySlabs(field, grid), tmp_path / "one.stl", max_voxels=10 ** 9)
    for budget in (one_layer_slabs(grid), one_layer_slabs(grid) + 3 * grid.shape[1] * grid.shape[2]):
        many = write_mesh_slabs(ArraySlabs(field, grid), tmp_path / "many.stl", max_voxels=budget)
        assert many["slabs"] > 10
        assert many["triangles"] == one["triangles"]
        assert many["vertices"] == one["vertices"]
        assert many["volume_mm3"] == pytest.approx(one["volume_mm3"], rel=1e-6)


def test_stl_header_counts_the_records(lattice, tmp_path):
    field, grid = lattice
    path = tmp_path / "m.stl"
    s = write_mesh_slabs(ArraySlabs(field, grid), path, max_voxels=one_layer_slabs(grid))
    data = path.read_bytes()
    n = int(np.frombuffer(data[80:84], "<u4")[0])
    assert n == s["triangles"] > 0
    assert len(data) == 84 + 50 * n
    assert data[:80] == b"binary STL written by implicit_scaffold; units: mm".ljust(80, b" ")


def test_ply_header_is_padded_to_a_fixed_size_and_parses(sphere, tmp_path):
    field, grid = sphere
    path = tmp_path / "m.ply"
    s = write_mesh_slabs(ArraySlabs(field, grid), path, max_voxels=one_layer_slabs(grid))
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    assert header[:2] == ["ply", "format binary_little_endian 1.0"]
    assert f"element vertex {s['vertices']}" in header and f"element face {s['triangles']}" in header
    # header, then float64 vertices, then faces of one count byte and three int32
    assert len(data) == end + 24 * s["vertices"] + 13 * s["triangles"]
    faces = np.frombuffer(data[end + 24 * s["vertices"]:], dtype=[("n", "u1"), ("v", "<i4", (3,))])
    assert np.all(faces["n"] == 3)
    assert faces["v"].min() == 0 and faces["v"].max() == s["vertices"] - 1


def test_field_file_source_gives_the_same_bytes(lattice, tmp_path):
    field, grid = lattice
    budget = one_layer_slabs(grid) + 5 * grid.shape[1] * grid.shape[2]
    with FieldFile(grid, folder=tmp_path) as ff:
        ff.write(0, field)
        write_mesh_slabs(ff, tmp_path / "file.ply", max_voxels=budget)
    write_mesh_slabs(ArraySlabs(field, grid), tmp_path / "array.ply", max_voxels=budget)
    assert (tmp_path / "file.ply").read_bytes() == (tmp_path / "array.ply").read_bytes()
    # the same input gives the same bytes
    write_mesh_slabs(ArraySlabs(field.copy(), grid), tmp_path / "again.ply", max_voxels=budget)
    assert (tmp_path / "again.ply").read_bytes() == (tmp_path / "array.ply").read_bytes()


class CountingReads(ArraySlabs):
    """An in-memory source that records the planes each read asks for."""

    def __init__(self, field, grid):
        super().__init__(field, grid)
        self.reads = []

    def read(self, x0, x1):
        self.reads.append((x0, x1))
        return super().read(x0, x1)


@pytest.mark.parametrize("planes", [19, 20, 26, 200])
def test_each_slab_reads_within_the_budget_and_every_plane_is_read(lattice, tmp_path, planes):
    field, grid = lattice
    plane = grid.shape[1] * grid.shape[2]
    source = CountingReads(field, grid)
    s = write_mesh_slabs(source, tmp_path / "m.stl", max_voxels=planes * plane + plane // 2)
    assert len(source.reads) == s["slabs"]
    assert all((x1 - x0) <= planes for x0, x1 in source.reads)
    # the slabs start where the previous one's cube layers end, and the last reaches the grid's end
    starts = [x0 for x0, _ in source.reads]
    assert starts[0] == 0 and source.reads[-1][1] == grid.shape[0]
    assert all(b > a for a, b in zip(starts, starts[1:]))


def brute_force_closed(faces):
    """Every undirected edge used exactly twice, once each way (dicts over the directed edges)."""
    directed = {}
    for f in np.asarray(faces).tolist():
        for u, v in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0])):
            directed[(u, v)] = directed.get((u, v), 0) + 1
    return all(n == 1 and directed.get((v, u), 0) == 1 for (u, v), n in directed.items())


def test_face_ties_are_broken_the_same_way_in_every_slab(tmp_path):
    # Random -1/0/+1 fields: exact zeros and faces whose saddle lies on the level
    # (corners +1 -1 +1 -1) everywhere, so the tie breaking must give a shared plane
    # the same values in both slabs (global positions, look-ahead planes) or it cracks.
    for seed in range(8):
        rng = np.random.default_rng(seed)
        shape = tuple(int(n) for n in rng.integers(8, 15, 3))
        grid = Grid((0.0, 0.0, 0.0), 0.5, shape)
        field = rng.choice([-1.0, 0.0, 1.0], size=shape) * 0.5
        whole = whole_mesh(field, grid)
        s = write_mesh_slabs(ArraySlabs(field, grid), tmp_path / "t.ply", max_voxels=one_layer_slabs(grid))
        m = trimesh.load(tmp_path / "t.ply", process=False)
        assert brute_force_closed(m.faces)
        assert m.is_watertight and m.is_winding_consistent
        assert s["watertight"] and s["winding_consistent"]
        assert len(m.faces) == len(whole.faces) and len(m.vertices) == len(whole.vertices)
        assert m.volume == pytest.approx(whole.volume, rel=1e-6)


@pytest.mark.parametrize("workers", [None, 2])
def test_summary_reports_an_open_seam(tmp_path, monkeypatch, workers):
    # Break the look-ahead on purpose: the slabs then disagree on the shared planes of a
    # tie-heavy field, and the summary must say so, as the brute-force count does (with two
    # workers too: forked workers inherit the broken look-ahead).
    from implicit_scaffold.mesh import stream as mesh_stream

    monkeypatch.setattr(mesh_stream, "_AHEAD", 1)
    rng = np.random.default_rng(0)
    grid = Grid((0.0, 0.0, 0.0), 0.5, (12, 11, 13))
    field = rng.choice([-1.0, 1.0], size=grid.shape) * 0.5
    s = write_mesh_slabs(ArraySlabs(field, grid), tmp_path / "t.ply", max_voxels=3 * 11 * 13, workers=workers)
    m = trimesh.load(tmp_path / "t.ply", process=False)
    closed = brute_force_closed(m.faces)
    assert not closed  # the fixture tests something
    assert (s["watertight"] and s["winding_consistent"]) is closed
    assert s["watertight"] is m.is_watertight


# ----------------------------------------------------------------------------- progress, interrupts, errors


@pytest.mark.parametrize("ext", [".stl", ".ply"])
def test_progress_counts_slabs_and_an_interrupt_leaves_nothing(sphere, tmp_path, ext):
    field, grid = sphere
    calls = []
    s = write_mesh_slabs(ArraySlabs(field, grid), tmp_path / f"ok{ext}", max_voxels=one_layer_slabs(grid),
                         progress=lambda done, total: calls.append((done, total)))
    n = s["slabs"]
    assert calls == [(k, n) for k in range(1, n + 1)]
    os.remove(tmp_path / f"ok{ext}")

    def interrupt(done, total):
        if done == total // 2:
            raise KeyboardInterrupt  # what Ctrl-C raises mid-run

    with pytest.raises(KeyboardInterrupt):
        write_mesh_slabs(ArraySlabs(field, grid), tmp_path / f"m{ext}", max_voxels=one_layer_slabs(grid),
                         progress=interrupt)
    assert os.listdir(tmp_path) == []

    # an older file of that name is left as it was
    (tmp_path / f"m{ext}").write_bytes(b"old")
    with pytest.raises(KeyboardInterrupt):
        write_mesh_slabs(ArraySlabs(field, grid), tmp_path / f"m{ext}", max_voxels=one_layer_slabs(grid),
                         progress=interrupt)
    assert os.listdir(tmp_path) == [f"m{ext}"]
    assert (tmp_path / f"m{ext}").read_bytes() == b"old"


class NoReads:
    """A source that fails the test if it is read."""

    def __init__(self, grid):
        self.grid = grid

    def read(self, x0, x1):
        raise AssertionError("the field was read before the path was checked")


def test_bad_paths_fail_before_any_work(tmp_path):
    grid = Grid((0.0, 0.0, 0.0), 0.1, (20, 20, 20))
    with pytest.raises(ScaffoldError, match="folder does not exist") as err:
        write_mesh_slabs(NoReads(grid), tmp_path / "missing" / "m.stl", max_voxels=10 ** 6)
    assert "\n" not in str(err.value)
    with pytest.raises(ScaffoldError, match="unknown file type '.obj'"):
        write_mesh_slabs(NoReads(grid), tmp_path / "m.obj", max_voxels=10 ** 6)
    (tmp_path / "dir.stl").mkdir()
    with pytest.raises(ScaffoldError, match="it is a folder"):
        write_mesh_slabs(NoReads(grid), tmp_path / "dir.stl", max_voxels=10 ** 6)
    (tmp_path / "dir.stl").rmdir()
    with pytest.raises(ScaffoldError, match="raise --max-memory"):
        write_mesh_slabs(NoReads(grid), tmp_path / "m.stl", max_voxels=10 * 20 * 20)
    with pytest.raises(ScaffoldError, match="iso-level"):
        write_mesh_slabs(NoReads(grid), tmp_path / "m.stl", level=float("nan"), max_voxels=10 ** 6)
    assert os.listdir(tmp_path) == []


def test_no_solid_raises_once_and_writes_nothing(tmp_path):
    grid = Grid((0.0, 0.0, 0.0), 0.1, (30, 12, 12))
    field = np.ones(grid.shape, np.float32)
    field[0] = -1.0  # solid only in the outer layer, which is forced outside
    for ext in (".stl", ".ply"):
        with pytest.raises(ScaffoldError, match="nothing to mesh"):
            write_mesh_slabs(ArraySlabs(field, grid), tmp_path / f"m{ext}", max_voxels=one_layer_slabs(grid))
    assert os.listdir(tmp_path) == []
    # solid in one slab only: the others have none, and that is no error
    field[14:16, 5:7, 5:7] = -1.0
    s = write_mesh_slabs(ArraySlabs(field, grid), tmp_path / "m.ply", max_voxels=one_layer_slabs(grid))
    m = trimesh.load(tmp_path / "m.ply", process=False)
    assert s["slabs"] == 29 and m.is_watertight and s["triangles"] == len(whole_mesh(field, grid).faces)


def test_nan_is_reported_with_its_planes(tmp_path):
    grid = Grid((0.0, 0.0, 0.0), 0.1, (20, 10, 10))
    field = -np.ones(grid.shape, np.float32)
    field[13, 4, 4] = np.nan
    with pytest.raises(ScaffoldError, match="NaN"):
        write_mesh_slabs(ArraySlabs(field, grid), tmp_path / "m.stl", max_voxels=one_layer_slabs(grid))
    assert os.listdir(tmp_path) == []


# ----------------------------------------------------------------------------- worker processes


def _no_workers_left():
    import multiprocessing

    return multiprocessing.active_children() == []


@pytest.mark.parametrize("ext", [".stl", ".ply"])
def test_two_workers_write_the_bytes_one_writes(lattice, tmp_path, ext):
    # the sequential run (checked against the whole grid above) is the reference
    field, grid = lattice
    plane = grid.shape[1] * grid.shape[2]
    for budget in (one_layer_slabs(grid), one_layer_slabs(grid) + 4 * plane):
        one = write_mesh_slabs(ArraySlabs(field, grid), tmp_path / f"one{ext}", max_voxels=budget, workers=1)
        with FieldFile(grid) as ff:
            ff.write(0, field)
            two = write_mesh_slabs(ff, tmp_path / f"file{ext}", max_voxels=budget, workers=2)
        inherited = write_mesh_slabs(ArraySlabs(field, grid), tmp_path / f"array{ext}", max_voxels=budget,
                                     workers=2)
        assert one["workers"] == 1 and two["workers"] == 2 and inherited["workers"] == 2
        assert one["slabs"] > 5
        reference = (tmp_path / f"one{ext}").read_bytes()
        assert (tmp_path / f"file{ext}").read_bytes() == reference
        assert (tmp_path / f"array{ext}").read_bytes() == reference
        # the sums are added in slab order whoever meshed the slab: the same floats
        assert {k: v for k, v in two.items() if k != "workers"} == {k: v for k, v in one.items() if k != "workers"}
    assert sorted(os.listdir(tmp_path)) == sorted(f"{n}{ext}" for n in ("one", "file", "array"))
    assert _no_workers_left()


def test_small_grids_are_meshed_in_this_process(sphere, tmp_path):
    field, grid = sphere
    s = write_mesh_slabs(ArraySlabs(field, grid), tmp_path / "m.stl", max_voxels=one_layer_slabs(grid))
    assert s["slabs"] > 1 and s["workers"] == 1


def test_two_workers_close_the_tie_heavy_fields(tmp_path):
    for seed in range(3):
        rng = np.random.default_rng(seed)
        shape = tuple(int(n) for n in rng.integers(8, 15, 3))
        grid = Grid((0.0, 0.0, 0.0), 0.5, shape)
        field = rng.choice([-1.0, 0.0, 1.0], size=shape) * 0.5
        s = write_mesh_slabs(ArraySlabs(field, grid), tmp_path / "t.ply", max_voxels=one_layer_slabs(grid),
                             workers=2)
        m = trimesh.load(tmp_path / "t.ply", process=False)
        assert brute_force_closed(m.faces)
        assert s["watertight"] and s["winding_consistent"]
        assert len(m.faces) == len(whole_mesh(field, grid).faces)


@pytest.mark.parametrize("ext", [".stl", ".ply"])
def test_an_interrupt_stops_the_workers_and_leaves_nothing(lattice, tmp_path, ext):
    field, grid = lattice
    calls = []

    def interrupt(done, total):
        calls.append(done)
        if done == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        write_mesh_slabs(ArraySlabs(field, grid), tmp_path / f"m{ext}", max_voxels=one_layer_slabs(grid),
                         progress=interrupt, workers=2)
    assert calls == [1, 2, 3]  # in slab order
    assert os.listdir(tmp_path) == []
    assert _no_workers_left()


def test_a_worker_error_is_raised_in_slab_order_and_leaves_nothing(tmp_path):
    grid = Grid((0.0, 0.0, 0.0), 0.1, (30, 10, 10))
    field = -np.ones(grid.shape, np.float32)
    field[13, 4, 4] = np.nan
    field[25, 4, 4] = np.nan
    raised = []
    for workers in (1, 2):
        with pytest.raises(ScaffoldError, match="NaN values") as err:
            write_mesh_slabs(ArraySlabs(field, grid), tmp_path / "m.ply", max_voxels=one_layer_slabs(grid),
                             workers=workers)
        raised.append(str(err.value))
    # the first slab that reads a NaN (slab 0 reads planes 0..17) names it, as in one process
    assert raised[1] == raised[0] and "x-slab 0.." in raised[0]
    assert os.listdir(tmp_path) == []
    assert _no_workers_left()


def test_a_killed_worker_is_reported_in_one_line(lattice, tmp_path, monkeypatch):
    field, grid = lattice

    def die(self, x0, x1):
        os._exit(3)  # what the system's out-of-memory killer leaves: no message, no result

    monkeypatch.setattr(ArraySlabs, "read", die)  # only the forked workers read
    with pytest.raises(ScaffoldError, match="worker process stopped") as err:
        write_mesh_slabs(ArraySlabs(field, grid), tmp_path / "m.stl", max_voxels=one_layer_slabs(grid), workers=2)
    assert "\n" not in str(err.value)
    assert os.listdir(tmp_path) == []
    assert _no_workers_left()


def test_bad_workers_are_refused(lattice, tmp_path):
    field, grid = lattice
    for bad in (0, 3, 1.5, True):
        with pytest.raises(ScaffoldError, match="workers must be 1 or 2"):
            write_mesh_slabs(ArraySlabs(field, grid), tmp_path / "m.stl", max_voxels=10 ** 9, workers=bad)
    with pytest.raises(ScaffoldError, match="pass workers=1"):
        write_mesh_slabs(CountingReads(field, grid), tmp_path / "m.stl", max_voxels=one_layer_slabs(grid),
                         workers=2)
    assert os.listdir(tmp_path) == []


def test_field_file_opened_read_only_reads_the_planes_and_keeps_the_file(lattice, tmp_path):
    field, grid = lattice
    with FieldFile(grid, folder=tmp_path) as ff:
        ff.write(0, field)
        with FieldFile.open_readonly(ff.path, grid) as reader:
            assert np.array_equal(reader.read(7, 19), field[7:19])
        assert os.path.exists(ff.path)  # the reader's close keeps it
        assert np.array_equal(ff.read(0, 3), field[:3])  # and the writer still reads it
    assert os.listdir(tmp_path) == []


# ----------------------------------------------------------------------------- the compiled kernels


def random_soup(seed, nv=500, nf=3000):
    rng = np.random.default_rng(seed)
    vertices = rng.normal(size=(nv, 3)) * rng.choice([1e-3, 1.0, 1e3], 3)
    faces = rng.integers(0, nv, (nf, 3))
    faces[:3] = [[1, 1, 2], [4, 5, 4], [7, 7, 7]]  # collapsed: zero normal
    return vertices, faces


def test_stl_records_match_numpy(tmp_path):
    import io

    from implicit_scaffold.mesh.writers import _write_stl_records

    rec = np.dtype([("normal", "<f4", (3,)), ("vertex", "<f4", (3, 3)), ("attr", "<u2")])
    for seed in range(3):
        vertices, faces = random_soup(seed)
        out = io.BytesIO()
        _write_stl_records(vertices, faces, out)
        got = np.frombuffer(out.getvalue(), dtype=rec)
        assert len(got) == len(faces)
        tri = vertices[faces]
        assert np.array_equal(got["vertex"], tri.astype(np.float32))
        assert np.all(got["attr"] == 0)
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        length = np.linalg.norm(n, axis=1)
        ok = length > 0
        assert np.allclose(got["normal"][ok], n[ok] / length[ok, None], rtol=0, atol=2e-7)
        assert np.all(got["normal"][~ok] == 0) and (~ok[:3]).all()


def test_face_measures_match_numpy():
    from implicit_scaffold.mesh.marching import face_measures

    for seed in range(3):
        vertices, faces = random_soup(seed)
        ref = np.array([0.3, -0.2, 0.1])
        area, vol = face_measures(vertices, faces, ref=ref)
        a, b, c = (vertices[faces[:, k]] - ref for k in range(3))
        cross = np.cross(b - a, c - a)
        assert np.allclose(area, 0.5 * np.linalg.norm(cross, axis=1), rtol=1e-12, atol=0)
        assert np.allclose(vol, np.einsum("ij,ij->i", a, cross) / 6, rtol=1e-9, atol=1e-12 * np.abs(vol).max())


def brute_force_flags(faces):
    """(watertight, winding consistent) by counting each undirected edge's uses (dicts)."""
    uses = {}
    for f in np.asarray(faces).tolist():
        for u, v in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0])):
            uses.setdefault((min(u, v), max(u, v)), []).append(u > v)
    watertight = all(len(d) == 2 for d in uses.values())
    winding = all(d[0] != d[1] for d in uses.values() if len(d) == 2)
    return watertight, winding


def test_edge_check_matches_brute_force():
    from implicit_scaffold.mesh.marching import compiled_kernels

    edge_check = compiled_kernels()["edge_check"]
    sphere = trimesh.creation.icosphere(2)
    faces = np.asarray(sphere.faces, np.int64)
    nv = len(sphere.vertices)
    rng = np.random.default_rng(0)
    cases = {"closed": faces, "flipped": np.concatenate([faces[:5], faces[5:6, ::-1], faces[6:]]),
             "hole": faces[1:], "doubled": np.concatenate([faces, faces[:1]]),
             "loop edge": np.concatenate([faces, [[3, 3, 4]]]), "soup": rng.integers(0, 40, (200, 3))}
    seen = set()
    for name, f in cases.items():
        for dtype in (np.int64, np.int32):
            flags = edge_check(np.ascontiguousarray(f, dtype), nv, np.zeros(nv, np.int8))[:2]
            assert tuple(flags) == brute_force_flags(f), name
        seen.add(brute_force_flags(f))
    assert len(seen) >= 3  # the cases cover closed, open and badly wound
    # edges with both ends on one plane are returned, not checked; the rest are checked
    plane = np.zeros(nv, np.int8)
    plane[rng.choice(nv, 60, replace=False)] = 1
    plane[rng.choice(np.flatnonzero(plane == 0), 60, replace=False)] = 2
    watertight, winding, first, last = edge_check(faces, nv, plane)
    directed = np.stack([faces.reshape(-1), np.roll(faces, -1, axis=1).reshape(-1)], axis=1)
    for p, rows in ((1, first), (2, last)):
        on = (plane[directed[:, 0]] == p) & (plane[directed[:, 1]] == p)
        assert sorted(map(tuple, rows.tolist())) == sorted(map(tuple, directed[on].tolist()))
    kept = directed[~(((plane[directed[:, 0]] == 1) & (plane[directed[:, 1]] == 1))
                      | ((plane[directed[:, 0]] == 2) & (plane[directed[:, 1]] == 2)))]
    assert len(first) + len(last) > 0 and len(kept) < len(directed)
    # the kept edges of a closed surface alone are still closed: every pair is kept or set aside whole
    assert (watertight, winding) == (True, True)


def test_duplicate_positions_are_found_exactly():
    from implicit_scaffold.mesh.marching import compiled_kernels

    has_duplicates = compiled_kernels()["has_duplicates"]
    rng = np.random.default_rng(1)
    for trial in range(20):
        verts = rng.integers(0, 4, (int(rng.integers(0, 60)), 3)).astype(np.float32)
        expected = len(np.unique(verts.view(np.uint32), axis=0)) < len(verts)
        assert has_duplicates(verts.view(np.uint32)) is expected
    distinct = rng.permutation(np.arange(3000, dtype=np.float32)).reshape(-1, 3)
    assert not has_duplicates(distinct.view(np.uint32))
    assert has_duplicates(np.concatenate([distinct, distinct[17:18]]).view(np.uint32))


@pytest.mark.parametrize("workers", [1, 2])
def test_bodies_are_counted_across_slabs_as_on_the_whole_mesh(tmp_path, workers):
    # two solid balls, one of them hollow (a sealed void: a shell of negative volume), and a
    # U-shaped body whose two arms meet only beyond the slabs that cut them apart
    grid = Grid.covering((-4.0, -2.5, -2.5), (4.0, 2.5, 2.5), 0.1)
    x, y, z = coords(grid)
    first = ball(grid, (-2.5, 0.0, 0.0), 1.2)
    hollow = np.maximum(ball(grid, (1.0, -1.2, 0.0), 1.0), -ball(grid, (1.0, -1.2, 0.0), 0.5))
    arm = lambda yc: np.maximum(np.maximum(np.abs(y - yc) - 0.3, np.abs(z) - 0.3), np.abs(x - 2.2) - 1.4)  # noqa: E731
    base = np.maximum(np.maximum(np.abs(x - 3.4) - 0.3, np.abs(y - 1.0) - 0.9), np.abs(z) - 0.3)
    u = np.minimum(np.minimum(arm(0.4), arm(1.6)), base)
    field = np.minimum(np.minimum(first, hollow), u).astype(np.float32)
    whole = mesh_field(field, grid)
    pieces = [m for m in whole.split(only_watertight=True)]
    assert sum(m.volume > 0 for m in pieces) == 3 and sum(m.volume < 0 for m in pieces) == 1  # trimesh's count
    s = write_mesh_slabs(ArraySlabs(field, grid), tmp_path / "m.ply", max_voxels=4 * grid.shape[1] * grid.shape[2]
                         + 20 * grid.shape[1] * grid.shape[2], workers=workers)
    assert s["slabs"] > 3 and s["watertight"]
    assert s["bodies"] == 3
    streamed = trimesh.load(tmp_path / "m.ply", process=False)
    assert sum(m.volume > 0 for m in streamed.split(only_watertight=True)) == 3


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_surface_pieces_number_as_scipy_does(seed):
    # random triangles over shuffled vertex numbers (many pieces, some vertices in no
    # triangle), against scipy's connected components of the edge graph
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from implicit_scaffold.mesh.stream import _surface_pieces

    rng = np.random.default_rng(seed)
    nverts = 3000
    faces = rng.integers(0, nverts, (1200, 3)).astype(np.int32)
    a = np.concatenate([faces[:, 0], faces[:, 1]])
    b = np.concatenate([faces[:, 1], faces[:, 2]])
    expect_count, expect = connected_components(
        coo_matrix((np.ones(len(a)), (a, b)), shape=(nverts, nverts)), directed=False)
    count, labels = _surface_pieces(faces, nverts)
    assert 100 < count == expect_count
    np.testing.assert_array_equal(labels, expect)
