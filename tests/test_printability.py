"""The print certificate against synthetic volumes whose answers are known in closed form, and
the throat flood against a brute-force sphere percolation."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy import ndimage

from implicit_scaffold.measure import printability
from implicit_scaffold.errors import ScaffoldError
from implicit_scaffold.run.grid import Grid
from implicit_scaffold.measure.printability import (certificate, overhang_shares, printer_profile, profiles,
                                            reached_by, throat_radius)

H = 0.02


def _axes(n):
    x = (np.arange(n) + 0.5) * H
    return np.meshgrid(x, x, x, indexing="ij")


def _hollow_box(n=90, hole=None, wall=0.3):
    """A closed box (walls `wall` mm) around a cavity; optionally a round hole of diameter `hole` in its top."""
    X, Y, Z = _axes(n)
    c = n * H / 2
    outer = (np.abs(X - c) < c - 0.2) & (np.abs(Y - c) < c - 0.2) & (np.abs(Z - c) < c - 0.2)
    cavity = (np.abs(X - c) < c - 0.2 - wall) & (np.abs(Y - c) < c - 0.2 - wall) & (np.abs(Z - c) < c - 0.2 - wall)
    solid = outer & ~cavity
    if hole is not None:
        solid &= ~((np.hypot(X - c, Y - c) < hole / 2) & (Z > c))
    return solid, outer, cavity


def brute_force_throat(solid):
    """For every radius, the void whose distance allows it, flooded from the grid's faces (6-connected)."""
    # SciPy's distance transform: beyond the array is void, as the outside of the scaffold
    d2 = np.rint(ndimage.distance_transform_edt(~solid) ** 2).astype(np.int32)
    out = np.zeros_like(d2)
    six = ndimage.generate_binary_structure(3, 1)
    for v in np.unique(d2[d2 > 0]):
        labels, _ = ndimage.label(d2 >= v, structure=six)
        faces = np.concatenate([labels[0].ravel(), labels[-1].ravel(), labels[:, 0].ravel(), labels[:, -1].ravel(),
                                labels[:, :, 0].ravel(), labels[:, :, -1].ravel()])
        out[np.isin(labels, np.unique(faces[faces > 0]))] = v
    return d2, out


@pytest.mark.parametrize("seed, threshold", [(0, 0.5), (1, 0.5), (2, 0.48)])
def test_throat_flood_equals_brute_force_sphere_percolation(seed, threshold):
    rng = np.random.default_rng(seed)
    # a random lattice-like solid: smoothed noise, thresholded: narrow necks and, at 0.48, sealed pockets
    solid = ndimage.gaussian_filter(rng.random((34, 30, 28)), 1.6) > threshold
    d2, r2 = throat_radius(solid, H)
    want_d2, want = brute_force_throat(solid)
    assert np.array_equal(d2, want_d2)
    assert np.array_equal(r2, want)
    assert len(np.unique(r2)) > 8
    assert (r2[~solid] == 0).any() == (threshold < 0.5)
    # the void a sphere reaches: every voxel nearer than its radius to a centre the flood allows it,
    # by the exact nearest centre of every voxel (a k-d tree; squared distances are integers, the
    # radii half-integers, so no distance ties the radius)
    from scipy.spatial import cKDTree

    idx = np.argwhere(np.ones(solid.shape, bool))
    # the last sphere just fits the widest throat (so some centres allow it)
    for diameter in (2.0 * H, 4.0 * H, 6.0 * H, 8.0 * H, (2.0 * math.sqrt(want.max()) + 0.4) * H):
        rho = 0.5 * (diameter / H - 1.0)
        centres = np.argwhere(want >= rho * rho)
        assert len(centres) > 0
        dist = cKDTree(centres).query(idx)[0]
        near = (dist < rho).reshape(solid.shape)
        assert np.array_equal(reached_by(r2, diameter, H), near & (want > 0)), diameter
        # beyond the windows' radius the distance transform of the centres answers: the same voxels
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(printability, "WINDOW_RHO", 0.0)
            assert np.array_equal(reached_by(r2, diameter, H), near & (want > 0)), diameter


