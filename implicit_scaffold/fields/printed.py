"""The surface level for what gets printed: the mesh's volume or the slice stack's grey levels.

The quantile of :func:`~implicit_scaffold.fields.field.solve_level` meets the porosity target in
voxel-centre counts. A printer builds something else: marching cubes interpolates
linearly between voxel centres, which shaves walls only a few voxels thick (the
default cube's mesh read 0.815 for a target of 0.80), and the slices' anti-aliased
grey levels follow ``clip(0.5 - s / pixel, 0, 1)``. Both measures depend on the level
smoothly, so the level is found by a secant search on the measure itself.

Meshing the whole grid at every step would cost a marching cubes each; instead the
measure is taken on a calibration prism: every x and z plane, a central band of y rows
(the mesh's volume there is exact without caps, :func:`~implicit_scaffold.mesh.marching.prism_volume`).
The prism's own voxel porosity at the voxel level stands for the whole grid's (the
target), so the search asks the prism's printed porosity to equal it: what the prism
samples differently from the whole cancels out. The final porosity is then measured on
what was written (the mesh's volume, the stack's grey levels), never assumed.
"""
from __future__ import annotations


import numpy as np

from .field import scaffold_field

#: most voxels the calibration prism holds: its marching cubes runs a few times
PRISM_VOXELS = 2_000_000
#: printed porosity the search stops within (points of porosity / 100)
TOLERANCE = 2e-4
#: a whole mesh this far from the target gets one corrective step (:func:`correction`)
CORRECT_ABOVE = 1e-3
#: voxels a pixel centre may lie off a voxel centre and still count as on it (rounding)
ON_CENTRE = 1e-6


