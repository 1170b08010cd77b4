"""The one place that finds the OpenCL device, creates the context and compiles kernels.

Runtimes
--------
pyopencl finds OpenCL runtimes through its ICD loader. Three can be there:

- PoCL from pyopencl's wheel (``pocl-binary-distribution``): PoCL 3.0-rc2 on LLVM 14,
  which cannot name CPUs newer than its tables; on such a host it fails to build, builds
  programs with no kernels, or aborts the process at the first launch.
- Intel's CPU runtime from PyPI (``intel-opencl-rt``, a dependency on x86-64 Linux): its
  library lands in the environment's ``lib/``, where the loader does not look, so
  :func:`register_runtimes` writes a vendors folder naming it (with the system's own
  ``.icd`` files) and points ``OCL_ICD_VENDORS`` at it before pyopencl lists platforms.
- Any system runtime (``/etc/OpenCL/vendors``), e.g. Debian's ``pocl-opencl-icd``.

The device is chosen by proof, not by name: every device found is probed once per machine
and set of runtimes, each in a child process of its own (a runtime that cannot compile
for the host may abort rather than raise). The probe builds every kernel of ``kernels/``,
runs the lattice, struts and triangle kernels on a small grid against their NumPy
references, and times the lattice kernel. The fastest device that passes is used, or of
those within :data:`PROBE_NOISE` of it the first found (a probe's one timing cannot tell
them apart, and a machine should keep one device); one that fails is skipped with one line
saying why. The verdicts are kept in the user's
cache folder (:func:`cache_dir`), keyed by the runtimes, the devices, the host CPU and
the kernel sources, so later runs start at once.

``IMPLICIT_SCAFFOLD_DEVICE="TEXT[:N]"`` picks the N-th device (default 0) whose platform
name, platform version or device name contains TEXT (case-insensitive), e.g. ``intel``,
``pocl 3.1`` or ``portable:0``. Kernel sources live in the top-level ``kernels/`` folder,
which the build installs as the package ``implicit_scaffold.kernels``.
"""
from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import os
import platform as _host
import re
import subprocess
import sys
import time
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from .errors import OpenCLUnavailableError, ScaffoldWarning

DEVICE_ENV = "IMPLICIT_SCAFFOLD_DEVICE"
#: build options of every program. No -cl-fast-relaxed-math, no native_ functions: the
#: runtimes must agree to 1e-5 mm (measured: the paper field bit for bit, the struts'
#: smooth minimum to 3e-8 mm between Intel's runtime and PoCL 3.1)
BUILD_OPTIONS = ()
#: seconds a device's probe may take before it is skipped as hung
PROBE_TIMEOUT = 300.0
#: the probe's sanity bound against the NumPy references (the tests hold 1e-5 mm)
PROBE_TOLERANCE = 1e-4
#: devices whose probed rates lie within this share of the fastest's are taken as equally fast, and the first
#: found of them is used: the rate is one timing, and on a loaded machine it moves by more than two runtimes
#: on one CPU differ (Intel's 38.1 and PoCL's 35.4 Mvoxel/s on one machine, 2026-12-07; a build child that
#: probed again under a CI run's load chose PoCL where its parent had chosen Intel's). The first found is the
#: same on every run of a machine, and the results' bits are one runtime's
PROBE_NOISE = 0.15


class DeviceWarning(ScaffoldWarning):
    """An OpenCL device was found but skipped: the message names it and says why."""


def kernels_dir() -> Path:
    """Folder that holds the ``*.cl`` sources, from an install or a checkout."""
    try:
        from importlib.resources import files

        path = Path(str(files("implicit_scaffold.kernels")))
        if (path / "common.cl").is_file():
            return path
    except (ModuleNotFoundError, TypeError):
        pass
    path = Path(__file__).resolve().parent.parent / "kernels"
    if (path / "common.cl").is_file():
        return path
    raise OpenCLUnavailableError(
        "the OpenCL kernel sources (kernels/*.cl) are missing from the install; "
        "reinstall with pip install -e .")


def kernel_names() -> dict[str, list[str]]:
    """Every program of ``kernels/`` (a file with ``__kernel`` functions) and its kernels' names."""
    names = {}
    for path in sorted(kernels_dir().glob("*.cl")):
        found = re.findall(r"__kernel\s+void\s+(\w+)", path.read_text())
        if found:
            names[path.stem] = found
    return names