def test_rod_thickness_within_a_voxel():
    # a rod bent into a ring, so that it has no ends (a cut end is thinner at its rim)
    X, Y, Z = _axes(100)
    radius = 0.235
    rod = np.hypot(np.hypot(X - 1.0, Y - 1.0) - 0.7, Z - 1.0) < radius
    cert = certificate(rod, H, printer_profile("dlp-resin"))
    assert abs(cert["thinnest_mm"]["p1"] - 2 * radius) <= H
    # the voxels of the digitised surface's bumps hold only smaller spheres: the minimum (one bump)
    # reads less
    assert cert["thinnest_mm"]["min"] <= cert["thinnest_mm"]["p1"]
    # 0.47 mm passes DLP's 0.4 mm (but for a few surface bumps); a 0.5 mm minimum flags all of it
    assert cert["below_min_strut_share"] < 0.001 and cert["verdict"]["thinnest"] == "pass"
    thin = certificate(rod, H, printer_profile("custom:min_strut=0.5,min_throat=0.1"))
    assert thin["below_min_strut_share"] == 1.0 and thin["verdict"]["thinnest"] == "fail"


@pytest.mark.parametrize("hole", [0.3, 0.42])
def test_throat_of_a_hole_within_a_voxel(hole):
    solid, outer, _ = _hollow_box(hole=hole)
    cert = certificate(solid, H, printer_profile("custom:min_strut=0.1,min_throat=0.2,drain=0.5"), region=outer)
    # the cavity, nearly all of the box's void, is reached only through the hole
    assert abs(cert["throat_mm"] - hole) <= H
    assert cert["sealed_voids"]["count"] == 0
    # a 0.5 mm drain cannot pass the hole; 100 um cells can
    assert cert["void_reached_by_drain_share"] < 0.05 and cert["verdict"]["drain"] == "fail"
    assert cert["void_reached_by_100um_share"] > 0.99


def test_sealed_cavity_found_with_its_volume():
    solid, outer, cavity = _hollow_box()
    cert = certificate(solid, H, printer_profile("dlp-resin"), region=outer)
    assert cert["sealed_voids"]["count"] == 1
    assert cert["sealed_voids"]["volume_mm3"] == pytest.approx(np.count_nonzero(cavity) * H ** 3, rel=1e-9)
    assert cert["verdict"]["sealed_voids"] == "fail" and cert["verdict"]["overall"] == "fail"


def test_floating_ball_found_with_its_volume():
    X, Y, Z = _axes(70)
    block = Z < 0.3
    ball = np.sqrt((X - 0.7) ** 2 + (Y - 0.7) ** 2 + (Z - 0.9) ** 2) < 0.2
    cert = certificate(block | ball, H, printer_profile("dlp-resin"))
    assert cert["floating_solid"]["count"] == 1
    assert cert["floating_solid"]["volume_mm3"] == pytest.approx(np.count_nonzero(ball) * H ** 3, rel=1e-9)
    assert cert["verdict"]["floating_solid"] == "fail"


def test_overhang_share_of_a_ramp_within_one_percent():
    # a solid above a bent ramp: its underside rises at 30 deg, then at 60 deg; limit 45 deg
    h = 0.05
    nx, ny, nz = 160, 60, 200
    x, z = np.arange(nx) * h, np.arange(nz) * h
    a = 4.0
    floor = np.where(x < a, 0.5 + math.tan(math.radians(30)) * x,
                     0.5 + math.tan(math.radians(30)) * a + math.tan(math.radians(60)) * (x - a))
    field = np.broadcast_to((floor[:, None, None] - z[None, None, :]), (nx, ny, nz)).astype(np.float32)
    shares = overhang_shares(field, Grid((0.0, 0.0, 0.0), h, (nx, ny, nz)), 45.0)
    # the grid's outer layer is left out: the faces span x from h to (nx - 2) h
    a30 = (a - h) / math.cos(math.radians(30))
    a60 = ((nx - 2) * h - a) / math.cos(math.radians(60))
    assert shares["+z"] == pytest.approx(a30 / (a30 + a60), abs=0.01)
    # built the other way up, nothing faces down; sideways, the ramp's faces are walls or face up
    assert shares["-z"] == 0.0 and shares["+y"] == 0.0
    # a steeper limit than both faces: all of the underside is overhang
    assert overhang_shares(field, Grid((0.0, 0.0, 0.0), h, (nx, ny, nz)), 70.0)["+z"] == pytest.approx(1.0, abs=1e-6)


