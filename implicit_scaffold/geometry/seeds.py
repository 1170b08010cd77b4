"""Seeds: the points whose Voronoi cells become the scaffold's pores (paper §2.2, §3)."""
from __future__ import annotations

import math

import numpy as np

from ..errors import ScaffoldError


def seed_count(volume: float, porosity: float, pore_size: float) -> int:
    """The paper's seed count: the void volume over the volume of one spherical pore.

    ``n = V · P / (π Dp³ / 6)``, rounded to the nearest integer.

    Parameters
    ----------
    volume : float, mm³
        Volume the seeds populate (the bounding box in the paper).
    porosity : float
        Target porosity, a fraction in (0, 1).
    pore_size : float, mm
        Target pore diameter ``Dp``.

    Returns
    -------
    int
        At least 2.

    Examples
    --------
    >>> seed_count(1000.0, 0.8, 5.0), seed_count(1000.0, 0.8, 0.5)
    (12, 12223)
    """
    if not (pore_size > 0 and math.isfinite(pore_size)):
        raise ScaffoldError(f"--pore-size must be a positive number of mm, got {pore_size!r}")
    if not (0 < porosity < 1):
        raise ScaffoldError(f"porosity must lie in (0, 1), got {porosity!r}")
    return max(2, int(round(volume * porosity / (math.pi * pore_size ** 3 / 6))))


def uniform_seeds(lo, hi, n: int, rng: np.random.Generator) -> np.ndarray:
    """`n` points uniform in the box ``[lo, hi]`` (the paper's *Populate 3D*).

    Parameters
    ----------
    lo, hi : (3,) array_like of float, mm
    n : int
    rng : numpy.random.Generator
        Passed down from the caller's ``--seed``; no global state.

    Returns
    -------
    (n, 3) float64 ndarray, mm
    """
    if n < 2:
        raise ScaffoldError(f"a Voronoi lattice needs at least 2 seeds, got {n}; pass --seeds 2 or more")
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    return lo + rng.random((int(n), 3)) * (hi - lo)


def seeds_in_patient(patient_sdf: np.ndarray, grid, lo, hi, n: int, rng: np.random.Generator, *,
                     margin: float, total: bool = False) -> np.ndarray:
    """Seeds uniform in the patient grown by `margin`, at the density of `n` per patient volume.

    The margin (one cell) makes the cells cut by the patient surface whole Voronoi
    cells rather than slivers of the bounding box's.

    Parameters
    ----------
    patient_sdf : (nx, ny, nz) float ndarray, mm
        The patient's signed distance on `grid` (a coarse grid is enough).
    grid : Grid
    lo, hi : (3,) array_like of float, mm
        The box the seeds are drawn in (the cells' bounding box).
    n : int
        Seeds wanted inside the patient itself.
    rng : numpy.random.Generator
    margin : float, mm
    total : bool
        `n` is the count of all the seeds (a ``--seeds`` the user gave), margin included.

    Returns
    -------
    (m, 3) float64 ndarray, mm
        Points in ``[lo, hi]``, uniform in the patient grown by `margin`, drawn until `n` of
        them lie in the patient (by the interpolated `patient_sdf`; at least 2 points); ``m = n``
        with `total`.

    Notes
    -----
    The count inside is taken from the seeds themselves, not from the grid's points: on
    anatomy a few grid steps thin, the share of grid points inside misses the share of
    volume by tens of per cent (a 1.5 mm plate sampled every 0.5 mm), while the
    interpolated distance classifies each seed to a fraction of a step.
    """
    from ..fields.field import sample

    n = max(2, int(n))
    region = max(int(np.count_nonzero(patient_sdf < margin)), 1)
    inside = int(np.count_nonzero(patient_sdf < 0))
    # a patient no grid point lies in gets `n` seeds in its margin
    total = total or inside == 0
    inside = max(inside, 1)
    # candidates per kept seed (the box over the region), and kept seeds per seed inside
    rate = float(np.prod(patient_sdf.shape)) / region
    m = n if total else max(n, int(round(n * region / inside)))
    # the seeds inside may stay short of n (parts thinner than the grid's steps): a bound
    cap = m if total else 4 * m + 1024
    out, got, got_inside = [], 0, 0
    while got < cap and (total or got_inside < n):
        want = (m - got) if total else (n - got_inside) * max(1.0, region / inside)
        cand = uniform_seeds(lo, hi, max(1024, int(1.2 * want * rate) + 1), rng)
        v = sample(patient_sdf, grid, cand)
        kept = v < margin
        keep, v = cand[kept], v[kept]
        if not total:
            inn = np.flatnonzero(v < 0)
            if got_inside + len(inn) >= n:
                # stop at the n-th seed inside
                cut = int(inn[n - got_inside - 1]) + 1
                keep = keep[:cut]
                got_inside = n
            else:
                got_inside += len(inn)
        out.append(keep)
        got += len(keep)
    return np.concatenate(out)[:cap]


