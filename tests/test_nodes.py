"""Field nodes: the stage functions' bytes, whole or slab by slab."""
import numpy as np
import pytest

from implicit_scaffold.geometry.cells import voronoi_cells
from implicit_scaffold.fields.field import blend_field, scaffold_field, solve_level
from implicit_scaffold.run.grid import Grid
from implicit_scaffold.fields.lattice import lattice_sdf, struts_field
from implicit_scaffold.fields.nodes import SDF, Blend, Cut, FieldNode, PaperLattice, Patient, Struts, evaluate
from implicit_scaffold.fields.patient import Sphere, patient_sdf
from implicit_scaffold.geometry.skeleton import scaled_skeleton, voronoi_edges


@pytest.fixture(scope="module")
def cells():
    lo, hi = np.zeros(3), np.array([3.0, 2.6, 2.2])
    return voronoi_cells(np.random.default_rng(4).uniform(lo, hi, (40, 3)), lo, hi)


@pytest.fixture(scope="module")
def grid():
    # odd sizes, so that slabs and blocks do not divide the grid evenly
    return Grid.covering([0, 0, 0], [3.0, 2.6, 2.2], 0.07)


def _ball(x, y, z):
    return np.sqrt((x - 1.5) ** 2 + (y - 1.3) ** 2 + (z - 1.1) ** 2) - 1.0


def test_nodes_give_the_stage_functions_bytes(cells, grid):
    # the oracle: the stage functions called by hand, as the README's composed example does
    skeleton = scaled_skeleton(cells, sf=0.7, sv=0.7)
    by_hand = blend_field(lattice_sdf(skeleton, grid, cutoff=0.5), grid.spacing, k=0.15)
    lattice = Blend(PaperLattice(skeleton, cutoff=0.5), k=0.15)
    assert isinstance(lattice, FieldNode)
    assert evaluate(lattice, grid).tobytes() == by_hand.tobytes()
    x, y, z = np.meshgrid(*grid.axes(), indexing="ij")
    ball = _ball(x, y, z).astype(np.float32)
    level = solve_level(by_hand, ball < 0, porosity=0.6)
    expected = scaffold_field(by_hand.copy(), ball, level=level, skin=0.1, smooth_cut=0.05)
    cut = Cut(lattice, SDF(_ball), level=level, skin=0.1, smooth_cut=0.05)
    assert evaluate(cut, grid).tobytes() == expected.tobytes()
    sphere = Sphere(2.0)
    assert evaluate(Patient(sphere), grid).tobytes() == patient_sdf(sphere, grid).tobytes()


@pytest.mark.parametrize("k", [0.0, 0.2])
def test_slab_by_slab_is_the_whole_grid(cells, grid, k):
    # a blend reads a halo of planes: slabs of 5 planes (fewer than the 0.2 mm blend's halo
    # on either side is wide) must still give the whole grid's bits
    plane = grid.shape[1] * grid.shape[2]
    skeleton = scaled_skeleton(cells, sf=0.6, sv=0.75)
    for node in (Blend(PaperLattice(skeleton, cutoff=0.4), k=k),
                 Cut(Blend(PaperLattice(skeleton, cutoff=0.4), k=k), SDF(_ball), level=0.02, smooth_cut=k)):
        halo = node.reads(grid, (20, 21))
        assert halo == ((20 - (halo[1] - 21), halo[1]) if k else (20, 21))
        whole = evaluate(node, grid)
        slabs = evaluate(node, grid, max_voxels=(5 + 2 * (halo[1] - 21)) * plane)
        assert slabs.tobytes() == whole.tobytes()


def test_struts_node_is_the_struts_field(cells, grid):
    edges = voronoi_edges(cells)
    node = Struts(edges, cutoff=0.4, k=0.05)
    expected = struts_field(edges, grid, cutoff=0.4, blend=0.05)
    assert evaluate(node, grid).tobytes() == expected.tobytes()
    assert evaluate(node, grid, max_voxels=7 * grid.shape[1] * grid.shape[2]).tobytes() == expected.tobytes()