def test_profiles_have_sources_and_custom_ones_parse():
    table = profiles()
    assert {"dlp-resin", "sla-resin", "lpbf-ti64", "lpbf-cocr", "fdm-pcl"} <= set(table)
    for p in table.values():
        assert p.source and p.min_strut_mm > 0 and p.min_throat_mm > 0 and 0 < p.overhang_deg < 90
    c = printer_profile("custom:min_strut=0.3,min_throat=0.6,overhang=40,axis=-x,deviation=-0.02")
    assert (c.min_strut_mm, c.min_throat_mm, c.overhang_deg, c.build_axis, c.deviation_mm) == (0.3, 0.6, 40, "-x", -0.02)
    for bad in ["nope", "custom:min_strut", "custom:colour=red", "custom:min_strut=x", "custom:overhang=95",
                "custom:axis=up", "custom:", "custom: , "]:
        with pytest.raises(ScaffoldError):
            printer_profile(bad)


def test_as_built_offset_thickens_the_solid():
    solid, outer, _ = _hollow_box(hole=0.42)
    cert = certificate(solid, H, printer_profile("custom:min_strut=0.1,min_throat=0.2,deviation=0.04"), region=outer)
    # 2 voxels thicker all round: the hole's throat shrinks by about twice that, the porosity falls
    assert cert["as_built"]["porosity"] < cert["porosity"]
    assert abs(cert["as_built"]["throat_mm"] - (0.42 - 2 * 0.04)) <= 2 * H


def _run(args, tmp_path):
    from implicit_scaffold.cli import main

    import os

    cwd = os.getcwd()
    os.chdir(tmp_path)
    try:
        return main(args)
    finally:
        os.chdir(cwd)


def test_check_command_and_generate_printer(tmp_path, capsys):
    keys = {"printer", "thinnest_mm", "below_min_strut_share", "throat_mm", "void_reached_by_drain_share",
            "void_reached_by_100um_share", "sealed_voids", "floating_solid", "overhang_share", "best_build_axis",
            "as_built", "verdict"}
    code = _run(["generate", "--seeds", "30", "--size", "3", "--voxel", "0.05", "--printer", "fdm-pcl",
                 "-o", "s.stl", "--report", "r.html", "-q"], tmp_path)
    assert code == 0
    report = json.loads((tmp_path / "s.json").read_text())
    page = (tmp_path / "r.html").read_text()
    assert "Print certificate: fdm-pcl" in page and page.count("print certificate: where the problems lie") == 2
    assert keys <= set(report["print_check"])
    assert set(report["print_check"]["verdict"]) >= {"thinnest", "throat", "sealed_voids", "overhang", "overall"}
    assert _run(["check", "s.stl", "--printer", "fdm-pcl", "--voxel", "0.05", "-o", "cert.json"], tmp_path) == 0
    cert = json.loads((tmp_path / "cert.json").read_text())
    assert keys <= set(cert)
    # the STL's voxels and the run's agree on what was built
    assert cert["porosity"] == pytest.approx(report["porosity_voxel"], abs=0.02)
    out = capsys.readouterr().out
    assert "print check (fdm-pcl)" in out
    # a certificate that fails stops a pipeline with 3 when asked to, after writing it
    strict = "custom:min_strut=5,min_throat=5"
    assert _run(["check", "s.stl", "--printer", strict, "--voxel", "0.05", "--require-printable",
                 "-o", "strict.json", "-q"], tmp_path) == 3
    assert json.loads((tmp_path / "strict.json").read_text())["verdict"]["overall"] == "fail"


def test_check_bad_input_one_line_exit_2(tmp_path, capsys):
    np.save(tmp_path / "f.npy", np.zeros((4, 4, 4), np.float32))
    for args in (["check", "missing.stl", "--printer", "dlp-resin", "--voxel", "0.1"],
                 ["check", "f.npy", "--printer", "dlp-resin"],
                 ["check", "f.npy", "--printer", "no-such-printer", "--voxel", "0.1"]):
        assert _run(args, tmp_path) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "Traceback" not in err


# ----------------------------------------------------------------------------- in slabs


def _same_certificate(want, got):
    """Every figure of the two certificates equal (but the seconds), and the section maps."""
    assert {k: v for k, v in got.items() if k != "seconds"} == {k: v for k, v in want.items() if k != "seconds"}
    assert set(got.sections) == set(want.sections)
    for key, section in want.sections.items():
        assert np.array_equal(got.sections[key], section), key


def _by_slabs_equals_whole(s, p, grid, profile, max_voxels, **kw):
    from implicit_scaffold.measure.printability import certificate_by_slabs
    from implicit_scaffold.run.tiles import ArraySlabs

    want = certificate(s < 0, grid.spacing, profile, field=s, region=p < 0, origin=grid.origin)
    got = certificate_by_slabs(ArraySlabs(s, grid), ArraySlabs(p, grid), grid.spacing, profile,
                               max_voxels=max_voxels, origin=grid.origin, **kw)
    _same_certificate(want, got)
    return want


