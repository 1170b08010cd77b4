"""Tiled evaluation in bounded memory: slabs, an exact streamed quantile, fragments across slabs.

A grid too large for memory is cut into slabs along x. Each slab owns the voxel planes
``[x0, x1)`` and is computed with a halo of planes on either side, as wide as the
blend and marching cubes read; a value depends only on its global index, so a slab
gives the same bits as the whole grid. What needs the whole grid is gathered in
passes that keep only small summaries:

- the surface offset is a quantile of the field over the patient's voxels:
  :class:`StreamQuantile` finds the exact order statistics in two passes over the
  slabs (a radix select on the float32 bit patterns), so the level equals the one
  :func:`~implicit_scaffold.fields.field.solve_level` finds on the whole field, bit for bit;
- the solid pieces not attached to the main body are found by labelling each slab and
  joining labels across slab faces (:class:`SlabComponents`), with the same choice of
  main body as :func:`~implicit_scaffold.fields.field.remove_fragments` on the whole field;
  the same joins find the sealed void pieces (those that touch no face of the grid) that
  :func:`~implicit_scaffold.fields.field.fill_sealed_voids` fills.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import ScaffoldError


@dataclass(frozen=True)
class Slab:
    """Planes ``[x0, x1)`` owned by a slab, and ``[h0, h1)`` computed with its halo."""

    x0: int
    x1: int
    h0: int
    h1: int

    @property
    def owned(self) -> slice:
        """The owned planes, as a slice into the halo'd array."""
        return slice(self.x0 - self.h0, self.x1 - self.h0)


def plan_slabs(shape, *, max_voxels: int, halo: int) -> list[Slab]:
    """Cut a grid into slabs along x whose halo'd size stays within `max_voxels`.

    Parameters
    ----------
    shape : (3,) tuple of int
        The grid's voxels.
    max_voxels : int
        Voxels one slab may hold, halo included.
    halo : int
        Planes computed on either side of the owned ones (clipped at the grid).

    Returns
    -------
    list of Slab

    Raises
    ------
    ScaffoldError
        Not even one plane and its halo fit.
    """
    nx, ny, nz = (int(v) for v in shape)
    plane = ny * nz
    thick = int(max_voxels) // plane - 2 * int(halo)
    if thick < 1:
        need = (1 + 2 * halo) * plane
        raise ScaffoldError(f"one slab of the grid needs {need:,} voxels but the memory allows {int(max_voxels):,}; "
                            "raise --max-memory or use a larger --voxel")
    slabs = []
    for x0 in range(0, nx, thick):
        x1 = min(x0 + thick, nx)
        slabs.append(Slab(x0, x1, max(0, x0 - halo), min(nx, x1 + halo)))
    return slabs


def blend_halo(spacing: float, k: float) -> int:
    """Planes of halo that :func:`~implicit_scaffold.fields.field.blend_field` reads on either side.

    The Gaussian's radius in voxels, as scipy.ndimage truncates it.
    """
    from ..fields.field import BLEND_SIGMAS

    sigma = k / BLEND_SIGMAS / spacing
    if k <= 0 or sigma < 0.25:
        return 0
    return int(BLEND_SIGMAS * sigma + 0.5)


def _values_to_keys(values: np.ndarray) -> np.ndarray:
    """The ordered keys of float32 values (the inverse of :func:`_keys_to_values`)."""
    bits = np.asarray(values, np.float32).view(np.uint32)
    return np.where(bits >> 31, ~bits, bits | np.uint32(0x80000000)).astype(np.uint32)


def _keys_to_values(keys: np.ndarray) -> np.ndarray:
    keys = np.asarray(keys, np.uint32)
    bits = np.where(keys >> 31, keys & np.uint32(0x7FFFFFFF), ~keys).astype(np.uint32)
    return bits.view(np.float32)


_KEY_KERNELS = None