def cache_dir() -> Path:
    """The user's cache folder for this tool (``$XDG_CACHE_HOME/implicit_scaffold``)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "implicit_scaffold"


def _write_atomic(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


# ----------------------------------------------------------------------------- runtimes


def pip_runtime_libraries() -> dict[str, Path]:
    """OpenCL runtimes installed from PyPI whose library the ICD loader would not find.

    Returns
    -------
    dict
        ``{"intel-cpu": path of libintelocl.so}`` when ``intel-opencl-rt`` is installed.
    """
    from importlib import metadata

    found = {}
    try:
        dist = metadata.distribution("intel-opencl-rt")
    except metadata.PackageNotFoundError:
        return found
    for f in dist.files or ():
        if f.name == "libintelocl.so":
            path = Path(dist.locate_file(f)).resolve()
            if path.is_file():
                found["intel-cpu"] = path
    return found


def _vendor_files() -> dict[str, str]:
    """The ``.icd`` files the loader reads today: ``OCL_ICD_VENDORS`` (a folder or one file)
    or else the system folder. Name -> the library line."""
    given = os.environ.get("OCL_ICD_VENDORS")
    source = Path(given) if given else Path("/etc/OpenCL/vendors")
    paths = [source] if source.is_file() else sorted(source.glob("*.icd")) if source.is_dir() else []
    out = {}
    for p in paths:
        try:
            out[p.name] = p.read_text().strip()
        except OSError:
            continue
    return out


def register_runtimes() -> str | None:
    """Point the ICD loader at the runtimes installed from PyPI, keeping the ones it had.

    Writes a vendors folder under :func:`cache_dir` (named by its content, written
    atomically) and sets ``OCL_ICD_VENDORS`` to it. Must run before pyopencl first lists
    platforms; does nothing when no PyPI runtime is installed or it is already registered.

    Returns
    -------
    str or None
        The folder now in ``OCL_ICD_VENDORS``, or None when nothing was changed.
    """
    libraries = pip_runtime_libraries()
    if not libraries:
        return None
    files = _vendor_files()
    listed = set(files.values())
    for name, lib in libraries.items():
        if str(lib) not in listed:
            files[f"implicit-scaffold-{name}.icd"] = str(lib)
    if set(files.values()) == listed:
        return None
    digest = hashlib.sha256(json.dumps(sorted(files.items())).encode()).hexdigest()[:16]
    for base in (cache_dir(), Path(os.environ.get("TMPDIR", "/tmp")) / f"implicit_scaffold-{os.getuid()}"):
        folder = base / f"icd-{digest}"
        try:
            for name, line in files.items():
                target = folder / name
                if not (target.is_file() and target.read_text().strip() == line):
                    _write_atomic(target, line + "\n")
        except OSError:
            continue
        os.environ["OCL_ICD_VENDORS"] = str(folder)
        return str(folder)
    return None


def _install_hint() -> str:
    machine, system = _host.machine().lower(), sys.platform
    if system.startswith("linux") and machine in ("x86_64", "amd64"):
        return ("pip install intel-opencl-rt intel-cmplr-lib-rt (Intel's CPU runtime, any x86-64 CPU), "
                "or a system driver such as apt install pocl-opencl-icd")
    if system.startswith("linux"):
        return "install an OpenCL driver for this CPU, e.g. apt install pocl-opencl-icd"
    if system == "darwin":
        return "install PoCL (brew install pocl) or use a Mac whose OpenCL framework builds the kernels"
    return "install an OpenCL driver for this machine (PoCL or the CPU vendor's runtime)"


@functools.lru_cache(maxsize=None)
def platforms() -> tuple:
    """Every OpenCL platform the loader finds, after :func:`register_runtimes`."""
    register_runtimes()
    try:
        import pyopencl as cl
    except ImportError as exc:
        raise OpenCLUnavailableError(f"pyopencl cannot be imported ({exc}); {_install_hint()}") from None
    try:
        return tuple(cl.get_platforms())
    except cl.Error as exc:  # no ICD loader or no platform at all
        raise OpenCLUnavailableError(f"no OpenCL platform found ({_one_line(exc)}); {_install_hint()}") from None


# ----------------------------------------------------------------------------- choosing


@dataclass(frozen=True)
class DeviceCheck:
    """One device found and what its probe proved.

    Attributes
    ----------
    position : (int, int)
        Platform and device index in the loader's order.
    ok : bool
        True when every kernel built and matched its NumPy reference.
    reason : str
        Why the device was skipped ("" when ok).
    build_seconds : float or None
        Time to build every program of ``kernels/`` in the probe.
    mvoxels_per_second : float or None
        The paper lattice kernel's rate on the probe's grid.
    max_error_mm : float or None
        The largest difference from the NumPy references.
    """

    position: tuple
    platform: str
    platform_version: str
    device: str
    driver_version: str
    ok: bool
    reason: str = ""
    build_seconds: float | None = None
    mvoxels_per_second: float | None = None
    max_error_mm: float | None = None

    @property
    def label(self) -> str:
        version = re.sub(r"\s+", " ", self.platform_version).split(" Linux")[0].strip()
        return f"{self.platform} ({version}) / {self.device}"

    def matches(self, text: str) -> bool:
        hay = f"{self.platform} {self.platform_version} {self.device}".lower()
        return text.lower() in re.sub(r"\s+", " ", hay)


def _one_line(exc) -> str:
    text = str(exc).strip()
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    # a build log's telling line is an "error:" line; else the first line
    for ln in lines:
        if "error" in ln.lower() and not ln.lower().startswith("build on"):
            return ln[:200]
    return (lines[0] if lines else type(exc).__name__)[:200]


def check_devices(found, probe) -> list[DeviceCheck]:
    """Probe every device of every platform.

    Parameters
    ----------
    found : sequence of platform-like objects
        Each with ``name``, ``version`` and ``get_devices()`` (pyopencl platforms, or fakes).
    probe : callable
        ``probe(platform_index, device_index) -> dict`` with keys ``ok``, ``reason``,
        ``build_seconds``, ``mvoxels_per_second``, ``max_error_mm``; an exception it raises
        marks the device as failed with that exception's line.

    Returns
    -------
    list of DeviceCheck
        One per device, and one (not ok) per platform that has no device.
    """
    checks = []
    for pi, p in enumerate(found):
        try:
            devices = list(p.get_devices())
        except Exception as exc:  # CL_DEVICE_NOT_FOUND and kin: the platform is unusable
            devices, why = [], f"no devices ({_one_line(exc)})"
        else:
            why = "no devices"
        if not devices:
            checks.append(DeviceCheck((pi, -1), p.name, p.version, "(none)", "", False, why))
            continue
        for di, d in enumerate(devices):
            try:
                res = dict(probe(pi, di))
            except Exception as exc:
                res = {"ok": False, "reason": _one_line(exc)}
            checks.append(DeviceCheck((pi, di), p.name, p.version, d.name, getattr(d, "driver_version", ""),
                                      **{k: res.get(k) for k in ("ok", "build_seconds", "mvoxels_per_second",
                                                                "max_error_mm")},
                                      reason=res.get("reason") or ""))
    return checks


def choose(checks, wanted: str = "") -> DeviceCheck:
    """The device to use: the one `wanted` names, else the fastest that passed its probe (of those within
    :data:`PROBE_NOISE` of the fastest, the first found).

    Raises
    ------
    OpenCLUnavailableError
        `wanted` names no device, or names one that failed; or no device passed.
    """
    devices = [c for c in checks if c.position[1] >= 0]
    if wanted:
        m = re.fullmatch(r"(.*?)(?::(\d+))?", wanted.strip())
        text, n = m.group(1), int(m.group(2) or 0)
        hits = [c for c in devices if c.matches(text)]
        if n >= len(hits):
            raise OpenCLUnavailableError(
                f"{DEVICE_ENV}={wanted!r} matches no OpenCL device; unset it or name one of: "
                + "; ".join(c.label for c in devices))
        c = hits[n]
        if not c.ok:
            working = [w.label for w in devices if w.ok]
            raise OpenCLUnavailableError(
                f"{DEVICE_ENV}={wanted!r} names {c.label}, which cannot run the kernels ({c.reason}); "
                + (f"unset it or name one of: {'; '.join(working)}" if working else _install_hint()))
        return c
    ok = [c for c in devices if c.ok]
    if not ok:
        tried = "; ".join(f"{c.label}: {c.reason}" for c in checks) or "none found"
        raise OpenCLUnavailableError(f"no OpenCL device can run the kernels ({tried}); {_install_hint()}")
    top = max(c.mvoxels_per_second or 0.0 for c in ok)
    near = [c for c in ok if (c.mvoxels_per_second or 0.0) >= (1.0 - PROBE_NOISE) * top]
    return min(near, key=lambda c: tuple(c.position))


def _cpu_identity() -> str:
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return _host.processor() or _host.machine()
    keep = [ln for ln in text.splitlines()[:40]
            if ln.split(":")[0].strip() in ("vendor_id", "cpu family", "model", "model name", "flags")]
    return "\n".join(dict.fromkeys(keep))


def _hash_kernels(h) -> None:
    """Feed the sources of ``kernels/`` to the hash `h`, in a fixed order (a key that changes with them)."""
    for path in sorted(kernels_dir().glob("*.cl")):
        h.update(path.read_bytes())


def _probe_key(found) -> str:
    from . import __version__

    h = hashlib.sha256()
    h.update(f"{__version__}\n{sys.version}\n{_cpu_identity()}\n{BUILD_OPTIONS}\n".encode())
    # the kernels and this probe: a change to either proves the devices again
    _hash_kernels(h)
    h.update(Path(__file__).read_bytes())
    for p in found:
        h.update(f"{p.name}|{p.version}\n".encode())
        try:
            for d in p.get_devices():
                h.update(f"  {d.name}|{d.driver_version}|{d.version}\n".encode())
        except Exception:
            h.update(b"  none\n")
    return h.hexdigest()[:24]


def _probe_in_child(platform_index: int, device_index: int) -> dict:
    """Run :func:`probe_here` in a child process, so that an abort only loses that device."""
    cmd = [sys.executable, "-m", "implicit_scaffold.opencl", str(platform_index), str(device_index)]
    try:
        run = subprocess.run(cmd, capture_output=True, text=True, timeout=PROBE_TIMEOUT,
                             env={**os.environ, "PYTHONWARNINGS": "ignore"}, stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired:
        return {"ok": False, "reason": f"the probe did not finish in {PROBE_TIMEOUT:.0f} s"}
    for line in reversed(run.stdout.splitlines()):
        if line.startswith("{"):
            return json.loads(line)
    lines = [ln for ln in run.stderr.splitlines() if ln.strip()]
    telling = next((ln for ln in lines if "error" in ln.lower()), lines[-1] if lines else "")
    how = f"signal {-run.returncode}" if run.returncode < 0 else f"exit code {run.returncode}"
    return {"ok": False, "reason": f"the probe crashed ({how}): {telling.strip()[:160]}"}


@functools.lru_cache(maxsize=None)
def device_checks() -> tuple:
    """Every device found, each with its probe's verdict (from the cache when it is current)."""
    found = platforms()
    path = cache_dir() / f"devices-{_probe_key(found)}.json"
    try:
        saved = json.loads(path.read_text())
        return tuple(DeviceCheck(**{**c, "position": tuple(c["position"])}) for c in saved)
    except (OSError, ValueError, TypeError, KeyError):
        pass
    checks = check_devices(found, _probe_in_child)
    _PROBED_NOW.append(True)
    try:
        _write_atomic(path, json.dumps([asdict(c) for c in checks], indent=1))
    except OSError:  # a read-only home: probe again next time
        pass
    return tuple(checks)


