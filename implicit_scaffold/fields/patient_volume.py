"""Volume patients: bone from a CT or a segmentation (NIfTI, NRRD, MHA/MHD, DICOM series).

The frame is SimpleITK's (ITK's) physical space: voxel index ``(i, j, k)`` lies at
``origin + direction @ (spacing * (i, j, k))`` in mm, which for DICOM and for NIfTI read by
ITK is the patient's LPS frame (x towards the patient's left, y posterior, z superior).
The scaffold is built in that frame, so it sits where the bone is in the scan, and a mesh
written by the tool overlays the volume in any viewer that reads meshes as LPS.

The bone's surface is a smooth signed distance built from the voxel mask:

1. the mask, cropped to the bone plus a margin (voxels beyond the image are not bone, so
   bone cut by the image border is closed at the border), gives the signed distance to the
   union of its voxel boxes (exact for faces, with the half-voxel correction built in);
2. a Gaussian of :data:`SMOOTH_VOXELS` voxels (in index space, so each axis is smoothed at
   its own spacing), with its curvature bias removed to second order, damps the staircase
   of coarse voxels; it is kept within half a voxel (measured along the normal) of the voxel
   boundary, and every voxel centre stays on its side, so a rod or plate one voxel thin is
   kept (a plain Gaussian erases it);
3. the smooth surface is redistanced (closest points by Newton steps on a cubic interpolant,
   carried outwards by the distance transform), so the field is a signed distance in mm;
4. a constant offset, solved so that the surface encloses the mask's volume (voxel count
   times voxel volume), removes what bias remains; ``volume`` is then measured on the
   surface itself (the trilinear interpolant's, column by column in each cell);
5. the field is interpolated trilinearly at any point mapped through the inverse of
   ``direction @ diag(spacing)``, tile by tile; outside the crop it grows with the distance
   to the crop, so it stays positive (outside) everywhere beyond the bone.

Every step and the bounds run as compiled kernels (:mod:`~implicit_scaffold.fields.volume_kernels`); their
NumPy/SciPy forms stay here as oracles (``load_volume(..., reference=True)``), many times
slower (``benchmarks/bench_load.py`` prints the ratio).
"""
from __future__ import annotations

import math
from pathlib import Path

import warnings

import numpy as np

from ..errors import ScaffoldError, ScaffoldWarning
from ..run.grid import Grid, evaluate_by_slabs

#: Gaussian width of the staircase removal, in voxels of the volume (per axis); 1.5 measured
#: best on a 3 mm ball (normals 5 degrees off on average) among 1.0-2.0
SMOOTH_VOXELS = 1.5
#: how far (in voxels along the surface normal) the smoothing may move the surface off the voxel
#: boundary: half a voxel keeps it between inside and outside voxel centres, as Whitaker (1998)
TUBE_VOXELS = 0.5
#: margin (in voxels of the smallest spacing) by which every voxel centre stays on its side
KEEP_VOXELS = 0.1
#: voxels of "outside" kept around the bone's bounding box: the smoothing's support
#: (4 sigma) plus room for the surface to move and for the outside distance
MARGIN_VOXELS = 8
#: grid points evaluated per tile in :meth:`VolumePatient.sdf_grid` (bounds the work arrays)
_TILE_POINTS = 1_000_000
#: columns per cell side in :meth:`VolumePatient._level_volume` (the cross-section's samples)
VOLUME_COLUMNS = 4
#: the volume fit stops within this share of the mask's volume
VOLUME_TOLERANCE = 1e-5
#: the volume fit's offset stays within this many voxels (of the largest spacing) of the smoothed surface,
#: which the smoothing keeps within half a voxel of the mask's boundary: a bone that fills the image to its
#: borders (the box cuts it, and the volume's cells round the box's edges) left the volume short of the mask's
#: at any offset, and the secant steps ran the field off to -29,000 mm
FIT_OFFSET_VOXELS = 1.0
#: the redistance's Newton steps stop after a chord step this short (voxels; the closest points then
#: move by less than 1e-6 voxel)
NEWTON_STILL = 1e-5


def _name(path: Path) -> str:
    return path.name or str(path)


def _read_image(path: Path):
    """The image at `path` (a file, or a folder holding a DICOM series) (:func:`~implicit_scaffold.io.images.read_image`)."""
    from ..io.images import read_image

    return read_image(path, folder="dicom", what="a volume (NIfTI, NRRD, MHA/MHD or a DICOM folder)")


#: a label map holds at most this many distinct labels (TotalSegmentator's has 117); an image
#: with more, or with a negative or fractional value, holds intensities (a CT's Hounsfield units)
MAX_LABELS = 1000
#: voxels sampled to count an image's distinct values: a stride over the flat array, so that a
#: 512 x 512 x 500 CT is judged in milliseconds, not by sorting all of it
_LABEL_SAMPLE = 2_000_000


