"""Memory budgets: what a run may hold, what it holds now, and giving freed memory back.

Every stage that sizes its work by memory asks here. A run's budget (``--max-memory``)
defaults to :data:`DEFAULT_MAX_MEMORY`, or less when less is free, so that a run sized
on one machine behaves the same on another; a grid that does not fit whole is built in
slabs (:mod:`~implicit_scaffold.run.tiled`), and one that cannot fit even so is refused before the work
starts, naming the smallest budget that would do.
"""
from __future__ import annotations

import contextlib
import ctypes
import gc
import os
import sys
import threading
from pathlib import Path

import numpy as np

from ..errors import ScaffoldError

#: the default --max-memory, bytes: 4 GiB, whatever the machine has beyond it
DEFAULT_MAX_MEMORY = 4 * 2**30
#: at most this share of the memory free when the run starts, when that is below the default
DEFAULT_MEMORY_SHARE = 0.8


def available_memory() -> int:
    """Bytes of memory this process can still take (free plus reclaimable cache)."""
    import psutil

    return int(psutil.virtual_memory().available)


def default_max_memory() -> int:
    """The default memory budget, bytes: :data:`DEFAULT_MAX_MEMORY`, or a safe share of
    what is free now when that is less."""
    return int(min(DEFAULT_MAX_MEMORY, DEFAULT_MEMORY_SHARE * available_memory()))


def parse_memory(text) -> int:
    """A memory size such as ``4G``, ``3.5GB``, ``800M`` or ``800MiB`` (a bare number is GiB), as bytes."""
    units = {"": 2**30, "k": 2**10, "m": 2**20, "g": 2**30, "t": 2**40}
    raw = str(text).strip().lower()
    for suffix in ("ib", "b"):
        if raw.endswith(suffix) and raw[:-len(suffix)][-1:] in "kmgt":
            raw = raw[:-len(suffix)]
            break
    unit = raw[-1:] if raw[-1:] in "kmgt" else ""
    try:
        value = float(raw[:len(raw) - len(unit)])
    except ValueError:
        raise ScaffoldError(f"--max-memory must be a size such as 4G or 800M, got {text!r}") from None
    if not (np.isfinite(value) and value > 0):
        raise ScaffoldError(f"--max-memory must be a positive size such as 4G, got {text!r}")
    return int(value * units[unit])


def budget(max_memory=None) -> int:
    """`max_memory` as bytes: a size (``"4G"``), a number of bytes, or None for the default."""
    if max_memory is None:
        return default_max_memory()
    if isinstance(max_memory, str):
        return parse_memory(max_memory)
    return int(max_memory)


def format_size(nbytes: float) -> str:
    """A size as ``--max-memory`` takes it, rounded up to the next tenth of a GiB (below 1 GiB: to the next
    ten MiB, but a whole number of MiB as it is, so that a budget given as ``1M`` is named as given)."""
    if nbytes >= 2**30:
        return f"{np.ceil(nbytes / 2**30 * 10) / 10:.1f}G"
    if nbytes > 0 and nbytes % 2**20 == 0:
        return f"{int(nbytes) // 2**20}M"
    return f"{int(np.ceil(nbytes / 2**20 / 10) * 10)}M"


def amount(nbytes: float) -> str:
    """A size to read in a message: GiB to two decimals from 1 GiB, else whole MiB (a 50 MiB need was
    "0.00 GiB")."""
    if nbytes >= 2**30:
        return f"{nbytes / 2**30:.2f} GiB"
    return f"{max(1, int(np.ceil(nbytes / 2**20)))} MiB"


def process_memory() -> int:
    """Bytes this process holds now (resident set)."""
    import psutil

    return int(psutil.Process().memory_info().rss)


def peak_memory(children: bool = False) -> int:
    """The most bytes this process has held (its peak resident set), or the largest of its
    finished child processes' peaks.

    On Linux the process's own peak is its address space's high-water mark (``VmHWM``):
    ``ru_maxrss`` keeps, across ``exec``, the peak of the process it was forked from, so a
    run started by a large parent would report the parent's size.
    """
    import resource

    if not children:
        try:
            with open("/proc/self/status") as fh:
                for line in fh:
                    if line.startswith("VmHWM:"):
                        return int(line.split()[1]) * 1024
        except OSError:
            pass
    who = resource.RUSAGE_CHILDREN if children else resource.RUSAGE_SELF
    return int(resource.getrusage(who).ru_maxrss) * 1024


