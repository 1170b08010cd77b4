"""The OpenCL device: chosen by proof (fake platform lists), the PyPI runtimes' vendors folder,
and every device that works on this machine against the NumPy references."""
from __future__ import annotations

import dataclasses
import os
import subprocess

import numpy as np
import pytest

from implicit_scaffold import opencl
from implicit_scaffold.errors import OpenCLUnavailableError

# float32 coordinates of a few mm relative to the grid origin carry ~1e-7 mm of rounding
TOL = 1e-5


class FakeDevice:
    def __init__(self, name):
        self.name = name
        self.driver_version = "1.0"


class FakePlatform:
    def __init__(self, name, version, devices):
        self.name, self.version, self._devices = name, version, devices

    def get_devices(self):
        if isinstance(self._devices, Exception):
            raise self._devices
        return self._devices


BUILD_FAILURE = ("clBuildProgram failed: BUILD_PROGRAM_FAILURE - clBuildProgram failed: BUILD_PROGRAM_FAILURE\n\n"
                 "Build on <pyopencl.Device 'pthread-AMD EPYC' on 'Portable Computing Language'>:\n\n"
                 "error: unknown target CPU 'generic'\n(options: -I/k)")


def _fake_platforms():
    return [FakePlatform("Portable Computing Language", "OpenCL 3.0 PoCL 3.0-rc2  Linux, LLVM 14.0.6",
                         [FakeDevice("pthread-AMD EPYC")]),
            FakePlatform("Empty Platform", "OpenCL 1.2", []),
            FakePlatform("Gone Platform", "OpenCL 2.0", RuntimeError("clGetDeviceIDs failed: DEVICE_NOT_FOUND")),
            FakePlatform("Intel(R) OpenCL", "OpenCL 3.1 LINUX", [FakeDevice("AMD EPYC")])]


def _probe(rates):
    calls = []

    def probe(pi, di):
        calls.append((pi, di))
        if rates.get(pi) is None:
            raise RuntimeError(BUILD_FAILURE)
        return {"ok": True, "reason": "", "build_seconds": 0.1, "mvoxels_per_second": rates[pi],
                "max_error_mm": 1e-7}

    return probe, calls


def test_a_device_that_fails_to_build_and_platforms_without_devices_are_skipped():
    probe, calls = _probe({3: 20.0})
    checks = opencl.check_devices(_fake_platforms(), probe)
    assert [c.ok for c in checks] == [False, False, False, True]
    # the build log's error line, not its first line
    assert checks[0].reason == "error: unknown target CPU 'generic'"
    assert checks[1].reason == "no devices" and "DEVICE_NOT_FOUND" in checks[2].reason
    # only platforms that have devices are probed
    assert calls == [(0, 0), (3, 0)]
    pick = opencl.choose(checks)
    assert pick.platform == "Intel(R) OpenCL" and pick.position == (3, 0)


def test_the_default_is_the_fastest_and_the_variable_picks_any_working_device():
    platforms = _fake_platforms()
    platforms[0]._devices = [FakeDevice("pthread-AMD EPYC"), FakeDevice("second")]
    probe, _ = _probe({0: 12.0, 3: 30.0})
    checks = opencl.check_devices(platforms, probe)
    assert opencl.choose(checks).platform == "Intel(R) OpenCL"
    probe, _ = _probe({0: 40.0, 3: 30.0})
    checks = opencl.check_devices(platforms, probe)
    assert opencl.choose(checks).position == (0, 0)
    # by platform name, platform version or device name, and the N-th match
    assert opencl.choose(checks, "intel").position == (3, 0)
    assert opencl.choose(checks, "pocl 3.0-rc2").position == (0, 0)
    assert opencl.choose(checks, "portable:1").device == "second"
    assert opencl.choose(checks, "AMD EPYC:1").position == (3, 0)


def test_devices_within_the_probes_noise_of_the_fastest_give_the_first_found():
    # two runtimes on one CPU probe near each other, and which is faster moves with the load: the first found of
    # those near the fastest is used, whichever of them timed faster; one clearly faster is used wherever it is
    platforms = _fake_platforms()
    top = 38.1
    near = top * (1 - opencl.PROBE_NOISE) * 1.01
    far = top * (1 - opencl.PROBE_NOISE) * 0.99
    for rates, want in (({0: top, 3: near}, (0, 0)), ({0: near, 3: top}, (0, 0)),
                        ({0: far, 3: top}, (3, 0)), ({0: top, 3: far}, (0, 0))):
        probe, _ = _probe(rates)
        assert opencl.choose(opencl.check_devices(platforms, probe)).position == want, rates


