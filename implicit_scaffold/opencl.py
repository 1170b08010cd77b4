"""The one place that finds the OpenCL device, creates the context and compiles kernels.

The device is chosen explicitly, never by prompt: the first CPU device of the
Portable Computing Language (PoCL) platform when there is one, else the first
device of any platform. ``IMPLICIT_SCAFFOLD_DEVICE="platform substring:device index"``
overrides the choice. Kernel sources live in the top-level ``kernels/`` folder,
which the build installs as the package ``implicit_scaffold.kernels``.
"""
from __future__ import annotations

import functools
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import OpenCLUnavailableError


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


def _choose_device():
    import pyopencl as cl

    try:
        platforms = cl.get_platforms()
    except cl.Error as exc:  # no ICD loader or no platform at all
        raise OpenCLUnavailableError(
            f"no OpenCL platform found ({exc}); install the CPU driver with "
            "pip install pocl-binary-distribution") from None
    wanted = os.environ.get("IMPLICIT_SCAFFOLD_DEVICE", "")
    if wanted:
        pname, _, index = wanted.partition(":")
        for p in platforms:
            if pname.lower() in p.name.lower():
                devices = p.get_devices()
                i = int(index or 0)
                if i < len(devices):
                    return devices[i]
        raise OpenCLUnavailableError(
            f"IMPLICIT_SCAFFOLD_DEVICE={wanted!r} matches no OpenCL device; "
            f"unset it or name one of: {', '.join(p.name for p in platforms)}")
    ordered = sorted(platforms, key=lambda p: 0 if "portable" in p.name.lower() else 1)
    for p in ordered:
        try:
            devices = p.get_devices()
        except cl.Error:
            continue
        if devices:
            return devices[0]
    raise OpenCLUnavailableError(
        "no OpenCL device found; install the CPU driver with pip install pocl-binary-distribution")


@functools.lru_cache(maxsize=None)
def context():
    """The process-wide ``(context, queue)`` pair."""
    import pyopencl as cl

    dev = _choose_device()
    ctx = cl.Context([dev])
    return ctx, cl.CommandQueue(ctx)


def device() -> Device:
    """The chosen device's description."""
    ctx, _ = context()
    d = ctx.devices[0]
    return Device(platform=d.platform.name, name=d.name, version=d.version,
                  compute_units=int(d.max_compute_units),
                  max_work_group_size=int(d.max_work_group_size),
                  global_memory=int(d.global_mem_size))


@functools.lru_cache(maxsize=None)
def program(name: str, **defines):
    """Compile ``kernels/<name>.cl`` once per set of ``-D`` defines and keep it.

    ``#include "common.cl"`` works through ``-I`` to the kernels folder.
    """
    import pyopencl as cl

    ctx, _ = context()
    src_dir = kernels_dir()
    source = (src_dir / f"{name}.cl").read_text()
    options = [f"-I{src_dir}", "-cl-fast-relaxed-math" if defines.pop("fast", False) else ""]
    options += [f"-D{k}={v}" for k, v in sorted(defines.items())]
    # PoCL keeps compiled binaries in its own cache between runs.
    return cl.Program(ctx, source).build(options=[o for o in options if o])


@functools.lru_cache(maxsize=None)
def kernel(source: str, name: str, **defines):
    """The kernel `name` of ``kernels/<source>.cl``, built and retrieved once."""
    import pyopencl as cl

    return cl.Kernel(program(source, **defines), name)


def to_device(array, dtype=np.float32):
    """Copy a host array to a read-only device buffer (a 1-element dummy when empty)."""
    import pyopencl as cl

    ctx, _ = context()
    a = np.ascontiguousarray(array, dtype=dtype)
    if a.size == 0:
        a = np.zeros(1, dtype=dtype)
    return cl.Buffer(ctx, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=a)