def _key_kernels():
    """Compiled (numba) histograms of the ordered keys of float32 values under a mask."""
    # the helpers are module globals, not closure cells: numba keys its disk cache on a
    # closure's cells, and a dispatcher pickles differently in every process (a fresh
    # compile each run)
    global _KEY_KERNELS, _ordered_key
    if _KEY_KERNELS is not None:
        return _KEY_KERNELS
    import numba as nb

    @nb.njit(cache=True, boundscheck=False)
    def _ordered_key(bits):  # pragma: no cover - compiled
        # float32 bits as uint32 keys in the same order (negative numbers reversed, -0 < +0)
        return ~bits if bits >> np.uint32(31) else bits | np.uint32(0x80000000)

    @nb.njit(cache=True, boundscheck=False)
    def count_high(bits, mask, high):  # pragma: no cover - compiled
        n = 0
        for i in range(bits.size):
            if mask[i]:
                high[_ordered_key(bits[i]) >> np.uint32(16)] += 1
                n += 1
        return n

    @nb.njit(cache=True, boundscheck=False)
    def count_low(bits, mask, tops, lows):  # pragma: no cover - compiled
        for i in range(bits.size):
            if mask[i]:
                k = _ordered_key(bits[i])
                t = k >> np.uint32(16)
                for j in range(tops.size):
                    if tops[j] == t:
                        lows[j, k & np.uint32(0xFFFF)] += 1

    @nb.njit(cache=True, boundscheck=False)
    def count_high_groups(bits, group, high):  # pragma: no cover - compiled
        for i in range(bits.size):
            high[group[i], _ordered_key(bits[i]) >> np.uint32(16)] += 1

    @nb.njit(cache=True, boundscheck=False)
    def count_low_groups(bits, group, tops, lows):  # pragma: no cover - compiled
        for i in range(bits.size):
            g = group[i]
            k = _ordered_key(bits[i])
            t = k >> np.uint32(16)
            for j in range(tops.shape[1]):
                if tops[g, j] == t:
                    lows[g, j, k & np.uint32(0xFFFF)] += 1

    @nb.njit(cache=True, boundscheck=False)
    def bracket(bits, mask, lo_key, hi_key, out):  # pragma: no cover - compiled
        # the count of keys below lo_key, and the keys in [lo_key, hi_key] (as many as fit)
        below = 0
        j = 0
        for i in range(bits.size):
            if mask[i]:
                k = _ordered_key(bits[i])
                if k < lo_key:
                    below += 1
                elif k <= hi_key:
                    if j < out.size:
                        out[j] = k
                    j += 1
        return below, j

    _KEY_KERNELS = count_high, count_low, count_high_groups, count_low_groups, bracket
    return _KEY_KERNELS


#: every how many values :func:`order_pair_sampled` samples to bracket a rank
SAMPLE_STRIDE = 61


def order_pair_sampled(values, where, rank: int, n: int) -> tuple[float, float] | None:
    """The order statistics `rank` and ``rank + 1`` (from 0) of the float32 `values` where `where`
    (``n`` of them), in one pass instead of :class:`StreamQuantile`'s two: a sample of every 61st
    value brackets the rank by keys well beyond its sampling error, and the pass counts the
    values below the bracket and keeps those in it. None when the bracket misses the ranks."""
    bits, mask = _flat_bits(values, where)
    sample = bits[::SAMPLE_STRIDE][mask[::SAMPLE_STRIDE]]
    m = len(sample)
    if m < 100:
        return None
    keys = np.sort(_values_to_keys(sample.view(np.float32)))
    # the sample's rank of the target, +- 6 standard deviations of a binomial count (and 2 more)
    centre = (rank + 0.5) / n * m
    spread = 6 * math.sqrt(max(centre * (1 - centre / m), 1.0)) + 2
    lo_key = keys[max(int(centre - spread), 0)] if centre - spread > 0 else np.uint32(0)
    hi_key = keys[min(int(centre + spread) + 1, m - 1)] if centre + spread < m - 1 else np.uint32(0xFFFFFFFF)
    room = int(4 * (spread + 2) * n / m) + 1024
    out = np.empty(room, np.uint32)
    below, count = _key_kernels()[4](bits, mask, np.uint32(lo_key), np.uint32(hi_key), out)
    r = rank - int(below)
    if count > room or r < 0 or r + 1 >= count:
        return None
    below_value, above_value = _keys_to_values(np.partition(out[:count], (r, r + 1))[r:r + 2])
    return float(below_value), float(above_value)


def _flat_bits(values, where):
    bits = np.ascontiguousarray(values, np.float32).reshape(-1).view(np.uint32)
    mask = (np.ones(bits.size, np.bool_) if where is None
            else np.ascontiguousarray(where, np.bool_).reshape(-1))
    if mask.size != bits.size:
        raise ValueError(f"a mask of {mask.size} values for {bits.size} values")
    return bits, mask