@pytest.fixture(scope="module")
def small_scaffold():
    from implicit_scaffold import generate

    r = generate(size=2.0, voxel=0.05, seed=1, mesh=False, morphometry=False)
    return np.asarray(r.field), np.asarray(r.patient_sdf), r.grid


# slabs of one plane (thinner than any halo), a few planes, and most of the grid
@pytest.mark.parametrize("planes", [1, 5, 30])
def test_certificate_by_slabs_is_the_whole_grid_certificate(small_scaffold, planes):
    s, p, grid = small_scaffold
    plane = grid.shape[1] * grid.shape[2]
    want = _by_slabs_equals_whole(s, p, grid, printer_profile("dlp-resin"), planes * plane, halo=1)
    assert want["pore_throats_mm"]["pores"] > 10  # a real scaffold: many pores, real throats


def _sdf_grid(shape):
    n = np.asarray(shape)
    return Grid((0.0, 0.0, 0.0), H, tuple(int(v) for v in n))


def _centres(shape):
    return np.meshgrid(*[(np.arange(n) + 0.5) * H for n in shape], indexing="ij")


def _signed(solid):
    """A signed distance (mm, negative in `solid`) from a voxel mask."""
    return (H * (ndimage.distance_transform_edt(~solid) - ndimage.distance_transform_edt(solid))).astype(np.float32)


@pytest.mark.parametrize("planes", [1, 4])
def test_certificate_by_slabs_with_a_sealed_void_and_a_floating_piece(planes):
    # a block pierced by two round channels along x, a sealed spherical cavity in it, and a
    # ball floating in free space beside it; the patient is the whole grid
    shape = (50, 36, 34)
    X, Y, Z = _centres(shape)
    block = (np.abs(X - 0.35) < 0.3) & (np.abs(Y - 0.36) < 0.3) & (np.abs(Z - 0.34) < 0.28)
    channels = (np.hypot(Y - 0.2, Z - 0.2) < 0.06) | (np.hypot(Y - 0.5, Z - 0.45) < 0.04)
    cavity = np.sqrt((X - 0.35) ** 2 + (Y - 0.45) ** 2 + (Z - 0.2) ** 2) < 0.08
    ball = np.sqrt((X - 0.83) ** 2 + (Y - 0.36) ** 2 + (Z - 0.34) ** 2) < 0.1
    s = _signed((block & ~channels & ~cavity) | ball)
    p = np.full(shape, -1.0, np.float32)
    want = _by_slabs_equals_whole(s, p, _sdf_grid(shape), printer_profile("dlp-resin"),
                                  planes * shape[1] * shape[2], halo=1)
    assert want["sealed_voids"]["count"] == 1 and want["floating_solid"]["count"] == 1


@pytest.mark.parametrize("planes", [2, 9])
def test_certificate_by_slabs_of_a_patient_far_from_the_grid_corners(small_scaffold, planes):
    # a ball patient in a grid twice its size: the void's distance grows to tens of voxels in the
    # corners, where no figure reads it exactly; the slabs cap it (a halo that wide would make
    # every slab read most of the grid) and must still give the whole grid's certificate
    s0, _, _ = small_scaffold
    n = 2 * np.asarray(s0.shape)
    s = np.full(tuple(n), H, np.float32)
    q = (n - np.asarray(s0.shape)) // 2
    s[q[0]:q[0] + s0.shape[0], q[1]:q[1] + s0.shape[1], q[2]:q[2] + s0.shape[2]] = s0
    X, Y, Z = _centres(tuple(n))
    c = n * H / 2
    p = (np.sqrt((X - c[0]) ** 2 + (Y - c[1]) ** 2 + (Z - c[2]) ** 2) - 0.45 * s0.shape[0] * H).astype(np.float32)
    s = np.maximum(s, p)
    d2, _ = throat_radius(s < 0, H)
    assert d2[0, 0, 0] > 20 ** 2  # the corners lie far from any solid
    want = _by_slabs_equals_whole(s, p, _sdf_grid(tuple(n)), printer_profile("dlp-resin"),
                                  planes * int(n[1]) * int(n[2]), halo=1)
    assert want["pore_throats_mm"]["pores"] > 10