#: seed rules: "pore-size" solves the density for the measured pore size; "paper" is the paper's formula
SEED_RULES = ("pore-size", "paper")

#: mean of ``v^(1/3)`` over the cells of a Poisson–Voronoi tessellation of unit mean cell volume,
#: from the gamma law of the cell volumes (shape k = 5.586, Ferenc & Néda, Physica A 385, 2007):
#: ``Γ(k + 1/3) / (Γ(k) k^(1/3))``; the cube root of the mean volume is 1, its mean is a little less
PV_CUBE_ROOT_MEAN = 0.98013556

#: relative miss of the measured mean pore size after which the seed count is corrected once more
#: (a cell pass each; well inside the 5 % the rule promises, since the scaffold's cells are measured
#: on the fine grid afterwards)
PORE_SIZE_TOLERANCE = 0.02
#: cell passes at most when solving the seed count for the pore size
PORE_SIZE_PASSES = 4


def density_for_pore_size(pore_size, sv: float):
    """Seeds per mm³ whose cells have a mean polyhedron-sphere pore size of `pore_size`.

    The pore of a cell of volume ``V`` has the diameter ``D = Sv (6 V / π)^(1/3)`` (the
    paper's measure); for Poisson–Voronoi cells of density ``λ`` (mean volume ``1/λ``)
    its mean is ``Sv (6 / (π λ))^(1/3) · E[v^(1/3)]``. Solved for ``λ``. A graded run
    applies it locally, to the target pore size at each point.

    Parameters
    ----------
    pore_size : float or (m,) array_like of float, mm
        Target mean pore size (polyhedron-sphere).
    sv : float
        Cell scale factor, 0 < Sv < 1.

    Returns
    -------
    float, or (m,) float64 ndarray, seeds per mm³
        A float for a scalar `pore_size`.
    """
    size = np.asarray(pore_size, np.float64)
    if not np.all((size > 0) & np.isfinite(size)):
        bad = size if size.ndim == 0 else size[~((size > 0) & np.isfinite(size))][0]
        raise ScaffoldError(f"--pore-size must be a positive number of mm, got {float(bad)!r}")
    rho = 6.0 / math.pi * (sv * PV_CUBE_ROOT_MEAN / size) ** 3
    return float(rho) if rho.ndim == 0 else rho


def pore_size_for_density(density, sv: float):
    """The mean polyhedron-sphere pore size of Poisson–Voronoi cells of `density`, mm: the
    inverse of :func:`density_for_pore_size`, ``Sv (6 / (π λ))^(1/3) · E[v^(1/3)]``.

    Parameters
    ----------
    density : float or (m,) array_like of float, seeds per mm³
    sv : float

    Returns
    -------
    float64 ndarray, mm
    """
    return sv * PV_CUBE_ROOT_MEAN * np.cbrt(6.0 / (math.pi * np.asarray(density, np.float64)))


def corrected_count(n: int, measured: float, target: float) -> int:
    """The seed count that moves a measured mean pore size to `target`: ``n (measured / target)³``
    (the pore size goes as the cube root of the cell volume, which goes as 1/n)."""
    return max(2, int(round(n * (measured / target) ** 3)))
