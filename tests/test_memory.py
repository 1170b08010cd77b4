"""Tests of implicit_scaffold.run.memory: keeping freed memory in a worker's heap, or in a solve's."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

#: in a fresh process: what it holds (RSS, MiB) with a 256 MiB array, and after freeing it,
#: with keep_freed_memory() called first or not (argv[1])
_FREE_AND_LOOK = """
import json, sys
import numpy as np, psutil
from implicit_scaffold.run.memory import keep_freed_memory
if sys.argv[1] == "keep":
    keep_freed_memory()
rss = lambda: psutil.Process().memory_info().rss / 2**20
a = np.ones(2**25)  # 256 MiB, touched
held = rss()
del a
print(json.dumps({"held": held, "after": rss()}))
"""


def _held_and_after(mode: str) -> dict:
    done = subprocess.run([sys.executable, "-c", _FREE_AND_LOOK, mode], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_keep_freed_memory_keeps_a_large_freed_block_in_the_process():
    # by default glibc maps a block this large on its own and returns it to the system when
    # freed; kept, it stays with the process for the next allocation
    plain = _held_and_after("plain")
    kept = _held_and_after("keep")
    assert plain["held"] - plain["after"] > 200
    assert kept["held"] - kept["after"] < 50


#: in a fresh process: what it holds (RSS, MiB) after freeing a 256 MiB array inside keeping_freed_memory(),
#: nested twice, after leaving the inner block, after leaving the outer one, and after freeing another after it
_KEEPING_AND_AFTER = """
import json
import numpy as np, psutil
from implicit_scaffold.run.memory import keeping_freed_memory
rss = lambda: psutil.Process().memory_info().rss / 2**20
start = rss()
out = {}
with keeping_freed_memory():
    with keeping_freed_memory():
        a = np.ones(2**25)  # 256 MiB, touched
        del a
        out["inner"] = rss() - start
    out["outer"] = rss() - start
out["left"] = rss() - start
b = np.ones(2**25)
del b
out["after"] = rss() - start
with keeping_freed_memory(False):
    c = np.ones(2**25)
    del c
    out["off"] = rss() - start