class StreamQuantile:
    """Exact order statistics of float32 values seen slab by slab, in two passes.

    Pass 1 (:meth:`count`) histograms the top 16 bits of each value's ordered key;
    :meth:`select` then fixes the ranks wanted; pass 2 (:meth:`refine`) histograms
    the low 16 bits of the values whose top bits hold those ranks. Memory: two
    65,536-bin histograms per rank, whatever the number of values.
    """

    def __init__(self):
        self.high = np.zeros(1 << 16, np.int64)
        self.n = 0
        self._ranks: tuple[int, ...] = ()
        self._low: dict[int, np.ndarray] = {}

    def count(self, values, where=None) -> None:
        """Pass 1: add values (any shape), or those where the mask `where` (same shape) is true."""
        bits, mask = _flat_bits(values, where)
        self.n += int(_key_kernels()[0](bits, mask, self.high))

    def merge(self, high: np.ndarray, n: int) -> None:
        """Pass 1: add another :class:`StreamQuantile`'s counts (its ``high`` and ``n``), as
        :meth:`count` would have added its values: counts add in any order, so slabs counted
        in worker processes give the same histogram as slabs counted here."""
        self.high += high
        self.n += int(n)

    def select(self, *ranks: int) -> None:
        """Fix the 0-based ranks wanted (after pass 1, before pass 2)."""
        for r in ranks:
            if not 0 <= r < self.n:
                raise ValueError(f"rank {r} outside 0..{self.n - 1}")
        self._ranks = tuple(int(r) for r in ranks)
        self._cum = np.cumsum(self.high)
        self._top = {r: int(np.searchsorted(self._cum, r, side="right")) for r in self._ranks}
        self._low = {top: np.zeros(1 << 16, np.int64) for top in set(self._top.values())}

    def refine(self, values, where=None) -> None:
        """Pass 2: add the same values again (any order, any slabs), with the same mask."""
        bits, mask = _flat_bits(values, where)
        tops = np.array(sorted(self._low), np.uint32)
        lows = np.zeros((len(tops), 1 << 16), np.int64)
        _key_kernels()[1](bits, mask, tops, lows)
        for t, row in zip(tops, lows):
            self._low[int(t)] += row

    def values(self) -> list[float]:
        """The values at the selected ranks, in the order they were given."""
        out = []
        for r in self._ranks:
            t = self._top[r]
            before = int(self._cum[t - 1]) if t > 0 else 0
            low = int(np.searchsorted(np.cumsum(self._low[t]), r - before, side="right"))
            out.append(float(_keys_to_values(np.array([(t << 16) | low], np.uint32))[0]))
        return out


class GroupQuantile:
    """Exact order statistics of float32 values in groups (the bins of a graded offset),
    seen slab by slab in two passes, as :class:`StreamQuantile` finds them for one group.

    Memory: a 65,536-bin histogram per group for pass 1 and one per selected rank for pass 2.

    Parameters
    ----------
    groups : int
    """

    def __init__(self, groups: int):
        self.high = np.zeros((int(groups), 1 << 16), np.int64)

    @property
    def n(self) -> np.ndarray:
        """Values seen per group."""
        return self.high.sum(axis=1)

    @staticmethod
    def _flat(values, group):
        bits = np.ascontiguousarray(values, np.float32).reshape(-1).view(np.uint32)
        group = np.ascontiguousarray(group, np.int32).reshape(-1)
        if group.size != bits.size:
            raise ValueError(f"{group.size} group numbers for {bits.size} values")
        return bits, group

    def count(self, values, group) -> None:
        """Pass 1: add `values` (1-d), each in its group ``group[i]`` (0-based)."""
        bits, group = self._flat(values, group)
        if group.size and not 0 <= int(group.min()) <= int(group.max()) < len(self.high):
            raise ValueError(f"group numbers outside 0..{len(self.high) - 1}")
        _key_kernels()[2](bits, group, self.high)

    def select(self, ranks) -> None:
        """Fix the 0-based ranks wanted, ``(groups, r)``; a group with no values takes ranks 0."""
        ranks = np.asarray(ranks, np.int64).reshape(len(self.high), -1)
        n = self.n
        if np.any((ranks < 0) | ((ranks >= n[:, None]) & (n[:, None] > 0))):
            raise ValueError("a rank outside its group's values")
        self._ranks = ranks
        self._cum = np.cumsum(self.high, axis=1)
        self._top = np.array([np.searchsorted(c, r, side="right") for c, r in zip(self._cum, ranks)],
                             np.uint32).reshape(ranks.shape)
        self._low = np.zeros((*ranks.shape, 1 << 16), np.int64)

    def refine(self, values, group) -> None:
        """Pass 2: the same values and groups again (any order, any slabs)."""
        bits, group = self._flat(values, group)
        _key_kernels()[3](bits, group, self._top, self._low)

    def values(self) -> np.ndarray:
        """``(groups, r)`` float64: the values at the selected ranks (NaN for an empty group)."""
        out = np.full(self._ranks.shape, np.nan)
        for g, (row, tops) in enumerate(zip(self._ranks, self._top)):
            if self._cum[g, -1] == 0:
                continue
            for j, (r, t) in enumerate(zip(row, tops)):
                before = int(self._cum[g, t - 1]) if t > 0 else 0
                low = int(np.searchsorted(np.cumsum(self._low[g, j]), r - before, side="right"))
                out[g, j] = float(_keys_to_values(np.array([(int(t) << 16) | low], np.uint32))[0])
        return out