def test_certificate_by_slabs_follows_a_serpentine_across_slabs():
    # a solid block whose only wide way in is a channel (5 voxels square) that enters at x = 0
    # and runs along x three times (there, back, there again), so the widest path to its last
    # leg crosses every slab face three times; a hole one voxel wide from the top face reaches
    # the last leg first, so its radii must rise as the wide path arrives over later sweeps
    shape = (40, 32, 12)
    channel = np.zeros(shape, bool)
    for xs, ys in [((0, 34), (3, 8)), ((29, 34), (3, 18)), ((6, 34), (13, 18)), ((6, 11), (13, 28)),
                   ((6, 36), (23, 28))]:
        channel[slice(*xs), slice(*ys), 4:9] = True
    channel[20, 27:, 6] = True
    s = _signed(~channel)
    p = np.full(shape, -1.0, np.float32)
    profile = printer_profile("custom:min_strut=0.1,min_throat=0.1,drain=0.1")
    _by_slabs_equals_whole(s, p, _sdf_grid(shape), profile, 3 * shape[1] * shape[2], halo=1)
    # the oracle: the last leg holds the channel's inscribed radius (3 voxels), brought by the
    # wide path, where the narrow hole alone allows 1 voxel
    _, r2 = throat_radius(s < 0, H)
    assert r2[30, 25, 6] == 9 and r2[20, 31, 6] == 1


def test_tiled_run_with_a_printer_gives_the_whole_grid_certificate(tmp_path):
    from implicit_scaffold import generate

    kw = dict(size=2.0, voxel=0.05, seed=2, mesh=False, morphometry=False, printer="dlp-resin")
    whole = generate(output=tmp_path / "whole.npy", tiled=False, **kw)
    n = whole.grid.shape[1] * whole.grid.shape[2]
    tiled = generate(output=tmp_path / "tiled.npy", tiled=6 * n, **kw)
    assert tiled.report["tiled"]["slabs"] > 1
    _same_certificate(whole.report["print_check"], tiled.report["print_check"])
    # the run's page draws the certificate's two section maps from the tiled run too
    from implicit_scaffold.io.report import write_run_report

    write_run_report(tiled, tmp_path / "r.html")
    assert (tmp_path / "r.html").read_text().count("print certificate: where the problems lie") == 2


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_flood_in_two_halves_gives_the_single_floods_fixpoint(seed):
    # the halves flooded on two cores and joined across the cut, against one flood of the whole
    # (a reconstruction has one fixpoint); a blobby void whose best paths cross the cut both ways
    from scipy import ndimage

    from implicit_scaffold.measure.morphometry import _squared_edt
    from implicit_scaffold.measure.printability import _flood_kernels

    flood, flood_faces = _flood_kernels()
    solid = ndimage.gaussian_filter(np.random.default_rng(seed).normal(size=(40 + seed, 27, 33)), 1.5) > 0.1
    d2 = np.ascontiguousarray(_squared_edt(~solid))
    halves, whole = np.zeros_like(d2), np.zeros_like(d2)
    assert flood(d2, halves) and flood_faces(d2, whole, True, True)
    assert 0 < np.count_nonzero(whole) and np.count_nonzero(whole < d2) > 100
    np.testing.assert_array_equal(halves, whole)


@pytest.mark.parametrize("plate, min_strut, unresolved, verdict", [
    (1, 2.5, 1.0, "warn"),   # 1 voxel thick reads 3: it cannot be told from 2.5
    (2, 2.5, 1.0, "warn"),   # 2 voxels thick reads 3 too
    (6, 2.5, 0.0, "pass"),   # 6 voxels read 5 to 7: resolved
    (1, 1.0, 0.0, "pass"),   # a minimum of one voxel: any solid meets it
])
def test_solid_the_voxels_cannot_tell_from_the_minimum_strut_is_not_passed(plate, min_strut, unresolved, verdict):
    # a plate of `plate` voxels (true thickness plate x 1 mm) through a 1 mm grid
    solid = np.zeros((24, 24, 24), bool)
    solid[:, :, 10:10 + plate] = True
    cert = certificate(solid, 1.0, printer_profile(f"custom:min_strut={min_strut},min_throat=0.5"))
    assert cert["thinnest_mm"]["unresolved_share"] == pytest.approx(unresolved)
    assert cert["verdict"]["thinnest"] == verdict


