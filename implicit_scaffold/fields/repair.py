"""Repair for a printer: thin struts thickened and narrow throats opened by local offsets of the field.

A print certificate (:mod:`~implicit_scaffold.measure.printability`) finds struts thinner than the printer builds and
void that its resin or powder cannot drain from. Both are fixed where they are, on the
field, not by a new lattice: the scaffold's signed distance ``s`` (negative in the solid) is
offset by a local field ``delta`` (mm), ``s - delta``, positive around thin struts (the
solid grows by the strut's shortfall, half on each side) and negative around undrained void
(the solid recedes so that a drain-sized sphere passes), never thinning a strut below the
minimum. The porosity target is then met again by one global offset ``t`` (a quantile of
``s - delta`` over the patient, as :func:`~implicit_scaffold.fields.field.solve_level` finds it), and the whole is
measured again; a few rounds settle it. What cannot be met (a minimum strut too thick for
the porosity at this pore size, throats that cannot open without breaking struts) is named.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: rounds of measure, offset and level
REPAIR_ROUNDS = 3
#: offsets are spread in steps of this many voxels (one distance transform per step)
STEP_VOXELS = 0.5
#: at most this many steps of each kind per round
MAX_STEPS = 8
#: the porosity holds when within this much of the target (a fraction)
POROSITY_TOLERANCE = 1e-3
#: a share of the solid in thin struts, or of the void in undrained pores, this small is met
LEFT_OVER = 1e-3
#: a solid piece smaller than this share of the solid is a speck, not a body (:func:`_bodies`)
SPECK = 1e-3
#: a round's offsets are tried at these scales, the first that does no harm kept
STEP_SCALES = (1.0, 0.5)


def measure(solid: np.ndarray, h: float, profile, region: np.ndarray) -> dict:
    """What a repair reads: each solid voxel's thickness and each void voxel's reach.

    Returns
    -------
    dict
        ``thickness`` (mm, float32, 0 in the void; boundary to boundary, as the certificate
        reads it), ``thin`` (voxels of struts below the profile's minimum: below it, and not
        within the minimum's radius of a ball of the minimum's diameter that fits in the solid),
        ``undrained`` (the void that a drain-sized sphere does not reach from outside, in the
        pieces of it where such a sphere fits: not the crevices along the drained void's walls;
        none when the profile drains nothing), ``throat`` (the middle of the channels narrower than the drain on an
        undrained pore's widest way out), ``d2`` and ``r2`` (the squared void distance and reach
        radius in voxels,
        :func:`~implicit_scaffold.measure.printability.throat_radius`), and the figures the certificate reports
        (``below_min_strut_share``, ``thinnest_p1_mm``, ``void_reached_by_drain_share``).
    """
    from ..measure.morphometry import local_thickness
    from ..measure.printability import reached_by, throat_radius

    thickness = local_thickness(solid, h)
    thickness[solid] += np.float32(h)
    below = solid & (thickness < profile.min_strut_mm)
    # a strut is thin where no ball of the minimum's diameter fits near it (within the distance from a
    # cube's corner to such a ball inside it, sqrt(3) m / 2); a sharp edge or corner of a thick
    # part (where the patient cuts the lattice) reads thin too, but lies next to such a ball
    core = _far(solid, h) >= profile.min_strut_mm / 2
    thin = below & ~(_far(~core, h) <= 0.87 * profile.min_strut_mm + h) if core.any() else below
    void_in = region & ~solid
    d2, r2 = throat_radius(solid, h)
    if profile.drain_mm > 0:
        from scipy import ndimage

        from ..run.pieces import label_pieces

        unreached = void_in & ~reached_by(r2, profile.drain_mm, h)
        rho2 = (0.5 * (float(profile.drain_mm) / h - 1.0)) ** 2  # the drain's radius, voxels², as reached_by
        # an undrained pore holds a drain-sized ball that cannot get out; the crevices along the
        # drained void's walls, where no such ball fits, drain with it
        fits = bool(void_in.any() and d2[void_in].max() >= rho2)
        labels, count = label_pieces(unreached)
        widest = np.asarray(ndimage.maximum(d2, labels, np.arange(1, count + 1))) if count else np.zeros(0)
        undrained = np.concatenate([[False], widest >= rho2])[labels]
        del labels
        # the throats: the middles of the channels narrower than the drain (a ridge of the void's
        # distance) that lead out of an undrained pore into the drained void; not the ridges in a
        # pore's own narrow corners, which lead nowhere
        middles = undrained & (r2 > 0) & (d2 < rho2) & (d2 >= r2) & _ridge(d2)
        labels, count = ndimage.label(middles, np.ones((3, 3, 3), bool))
        near = _far(~(void_in & ~unreached), h) <= 2 * h
        leads_out = np.zeros(count + 1, bool)
        leads_out[np.unique(labels[near & middles])] = True
        leads_out[0] = False
        throat = leads_out[labels]
        del labels
        n_unreached = int(np.count_nonzero(unreached))
    else:
        undrained = throat = np.zeros(solid.shape, bool)
        n_unreached, fits = 0, True
    n_solid, n_void = int(np.count_nonzero(solid)), int(np.count_nonzero(void_in))
    return {"thickness": thickness, "thin": thin, "undrained": undrained, "throat": throat, "d2": d2, "r2": r2,
            "below_min_strut_share": float(np.count_nonzero(below) / n_solid) if n_solid else 0.0,
            "thin_share": float(np.count_nonzero(thin) / n_solid) if n_solid else 0.0,
            "drain_fits": fits,
            "undrained_share": float(np.count_nonzero(undrained) / n_void) if n_void else 0.0,
            "thinnest_p1_mm": float(np.percentile(thickness[solid], 1)) if n_solid else 0.0,
            "void_reached_by_drain_share": (float(1.0 - n_unreached / n_void) if n_void else 1.0)
            if profile.drain_mm > 0 else None}


def _ridge(d2: np.ndarray) -> np.ndarray:
    """Voxels where the distance map peaks across at least one axis (no lower than both
    neighbours along it, higher than one): the middle of a channel or a wall, not its side."""
    out = np.zeros(d2.shape, bool)
    for axis in range(3):
        a = np.moveaxis(d2, axis, 0)
        o = np.moveaxis(out, axis, 0)
        mid, lo, hi = a[1:-1], a[:-2], a[2:]
        o[1:-1] |= (mid >= lo) & (mid >= hi) & ((mid > lo) | (mid > hi))
    return out


def _far(source_not: np.ndarray, h: float) -> np.ndarray:
    """Distance (mm, float32) from each voxel to the nearest voxel where `source_not` is False."""
    from ..measure.morphometry import _squared_edt

    return np.sqrt(_squared_edt(source_not)).astype(np.float32) * np.float32(h)


def _spread(amount: np.ndarray, where: np.ndarray, h: float, full: float, fade: float) -> np.ndarray:
    """A field that carries `amount` (mm, >= 0) of the voxels `where` to their surroundings.

    Each voxel within `full` mm of a source of at least ``a`` takes ``a`` (the largest such),
    fading linearly to 0 over the next `fade` mm, so that the offset makes no step on a
    neighbouring surface. Amounts are rounded up to steps of :data:`STEP_VOXELS` voxels.
    """
    out = np.zeros(where.shape, np.float32)
    if not where.any():
        return out
    step = STEP_VOXELS * h
    top = float(amount[where].max())
    levels = step * np.arange(1, int(np.ceil(top / step)) + 1)
    if len(levels) > MAX_STEPS:
        levels = np.linspace(levels[0], levels[-1], MAX_STEPS)
    rounded = np.zeros(where.shape, np.float32)
    # each source's amount rounded up to the next level it reaches
    rounded[where] = levels[np.minimum(np.searchsorted(levels, amount[where] - 1e-9), len(levels) - 1)]
    for level in levels:
        source = where & (rounded >= level - 1e-9)
        if not source.any():
            continue
        d = _far(~source, h)
        taper = np.clip((full + fade - d) / fade, 0.0, 1.0) if fade > 0 else (d <= full).astype(np.float32)
        np.maximum(out, np.float32(level) * taper.astype(np.float32), out=out)
    return out


def offsets(found: dict, solid: np.ndarray, h: float, profile, *, thin=None, undrained=None
            ) -> tuple[np.ndarray, np.ndarray]:
    """The local offset ``delta`` (mm, float32) for one round, from :func:`measure`'s maps, and
    where it acts (``weight``: 1 far from any repair, 0 where it acts, between as it fades).

    Thin struts grow by half their shortfall (``(min - t) / 2``, plus half a voxel so that
    the voxels read the minimum) within the minimum strut's half width of them; undrained
    void opens at its throats (:func:`measure`'s ``throat``) by what their width lacks of the
    drain's, within the drain's radius of them, but no solid voxel recedes by more
    than what keeps its strut at the minimum (``(t - min) / 2``). `thin` and `undrained`,
    when given, are the voxels to repair (by default :func:`measure`'s ``thin`` and ``throat``).
    """
    m = float(profile.min_strut_mm)
    thickness = found["thickness"]
    thin = found["thin"] if thin is None else thin
    undrained = found["throat"] if undrained is None else undrained
    grow = np.where(thin, (m - thickness) / 2 + h / 2, 0).astype(np.float32)
    delta = _spread(grow, thin, h, full=m / 2 + h, fade=h)
    acts = _spread(thin.astype(np.float32), thin, h, full=m / 2 + h, fade=h)
    if profile.drain_mm > 0 and undrained.any():
        rho = 0.5 * (float(profile.drain_mm) / h - 1.0)  # voxels, as reached_by reads the drain
        short = np.where(undrained, (rho - np.sqrt(found["d2"].astype(np.float32))) * h + h / 2, 0).astype(np.float32)
        np.maximum(short, 0, out=short)
        full = float(profile.drain_mm) / 2 + h
        opening = _spread(short, undrained, h, full=full, fade=h)
        # a wall recedes from both sides: at most half of what it has above the minimum, each side;
        # its thickness read within the minimum's radius, since near a sharp edge (where a hole
        # meets a face) the maximal balls shrink with the distance to the edge
        from scipy import ndimage

        wall = ndimage.maximum_filter(thickness, size=2 * int(np.ceil(m / 2 / h)) + 1)
        spare = np.where(solid & ~found["thin"], np.maximum(wall - m, 0) / 2, 0).astype(np.float32)
        spare[~solid] = np.inf
        del wall
        np.minimum(opening, spare, out=opening)
        opening[thin] = 0
        delta -= opening
        np.maximum(acts, _spread(undrained.astype(np.float32), undrained, h, full=full, fade=h), out=acts)
    return delta, (1.0 - acts).astype(np.float32)


@dataclass(frozen=True)
class _State:
    """A repair's state after a round: the field, its solid and measures, the summed local
    offsets, the global offset's weights and the global offset (mm)."""

    field: np.ndarray
    solid: np.ndarray
    found: dict
    total: np.ndarray
    weight: np.ndarray
    shift: float


def _score(found: dict) -> int:
    """What a round must lower: the voxels of thin struts and of undrained pores."""
    return int(np.count_nonzero(found["thin"])) + int(np.count_nonzero(found["undrained"]))


def _bodies(solid: np.ndarray) -> int:
    """The solid's 6-connected pieces of more than :data:`SPECK` of its voxels: a strut cut through
    leaves a piece that large, while a voxel or two left by the global offset on a flat wall
    (which the pipeline's clean-up removes) is not counted."""
    from ..run.pieces import label_pieces

    labels, count = label_pieces(solid)
    if count <= 1:
        return count
    sizes = np.bincount(labels.ravel())[1:]
    return int(np.count_nonzero(sizes > SPECK * sizes.sum()))


def _holds(found: dict, profile, each: bool = False):
    """Whether (but for :data:`LEFT_OVER` of the solid or void) no strut is thinner than the minimum
    and no pore is undrained (:func:`measure`'s ``thin_share`` and ``undrained_share``: the sharp
    edges and crevices the certificate's shares count are not struts or pores, and no offset
    changes them); and a drain-sized ball fits somewhere in the void."""
    strut = found["thin_share"] <= LEFT_OVER
    drain = found["drain_fits"] and found["undrained_share"] <= LEFT_OVER
    return {"min_strut": strut, "drain": drain} if each else strut and drain


def level_for(moved: np.ndarray, weight: np.ndarray, region: np.ndarray, solid: int) -> float:
    """The global offset ``t`` for which ``moved - t * weight < 0`` holds `solid` voxels of `region`.

    Where the weight is 0 the sign is ``moved``'s; elsewhere a voxel is solid when
    ``moved / weight < t``, so ``t`` is a quantile of that ratio (midway between two
    consecutive values, :func:`~implicit_scaffold.fields.field.level_between`), exact in the voxel count.
    """
    from .field import level_between

    free = region & (weight > 0)
    fixed = int(np.count_nonzero(region & ~free & (moved < 0)))
    values = moved[free] / weight[free]
    k = int(solid) - fixed
    if values.size == 0 or k <= 0:
        return float(values.min()) - 1e-6 if values.size else 0.0
    if k >= values.size:
        return float(values.max()) + 1e-6
    part = np.partition(values, (k - 1, k))
    return float(level_between(part[k - 1], part[k]))


def repair(field: np.ndarray, patient: np.ndarray, h: float, profile, *, porosity: float | None,
           rounds: int = REPAIR_ROUNDS, progress=None) -> tuple[np.ndarray, dict]:
    """Thicken the thin struts and open the undrained void of a scaffold's field, keeping its porosity.

    Each round measures the solid (:func:`measure`), adds the local offsets (:func:`offsets`),
    and meets the porosity again by a global offset away from the repairs (:func:`level_for`),
    so that a thickened strut is not thinned back by it. A round is kept only if it does no
    harm (the porosity kept, the solid in no more pieces, fewer voxels in thin struts and
    undrained pores), else tried at half its offsets, else the repair stops there: a scaffold
    whose struts are mostly too thin for the printer at its porosity is left as it is, and
    the report says why.

    Parameters
    ----------
    field : (nx, ny, nz) float32 ndarray, mm
        The scaffold's signed distance, negative in the solid (not modified).
    patient : (nx, ny, nz) float ndarray, mm
        The patient's signed distance, negative inside: the region whose porosity is kept,
        and the bound of the solid (``max(s, patient)``).
    h : float, mm
    profile : PrinterProfile
    porosity : float or None
        The void fraction of the patient to keep (None: the field's own, as built).
    rounds : int

    Returns
    -------
    field : (nx, ny, nz) float32 ndarray, mm
        The repaired field, ``max(s - delta - t * weight, patient)``.
    info : dict
        ``rounds``, ``porosity`` ({target, before, after}), ``volume_moved_mm3`` (voxels that
        changed phase: ``grown_mm3`` made solid, ``opened_mm3`` made void),
        ``below_min_strut_share`` and ``void_reached_by_drain_share`` ({before, after}),
        ``level_shift_mm`` (``t``), ``holds`` ({min_strut, drain, porosity}) and ``why``
        (plain words for what does not hold).
    """
    patient = np.asarray(patient, np.float32)
    region = patient < 0
    n_region = int(np.count_nonzero(region))
    original = np.asarray(field, np.float32)
    solid0 = original < 0
    before_porosity = 1.0 - np.count_nonzero(solid0 & region) / n_region
    target = before_porosity if porosity is None else float(porosity)
    want = int(round(n_region * (1.0 - target)))
    # a global offset wider than the repairs themselves would remake the scaffold, not repair it
    cap = max(float(profile.min_strut_mm), float(profile.drain_mm))
    state = _State(original, original < 0, measure(original < 0, h, profile, region),
                   np.zeros(original.shape, np.float32), np.ones(original.shape, np.float32), 0.0)
    before, solid0 = state.found, state.solid
    bodies0 = _bodies(solid0)
    thin, undrained = before["thin"], before["throat"]
    done, stopped = 0, None
    for step in range(1, rounds + 1):
        if _holds(state.found, profile) or not (thin.any() or undrained.any()):
            break
        delta, acts = offsets(state.found, state.solid, h, profile, thin=thin, undrained=undrained)
        accepted = None
        for scale in STEP_SCALES:
            total = state.total + np.float32(scale) * delta
            weight = np.minimum(state.weight, acts)  # a place repaired once stays out of the global offset
            moved = original - total
            shift = float(np.clip(level_for(moved, weight, region, want), -cap, cap))
            current = np.maximum(moved - np.float32(shift) * weight, patient)
            del moved
            solid = current < 0
            trial = _State(current, solid, measure(solid, h, profile, region), total, weight, shift)
            # a round is kept only if it does no harm: the porosity kept, the solid in no more
            # pieces, and fewer voxels of thin struts and undrained pores than before it
            porosity = 1.0 - np.count_nonzero(solid & region) / n_region
            if (abs(porosity - target) <= POROSITY_TOLERANCE and _bodies(solid) <= bodies0
                    and _score(trial.found) < _score(state.found)):
                accepted = trial
                break
            del trial, current, solid, total, weight
        if accepted is None:
            stopped = (f"round {step} stopped: its offsets, even scaled by {STEP_SCALES[-1]:g}, broke the porosity, "
                       "the solid's connection or made more thin struts or undrained pores than they fixed")
            break
        last, state = state, accepted
        # what a round's offset did not improve (a sharp edge where the patient cuts the lattice
        # reads thin however much its strut grows) is not offset again
        thin = state.found["thin"] & ~(last.found["thin"] & (state.found["thickness"] < last.found["thickness"] + h / 2))
        undrained = state.found["throat"] & ~(last.found["throat"] & (state.found["r2"] <= last.found["r2"]))
        done = step
        if progress is not None:
            progress(step, rounds)
    current, solid, found, shift = state.field, state.solid, state.found, state.shift
    grown = int(np.count_nonzero(solid & ~solid0))
    opened = int(np.count_nonzero(solid0 & ~solid))
    after_porosity = 1.0 - np.count_nonzero(solid & region) / n_region
    holds = {**_holds(found, profile, each=True),
             # ties in the field (equal values the level cannot split) may leave a few voxels over
             "porosity": abs(after_porosity - target) <= POROSITY_TOLERANCE}
    why = []
    if not holds["min_strut"]:
        why.append(f"{found['thin_share']:.1%} of the solid is in struts still thinner than "
                   f"{profile.min_strut_mm:g} mm after {done} rounds: at porosity {target:.3g} the struts this pore "
                   "size leaves are too thin to thicken them all with what the rest can give; lower --porosity or "
                   "raise --pore-size")
    if not found["drain_fits"]:
        why.append(f"no pore holds a {profile.drain_mm:g} mm ball: the pores are smaller than the printer's drain, "
                   "which no local offset changes; raise --pore-size")
    elif not holds["drain"]:
        why.append(f"{found['undrained_share']:.1%} of the void is in pores a {profile.drain_mm:g} mm drain still "
                   f"cannot reach after {done} rounds: their windows cannot open that wide without thinning struts "
                   "below the minimum; raise --pore-size or --sf")
    if not holds["porosity"]:
        why.append(f"the porosity is {after_porosity:.4f} against {target:.4f}: the repairs leave too little "
                   "material elsewhere to give back")
    if stopped and why:
        why.append(stopped)
    info = {"printer": profile.name, "rounds": done,
            "porosity": {"target": float(target), "before": float(before_porosity), "after": float(after_porosity)},
            "level_shift_mm": float(shift),
            "volume_moved_mm3": float((grown + opened) * h ** 3),
            "grown_mm3": float(grown * h ** 3), "opened_mm3": float(opened * h ** 3),
            "below_min_strut_share": {"before": before["below_min_strut_share"],
                                      "after": found["below_min_strut_share"]},
            "thinnest_p1_mm": {"before": before["thinnest_p1_mm"], "after": found["thinnest_p1_mm"]},
            "thin_strut_share": {"before": before["thin_share"], "after": found["thin_share"]},
            "undrained_pore_share": {"before": before["undrained_share"], "after": found["undrained_share"]},
            "void_reached_by_drain_share": {"before": before["void_reached_by_drain_share"],
                                            "after": found["void_reached_by_drain_share"]},
            "holds": holds, "why": why}
    return np.ascontiguousarray(current, np.float32), info