def prism_bands(shape, max_voxels: int | None = None, rows=None) -> tuple[slice, slice]:
    """The calibration prism's y and z bands: every z plane and a band of y rows, as many as
    `max_voxels` allows (the whole grid when it holds no more): the central band, or, where `rows`
    says it holds under half the patient of the band that holds most, that band.

    The prism keeps the grid's x and z faces, so the lattice cut by the patient's surface
    there is sampled in proportion, as well as the interior; only the y faces are missed.

    Parameters
    ----------
    shape : (3,) ints
        The grid's shape.
    max_voxels : int, optional
        Default :data:`PRISM_VOXELS`.
    rows : (ny,) array_like, optional
        The patient's voxels in each y row (estimates will do): two bones apart along y leave the
        central rows empty, and a prism there measures nothing (the calibration was then skipped, and
        the printed porosity missed its target by 4 points).

    Returns
    -------
    (slice, slice)
        Index ranges along y and z; the prism is ``field[:, ys, zs]``.
    """
    nx, ny, nz = (int(v) for v in shape)
    wy = min(ny, max(3, (PRISM_VOXELS if max_voxels is None else max_voxels) // (nx * nz)))
    y0 = (ny - wy) // 2
    if rows is not None and wy < ny:
        held = np.convolve(np.asarray(rows, np.float64), np.ones(wy), mode="valid")  # held[y] by rows y .. y + wy - 1
        # the fullest band, the central one among equals
        best = int(np.lexsort((np.abs(np.arange(held.size) - y0), -held))[0])
        if held[y0] < 0.5 * held[best]:
            y0 = best
    return slice(y0, y0 + wy), slice(0, nz)


#: rows of a y-face band: the grid's face row, the row its surface closes against, one more
#: so that the band's open cut stays off that surface
FACE_ROWS = 3


def face_bands(shape, ys: slice) -> list[slice]:
    """The bands of rows at the grid's two y faces, when the prism's `ys` leaves them out.

    Marching cubes closes the whole mesh inside the grid's forced outer layer, a shave
    the prism's open y faces do not see (about 0.05 point of porosity on the default
    cube); :func:`face_shave` measures it on these bands.
    """
    ny = int(shape[1])
    if (ys.start == 0 and ys.stop == ny) or ny < 2 * FACE_ROWS:
        return []
    return [slice(0, FACE_ROWS), slice(ny - FACE_ROWS, ny)]


def face_shave(s: np.ndarray, spacing: float, *, z_faces: bool) -> float:
    """The solid volume (mm^3) that forcing a band's first y row outside takes off the mesh.

    Parameters
    ----------
    s : (nx, FACE_ROWS, nz) float32 ndarray, mm
        The scaffold field on a band of rows, the grid's face row first.
    spacing : float, mm
    z_faces : bool
        The band spans the grid's z faces (forced outside too).
    """
    from ..mesh.marching import prism_volume

    open_, _ = prism_volume(s, spacing, z_faces=z_faces)
    forced, _ = prism_volume(s, spacing, z_faces=z_faces, first_y=True)
    return open_ - forced


#: pixel centres of the calibration prism sampled at a time when the printed porosity is measured on slices
PRINTED_BLOCK_POINTS = 1 << 21


def printed_measure(by: str, grid, ys: slice, zs: slice, *, pixel: float | None = None,
                    layer: float | None = None):
    """``f(s) -> (solid volume mm^3, d volume / d level mm^2)`` of a field on the prism, as printed.

    Parameters
    ----------
    by : {"mesh", "slices"}
        Marching cubes' volume (:func:`~implicit_scaffold.mesh.marching.prism_volume`), or the grey levels of the
        printer's pixels whose centres fall in the prism: the field sampled trilinearly
        there, ``clip(0.5 - s / pixel, 0, 1)``, as :mod:`~implicit_scaffold.mesh.slices` writes them.
    grid : Grid
        The whole grid.
    ys, zs : slice
        The prism's bands (:func:`prism_bands`).
    pixel, layer : float, mm, optional
        Slices only; the voxel size by default.
    """
    h = float(grid.spacing)
    if by == "mesh":
        from ..mesh.marching import prism_volume

        y_faces, z_faces = ys.start == 0 and ys.stop == grid.shape[1], zs.start == 0 and zs.stop == grid.shape[2]
        # raising the level by dt moves the surface out by about dt: the volume grows by area * dt
        return lambda s: prism_volume(s, h, y_faces=y_faces, z_faces=z_faces)
    from scipy import ndimage

    from ..mesh.slices import stack_geometry

    pixel, layer = float(pixel or h), float(layer or h)
    origin, (width, height, layers) = stack_geometry(grid, pixel, layer)
    centres = [(origin[0] + (np.arange(width) + 0.5) * pixel - grid.origin[0]) / h,
               (origin[1] + (np.arange(height) + 0.5) * pixel - grid.origin[1]) / h,
               (origin[2] + (np.arange(layers) + 0.5) * layer - grid.origin[2]) / h]
    # the pixels whose centres the prism's voxels surround, in the prism's own indices; a centre
    # on a voxel's centre computes a rounding away from it (0.03 mm pixels put row 413 at
    # 412.99999999999994), and a strict test there dropped a whole row of a thin prism: 1 of 3
    # rows, so the femoral shaft at 0.03 mm printed 0.55 for 0.70
    centres[0] = np.clip(centres[0], 0, grid.shape[0] - 1)
    for axis, band in ((1, ys), (2, zs)):
        c = centres[axis]
        centres[axis] = np.clip(c[(c >= band.start - ON_CENTRE) & (c <= band.stop - 1 + ON_CENTRE)] - band.start,
                                0, band.stop - band.start - 1)
    cell = pixel * pixel * layer
    cx, cy, cz = centres
    # the pixels' coordinates a block of x columns at a time (PRINTED_BLOCK_POINTS): made at once, 24 bytes a
    # pixel and layer and as much again to sample them, a 4 mm cube sliced at 0.001 mm pixels took 24 GB and was
    # killed by the system, whatever --max-memory said
    block = max(1, PRINTED_BLOCK_POINTS // max(1, cy.size * cz.size))
    # one block: its coordinates made once for every level tried
    whole = (np.stack([g.ravel() for g in np.meshgrid(cx, cy, cz, indexing="ij")]) if cx.size <= block else None)

    def grey_levels(s):
        s = np.asarray(s, np.float32)
        total, ramp = 0.0, 0
        for a in range(0, cx.size, block):
            coords = whole if whole is not None else \
                np.stack([g.ravel() for g in np.meshgrid(cx[a:a + block], cy, cz, indexing="ij")])
            v = ndimage.map_coordinates(s, coords, order=1, mode="nearest")
            cover = np.clip(0.5 - v / pixel, 0.0, 1.0)
            ramp += int(np.count_nonzero((cover > 0) & (cover < 1)))
            total += float(cover.sum(dtype=np.float64))
        return total * cell, ramp * cell / pixel

    return grey_levels


def clean_prism(s: np.ndarray, spacing: float, *, remove_fragments: bool, fill_sealed_voids: bool,
                cut_y: bool, cut_z: bool, pieces: np.ndarray | None = None,
                keep_interior: bool = False) -> np.ndarray:
    """What the scaffold stage does after the level, on a prism: fragments out, sealed voids filled.

    A piece that touches a face where the prism cuts the grid (`cut_y`, `cut_z`) may go
    on outside it: it is kept as solid, or left open as void. On the whole grid this is
    :func:`~implicit_scaffold.fields.field.remove_fragments` then :func:`~implicit_scaffold.fields.field.fill_sealed_voids`, exactly. With the
    patient's `pieces` (their labels on the prism), each piece keeps its own main body, as the
    scaffold stage does (:func:`~implicit_scaffold.run.pieces.remove_fragments_by_piece`).
    """
    from ..run.pieces import label_pieces

    from .field import fill_sealed_voids

    if remove_fragments:
        labels, count = label_pieces(s < 0)
        if count > 1:
            sizes = np.bincount(labels.ravel())
            sizes[0] = 0
            if pieces is not None:
                from ..run.pieces import main_bodies

                keep = main_bodies(labels, sizes, pieces)
            else:
                keep = np.zeros(count + 1, bool)
                keep[int(np.argmax(sizes))] = True
            for face in ([labels[:, 0], labels[:, -1]] if cut_y else []) + \
                        ([labels[:, :, 0], labels[:, :, -1]] if cut_z else []):
                keep[face] = True
            keep[0] = True
            s[~keep[labels]] = np.float32(spacing)
    if fill_sealed_voids:
        # void pieces on a cut face touch the prism's (forced void) outer layer: open
        fill_sealed_voids(s, inside=spacing, keep_interior=keep_interior)
    return s


def printed_level(base: np.ndarray, patient: np.ndarray, level: float, measure, *, spacing: float,
                  skin: float = 0.0, smooth_cut: float = 0.0, iterations: int = 8, clean=None,
                  open_faces: tuple[bool, bool] = (False, False), bands=(), shave=None,
                  whole_volume: float | None = None) -> tuple[float, dict]:
    """The level at which the prism's printed porosity equals its voxel porosity at `level`.

    Parameters
    ----------
    base : (nx, py, pz) float32 ndarray, mm
        The blended lattice field on the calibration prism (solid below the level).
    patient : (nx, py, pz) float32 ndarray, mm
        The patient's signed distance on the prism.
    level : float, mm
        The level that meets the target in voxel counts (the quantile).
    measure : callable
        From :func:`printed_measure`.
    spacing : float, mm
        The voxel size.
    skin, smooth_cut : float, mm
        As in :func:`~implicit_scaffold.fields.field.scaffold_field`.
    iterations : int
        Most measures taken.
    clean : callable(s) -> s, optional
        What follows the level in the scaffold stage (:func:`clean_prism`).
    open_faces : (bool, bool)
        Whether the prism's y (z) faces are open cuts of the grid, where the marching
        cubes' volume (:func:`~implicit_scaffold.mesh.marching.prism_volume`) stops at the outer rows' centres: the
        patient's volume it is divided by then counts those rows by half.
    bands : sequence of (base, patient) float32 ndarray pairs, mm
        The fields on the grid's y-face bands (:func:`face_bands`), the face row first.
    shave : callable(s) -> float, optional
        The volume the face's forced row takes off a band (:func:`face_shave`).
    whole_volume : float, mm^3, optional
        The patient's whole volume: the bands' shave, added to the prism's printed
        porosity, is a share of it.

    Returns
    -------
    (float, dict)
        The level, mm, and what the search did: the prism's voxels, its target porosity,
        the porosity printed at the voxel level and at the level found, the steps.
    """
    inside = int(np.count_nonzero(patient < 0))
    info = {"prism_voxels": int(base.size), "prism_inside_voxels": inside, "voxel_level_mm": float(level)}
    if inside < 1000:
        # too little of the patient in the prism to measure anything: keep the voxel level
        info["skipped"] = "the calibration prism holds too little of the patient"
        return float(level), info
    # the patient's volume in the prism (exact for flat faces): the report divides by the
    # patient's true volume, so a mesh that the grid's outer layer clips counts as printed
    h = float(spacing)
    cover = np.clip(0.5 - patient / np.float32(h), 0.0, 1.0).astype(np.float64)
    # the measured volume spans from the first to the last row's centre across an open face
    for axis, is_open in ((1, open_faces[0]), (2, open_faces[1])):
        if is_open and cover.shape[axis] > 1:
            ends = [slice(None)] * 3
            for end in (0, -1):
                ends[axis] = end
                cover[tuple(ends)] *= 0.5
    whole = float(cover.sum()) * h ** 3
    del cover

    def porosity(t):
        s = scaffold_field(base, patient, level=t, skin=skin, smooth_cut=smooth_cut)
        solid_voxels = int(np.count_nonzero(s < 0))
        if clean is not None:
            s = clean(s)
        solid, rate = measure(s)
        lost = 0.0
        if shave is not None and whole_volume:
            lost = sum(shave(scaffold_field(b, pt, level=t, skin=skin, smooth_cut=smooth_cut))
                       for b, pt in bands) / whole_volume
        return 1.0 - solid / whole + lost, rate / whole, solid_voxels

    p, slope, solid_voxels = porosity(level)
    target = 1.0 - solid_voxels / inside
    info.update(prism_target=target, printed_at_voxel_level=p)
    points = [(float(level), p)]
    t = float(level)
    for step in range(1, iterations):
        if abs(p - target) <= TOLERANCE:
            break
        if len(points) >= 2 and points[-1][1] != points[-2][1]:
            (t0, p0), (t1, p1) = points[-2], points[-1]
            t = t1 + (target - p1) * (t1 - t0) / (p1 - p0)
        elif slope > 0:
            t = t + (p - target) / slope
        else:
            break
        p, slope, _ = porosity(t)
        points.append((t, p))
    t, p = min(points, key=lambda tp: abs(tp[1] - target))
    info.update(level_mm=t, printed_at_level=p, steps=len(points), slope_per_mm=_slope(points))
    return t, info


def _slope(points) -> float | None:
    """d porosity / d level from the search's two points closest to its end (None if flat)."""
    pts = sorted(points, key=lambda tp: tp[0])
    if len(pts) < 2:
        return None
    (t0, p0), (t1, p1) = sorted(points[-2:], key=lambda tp: tp[0])
    return (p1 - p0) / (t1 - t0) if t1 > t0 and p1 != p0 else None


def correction(printed: float, target: float, info: dict, max_step: float | None = None) -> float | None:
    """The level step that brings the whole mesh's measured porosity to the target, or None.

    The prism samples a few thousand cells; how much marching cubes shaves varies from
    cell to cell, so the whole mesh can land a few tenths of a point off. One Newton step
    with the prism's slope then fixes it (the porosity is close to linear over such a
    step). None when the mesh is within :data:`CORRECT_ABOVE` already. A tiled run takes
    the step on its field on disk and streams its mesh once more
    (:func:`~implicit_scaffold.run.tiled.shift_level`), as the whole grid meshes twice.
    """
    slope = (info or {}).get("slope_per_mm")
    if not slope or abs(printed - target) <= CORRECT_ABOVE:
        return None
    step = (target - printed) / slope
    if max_step is not None and abs(step) > max_step:
        # a step of more than a voxel is no correction: the prism's slope does not hold that far
        # (walls broken into fragments gave 0.84 mm at 0.33 mm voxels, and a solid block)
        info["correction"] = f"none: the step, {step:+.3g} mm, is more than a {max_step:.3g} mm voxel"
        return None
    return step