def test_check_of_a_mesh_offsets_it_as_built_by_its_own_signed_distance(tmp_path):
    # a tube (radii 1 and 2 mm, 4 mm tall) as a mesh, checked at 0.25 mm voxels for a process that builds
    # 0.1 mm thicker: the as-built solid is every voxel centre within 0.1 mm of the tube, by the closed-form
    # distance (a printer's deviation under a voxel moved nothing before: whole voxels only)
    import json

    import trimesh

    from implicit_scaffold.cli import main
    from implicit_scaffold.run.grid import Grid

    tube = trimesh.creation.annulus(r_min=1.0, r_max=2.0, height=4.0, sections=512)
    tube.export(tmp_path / "tube.stl")
    out = tmp_path / "cert.json"
    assert main(["check", str(tmp_path / "tube.stl"), "--voxel", "0.25", "-q", "-o", str(out), "--printer",
                 "custom:min_strut=0.1,min_throat=0.1,deviation=0.1"]) in (0, 3)
    cert = json.loads(out.read_text())
    lo, hi = tube.bounds
    grid = Grid.covering(lo, hi, 0.25)
    x, y, z = np.meshgrid(*grid.axes(), indexing="ij")
    r = np.hypot(x, y)
    q = np.stack([np.abs(r - 1.5) - 0.5, np.abs(z) - 2.0])
    sdf = np.linalg.norm(np.maximum(q, 0), axis=0) + np.minimum(q.max(axis=0), 0)
    region = np.all([(c >= lo[a]) & (c <= hi[a]) for a, c in enumerate((x, y, z))], axis=0)
    expect = np.count_nonzero(region & (sdf >= 0.1)) / np.count_nonzero(region)
    designed = np.count_nonzero(region & (sdf >= 0)) / np.count_nonzero(region)
    assert cert["as_built"]["porosity"] == pytest.approx(expect, abs=2e-3)
    assert cert["porosity"] == pytest.approx(designed, abs=2e-3) and expect < designed - 0.02


def test_check_of_generates_own_volume_field_offsets_it_as_the_npy(tmp_path, capsys):
    # a float .nrrd generate wrote was read as its solid alone: the as-built offset moved whole voxels (nothing at
    # 0.05 mm of a 0.05 mm grid); with its distance it is the .npy's of the same run, the oracle
    import json

    from implicit_scaffold.cli import main

    common = ["--size", "1.5", "--pore-size", "0.6", "--voxel", "0.05", "-q"]
    assert main(["generate", "-o", str(tmp_path / "f.npy"), *common]) == 0
    assert main(["generate", "-o", str(tmp_path / "g.nrrd"), *common]) == 0
    certs = []
    for name in ("f.npy", "g.nrrd"):
        out = tmp_path / f"c_{name}.json"
        main(["check", str(tmp_path / name), "--printer", "custom:min_strut=0.1,min_throat=0.1,deviation=0.05",
              "-o", str(out), "-q"])
        certs.append(json.loads(out.read_text()))
    assert certs[1]["as_built"] == certs[0]["as_built"]
    assert certs[1]["as_built"]["porosity"] < certs[1]["porosity"] - 0.05  # the offset thickened the struts


# ----------------------------------------------------------------------------- as built, from a field


def _ball_field(n, h, radius, scale):
    """``scale (|x - c|² - radius²)`` on an n³ grid of voxel h (mm): its zero set is the sphere of
    `radius` about the grid's centre, its gradient ``2 scale |x - c|`` (0.5 at the surface for a
    scale of 0.25 per mm on a 1 mm ball: a field, not a distance, as generate's blended one)."""
    x = (np.arange(n) + 0.5) * h - 0.5 * n * h
    X, Y, Z = np.meshgrid(x, x, x, indexing="ij")
    return (scale * (X * X + Y * Y + Z * Z - radius * radius)).astype(np.float32)


def _radius_of(count, h):
    """The radius of the ball of `count` voxels' volume, mm."""
    return (3.0 * count * h ** 3 / (4.0 * math.pi)) ** (1.0 / 3.0)


@pytest.mark.parametrize("scale", [0.25, 4.0])
@pytest.mark.parametrize("deviation", [0.05, -0.05])
def test_as_built_offset_of_a_field_is_the_ball_grown_by_the_deviation(scale, deviation):
    # a 1 mm ball as a field whose gradient at the surface is 0.5 or 8, not 1: offset by δ the solid must be
    # the ball of radius 1 + δ (closed form), where the plain threshold φ < δ makes it sqrt(1 + δ / scale)
    # (1.095 and 1.006 mm for +0.05). Tolerance 0.15 voxel of radius: the first-order offset's own error
    # (δ² / 2R = 0.03 voxel), the upwind differences' (under δ h √3 / 2R = 0.04 voxel) and the voxel
    # count's (a ball of 26 voxels' radius: well under 0.05 voxel)
    h, R = 0.04, 1.0
    phi = _ball_field(60, h, R, scale)
    profile = printer_profile(f"custom:min_strut=0.1,min_throat=0.1,deviation={deviation}")
    cert = certificate(phi < 0, h, profile, field=phi)
    grown = round((1.0 - cert["as_built"]["porosity"]) * phi.size)
    assert abs(_radius_of(grown, h) - (R + deviation)) < 0.15 * h
    plain = np.count_nonzero(phi < deviation)
    assert abs(_radius_of(plain, h) - (R + deviation)) > 0.15 * h  # the oracle tells the two apart
    # the designed solid is the ball of radius R
    assert abs(_radius_of(np.count_nonzero(phi < 0), h) - R) < 0.05 * h