def percentile_1(n: int, at) -> float:
    """``np.percentile(values, 1)`` of `n` float32 values from their order statistics ``at(r0, r1)``
    (the values at 0-based ranks, from a streamed count or a tally): NumPy's linear
    interpolation, step for step, in float32."""
    q = np.true_divide(1, 100)
    virtual = n * q + (1 + q * (1 - 1 - 1)) - 1
    r0 = int(np.floor(virtual))
    r0, r1 = (n - 1, n - 1) if virtual >= n - 1 else (0, 0) if virtual < 0 else (r0, r0 + 1)
    gamma = float(virtual - np.floor(virtual))
    a, b = (np.float32(v) for v in at(r0, r1))
    diff = b - a
    return float(b - diff * (1 - gamma) if gamma >= 0.5 else a + diff * gamma)


def level_ranks(n_inside: int, porosity: float) -> tuple[int, int] | None:
    """The two ranks whose midpoint (:func:`~implicit_scaffold.fields.field.level_between`) is the level of
    :func:`~implicit_scaffold.fields.field.solve_level`.

    Returns None when the level lies beyond the values (no solid or all solid).
    """
    from ..fields.field import solid_voxels

    solid = solid_voxels(n_inside, porosity)
    if solid <= 0 or solid >= n_inside:
        return None
    return solid - 1, solid