def test_a_devices_spec_names_it_alone_among_devices_of_the_same_name(monkeypatch):
    # a build child is told its parent's device by IMPLICIT_SCAFFOLD_DEVICE: two devices of one name (two of one
    # GPU), and a name inside another's ("AMD EPYC" in "pthread-AMD EPYC"), each chosen by its own spec
    platforms = _fake_platforms()
    platforms[0]._devices = [FakeDevice("pthread-AMD EPYC"), FakeDevice("pthread-AMD EPYC")]
    platforms[3]._devices = [FakeDevice("AMD EPYC"), FakeDevice("AMD EPYC")]
    probe, _ = _probe({0: 10.0, 3: 30.0})
    checks = opencl.check_devices(platforms, probe)
    monkeypatch.setattr(opencl, "device_checks", lambda: tuple(checks))
    working = [c for c in checks if c.ok]
    assert len(working) == 4
    for c in working:
        assert opencl.choose(checks, opencl._device_spec(c)).position == c.position


def test_a_named_device_that_failed_or_does_not_exist_is_refused_in_one_line():
    probe, _ = _probe({3: 20.0})
    checks = opencl.check_devices(_fake_platforms(), probe)
    with pytest.raises(OpenCLUnavailableError) as e:
        opencl.choose(checks, "portable")
    msg = str(e.value)
    assert "unknown target CPU" in msg and "Intel(R) OpenCL" in msg and "\n" not in msg
    with pytest.raises(OpenCLUnavailableError, match="matches no OpenCL device"):
        opencl.choose(checks, "nvidia")


def test_no_working_device_says_what_to_install(monkeypatch):
    probe, _ = _probe({})
    checks = opencl.check_devices(_fake_platforms(), probe)
    monkeypatch.setattr(opencl._host, "machine", lambda: "x86_64")
    monkeypatch.setattr(opencl.sys, "platform", "linux")
    with pytest.raises(OpenCLUnavailableError) as e:
        opencl.choose(checks)
    msg = str(e.value)
    assert "pip install intel-opencl-rt" in msg and "unknown target CPU" in msg and "\n" not in msg