def _upwind_offset_reference(phi, deviation, h):
    """``δ |∇φ|`` with Godunov's upwind |∇φ| on the whole array, the obvious way: along each axis the
    differences towards both neighbours (none beyond the array), for a front moving into the void
    (into the solid for δ < 0), float64. The offset solid is ``φ`` below it."""
    f = phi.astype(np.float64) * np.sign(deviation)
    total = np.zeros_like(f)
    for axis in range(3):
        lower = np.concatenate([np.take(f, [0], axis), np.take(f, range(f.shape[axis] - 1), axis)], axis)
        upper = np.concatenate([np.take(f, range(1, f.shape[axis]), axis), np.take(f, [-1], axis)], axis)
        total += np.maximum(np.maximum(f - lower, f - upper), 0.0) ** 2
    return deviation * np.sqrt(total) / h


@pytest.mark.parametrize("deviation", [0.04, -0.04])
@pytest.mark.parametrize("block_planes", [1, 2, 7, 100])
def test_grown_solid_by_blocks_and_slabs_is_the_whole_grids_and_the_reference(block_planes, deviation,
                                                                              monkeypatch):
    # a smooth random field (not a distance) on an odd grid, cut into blocks of 1, 2, 7 planes or taken whole,
    # and asked for slabs of odd widths: every plane as the whole grid's, bit for bit (each block reads a plane
    # of halo on either side), and as the float64 reference but where φ is within float32 rounding of δ |∇φ|
    from implicit_scaffold.measure.printability import grown_solid

    rng = np.random.default_rng(3)
    phi = ndimage.gaussian_filter(rng.normal(size=(23, 17, 19)), 2.0).astype(np.float32)
    phi *= np.float32(0.3 / np.abs(phi).max())
    h = 0.05

    def read(lo, hi):
        return phi[lo:hi]

    whole = grown_solid(read, phi.shape, 0, phi.shape[0], deviation, h)
    monkeypatch.setattr(printability, "OFFSET_BLOCK_VOXELS", block_planes * phi.shape[1] * phi.shape[2])
    for cuts in ([0, 23], [0, 1, 8, 9, 22, 23], [0, 5, 6, 13, 23]):
        got = np.concatenate([grown_solid(read, phi.shape, a, b, deviation, h) for a, b in zip(cuts, cuts[1:])])
        np.testing.assert_array_equal(got, whole)
    level = _upwind_offset_reference(phi, deviation, h)
    clear = np.abs(phi - level) > 1e-5
    # the offset moved the surface by many voxels' worth, both ways of the sign
    assert np.count_nonzero(whole != (phi < 0)) > 100
    np.testing.assert_array_equal(whole[clear], (phi < level)[clear])


@pytest.fixture(scope="module")
def cylinder_runs(tmp_path_factory):
    """One run of a cylinder patient written twice, as a .npy field (with generate's own certificate) and as an
    STL, each with its report beside it: the cylinder's bounding box holds void that is not the patient's."""
    from implicit_scaffold.cli import main

    root = tmp_path_factory.mktemp("cyl")
    common = ["--shape", "cylinder", "--size", "2", "--pore-size", "0.6", "--voxel", "0.05", "--seed", "4", "-q",
              "--printer", "dlp-resin"]
    for name in ("f.npy", "f.stl"):
        (root / name[2:]).mkdir()
        assert main(["generate", "-o", str(root / name[2:] / name), *common]) == 0
    return root / "npy" / "f.npy", root / "stl" / "f.stl"


def _check_json(path, tmp_path, printer="dlp-resin"):
    from implicit_scaffold.cli import main

    out = tmp_path / f"cert_{path.suffix[1:]}.json"
    assert main(["check", str(path), "--printer", printer, "-o", str(out), "-q"]) in (0, 3)
    return json.loads(out.read_text())