def working_devices() -> list[DeviceCheck]:
    """The devices that passed their probe, fastest first."""
    ok = [c for c in device_checks() if c.ok]
    return sorted(ok, key=lambda c: -(c.mvoxels_per_second or 0.0))


#: set when this process ran the probes (not read from the cache)
_PROBED_NOW: list = []


def chosen() -> DeviceCheck:
    """The device this process uses (``IMPLICIT_SCAFFOLD_DEVICE``, else the fastest that works).

    The first run on a machine says, one line each, which devices it skipped and why; a
    run that names its device, or finds none, says only that (the error lists every reason).
    """
    checks = device_checks()
    wanted = os.environ.get(DEVICE_ENV, "")
    pick = choose(checks, wanted)
    if _PROBED_NOW and not wanted:
        _PROBED_NOW.clear()
        for c in checks:
            if not c.ok and c.position[1] >= 0:
                warnings.warn(f"OpenCL device {c.label} skipped: {c.reason}", DeviceWarning, stacklevel=2)
    return pick


# ----------------------------------------------------------------------------- the context

#: the active device: {"check", "context", "queue"}
_ACTIVE: dict = {}


def _activate(position) -> dict:
    import pyopencl as cl

    pi, di = position
    dev = platforms()[pi].get_devices()[di]
    ctx = cl.Context([dev])
    return {"position": tuple(position), "context": ctx, "queue": cl.CommandQueue(ctx)}