_LIBC = None


def _glibc(name: str, *args) -> None:
    """Call glibc's `name` with `args` on Linux; nothing on another C library or system."""
    global _LIBC
    if not sys.platform.startswith("linux"):
        return
    try:
        if _LIBC is None:
            _LIBC = ctypes.CDLL("libc.so.6")
        getattr(_LIBC, name)(*args)
    except (OSError, AttributeError):  # another C library
        pass


def release() -> int:
    """Give the memory freed so far back to the system; return what the process holds then.

    NumPy's large arrays are returned when freed, but the many small blocks of a stage
    (voro++'s cells as Python objects, sorting temporaries) stay in the C heap, where the
    resident set keeps counting them; glibc's ``malloc_trim`` hands them back. Called
    between stages and slabs, so that what a slab may take is measured on what is held.
    """
    # the young generations only: a stage's cyclic garbage is recent, and a full collection
    # walks every object the imported libraries hold (30 ms a call, three calls a run)
    gc.collect(1)
    _glibc("malloc_trim", 0)
    return process_memory()


#: glibc's mallopt parameters: the size from which a block is mapped on its own, and the free
#: top of the heap above which free() returns memory to the system
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3


def keep_freed_memory() -> None:
    """Have glibc keep freed memory, large blocks included, for the next allocations of this process.

    For a worker process that does the same work slab after slab (the mesh's): by default
    every block above 32 MB is mapped on its own and unmapped when freed, so each slab
    faults its arrays in again page by page, zeroed by the system, and on this project's
    virtual machine that system time was half a mesh worker's time. Kept in the heap
    instead, the next slab's arrays reuse those pages. What the process holds between
    slabs is then its largest slab's, which is what its memory budget counts anyway.
    Nothing on other C libraries.
    """
    global _kept_for_good
    _kept_for_good = True
    _keep()


def _keep() -> None:
    # (mallopt takes a C int) blocks above 1 GiB are still mapped on their own
    _thresholds(2**30, 2**31 - 1)


def _thresholds(mmap: int, trim: int) -> None:
    """glibc's mmap and trim thresholds, bytes."""
    _glibc("mallopt", _M_MMAP_THRESHOLD, mmap)
    _glibc("mallopt", _M_TRIM_THRESHOLD, trim)


#: what glibc's thresholds go back to after :func:`keeping_freed_memory`: its dynamic threshold's ceiling on a
#: 64-bit system (a block freed above it is mapped on its own, and the next such block with it) and twice it for
#: the heap's free top, as the dynamic rule sets them; mallopt ends the dynamic rule, so they stay fixed after
_MMAP_AFTER = 32 * 2**20
_TRIM_AFTER = 64 * 2**20
_kept_for_good = False
_keeping = 0
_keeping_lock = threading.Lock()


@contextlib.contextmanager
def keeping_freed_memory(keep: bool = True):
    """Within this block glibc keeps the memory freed (:func:`keep_freed_memory`); on leaving the outermost
    block it hands it back (:func:`release`) and maps large blocks on their own again. With `keep` False
    the block changes nothing (inside another block, memory stays kept by that one).

    For a solver, whose steps free and allocate the same large arrays again and again: a page the system
    took back is zeroed again when touched. (The 6 ms a MB first measured for that on this project's virtual
    machines, a fresh 130 MB array written in 0.7 to 1.2 s against 26 ms while the memory was kept, was
    NumPy's huge pages faulted in from the host: :func:`avoid_cold_huge_pages`. In small pages the 128^3
    benchmark scaffold's homogenization still took 0.1 to 0.4 s less inside the block, run twice in a process.)
    What the process holds within the block is its peak so far, which is what a solve's memory budget counts.
    Nothing on other C libraries; a process that keeps its memory for good stays so."""
    global _keeping
    if not keep:
        yield
        return
    with _keeping_lock:  # solves in two threads: the thresholds go back when the last one ends
        if _keeping == 0 and not _kept_for_good:
            _keep()
        _keeping += 1
    try:
        yield
    finally:
        with _keeping_lock:
            _keeping -= 1
            last = _keeping == 0 and not _kept_for_good
            if last:
                _thresholds(_MMAP_AFTER, _TRIM_AFTER)
        if last:
            release()


