"""Slabs give what the whole grid gives: the offset level and the fragments, bit for bit."""
import os

import numpy as np
import pytest
from scipy import ndimage

from implicit_scaffold.errors import ScaffoldError
from implicit_scaffold.fields.field import level_between, remove_fragments, solve_level
from implicit_scaffold.run.tiles import (SlabComponents, StreamQuantile, level_ranks,
                                     plan_slabs)


def test_slabs_cover_every_plane_once_within_the_budget():
    shape = (37, 11, 13)
    slabs = plan_slabs(shape, max_voxels=9 * 11 * 13, halo=2)
    owned = np.concatenate([np.arange(s.x0, s.x1) for s in slabs])
    assert np.array_equal(owned, np.arange(37))
    for s in slabs:
        assert (s.h1 - s.h0) * 11 * 13 <= 9 * 11 * 13
        assert s.h0 == max(0, s.x0 - 2) and s.h1 == min(37, s.x1 + 2)


def test_no_plane_fits():
    with pytest.raises(ScaffoldError, match="raise --max-memory"):
        plan_slabs((10, 100, 100), max_voxels=20_000, halo=1)


def _random_values(rng, n):
    v = rng.normal(0, 0.2, n).astype(np.float32)
    v[rng.integers(0, n, n // 20)] = 0.0            # ties at zero, both signs
    v[rng.integers(0, n, n // 50)] = -0.0
    v[rng.integers(0, n, n // 20)] = np.float32(0.25)  # a clamped value, repeated
    return v


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_stream_quantile_is_exact(seed):
    rng = np.random.default_rng(seed)
    v = _random_values(rng, 50_000)
    ranks = sorted(rng.integers(0, v.size, 4).tolist()) + [0, v.size - 1]
    cuts = np.sort(rng.integers(0, v.size, 6))
    q = StreamQuantile()
    for part in np.split(v, cuts):
        q.count(part)
    q.select(*ranks)
    for part in np.split(v[::-1], cuts):   # pass 2 in another order
        q.refine(part)
    expected = np.sort(v)[ranks]
    assert np.array_equal(np.array(q.values(), np.float32), expected)


def test_level_equals_solve_level_bit_for_bit():
    rng = np.random.default_rng(5)
    field = ndimage.gaussian_filter(rng.normal(size=(40, 30, 20)), 2).astype(np.float32)
    inside = ndimage.gaussian_filter(rng.normal(size=field.shape), 3) < 0.02
    slabs = plan_slabs(field.shape, max_voxels=7 * 30 * 20, halo=0)
    for porosity in (0.3, 0.8, 0.97):
        q = StreamQuantile()
        for s in slabs:
            q.count(field[s.x0:s.x1][inside[s.x0:s.x1]])
        ranks = level_ranks(q.n, porosity)
        q.select(*ranks)
        for s in slabs:
            q.refine(field[s.x0:s.x1][inside[s.x0:s.x1]])
        assert level_between(*q.values()) == solve_level(field, inside, porosity)


def _blobs_in_slabs(thickness: int, seeds: bool = False):
    """A shifted smooth noise (many separate blobs of solid, some spanning slab faces), its
    fragments removed on the whole grid (the oracle), and its solid joined across slabs of
    `thickness` planes: (field, whole, slabs, components)."""
    rng = np.random.default_rng(thickness)
    field = (ndimage.gaussian_filter(rng.normal(size=(40, 24, 18)), 1.5) + 0.05).astype(np.float32)
    whole = field.copy()
    removed = remove_fragments(whole, outside=1.0)
    assert removed > 3    # the oracle has fragments to remove
    slabs = plan_slabs(field.shape, max_voxels=thickness * 24 * 18, halo=0)
    comp = SlabComponents(seeds=seeds)
    for s in slabs:
        comp.add(field[s.x0:s.x1] < 0)
    assert comp.finish() == removed
    return field, whole, slabs, comp


@pytest.mark.parametrize("thickness", [1, 3, 8, 40])
def test_fragments_across_slabs_match_the_whole_grid(thickness):
    field, whole, slabs, comp = _blobs_in_slabs(thickness)
    tiled = field.copy()
    for i, s in enumerate(slabs):
        drop = comp.fragment_mask(i, field[s.x0:s.x1] < 0)
        tiled[s.x0:s.x1][drop] = 1.0
    assert np.array_equal(tiled, whole)
    # the painting pass writes the same voxels in place (the slab relabelled from its field)
    painted, written = field.copy(), 0
    for i, s in enumerate(slabs):
        written += comp.drop_fragments(i, painted[s.x0:s.x1], 1.0)
    assert np.array_equal(painted, whole)
    assert written == np.count_nonzero(whole != field)


@pytest.mark.parametrize("thickness", [1, 3, 8, 40])
def test_fragments_painted_from_first_voxels_match_the_whole_grid(thickness):
    # seeds: the pass-2 painting floods each fragment from its first voxel, without labelling again
    field, whole, slabs, comp = _blobs_in_slabs(thickness, seeds=True)
    painted, written = field.copy(), 0
    for i, s in enumerate(slabs):
        slab = np.ascontiguousarray(painted[s.x0:s.x1])
        # a slab said to hold no fragment is one the oracle leaves as it is
        assert comp.has_fragments(i) == bool(np.any(whole[s.x0:s.x1] != field[s.x0:s.x1]))
        written += comp.drop_fragments(i, slab, 1.0)
        painted[s.x0:s.x1] = slab
    assert np.array_equal(painted, whole)
    assert written == np.count_nonzero(whole != field)


@pytest.mark.parametrize("k", [0.0, 0.05, 0.13])
def test_blend_of_a_slab_with_its_halo_is_the_whole_blend(k):
    from implicit_scaffold.fields.field import blend_field
    from implicit_scaffold.run.tiles import blend_halo

    rng = np.random.default_rng(9)
    field = rng.normal(size=(45, 17, 19)).astype(np.float32)
    h = 0.02
    whole = blend_field(field, h, k)
    halo = blend_halo(h, k)
    # a halo one plane short of the Gaussian's reach would change the slab's edge values
    assert halo >= 1 or k == 0
    for s in plan_slabs(field.shape, max_voxels=(6 + 2 * halo) * 17 * 19, halo=halo):
        part = blend_field(field[s.h0:s.h1], h, k)[s.owned]
        assert np.array_equal(part, whole[s.x0:s.x1])


def test_field_file_holds_planes_and_vanishes(tmp_path):
    from implicit_scaffold.run.grid import Grid
    from implicit_scaffold.run.tiles import ArraySlabs, FieldFile

    grid = Grid((0.0, 0.0, 0.0), 0.1, (11, 6, 5))
    field = np.random.default_rng(2).standard_normal(grid.shape).astype(np.float32)
    with FieldFile(grid, folder=tmp_path) as f:
        # written out of order, in uneven pieces
        f.write(7, field[7:])
        f.write(0, field[:3])
        f.write(3, field[3:7])
        assert np.array_equal(f.read(0, 11), field)
        assert np.array_equal(f.read(4, 5), field[4:5])
        assert np.array_equal(ArraySlabs(field, grid).read(2, 9), f.read(2, 9))
        assert len(list(tmp_path.iterdir())) == 1
    assert not list(tmp_path.iterdir())


def test_field_file_removes_what_killed_runs_left(tmp_path):
    # a run killed outright (kill -9) leaves its field file: the next run removes it, and keeps
    # the files of runs still going and anything not named as a field file
    import subprocess
    import sys

    from implicit_scaffold.run.grid import Grid
    from implicit_scaffold.run.tiles import FieldFile

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True, check=True)
    orphan = tmp_path / f"implicit_scaffold-{int(dead.stdout)}-abc.f32"
    orphan.write_bytes(b"x" * 64)
    alive = tmp_path / f"implicit_scaffold-{os.getppid()}-def.f32"
    alive.write_bytes(b"y")
    other = tmp_path / "implicit_scaffold-notes.f32"
    other.write_bytes(b"z")
    with FieldFile(Grid((0.0, 0.0, 0.0), 0.1, (3, 2, 2)), folder=tmp_path) as f:
        assert not orphan.exists() and alive.exists() and other.exists()
        assert f.path.startswith(str(tmp_path / f"implicit_scaffold-{os.getpid()}-"))


def test_group_quantile_gives_each_groups_order_statistics():
    # against a sort of each group's values, fed in three uneven slabs, ties and signs mixed
    from implicit_scaffold.run.tiles import GroupQuantile

    rng = np.random.default_rng(5)
    values = np.concatenate([rng.normal(size=30_000), np.zeros(500), -np.zeros(500),
                             rng.integers(-3, 3, 4000).astype(float)]).astype(np.float32)
    group = rng.integers(0, 4, len(values))
    q = GroupQuantile(5)  # group 4 stays empty
    cuts = [0, 7000, 7001, len(values)]
    for a, b in zip(cuts[:-1], cuts[1:]):
        q.count(values[a:b], group[a:b])
    ranks = np.array([[0, 1], [17, 0], [5000, 5001], [0, 123], [0, 0]])
    ranks[1, 1] = np.count_nonzero(group == 1) - 2
    ranks[3, 0] = np.count_nonzero(group == 3) - 1
    q.select(ranks)
    for a, b in zip(cuts[:-1], cuts[1:]):
        q.refine(values[a:b], group[a:b])
    got = q.values()
    for g in range(4):
        ordered = np.sort(values[group == g])
        assert got[g].tolist() == ordered[ranks[g]].astype(float).tolist()
    assert np.isnan(got[4]).all()


def test_group_quantile_refuses_ranks_beyond_a_group():
    from implicit_scaffold.run.tiles import GroupQuantile

    q = GroupQuantile(2)
    q.count(np.arange(5, dtype=np.float32), np.array([0, 0, 1, 1, 1]))
    with pytest.raises(ValueError, match="rank outside"):
        q.select([[0, 2], [0, 1]])
    with pytest.raises(ValueError, match="group numbers outside"):
        q.count(np.ones(2, np.float32), np.array([0, 2]))


def test_kept_labels_give_the_relabelled_masks():
    # one slab held in memory keeps pass 1's labels: the same fragments and sealed pieces as
    # labelling the mask again (and as scipy's whole-grid labels)
    rng = np.random.default_rng(8)
    solid = ndimage.binary_opening(rng.random((30, 26, 22)) < 0.55)
    want_labels, n = ndimage.label(solid)
    sizes = np.bincount(want_labels.ravel())
    sizes[0] = 0
    want = (want_labels > 0) & (want_labels != np.argmax(sizes))
    for keep in (False, True):
        c = SlabComponents(keep_labels=keep)
        c.add(solid)
        assert c.finish() == n - 1 > 2
        np.testing.assert_array_equal(c.fragment_mask(0, solid), want)
    # a block with three closed cavities and a channel through it: the cavities are sealed
    block = np.ones((20, 18, 16), bool)
    cavities = np.zeros_like(block)
    cavities[3:6, 3:6, 3:6] = cavities[12:15, 4:7, 9:12] = cavities[8:10, 12:15, 2:4] = True
    block &= ~cavities
    block[:, 9, 8] = False
    void = ~block
    masks = []
    for keep in (False, True):
        v = SlabComponents(keep_labels=keep)
        v.add(void)
        v.finish()
        assert v.sealed(False)[0] == 3
        masks.append(v.sealed_mask(0, void))
    np.testing.assert_array_equal(masks[0], cavities)
    np.testing.assert_array_equal(masks[0], masks[1])
    # and painted in place from the kept labels (the mask's function is then not called)
    for keep in (False, True):
        v = SlabComponents(keep_labels=keep)
        v.add(void)
        v.finish()
        v.sealed(False)
        field = np.where(void, 1.0, -1.0).astype(np.float32)
        calls = []
        written = v.fill_sealed(0, lambda: calls.append(1) or void, field, -0.5)
        assert written == np.count_nonzero(cavities) and len(calls) == (0 if keep else 1)
        np.testing.assert_array_equal(field == -0.5, cavities)
    c = SlabComponents(keep_labels=True)
    c.add(solid)
    c.finish()
    field = np.where(solid, -1.0, 1.0).astype(np.float32)
    assert c.drop_fragments(0, field, 2.0) == np.count_nonzero(want)
    np.testing.assert_array_equal(field == 2.0, want)


@pytest.mark.parametrize("thickness", [1, 2, 5])
def test_26_connected_pieces_join_across_slabs_as_ndimage_labels_them(thickness):
    """SlabComponents(connectivity=26) against scipy.ndimage.label with a 3x3x3 structure on the
    whole mask: the same pieces (count and voxels per piece), joined across edges and corners
    of the slab faces too; 6-connected on the same mask gives more pieces."""
    from scipy import ndimage

    rng = np.random.default_rng(7)
    mask = rng.random((23, 17, 19)) < 0.12  # sparse: many pieces touch only by edges or corners
    labels, count = ndimage.label(mask, np.ones((3, 3, 3), bool))
    comp = SlabComponents(connectivity=26)
    local = []
    for x0 in range(0, 23, thickness):
        local.append((x0, comp.add(mask[x0:x0 + thickness])))
    comp.finish()
    assert comp.piece_count == count
    # every piece's voxels map to one root, and no two pieces to the same one
    roots = np.zeros(mask.shape, np.int64)
    for i, (x0, lab) in enumerate(local):
        roots[x0:x0 + lab.shape[0]] = comp.roots_of(i, lab)
    pairs = np.unique(np.stack([labels[mask], roots[mask]]), axis=1)
    assert pairs.shape[1] == count
    six = SlabComponents()
    for x0 in range(0, 23, thickness):
        six.add(mask[x0:x0 + thickness])
    six.finish()
    assert six.piece_count == ndimage.label(mask)[1] > count


def test_percentile_from_two_order_statistics_is_numpys():
    from implicit_scaffold.run.tiles import percentile_1

    rng = np.random.default_rng(5)
    for n in [1, 2, 3, 99, 100, 101, 1000, 4321]:
        values = (rng.random(n) * 3).astype(np.float32)
        ordered = np.sort(values)
        assert percentile_1(n, lambda *r: [ordered[i] for i in r]) == float(np.percentile(values, 1))
