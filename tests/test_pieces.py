"""A patient in several pieces: each piece keeps its scaffold (issue 17)."""
from __future__ import annotations

import numpy as np
import pytest

import implicit_scaffold
from implicit_scaffold.errors import ScaffoldWarning
from implicit_scaffold.run.grid import evaluate_by_slabs


class _Union:
    """A patient made of analytic parts: the minimum of their signed distances (as patient.py's
    primitives, but placed anywhere); its volume is the parts' sum (their interiors do not overlap)."""

    def __init__(self, parts):
        self.parts = parts
        self.lo = np.min([p[1] for p in parts], axis=0)
        self.hi = np.max([p[2] for p in parts], axis=0)
        self.volume = float(sum(p[3] for p in parts))

    def sdf_axes(self, x, y, z):
        return np.minimum.reduce([p[0](x, y, z) for p in self.parts])

    def sdf_grid(self, grid, x_range=None):
        return evaluate_by_slabs(grid, self.sdf_axes, max_voxels=4_000_000, x_range=x_range)


def _ball(c, r):
    c = np.asarray(c, float)
    return (lambda x, y, z: np.sqrt((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2) - r,
            c - r, c + r, 4 / 3 * np.pi * r ** 3)


def _box(lo, hi):
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    mid, half = (lo + hi) / 2, (hi - lo) / 2

    def sdf(x, y, z):
        q = [np.abs(c - m) - h for c, m, h in zip((x, y, z), mid, half)]
        out = np.sqrt(sum(np.maximum(v, 0) ** 2 for v in q))
        return out + np.minimum(np.maximum(np.maximum(q[0], q[1]), q[2]), 0)

    return sdf, lo, hi, float(np.prod(hi - lo))


def _per_part(r, parts):
    """Brute force: porosity and voxels of each part, from the built field and the part's own distance."""
    x, y, z = r.grid.axes()
    X, Y, Z = np.meshgrid(x, y, z, indexing="ij")
    rows = []
    for p in parts:
        inside = p[0](X, Y, Z) < 0
        rows.append((1.0 - np.count_nonzero(r.field[inside] < 0) / np.count_nonzero(inside),
                     int(np.count_nonzero(inside))))
    return rows


def test_two_separate_balls_each_keep_their_scaffold():
    # before: the smaller solid body (the second ball's scaffold) was removed as a fragment
    parts = [_ball([3, 3, 3], 2.5), _ball([10, 3, 3], 2.0)]
    r = implicit_scaffold.generate(patient=_Union(parts), pore_size=1.0, porosity=0.7, voxel=0.1,
                                   morphometry=False)
    rep = r.report
    for porosity, _ in _per_part(r, parts):
        # each ball's own porosity near the target: its scaffold is there, not removed (~60-80
        # cells per ball: the local porosity wanders by a few points around the global level)
        assert abs(porosity - 0.7) < 0.05
    assert rep["bodies"] == 2 and rep["patient_pieces_count"] == 2
    # the report's table against the brute force, piece by piece (the larger ball first)
    for row, (porosity, voxels) in zip(rep["patient_pieces"], _per_part(r, parts)):
        assert row["volume_mm3"] == pytest.approx(voxels * r.grid.voxel_volume)
        assert row["porosity_voxel"] == pytest.approx(porosity) and row["bodies"] == 1
    assert sum(row["cells"] for row in rep["patient_pieces"]) == rep["cells_in_scaffold"]


def test_two_boxes_touching_along_a_face_each_keep_their_scaffold():
    parts = [_box([0, 0, 0], [4, 4, 4]), _box([4, 0.5, 0.5], [7, 3.5, 3.5])]
    r = implicit_scaffold.generate(patient=_Union(parts), pore_size=1.0, porosity=0.7, voxel=0.1,
                                   morphometry=False)
    for porosity, _ in _per_part(r, parts):
        assert abs(porosity - 0.7) < 0.05
    # one piece of patient (the boxes share a face), one body across it
    assert r.report["patient_pieces_count"] == 1 and r.report["bodies"] == 1


def test_a_piece_smaller_than_one_pore_is_warned_about():
    # a 0.3 mm ball beside a 5 mm one, 1 mm pores: it cannot hold a pore, and the run says so
    parts = [_ball([3, 3, 3], 2.5), _ball([7, 3, 3], 0.3)]
    with pytest.warns(ScaffoldWarning, match=r"1 of the patient's 2 pieces .* smaller than one 1 mm pore"):
        r = implicit_scaffold.generate(patient=_Union(parts), pore_size=1.0, porosity=0.7, voxel=0.1,
                                       morphometry=False, mesh=False)
    assert any("cannot hold a pore" in w for w in r.report["warnings"])


def test_one_pore_sized_pieces_raise_no_warning():
    # the trigger's other side: two balls each far larger than a pore
    parts = [_ball([3, 3, 3], 2.5), _ball([10, 3, 3], 2.5)]
    r = implicit_scaffold.generate(patient=_Union(parts), pore_size=1.0, porosity=0.7, voxel=0.1,
                                   morphometry=False, mesh=False)
    assert not any("pore" in w and "pieces" in w for w in r.report["warnings"])


def test_main_body_per_piece_against_brute_force():
    from scipy import ndimage

    from implicit_scaffold.run.pieces import remove_fragments_by_piece

    rng = np.random.default_rng(3)
    field = rng.normal(0.3, 1.0, (30, 20, 16)).astype(np.float32)
    pieces = np.zeros(field.shape, np.int32)
    pieces[:14], pieces[15:] = 1, 2  # two patient pieces apart by one plane; no solid outside them
    field[14] = 1.0
    out = field.copy()
    remove_fragments_by_piece(out, pieces, outside=1.0)
    # brute force: each piece on its own, its largest solid piece kept (first in C order on a tie)
    want = field.copy()
    for k in (1, 2):
        lab, n = ndimage.label((field < 0) & (pieces == k))
        sizes = [np.count_nonzero(lab == i) for i in range(1, n + 1)]
        main = 1 + int(np.argmax(sizes))
        want[(lab > 0) & (lab != main)] = 1.0
    assert np.array_equal(out, want)


@pytest.mark.parametrize("planes", [9, 40])
def test_a_tiled_run_keeps_each_pieces_scaffold_with_the_whole_grid_bytes(tmp_path, planes):
    # the patient's pieces are joined across slabs as the solid's are: each keeps its main body,
    # with slabs that cut through both balls and the gap between them
    parts = [_ball([3, 3, 3], 2.5), _ball([10, 3, 3], 2.0)]
    kw = dict(pore_size=1.0, porosity=0.7, voxel=0.1, mesh=False, morphometry=False)
    whole = implicit_scaffold.generate(patient=_Union(parts), output=tmp_path / "w.npy", tiled=False, **kw)
    plane = whole.grid.shape[1] * whole.grid.shape[2]
    tiled = implicit_scaffold.generate(patient=_Union(parts), output=tmp_path / "t.npy",
                                       tiled=(planes + 10) * plane, **kw).report
    assert tiled["tiled"]["slabs"] > 2
    assert (tmp_path / "t.npy").read_bytes() == (tmp_path / "w.npy").read_bytes()
    assert tiled["fragments_removed"] == whole.report["fragments_removed"] > 0
    assert tiled["patient_pieces_count"] == whole.report["patient_pieces_count"] == 2
    assert tiled["bodies_voxels"] == 2
    # the pieces' table, slab by slab, is the whole grid's
    assert tiled["patient_pieces"] == whole.report["patient_pieces"]


@pytest.mark.parametrize("main_bodies_only", [False, True])
@pytest.mark.parametrize("planes", [1, 3, 7, 40])
def test_the_pieces_table_by_slabs_is_the_whole_grids(planes, main_bodies_only):
    from scipy import ndimage

    from implicit_scaffold.run.grid import Grid
    from implicit_scaffold.run.pieces import label_pieces, piece_table, piece_table_by_slabs
    from implicit_scaffold.run.tiles import ArraySlabs

    rng = np.random.default_rng(11)
    grid = Grid(origin=(0.0, 0.0, 0.0), spacing=0.1, shape=(33, 21, 18))
    # smoothed noise: patient pieces and solid pieces that wind across the slabs' faces
    patient = ndimage.gaussian_filter(rng.normal(size=grid.shape), 1.5).astype(np.float32)
    patient = patient - np.float32(np.percentile(patient, 20))
    field = np.maximum(ndimage.gaussian_filter(rng.normal(size=grid.shape), 1.0).astype(np.float32), patient)
    seeds = rng.uniform(0, np.asarray(grid.shape) * 0.1, (300, 3))
    labels, count = label_pieces(patient < 0)
    assert count >= 4  # the test's premise: several pieces
    solid = field < 0
    want = piece_table(labels, count, solid, grid, seeds, main_bodies_only=main_bodies_only)
    got = piece_table_by_slabs(ArraySlabs(field, grid), ArraySlabs(patient, grid), grid, seeds,
                               max_voxels=planes * grid.shape[1] * grid.shape[2], main_bodies_only=main_bodies_only)
    assert got == want


def test_the_prisms_pieces_by_slabs_are_the_whole_grids():
    from scipy import ndimage

    from implicit_scaffold.run.grid import Grid
    from implicit_scaffold.run.pieces import label_pieces
    from implicit_scaffold.run.tiled import prism_pieces
    from implicit_scaffold.run.tiles import FieldFile, plan_slabs

    rng = np.random.default_rng(5)
    grid = Grid(origin=(0.0, 0.0, 0.0), spacing=0.1, shape=(30, 24, 20))
    patient = ndimage.gaussian_filter(rng.normal(size=grid.shape), 1.5).astype(np.float32)
    patient -= np.float32(np.percentile(patient, 25))
    ys, zs = slice(6, 13), slice(0, 20)
    want = label_pieces(patient < 0)[0][:, ys, zs]
    assert len(np.unique(want)) > 3  # several pieces cross the prism
    with FieldFile(grid) as f:
        f.write(0, patient)
        slabs = plan_slabs(grid.shape, max_voxels=4 * 24 * 20, halo=0)
        assert np.array_equal(prism_pieces(f, slabs, ys, zs), want)


def test_a_patient_in_pieces_gets_the_same_printed_level_in_slabs(tmp_path):
    # the level solved for the mesh keeps each piece's main body on the calibration prism, in
    # memory and in slabs alike (the STL's bytes differ in the last bit of some vertices: marching
    # cubes places them slab-locally; the level and the counts do not)
    parts = [_ball([3, 3, 3], 2.5), _ball([10, 3, 3], 2.0)]
    kw = dict(pore_size=1.0, porosity=0.7, voxel=0.1, morphometry=False)
    whole = implicit_scaffold.generate(patient=_Union(parts), output=tmp_path / "w.stl", tiled=False, **kw).report
    plane = round(5.2 / 0.1 + 3) ** 2
    tiled = implicit_scaffold.generate(patient=_Union(parts), output=tmp_path / "t.stl", tiled=30 * plane,
                                       **kw).report
    assert tiled["tiled"]["slabs"] > 2 and whole["printed_level"]["by"] == "mesh"
    assert tiled["surface_offset_mm"] == whole["surface_offset_mm"]
    assert tiled["triangles"] == whole["triangles"] and tiled["bodies"] == whole["bodies"] == 2


@pytest.mark.parametrize("shape", ["sphere", "cylinder"])
def test_a_primitives_one_row_in_slabs_is_the_whole_grids(shape):
    # a primitive's row comes from the passes' counts, in memory and in slabs; the oracle labels
    # the finished grid's patient and solid and reads the table off them
    from implicit_scaffold.fields.field import sample
    from implicit_scaffold.run.pieces import label_pieces, piece_table

    kw = dict(shape=shape, size=4, pore_size=0.8, porosity=0.7, voxel=0.08, mesh=False, morphometry=False)
    whole = implicit_scaffold.generate(tiled=False, **kw)
    plane = whole.grid.shape[1] * whole.grid.shape[2]
    tiled = implicit_scaffold.generate(tiled=12 * plane, **kw)
    assert tiled.report["tiled"]["slabs"] > 2
    s, s_p = np.asarray(whole.field), np.asarray(whole.patient_sdf)
    labels, count = label_pieces(s_p < 0)
    seeds = whole.cells.seeds[sample(s_p, whole.grid, whole.cells.seeds) < 0]
    want = piece_table(labels, count, s < 0, whole.grid, seeds)
    assert count == 1 and want[0]["bodies"] == 1
    assert whole.report["patient_pieces"] == want
    assert tiled.report["patient_pieces"] == want


def test_label_sizes_count_as_bincount_does():
    from implicit_scaffold.run.pieces import label_pieces, label_sizes

    rng = np.random.default_rng(5)
    labels, count = label_pieces(rng.random((23, 17, 31)) < 0.4)
    assert count > 10
    np.testing.assert_array_equal(label_sizes(labels, count), np.bincount(labels.ravel(), minlength=count + 1))
    where = rng.random(labels.shape) < 0.5
    np.testing.assert_array_equal(label_sizes(labels, count, where=where),
                                  np.bincount(labels[where], minlength=count + 1))
    # long runs of one label (counted run by run), a run through the last voxel, one voxel, none
    blobs, n = label_pieces((np.arange(40) % 9 < 6)[:, None, None] & np.ones((12, 50), bool))
    assert n > 2 and blobs.reshape(-1)[-1] > 0
    np.testing.assert_array_equal(label_sizes(blobs, n), np.bincount(blobs.ravel(), minlength=n + 1))
    np.testing.assert_array_equal(label_sizes(np.array([[[3]]], np.int32), 3), [0, 0, 0, 1])
    np.testing.assert_array_equal(label_sizes(np.zeros((0, 4, 4), np.int32), 2), [0, 0, 0])


@pytest.mark.parametrize("contiguous", [True, False])
def test_paint_labels_writes_what_a_boolean_mask_writes(contiguous):
    from implicit_scaffold.run.pieces import label_pieces, paint_labels

    rng = np.random.default_rng(4)
    labels, count = label_pieces(rng.random((23, 19, 17)) < 0.4)
    table = rng.random(count + 1) < 0.3
    table[0] = False
    field = rng.normal(size=labels.shape).astype(np.float32)
    want = field.copy()
    want[table[labels]] = 7.5
    got = field.copy() if contiguous else np.asfortranarray(field)
    assert paint_labels(labels, table, got, 7.5) == np.count_nonzero(table[labels]) > 0
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("below", [True, False])
def test_flood_paint_paints_the_pieces_of_its_seeds(below):
    from scipy import ndimage

    from implicit_scaffold.run.pieces import flood_paint

    rng = np.random.default_rng(5)
    # shifted so that the painted side is the sparse one: many pieces of it
    noise = ndimage.gaussian_filter(rng.normal(size=(30, 21, 17)), 1.2)
    field = (noise + (0.05 if below else -0.05)).astype(np.float32)
    mask = field < 0 if below else field >= 0
    labels, count = ndimage.label(mask)  # the oracle: scipy's 6-connected pieces
    assert count > 5  # several pieces, most of them left as they are
    seeds = rng.choice(np.flatnonzero(mask), 4, replace=False)
    seeds = np.concatenate([seeds, seeds[:3]])  # a seed met twice paints once
    value = 2.0 if below else -2.0
    want = field.copy()
    want[np.isin(labels, labels.ravel()[seeds])] = value
    got = field.copy()
    assert flood_paint(got, seeds, value, below=below) == np.count_nonzero(want != field)
    assert np.array_equal(got, want)
    with pytest.raises(ValueError):
        flood_paint(field.copy(), seeds, -value, below=below)


def test_label_sizes_first_gives_the_sizes_and_first_voxels():
    from scipy import ndimage

    from implicit_scaffold.run.pieces import label_sizes_first

    rng = np.random.default_rng(6)
    labels, count = ndimage.label(ndimage.gaussian_filter(rng.normal(size=(20, 15, 11)), 1.0) < 0)
    labels = labels.astype(np.int32)
    labels[labels == 3] = 0  # a label absent: no first voxel
    sizes, first = label_sizes_first(labels, count)
    assert np.array_equal(sizes, np.bincount(labels.ravel(), minlength=count + 1))
    values, where = np.unique(labels.ravel(), return_index=True)
    want = np.full(count + 1, -1)
    want[values] = where
    assert np.array_equal(first, want)


def _hollow_ball(c, r_out, r_in):
    """A ball with a closed spherical cavity: outside the patient, yet enclosed by it."""
    c = np.asarray(c, float)

    def sdf(x, y, z):
        d = np.sqrt((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2)
        return np.maximum(d - r_out, r_in - d)

    return sdf, c - r_out, c + r_out, 4 / 3 * np.pi * (r_out ** 3 - r_in ** 3)


@pytest.mark.parametrize("skin", [0.0, 0.12])
def test_a_one_piece_patients_row_from_the_passes_counts_is_the_whole_grids(skin):
    # a patient (not a primitive) the passes find in one piece: its row from their counts; with a
    # skin, its closed cavity (outside the patient) is a sealed void filled, which the row must not
    # count as the patient's solid. The oracle labels the finished grid's patient and reads the table
    from implicit_scaffold.fields.field import sample
    from implicit_scaffold.run.pieces import label_pieces, piece_table

    patient = _Union([_hollow_ball([3, 3, 3], 2.6, 0.9)])
    kw = dict(pore_size=0.8, porosity=0.7, voxel=0.08, mesh=False, morphometry=False, skin=skin)
    whole = implicit_scaffold.generate(patient=patient, tiled=False, **kw)
    plane = whole.grid.shape[1] * whole.grid.shape[2]
    tiled = implicit_scaffold.generate(patient=patient, tiled=14 * plane, **kw)
    assert tiled.report["tiled"]["slabs"] > 2
    assert "pieces" not in tiled.timings  # the row from the passes' counts, without the stage
    s, s_p = np.asarray(whole.field), np.asarray(whole.patient_sdf)
    assert np.array_equal(np.asarray(tiled.field), s)
    if skin:
        assert np.count_nonzero((s < 0) & (s_p >= 0)) > 0  # the cavity, filled
    labels, count = label_pieces(s_p < 0)
    seeds = whole.cells.seeds[sample(s_p, whole.grid, whole.cells.seeds) < 0]
    want = piece_table(labels, count, s < 0, whole.grid, seeds)
    assert count == 1
    assert whole.report["patient_pieces"] == want
    assert tiled.report["patient_pieces"] == want


@pytest.mark.parametrize("tiled", [False, 30 * 52 * 52])
def test_fragments_are_the_pieces_besides_each_patient_pieces_main_body(tiled):
    # two balls, each keeping its scaffold's main body: no fragment (the whole grid's pieces besides
    # one read 1); the oracle: the built solid's 6-connected pieces, counted by SciPy, less the patient's
    from scipy import ndimage

    parts = [_ball([3, 3, 3], 2.5), _ball([10, 3, 3], 2.0)]
    r = implicit_scaffold.generate(patient=_Union(parts), pore_size=1.0, porosity=0.7, voxel=0.1, tiled=tiled)
    inside = r.patient_sdf < 0
    _, pieces = ndimage.label((r.field < 0) & inside)
    assert r.report["fragments"] == pieces - 2 == 0


def test_the_speck_advice_fits_a_mesh_patient(tmp_path):
    # a mesh has no --threshold: the advice names what removes a mesh's specks
    import trimesh

    from implicit_scaffold.io.patient_io import load_patient

    big = trimesh.creation.icosphere(subdivisions=3, radius=2.5)
    big.apply_translation([3, 3, 3])
    speck = trimesh.creation.icosphere(subdivisions=2, radius=0.3)
    speck.apply_translation([7, 3, 3])
    path = tmp_path / "two.stl"
    trimesh.util.concatenate([big, speck]).export(path)
    with pytest.warns(ScaffoldWarning) as seen:
        implicit_scaffold.generate(patient=load_patient(path), pore_size=1.0, porosity=0.7, voxel=0.1,
                                   morphometry=False, mesh=False)
    text = [str(w.message) for w in seen if "cannot hold a pore" in str(w.message)]
    assert len(text) == 1 and "--threshold" not in text[0] and "from the mesh" in text[0]


@pytest.mark.parametrize("source, words", [
    ({"file": "/x/bone.stl", "threshold": None, "label": None}, "from the mesh"),
    ({"file": "/x/ct.nii.gz", "threshold": 300.0, "label": None}, "a higher --threshold"),
    ({"file": "/x/seg.nii.gz", "threshold": None, "label": [31]}, "from the segmentation"),
    (None, "from the patient")])
def test_the_speck_advice_names_the_inputs_own_remedy(source, words):
    from implicit_scaffold.run.pieces import speck_remedy

    said = speck_remedy(source)
    assert words in said
    assert ("--threshold" in said) == (words == "a higher --threshold")


def test_a_mesh_patient_smaller_than_one_pore_is_asked_for_its_unit():
    from implicit_scaffold.run.pieces import speck_remedy

    mesh = {"file": "/x/femur_m.stl", "threshold": None, "label": None}
    assert "--units" in speck_remedy(mesh, whole=True)
    assert "--units" not in speck_remedy(mesh)