class SlabComponents:
    """6-connected solid pieces of a grid seen slab by slab, joined across slab faces.

    Feed the slabs in order of x with :meth:`add` (the solid of the owned planes);
    :meth:`finish` picks the main body as :func:`~implicit_scaffold.fields.field.remove_fragments`
    does on the whole grid (the largest piece; on a tie the one met first in C
    order); :meth:`fragment_mask` then tells, slab by slab, which voxels to drop.
    The pieces that touch no face of the grid are the sealed ones (:meth:`sealed`,
    :meth:`sealed_mask`), as :func:`~implicit_scaffold.fields.field.fill_sealed_voids` finds them.
    """

    def __init__(self, keep_labels: bool = False, connectivity: int = 6, seeds: bool = False):
        # a run of one slab held in memory keeps its labels for the second pass (4 bytes a
        # voxel) instead of labelling the same mask again
        self._keep_labels = bool(keep_labels)
        # with `seeds`, each label's first voxel (8 bytes a label): pass 2 then repaints the few
        # pieces it changes from them (:func:`~implicit_scaffold.run.pieces.flood_paint`) instead
        # of labelling the slab again, and skips the slabs that hold none
        self._firsts: list[np.ndarray] | None = [] if seeds else None
        if seeds and connectivity != 6:
            raise ValueError("seeds repaint 6-connected pieces only")
        if connectivity not in (6, 26):
            raise ValueError(f"connectivity {connectivity}: 6 (faces) or 26 (faces, edges and corners)")
        # 26: pieces joined across edges and corners too, as scipy.ndimage.label with a 3x3x3 structure
        self.connectivity = int(connectivity)
        self._labels_of: dict[int, np.ndarray] = {}
        self._offsets: list[int] = []
        self._sizes: list[np.ndarray] = []
        self._parent = np.zeros(0, np.int64)
        self._last_plane: np.ndarray | None = None
        self._last_offset = 0
        self._edge: list[np.ndarray] = []   # global labels on a face of the grid
        self._tallies: list[np.ndarray] = []
        self.main: int | None = None

    def _find(self, i: np.ndarray) -> np.ndarray:
        root = np.asarray(i, np.int64).copy()
        while True:
            nxt = self._parent[root]
            if np.array_equal(nxt, root):
                return root
            root = nxt

    def _labels_again(self, index: int, mask: np.ndarray):
        """Slab `index`'s labels of pass 1 (kept, or the same mask labelled again) and their count."""
        labels = self._labels_of.pop(index, None)
        if labels is None:
            return self._label(mask() if callable(mask) else mask)
        nxt = self._offsets[index + 1] if index + 1 < len(self._offsets) else len(self._parent)
        return labels, nxt - self._offsets[index]

    def _label(self, solid: np.ndarray):
        from .pieces import label_pieces

        return label_pieces(solid, connectivity=self.connectivity)

    def add(self, solid: np.ndarray, opens: np.ndarray | None = None, tally: np.ndarray | None = None) -> np.ndarray:
        """Pass 1: the solid (bool, owned planes only) of the next slab along x.

        `opens` marks voxels that make their piece open as a face of the grid does (for
        the void: the space outside the patient); `tally` marks voxels counted per piece
        (:meth:`open_tally`). Returns the slab's labels (1-based, 0 for none).
        """
        from .pieces import label_sizes, label_sizes_first

        labels, count = self._label(solid)
        offset = len(self._parent)
        if self._keep_labels:
            self._labels_of[len(self._offsets)] = labels
        self._offsets.append(offset)
        if self._firsts is None:
            self._sizes.append(label_sizes(labels, count)[1:])
        else:
            sizes, first = label_sizes_first(labels, count)
            self._sizes.append(sizes[1:])
            self._firsts.append(first[1:])
        if tally is not None:
            self._tallies.append(label_sizes(labels, count, where=tally)[1:])
        self._parent = np.concatenate([self._parent, np.arange(offset, offset + count, dtype=np.int64)])
        first = labels[0]
        faces = [labels[:, 0], labels[:, -1], labels[:, :, 0], labels[:, :, -1]]
        if self._last_plane is None:
            faces.append(first)  # the grid's first plane
        if opens is not None:
            faces.append(labels[opens])
        edge = np.unique(np.concatenate([f.ravel() for f in faces]))
        self._edge.append(edge[edge > 0].astype(np.int64) - 1 + offset)
        if self._last_plane is not None:
            a, b = self._face_pairs(self._last_plane, first)
            a, b = a + self._last_offset, b + offset
            # the distinct pairs, as one int64 key each (a 1-D unique, not a row-wise one)
            span = int(b.max(initial=0)) + 1
            keys = np.unique(a * span + b)
            pairs = np.stack([keys // span, keys % span], axis=1)
            for u, v in pairs:
                ru, rv = int(self._find(u)), int(self._find(v))
                if ru != rv:
                    # the root met first in C order stays the root: it names the piece
                    self._parent[max(ru, rv)] = min(ru, rv)
        self._last_plane = labels[-1].copy()
        self._last_offset = offset
        return labels

    def _face_pairs(self, last: np.ndarray, first: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The 0-based labels of the voxels that touch across the face between two slabs: face to
        face, and for 26-connected pieces edge to edge and corner to corner too."""
        ny, nz = last.shape
        shifts = [(0, 0)] if self.connectivity == 6 else [(dj, dk) for dj in (-1, 0, 1) for dk in (-1, 0, 1)]
        a_all, b_all = [], []
        for dj, dk in shifts:
            u = last[max(0, -dj):ny - max(0, dj), max(0, -dk):nz - max(0, dk)]
            v = first[max(0, dj):ny - max(0, -dj), max(0, dk):nz - max(0, -dk)]
            both = (u > 0) & (v > 0)
            a_all.append(u[both].astype(np.int64) - 1)
            b_all.append(v[both].astype(np.int64) - 1)
        return np.concatenate(a_all), np.concatenate(b_all)

    def finish(self) -> int:
        """Choose the main body; return the number of fragments (pieces but the main one)."""
        if not len(self._parent):
            self.main = None
            return 0
        roots = self._find(np.arange(len(self._parent)))
        self._roots = roots
        sizes = np.bincount(roots, weights=np.concatenate(self._sizes), minlength=len(self._parent))
        # labels are numbered in C order within a slab and slabs come in x order, so the
        # smallest root of equal size is the piece that whole-grid labelling numbers first
        self.main = int(np.argmax(sizes))
        self._piece_sizes = sizes
        last = np.unique(self._last_plane)
        edge = np.concatenate(self._edge + [last[last > 0].astype(np.int64) - 1 + self._last_offset])
        self._open = np.zeros(len(self._parent), bool)
        self._open[roots[edge]] = True
        return int(np.count_nonzero(sizes)) - 1

    def open_tally(self) -> tuple[int, int]:
        """After :meth:`finish`: the `tally` voxels in open pieces, and in all pieces."""
        per_root = self.tally_by_root()
        if not per_root.size:
            return 0, 0
        return int(per_root[self._open].sum()), int(per_root.sum())

    def sealed(self, keep_interior: bool = False) -> tuple[int, int]:
        """After :meth:`finish`: the pieces that touch no face of the grid, and their voxels; with
        `keep_interior`, all but the largest of them (as :func:`~implicit_scaffold.fields.field.fill_sealed_voids`)."""
        self._kept = -1
        if not len(self._parent):
            return 0, 0
        pick = (self._piece_sizes > 0) & ~self._open
        if keep_interior and pick.any():
            self._kept = int(np.argmax(np.where(pick, self._piece_sizes, -1)))
            pick[self._kept] = False
        return int(np.count_nonzero(pick)), int(self._piece_sizes[pick].sum())

    def sealed_mask(self, index: int, mask: np.ndarray) -> np.ndarray:
        """Pass 2: voxels of slab `index` (same mask as given to :meth:`add`) in a sealed piece."""
        labels, count = self._labels_again(index, mask)
        return self._sealed_table(index, count)[labels]

    def fill_sealed(self, index: int, mask, field: np.ndarray, value: float) -> int:
        """Pass 2: write `value` into the voxels of slab `index` in a sealed piece, in place;
        `mask` is the void given to :meth:`add` (or a function that makes it: not called when
        the labels were kept). Returns the voxels written."""
        from .pieces import paint_labels

        if self._seeded(index):
            table = self._sealed_table(index, self._count(index))
            if self._floods(index, table, field):
                return self._flood(index, table, field, value, below=False)
        labels, count = self._labels_again(index, mask)
        return paint_labels(labels, self._sealed_table(index, count), field, value)

    def has_sealed(self, index: int) -> bool:
        """After :meth:`sealed`: whether slab `index` holds a voxel that :meth:`fill_sealed` fills."""
        return bool(len(self._parent)) and bool(self._sealed_table(index, self._count(index)).any())

    def _count(self, index: int) -> int:
        """Labels of slab `index`."""
        nxt = self._offsets[index + 1] if index + 1 < len(self._offsets) else len(self._parent)
        return nxt - self._offsets[index]

    def _seeded(self, index: int) -> bool:
        """Whether pass 2 on slab `index` paints from the first voxels (no labels kept for it)."""
        return self._firsts is not None and index not in self._labels_of

    def _floods(self, index: int, table: np.ndarray, field: np.ndarray) -> bool:
        """Whether to paint the labels `table` picks from their first voxels: when the field is one
        :func:`~implicit_scaffold.run.pieces.flood_paint` takes and the voxels to paint are few, so that
        its stack (8 bytes a painted voxel at most) stays within a byte a voxel of the slab, less than
        labelling it again holds."""
        if not (field.dtype == np.float32 and field.flags.c_contiguous and field.ndim == 3):
            return False
        return int(self._sizes[index][table[1:]].sum()) * 8 <= field.size

    def _flood(self, index: int, table: np.ndarray, field: np.ndarray, value: float, *, below: bool) -> int:
        """Paint the labels of slab `index` that `table` (0 first) picks, from their first voxels: the
        same voxels as painting the slab's labels (each label is the piece of its first voxel in the
        slab's mask, ``field < 0`` for the solid, :func:`~implicit_scaffold.fields.field.void_mask` for the
        void, whose forced outer layer no sealed piece reaches)."""
        from .pieces import flood_paint

        seeds = self._firsts[index][table[1:]]
        return flood_paint(field, seeds, value, below=below) if seeds.size else 0

    def _sealed_table(self, index: int, count: int) -> np.ndarray:
        root = self._roots[self._offsets[index]:self._offsets[index] + count]
        return np.concatenate([[False], ~self._open[root] & (root != getattr(self, "_kept", -1))])

    @property
    def labels(self) -> int:
        """Labels given so far, over all slabs (a piece's root is one of them)."""
        return len(self._parent)

    @property
    def piece_count(self) -> int:
        """After :meth:`finish`: the pieces (of any size) joined across the slabs."""
        return int(np.count_nonzero(self._piece_sizes > 0)) if len(self._parent) else 0

    @property
    def sizes(self) -> np.ndarray:
        """After :meth:`finish`: voxels of each piece, by root (0 for the labels that are not roots)."""
        return self._piece_sizes if len(self._parent) else np.zeros(0)

    def roots_of_all(self) -> np.ndarray:
        """After :meth:`finish`: the piece (root) of every label given, slab after slab."""
        return self._roots if len(self._parent) else np.zeros(0, np.int64)

    def tally_by_root(self) -> np.ndarray:
        """After :meth:`finish`: the `tally` voxels (:meth:`add`) of each piece, by root."""
        tallies = np.concatenate(self._tallies or [np.zeros(0, np.int64)])
        if not len(self._parent) or not tallies.size:
            return np.zeros(0, np.int64)
        return np.bincount(self._roots, weights=tallies, minlength=len(self._parent)).astype(np.int64)

    def roots_of(self, index: int, local: np.ndarray) -> np.ndarray:
        """After :meth:`finish`: the pieces (roots) of labels `local` (1-based) of slab `index`; -1 for 0."""
        local = np.asarray(local, np.int64)
        out = np.full(local.shape, -1, np.int64)
        # only the labels there are: a slab without any has no entry at its offset to read
        some = local > 0
        if some.any():
            out[some] = self._roots[local[some] - 1 + self._offsets[index]]
        return out

    def keep_largest_per(self, group: np.ndarray) -> None:
        """After :meth:`finish`: keep the largest piece of each group instead of the one main body.

        `group` gives each root its group (e.g. the patient piece it lies in; any value for
        the other indices). On a tie the root met first in C order is kept, as
        :func:`~implicit_scaffold.run.pieces.main_bodies` does on the whole grid.
        """
        roots = np.nonzero(self._piece_sizes > 0)[0]
        order = np.lexsort((roots, -self._piece_sizes[roots], group[roots]))
        first = np.ones(len(roots), bool)
        first[1:] = group[roots][order[1:]] != group[roots][order[:-1]]
        self._kept_roots = np.zeros(len(self._parent), bool)
        self._kept_roots[roots[order[first]]] = True

    def fragments(self) -> int:
        """After :meth:`finish` (and :meth:`keep_largest_per`): the pieces that are not kept."""
        kept = getattr(self, "_kept_roots", None)
        return self.piece_count - (int(kept.sum()) if kept is not None else min(self.piece_count, 1))

    def fragment_mask(self, index: int, solid: np.ndarray) -> np.ndarray:
        """Pass 2: voxels of slab `index` (same solid as given to :meth:`add`) to turn into void."""
        labels, count = self._labels_again(index, solid)
        return self._fragment_table(index, count)[labels]

    def drop_fragments(self, index: int, field: np.ndarray, value: float) -> int:
        """Pass 2: write `value` into the voxels of slab `index` (the field whose ``field < 0`` was
        given to :meth:`add`) that lie in a fragment, in place. Returns the voxels written."""
        from .pieces import paint_labels

        if self._seeded(index):
            table = self._fragment_table(index, self._count(index))
            if self._floods(index, table, field):
                return self._flood(index, table, field, value, below=True)
        labels, count = self._labels_again(index, lambda: field < 0)
        return paint_labels(labels, self._fragment_table(index, count), field, value)

    def has_fragments(self, index: int) -> bool:
        """After :meth:`finish`: whether slab `index` holds a voxel that :meth:`drop_fragments` drops."""
        return bool(len(self._parent)) and bool(self._fragment_table(index, self._count(index)).any())

    def _fragment_table(self, index: int, count: int) -> np.ndarray:
        """Whether each label of slab `index` (0 first: never) lies in a fragment."""
        root = self._roots[self._offsets[index]:self._offsets[index] + count]
        kept = getattr(self, "_kept_roots", None)
        drop = ~kept[root] if kept is not None else root != self.main
        return np.concatenate([[False], drop])


class ArraySlabs:
    """A field held in memory, read and written plane range by plane range like a :class:`FieldFile`.

    It is the slab store of a run whose whole grid fits in memory: the same passes
    (:func:`~implicit_scaffold.run.tiled.tiled_scaffold`) then run over one slab, the whole grid,
    and the finished field is the array itself.

    Parameters
    ----------
    field : (nx, ny, nz) float ndarray, mm, or None
        The field; None for a store that its first :meth:`write` fills.
    grid : Grid
    views : bool
        :meth:`read` gives views of the array (writing into them writes the store), not
        copies: a pass over the whole grid then holds no second copy of it.
    """

    path = None  # nothing on disk

    def __init__(self, field: np.ndarray | None, grid, *, views: bool = False):
        if field is not None and tuple(field.shape) != tuple(grid.shape):
            raise ScaffoldError(f"the field's shape {field.shape} does not match its grid {grid.shape}")
        self.field = field
        self.grid = grid
        self.views = views

    def read(self, x0: int, x1: int) -> np.ndarray:
        """Planes ``[x0, x1)``, ``(x1 - x0, ny, nz)`` float32 (a copy, or a view if :attr:`views`)."""
        if self.views and self.field.dtype == np.float32:
            return self.field[x0:x1]
        return np.array(self.field[x0:x1], np.float32)

    def write(self, x0: int, planes: np.ndarray) -> None:
        """Store planes ``x0 .. x0 + len(planes)``; a float32 array of the whole grid is kept as it is."""
        shape = tuple(self.grid.shape)
        if (int(x0) == 0 and tuple(planes.shape) == shape and planes.dtype == np.float32
                and planes.flags.c_contiguous):
            self.field = planes
            return
        if self.field is None:
            self.field = np.empty(shape, np.float32)
        if planes.shape[1:] != shape[1:]:
            raise ValueError(f"planes of shape {planes.shape[1:]} for a grid of {shape}")
        target = self.field[int(x0):int(x0) + len(planes)]
        if np.may_share_memory(target, planes):
            if (target.__array_interface__["data"][0] == planes.__array_interface__["data"][0]
                    and target.shape == planes.shape and target.strides == planes.strides):
                return  # a view that read() gave, written into in place
            planes = np.array(planes)
        target[...] = planes

    def close(self) -> None:
        """Let the array go (the caller may still hold it)."""
        self.field = None


def _remove_orphans(folder) -> None:
    """Remove the field files that runs killed outright (SIGKILL, a lost machine) left in
    `folder`: those named after a process that no longer runs. A run that ends any other way
    removes its own (:meth:`FieldFile.close`)."""
    import os
    from pathlib import Path

    for path in Path(folder).glob("implicit_scaffold-*-*.f32"):
        pid = path.name.split("-")[1]
        if not pid.isdigit() or int(pid) == os.getpid():
            continue
        try:
            os.kill(int(pid), 0)
        except ProcessLookupError:
            try:
                path.unlink()
            except OSError:
                pass
        except OSError:
            pass  # alive, another user's


class FieldFile:
    """A float32 field over a grid kept in a raw file (C order, x slowest), written and read by planes.

    Planes of one x are contiguous, so a slab is one read or write; the file is read
    with plain reads, not mapped, so what a slab costs in memory is what it holds.
    Use as a context manager: the file is removed at the end.

    Parameters
    ----------
    grid : Grid
    folder : str or Path, optional
        Where to keep the file (the system's temporary folder by default).
    """

    def __init__(self, grid, folder=None):
        import os
        import tempfile

        self.grid = grid
        self._plane = int(grid.shape[1]) * int(grid.shape[2])
        _remove_orphans(folder or tempfile.gettempdir())
        # the process's id in the name: a run killed outright leaves its file to the next run
        fd, name = tempfile.mkstemp(prefix=f"implicit_scaffold-{os.getpid()}-", suffix=".f32", dir=folder)
        self.path = name
        self._fh = open(fd, "r+b", buffering=0)
        try:
            self._fh.truncate(4 * self._plane * int(grid.shape[0]))
        except OSError as exc:
            self.close()
            raise ScaffoldError(f"cannot keep a {4 * self._plane * grid.shape[0] / 2**30:.1f} GiB field "
                                f"on disk in {folder or tempfile.gettempdir()}: {exc.strerror or exc}; "
                                "free disk space or set TMPDIR to a larger disk") from None

    def write(self, x0: int, planes: np.ndarray) -> None:
        """Store planes ``x0 .. x0 + len(planes)``."""
        data = np.ascontiguousarray(planes, np.float32)
        if data.shape[1:] != tuple(self.grid.shape[1:]):
            raise ValueError(f"planes of shape {data.shape[1:]} for a grid of {self.grid.shape}")
        self._fh.seek(4 * self._plane * int(x0))
        view = memoryview(data.reshape(-1).view(np.uint8))
        while view:
            view = view[self._fh.write(view):]

    def read(self, x0: int, x1: int) -> np.ndarray:
        """Planes ``[x0, x1)``, ``(x1 - x0, ny, nz)`` float32."""
        out = np.empty((int(x1) - int(x0),) + tuple(self.grid.shape[1:]), np.float32)
        self._fh.seek(4 * self._plane * int(x0))
        view = memoryview(out.reshape(-1).view(np.uint8))
        while view:
            n = self._fh.readinto(view)
            if not n:
                raise OSError(f"{self.path} ended early")
            view = view[n:]
        return out

    @classmethod
    def attach(cls, path, grid, *, write: bool = False) -> "FieldFile":
        """An existing field file (another :class:`FieldFile`'s ``.path``), for reading, or
        for writing planes too (`write`).

        For a process that reads or fills planes of the file another process keeps (a worker
        of :mod:`~implicit_scaffold.run.executor`): closing it (or leaving its ``with`` block) closes this handle and
        keeps the file, which is its creator's to remove.
        """
        self = cls.__new__(cls)
        self.grid = grid
        self._plane = int(grid.shape[1]) * int(grid.shape[2])
        self.path = str(path)
        self._fh = open(self.path, "r+b" if write else "rb", buffering=0)
        self.close = self._fh.close  # shadows close(): the file is the creator's to remove
        return self

    @classmethod
    def open_readonly(cls, path, grid) -> "FieldFile":
        """:meth:`attach` for reading only."""
        return cls.attach(path, grid)

    def close(self) -> None:
        """Remove the file."""
        import os

        if not self._fh.closed:
            self._fh.close()
        try:
            os.unlink(self.path)
        except FileNotFoundError:
            pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