def test_check_of_a_runs_field_and_mesh_measures_the_runs_patient(cylinder_runs, tmp_path):
    # the .npy was measured over its whole grid (the cylinder's corners and the grid's outer layer counted as
    # void: its porosity, pores and drainage were not the run's), the STL over its bounding box: with the run's
    # report beside them both are measured over the run's patient, as generate measured its own certificate
    # (the oracle: the same function on the same voxels, every figure equal)
    npy, stl = cylinder_runs
    run = json.loads(npy.with_suffix(".json").read_text())
    cert_npy, cert_stl = _check_json(npy, tmp_path), _check_json(stl, tmp_path)
    own = run["print_check"]
    assert cert_npy["region"] == "the patient of f.json (cylinder)" == cert_stl["region"]
    assert {k: v for k, v in cert_npy.items() if k not in ("seconds", "source", "region", "timings_s")} == \
        {k: v for k, v in own.items() if k != "seconds"}
    assert cert_npy["porosity"] == pytest.approx(run["porosity_voxel"], abs=1e-12)
    # the STL voxelised on its run's grid is the same solid: every figure but those read from each file's own
    # distance (as built, and the overhangs' normals: the mesh's exact distance, the field's blended one)
    same = ("porosity", "thinnest_mm", "below_min_strut_share", "throat_mm", "pore_throats_mm",
            "void_reached_by_drain_share", "void_reached_by_100um_share", "sealed_voids", "floating_solid")
    assert {k: cert_stl[k] for k in same} == {k: cert_npy[k] for k in same}
    # as built, the field's offset within 0.01 of the mesh's exact one (0.0024 on the 4 mm box)
    assert cert_stl["as_built"]["porosity"] == pytest.approx(cert_npy["as_built"]["porosity"], abs=0.01)


def _within_of_mesh(mesh, points, reach):
    """Which `points` lie within `reach` mm of the triangles of `mesh`: trimesh's closest point on each
    triangle whose centroid is near enough (a triangle within `reach` has its centroid within `reach` plus
    the farthest any triangle's vertex lies from its centroid), a k-d tree finding those."""
    import trimesh
    from scipy.spatial import cKDTree

    tri = np.asarray(mesh.triangles, np.float64)
    centroid = tri.mean(axis=1)
    spread = float(np.linalg.norm(tri - centroid[:, None], axis=2).max())
    lists = cKDTree(centroid).query_ball_point(points, reach + spread)
    which = np.repeat(np.arange(len(points)), [len(c) for c in lists])
    tris = np.concatenate([np.asarray(c, np.int64) for c in lists])
    q = trimesh.triangles.closest_point(tri[tris], points[which])
    near = np.zeros(len(points), bool)
    near[which[np.linalg.norm(q - points[which], axis=1) <= reach]] = True
    return near


def test_as_built_porosity_of_a_runs_field_against_its_meshs_exact_offset(cylinder_runs, tmp_path):
    # the oracle: every void voxel centre of the run's patient (the closed-form cylinder) farther than the
    # deviation from the run's mesh, by exact point-triangle distances (trimesh). The field is not a distance
    # (its gradient is about 0.4 to 1 at the surface), so `field < deviation` grew the solid too far; its
    # first-order offset comes within 0.01 (0.0024 on a 4 mm box), the mesh's own distance within a voxel
    import trimesh

    from implicit_scaffold.measure.morphometry import run_grid

    npy, stl = cylinder_runs
    run = json.loads(npy.with_suffix(".json").read_text())
    grid, delta = run_grid(run), printer_profile("dlp-resin").deviation_mm
    field = np.load(npy)
    x, y, z = np.meshgrid(*grid.axes(), indexing="ij")
    radius = 1.0  # the cylinder of --size 2: diameter 2 mm, axis (1, 1), z in [0, 2]
    region = (np.hypot(x - radius, y - radius) < radius) & (z > 0) & (z < 2.0)
    void = region & (field >= 0)
    points = np.stack([x[void], y[void], z[void]], axis=1)
    far = ~_within_of_mesh(trimesh.load(stl, force="mesh"), points, delta)
    exact = np.count_nonzero(far) / np.count_nonzero(region)
    plain = np.count_nonzero(region & (field >= delta)) / np.count_nonzero(region)
    cert_npy, cert_stl = _check_json(npy, tmp_path), _check_json(stl, tmp_path)
    assert cert_stl["as_built"]["porosity"] == pytest.approx(exact, abs=1.0 / np.count_nonzero(region) * 5)
    assert abs(cert_npy["as_built"]["porosity"] - exact) < 0.01
    assert abs(plain - exact) > 3 * abs(cert_npy["as_built"]["porosity"] - exact)