def active() -> bool:
    """Whether this process has made its OpenCL context already (:func:`context`)."""
    return bool(_ACTIVE)


def context():
    """The process-wide ``(context, queue)`` pair of the chosen device."""
    if not _ACTIVE:
        _ACTIVE.update(_activate(chosen().position))
    return _ACTIVE["context"], _ACTIVE["queue"]


class using:
    """Run the kernels on another working device inside a ``with`` block (benchmarks, tests).

    Parameters
    ----------
    check : DeviceCheck
        One of :func:`working_devices`.
    """

    def __init__(self, check: DeviceCheck):
        self.check = check

    def __enter__(self):
        self.previous = dict(_ACTIVE)
        _ACTIVE.clear()
        _ACTIVE.update(_activate(self.check.position))
        return self.check

    def __exit__(self, *exc):
        _ACTIVE.clear()
        _ACTIVE.update(self.previous)
        return False


@dataclass(frozen=True)
class Device:
    """What the chosen device is and what it supports."""

    platform: str
    name: str
    version: str
    compute_units: int
    max_work_group_size: int
    global_memory: int

    def describe(self) -> str:
        return (f"{self.platform} / {self.name} ({self.version}, {self.compute_units} compute units, "
                f"{self.global_memory / 2**30:.1f} GiB)")


