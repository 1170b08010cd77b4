"""Graded scaffolds: pore size and porosity as fields in space (issue 6).

Cortical bone is dense with small pores, cancellous bone open with large ones; a graded
scaffold follows it. This module turns a target into fields and the fields into seeds,
an offset field and the profiles of the report:

- **targets** (:class:`GradeField`): the pore size ``Dp(x)`` as a function of the depth
  below the patient surface (``--grade "0:0.3,2:0.8"``, depth ``= -s_P``), as a Python
  callable of ``(x, y, z)`` in mm, or from the patient's CT: intensity (HU) -> bone
  density by a linear calibration -> porosity -> pore size (:class:`Calibration`); the
  porosity ``P(x)`` is the run's constant target, or the CT's;
- **seeds** (:func:`seed_density`, :func:`draw_seeds`): the seed count per unit volume
  by the run's seed rule applied locally (:meth:`GradeField.density`): under
  ``pore-size`` (the default, as for an even run) the density whose Poisson-Voronoi cells
  measure a mean polyhedron-sphere pore size of ``Dp(x)``
  (:func:`~implicit_scaffold.geometry.seeds.density_for_pore_size`), under ``paper`` the
  paper's ``ρ(x) = P(x) / (π Dp(x)³ / 6)``, whose cells measure ``0.98 Sv Dp / P^(1/3)``
  (0.83 Dp at P = 0.7, Sv = 0.75); integrated over the patient (plus one cell) for the
  count, and honoured in expectation by rejection sampling against the field on a fine
  grid; optional Lloyd relaxation (:func:`lloyd_relax`) narrows the spread of the cells'
  sizes while keeping the density;
- **offset** (:func:`level_plan`, :func:`solve_level_field`, :func:`shift_planes`): the
  surface offset becomes a field, piecewise linear in a coordinate (the depth, or the
  target pore size or porosity), whose value at each bin centre is the per-bin quantile
  of the lattice field that meets that bin's porosity; found by passes over chunks of
  planes, so that the whole grid in memory and a tiled run's slabs on disk take the
  same steps;
- **profiles** (:func:`profiles`): porosity and mean pore size per depth bin and along
  the patient's longest axis, measured beside their targets.

All lengths are mm; densities are seeds per mm³ (seeding) or g/cm³ (bone).

- **weighted cells** (:func:`power_radii`): optionally power (Laguerre) cells instead of
  Voronoi cells, each seed weighted by the local cell size of the field, so that a
  cell's size follows its own target where its neighbours' targets differ.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..errors import ScaffoldError
from ..fields.field import level_between
from ..run.grid import Grid

#: apparent density of fully dense cortical bone, g/cm³: the density at which the
#: calibrated porosity ``1 - ρ / ρ_max`` reaches 0
DENSITY_MAX = 1.8
#: the scaffold's porosity is kept in this range whatever the bone's: below 0.5 the
#: void stops being reliably interconnected, above 0.9 the struts stop carrying load
POROSITY_RANGE = (0.5, 0.9)
#: pore sizes (mm) at the two ends of POROSITY_RANGE: the issue's cortical and
#: cancellous targets
PORE_RANGE = (0.3, 0.8)
#: Lloyd relaxation weights the density by this power: a centroidal Voronoi
#: tessellation of density w has points of density w^(3/5) in 3-D (Gersho)
LLOYD_EXPONENT = 5.0 / 3.0
#: at most this many voxels in the seeding grid
SEEDING_MAX_VOXELS = 4_000_000
#: a level bin holds at least this many patient voxels (its quantile is then stable)
MIN_BIN_VOXELS = 2000
#: the offset field's nodes stop when they move by less than this (a 400th of a 0.04 mm
#: voxel: the bins' porosities then change by far less than their 2-point tolerance)
LEVEL_TOLERANCE_MM = 1e-4
#: the offset nodes settle on a sample of about this many patient voxels before the
#: exact passes over all of them (each pass over 10^8 voxels takes seconds)
LEVEL_SAMPLE_VOXELS = 4_000_000


# --- targets ------------------------------------------------------------------------

@dataclass(frozen=True)
class GradeProfile:
    """Pore size against depth below the patient surface, linear between the points.

    Attributes
    ----------
    depths : tuple of float, mm
        Increasing, >= 0.
    sizes : tuple of float, mm
        Target pore size ``Dp`` at each depth; constant before the first depth and
        after the last (outside the patient, depth < 0, it is the surface value).
    """

    depths: tuple
    sizes: tuple

    def __call__(self, depth) -> np.ndarray:
        """Target pore size at `depth` (array_like, mm), float64 mm."""
        return np.interp(np.asarray(depth, np.float64), self.depths, self.sizes)

    def describe(self) -> str:
        return ",".join(f"{d:g}:{s:g}" for d, s in zip(self.depths, self.sizes))


def parse_grade(text) -> GradeProfile:
    """``"0:0.3,2:0.8"`` (depth:pore size pairs, mm) as a :class:`GradeProfile`.

    Raises
    ------
    ScaffoldError
        Not pairs of numbers, a negative or repeated depth, depths out of order, or a
        pore size that is not a positive length.
    """
    hint = '; e.g. --grade "0:0.3,2:0.8" (0.3 mm pores at the surface, 0.8 mm from 2 mm deep)'
    if isinstance(text, GradeProfile):
        return text
    if not isinstance(text, str) or not text.strip():
        raise ScaffoldError(f"--grade takes depth:pore-size pairs in mm, got {text!r}{hint}")
    depths, sizes = [], []
    for part in text.replace(";", ",").split(","):
        part = part.strip()
        if not part:
            continue
        bits = part.split(":")
        try:
            if len(bits) != 2:
                raise ValueError
            d, s = float(bits[0]), float(bits[1])
        except ValueError:
            raise ScaffoldError(f"--grade: {part!r} is not a depth:pore-size pair of numbers{hint}") from None
        if not (math.isfinite(d) and d >= 0):
            raise ScaffoldError(f"--grade: depth {bits[0].strip()} must be a finite depth >= 0 mm below the "
                                f"patient surface{hint}")
        if not (math.isfinite(s) and s > 0):
            raise ScaffoldError(f"--grade: pore size {bits[1].strip()} must be a positive length in mm{hint}")
        depths.append(d)
        sizes.append(s)
    if not depths:
        raise ScaffoldError(f"--grade takes depth:pore-size pairs in mm, got {text!r}{hint}")
    if any(b <= a for a, b in zip(depths, depths[1:])):
        raise ScaffoldError(f"--grade: depths must increase from one pair to the next, got "
                            f"{', '.join(f'{d:g}' for d in depths)}{hint}")
    return GradeProfile(tuple(depths), tuple(sizes))


@dataclass(frozen=True)
class Calibration:
    """CT intensity -> bone density -> scaffold porosity -> pore size (documented rules).

    1. density ``ρ = slope · HU + intercept`` (g/cm³; the linear calibration of a
       phantom scanned with the patient);
    2. porosity ``P = 1 - ρ / density_max``, clipped to `porosity_range`: the scaffold
       is as porous as the bone it replaces, within what a scaffold can be;
    3. pore size linear in porosity between ``(porosity_range[0], pore_range[0])`` and
       ``(porosity_range[1], pore_range[1])``: monotone, dense bone gets small pores.

    Attributes
    ----------
    slope : float, g/cm³ per HU
    intercept : float, g/cm³
    density_max : float, g/cm³
    porosity_range : (2,) tuple of float
    pore_range : (2,) tuple of float, mm
    """

    slope: float
    intercept: float
    density_max: float = DENSITY_MAX
    porosity_range: tuple = POROSITY_RANGE
    pore_range: tuple = PORE_RANGE

    def density(self, hu) -> np.ndarray:
        """Bone density at intensities `hu`, g/cm³ (float64)."""
        return self.slope * np.asarray(hu, np.float64) + self.intercept

    def porosity(self, hu) -> np.ndarray:
        """Target porosity at intensities `hu` (float64, within `porosity_range`)."""
        lo, hi = self.porosity_range
        return np.clip(1.0 - self.density(hu) / self.density_max, lo, hi)

    def pore_size(self, porosity) -> np.ndarray:
        """Target pore size at `porosity`, mm (float64), monotone increasing."""
        (p0, p1), (d0, d1) = self.porosity_range, self.pore_range
        t = np.clip((np.asarray(porosity, np.float64) - p0) / (p1 - p0), 0.0, 1.0)
        return d0 + t * (d1 - d0)


@dataclass(frozen=True)
class ModulusPorosity:
    """A scaffold's apparent modulus against its porosity, measured: ``E = E_solid c (1 - P)^n``.

    Fitted (least squares on the logs) to forward builds of a representative volume
    (:func:`~implicit_scaffold.design.fit_modulus_porosity`); Gibson and Ashby's scaling law in form, its
    constants measured. Only the fitted porosity span is trusted.

    Attributes
    ----------
    c : float
        The relative modulus at zero porosity of the fit.
    n : float
        The exponent.
    solid_gpa : float, GPa
        The solid's Young's modulus.
    porosity_range : (2,) tuple of float
        The porosities built for the fit.
    """

    c: float
    n: float
    solid_gpa: float
    porosity_range: tuple

    def modulus_gpa(self, porosity) -> np.ndarray:
        """Apparent modulus (GPa, float64) at `porosity`."""
        return self.solid_gpa * self.c * (1.0 - np.asarray(porosity, np.float64)) ** self.n

    def porosity(self, modulus_gpa) -> np.ndarray:
        """The porosity whose modulus is `modulus_gpa` (the closed-form inverse; float64, not clipped)."""
        e = np.clip(np.asarray(modulus_gpa, np.float64), 0.0, None)
        return 1.0 - (e / (self.solid_gpa * self.c)) ** (1.0 / self.n)

    def to_json(self) -> dict:
        return {"c": self.c, "n": self.n, "solid_gpa": self.solid_gpa, "porosity_range": list(self.porosity_range)}


@dataclass(frozen=True)
class ModulusCalibration(Calibration):
    """CT intensity -> bone density -> bone modulus -> the scaffold porosity of that modulus.

    1. density ``ρ = slope · HU + intercept`` (g/cm³), as :class:`Calibration`;
    2. the bone's apparent modulus ``E = a ρ^b`` (:class:`~implicit_scaffold.measure.mechanics.DensityModulus`, a
       site of Morgan, Bayraktar & Keaveny 2003, J Biomech 36:897-904);
    3. the porosity whose scaffold modulus is that (:meth:`ModulusPorosity.porosity`, the
       measured law inverted in closed form), clipped to the law's fitted span
       (``porosity_range`` is set to it): beyond it the bone is stiffer (or softer) than
       any scaffold built for the fit;
    4. the pore size: `pore_size_mm` everywhere, the mean polyhedron-sphere pore size the cells
       are seeded for by the run's seed rule (:meth:`GradeField.density`; under ``pore-size``,
       :func:`~implicit_scaffold.geometry.seeds.density_for_pore_size`), so the cells have one size
       everywhere and the porosity alone follows the bone.

    Attributes
    ----------
    law : DensityModulus
    scaffold : ModulusPorosity
    pore_size_mm : float, mm
    sv : float
        The Sv of the fit's builds (the run's Sv seeds the cells).
    """

    law: object = None
    scaffold: ModulusPorosity | None = None
    pore_size_mm: float = 0.5
    sv: float = 0.75

    def __post_init__(self):
        lo, hi = (float(p) for p in self.scaffold.porosity_range)
        object.__setattr__(self, "porosity_range", (lo, hi))
        object.__setattr__(self, "pore_range", (float(self.pore_size(lo)), float(self.pore_size(hi))))

    def bone_modulus(self, hu) -> np.ndarray:
        """The bone's apparent modulus at intensities `hu`, GPa (float64)."""
        return self.law.modulus_gpa(self.density(hu))

    def porosity(self, hu) -> np.ndarray:
        """Target porosity at intensities `hu` (float64, within the fitted span)."""
        lo, hi = self.porosity_range
        return np.clip(self.scaffold.porosity(self.bone_modulus(hu)), lo, hi)

    def pore_size(self, porosity) -> np.ndarray:
        """Target pore size at `porosity`: `pore_size_mm` whatever the porosity, mm (float64)."""
        return np.full(np.shape(porosity), float(self.pore_size_mm))

    def to_json(self) -> dict:
        return {"calibration": [self.slope, self.intercept], "site": self.law.site, "law_a_mpa": self.law.a_mpa,
                "law_b": self.law.b, "scaffold": self.scaffold.to_json(), "pore_size_mm": self.pore_size_mm,
                "sv": self.sv}

    @classmethod
    def from_json(cls, data: dict) -> "ModulusCalibration":
        """The calibration :meth:`to_json` wrote (ScaffoldError when malformed)."""
        from ..measure.mechanics import DensityModulus

        try:
            s = data["scaffold"]
            slope, intercept = (float(v) for v in data["calibration"])
            return cls(slope, intercept, law=DensityModulus(str(data["site"]), float(data["law_a_mpa"]),
                                                            float(data["law_b"])),
                       scaffold=ModulusPorosity(float(s["c"]), float(s["n"]), float(s["solid_gpa"]),
                                                tuple(float(p) for p in s["porosity_range"])),
                       pore_size_mm=float(data["pore_size_mm"]), sv=float(data["sv"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise ScaffoldError(f"a design's stiffness_from_ct is malformed ({exc!r}); write it again with "
                                "implicit-scaffold design --stiffness-from-ct") from None


def parse_calibration(values) -> Calibration | None:
    """``(SLOPE, INTERCEPT)`` (g/cm³ per HU, g/cm³) as a :class:`Calibration`; None stays None."""
    if values is None or isinstance(values, Calibration):
        return values
    hint = "; e.g. --calibration 0.0008 1.0 (density g/cm³ = 0.0008 HU + 1.0)"
    try:
        slope, intercept = (float(v) for v in values)
    except (TypeError, ValueError):
        raise ScaffoldError(f"--calibration takes two numbers, SLOPE and INTERCEPT, got {values!r}{hint}") from None
    if not (math.isfinite(slope) and math.isfinite(intercept)):
        raise ScaffoldError(f"--calibration values must be finite, got {slope:g} {intercept:g}{hint}")
    if slope <= 0:
        raise ScaffoldError(f"--calibration SLOPE must be positive (denser bone is brighter), got {slope:g}{hint}")
    return Calibration(slope, intercept)


def check_grade(grade):
    """A ``--grade`` value as a :class:`GradeProfile` or a callable ``f(x, y, z) -> Dp`` (mm); None stays None."""
    if grade is None or isinstance(grade, GradeProfile):
        return grade
    if callable(grade):
        return grade
    return parse_grade(grade)


@dataclass(frozen=True)
class CTImage:
    """CT intensities in physical space (mm), as SimpleITK reads them.

    Attributes
    ----------
    values : (ni, nj, nk) float32 ndarray
        Intensities (HU for a CT), indexed ``(i, j, k)``.
    affine : (3, 4) float64 ndarray
        ``physical = affine[:, :3] @ (i, j, k) + affine[:, 3]``, mm.
    source : str
    """

    values: np.ndarray
    affine: np.ndarray
    source: str = "CT"

    def sample(self, points) -> np.ndarray:
        """Trilinear intensity at `points` ``(m, 3)`` mm (the nearest border value beyond the scan), float64."""
        from scipy import ndimage

        p = np.asarray(points, np.float64).reshape(-1, 3)
        idx = np.linalg.solve(self.affine[:, :3], (p - self.affine[:, 3]).T)
        return ndimage.map_coordinates(self.values, idx, order=1, mode="nearest").astype(np.float64)


def load_ct(path) -> CTImage:
    """The intensities of the CT volume at `path` (NIfTI, NRRD, MHA/MHD or a DICOM folder).

    The frame is the one :func:`~implicit_scaffold.fields.patient_volume.load_volume` builds the
    patient in, so the intensities sit on the bone.
    """
    from pathlib import Path

    import SimpleITK as sitk

    from ..io.images import read_image

    path = Path(path)
    image = read_image(path, folder="dicom", what="a CT volume (NIfTI, NRRD, MHA/MHD or a DICOM folder)")
    if image.GetDimension() != 3 or image.GetNumberOfComponentsPerPixel() != 1:
        raise ScaffoldError(f"--calibration reads intensities from a 3-D scalar CT; {path.name} is not one")
    spacing = np.asarray(image.GetSpacing(), np.float64)
    direction = np.asarray(image.GetDirection(), np.float64).reshape(3, 3)
    origin = np.asarray(image.GetOrigin(), np.float64)
    values = np.ascontiguousarray(sitk.GetArrayFromImage(image).T, np.float32)
    affine = np.concatenate([direction * spacing[None, :], origin[:, None]], axis=1)
    return CTImage(values, affine, path.name or str(path))


@dataclass(frozen=True)
class GradeField:
    """The targets of a graded run: pore size ``Dp(x)`` and porosity ``P(x)``.

    Attributes
    ----------
    kind : {'depth', 'function', 'ct'}
    porosity : float
        The constant porosity target (kinds depth and function).
    profile : GradeProfile, optional
        Kind depth.
    function : callable, optional
        Kind function: ``f(x, y, z)`` of coordinate arrays (mm) -> pore size (mm).
    ct : CTImage, optional
    calibration : Calibration, optional
        Kind ct.
    seed_rule : {'pore-size', 'paper'}
        How a target pore size becomes a seed density (:meth:`density`), as ``--seed-rule``.
    sv : float
        The run's cell scale factor (the pore-size rule's pore is the cell scaled by it).
    """

    kind: str
    porosity: float
    profile: GradeProfile | None = None
    function: Callable | None = None
    ct: CTImage | None = None
    calibration: Calibration | None = None
    seed_rule: str = "pore-size"
    sv: float = 0.75

    @property
    def coordinate(self) -> str:
        """What the offset field is a function of: ``depth``, ``pore_size`` or ``porosity``."""
        return {"depth": "depth", "function": "pore_size", "ct": "porosity"}[self.kind]

    def min_pore_size(self) -> float | None:
        """The smallest target pore size, mm, when known before sampling."""
        if self.kind == "depth":
            return float(min(self.profile.sizes))
        if self.kind == "ct":
            return float(min(self.calibration.pore_range))
        return None

    def targets(self, points, depth) -> tuple[np.ndarray, np.ndarray]:
        """Target pore size and porosity at `points`.

        Parameters
        ----------
        points : (m, 3) float ndarray, mm
        depth : (m,) float ndarray, mm
            Depth below the patient surface, ``-s_P`` (used by kind depth).

        Returns
        -------
        pore_size : (m,) float64 ndarray, mm
        porosity : (m,) float64 ndarray
        """
        p = np.asarray(points, np.float64).reshape(-1, 3)
        if self.kind == "depth":
            size = self.profile(depth)
            por = np.full(len(p), self.porosity)
        elif self.kind == "function":
            size = np.broadcast_to(np.asarray(self.function(p[:, 0], p[:, 1], p[:, 2]), np.float64),
                                   (len(p),)).copy()
            bad = ~(np.isfinite(size) & (size > 0))
            if bad.any():
                i = int(np.argmax(bad))
                raise ScaffoldError(f"the grade function returned pore size {size[i]!r} at "
                                    f"({p[i, 0]:.3g}, {p[i, 1]:.3g}, {p[i, 2]:.3g}) mm; it must return "
                                    "positive lengths in mm")
            por = np.full(len(p), self.porosity)
        else:
            por = self.calibration.porosity(self.ct.sample(p))
            size = self.calibration.pore_size(por)
        return size, por

    def density(self, pore_size, porosity) -> np.ndarray:
        """Seeds per mm³ for target pore sizes and porosities (float64), by :attr:`seed_rule`.

        ``pore-size``: :func:`~implicit_scaffold.geometry.seeds.density_for_pore_size` of the
        local ``Dp`` (the porosity plays no part: the offset meets it); ``paper``: the paper's
        ``P / (π Dp³ / 6)`` (:func:`seed_density_of`).

        Parameters
        ----------
        pore_size : (m,) array_like of float, mm
        porosity : (m,) array_like of float
        """
        if self.seed_rule == "paper":
            return seed_density_of(pore_size, porosity)
        from .seeds import density_for_pore_size

        size = np.asarray(pore_size, np.float64)
        return np.broadcast_to(density_for_pore_size(size, self.sv), np.broadcast(size, porosity).shape).copy()

    def describe(self) -> str:
        if self.kind == "depth":
            return f"pore size by depth {self.profile.describe()} mm"
        if self.kind == "function":
            return f"pore size from {getattr(self.function, '__name__', 'a function')}(x, y, z)"
        c = self.calibration
        return f"CT {self.ct.source}, density = {c.slope:g} HU + {c.intercept:g} g/cm3"


def grade_field(grade=None, calibration=None, ct=None, *, porosity: float, seed_rule: str = "pore-size",
                sv: float = 0.75) -> GradeField:
    """The :class:`GradeField` of a run's options.

    Parameters
    ----------
    grade : GradeProfile or callable, optional
    calibration : Calibration, optional
    ct : CTImage, optional
        Needed with `calibration`.
    porosity : float
        The constant porosity target (kinds depth and function).
    seed_rule : {'pore-size', 'paper'}
        The run's ``--seed-rule``, applied locally (:meth:`GradeField.density`).
    sv : float
        The run's cell scale factor.
    """
    rule = {"seed_rule": str(seed_rule), "sv": float(sv)}
    if calibration is not None:
        if ct is None:
            raise ScaffoldError("--calibration maps the patient's CT intensities to porosity; give --patient a "
                                "CT volume (.nii, .nrrd, .mha or a DICOM folder)")
        return GradeField("ct", float(porosity), ct=ct, calibration=calibration, **rule)
    if isinstance(grade, GradeProfile):
        return GradeField("depth", float(porosity), profile=grade, **rule)
    return GradeField("function", float(porosity), function=grade, **rule)


def seed_density_of(pore_size, porosity) -> np.ndarray:
    """The paper's seed count per unit volume, ``P / (π Dp³ / 6)``, seeds per mm³."""
    return np.asarray(porosity, np.float64) / (np.pi * np.asarray(pore_size, np.float64) ** 3 / 6.0)


def polyhedron_sphere_expected(pore_size, porosity, field: GradeField) -> np.ndarray:
    """Expected polyhedron-sphere diameter of Poisson-Voronoi cells seeded for these targets by
    the field's seed rule, mm.

    Cells of mean volume ``1/ρ`` with gamma-distributed volumes have
    ``E[Sv (6 V / π)^(1/3)] = Sv c (6 / (π ρ))^(1/3)``, ``c = Γ(k + 1/3) / (Γ(k) k^(1/3)) ≈ 0.980``
    (:func:`~implicit_scaffold.geometry.seeds.pore_size_for_density`). Under the pore-size rule
    this is ``Dp`` itself; under the paper's, ``ρ = P / (π Dp³ / 6)``, it is ``Sv c Dp / P^(1/3)``
    (0.83 Dp at P = 0.7, Sv = 0.75). It is what the uniform case measures for a target ``Dp``.

    Parameters
    ----------
    pore_size : (m,) array_like of float, mm
    porosity : (m,) array_like of float
    field : GradeField
        Its seed rule and Sv.
    """
    from .seeds import pore_size_for_density

    return pore_size_for_density(field.density(pore_size, porosity), field.sv)


# --- seeds --------------------------------------------------------------------------

@dataclass(frozen=True)
class SeedDensity:
    """The graded seed density on a fine grid, ready to draw from.

    Attributes
    ----------
    field : GradeField
    grid : Grid
        The seeding grid (no padding) over the box.
    patient_sdf : (nx, ny, nz) float32 ndarray, mm
        The patient's signed distance on `grid` (the depth is its negative).
    lo, hi : (3,) float64 ndarray, mm
        The box the seeds are drawn in.
    margin : float, mm
        Seeds fill the patient grown by one cell of the densest part: ``s_P < margin``.
    density_max : float, seeds/mm³
        A bound of the density, for rejection.
    count : int
        Seeds to draw: the density integrated over the box within the margin.
    """

    field: GradeField
    grid: Grid
    patient_sdf: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    margin: float
    density_max: float
    count: int

    def at(self, points) -> np.ndarray:
        """Seeds per mm³ at `points` ``(m, 3)`` mm (0 beyond the margin), float64."""
        from ..fields.field import sample

        p = np.asarray(points, np.float64).reshape(-1, 3)
        s = sample(self.patient_sdf, self.grid, p).astype(np.float64)
        out = np.zeros(len(p))
        keep = s < self.margin
        if keep.any():
            out[keep] = self.field.density(*self.field.targets(p[keep], -s[keep]))
        return out


def _overlap(axis_centres: np.ndarray, h: float, lo: float, hi: float) -> np.ndarray:
    """Length of each voxel ``[c - h/2, c + h/2]`` inside ``[lo, hi]``, mm."""
    return np.clip(np.minimum(axis_centres + h / 2, hi) - np.maximum(axis_centres - h / 2, lo), 0, None)


def seed_density(field: GradeField, patient, lo, hi) -> SeedDensity:
    """Sample the graded seed density on a fine grid and integrate it into a seed count.

    The grid's voxels are at most half the smallest target pore size (when known) and
    at most :data:`SEEDING_MAX_VOXELS` in number. The count is the integral of the local
    density ``ρ(x)`` of the field's seed rule (:meth:`GradeField.density`) over the box
    within ``s_P < margin`` (midpoint rule, each voxel weighted by its overlap with the box,
    so a constant field gives ``ρ V`` exactly: an even run's first count under the same
    rule), the margin being one cell of the densest part inside the patient.

    Parameters
    ----------
    field : GradeField
    patient : object with ``sdf_grid(grid)``
    lo, hi : (3,) array_like of float, mm

    Returns
    -------
    SeedDensity
    """
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    size = hi - lo
    h = (float(np.prod(size)) / SEEDING_MAX_VOXELS) ** (1 / 3)
    smallest = field.min_pore_size()
    h = max(h, smallest / 2 if smallest else float(size.max()) / 96)
    h = min(h, float(size.max()) / 24)
    grid = Grid.covering(lo, hi, h, pad=0)
    sdf = np.asarray(patient.sdf_grid(grid), np.float32)
    ax = grid.axes()
    weights = [_overlap(ax[a], h, lo[a], hi[a]) for a in range(3)]
    rho = np.zeros(grid.shape)
    dmax = 0.0
    for i in range(grid.shape[0]):
        pts = np.stack(np.meshgrid([ax[0][i]], ax[1], ax[2], indexing="ij"), -1).reshape(-1, 3)
        s = sdf[i].ravel().astype(np.float64)
        r = field.density(*field.targets(pts, -s)).reshape(grid.shape[1:])
        rho[i] = r
        inside = sdf[i] < 0
        if inside.any():
            dmax = max(dmax, float(r[inside].max()))
    if dmax <= 0:
        raise ScaffoldError("the patient covers no voxel of the seeding grid; it is too thin to grade")
    margin = dmax ** (-1 / 3)
    region = sdf < margin
    w = weights[0][:, None, None] * weights[1][None, :, None] * weights[2][None, None, :]
    count = int(round(float(np.sum(rho * w * region))))
    bound = float(rho[region].max())
    if field.kind == "ct":
        c = field.calibration
        bound = max(bound, float(field.density(min(c.pore_range), max(c.porosity_range))))
    elif field.kind == "depth":
        bound = max(bound, float(field.density(min(field.profile.sizes), field.porosity)))
    else:
        # a callable is known only at the grid's centres: allow for a peak between them
        bound *= 1.25
    if count < 2:
        raise ScaffoldError(f"the graded field asks for {count} seeds in this patient; a Voronoi lattice needs "
                            "at least 2: use smaller pore sizes")
    return SeedDensity(field, grid, sdf, lo, hi, float(margin), bound, count)


def draw_seeds(density: SeedDensity, rng: np.random.Generator, count: int | None = None) -> np.ndarray:
    """`count` seeds whose density honours the field in expectation (rejection sampling).

    Candidates are uniform in the box; each is kept with probability
    ``ρ(x) / ρ_max``, ``ρ`` read from the seeding grid (depth trilinear) at the
    candidate itself. The kept points are independent draws from the density
    ``ρ / ∫ρ``, so the seeds in a region number ``count ∫_R ρ / ∫ ρ`` on average.

    Parameters
    ----------
    density : SeedDensity
    rng : numpy.random.Generator
        From the run's ``--seed``; no global state.
    count : int, optional
        Default ``density.count``.

    Returns
    -------
    (count, 3) float64 ndarray, mm
    """
    from .seeds import uniform_seeds

    n = int(density.count if count is None else count)
    out, got = [], 0
    accept = None
    over = 0.0
    while got < n:
        want = n - got
        batch = max(4096, int(2 * want / accept) if accept else 4 * want)
        cand = uniform_seeds(density.lo, density.hi, min(batch, 4_000_000), rng)
        rho = density.at(cand)
        over = max(over, float(rho.max()) / density.density_max)
        keep = rng.random(len(cand)) * density.density_max < rho
        accept = max(float(np.mean(keep)), 1e-4)
        out.append(cand[keep])
        got += int(np.count_nonzero(keep))
    if over > 1:
        import warnings

        from ..errors import ScaffoldWarning

        warnings.warn(f"the pore-size field peaks between the seeding grid's points ({over:.2f} times the density "
                      "seen on the grid), where it got too few seeds; give a smoother grade function",
                      ScaffoldWarning, stacklevel=2)
    return np.concatenate(out)[:n]


def lloyd_relax(seeds, density: SeedDensity, iterations: int) -> np.ndarray:
    """Move each seed to its cell's density-weighted centroid, `iterations` times.

    Cells come from :func:`~implicit_scaffold.geometry.cells.voronoi_cells`; each cell is cut into
    tetrahedra (seed, face centroid, face edge) and integrated with one point per
    tetrahedron. The weight is ``ρ^(5/3)`` (:data:`LLOYD_EXPONENT`), so that the relaxed
    seeds keep the density ``ρ``; beyond the margin the weight is 0, so seeds stay in
    the patient. Cells shrink towards equal sizes where the density is even, which
    narrows the spread of the pore sizes.

    Parameters
    ----------
    seeds : (n, 3) float ndarray, mm
    density : SeedDensity
    iterations : int

    Returns
    -------
    (n, 3) float64 ndarray, mm
    """
    from .cells import voronoi_cells

    seeds = np.asarray(seeds, np.float64)
    for _ in range(int(iterations)):
        cells = voronoi_cells(seeds, density.lo, density.hi)
        start = cells.face_start
        counts = np.diff(start)
        face = np.repeat(np.arange(len(counts)), counts)
        nxt = np.arange(len(cells.face_vertices)) + 1
        nxt[start[1:] - 1] = start[:-1]
        owner = cells.face_cell[face]
        a = cells.seeds[owner]
        b = cells.face_vertices
        c = cells.face_vertices[nxt]
        d = cells.face_centroids[face]
        vol = np.abs(np.einsum("ij,ij->i", b - a, np.cross(c - a, d - a))) / 6.0
        cen = (a + b + c + d) / 4.0
        w = vol * density.at(cen) ** LLOYD_EXPONENT
        total = np.bincount(owner, weights=w, minlength=cells.n)
        moved = np.stack([np.bincount(owner, weights=w * cen[:, k], minlength=cells.n) for k in range(3)], 1)
        ok = total > 0
        new = seeds.copy()
        new[ok] = moved[ok] / total[ok, None]
        seeds = np.clip(new, density.lo, density.hi)
    return seeds


def power_radii(density: SeedDensity, seeds) -> np.ndarray:
    """Power radii that make each seed's cell follow its local target size, mm.

    The rule: ``r_i = L_i / 2``, ``L_i = ρ(s_i)^(-1/3)`` the seed spacing the field's seed
    rule asks for at the seed (:meth:`GradeField.density`; under the paper's,
    ``ρ = P / (π Dp³ / 6)``, so ``L = Dp (π / (6 P))^(1/3)``).
    For two neighbouring seeds at the mean of their spacings, ``d = (L_i + L_j) / 2``,
    the power plane ``|x - s_i|² - r_i² = |x - s_j|² - r_j²`` (weights ``w = r²``) lies
    at ``(d² + r_i² - r_j²) / (2 d) = L_i / 2`` from ``s_i``: each cell reaches half its
    own spacing, where the Voronoi plane (``d / 2``) would give the larger cell too little
    and the smaller too much. Where the neighbours' targets are equal the weights cancel
    and the plane is the Voronoi one.

    Parameters
    ----------
    density : SeedDensity
    seeds : (n, 3) float ndarray, mm

    Returns
    -------
    (n,) float64 ndarray, mm
    """
    from ..fields.field import sample

    p = np.asarray(seeds, np.float64).reshape(-1, 3)
    depth = -sample(density.patient_sdf, density.grid, p).astype(np.float64)
    return 0.5 * np.cbrt(1.0 / density.field.density(*density.field.targets(p, depth)))


# --- offset field -------------------------------------------------------------------
#
# One solver for every size: the offset is found from passes over the patient's and the
# lattice's planes, a chunk of planes at a time, so the whole grid in memory and a tiled
# run's fields on disk (:class:`~implicit_scaffold.run.tiles.FieldFile`) take the same steps and get the same
# offsets bit for bit, whatever the slabs.

#: planes are visited in chunks of about this many voxels (each pass holds one chunk's
#: band arrays, about 70 bytes per voxel at most); the figures do not depend on it
CHUNK_VOXELS = 4_000_000


def _chunks(grid: Grid, max_voxels: int | None = None) -> list:
    """Chunks of whole planes of `grid`, each of at most :data:`CHUNK_VOXELS` voxels (and
    `max_voxels`), one plane at least."""
    from ..run.tiles import Slab

    most = CHUNK_VOXELS if max_voxels is None else min(CHUNK_VOXELS, int(max_voxels))
    step = max(1, most // max(1, grid.shape[1] * grid.shape[2]))
    return [Slab(x0, min(x0 + step, grid.shape[0]), x0, min(x0 + step, grid.shape[0]))
            for x0 in range(0, grid.shape[0], step)]


def _reader(source) -> Callable[[int, int], np.ndarray]:
    """Planes ``[x0, x1)`` of an array (a view), an ArraySlabs (a view) or a FieldFile (read)."""
    if isinstance(source, np.ndarray):
        return lambda x0, x1: source[x0:x1]
    held = getattr(source, "field", None)
    if isinstance(held, np.ndarray):
        return lambda x0, x1: held[x0:x1]
    return source.read


@dataclass(frozen=True)
class BandPlanes:
    """The band voxels of a chunk of planes and their targets (C order).

    Attributes
    ----------
    mask : (x1 - x0, ny, nz) bool ndarray
        Voxels whose offset matters: the patient and two voxels around it.
    coord : (m,) float32 ndarray
        The offset's coordinate at the band's voxels (depth mm, pore size mm or porosity).
    inside : (m,) bool ndarray
        Band voxels the bins count: in the patient, below any skin.
    porosity : (m,) float32 ndarray
    pore_size : (m,) float32 ndarray, mm
    """

    mask: np.ndarray
    coord: np.ndarray
    inside: np.ndarray
    porosity: np.ndarray
    pore_size: np.ndarray


def band_planes(field: GradeField, s_p: np.ndarray, grid: Grid, x0: int, skin: float = 0.0) -> BandPlanes:
    """The band of the patient planes `s_p` (the grid's planes from `x0`) and its targets.

    Parameters
    ----------
    field : GradeField
    s_p : (x1 - x0, ny, nz) float32 ndarray, mm
    grid : Grid
    x0 : int
    skin : float, mm
        Voxels shallower than this are solid skin: the bins leave them out.
    """
    h = grid.spacing
    mask = s_p < np.float32(2 * h)
    s = s_p[mask]
    inside = s < np.float32(-skin) if skin > 0 else s < 0
    depth = -s
    if field.kind == "depth":
        # the depth alone decides: no need for the voxels' coordinates
        size = field.profile(depth).astype(np.float32)
        por = np.full(len(depth), field.porosity, np.float32)
    else:
        idx = np.argwhere(mask)
        idx[:, 0] += x0
        size, por = field.targets(np.asarray(grid.origin) + idx * h, depth)
        size, por = size.astype(np.float32), por.astype(np.float32)
    coord = {"depth": depth.astype(np.float32, copy=False), "pore_size": size, "porosity": por}[field.coordinate]
    return BandPlanes(mask, coord, inside, por, size)


@dataclass(frozen=True)
class LevelPlan:
    """The bins of the offset field: what it needs from the patient, found once per run.

    Attributes
    ----------
    field : GradeField
    grid : Grid
    edges : (b + 1,) float64 ndarray
        Bins of the coordinate, each holding at least :data:`MIN_BIN_VOXELS` patient voxels.
    skin : float, mm
        The bins count the patient's voxels deeper than this (the skin's are solid).
    porosity_mean : float
        The target porosity's mean over the voxels the bins count.
    """

    field: GradeField
    grid: Grid
    edges: np.ndarray
    skin: float = 0.0
    porosity_mean: float = 0.0

    @property
    def coordinate(self) -> str:
        return self.field.coordinate

    def band(self, s_p: np.ndarray, x0: int) -> BandPlanes:
        """:func:`band_planes` of a chunk of patient planes."""
        return band_planes(self.field, s_p, self.grid, x0, self.skin)

    def bin_of(self, coord: np.ndarray) -> np.ndarray:
        """Each coordinate's bin (0-based, int32)."""
        nb = len(self.edges) - 1
        return np.clip(np.searchsorted(self.edges, coord, side="right") - 1, 0, nb - 1).astype(np.int32)


@dataclass(frozen=True)
class LevelField:
    """The surface offset as a piecewise linear function of the plan's coordinate.

    Attributes
    ----------
    coordinate : str
    nodes : (b,) float64 ndarray
        Bin centres (coordinate units: mm, or a fraction).
    levels : (b,) float64 ndarray, mm
        The offset at each node; constant beyond the first and last.
    mean_inside : float, mm
        The mean offset over the patient's voxels (the report's one figure).
    """

    coordinate: str
    nodes: np.ndarray
    levels: np.ndarray
    mean_inside: float = 0.0

    def __call__(self, coord) -> np.ndarray:
        return np.interp(np.asarray(coord, np.float64), self.nodes, self.levels).astype(np.float32)

    def reach(self, style: str) -> float:
        """The scalar the cut-off rule reads: the largest |offset| (paper), the largest radius (struts)."""
        return float(np.max(np.abs(self.levels))) if style == "paper" else float(np.max(self.levels))


def _equal_bins(lo: float, hi: float, width: float) -> np.ndarray:
    """Equal-width edges over ``[lo, hi]``, the last just above `hi`; two for a single value."""
    if hi - lo <= 1e-9 * max(1.0, abs(hi)):
        return np.array([lo - 0.5, hi + 0.5])
    n = max(1, int(math.ceil((hi - lo) / width)))
    edges = np.linspace(lo, hi, n + 1)
    edges[-1] = np.nextafter(hi, np.inf)
    return edges


def _merge_bins(edges: np.ndarray, counts: np.ndarray, min_count: int) -> np.ndarray:
    """`edges` with each bin merged into the next until it holds `min_count`."""
    if len(edges) == 2:
        return np.asarray(edges, np.float64)
    keep = [edges[0]]
    acc = 0
    for e, c in zip(edges[1:], counts):
        acc += c
        if acc >= min_count:
            keep.append(e)
            acc = 0
    if acc and len(keep) > 1:
        keep[-1] = edges[-1]
    elif len(keep) == 1:
        keep.append(edges[-1])
    return np.asarray(keep, np.float64)


def level_plan(field: GradeField, patient_sdf, grid: Grid, *, max_voxels: int | None = None,
               skin: float = 0.0) -> LevelPlan:
    """The bins of the offset field on the run's grid, from two passes over the patient.

    Parameters
    ----------
    field : GradeField
    patient_sdf : (nx, ny, nz) float32 ndarray or FieldFile, mm
    grid : Grid
    max_voxels : int, optional
        Visit chunks of planes of at most this many voxels (a tiled run's slab size), and
        at most :data:`CHUNK_VOXELS`.
    skin : float, mm
        The skin's (and the smooth cut's) depth: its voxels are solid or cut whatever the
        offset, so the bins meet their porosity on the voxels below it.

    Returns
    -------
    LevelPlan
    """
    read, chunks = _reader(patient_sdf), _chunks(grid, max_voxels)
    lo, hi, count, por_sum = np.inf, -np.inf, 0, 0.0
    for sl in chunks:
        b = band_planes(field, read(sl.x0, sl.x1), grid, sl.x0, skin)
        c = b.coord[b.inside]
        if c.size:
            lo, hi = min(lo, float(c.min())), max(hi, float(c.max()))
            count += c.size
            por_sum += float(np.sum(b.porosity[b.inside], dtype=np.float64))
        del b, c  # before the next chunk's: one chunk's arrays at a time
    if count == 0:
        return LevelPlan(field, grid, np.array([0.0, 1.0]), float(skin), float(field.porosity))
    if field.coordinate == "depth":
        width = max(2 * grid.spacing, 0.5 * float(min(field.profile.sizes)))
    else:
        width = (hi - lo) / 24
    edges = _equal_bins(lo, hi, width)
    counts = np.zeros(len(edges) - 1, np.int64)
    if len(edges) > 2:
        for sl in chunks:
            b = band_planes(field, read(sl.x0, sl.x1), grid, sl.x0, skin)
            counts += np.histogram(b.coord[b.inside], edges)[0]
            del b
    return LevelPlan(field, grid, _merge_bins(edges, counts, MIN_BIN_VOXELS), float(skin), por_sum / count)


def _sampled(index: np.ndarray, fraction: float) -> np.ndarray:
    """Which of the voxels of global flat `index` fall in a deterministic sample of about
    `fraction` of them: a multiplicative hash of the index, so the sample is the same
    whichever slabs the voxels come in."""
    if fraction >= 1:
        return np.ones(index.shape, bool)
    hashed = (index.astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)) >> np.uint64(32)
    return hashed < np.uint64(int(fraction * 2**32))


def solve_level_field(base, patient_sdf, plan: LevelPlan, *, max_voxels: int | None = None, iterations: int = 6,
                      tolerance: float = LEVEL_TOLERANCE_MM, progress=None) -> LevelField:
    """The offset field whose solid ``base < L(x)`` meets each bin's porosity.

    The offset is linear in the coordinate between the bins' centres. Its nodes start at
    zero and settle by passes that move each node by the quantile of ``base - L(x)`` that
    meets its bin's solid count: first on a deterministic sample of about
    :data:`LEVEL_SAMPLE_VOXELS` of the bins' voxels (the same whatever the slabs), then by
    one or two exact passes over all of them, each an exact order statistic per bin
    (:class:`~implicit_scaffold.run.tiles.GroupQuantile`) over the slabs.

    Parameters
    ----------
    base : (nx, ny, nz) float32 ndarray or FieldFile, mm
        The (blended) lattice field.
    patient_sdf : (nx, ny, nz) float32 ndarray or FieldFile, mm
    plan : LevelPlan
    max_voxels : int, optional
        As for :func:`level_plan`.
    iterations : int
        At most this many passes.
    tolerance : float, mm
        Stop once no node moves by more.

    Returns
    -------
    LevelField
    """
    from ..run.tiles import GroupQuantile

    grid = plan.grid
    read_base, read_patient, chunks = _reader(base), _reader(patient_sdf), _chunks(grid, max_voxels)
    nb = len(plan.edges) - 1
    nodes = (plan.edges[:-1] + plan.edges[1:]) / 2
    plane = grid.shape[1] * grid.shape[2]

    def visit():
        # each chunk's bin voxels: their lattice values, coordinates, bins, shares and flat
        # indices; every array is let go before the next chunk's (the callers del theirs too)
        for sl in chunks:
            b = plan.band(read_patient(sl.x0, sl.x1), sl.x0)
            keep = b.inside
            vals = read_base(sl.x0, sl.x1)[b.mask][keep]
            coord = b.coord[keep]
            yield sl, b, keep, vals, coord
            del b, keep, vals, coord

    counts = np.zeros(nb, np.int64)
    shares = np.zeros(nb)
    for _, b, keep, _, coord in visit():
        which = plan.bin_of(coord)
        counts += np.bincount(which, minlength=nb)
        shares += np.bincount(which, weights=1.0 - b.porosity[keep].astype(np.float64), minlength=nb)
        del b, keep, coord, which
    total = int(counts.sum())
    if total == 0:
        return LevelField(plan.coordinate, nodes, np.zeros(nb), 0.0)
    fraction = LEVEL_SAMPLE_VOXELS / total
    parts = []
    for sl, b, keep, vals, coord in visit():
        index = (np.flatnonzero(b.mask)[keep] + sl.x0 * plane).astype(np.int64)
        pick = _sampled(index, fraction)
        parts.append((vals[pick], coord[pick], plan.bin_of(coord[pick]),
                      1.0 - b.porosity[keep][pick].astype(np.float64), index[pick]))
        del b, keep, vals, coord, index, pick
    vals, coord, which, share, index = (np.concatenate([p[i] for p in parts]) for i in range(5))
    del parts
    order = np.lexsort((index, which))
    vals, coord, which, share = vals[order], coord[order], which[order], share[order]
    del order, index
    # each node at its bin's mean coordinate, over the sample (in the sample's order, which no
    # slab decides): the bins' voxels are not spread evenly (fewer deeper in), so the midpoint
    # would set the offset off the voxels it serves
    bounds = np.concatenate([[0], np.cumsum(np.bincount(which, minlength=nb))])
    nodes = np.array([coord[bounds[b]:bounds[b + 1]].mean(dtype=np.float64) if bounds[b + 1] > bounds[b]
                      else nodes[b] for b in range(nb)])
    levels = _settle(vals, coord, which, share, nb, nodes, np.zeros(nb), iterations, tolerance)
    del vals, coord, which, share
    if fraction < 1:
        # the exact passes: each bin's solid count over all its voxels
        solid = np.rint(shares).astype(np.int64)
        def shifted(coord, vals):
            return vals - np.interp(coord, nodes, levels).astype(np.float32)

        for _ in range(2):
            quantile = GroupQuantile(nb)
            for _, _, _, vals, coord in visit():
                quantile.count(shifted(coord, vals), plan.bin_of(coord))
                del vals, coord
            full = solid >= counts
            ranks = np.where(solid <= 0, 0, np.where(full, counts - 1, solid - 1))
            ranks = np.stack([ranks, np.where((solid <= 0) | full, ranks, solid)], axis=1)
            quantile.select(np.maximum(ranks, 0))
            for _, _, _, vals, coord in visit():
                quantile.refine(shifted(coord, vals), plan.bin_of(coord))
                del vals, coord
            below, above = quantile.values().T
            step = np.where(counts == 0, 0.0, np.where(solid <= 0, below - 1e-6, np.where(
                full, above + 1e-6, level_between(below, above))))
            levels = levels + step
            if np.max(np.abs(step)) < tolerance:
                break
    total_level = 0.0
    for sl in chunks:
        b = plan.band(read_patient(sl.x0, sl.x1), sl.x0)
        total_level += float(np.sum(np.interp(b.coord[b.inside], nodes, levels)))
        del b
    return LevelField(plan.coordinate, nodes, levels, total_level / total)


def _settle(vals, coord, which, share, nb: int, nodes, levels, iterations: int, tolerance: float) -> np.ndarray:
    """Passes of per-bin quantile corrections of the offset nodes (voxels sorted by bin)."""
    bounds = np.concatenate([[0], np.cumsum(np.bincount(which, minlength=nb))])
    solid = np.rint(np.bincount(which, weights=share, minlength=nb)).astype(np.int64)
    levels = np.array(levels, np.float64)
    for _ in range(iterations):
        shifted = vals - np.interp(coord, nodes, levels).astype(np.float32)
        step = np.zeros(nb)
        for b in range(nb):
            seg = shifted[bounds[b]:bounds[b + 1]]
            m, k = len(seg), solid[b]
            if m == 0:
                continue
            if k <= 0:
                step[b] = float(seg.min()) - 1e-6
            elif k >= m:
                step[b] = float(seg.max()) + 1e-6
            else:
                part = np.partition(seg, (k - 1, k))
                below, above = float(part[k - 1]), float(part[k])
                step[b] = level_between(below, above)
        levels = levels + step
        if np.max(np.abs(step)) < tolerance:
            break
    return levels


def shift_planes(base: np.ndarray, s_p: np.ndarray, x0: int, plan: LevelPlan, level: LevelField) -> np.ndarray:
    """``base - L(x)`` in place over the band of a chunk of planes (beyond it the patient cut
    decides alone); `base` and `s_p` are the grid's planes from `x0`."""
    b = plan.band(s_p, x0)
    base[b.mask] -= level(b.coord)
    return base


def apply_level(base: np.ndarray, patient_sdf: np.ndarray, plan: LevelPlan, level: LevelField) -> np.ndarray:
    """:func:`shift_planes` over the whole grid in memory, a chunk of planes at a time."""
    for sl in _chunks(plan.grid):
        shift_planes(base[sl.x0:sl.x1], patient_sdf[sl.x0:sl.x1], sl.x0, plan, level)
    return base


# --- profiles for the report ----------------------------------------------------------

def _profile_sums(coord_vox, solid_vox, target_por, target_size, edges) -> np.ndarray:
    """``(4, b)`` per bin: voxels, solid voxels, target porosity and target pore size sums."""
    nb = len(edges) - 1
    which = np.clip(np.searchsorted(edges, coord_vox, side="right") - 1, 0, nb - 1)
    return np.stack([np.bincount(which, minlength=nb).astype(np.float64),
                     np.bincount(which, weights=solid_vox.astype(np.float64), minlength=nb),
                     np.bincount(which, weights=target_por, minlength=nb),
                     np.bincount(which, weights=target_size, minlength=nb)])


def _profile(sums, coord_seeds, sizes, expected, edges) -> dict:
    nb = len(edges) - 1
    nvox, nsolid, tpor, tsize = sums
    cw = np.clip(np.searchsorted(edges, coord_seeds, side="right") - 1, 0, nb - 1)
    inb = (coord_seeds >= edges[0]) & (coord_seeds <= edges[-1])
    ncell = np.bincount(cw[inb], minlength=nb).astype(np.float64)
    dsum = np.bincount(cw[inb], weights=sizes[inb], minlength=nb)
    esum = np.bincount(cw[inb], weights=expected[inb], minlength=nb)

    def ratio(a, b):
        return [float(x / y) if y > 0 else None for x, y in zip(a, b)]

    return {
        "edges_mm": [float(e) for e in edges],
        "voxels": [int(v) for v in nvox],
        "porosity": [None if v == 0 else float(1 - s / v) for s, v in zip(nsolid, nvox)],
        "porosity_target": ratio(tpor, nvox),
        "pore_size_target_mm": ratio(tsize, nvox),
        "cells": [int(c) for c in ncell],
        "pore_size_mm": ratio(dsum, ncell),
        "pore_size_expected_mm": ratio(esum, ncell),
    }


def profiles(s, grid: Grid, cells, sv: float, field: GradeField, patient_sdf, *, axis: int | None = None,
             bins: int = 24, max_voxels: int | None = None, below: float = 0.0) -> dict:
    """Porosity and mean pore size against depth and along an axis, beside their targets.

    Porosity is measured on the voxels (``1 - solid / patient`` per bin, the skin
    included); pore size is the mean polyhedron-sphere diameter of the cells whose seed
    lies in the bin, beside the mean target ``Dp`` of the bin's voxels and the
    polyhedron-sphere size expected for the targets at the seeds under the field's seed
    rule (:func:`polyhedron_sphere_expected`: the target itself under ``pore-size``). Three passes over the planes (the range, the
    depth bins' counts, the sums), so a tiled run's fields on disk give the figures
    of the whole grid.

    Parameters
    ----------
    s : (nx, ny, nz) float32 ndarray or FieldFile, mm
        The scaffold field (negative in the solid).
    grid : Grid
    cells : Cells
    sv : float
    field : GradeField
    patient_sdf : (nx, ny, nz) float32 ndarray or FieldFile, mm
    axis : int, optional
        Default: the grid's longest axis.
    bins : int
        Bins along the axis (and at most this many times two in depth).
    max_voxels : int, optional
        As for :func:`level_plan`.
    below : float, mm
        A skin's depth: the porosity of the voxels deeper than it is measured too.

    Returns
    -------
    dict
        ``{"depth": {...}, "axis": {...}, "axis_name": "z", "below": {...}}``, each profile with
        ``edges_mm``, ``porosity``, ``porosity_target``, ``pore_size_mm``,
        ``pore_size_target_mm``, ``pore_size_expected_mm``, ``voxels``, ``cells``; with
        `below`, ``below`` is ``{"depth_mm", "voxels", "porosity", "porosity_target"}``.
    """
    from ..measure.metrics import pore_sizes
    from ..run.tiled import sample_slabs
    from ..run.tiles import ArraySlabs

    read_s, read_patient, chunks = _reader(s), _reader(patient_sdf), _chunks(grid, max_voxels)
    axis = int(np.argmax(grid.shape)) if axis is None else int(axis)

    def visit():
        # one chunk's arrays at a time: each is let go before the next (the callers del theirs)
        for sl in chunks:
            s_p = read_patient(sl.x0, sl.x1)
            b = band_planes(field, s_p, grid, sl.x0)
            shape = [1, 1, 1]
            shape[axis] = s_p.shape[axis]
            start = sl.x0 if axis == 0 else 0
            index = np.arange(start, start + s_p.shape[axis], dtype=np.int32).reshape(shape)
            idx = np.broadcast_to(index, s_p.shape)[b.mask][b.inside]
            depth = -s_p[b.mask][b.inside].astype(np.float64)
            del s_p
            along = grid.origin[axis] + idx * grid.spacing
            del idx
            yield sl, b, depth, along
            del b, depth, along

    seeds_from = patient_sdf if not isinstance(patient_sdf, np.ndarray) else ArraySlabs(patient_sdf, grid)
    seed_sdf = sample_slabs(seeds_from, grid, cells.seeds).astype(np.float64)
    seed_in = seed_sdf < 0
    d_cells = pore_sizes(cells, sv)[seed_in]
    sp, sporo = field.targets(cells.seeds[seed_in], -seed_sdf[seed_in])
    expected = polyhedron_sphere_expected(sp, sporo, field)
    dlo, dhi, alo, ahi = np.inf, -np.inf, np.inf, -np.inf
    for _, _, depth, along in visit():
        if depth.size:
            dlo, dhi = min(dlo, float(depth.min())), max(dhi, float(depth.max()))
            alo, ahi = min(alo, float(along.min())), max(ahi, float(along.max()))
        del depth, along
    if not np.isfinite(dlo):
        dlo = dhi = alo = ahi = 0.0
    width = max(2 * grid.spacing, dhi / (2 * bins))
    if field.kind == "depth":
        width = max(width, 0.5 * float(min(field.profile.sizes)))
    depth_edges = _equal_bins(dlo, dhi, width)
    counts = np.zeros(len(depth_edges) - 1, np.int64)
    for _, _, depth, _ in visit():
        counts += np.histogram(depth, depth_edges)[0]
        del depth
    # bins too thin to count reliably (the deepest, near the core's axis) join their neighbours
    depth_edges = _merge_bins(depth_edges, counts, MIN_BIN_VOXELS)
    axis_edges = np.linspace(alo - grid.spacing / 2, ahi + grid.spacing / 2, bins + 1)
    depth_sums, axis_sums, deep = 0.0, 0.0, np.zeros(3)
    for sl, b, depth, along in visit():
        solid = (read_s(sl.x0, sl.x1)[b.mask] < 0)[b.inside]
        tpor, tsize = b.porosity[b.inside].astype(np.float64), b.pore_size[b.inside].astype(np.float64)
        depth_sums = depth_sums + _profile_sums(depth, solid, tpor, tsize, depth_edges)
        axis_sums = axis_sums + _profile_sums(along, solid, tpor, tsize, axis_edges)
        if below > 0:
            # as the offset's bins count them (band_planes): the patient's distance below -skin
            under = (-depth).astype(np.float32) < np.float32(-below)
            deep += [np.count_nonzero(under), np.count_nonzero(solid[under]), float(np.sum(tpor[under]))]
            del under
        del b, depth, along, solid, tpor, tsize
    out = {"depth": _profile(depth_sums, -seed_sdf[seed_in], d_cells, expected, depth_edges),
           "axis": _profile(axis_sums, cells.seeds[seed_in, axis], d_cells, expected, axis_edges),
           "axis_name": "xyz"[axis]}
    if below > 0:
        out["below"] = {"depth_mm": float(below), "voxels": int(deep[0]),
                        "porosity": float(1 - deep[1] / deep[0]) if deep[0] else None,
                        "porosity_target": float(deep[2] / deep[0]) if deep[0] else None}
    return out
