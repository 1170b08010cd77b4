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

A field in slabs on disk is repaired slab by slab (:func:`repair_by_slabs`): the same rounds, each
step with the halo it reads and exact reductions across slabs, and the same field, bit for bit.
"""
from __future__ import annotations

import math
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
    if not where.any():
        return np.zeros(where.shape, np.float32)
    return _spread_levels(amount, where, h, full, fade, _levels(float(amount[where].max()), h))


def _levels(top: float, h: float) -> np.ndarray:
    """The amounts (mm) :func:`_spread` rounds up to, for sources of at most `top` mm."""
    step = STEP_VOXELS * h
    levels = step * np.arange(1, int(np.ceil(top / step)) + 1)
    if len(levels) > MAX_STEPS:
        levels = np.linspace(levels[0], levels[-1], MAX_STEPS)
    return levels


def _spread_levels(amount: np.ndarray, where: np.ndarray, h: float, full: float, fade: float,
                   levels: np.ndarray) -> np.ndarray:
    """:func:`_spread` with the `levels` of the whole grid's sources (:func:`_levels`): on a slab
    with a halo of ``full + fade`` mm, its owned planes are the whole grid's."""
    out = np.zeros(where.shape, np.float32)
    if not where.any() or not len(levels):
        return out
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
    free = region & (weight > 0)
    fixed = int(np.count_nonzero(region & ~free & (moved < 0)))
    values = moved[free] / weight[free]
    k = int(solid) - fixed

    def order(*ranks):
        part = np.partition(values, ranks)
        return [part[r] for r in ranks]

    return _level_at(k, values.size, values.min() if values.size else None,
                     values.max() if values.size else None, order)


def _level_at(k: int, n: int, low, high, order) -> float:
    """:func:`level_for`'s offset from the `k` voxels to make solid among `n` free ones, their
    ratios' least and largest (float32) and ``order(*ranks)``, the ratios at 0-based ranks."""
    from .field import level_between

    if n == 0 or k <= 0:
        return float(low) - 1e-6 if n else 0.0
    if k >= n:
        return float(high) + 1e-6
    below, above = order(k - 1, k)
    return float(level_between(np.float32(below), np.float32(above)))


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
            stopped = _stopped(step)
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
    info = _summary(profile, h, done, target, before_porosity, after_porosity, shift, grown, opened, before, found,
                    stopped)
    return np.ascontiguousarray(current, np.float32), info


def _stopped(step: int) -> str:
    return (f"round {step} stopped: its offsets, even scaled by {STEP_SCALES[-1]:g}, broke the porosity, "
            "the solid's connection or made more thin struts or undrained pores than they fixed")