def intensity_range(array: np.ndarray) -> tuple[float, float] | None:
    """``(min, max)`` of `array` when it holds intensities (a CT or a grey-level scan), not labels.

    A label map holds whole, non-negative values, at most :data:`MAX_LABELS` distinct ones. A CT
    in Hounsfield units holds air at about -1000; a grey-level scan, or a probability map, holds
    many distinct or fractional values. The minimum and maximum are the whole array's; the
    distinct and fractional values are judged on a strided sample of its voxels (no copy of a
    float CT, which can be half a GB). None for a label map or a binary mask.
    """
    flat = array.reshape(-1)
    sample = flat[::max(1, flat.size // _LABEL_SAMPLE)]
    if np.issubdtype(array.dtype, np.floating):
        sample = sample[np.isfinite(sample)]
        if sample.size == 0:
            return None
        # the finite values' range: an infinite voxel (warned about by bone_mask) is no intensity, and -inf
        # made a label map read as a CT ("intensities (-inf to inf)")
        finite = np.isfinite(flat)
        lo = float(np.min(flat, where=finite, initial=np.inf))
        hi = float(np.max(flat, where=finite, initial=-np.inf))
        del finite
        fractional = bool(np.any(sample != np.round(sample)))
    else:
        lo, hi = float(flat.min()), float(flat.max())
        fractional = False
    if lo < 0 or fractional or np.unique(sample).size > MAX_LABELS:
        return lo, hi
    return None


def _labels(label) -> list[int]:
    """`label` (a whole number, several of them, or a text such as ``"30,31"``) as a list of ints;
    a one-line :class:`ScaffoldError` otherwise."""
    parts = str(label).replace(",", " ").split() if isinstance(label, str) else \
        (list(label) if isinstance(label, (list, tuple, np.ndarray)) else [label])
    out = []
    for v in parts:
        try:
            lab = float(v)
        except (TypeError, ValueError):
            lab = float("nan")
        if not (math.isfinite(lab) and lab == int(lab)):
            raise ScaffoldError(f"--label must be a whole number, or several as 30,31, got {label!r}")
        if int(lab) not in out:
            out.append(int(lab))
    if not out:
        raise ScaffoldError(f"--label must be a whole number, or several as 30,31, got {label!r}")
    return out


def _warn_not_numbers(array: np.ndarray, name: str, label, threshold) -> None:
    """A :class:`ScaffoldWarning` naming the voxels of a float image that are NaN or infinite, and what
    :func:`bone_mask`'s selection makes of them: NaN reaches no threshold, is no label and is left out of a
    mask (no bone, holes in it without a word); +inf reaches every threshold and -inf none, and a mask's
    non-zero voxels take both."""
    nan = int(np.count_nonzero(np.isnan(array)))
    inf = int(np.count_nonzero(np.isinf(array)))
    if not (nan or inf):
        return
    parts = [f"{nan:,} NaN voxels, read as no bone"] if nan else []
    if inf:
        how = ("read as no bone" if label is not None else
               "+inf read as bone, -inf as no bone" if threshold is not None else "read as bone")
        parts.append(f"{inf:,} infinite voxels, {how}")
    warnings.warn(f"{name} holds {' and '.join(parts)}; replace them in the image with the intensities they "
                  "stand for", ScaffoldWarning, stacklevel=3)


def bone_mask(array: np.ndarray, name: str, label, threshold) -> tuple[np.ndarray, str]:
    """The bone voxels of `array` and a phrase saying how they were chosen.

    `label` keeps a segmentation's label (or several: a list, or a text such as ``"30,31"``: a
    bone in several pieces, e.g. four vertebrae), `threshold` a CT's intensities at or above it (HU);
    with neither, every non-zero voxel of a mask (one non-zero value), unless the image holds intensities
    (:func:`intensity_range`) or several labels (a one-line :class:`ScaffoldError` asks for `label` then).
    The patient of ``generate`` and the volumes of ``analyze``, ``check`` and ``mechanics`` are chosen here.
    """
    if label is not None and threshold is not None:
        raise ScaffoldError("give --label (a segmentation) or --threshold (a CT), not both")
    if np.issubdtype(array.dtype, np.floating):
        _warn_not_numbers(array, name, label, threshold)
    if threshold is None:
        # a CT given as if it were a segmentation: a label would keep the voxels of exactly that
        # many HU (scattered soft tissue), no selection every voxel but those of 0 HU
        span = intensity_range(array)
        if span is not None:
            what = f"--label {label} would keep only its voxels of exactly {label}" if label is not None \
                else "every non-zero voxel would be bone"
            ct = " (bone is about 200 HU and above in a CT)" if span[0] < 0 else ""
            # the example is one the image reaches: 200 HU for a CT, else its range's middle (a label map
            # resampled linearly holds 0 to its largest label, and 200 would keep no voxel)
            example = 200 if span[0] < 200 <= span[1] else float(f"{(span[0] + span[1]) / 2:.2g}")
            raise ScaffoldError(f"{name} holds intensities ({span[0]:g} to {span[1]:g}), not labels, so {what}; "
                                f"pass --threshold with the bone's lowest intensity{ct}, e.g. --threshold {example:g}, "
                                "or give its segmentation's label map with --label N (resampled to nearest neighbour)")
    if label is not None:
        labs = _labels(label)
        mask = np.isin(array, labs)
        # one label: its mask says it; several: each is looked for (a pass each)
        missing = [] if len(labs) == 1 and mask.any() else [v for v in labs if not np.any(array == v)]
        if missing:
            present = np.unique(array[np.isfinite(array)]) if np.issubdtype(array.dtype, np.floating) \
                else np.unique(array)
            present = present[present != 0]
            shown = ", ".join(f"{v:g}" for v in present[:40]) + (" ..." if present.size > 40 else "")
            which = f"label {missing[0]} has" if len(missing) == 1 else \
                f"labels {', '.join(str(v) for v in missing)} have"
            raise ScaffoldError(f"{which} no voxel in {name}; labels present: {shown or 'none (every voxel is 0)'}")
        return mask, (f"label {labs[0]}" if len(labs) == 1 else f"labels {', '.join(str(v) for v in labs)}")
    if threshold is not None:
        try:
            thr = float(threshold)
        except (TypeError, ValueError):
            raise ScaffoldError(f"--threshold must be a number (HU), got {threshold!r}") from None
        if not math.isfinite(thr):
            raise ScaffoldError(f"--threshold must be a finite number (HU), got {threshold!r}")
        mask = array >= thr
        if not mask.any():
            raise ScaffoldError(f"no voxel of {name} reaches the threshold {thr:g} (intensities "
                                f"{np.nanmin(array):g} to {np.nanmax(array):g}); use a lower --threshold")
        if mask.all() and mask.size > 1:
            # air and soft tissue too: the bone is the image's whole box
            warnings.warn(f"every voxel of {name} reaches the threshold {thr:g} (intensities {np.nanmin(array):g} "
                          f"to {np.nanmax(array):g}): the bone is the whole image; bone is about 200 HU and above "
                          "in a CT", ScaffoldWarning, stacklevel=2)
        return mask, f"intensity >= {thr:g}"
    mask = (array != 0) & ~np.isnan(array) if np.issubdtype(array.dtype, np.floating) else array != 0
    if not mask.any():
        raise ScaffoldError(f"{name} has no bone: every voxel is 0; pass --threshold HU for a CT "
                            "or --label N for a segmentation")
    # a segmentation of several structures (a whole-body label map holds organs beside the bones):
    # which labels are bone is the user's to say; a mask (one non-zero value) is bone throughout
    first = array.reshape(-1)[np.argmax(mask.reshape(-1))]
    if np.any(mask & (array != first)):
        present = np.unique(array[mask])
        shown = ", ".join(f"{v:g}" for v in present[:40]) + (" ..." if present.size > 40 else "")
        raise ScaffoldError(f"{name} is a label map of {present.size} labels ({shown}); name the bone's with "
                            f"--label N, or several as --label {present[0]:g},{present[1]:g} (every labelled voxel "
                            f"would otherwise be bone, organs too)")
    return mask, "non-zero voxels"


def _signed_box_distance(mask: np.ndarray, spacing: np.ndarray) -> np.ndarray:
    """Signed distance (mm, float32, negative inside) from each voxel centre to the boundary of
    the union of the mask's voxel boxes: :func:`_box_distance` outside minus inside, by the
    compiled feature transform (:mod:`~implicit_scaffold.fields.volume_kernels`).
    """
    from .volume_kernels import feature_transform, kernels

    h = [float(v) for v in spacing]
    out = np.zeros(mask.shape, np.float32)
    box = kernels().box_distance
    for features, sign in ((mask, 1.0), (~mask, -1.0)):
        fi, fj, fk = feature_transform(features, h)
        box(features, fi, fj, fk, h[0], h[1], h[2], sign, out)
        del fi, fj, fk
    return out


def _box_distance(mask: np.ndarray, spacing: np.ndarray) -> np.ndarray:
    """Distance (mm) from each voxel centre outside `mask` to the union of the mask's voxel boxes
    (the NumPy/SciPy oracle of :func:`_signed_box_distance`).

    The nearest voxel centre (Euclidean, anisotropic) is found by the distance transform;
    the distance to that voxel's box is the half-voxel correction, exact across a face.
    """
    from scipy import ndimage

    near = ndimage.distance_transform_edt(~mask, sampling=spacing, return_distances=False,
                                          return_indices=True)
    out = np.zeros(mask.shape, np.float32)
    sq = np.zeros(mask.shape, np.float32)
    for a in range(3):
        idx = np.arange(mask.shape[a], dtype=np.float32).reshape([-1 if b == a else 1 for b in range(3)])
        gap = np.abs(near[a].astype(np.float32) - idx) * spacing[a] - spacing[a] / 2
        sq += np.maximum(gap, 0) ** 2
    np.sqrt(sq, out=out)
    return out


def _gaussian_weights(sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """The 1-D Gaussian of `sigma` (voxels) and its second derivative, as
    ``scipy.ndimage.gaussian_filter1d`` samples them (truncated at 4 sigma), float32."""
    r = int(4.0 * sigma + 0.5)
    x = np.arange(-r, r + 1, dtype=np.float64)
    g = np.exp(-0.5 * x * x / sigma ** 2)
    g /= g.sum()
    return g.astype(np.float32), ((x * x / sigma ** 4 - 1 / sigma ** 2) * g).astype(np.float32)


def _unbiased_gaussian(field: np.ndarray, sigma: float) -> np.ndarray:
    """:func:`_unbiased_gaussian_reference` by the compiled separable passes of
    :mod:`~implicit_scaffold.fields.volume_kernels` (three passes over the grid, the 1-D Gaussians and their second
    derivatives shared between the terms, float32 throughout, both cores)."""
    from .volume_kernels import kernels

    if sigma <= 0:
        return field.astype(np.float32, copy=True)
    k = kernels()
    w0, w2 = _gaussian_weights(sigma)
    half = np.float32(sigma ** 2 / 2)
    f = np.ascontiguousarray(field, np.float32)
    a, b = np.empty_like(f), np.empty_like(f)
    k.gauss_k(f, w0, w2, a, b)                       # along k: G, G''
    c, d = np.empty_like(f), np.empty_like(f)
    k.gauss_j(a, b, w0, w2, half, c, d)              # G G, G G - sigma²/2 (G'' G + G G'')
    del a, b
    out = np.empty_like(f)
    k.gauss_i(c, d, w0, w2, half, out)               # ... - sigma²/2 G'' G G
    return out


def _unbiased_gaussian_reference(field: np.ndarray, sigma: float) -> np.ndarray:
    """A Gaussian of `sigma` voxels without its curvature bias: ``G - sigma²/2 · ΔG``.

    A Gaussian moves a curved surface by ``sigma²/2 · Δf`` (it shrinks convex parts); the
    correction removes that to second order, while the voxel staircase (wavelengths of
    two voxels, damped by ``exp(-π²σ²/2)``) stays damped.
    """
    from scipy import ndimage

    if sigma <= 0:
        return field.astype(np.float32, copy=True)
    out = ndimage.gaussian_filter(field, sigma, mode="nearest", output=np.float32)
    for a in range(3):
        order = [0, 0, 0]
        order[a] = 2
        out -= np.float32(sigma ** 2 / 2) * ndimage.gaussian_filter(field, sigma, order=order, mode="nearest",
                                                                      output=np.float32)
    return out


def _smooth_surface(mask: np.ndarray, spacing: np.ndarray, *, reference: bool = False) -> np.ndarray:
    """A smooth field whose zero level is the bone's surface without the voxel staircase.

    The signed distance to the union of the voxel boxes is smoothed by an unbiased
    Gaussian of :data:`SMOOTH_VOXELS` voxels along each index axis, kept within a tube around
    it of :data:`TUBE_VOXELS` x the voxel's extent along the surface normal (with anisotropic
    voxels the tube is wide across the thick slices, where the steps are) and with every voxel
    centre :data:`KEEP_VOXELS` on its own side (so a plate one voxel thin, which a plain
    Gaussian erases, is kept), then smoothed again lightly to round the constraints' kinks.
    Negative inside, mm. `reference`: every step in NumPy/SciPy (SciPy's feature transform).
    """
    if reference:
        box = _box_distance(mask, spacing) - _box_distance(~mask, spacing)
        gaussian, tube = _unbiased_gaussian_reference, _tube_clip_reference
    else:
        box = _signed_box_distance(mask, spacing)
        gaussian, tube = _unbiased_gaussian, _tube_clip
    lower, upper, field = tube(gaussian(box, SMOOTH_VOXELS), box, mask, spacing)
    del box
    field = gaussian(field, SMOOTH_VOXELS / 2)
    return np.clip(field, lower, upper, out=field)


def _tube_clip(field: np.ndarray, box: np.ndarray, mask: np.ndarray, spacing: np.ndarray):
    """:func:`_tube_clip_reference` in one compiled pass (:mod:`~implicit_scaffold.fields.volume_kernels`)."""
    from .volume_kernels import kernels

    lower, upper, clipped = (np.empty(field.shape, np.float32) for _ in range(3))
    h = [float(v) for v in spacing]
    kernels().tube_clip(field, box, mask, h[0], h[1], h[2], float(TUBE_VOXELS), float(KEEP_VOXELS * min(h)),
                        lower, upper, clipped)
    return lower, upper, clipped


def _tube_clip_reference(field: np.ndarray, box: np.ndarray, mask: np.ndarray, spacing: np.ndarray):
    """``(lower, upper, clipped)``: the bounds a smoothed `field` must keep (mm), the box
    distance `box` -/+ :data:`TUBE_VOXELS` x the voxel's extent along the normal of `field`,
    every voxel centre :data:`KEEP_VOXELS` on its side of the `mask`; and `field` clipped to them.
    """
    # the voxel's extent along the unit normal n: sum |n_a| h_a (its support width)
    grad = np.gradient(field, *spacing)
    norm = np.sqrt(sum(g * g for g in grad))
    np.maximum(norm, np.float32(1e-6), out=norm)
    tube = sum(np.abs(g) * np.float32(h) for g, h in zip(grad, spacing)) / norm
    del grad, norm
    tube *= np.float32(TUBE_VOXELS)
    # every voxel centre stays on its side, by a margin: a rod one voxel thin survives
    margin = np.float32(KEEP_VOXELS * spacing.min())
    lower = box - tube
    upper = box + tube
    np.minimum(upper, -margin, out=upper, where=mask)
    np.maximum(lower, margin, out=lower, where=~mask)
    del tube
    return lower, upper, np.clip(field, lower, upper)


def _band(field: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(inside, band)``: the voxels below 0, and those next to a sign change with their neighbours."""
    from scipy import ndimage

    inside = field < 0
    band = ndimage.binary_dilation(inside) & ~ndimage.binary_erosion(inside, border_value=1)
    return inside, ndimage.binary_dilation(band)


def _redistance(field: np.ndarray, spacing: np.ndarray, newton: int = 5) -> np.ndarray:
    """The signed distance (mm) to the zero level of `field`, on the same grid.

    Points near the surface are projected onto it by Newton steps along the gradient
    (closest points on the smooth surface: a cubic spline of `field`); every other point
    takes the distance to the closest point of its nearest near-surface voxel. The
    compiled form (:mod:`~implicit_scaffold.fields.volume_kernels`) of :func:`_redistance_reference`: the spline's
    analytic gradient where that one takes central differences of 0.05 voxel, the feature
    transform's choice among equally near band voxels, otherwise the same steps.
    """
    from .volume_kernels import feature_transform, kernels, spline_coefficients

    k = kernels()
    h = np.asarray(spacing, np.float64)
    inside = field < 0
    band = np.empty(field.shape, bool)
    k.band(inside, band)
    pts = np.argwhere(band).astype(np.int32)                # crop indices
    coef = spline_coefficients(field)
    q = np.empty(pts.shape, np.float64)
    valid = np.empty(len(pts), bool)
    # two full Newton steps, then the gradient is kept (see _redistance_reference)
    k.newton(coef, pts, h, newton, 2, 2 * float(h.max()), NEWTON_STILL * float(h.min()), 0.01 * float(h.min()),
             q, valid)
    del coef
    lookup = np.full(field.shape, -1, np.int32)
    lookup[band] = np.arange(len(pts), dtype=np.int32)
    chosen = np.empty(len(pts), np.int64)
    k.choose(pts, q, valid, lookup, h, chosen)
    q = q[chosen]
    fi, fj, fk = feature_transform(band, h)
    out = np.empty(field.shape, np.float32)
    k.owner_distance(inside, fi, fj, fk, lookup, q, h, out)
    return out


def _redistance_reference(field: np.ndarray, spacing: np.ndarray, newton: int = 5) -> np.ndarray:
    """:func:`_redistance` in NumPy and SciPy (its oracle, 10-30x slower)."""
    from scipy import ndimage

    spacing = np.asarray(spacing, np.float64)
    # the voxels next to a sign change, and their neighbours
    inside = field < 0
    band = ndimage.binary_dilation(inside) & ~ndimage.binary_erosion(inside, border_value=1)
    band = ndimage.binary_dilation(band)
    pts = np.argwhere(band).astype(np.float64)              # crop indices
    q = pts.copy()
    coef = ndimage.spline_filter(field, order=3, output=np.float32, mode="nearest")

    def spline(x):
        return ndimage.map_coordinates(coef, x.T, order=3, mode="nearest", prefilter=False).astype(np.float64)

    eye = 0.05 * np.eye(3)   # central differences of the spline itself, so Newton is consistent
    limit = 2 * float(spacing.max())
    for it in range(newton):
        f = spline(q)
        if it < 2:
            # the gradient of a field close to a distance hardly turns along the short step to the
            # surface: after two full steps the later ones keep it (a chord method), which saves
            # six of every seven spline evaluations there, the bulk of the loading time
            g = np.stack([(spline(q + eye[a]) - spline(q - eye[a])) / (0.1 * spacing[a]) for a in range(3)], 1)
        g2 = np.maximum((g ** 2).sum(axis=1), 1e-12)
        step = (f / g2)[:, None] * g                        # mm
        # band points lie within two voxels of the surface: a longer step is a flat spot's blunder
        length = np.linalg.norm(step, axis=1)
        step[length > limit] *= (limit / length[length > limit])[:, None]
        q = q - step / spacing
    # where Newton fails (a flat spot: the mid-plane of a plate one voxel thin) a neighbour's
    # closest point is the right one: each band voxel takes the nearest of its 27 neighbours'
    valid = np.abs(spline(q)) <= 0.01 * float(spacing.min())
    lookup = np.full(field.shape, -1, np.int64)
    lookup[band] = np.arange(len(pts))
    ipts = pts.astype(np.int64)
    best = np.full(len(pts), np.inf)
    chosen = np.arange(len(pts))
    for off in np.ndindex(3, 3, 3):
        nb = ipts + np.asarray(off) - 1
        ok = np.all((nb >= 0) & (nb < np.asarray(field.shape)), axis=1)
        cand = np.full(len(pts), -1, np.int64)
        cand[ok] = lookup[tuple(nb[ok].T)]
        cand[cand >= 0] = np.where(valid[cand[cand >= 0]], cand[cand >= 0], -1)
        use = cand >= 0
        d = np.full(len(pts), np.inf)
        d[use] = (((pts[use] - q[cand[use]]) * spacing) ** 2).sum(axis=1)
        better = d < best
        best[better], chosen[better] = d[better], cand[better]
    q = q[chosen]
    near = ndimage.distance_transform_edt(~band, sampling=spacing, return_distances=False,
                                          return_indices=True)
    owner = lookup[tuple(near)]
    del near
    dist_sq = np.zeros(field.shape, np.float32)
    for a in range(3):
        idx = np.arange(field.shape[a], dtype=np.float32).reshape([-1 if b == a else 1 for b in range(3)])
        dist_sq += ((idx - q[owner, a].astype(np.float32)) * np.float32(spacing[a])) ** 2
    dist = np.sqrt(dist_sq)
    return np.where(inside, -dist, dist).astype(np.float32)


class VolumePatient:
    """A patient read from a volume: the bone's smooth signed distance in physical space (mm).

    Use :func:`load_volume` to build one. The signed distance is kept at the volume's own
    resolution, on the bone's bounding box plus :data:`MARGIN_VOXELS` (float32), and is
    interpolated at any point; memory does not grow with the scaffold grid.

    Attributes
    ----------
    lo, hi : (3,) float64 ndarray, mm
        Axis-aligned bounds of the bone's surface in physical space.
    volume : float, mm³
        Volume enclosed by the smooth surface (the zero level of :meth:`sdf_grid`); equal to
        the mask's voxel count times the voxel volume (by construction, to
        :data:`VOLUME_TOLERANCE`; 1e-4 with ``reference=True``).
    spacing : (3,) float64 ndarray, mm
        The volume's voxel size along its index axes i, j, k.
    image_shape : (3,) tuple of int
        Voxels of the whole image along i, j, k.
    mask_voxels : int
        Voxels selected as bone.
    source, selection : str
        The file's name, and how bone was chosen (label, threshold or non-zero).
    """

    def __init__(self, field: np.ndarray, affine: np.ndarray, shift: np.ndarray, *, source: str,
                 selection: str, image_shape, spacing, mask_voxels: int, reference: bool = False):
        self._field = np.ascontiguousarray(field, np.float32)
        self._affine = np.asarray(affine, np.float64)          # physical = A[:, :3] @ index + A[:, 3]
        self._inverse = np.linalg.inv(self._affine[:, :3])
        self._shift = np.asarray(shift, np.float64)            # crop index 0 in the full image's indices
        self.source = source
        self.selection = selection
        self.image_shape = tuple(int(v) for v in image_shape)
        self.spacing = np.asarray(spacing, np.float64)
        self.mask_voxels = int(mask_voxels)
        target = self.mask_voxels * float(np.prod(self.spacing))
        if reference:
            self.volume = self._fit_volume_reference(target)
            self.lo, self.hi = self._bounds_reference()
        else:
            self.volume = self._fit_volume(target)
            self.lo, self.hi = self._bounds()

    # --- evaluation ---------------------------------------------------------------------
    def _to_index(self, x, y, z) -> np.ndarray:
        """Crop indices ``(3, ...)`` of physical points given as broadcastable coordinate arrays."""
        m, t = self._inverse, self._affine[:, 3]
        p = (x - t[0], y - t[1], z - t[2])
        return np.stack(np.broadcast_arrays(*[m[r, 0] * p[0] + m[r, 1] * p[1] + m[r, 2] * p[2]
                                              - self._shift[r] for r in range(3)]))

    def _lookup(self, idx: np.ndarray) -> np.ndarray:
        """Field at crop indices ``(3, ...)``; beyond the crop, the border value plus the distance to it."""
        from scipy import ndimage

        hi = np.asarray(self._field.shape, np.float64)[:, None] - 1
        flat = idx.reshape(3, -1)
        inside = np.clip(flat, 0, hi)
        val = ndimage.map_coordinates(self._field, inside, order=1, mode="nearest", output=np.float32)
        gap = (flat - inside) * self.spacing[:, None]
        far = np.any(gap != 0, axis=0)
        if far.any():
            val[far] = np.maximum(val[far], 0) + np.sqrt((gap[:, far] ** 2).sum(axis=0))
        val = np.maximum(val, self._image_box(*flat))
        return val.reshape(idx.shape[1:])

    def _image_box(self, i, j, k) -> np.ndarray:
        """Signed distance (mm) to the image's extent at broadcastable crop indices.

        Bone stops where the scan stops: the field is intersected with the image's box
        (half a voxel beyond the first and last voxel centres), so no surface offset or
        smoothing carries the bone past the border.
        """
        q = []
        for a, c in enumerate((i, j, k)):
            n = self.image_shape[a]
            q.append((np.abs(c + self._shift[a] - (n - 1) / 2) - n / 2) * self.spacing[a])
        outside = np.sqrt(sum(np.maximum(v, 0) ** 2 for v in q))
        return (outside + np.minimum(np.maximum(np.maximum(q[0], q[1]), q[2]), 0)).astype(np.float32)

    def sdf(self, points) -> np.ndarray:
        """Signed distance at `points` ``(m, 3)`` mm, ``(m,)`` float32, negative inside the bone."""
        p = np.asarray(points, np.float64).reshape(-1, 3)
        return self._lookup(self._to_index(p[:, 0], p[:, 1], p[:, 2]))

    def sdf_grid(self, grid: Grid, x_range=None) -> np.ndarray:
        """Signed distance on `grid` (the planes `x_range` only, if given), float32, mm,
        negative inside; tile by tile."""
        return evaluate_by_slabs(grid, lambda x, y, z: self._lookup(self._to_index(x, y, z)),
                                 max_voxels=_TILE_POINTS, x_range=x_range)

    # --- measures -----------------------------------------------------------------------
    def _samples(self, upsample: int, x0: int, x1: int, level: float = 0.0) -> np.ndarray:
        """Field minus `level` on the crop's lattice refined `upsample` (1 or 2) times, planes
        ``[x0, x1)`` along i, cut by the image's box.
        """
        n = (np.asarray(self._field.shape) - 1) * upsample + 1
        axes = [np.arange(x0, x1)[:, None, None] / upsample, np.arange(n[1])[None, :, None] / upsample,
                np.arange(n[2])[None, None, :] / upsample]
        values = self._refined(upsample, x0, x1) - np.float32(level)
        return np.maximum(values, self._image_box(*axes))

    def _refined(self, upsample: int, x0: int, x1: int) -> np.ndarray:
        """The (bone) field on the crop's lattice refined `upsample` (1 or 2) times, planes ``[x0, x1)``.

        Trilinear values at the midpoints are means of the neighbouring samples, so the
        refinement is separable slicing, with no interpolation call.
        """
        if upsample == 1:
            return self._field[x0:x1]
        c0, c1 = x0 // 2, (x1 - 1 + 1) // 2 + 1
        block = self._field[c0:c1]
        for axis in range(3):
            n = block.shape[axis]
            fine = np.empty(block.shape[:axis] + (2 * n - 1,) + block.shape[axis + 1:], np.float32)
            even = [slice(None)] * 3
            odd = [slice(None)] * 3
            even[axis], odd[axis] = slice(0, None, 2), slice(1, None, 2)
            fine[tuple(even)] = block
            lo_, hi_ = [slice(None)] * 3, [slice(None)] * 3
            lo_[axis], hi_[axis] = slice(0, -1), slice(1, None)
            fine[tuple(odd)] = (block[tuple(lo_)] + block[tuple(hi_)]) * np.float32(0.5)
            block = fine
        return block[x0 - 2 * c0:x1 - 2 * c0]

    def _mc_volume(self, upsample: int, level: float = 0.0) -> tuple[float, float]:
        """Volume (mm³) and area (mm²) inside the `level` set, by marching cubes, slab by slab.

        Slabs share their boundary plane, so their cubes partition the lattice and the
        divergence-theorem sums of their (open) pieces add up to the closed surface's.
        """
        from skimage import measure

        n = (np.asarray(self._field.shape) - 1) * upsample + 1
        rows = max(2, _TILE_POINTS // int(n[1] * n[2]))
        volume = area = 0.0
        step = 1.0 / upsample
        for x0 in range(0, n[0] - 1, rows - 1):
            x1 = min(x0 + rows, n[0])
            values = self._samples(upsample, x0, x1, level)
            if x0 == 0:
                values = np.concatenate([np.ones_like(values[:1]), values])
            if x1 == n[0]:
                values = np.concatenate([values, np.ones_like(values[:1])])
            # "outside" around the crop closes the surface
            values = np.pad(values, ((0, 0), (1, 1), (1, 1)), constant_values=np.float32(1))
            if not (values.min() < 0 < values.max()):
                continue
            verts, faces, _, _ = measure.marching_cubes(values, 0.0, spacing=(step,) * 3, method="lewiner")
            verts += np.array([x0 * step - (step if x0 == 0 else 0.0), -step, -step])
            phys = (verts + self._shift) @ self._affine[:, :3].T   # translation does not change volume
            tri = phys[faces]
            volume += float(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum()) / 6
            area += float(np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()) / 2
        return abs(volume), area

    def _volume(self, level: float = 0.0) -> tuple[float, float]:
        """Volume (mm³) inside the `level` set of the interpolated field, and its area (mm²).

        Marching cubes misses a convex surface's volume by O(h²); two refinements (the
        volume's own lattice and one twice as fine) extrapolate that away (Richardson).
        """
        v1, _ = self._mc_volume(1, level)
        v2, area = self._mc_volume(2, level)
        return (4 * v2 - v1) / 3, area

    def _level_volume(self, level: float) -> tuple[float, float]:
        """Volume (mm³) inside the `level` set of the interpolated field cut by the image's box,
        and its derivative with `level` (mm²).

        Each cell of the crop is cut into :data:`VOLUME_COLUMNS`² columns along k, along which the
        trilinear field is linear, so the length inside each column is exact; the columns'
        midpoints sample the cell's cross-section (compiled, :mod:`~implicit_scaffold.fields.volume_kernels`).
        """
        from .volume_kernels import kernels

        shape = np.asarray(self.image_shape, np.float64)
        vol, der = kernels().level_volume(self._field, float(level), self._shift.astype(np.float64), shape,
                                          self.spacing, VOLUME_COLUMNS)
        cell = float(np.prod(self.spacing))
        return vol * cell, der * cell

    def _fit_volume(self, target: float) -> float:
        """Offset the surface so that it encloses `target` mm³; return the volume it then encloses.

        The smoothing shrinks convex parts of the bone by about ``sigma² x mean curvature``;
        a constant offset (the field stays a distance) restores the mask's volume on average.
        A Newton step on :meth:`_level_volume` (its derivative comes with it), then secant
        steps (the sampled derivative runs a few per cent off the volume's own slope, which
        left Newton converging only linearly), stop within :data:`VOLUME_TOLERANCE` of `target`.
        """
        c = 0.0
        vol, der = self._level_volume(c)
        limit = FIT_OFFSET_VOXELS * float(np.max(self.spacing))
        for _ in range(12):
            if abs(vol - target) <= VOLUME_TOLERANCE * target or der <= 0:
                break
            c_new = min(max(c + (target - vol) / der, -limit), limit)
            if c_new == c:
                break  # at the limit: the mask's volume lies beyond the reach of an offset
            step = c_new - c
            vol_new, der_new = self._level_volume(c_new)
            secant = (vol_new - vol) / step
            c, vol, der = c_new, vol_new, secant if secant > 0 else der_new
        self._field -= np.float32(c)
        return vol

    def _fit_volume_reference(self, target: float) -> float:
        """Offset the surface so that it encloses `target` mm³; return the volume it then encloses.

        The smoothing shrinks convex parts of the bone by about ``sigma² x mean curvature``;
        a constant offset (the field stays a distance) restores the mask's volume on average.
        The Richardson correction of marching cubes' volume (:meth:`_volume`) is computed once,
        at the unshifted surface: the offset is a fraction of a voxel, which changes that O(h²)
        term by far less than the 1e-4 the fit stops at, and the lattice twice as fine (8x the
        samples) is where most of the loading time went on a bone with much surface.
        """
        c0 = 0.0
        v1, _ = self._mc_volume(1, c0)
        v2, area = self._mc_volume(2, c0)
        correction = 4 * (v2 - v1) / 3
        f0 = v1 + correction
        c1 = (target - f0) / max(area, 1e-12)
        f1 = f0
        for _ in range(8):
            f1 = self._mc_volume(1, c1)[0] + correction
            if abs(f1 - target) <= 1e-4 * target or f1 == f0:
                break
            c0, f0, c1 = c1, f1, c1 + (target - f1) * (c1 - c0) / (f1 - f0)
        self._field -= np.float32(c1)
        return f1

    def _bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounds (mm) of the bone: :meth:`_bounds_reference`, compiled
        (:mod:`~implicit_scaffold.fields.volume_kernels`), without the refined lattice in memory."""
        from .volume_kernels import kernels

        n0 = self._field.shape[0]
        lo = np.full((n0, 3), np.inf)
        hi = np.full((n0, 3), -np.inf)
        kernels().near_bounds(self._field, self._shift.astype(np.float64), np.asarray(self.image_shape, np.float64),
                              self.spacing, float(self.spacing.max()), self._affine, lo, hi)
        return lo.min(axis=0), hi.max(axis=0)

    def _bounds_reference(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounds (mm) of the bone: inscribed balls of the inside samples.

        A sample at signed distance ``-d`` has the ball of radius ``d`` inside the bone, and
        the sample nearest an extreme point touches it there; samples at twice the volume's
        resolution make the bounds tight.
        """
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        n = (np.asarray(self._field.shape) - 1) * 2 + 1
        rows = max(1, _TILE_POINTS // int(n[1] * n[2]))
        for x0 in range(0, n[0], rows):
            x1 = min(x0 + rows, n[0])
            values = self._samples(2, x0, x1)
            # only near the surface: deep samples carry the interpolation's error at the medial axis
            near = (values < 0) & (values > -self.spacing.max())
            inside = np.argwhere(near)
            if inside.size == 0:
                continue
            d = -values[near].astype(np.float64)
            idx = (inside + [x0, 0, 0]) / 2.0 + self._shift
            phys = idx @ self._affine[:, :3].T + self._affine[:, 3]
            lo = np.minimum(lo, (phys - d[:, None]).min(axis=0))
            hi = np.maximum(hi, (phys + d[:, None]).max(axis=0))
        return lo, hi

    def describe(self) -> str:
        """One line: the source, what was kept, the voxel size and the bone's size and volume."""
        size = self.hi - self.lo
        return (f"volume {self.source} ({self.selection}; {'x'.join(map(str, self.image_shape))} voxels of "
                f"{' x '.join(f'{s:.4g}' for s in self.spacing)} mm): bone "
                f"{' x '.join(f'{s:.1f}' for s in size)} mm, {self.volume:.1f} mm3")


def load_volume(path, *, label=None, threshold=None, reference: bool = False, spacing=None) -> VolumePatient:
    """Read a bone volume and build its smooth signed distance.

    Parameters
    ----------
    path : str or Path
        A NIfTI (``.nii``, ``.nii.gz``), NRRD, MHA/MHD file, or a folder holding a DICOM series.
    label : int, optional
        Keep the voxels equal to this segmentation label.
    threshold : float, optional
        Keep the voxels whose intensity is at least this (Hounsfield units for a CT).
        Without `label` or `threshold`, every non-zero voxel is bone.
    reference : bool
        Build the field by the NumPy/SciPy oracles of the compiled steps (SciPy's feature
        transform, the redistance in NumPy, marching cubes' volume at two resolutions):
        10-30x slower; for tests and benchmarks.
    spacing : float or (3,) floats, mm, optional
        The voxel spacing of a file whose header states none (a NRRD or MetaImage without
        one: ITK would read 1 mm voxels, and a 0.05 mm micro-CT would become a bone 20 times
        its size); it replaces the header's.

    Returns
    -------
    VolumePatient
        In SimpleITK's physical space (mm; LPS for DICOM and NIfTI).

    Raises
    ------
    ScaffoldError
        Unreadable file, not a 3-D scalar volume, bad spacing or direction, or no bone voxel.
    """
    import SimpleITK as sitk

    path = Path(path)
    name = _name(path)
    image = _read_image(path)
    if image.GetNumberOfComponentsPerPixel() != 1:
        raise ScaffoldError(f"{name} has {image.GetNumberOfComponentsPerPixel()} values per voxel; "
                            "give a scalar volume (a CT or a label map)")
    dim = image.GetDimension()
    size = image.GetSize()
    if dim != 3 or min(size) < 2:
        shape = "x".join(map(str, size))
        raise ScaffoldError(f"{name} is a {dim}-D image of {shape} voxels, not a volume; give a 3-D scan "
                            "(a DICOM folder holds one file per slice)")
    from ..io.images import header_states_spacing, spacing_triple, warn_spacing_override

    if spacing is not None:
        warn_spacing_override(path, image, spacing, folder="dicom")
        image.SetSpacing(spacing_triple(spacing))
    elif not header_states_spacing(path, folder="dicom"):
        raise ScaffoldError(f"{name} states no voxel spacing, so its size is unknown (ITK would read 1 mm voxels); "
                            "give it with --spacing (mm), e.g. --spacing 0.05 or --spacing \"0.05 0.05 0.1\"")
    spacing = np.asarray(image.GetSpacing(), np.float64)
    if not (np.all(np.isfinite(spacing)) and np.all(spacing > 0)):
        raise ScaffoldError(f"{name} has voxel spacing {tuple(spacing.tolist())}; spacings must be "
                            "positive finite mm (fix the header)")
    direction = np.asarray(image.GetDirection(), np.float64).reshape(3, 3)
    origin = np.asarray(image.GetOrigin(), np.float64)
    if not (np.all(np.isfinite(direction)) and np.all(np.isfinite(origin))):
        raise ScaffoldError(f"{name} has a non-finite origin or direction in its header; fix the header")
    # distances are computed along the index axes: they must be orthogonal
    if not np.allclose(direction.T @ direction, np.eye(3), atol=1e-4):
        raise ScaffoldError(f"{name} has a sheared (non-orthogonal) direction matrix; resample it to an "
                            "orthogonal grid first")

    array = sitk.GetArrayViewFromImage(image).T       # (i, j, k): SimpleITK arrays are (k, j, i)
    mask, selection = bone_mask(array, name, label, threshold)
    count = int(np.count_nonzero(mask))
    nz = np.nonzero(mask.any(axis=(1, 2)))[0], np.nonzero(mask.any(axis=(0, 2)))[0], \
        np.nonzero(mask.any(axis=(0, 1)))[0]
    first = np.array([v[0] for v in nz])
    last = np.array([v[-1] for v in nz])
    # crop to the bone plus a margin; beyond the image the padding is "not bone"
    start = first - MARGIN_VOXELS
    stop = last + 1 + MARGIN_VOXELS
    lo_in, hi_in = np.maximum(start, 0), np.minimum(stop, np.asarray(mask.shape))
    crop = np.zeros(tuple(stop - start), bool)
    crop[tuple(slice(a - s, b - s) for a, b, s in zip(lo_in, hi_in, start))] = \
        mask[tuple(slice(a, b) for a, b in zip(lo_in, hi_in))]
    del array, mask

    smooth = _smooth_surface(crop, spacing, reference=reference)
    field = (_redistance_reference if reference else _redistance)(smooth, spacing)
    del smooth
    affine = np.concatenate([direction * spacing[None, :], origin[:, None]], axis=1)
    patient = VolumePatient(field, affine, start, source=name, selection=selection, image_shape=size,
                            spacing=spacing, mask_voxels=count, reference=reference)
    return patient