def test_cli_with_no_working_device_exits_2_in_one_line(monkeypatch, tmp_path, capsys):
    from implicit_scaffold.cli import main

    probe, _ = _probe({})
    checks = tuple(opencl.check_devices(_fake_platforms(), probe))
    monkeypatch.setattr(opencl, "device_checks", lambda: checks)
    monkeypatch.setattr(opencl, "_ACTIVE", {})
    monkeypatch.delenv(opencl.DEVICE_ENV, raising=False)
    monkeypatch.chdir(tmp_path)
    assert main(["generate", "--seeds", "20", "--size", "3", "-o", "s.stl"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no OpenCL device can run the kernels" in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []


def test_a_probe_that_aborts_only_loses_its_device(monkeypatch):
    def aborted(cmd, **kwargs):
        return subprocess.CompletedProcess(cmd, -6, "", "warning: something\nLLVM ERROR: Cannot select: fsqrt\n")

    monkeypatch.setattr(opencl.subprocess, "run", aborted)
    res = opencl._probe_in_child(0, 0)
    assert res["ok"] is False and "signal 6" in res["reason"] and "LLVM ERROR: Cannot select" in res["reason"]


def test_pip_runtimes_are_registered_beside_the_loaders_own(monkeypatch, tmp_path):
    lib = tmp_path / "lib" / "libintelocl.so"
    lib.parent.mkdir()
    lib.write_bytes(b"")
    vendors = tmp_path / "vendors"
    vendors.mkdir()
    (vendors / "pocl.icd").write_text("libpocl.so.2\n")
    monkeypatch.setattr(opencl, "pip_runtime_libraries", lambda: {"intel-cpu": lib})
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.setenv("OCL_ICD_VENDORS", str(vendors))
    folder = opencl.register_runtimes()
    assert folder is not None and os.environ["OCL_ICD_VENDORS"] == folder
    assert folder.startswith(str(tmp_path / "cache"))
    lines = sorted(p.read_text().strip() for p in (tmp_path / "cache").rglob("*.icd"))
    assert lines == sorted(["libpocl.so.2", str(lib)])
    # a second call (or a child process that inherits the variable) changes nothing
    assert opencl.register_runtimes() is None and os.environ["OCL_ICD_VENDORS"] == folder


def test_every_kernel_builds_on_the_chosen_device():
    from implicit_scaffold.fields.lattice import BLOCK

    names = opencl.kernel_names()
    assert {"lattice", "patient"} <= set(names)
    assert {"lattice_paper", "lattice_struts", "bin_sort"} <= set(names["lattice"])
    assert {"triangle_distance", "triangle_nearest", "triangle_clamped"} <= set(names["patient"])
    for source, wanted in names.items():
        built = {k.function_name for k in opencl.program(source, BLOCK=BLOCK).all_kernels()}
        assert set(wanted) <= built, source


def test_a_build_lock_left_by_a_killed_run_does_not_stop_the_next_build(monkeypatch, tmp_path):
    # PyOpenCL's lock file in the binary cache, as a run killed mid-build leaves it: the next build must go
    # ahead and remove it (it waited a minute for it, then failed: 31 tests of one CI run), and store its
    # binary in the cache
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    folder = opencl.binaries_dir()
    assert folder.is_relative_to(tmp_path)
    folder.mkdir(parents=True)
    (folder / "lock").write_text("")
    # defines of its own: a build, not this process's program kept from an earlier test
    built = {k.function_name for k in opencl.program("mechanics", NCASE=1, USE_DOUBLE=0, STALE_LOCK=1).all_kernels()}
    assert "stiffness_rows" in built
    assert not (folder / "lock").exists()
    assert any(entry.is_dir() for entry in folder.iterdir())  # the binary, cached


def test_programs_not_built_on_this_machine_are_compiled_in_a_child(monkeypatch, tmp_path):
    # a compile loads the runtime's compiler into the process (+152 MiB measured), which a solve's memory
    # estimate does not count: a measure's programs not built on this machine yet are built by a child, and
    # this process loads their binaries from the cache
    import shutil

    from implicit_scaffold.measure import mechanics_cl

    opencl.context()  # this process's device, chosen (and its probes cached) before the cache moves
    probes = list(opencl.cache_dir().glob("devices-*.json"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    # the child reads the same probes, so it builds for this process's device: probing again, it would choose
    # by its own timing, and two devices can be near (Intel's runtime 38.1 and PoCL 35.4 Mvoxel/s on one
    # machine; a CI run, 2026-12-07, had the child build for the other one, and this process compiled)
    opencl.cache_dir().mkdir(parents=True, exist_ok=True)
    for path in probes:
        shutil.copy(path, opencl.cache_dir() / path.name)
    monkeypatch.setattr(opencl, "_COMPILED", [])
    # defines of their own: builds, not this process's programs kept from an earlier test
    mine = [dict(NCASE=1, USE_DOUBLE=0, CHILD=1), dict(NCASE=2, USE_DOUBLE=0, CHILD=1)]
    assert opencl.unbuilt("mechanics", mine) == mine
    mechanics_cl.prebuild(mine)
    assert opencl.unbuilt("mechanics", mine) == []
    for defines in mine:
        opencl.program("mechanics", VOTE=int(mechanics_cl.has_vote()), **defines)
    assert not opencl._COMPILED
    # the device's own defines are left out of the markers: they are read before the device is chosen
    assert opencl.unbuilt("mechanics", [dict(mine[0], VOTE=1 - int(mechanics_cl.has_vote()))]) == []
    # a build in this process that misses the cache compiles, and marks the variant built
    alone = dict(NCASE=1, USE_DOUBLE=0, CHILD=2)
    opencl.program("mechanics", VOTE=0, **alone)
    assert opencl._COMPILED and opencl.unbuilt("mechanics", [alone]) == []


def test_a_built_marker_is_one_devices(monkeypatch, tmp_path):
    # a binary is one device's: variants built for this process's device are not built for another, whose
    # process has a child build them; with two working devices here, a child builds for the device of `using`
    # (whether this process then loads a binary is the runtime's: PyOpenCL leaves PoCL's to PoCL's own cache)
    import shutil

    from implicit_scaffold.measure import mechanics_cl

    opencl.context()
    probes = list(opencl.cache_dir().glob("devices-*.json"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    opencl.cache_dir().mkdir(parents=True, exist_ok=True)
    for path in probes:
        shutil.copy(path, opencl.cache_dir() / path.name)
    mine = [dict(NCASE=1, USE_DOUBLE=0, CHILD=3)]
    opencl.program("mechanics", VOTE=int(mechanics_cl.has_vote()), **mine[0])
    assert opencl.unbuilt("mechanics", mine) == []
    here = opencl.build_device()
    other = dataclasses.replace(here, device=here.device + " (another)")
    monkeypatch.setattr(opencl, "build_device", lambda: other)
    assert opencl.unbuilt("mechanics", mine) == mine
    monkeypatch.undo()
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    rest = [c for c in opencl.working_devices() if c.position != here.position]
    if not rest:
        return
    with opencl.using(rest[0]):
        assert opencl.unbuilt("mechanics", mine) == mine
        # the child marks what it built for the device its context holds: this one, which it was told
        mechanics_cl.prebuild(mine)
        assert opencl.unbuilt("mechanics", mine) == []


def test_a_cache_folder_that_cannot_be_made_leaves_the_build_uncached(monkeypatch, tmp_path):
    # the user's cache path runs through a file: nothing can be kept there, and the build still happens.
    # The device is chosen and PyOpenCL's own caches opened first, as in a process that has run kernels: in a
    # fresh one PyOpenCL's kernel invoker cache fails on such a path itself (this test, run alone, failed so)
    opencl.program("mechanics", NCASE=1, USE_DOUBLE=0).all_kernels()
    (tmp_path / "file").write_text("")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "file" / "cache"))
    built = {k.function_name for k in opencl.program("mechanics", NCASE=1, USE_DOUBLE=0, NO_CACHE=1).all_kernels()}
    assert "stiffness_rows" in built
    assert not opencl.binaries_dir().exists()


def test_every_working_device_matches_the_numpy_references(small_cells):
    import implicit_scaffold
    from implicit_scaffold.run.grid import Grid
    from implicit_scaffold.fields.lattice import (lattice_sdf, lattice_sdf_reference, struts_field,
                                           struts_field_reference)
    from implicit_scaffold.fields.patient_mesh import triangle_distance, triangle_distance_reference
    from implicit_scaffold.geometry.skeleton import scaled_skeleton, voronoi_edges

    devices = opencl.working_devices()
    assert devices, "the chosen device is a working one"
    sk = scaled_skeleton(small_cells, 0.75, 0.75)
    edges = voronoi_edges(small_cells)
    grid = Grid.covering(small_cells.lo, small_cells.hi, 0.05)
    rng = np.random.default_rng(2)
    idx = np.stack([rng.integers(0, s, 1500) for s in grid.shape], 1)
    pts = grid.indices_to_points(idx)
    paper_ref = lattice_sdf_reference(sk, pts, cutoff=0.15)
    struts_ref = struts_field_reference(edges, pts, cutoff=0.3, blend=0.05)
    # the smooth minimum sums the struts nearer than the cut-off, so the field steps where a
    # strut lies at the cut-off: float32 and float64 may see it on either side there
    from implicit_scaffold.fields.lattice import _segment_dist

    d = _segment_dist(pts[:, None], edges[None, :, 0], edges[None, :, 1])
    smooth = ~(np.abs(d - 0.3) < 1e-4).any(axis=1)
    assert smooth.mean() > 0.95
    tris = rng.uniform(0, 2, (15, 3, 3))
    tri_ref = triangle_distance_reference(pts, tris)
    near = tri_ref <= 2 * grid.spacing
    assert near.sum() > 50
    fields, porosity = [], []
    for dev in devices:
        with opencl.using(dev):
            paper = lattice_sdf(sk, grid, cutoff=0.15)
            struts = struts_field(edges, grid, cutoff=0.3, blend=0.05)
            tri = triangle_distance(tris.reshape(-1, 3), np.arange(45).reshape(-1, 3), grid).reshape(grid.shape)
            assert np.abs(paper[tuple(idx.T)] - paper_ref).max() < TOL, dev.label
            assert np.abs(struts[tuple(idx.T)] - struts_ref)[smooth].max() < TOL, dev.label
            assert np.abs(tri[tuple(idx.T)][near] - tri_ref[near]).max() < TOL, dev.label
            runs = [implicit_scaffold.generate(seeds=40, size=3.0, voxel=0.06, mesh=False, morphometry=False)
                    for _ in range(2)]
            # one device, the same inputs and seed: the same bytes
            assert runs[0].field.tobytes() == runs[1].field.tobytes(), dev.label
            fields.append((paper, struts, runs[0].field))
            porosity.append(runs[0].report["porosity_voxel"])
    for other, p in zip(fields[1:], porosity[1:]):
        for a, b in zip(fields[0], other):
            assert np.abs(a - b).max() < TOL
        assert abs(p - porosity[0]) <= 1e-4


@pytest.mark.parametrize("offset", [0, 4])
def test_a_host_buffer_reads_the_hosts_values_aligned_or_not(offset):
    # an aligned array is read in place, any other is copied: either way the device reads the host's values
    # (oracle: the array itself, read back)
    import pyopencl as cl

    host = opencl.aligned_empty((1000 + offset,), np.int32)
    assert host.ctypes.data % opencl.ALIGN == 0 and host.flags.c_contiguous
    host[:] = np.arange(host.size, dtype=np.int32) * 7 - 3
    view = host[offset:]  # 16 bytes past the boundary when offset is 4
    buf = opencl.host_buffer(view)
    back = np.empty_like(view)
    _, queue = opencl.context()
    cl.enqueue_copy(queue, back, buf)
    queue.finish()
    assert np.array_equal(back, view)
    assert opencl.host_buffer(np.zeros(0, np.float32)).size > 0  # an empty array: a dummy, as to_device's