#: a virtio balloon's device id, and its feature bit VIRTIO_BALLOON_F_REPORTING (the Virtio 1.2 specification,
#: 5.5.3): the guest reports the free memory it holds in blocks of 2 MB or more to its host, which takes it back
_BALLOON_DEVICE = 0x5
_BALLOON_REPORTING = 5


def free_page_reporting(sysfs="/sys") -> bool:
    """Whether this machine hands its free memory back to its host: a virtio balloon device, bound to its
    driver, that has negotiated free page reporting (read from `sysfs`; False where there is none).

    ``features`` in a virtio device's sysfs folder is one character a feature bit, bit 0 first."""
    root = Path(sysfs) / "bus" / "virtio" / "devices"
    try:
        devices = sorted(root.iterdir())
    except OSError:
        return False
    for device in devices:
        try:
            if int((device / "device").read_text().strip(), 16) != _BALLOON_DEVICE:
                continue
            bits = (device / "features").read_text().strip()
        except (OSError, ValueError):
            continue
        if len(bits) > _BALLOON_REPORTING and bits[_BALLOON_REPORTING] == "1" and (device / "driver").exists():
            return True
    return False


def avoid_cold_huge_pages(sysfs="/sys") -> bool:
    """Stop NumPy asking for transparent huge pages on a machine that reports its free memory to its host
    (:func:`free_page_reporting`); return whether it was stopped. Called once, when the package is imported.

    NumPy advises the system to back each array of 4 MB or more with 2 MB pages (``madvise``). A huge page
    needs a free 2 MB block, and on such a machine those are the blocks the host has taken back: each is
    faulted in from the host. On this project's virtual machines a fresh 128 MB array took 480 to 870 ms to
    fill in huge pages against 54 to 75 ms in 4 kB pages (63 huge-page faults against 32,768 small ones), and
    the default ``generate`` took 14.79 and 13.52 s against 8.44 and 7.58 s. Small pages come from the blocks
    the machine holds already. A user's own ``NUMPY_MADVISE_HUGEPAGE`` (NumPy's switch for the same thing,
    read when NumPy is imported) is left to decide.
    """
    if "NUMPY_MADVISE_HUGEPAGE" in os.environ or not free_page_reporting(sysfs):
        return False
    setter = numpy_huge_pages_switch("set")
    if setter is None:
        return False
    setter(False)
    return True


def numpy_huge_pages_switch(which: str):
    """NumPy's ``_get_madvise_hugepage`` (`which` "get") or ``_set_madvise_hugepage`` ("set"), where NumPy 2
    (``numpy._core``) or NumPy 1 (``numpy.core``) keeps it; None in a NumPy without it."""
    core = getattr(np, "_core", None) or getattr(np, "core", None)
    return getattr(getattr(core, "multiarray", None), f"_{which}_madvise_hugepage", None)


def check_memory(grid, bytes_per_voxel: int, available: int | None = None) -> int:
    """Raise a :class:`ScaffoldError` before allocating a grid that cannot fit.

    Returns
    -------
    int
        The estimate, bytes.
    """
    need = grid.memory_estimate(bytes_per_voxel)
    have = available_memory() if available is None else int(available)
    if need > have:
        raise ScaffoldError(
            f"a grid of {grid.shape[0]}x{grid.shape[1]}x{grid.shape[2]} voxels needs about "
            f"{need / 2**30:.1f} GiB but only {have / 2**30:.1f} GiB is free; "
            f"use a larger --voxel (e.g. {grid.spacing * (need / have) ** (1 / 3) * 1.1:.3g} mm)")
    return need