def device() -> Device:
    """The active device's description."""
    ctx, _ = context()
    d = ctx.devices[0]
    return Device(platform=d.platform.name, name=d.name, version=d.version,
                  compute_units=int(d.max_compute_units),
                  max_work_group_size=int(d.max_work_group_size),
                  global_memory=int(d.global_mem_size))


#: seconds spent building programs in this process
BUILD_SECONDS: dict = {}

#: defines a program's caller takes from the device: a built marker leaves them out, since it names the device
#: (:func:`unbuilt` is asked before a caller reads them)
DEVICE_DEFINES = ("VOTE",)
#: set when this process has compiled a program (a miss of the binary cache: the runtime's compiler is loaded)
_COMPILED: list = []
#: seconds a child that builds programs (:func:`build_in_child`) may take
BUILD_TIMEOUT = 900.0


def _device_identity(platform: str, platform_version: str, device: str, driver_version: str) -> str:
    """One device's name in the built markers: what the loader reports of it and of its platform."""
    return f"{platform}|{platform_version}|{device}|{driver_version}"


def _context_identity(ctx) -> str:
    d = ctx.devices[0]
    return _device_identity(d.platform.name, d.platform.version, d.name, d.driver_version)


def build_device() -> DeviceCheck | None:
    """The device this process builds for: the active one (:func:`context`, or :class:`using`'s), else the one
    it would choose (:func:`chosen`); None when the active device is not among the probed ones (a probe's)."""
    if _ACTIVE:
        return next((c for c in device_checks() if tuple(c.position) == tuple(_ACTIVE["position"])), None)
    return chosen()


def _built_marker(name: str, defines: dict, identity: str) -> Path:
    """The file that says ``kernels/<name>.cl`` with `defines` was built on this machine for the device
    `identity` (:func:`_device_identity`), by these kernels, this PyOpenCL and this Python (:func:`_program`
    writes it). The device is in it: a binary is one device's, and a process whose device changed (one
    :data:`PROBE_NOISE` faster appeared, or ``IMPLICIT_SCAFFOLD_DEVICE`` names another) found its variants
    marked built, and compiled them in place, with the compiler's memory."""
    from importlib.metadata import version

    kept = sorted((k, int(v)) for k, v in defines.items() if k not in DEVICE_DEFINES)
    h = hashlib.sha256()
    h.update(f"{name}\n{kept}\n{version('pyopencl')}\n{sys.version}\n{_cpu_identity()}\n{BUILD_OPTIONS}\n"
             f"{identity}\n".encode())
    _hash_kernels(h)
    return _built_dir() / h.hexdigest()[:24]


def _built_dir() -> Path:
    """The folder of the built markers (:func:`_built_marker`)."""
    return cache_dir() / "built"


def unbuilt(name: str, variants) -> list:
    """The `variants` (dicts of ``-D`` defines; the device's, :data:`DEVICE_DEFINES`, may be left out) of
    ``kernels/<name>.cl`` not built on this machine for :func:`build_device` yet: their build would compile,
    not load a binary."""
    check = build_device()
    if check is None:
        return list(variants)
    identity = _device_identity(check.platform, check.platform_version, check.device, check.driver_version)
    return [d for d in variants if not _built_marker(name, d, identity).exists()]


def _device_spec(check: DeviceCheck) -> str:
    """An ``IMPLICIT_SCAFFOLD_DEVICE`` value that names `check` alone (:func:`choose`)."""
    text = re.sub(r"\s+", " ", f"{check.platform} {check.platform_version} {check.device}").strip()
    same = [c for c in device_checks() if c.position[1] >= 0 and c.matches(text)]
    return f"{text}:{[tuple(c.position) for c in same].index(tuple(check.position))}"


