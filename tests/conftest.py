"""Shared fixtures: small tessellations and the header line with versions and device."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def pytest_report_header(config):
    import pyopencl
    import trimesh

    try:
        from implicit_scaffold import opencl

        dev = opencl.device().describe()
    except Exception as exc:  # the header must never stop the run
        dev = f"unavailable ({exc})"
    return [f"numpy {np.__version__}, pyopencl {pyopencl.VERSION_TEXT}, trimesh {trimesh.__version__}",
            f"OpenCL device: {dev}"]


@pytest.fixture(scope="session")
def cube_cells():
    """500 uniform seeds in the paper's 10 mm cube, seed 0."""
    from implicit_scaffold.geometry.cells import voronoi_cells

    rng = np.random.default_rng(0)
    return voronoi_cells(rng.uniform(0, 10, (500, 3)), [0, 0, 0], [10, 10, 10])


@pytest.fixture(scope="session")
def small_cells():
    """40 uniform seeds in a 3 x 2.5 x 2 mm box: small enough for brute-force oracles."""
    from implicit_scaffold.geometry.cells import voronoi_cells

    rng = np.random.default_rng(7)
    hi = np.array([3.0, 2.5, 2.0])
    return voronoi_cells(rng.uniform(0, 1, (40, 3)) * hi, [0, 0, 0], hi)


@pytest.fixture()
def data_dir():
    """The shared real-bone data folder; skips with a reason when it is missing."""
    if not DATA.is_dir():
        pytest.skip(f"needs the shared data folder {DATA} (not present on this machine)")
    return DATA