print(json.dumps(out))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_keeping_freed_memory_keeps_it_in_its_blocks_and_hands_it_back_after():
    done = subprocess.run([sys.executable, "-c", _KEEPING_AND_AFTER], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    held = json.loads(done.stdout.strip().splitlines()[-1])
    # freed inside the blocks, the 256 MiB stay with the process until the outermost block ends
    assert held["inner"] > 200 and held["outer"] > 200
    # then it goes back to the system, and a large block freed after is returned at once, as by default
    assert held["left"] < 50
    assert held["after"] < 50
    # keep=False: a block that changes nothing
    assert held["off"] < 50


def test_a_solve_keeps_freed_memory_only_with_six_load_cases_a_block(monkeypatch):
    import numpy as np

    from implicit_scaffold.measure import mechanics as M
    from implicit_scaffold.run import memory

    calls = []
    monkeypatch.setattr(memory, "_glibc", lambda name, *args: calls.append(name))
    solid = np.ones((3, 3, 3), bool)
    mat = M.material("ti64")
    M.homogenize(solid, 0.1, mat, cases_per_block=1, tol=1e-6)
    # under a budget too short for six cases a block the solve hands its memory back as it goes
    assert "mallopt" not in calls
    M.homogenize(solid, 0.1, mat, tol=1e-6)
    M.compress(solid, 0.1, mat, tol=1e-6)
    # six a block (the default), and a compression: kept (thresholds raised, then restored), then trimmed
    assert calls.count("mallopt") == 8 and calls.count("malloc_trim") == 2


def test_a_size_is_named_as_max_memory_takes_it_a_whole_mib_as_given():
    from implicit_scaffold.run.memory import format_size, parse_memory

    # a budget given in whole MiB is named as given (a refusal once named --max-memory 1M as 10M)
    for given in ("1M", "7M", "550M", "1000M"):
        assert format_size(parse_memory(given)) == given
    # anything else is rounded up: ten MiB below 1 GiB, a tenth of a GiB above
    assert format_size(2**20 + 1) == "10M" and format_size(341 * 2**20 + 5) == "350M"
    assert format_size(4 * 2**30) == "4.0G" and format_size(4 * 2**30 + 1) == "4.1G"


def test_a_messages_amount_is_never_zero_gib():
    # "95 seeds need about 0.00 GiB": under a GiB, whole MiB (rounded up)
    from implicit_scaffold.run.memory import amount

    assert [amount(v) for v in (3.2 * 2**20, 50 * 2**20, 2**30, 3.456 * 2**30)] == \
        ["4 MiB", "50 MiB", "1.00 GiB", "3.46 GiB"]


def _sysfs(tmp_path, devices: dict):
    """A sysfs tree of virtio devices: name -> (device id, features, bound to a driver)."""
    root = tmp_path / "sys"
    for name, (device, features, bound) in devices.items():
        folder = root / "bus" / "virtio" / "devices" / name
        folder.mkdir(parents=True)
        (folder / "device").write_text(f"0x{device:04x}\n")
        (folder / "features").write_text(features + "\n")
        if bound:
            (folder / "driver").mkdir()
    return root


def _bits(*on, width=64) -> str:
    return "".join("1" if i in on else "0" for i in range(width))


def test_free_page_reporting_is_a_bound_virtio_balloon_with_feature_bit_5(tmp_path):
    from implicit_scaffold.run.memory import free_page_reporting

    # the Virtio 1.2 specification: device id 5 is the memory balloon, its feature bit 5 VIRTIO_BALLOON_F_REPORTING;
    # the other devices and bits below are a block device and the balloon's stats and deflate-on-OOM bits
    balloon_reports = _bits(1, 2, 5, 32)
    assert free_page_reporting(_sysfs(tmp_path / "a", {"virtio0": (5, balloon_reports, True),
                                                       "virtio1": (2, _bits(1, 5), True)}))
    assert not free_page_reporting(_sysfs(tmp_path / "b", {"virtio0": (5, _bits(1, 2, 32), True)}))
    assert not free_page_reporting(_sysfs(tmp_path / "c", {"virtio0": (5, balloon_reports, False)}))
    assert not free_page_reporting(_sysfs(tmp_path / "d", {"virtio1": (2, balloon_reports, True)}))
    assert not free_page_reporting(tmp_path / "none")


def test_numpy_stops_asking_for_huge_pages_only_where_the_host_takes_free_memory_back(tmp_path, monkeypatch):
    from implicit_scaffold.run.memory import avoid_cold_huge_pages, numpy_huge_pages_switch

    get, put = numpy_huge_pages_switch("get"), numpy_huge_pages_switch("set")
    reporting = _sysfs(tmp_path / "a", {"virtio0": (5, _bits(1, 2, 5), True)})
    plain = _sysfs(tmp_path / "b", {"virtio0": (5, _bits(1, 2), True)})
    before = put(True)
    try:
        monkeypatch.delenv("NUMPY_MADVISE_HUGEPAGE", raising=False)
        assert not avoid_cold_huge_pages(plain) and get()
        assert avoid_cold_huge_pages(reporting) and not get()
        put(True)
        # the user's own choice of NumPy's switch stands
        monkeypatch.setenv("NUMPY_MADVISE_HUGEPAGE", "1")
        assert not avoid_cold_huge_pages(reporting) and get()
    finally:
        put(before)


def test_importing_the_package_decides_huge_pages_by_this_machine():
    # in fresh processes: NumPy's own default, then after importing the package
    code = ("import sys, numpy as np\ncore = getattr(np, '_core', None) or np.core\nif sys.argv[1] == 'package':\n"
            "    import implicit_scaffold\n    from implicit_scaffold.run.memory import free_page_reporting\n"
            "else:\n    free_page_reporting = lambda: None\n"
            "print(core.multiarray._get_madvise_hugepage(), free_page_reporting())")
    env = {k: v for k, v in os.environ.items() if k != "NUMPY_MADVISE_HUGEPAGE"}
    runs = {}
    for mode in ("numpy", "package"):
        done = subprocess.run([sys.executable, "-c", code, mode], capture_output=True, text=True, env=env)
        assert done.returncode == 0, done.stderr[-2000:]
        runs[mode] = done.stdout.split()
    default, (after, reporting) = runs["numpy"][0], runs["package"]
    assert after == ("False" if reporting == "True" else default)