def test_mirror_sources_reflect_a_linear_field():
    # a linear field's mirror image is known at every point: f(2 wall - c)
    from implicit_scaffold.fields.field import mirror_along, mirror_sources

    origin, h, n, lo, hi = -0.33, 0.1, 30, 0.0, 2.2
    c = origin + h * np.arange(n)
    f = (3 * c + 1).astype(np.float32)[:, None, None] * np.ones((1, 2, 3), np.float32)
    reach = 0.25
    j, t, moved = mirror_sources(origin, h, n, lo, hi, reach, -4, n + 4)
    got = mirror_along(f, 0, 0, j, t)[:, 0, 0]
    i = np.arange(-4, n + 4)
    ci = origin + h * i
    beyond = np.where(ci < lo, lo - ci, ci - hi)
    assert np.array_equal(moved, (beyond > 0) & (beyond <= reach))
    want = np.where(ci < lo, 3 * (2 * lo - ci) + 1, 3 * (2 * hi - ci) + 1)
    assert np.allclose(got[moved], want[moved], atol=1e-5)
    # the others keep their own value, or beyond the grid the nearest plane's (mode "nearest")
    assert np.array_equal(got[~moved], f[np.clip(i[~moved], 0, n - 1), 0, 0])


def test_blend_mirrors_the_cells_walls_as_scipy_reflects():
    # walls half a voxel beyond the first and last planes inside: the mirror is SciPy's mode
    # "reflect" of the box's planes, whatever the field holds outside the box
    from scipy import ndimage

    h, k = 0.1, 0.6  # sigma 2 voxels, a halo of 6 planes: beyond the 2 planes of margin
    lo, hi = np.zeros(3), np.array([2.0, 1.6, 1.2])
    grid = Grid((-0.15, -0.15, -0.15), h, (24, 20, 16))

    def fn(x, y, z):
        inside = (x > 0) & (x < 2.0) & (y > 0) & (y < 1.6) & (z > 0) & (z < 1.2)
        return np.where(inside, np.sin(3 * x) * np.cos(2 * y) + 0.5 * z * x, -5.0)

    node = Blend(SDF(fn), k=k, mirror=(tuple(lo), tuple(hi)))
    whole = evaluate(node, grid)
    x, y, z = np.meshgrid(*grid.axes(), indexing="ij")
    box = (slice(2, 22), slice(2, 18), slice(2, 14))
    raw = fn(x, y, z).astype(np.float32)[box]
    want = ndimage.gaussian_filter(raw, k / 3 / h, mode="reflect", truncate=3.0, output=np.float32)
    assert np.abs(whole[box] - want).max() < 2e-6
    # without the mirror the outside's -5 bleeds in: the test can tell the two apart
    plain = evaluate(Blend(SDF(fn), k=k), grid)
    assert np.abs(plain[box] - want).max() > 0.1
    # slab by slab, down to single planes beside the walls, the same bits
    plane = grid.shape[1] * grid.shape[2]
    for planes in (1, 3, 7):
        assert evaluate(node, grid, max_voxels=(planes + 2 * 12) * plane).tobytes() == whole.tobytes()


def test_mirror_beyond_the_grid_changes_nothing(cells, grid):
    # a box wider than the grid by more than the halo (a patient's cells reach a cell beyond
    # it): no plane is mirrored, and the bits are the plain blend's
    skeleton = scaled_skeleton(cells, sf=0.6, sv=0.75)
    far = ((-1.0, -1.0, -1.0), (4.0, 3.6, 3.2))
    mirrored = evaluate(Blend(PaperLattice(skeleton, cutoff=0.4), k=0.2, mirror=far), grid)
    plain = evaluate(Blend(PaperLattice(skeleton, cutoff=0.4), k=0.2), grid)
    assert mirrored.tobytes() == plain.tobytes()