def build_in_child(module: str, variants) -> bool:
    """Build `variants` in a child process (``python -m <module> <variants as JSON>``, whose ``__main__``
    builds them), which leaves their binaries in the cache for this process to load; False when the child
    failed (this process then compiles them itself).

    A compile loads the runtime's compiler into the process, and it stays: in a fresh process with its
    context made (Intel CPU runtime 2026.22, 2026-12-06) the first compile added 152 MiB to the resident
    set, a binary from the cache 6 to 7; three more compiles (``mechanics`` variants) 23, 26 and 31 MiB. A
    first run's ``mechanics`` of a 64^3 gyroid, nothing cached, peaked at 564.8 MiB resident (``/usr/bin/time``)
    under ``--max-memory 490M``, the same command again at 388.7: a solve's budget holds its own arrays, not a
    compiler's. Where the cache folder cannot be written the child could leave nothing behind: none is started."""
    folder = _built_dir()
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        return False
    if not os.access(folder, os.W_OK):
        return False
    check = build_device()
    if check is None:
        return False
    cmd = [sys.executable, "-m", module, json.dumps(list(variants))]
    # the child builds for this process's device, which it names: a device of :class:`using`'s, or of this
    # process's choice where a child probing afresh could choose another (:data:`PROBE_NOISE`)
    env = {**os.environ, "PYTHONWARNINGS": "ignore", DEVICE_ENV: _device_spec(check)}
    try:
        run = subprocess.run(cmd, capture_output=True, text=True, timeout=BUILD_TIMEOUT, env=env,
                             stdin=subprocess.DEVNULL)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return run.returncode == 0


def binaries_dir() -> Path:
    """The folder of PyOpenCL's binary cache for this tool's builds (under :func:`cache_dir`, by PyOpenCL's
    and Python's versions), which only :func:`_program` uses, under :func:`_build_lock`."""
    import pyopencl as cl

    return cache_dir() / f"binaries-pyopencl-{cl.VERSION_TEXT}-py{sys.version_info[0]}.{sys.version_info[1]}"