def _summary(profile, h: float, done: int, target: float, before_porosity: float, after_porosity: float,
             shift: float, grown: int, opened: int, before: dict, found: dict, stopped: str | None) -> dict:
    """:func:`repair`'s info from its counts and the figures of :func:`measure` before and after."""
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
    return {"printer": profile.name, "rounds": done,
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


# ----------------------------------------------------------------------------- in slabs

#: bytes per voxel of a slab (its halo included) while :func:`repair_by_slabs` works on it: the
#: window's solid, thickness, flags and squared distances, and a spread's levels, distances and tapers
SLAB_REPAIR_BYTES_PER_VOXEL = 80

# what :func:`measure` marks per voxel, kept as bits of one int32 plane store; the last two are
# the voxels a round repairs (:func:`offsets`' `thin` and `undrained`)
_BELOW, _THIN, _UNREACHED, _UNDRAINED, _MIDDLE, _THROAT, _FIX_THIN, _FIX_OPEN = (1 << i for i in range(8))


class _Stores:
    """Float32 and int32 planes over the grid on disk, closed (and removed) together."""

    def __init__(self, grid, folder):
        self.grid, self.folder, self._open = grid, folder, []

    def floats(self):
        from ..run.tiles import FieldFile

        self._open.append(FieldFile(self.grid, self.folder))
        return self._open[-1]

    def ints(self):
        from ..measure.printability import _IntPlanes

        return self.keep(_IntPlanes(self.grid, self.folder))

    def keep(self, store):
        """Close `store` (one made elsewhere) with the others."""
        self._open.append(store)
        return store

    def close(self) -> None:
        for store in self._open:
            store.close()
        self._open = []


@dataclass
class _SlabState:
    """A round's state in slabs (as :class:`_State`): the field, the summed local offsets and the
    global offset's weights (None: zeros and ones) on disk, :func:`measure`'s maps (thickness,
    flags, ``d2``, ``r2``) on disk and its figures, and the global offset (mm)."""

    field: object
    total: object
    weight: object
    maps: dict
    found: dict
    shift: float
    stores: _Stores | None = None


def _windows(nx: int, plane: int, max_voxels: int, halo: int):
    """``(x0, x1, lo, hi, own)``: the slabs' owned planes, their planes read with `halo` on either
    side, and the owned planes' slice of those (:func:`~implicit_scaffold.measure.printability._spans`)."""
    from ..measure.printability import _spans

    for x0, x1 in _spans(nx, plane, max_voxels, halo):
        lo, hi = max(0, x0 - halo), min(nx, x1 + halo)
        yield x0, x1, lo, hi, slice(x0 - lo, x1 - lo)


def _measure_by_slabs(solid_of, region_of, grid, h: float, profile, max_voxels: int, stores: _Stores,
                      halo: int) -> tuple[dict, dict, int]:
    """:func:`measure` of the solid ``solid_of(lo, hi)`` (planes ``[lo, hi)``) in the region
    ``region_of(lo, hi)``, slab by slab: its maps on disk (``thickness``, float32; ``flags``, the
    bits ``_BELOW`` to ``_THROAT``; ``d2`` and ``r2``, int32, when the profile drains), identical
    on every voxel to the whole grid's where :func:`repair` reads them, and its figures.

    How far each step reads beyond a slab (its halo):

    - thickness: a sphere that paints an owned voxel has its centre within its radius ``r``, whose
      distance is exact with a halo of ``2 r``; the halo is widened until the thickest owned
      voxel (which bounds the largest inscribed sphere) is within it, as
      :func:`~implicit_scaffold.measure.morphometry.morphometry_by_slabs` does;
    - thin: the core (solid at least ``m / 2`` from the void) is read within ``0.87 m + h`` of a
      voxel, and a core voxel's distance within ``m / 2`` of it: a distance compared with a
      bound is exact on a window that holds every voxel within the bound, so ``ceil(m / 2h) + 1``
      plus ``ceil((0.87 m + h) / h) + 1`` planes;
    - drain reach: the void's squared distance, capped above the drain's (the certificate's
      :func:`~implicit_scaffold.measure.printability._distances_by_slabs`: every comparison
      :func:`measure` makes keeps its answer under the cap), and the max-min flood iterated
      over the slabs to the whole grid's fixpoint (``_flood_by_slabs``); the sphere's reach with
      a halo of its radius (``_pores_by_slabs``). Undrained pores are pieces of the unreached
      void joined across slabs by union-find (:class:`~implicit_scaffold.run.tiles.SlabComponents`), a
      piece undrained when some voxel of it holds a drain-sized ball (a count per piece);
    - throats: the ridge of ``d2`` reads one plane, the drained void within ``2 h`` three; the
      channels' middles are joined across slabs 26-connected, as ``ndimage.label`` with a 3x3x3
      structure joins them, and lead out when some voxel of theirs is near the drained void.

    Returns the maps, the figures and the thickness's halo (a start for the next measure).
    """
    from ..measure.morphometry import ThicknessTally, local_thickness
    from ..measure.printability import _distances_by_slabs, _flood_by_slabs, _pores_by_slabs
    from ..run.pieces import label_pieces
    from ..run.tiles import SlabComponents, StreamQuantile, percentile_1

    nx = int(grid.shape[0])
    plane = int(grid.shape[1]) * int(grid.shape[2])
    m = profile.min_strut_mm
    maps = {"thickness": stores.floats(), "flags": stores.ints(), "d2": None, "r2": None}
    flags, thickness = maps["flags"], maps["thickness"]
    while True:
        tally = ThicknessTally(h)
        windows = list(_windows(nx, plane, max_voxels, halo))
        for x0, x1, lo, hi, own in windows:
            solid_w = solid_of(lo, hi)
            thick = local_thickness(solid_w, h)[own]
            solid = solid_w[own]
            del solid_w
            tally.add(thick, solid)
            thick[solid] += np.float32(h)
            thickness.write(x0, thick)
        if tally.max_voxels <= halo or len(windows) == 1:
            break
        halo = max(2 * halo, int(math.ceil(tally.max_voxels)) + 2)
    core_halo = math.ceil(m / 2 / h) + 1
    width = core_halo + math.ceil((0.87 * m + h) / h) + 1
    n = {"solid": 0, "below": 0, "thin": 0, "void": 0, "unreached": 0, "undrained": 0}
    p1 = StreamQuantile()
    for x0, x1, lo, hi, own in _windows(nx, plane, max_voxels, width):
        solid_w = solid_of(lo, hi)
        core = _far(solid_w, h) >= m / 2
        # no core within the window: none within the bound either, as on the whole grid without any
        near = _far(~core, h)[own] <= 0.87 * m + h
        del core
        solid = solid_w[own]
        del solid_w
        thick = thickness.read(x0, x1)
        below = solid & (thick < m)
        thin = below & ~near
        flags.write(x0, np.where(below, _BELOW, 0) | np.where(thin, _THIN, 0))
        p1.count(thick, solid)
        n["solid"] += int(np.count_nonzero(solid))
        n["below"] += int(np.count_nonzero(below))
        n["thin"] += int(np.count_nonzero(thin))
        n["void"] += int(np.count_nonzero(region_of(x0, x1) & ~solid))
    fits = True
    if profile.drain_mm > 0:
        rho2 = (0.5 * (float(profile.drain_mm) / h - 1.0)) ** 2  # as measure reads the drain
        maps["d2"] = stores.keep(_distances_by_slabs(solid_of, region_of, grid, max_voxels, halo, stores.folder,
                                                     math.ceil(rho2) + 1)[0])
        maps["r2"] = stores.keep(_flood_by_slabs(maps["d2"], grid, max_voxels, stores.folder)[0])
        d2s, r2s = maps["d2"], maps["r2"]
        unreached_parts, seen, wide = SlabComponents(), [], [False]

        def visit(x0, void, r2, reached):
            x1 = x0 + len(void)
            unreached = void & ~reached[0]
            d2 = d2s.read(x0, x1)
            wide[0] |= bool(np.any(d2[void] >= rho2))
            unreached_parts.add(unreached, tally=unreached & (d2 >= rho2))
            flags.write(x0, flags.read(x0, x1) | np.where(unreached, _UNREACHED, 0))
            n["unreached"] += int(np.count_nonzero(unreached))
            seen.append((x0, x1))

        _pores_by_slabs(d2s, r2s, lambda x0, x1: region_of(x0, x1) & ~solid_of(x0, x1), grid, h, max_voxels,
                        [profile.drain_mm], visit)
        fits = wide[0]
        unreached_parts.finish()
        holds_ball = unreached_parts.tally_by_root() > 0
        for index, (x0, x1) in enumerate(seen):
            f = flags.read(x0, x1)
            roots = unreached_parts.roots_of(index, label_pieces((f & _UNREACHED) > 0)[0])
            undrained = (roots >= 0) & holds_ball[np.maximum(roots, 0)] if holds_ball.size else np.zeros(roots.shape, bool)
            n["undrained"] += int(np.count_nonzero(undrained))
            flags.write(x0, f | np.where(undrained, _UNDRAINED, 0))
        middle_parts, seen = SlabComponents(connectivity=26), []
        for x0, x1, lo, hi, own in _windows(nx, plane, max_voxels, 3):
            f = flags.read(lo, hi)
            drained = region_of(lo, hi) & ~solid_of(lo, hi) & ((f & _UNREACHED) == 0)
            near = (_far(~drained, h) <= 2 * h)[own]
            del drained
            d2w = d2s.read(lo, hi)
            d2, r2 = d2w[own], r2s.read(x0, x1)
            middles = ((f[own] & _UNDRAINED) > 0) & (r2 > 0) & (d2 < rho2) & (d2 >= r2) & _ridge(d2w)[own]
            del d2w
            middle_parts.add(middles, tally=near & middles)
            flags.write(x0, f[own] | np.where(middles, _MIDDLE, 0))
            seen.append((x0, x1))
        middle_parts.finish()
        leads_out = middle_parts.tally_by_root() > 0
        for index, (x0, x1) in enumerate(seen):
            f = flags.read(x0, x1)
            roots = middle_parts.roots_of(index, label_pieces((f & _MIDDLE) > 0, connectivity=26)[0])
            throat = (roots >= 0) & leads_out[np.maximum(roots, 0)] if leads_out.size else np.zeros(roots.shape, bool)
            flags.write(x0, f | np.where(throat, _THROAT, 0))
    thinnest = 0.0
    if n["solid"]:
        def at(*ranks):
            p1.select(*ranks)
            for x0, x1, _, _, _ in _windows(nx, plane, max_voxels, 0):
                p1.refine(thickness.read(x0, x1), solid_of(x0, x1))
            return p1.values()

        thinnest = percentile_1(n["solid"], at)
    n_solid, n_void = n["solid"], n["void"]
    found = {"below_min_strut_share": float(n["below"] / n_solid) if n_solid else 0.0,
             "thin_share": float(n["thin"] / n_solid) if n_solid else 0.0,
             "drain_fits": fits,
             "undrained_share": float(n["undrained"] / n_void) if n_void else 0.0,
             "thinnest_p1_mm": thinnest,
             "void_reached_by_drain_share": (float(1.0 - n["unreached"] / n_void) if n_void else 1.0)
             if profile.drain_mm > 0 else None,
             "thin": n["thin"], "undrained": n["undrained"]}
    return maps, found, halo


def _offsets_by_slabs(maps: dict, solid_of, grid, h: float, profile, max_voxels: int, delta, weight) -> None:
    """:func:`offsets` slab by slab, from :func:`_measure_by_slabs`' maps (the voxels to repair
    marked ``_FIX_THIN`` and ``_FIX_OPEN``), into the float32 stores `delta` and `weight`.

    Each spread's levels come from its sources' largest amount over the whole grid (a first pass);
    a slab then reads the halo its sources reach, ``full + fade`` mm (``m / 2 + 2 h`` for a thin
    strut, ``drain / 2 + 2 h`` for a throat), and the walls' maximum filter its radius
    (``ceil(m / 2h)``): a source beyond that adds nothing to an owned voxel.
    """
    from scipy import ndimage

    nx = int(grid.shape[0])
    plane = int(grid.shape[1]) * int(grid.shape[2])
    m = float(profile.min_strut_mm)
    flags, thickness, d2s = maps["flags"], maps["thickness"], maps["d2"]
    rho = 0.5 * (float(profile.drain_mm) / h - 1.0)  # voxels, as reached_by reads the drain

    def grow_of(thin, thick):
        return np.where(thin, (m - thick) / 2 + h / 2, 0).astype(np.float32)

    def short_of(undrained, d2):
        short = np.where(undrained, (rho - np.sqrt(d2.astype(np.float32))) * h + h / 2, 0).astype(np.float32)
        return np.maximum(short, 0, out=short)

    tops = {"grow": None, "short": None}
    for x0, x1, _, _, _ in _windows(nx, plane, max_voxels, 0):
        f = flags.read(x0, x1)
        thin, undrained = (f & _FIX_THIN) > 0, (f & _FIX_OPEN) > 0
        if thin.any():
            top = float(grow_of(thin, thickness.read(x0, x1))[thin].max())
            tops["grow"] = top if tops["grow"] is None else max(tops["grow"], top)
        if profile.drain_mm > 0 and undrained.any():
            top = float(short_of(undrained, d2s.read(x0, x1))[undrained].max())
            tops["short"] = top if tops["short"] is None else max(tops["short"], top)
    empty = np.zeros(0)
    grow_levels = _levels(tops["grow"], h) if tops["grow"] is not None else empty
    ones = _levels(1.0, h)
    opens = tops["short"] is not None
    full_thin, full_open, fade = m / 2 + h, float(profile.drain_mm) / 2 + h, h
    short_levels = _levels(tops["short"], h) if opens else empty
    radius = int(np.ceil(m / 2 / h))
    halo = max(math.ceil((max(full_thin, full_open if opens else 0.0) + fade) / h) + 1, radius)
    for x0, x1, lo, hi, own in _windows(nx, plane, max_voxels, halo):
        f = flags.read(lo, hi)
        thick = thickness.read(lo, hi)
        thin = (f & _FIX_THIN) > 0
        out = _spread_levels(grow_of(thin, thick), thin, h, full_thin, fade, grow_levels)[own]
        acts = _spread_levels(thin.astype(np.float32), thin, h, full_thin, fade, ones)[own]
        if opens:
            undrained = (f & _FIX_OPEN) > 0
            opening = _spread_levels(short_of(undrained, d2s.read(lo, hi)), undrained, h, full_open, fade,
                                     short_levels)[own]
            solid = solid_of(x0, x1)
            wall = ndimage.maximum_filter(thick, size=2 * radius + 1)[own]
            spare = np.where(solid & ((f[own] & _THIN) == 0), np.maximum(wall - m, 0) / 2, 0).astype(np.float32)
            spare[~solid] = np.inf
            del wall
            np.minimum(opening, spare, out=opening)
            opening[thin[own]] = 0
            out -= opening
            np.maximum(acts, _spread_levels(undrained.astype(np.float32), undrained, h, full_open, fade,
                                            ones)[own], out=acts)
        delta.write(x0, out)
        weight.write(x0, (1.0 - acts).astype(np.float32))


def _bodies_of(parts) -> int:
    """:func:`_bodies` from the solid's pieces joined across slabs (:class:`~implicit_scaffold.run.tiles.SlabComponents`)."""
    parts.finish()
    sizes = parts.sizes[parts.sizes > 0]
    if len(sizes) <= 1:
        return len(sizes)
    return int(np.count_nonzero(sizes > SPECK * sizes.sum()))


def repair_by_slabs(source, patient, h: float, profile, *, porosity: float | None, max_voxels: int,
                    rounds: int = REPAIR_ROUNDS, folder=None, progress=None) -> dict:
    """:func:`repair` of the field `source` (a FieldFile or ArraySlabs) in the region
    ``patient < 0``, slab by slab: the same rounds, offsets and level, and the same repaired
    field, bit for bit, written into `source`; returns the same info.

    Every step reads its slab with the halo it needs (:func:`_measure_by_slabs`,
    :func:`_offsets_by_slabs`), and what needs the whole grid is an exact reduction across
    slabs: the level by the streamed quantile of :func:`level_for`'s ratios
    (:class:`~implicit_scaffold.run.tiles.StreamQuantile`, two passes), the solid's bodies and the
    undrained pores by union-find, the counts and the largest amounts by sums and maxima. The
    maps of the current round, the one before and the round being tried are kept on disk
    (up to about 70 bytes a voxel in `folder`, removed at the end); a slab holds about `max_voxels` voxels of each working
    array, its halo included (:data:`SLAB_REPAIR_BYTES_PER_VOXEL` bytes a voxel in all).
    """
    from ..run.tiles import SlabComponents, StreamQuantile

    grid = source.grid
    nx = int(grid.shape[0])
    plane = int(grid.shape[1]) * int(grid.shape[2])
    max_voxels = max(1, int(max_voxels))

    def spans():
        return [(x0, x1) for x0, x1, _, _, _ in _windows(nx, plane, max_voxels, 0)]

    def region_of(lo, hi):
        return patient.read(lo, hi) < 0

    def solid_in(store):
        return lambda lo, hi: store.read(lo, hi) < 0

    n_region = n_solid0 = 0
    parts = SlabComponents()
    for x0, x1 in spans():
        solid, region = source.read(x0, x1) < 0, region_of(x0, x1)
        n_region += int(np.count_nonzero(region))
        n_solid0 += int(np.count_nonzero(solid & region))
        parts.add(solid)
    bodies0 = _bodies_of(parts)
    del parts
    before_porosity = 1.0 - n_solid0 / n_region
    target = before_porosity if porosity is None else float(porosity)
    want = int(round(n_region * (1.0 - target)))
    cap = max(float(profile.min_strut_mm), float(profile.drain_mm))
    stores = _Stores(grid, folder)
    halo = max(1, math.ceil(profile.min_strut_mm / h) + 1)
    live = [stores]  # every store opened, closed (and its files removed) at the end whatever happens
    try:
        maps, found, halo = _measure_by_slabs(solid_in(source), region_of, grid, h, profile, max_voxels, stores,
                                              halo)
        state = _SlabState(source, None, None, maps, found, 0.0, stores)
        before = found
        fix = {"thin": found["thin"], "open": 0}
        for x0, x1 in spans():
            f = maps["flags"].read(x0, x1)
            fix["open"] += int(np.count_nonzero(f & _THROAT))
            maps["flags"].write(x0, f | np.where(f & _THIN, _FIX_THIN, 0) | np.where(f & _THROAT, _FIX_OPEN, 0))
        done, stopped = 0, None
        for step in range(1, rounds + 1):
            if _holds(state.found, profile) or not (fix["thin"] or fix["open"]):
                break
            work = _Stores(grid, folder)
            live.append(work)
            delta, acts = work.floats(), work.floats()
            _offsets_by_slabs(state.maps, solid_in(state.field), grid, h, profile, max_voxels, delta, acts)
            accepted = None
            for scale in STEP_SCALES:
                trial = _Stores(grid, folder)
                live.append(trial)
                field, total, weight = trial.floats(), trial.floats(), trial.floats()
                quantile, fixed, low, high = StreamQuantile(), 0, None, None
                for x0, x1 in spans():
                    d = delta.read(x0, x1)
                    t = (state.total.read(x0, x1) if state.total is not None else np.zeros_like(d)) \
                        + np.float32(scale) * d
                    w = np.minimum(state.weight.read(x0, x1) if state.weight is not None
                                   else np.ones_like(d), acts.read(x0, x1))
                    total.write(x0, t)
                    weight.write(x0, w)
                    moved = source.read(x0, x1) - t
                    region = region_of(x0, x1)
                    free = region & (w > 0)
                    fixed += int(np.count_nonzero(region & ~free & (moved < 0)))
                    values = moved[free] / w[free]
                    quantile.count(values)
                    if values.size:
                        low = values.min() if low is None else min(low, values.min())
                        high = values.max() if high is None else max(high, values.max())

                def order(*ranks):
                    quantile.select(*ranks)
                    for x0, x1 in spans():
                        w = weight.read(x0, x1)
                        free = region_of(x0, x1) & (w > 0)
                        quantile.refine((source.read(x0, x1) - total.read(x0, x1))[free] / w[free])
                    return quantile.values()

                shift = float(np.clip(_level_at(want - fixed, quantile.n, low, high, order), -cap, cap))
                n_solid, parts = 0, SlabComponents()
                for x0, x1 in spans():
                    moved = source.read(x0, x1) - total.read(x0, x1)
                    current = np.maximum(moved - np.float32(shift) * weight.read(x0, x1), patient.read(x0, x1))
                    field.write(x0, current)
                    solid = current < 0
                    n_solid += int(np.count_nonzero(solid & region_of(x0, x1)))
                    parts.add(solid)
                maps, found, halo = _measure_by_slabs(solid_in(field), region_of, grid, h, profile, max_voxels,
                                                      trial, halo)
                now = 1.0 - n_solid / n_region
                if (abs(now - target) <= POROSITY_TOLERANCE and _bodies_of(parts) <= bodies0
                        and found["thin"] + found["undrained"] < state.found["thin"] + state.found["undrained"]):
                    accepted = _SlabState(field, total, weight, maps, found, shift, trial)
                    break
                trial.close()
            work.close()
            if accepted is None:
                stopped = _stopped(step)
                break
            last, state = state, accepted
            # what a round's offset did not improve is not offset again (as repair)
            fix = {"thin": 0, "open": 0}
            for x0, x1 in spans():
                f, was = state.maps["flags"].read(x0, x1), last.maps["flags"].read(x0, x1)
                thin = ((f & _THIN) > 0) & ~(((was & _THIN) > 0) & (state.maps["thickness"].read(x0, x1)
                                                                   < last.maps["thickness"].read(x0, x1) + h / 2))
                opens = np.zeros(thin.shape, bool)
                if state.maps["r2"] is not None:
                    opens = ((f & _THROAT) > 0) & ~(((was & _THROAT) > 0)
                                                    & (state.maps["r2"].read(x0, x1) <= last.maps["r2"].read(x0, x1)))
                fix["thin"] += int(np.count_nonzero(thin))
                fix["open"] += int(np.count_nonzero(opens))
                state.maps["flags"].write(x0, f | np.where(thin, _FIX_THIN, 0) | np.where(opens, _FIX_OPEN, 0))
            last.stores.close()
            done = step
            if progress is not None:
                progress(step, rounds)
        grown = opened = n_solid = 0
        for x0, x1 in spans():
            was = source.read(x0, x1) < 0
            now = state.field.read(x0, x1) < 0 if state.field is not source else was
            grown += int(np.count_nonzero(now & ~was))
            opened += int(np.count_nonzero(was & ~now))
            n_solid += int(np.count_nonzero(now & region_of(x0, x1)))
        after_porosity = 1.0 - n_solid / n_region
        if state.field is not source:
            for x0, x1 in spans():
                source.write(x0, state.field.read(x0, x1))
    finally:
        for opened_stores in live:
            opened_stores.close()
    return _summary(profile, h, done, target, before_porosity, after_porosity, state.shift, grown, opened, before,
                    state.found, stopped)