@contextlib.contextmanager
def _build_lock(folder: Path):
    """Held by one of this tool's processes at a time while it builds with the cache in `folder`, and let go
    by the system when the process ends, however it ends (``fcntl.flock``).

    PyOpenCL's own lock is a file made with ``O_EXCL`` and removed after the build: a process killed
    meanwhile (a Ctrl-C during a build) leaves it behind, and every later build, in any run, waited a
    minute for it and then failed (a ``KeyError`` inside PyOpenCL's fallback; CI, 2026-12-06: 31 tests,
    after a test had interrupted a run). Under this lock no other build of ours runs, so a PyOpenCL lock
    file found there is such a leftover, and is removed."""
    try:
        import fcntl
    except ImportError:  # not POSIX: PyOpenCL's lock alone (yields False: a lock file there may be live)
        yield False
        return
    with open(folder / "build.lock", "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield True
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


@functools.lru_cache(maxsize=None)
def _program(ctx, name: str, defines: tuple):
    import pyopencl as cl

    src_dir = kernels_dir()
    source = (src_dir / f"{name}.cl").read_text()
    options = [f"-I{src_dir}", *BUILD_OPTIONS] + [f"-D{k}={v}" for k, v in defines]
    t0 = time.perf_counter()
    folder = binaries_dir()
    with contextlib.ExitStack() as held:
        try:
            folder.mkdir(parents=True, exist_ok=True)
            alone = held.enter_context(_build_lock(folder))
        except OSError:  # a cache folder we cannot write: built each time, uncached
            folder, alone = None, False
        if alone:
            (folder / "lock").unlink(missing_ok=True)  # PyOpenCL's, left by a process killed mid-build
        with warnings.catch_warnings():
            # a build log with only remarks is not a failure; a failed build raises
            warnings.simplefilter("ignore", cl.CompilerWarning)
            prg = cl.Program(ctx, source).build(options=options, cache_dir=False if folder is None else str(folder))
    BUILD_SECONDS[name] = time.perf_counter() - t0
    # PyOpenCL's record of the build: (how, whether from its binary cache, seconds); unknown: compiled
    if not (getattr(prg, "_build_duration_info", None) or (None, False))[1]:
        _COMPILED.append(True)
    if folder is not None:  # its binary is in the cache: a later build loads it
        try:
            marker = _built_marker(name, dict(defines), _context_identity(ctx))
            if not marker.exists():
                _write_atomic(marker, "")
        except OSError:
            pass
    return prg


def program(name: str, **defines):
    """Compile ``kernels/<name>.cl`` once per device and set of ``-D`` defines and keep it.

    ``#include "common.cl"`` works through ``-I`` to the kernels folder.
    """
    ctx, _ = context()
    return _program(ctx, name, tuple(sorted(defines.items())))


@functools.lru_cache(maxsize=None)
def _kernel(ctx, source: str, name: str, defines: tuple):
    import pyopencl as cl

    return cl.Kernel(_program(ctx, source, defines), name)


def kernel(source: str, name: str, **defines):
    """The kernel `name` of ``kernels/<source>.cl``, built and retrieved once per device."""
    ctx, _ = context()
    return _kernel(ctx, source, name, tuple(sorted(defines.items())))


#: host arrays a device uses in place (``USE_HOST_PTR``) start on this many bytes: a CPU device then takes them as
#: its buffers (zero copy); at any other address the Intel CPU runtime keeps a copy of its own (measured:
#: 16-byte-aligned NumPy arrays of 400 MB doubled the resident set, 4096-byte-aligned ones added nothing)
ALIGN = 4096


def aligned_view(raw: np.ndarray, shape, dtype) -> np.ndarray:
    """A C-contiguous `shape` array of `dtype` inside the bytes `raw` (at least :data:`ALIGN` more than it
    needs), its data on an :data:`ALIGN`-byte boundary."""
    dtype = np.dtype(dtype)
    shape = tuple(int(v) for v in np.atleast_1d(shape))
    nbytes = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    start = (-raw.ctypes.data) % ALIGN
    return raw[start:start + nbytes].view(dtype).reshape(shape)


def aligned_empty(shape, dtype=np.float64) -> np.ndarray:
    """An uninitialised C-contiguous array whose data start on an :data:`ALIGN`-byte boundary (for
    :func:`host_buffer`)."""
    nbytes = int(np.prod(np.atleast_1d(shape), dtype=np.int64)) * np.dtype(dtype).itemsize
    return aligned_view(np.empty(nbytes + ALIGN, np.uint8), shape, dtype)


def host_buffer(host: np.ndarray):
    """A read-only device buffer over `host` itself: no copy on a CPU device when `host` is C-contiguous and
    :data:`ALIGN`-aligned (:func:`aligned_empty`), so a large array is not held twice; otherwise a copy
    (:func:`to_device`). The caller keeps `host` alive, unchanged, while the buffer is used."""
    import pyopencl as cl

    if host.size == 0 or not host.flags.c_contiguous or host.ctypes.data % ALIGN:
        return to_device(host, host.dtype)
    ctx, _ = context()
    return cl.Buffer(ctx, cl.mem_flags.READ_ONLY | cl.mem_flags.USE_HOST_PTR, hostbuf=host)


def to_device(array, dtype=np.float32):
    """Copy a host array to a read-only device buffer (a 1-element dummy when empty)."""
    import pyopencl as cl

    ctx, _ = context()
    a = np.ascontiguousarray(array, dtype=dtype)
    if a.size == 0:
        a = np.zeros(1, dtype=dtype)
    return cl.Buffer(ctx, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=a)


def launch_tiles(kernel, tiles, out: np.ndarray, *, sizes, args, first: int = 0, progress=None) -> np.ndarray:
    """Run a grid kernel once per tile of x planes, each tile's result copied into `out`.

    Every field kernel (the lattice's rows, the patient's triangles) is launched this way: one
    device buffer, sized for the largest tile, serves every tile, and the host waits for each
    copy, so a tile's planes are final when `progress` hears of them.

    Parameters
    ----------
    kernel : pyopencl.Kernel
        Its first argument is the output buffer, one value per voxel of the tile, in C order.
    tiles : list of (x0, x1)
        Plane ranges, in the whole grid's frame.
    out : (planes, ny, nz) C-contiguous ndarray
        The host array; its plane 0 is the grid's plane `first`.
    sizes : callable(nx) -> (global_size, local_size)
        The work sizes for a tile of `nx` planes.
    args : callable(x0, nx) -> sequence
        The kernel's arguments after the output buffer.
    progress : callable(done, total), optional
    """
    import pyopencl as cl

    ctx, queue = context()
    plane = int(np.prod(out.shape[1:]))
    dev_out = cl.Buffer(ctx, cl.mem_flags.WRITE_ONLY,
                        size=max(1, out.itemsize * plane * max((x1 - x0 for x0, x1 in tiles), default=0)))
    for i, (x0, x1) in enumerate(tiles):
        global_size, local_size = sizes(x1 - x0)
        kernel(queue, global_size, local_size, dev_out, *args(x0, x1 - x0))
        cl.enqueue_copy(queue, out[x0 - first:x1 - first], dev_out, is_blocking=True)
        if progress is not None:
            progress(i + 1, len(tiles))
    return out


# ----------------------------------------------------------------------------- the probe


def probe_here(position) -> dict:
    """Prove one device in this process: build every kernel, check each field against its
    NumPy reference on a small grid, and time the paper lattice kernel.

    Returns
    -------
    dict
        ``ok``, ``reason``, ``build_seconds``, ``mvoxels_per_second``, ``max_error_mm``.
    """
    from .geometry.cells import voronoi_cells
    from .run.grid import Grid
    from .fields.lattice import lattice_sdf, lattice_sdf_reference, struts_field, struts_field_reference
    from .fields.patient_mesh import triangle_distance, triangle_distance_reference
    from .geometry.skeleton import scaled_skeleton, voronoi_edges

    _ACTIVE.clear()
    _ACTIVE.update(_activate(position))
    ctx, _ = context()
    t0 = time.perf_counter()
    from .fields.lattice import BLOCK

    for source, names in kernel_names().items():
        prg = _program(ctx, source, (("BLOCK", BLOCK),))
        built = {k.function_name for k in prg.all_kernels()}
        missing = [n for n in names if n not in built]
        if missing:
            return {"ok": False, "reason": f"{source}.cl built without its kernels ({', '.join(missing)})"}
    build = time.perf_counter() - t0

    rng = np.random.default_rng(5)
    hi = np.array([2.0, 1.8, 1.6])
    cells = voronoi_cells(rng.uniform(0, 1, (24, 3)) * hi, [0, 0, 0], hi)
    grid = Grid.covering(cells.lo, cells.hi, 0.05)
    idx = np.stack([rng.integers(0, s, 400) for s in grid.shape], 1)
    pts = grid.indices_to_points(idx)
    sk = scaled_skeleton(cells, 0.75, 0.75)
    errors = {}
    got = lattice_sdf(sk, grid, cutoff=0.15)[tuple(idx.T)]
    errors["lattice_paper"] = np.abs(got - lattice_sdf_reference(sk, pts, cutoff=0.15)).max()
    edges = voronoi_edges(cells)
    got = struts_field(edges, grid, cutoff=0.3, blend=0.05)[tuple(idx.T)]
    errors["lattice_struts"] = np.abs(got - struts_field_reference(edges, pts, cutoff=0.3, blend=0.05)).max()
    tris = rng.uniform(0, 1.6, (12, 3, 3))
    got = triangle_distance(tris.reshape(-1, 3), np.arange(36).reshape(-1, 3), grid).reshape(grid.shape)
    near = triangle_distance_reference(pts, tris) <= 2 * grid.spacing
    errors["triangle_distance"] = (np.abs(got[tuple(idx.T)] - triangle_distance_reference(pts, tris))[near].max()
                                   if near.any() else 0.0)
    worst = max(errors, key=errors.get)
    if not errors[worst] <= PROBE_TOLERANCE:  # NaN fails too
        return {"ok": False, "reason": f"{worst} differs from its NumPy reference by {errors[worst]:.3g} mm",
                "build_seconds": build}

    # B1's cube and seeds (benchmarks/bench_core.py) at 0.05 mm: small grids hide the
    # launch costs that differ most between runtimes
    cells = voronoi_cells(rng.uniform(0, 10, (500, 3)), [0, 0, 0], [10, 10, 10])
    sk = scaled_skeleton(cells, 0.75, 0.75)
    grid = Grid.covering(cells.lo, cells.hi, 0.05)
    lattice_sdf(sk, grid, cutoff=0.2)
    times = []
    for _ in range(3):
        t = time.perf_counter()
        lattice_sdf(sk, grid, cutoff=0.2)
        times.append(time.perf_counter() - t)
    # the best of three: other load on the machine only ever slows a run down
    return {"ok": True, "reason": "", "build_seconds": build,
            "mvoxels_per_second": grid.size / min(times) / 1e6,
            "max_error_mm": float(max(errors.values()))}


if __name__ == "__main__":  # the child of _probe_in_child
    # the package's own module, so that the kernels it runs use the device it activates
    from implicit_scaffold import opencl as _module

    try:
        verdict = _module.probe_here((int(sys.argv[1]), int(sys.argv[2])))
    except Exception as exc:  # a failed build or launch: its telling line is the reason
        verdict = {"ok": False, "reason": _module._one_line(exc)}
    print(json.dumps(verdict), flush=True)
