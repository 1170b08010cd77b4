"""The voxel finite-element operator on the OpenCL device (``kernels/mechanics.cl``).

:func:`~implicit_scaffold.measure.mechanics.apply_stiffness` is its NumPy reference; the tests hold
them together. The conjugate gradients stay on the host in float64 (the FFT preconditioner
is NumPy/SciPy); only ``K p`` runs here, in double when the device has ``cl_khr_fp64``.
"""
from __future__ import annotations

import contextlib
import functools
import sys

import numpy as np

from .. import opencl


def has_double() -> bool:
    """Whether the active device computes in double precision."""
    ctx, _ = opencl.context()
    return "cl_khr_fp64" in ctx.devices[0].extensions


def has_vote() -> bool:
    """Whether the active device's kernels can vote over a vector of work items
    (``cl_intel_subgroups``: a sub-group is the vector the Intel CPU runtime packs them into)."""
    ctx, _ = opencl.context()
    return _lists_subgroups(ctx)


@functools.lru_cache(maxsize=None)
def _lists_subgroups(ctx) -> bool:
    # asked once per context: defines() runs for every product's launches
    return "cl_intel_subgroups" in ctx.devices[0].extensions.split()


def defines(ncase: int, double: bool) -> dict:
    """The ``-D`` defines of ``kernels/mechanics.cl`` for products of `ncase` load cases a launch:
    one place, so that a caller building the kernels ahead (the benchmark) builds these."""
    return dict(_variant(ncase, double), VOTE=int(has_vote()))


def _variant(ncase: int, double: bool) -> dict:
    """:func:`defines` but the device's VOTE (what a built marker names: :func:`solve_variants`)."""
    return dict(NCASE=int(ncase), USE_DOUBLE=int(bool(double)))


def solve_variants(block: int, shape, boundary: str) -> list[dict]:
    """The builds of ``kernels/mechanics.cl`` a measure of a sample of `shape` voxels makes with load cases
    `block` at a time, as :func:`defines` but the device's VOTE: the fine operator one case a launch in float
    and in double; a block of two or more on the coarse levels, and where the first level has elements no
    child pattern covers (a box sample, or an odd axis), those by ``stiffness_apply`` with ADD
    (:class:`PatternLevelOperator`)."""
    out = [_variant(1, False), _variant(1, True)]
    if block >= PatternLevelOperator.MIN_CASES:
        out.append(_variant(block, False))
        if boundary != "periodic" or any(int(s) % 2 for s in shape):
            out.append(dict(ADD=1, **_variant(block, False)))
    return out


def prebuild(variants) -> None:
    """Have the `variants` (:func:`solve_variants`) built before a solve: those not built on this machine
    yet are compiled in a child process (:func:`~implicit_scaffold.opencl.build_in_child`), so that this
    process only loads their binaries and never holds the runtime's compiler (some 150 MiB, which the
    solve's memory estimate does not count). Nothing is started when all are built."""
    todo = opencl.unbuilt("mechanics", variants)
    if todo:
        opencl.build_in_child(__name__, todo)


#: host arrays the device reads and writes in place are aligned to this many bytes (:data:`opencl.ALIGN`)
ALIGN = opencl.ALIGN


#: arrays of at least this many bytes are taken from the pool of :func:`reusing` while one is open
POOLED_BYTES = 1 << 20
#: an array gets a free buffer of the pool at most this many times its size
FIT_RATIO = 2
#: the fine operator's :meth:`StiffnessOperator.live_product` spreads and multiplies this many nodes'
#: planes at a time (whole planes, at least one): 12 MiB of a case's vector and its product in double.
#: Each slab costs its launches, passes and two extra planes: on the 128^3 benchmark scaffold (medians of
#: 5, a throw-away script) a double product took 49.2 and 49.9 ms by slabs of 2^18 nodes, 49.6 and 48.4 by
#: slabs of 2^20, 38.8 and 38.6 over the whole grid; float 27.7 and 25.8, 27.0 and 27.8, 21.1 and 20.9
SLAB_NODES = 1 << 18
#: on a grid of more than :data:`FLOAT_SLABS_FROM` nodes the float products run by slabs of this many
#: nodes' planes: the CG's (:meth:`StiffnessOperator.live_product`) and the V-cycle's fine level
#: (:data:`~implicit_scaffold.measure.multigrid.FINE_SLAB_NODES`), so that no whole-grid vector is made
#: (two in float32, 24 bytes a node). Each slab costs its launches and passes, and a float product is
#: cheap: on the 128^3 benchmark scaffold (six cases, a throw-away script, quiet machine) slabs of 2^18
#: nodes took the solve from 17.80 and 18.37 s to 22.18 and 27.02 s; on the 200^3 one, slabs of 2^22 from
#: 63.62 s to 69.97 s (one run each), for 860 bytes a solid voxel against 872: with six load cases a
#: block the whole-grid vectors (one case's) are a small part of the peak. Hence only on grids larger than
#: the benchmark's, where memory is what stops a solve (the lumbar micro-CT's 27.3 million nodes)
FLOAT_SLAB_NODES = 1 << 22
FLOAT_SLABS_FROM = 1 << 24
#: the 3-D kernels' work groups hold this many rows (consecutive j) of a node plane: a group's rows share six of
#: the nine rows of u each reads. On the 128^3 benchmark scaffold's six-case homogenization (a throw-away script,
#: two rounds) the fine product fell from 9.96 and 10.02 ms a case to 8.94 and 9.17 with 8 rows a group, the
#: 32^3 level's from 2.56 and 2.76 to 2.29 and 2.37 ms; alone (medians of 31, three rounds) 8.87, 8.85 and
#: 9.09 ms with 1 row, 8.33, 8.54 and 8.30 with 8 (2, 4, 16, 32: 8.26 to 8.74)
ROWS_PER_GROUP = 8
#: a homogenization of one load case a block (what a tight memory budget takes: ``block_for``) runs its float
#: products, the CG's and the V-cycle's fine level, by slabs of this many nodes' planes on any grid (the
#: default of six a block keeps its whole-grid vectors, which are a small part of its peak): on the 128^3
#: benchmark scaffold the two whole-grid float vectors were 80 bytes a solid voxel of the one-case solve's
#: peak, some 11 by slabs of 2^18 nodes (2^19: the same peak; 2^20: 17 bytes a solid voxel more)
ONE_CASE_SLAB_NODES = 1 << 18
_pool: list | None = None


@contextlib.contextmanager
def reusing():
    """Within this block, :func:`aligned_empty` hands out again the memory of its large arrays
    that nothing refers to any more, instead of asking the system for new pages.

    A solver's iterations allocate and drop the same whole-grid vectors every step. Each new
    array of more than 32 MiB (and often a smaller one) is fresh pages, which the kernel zeroes as they are first
    touched: a homogenization of the 128^3 benchmark scaffold spent 9.4 s of system time without the
    pool, 5.4 s with it (one run each, peak resident 939 and 959 MiB; a pool that never frees took
    3.2 s but 1,170 MiB). An array is free when only the pool refers to its buffer (every NumPy view
    of it refers to the buffer itself, and so does an OpenCL buffer made over it). An array gets the
    smallest free buffer that holds it, if that is at most :data:`FIT_RATIO` times its size; on leaving
    the outermost block the pool is dropped.
    """
    global _pool
    outer = _pool
    if outer is None:
        _pool = []
    try:
        yield
    finally:
        if outer is None:
            _pool = None


def _counts(buffers: list) -> list:
    """``sys.getrefcount`` of each buffer, always seen from this one place."""
    return [sys.getrefcount(raw) for raw in buffers]


@functools.lru_cache(maxsize=None)
def _free_count() -> int:
    """The count :func:`_counts` gives for a buffer that only its list refers to (measured, not
    assumed: what an interpreter adds for its own frames differs between versions)."""
    return _counts([np.empty(1, np.uint8)])[0]


def _raw(nbytes: int) -> np.ndarray:
    """A byte buffer of `nbytes` (+ :data:`ALIGN`): a free one of the pool's, or a new one."""
    if _pool is None or nbytes < POOLED_BYTES:
        return np.empty(nbytes + ALIGN, np.uint8)
    free = [count == _free_count() for count in _counts(_pool)]
    need = nbytes + ALIGN
    # the smallest free buffer that holds it: with exact sizes only, the V-cycle's 23 MB transfer
    # intermediates missed every time on the 200^3 benchmark (148 misses), each miss freeing a
    # 96 MB grid vector that the next one then missed in turn (44 more). But none of more than
    # FIT_RATIO times its size: a coarse level's vector in a fine grid's buffer left the fine level's
    # next vector a miss, a third grid buffer (128^3 benchmark scaffold, one case a block: 24 MiB,
    # 40 bytes a solid voxel at the cycle's peak)
    fits = [raw for raw, idle in zip(_pool, free) if idle and need <= raw.size <= FIT_RATIO * need]
    if fits:
        return min(fits, key=lambda raw: raw.size)
    # a miss: free buffers no larger go first (a larger one serves the larger arrays), oldest first, as
    # many bytes as the new one takes, so that the pool holds no more than the peak of each size's arrays
    freed, keep = 0, []
    for raw, idle in zip(_pool, free):
        if idle and freed < nbytes and raw.size <= FIT_RATIO * need:
            freed += raw.size
        else:
            keep.append(raw)
    _pool[:] = keep
    del keep
    raw = None  # the loop's last buffer, if freed, goes before the new one is made
    raw = np.empty(nbytes + ALIGN, np.uint8)
    _pool.append(raw)
    return raw


def aligned_empty(shape, dtype=np.float64) -> np.ndarray:
    """An uninitialised C-contiguous array whose data start on an :data:`ALIGN`-byte boundary
    (inside :func:`reusing`, maybe memory that an array dropped before held)."""
    nbytes = int(np.prod(np.atleast_1d(shape), dtype=np.int64)) * np.dtype(dtype).itemsize
    return opencl.aligned_view(_raw(nbytes), shape, dtype)


def aligned_copy(a: np.ndarray, dtype=None) -> np.ndarray:
    """A copy of `a` (in `dtype`, default its own) in an :func:`aligned_empty` array."""
    out = aligned_empty(a.shape, a.dtype if dtype is None else dtype)
    np.copyto(out, a, casting="same_kind")
    return out


def _aligned(a: np.ndarray, dtype) -> np.ndarray:
    """`a` itself when it is C-contiguous, of `dtype` and aligned, else an aligned copy."""
    if a.dtype == dtype and a.flags.c_contiguous and a.ctypes.data % ALIGN == 0:
        return a
    return aligned_copy(a, dtype)


def _shared(array, dtype):
    """(the aligned host array, a read-only device buffer over it: :func:`opencl.host_buffer`, no copy on a CPU
    device); keep the host array beside the buffer."""
    host = _aligned(np.asarray(array).reshape(-1) if np.size(array) else np.zeros(1, dtype), dtype)
    return host, opencl.host_buffer(host)


def plane_starts(live: np.ndarray, n1: int, plane: int) -> np.ndarray:
    """(n1 + 1,) where each of the grid's `n1` node planes (of `plane` nodes) begins in the increasing flat node
    indices `live`: the positions of ``0, plane, 2 plane, ...``, searched in `live`'s own integer type where they
    fit it (in another, NumPy converts the whole of `live` for each search: an int32 `live` of 3.5 M nodes cost
    a product by slabs 24 ms there)."""
    bounds = np.arange(n1 + 1, dtype=np.int64) * plane
    if live.dtype.kind == "i" and bounds[-1] <= np.iinfo(live.dtype).max:
        bounds = bounds.astype(live.dtype)
    return np.searchsorted(live, bounds)


def plane_runs(planes: np.ndarray) -> list:
    """The runs of consecutive node planes of a slab's `planes` (:meth:`StiffnessOperator.slab`), as
    (start, stop) positions in it: one run, or two or three where the slab wraps round the grid's ends."""
    cuts = np.flatnonzero(np.diff(planes) != 1) + 1
    bounds = [0, *cuts.tolist(), int(planes.size)]
    return list(zip(bounds[:-1], bounds[1:]))


class _Gather:
    """``f = A u`` by the gather kernels of ``kernels/mechanics.cl`` on a periodic node grid (the
    fine operator's ``stiffness_rows`` and ``stiffness_ends``, a coarse level's ``stiffness_apply``).

    The kernel reads and writes host arrays in place (``USE_HOST_PTR`` on :data:`ALIGN`-aligned
    arrays): no device copies of the vectors, the element matrices or the solid flags."""

    def __init__(self, shape, owner, mats, *, double: bool, per_element: bool, halo: bool = False):
        self.shape = tuple(int(v) for v in shape)
        self.double = bool(double)
        self.dtype = np.float64 if self.double else np.float32
        self.per_element = int(per_element)
        # a slab's operator (:meth:`StiffnessOperator.slab`): its first and last node planes are its neighbours',
        # read and not computed
        self.halo = bool(halo) and not self.per_element and self.shape[0] > 2
        self._owner_host, self.owner = _shared(owner, np.int32 if per_element else np.uint8)
        self._mats_host, self.mats = _shared(mats, self.dtype)
        self.n = int(np.prod(self.shape))

    def _launches(self, ncase: int) -> list:
        """The kernel launches of one product of `ncase` load cases: (kernel, global size, local size,
        its two first arguments).

        A coarse level: ``stiffness_apply`` over every node. The fine operator: ``stiffness_rows``
        and ``stiffness_ends`` (:meth:`_rows`)."""
        opts = defines(ncase, self.double)
        if self.per_element:
            return [(opencl.kernel("mechanics", "stiffness_apply", **opts), (self.n,), None, (self.owner, self.mats))]
        return self._rows("stiffness", opts, (self.owner, self.mats))

    def _rows(self, name: str, opts: dict, args: tuple) -> list:
        """The launches of a 3-D gather kernel pair: ``<name>_rows`` over the rows' inner nodes, in
        work groups along a row whose length is a multiple of 16 (a CPU runtime packs 16 work items
        into a vector: a row of 126 would leave 14 to run one by one), :data:`ROWS_PER_GROUP` rows
        (consecutive j) a group, and ``<name>_ends`` over the rows' two end nodes; `args` are the
        kernels' first two arguments."""
        n1, n2, n3 = self.shape
        out = []
        inner = n3 - 2
        if inner > 0:
            most = opencl.device().max_work_group_size
            group = min(16 * -(-inner // 16), 256, most)
            rows = max(1, min(ROWS_PER_GROUP, n2, most // group))
            # the rows' range rounded up to whole groups (the kernel leaves j >= n2 out)
            out.append((opencl.kernel("mechanics", f"{name}_rows", **opts),
                        (group * -(-inner // group), rows * -(-n2 // rows), n1), (group, rows, 1), args))
        out.append((opencl.kernel("mechanics", f"{name}_ends", **opts), (min(n3, 2), n2, n1), None, args))
        return out

    def __call__(self, u: np.ndarray) -> np.ndarray:
        """A u for (m, 3, N) nodal values, in float64 (or in the operator's own float when
        `u` comes in it). `u` is read in place when it is aligned (:func:`aligned_empty`) and
        of the operator's float; the result is aligned."""
        import pyopencl as cl

        m = u.shape[0]
        ctx, queue = opencl.context()
        # the fine operator in double runs one case per launch: a quarter faster per case than
        # six together on the 128^3 scaffold of the benchmark (307 against 408 ms a case, and
        # 413 against 576 in another run; in float the two were within 10 %, either way; with
        # stiffness_rows, 559 against 740 ms of CPU time for the six cases, the machine loaded)
        step = 1 if self.double and not self.per_element else m
        launches = self._launches(step)
        native = u.dtype == self.dtype
        host = _aligned(u, self.dtype)
        out = aligned_empty(host.shape, self.dtype)
        flags = cl.mem_flags
        u_buf = cl.Buffer(ctx, flags.READ_ONLY | flags.USE_HOST_PTR, hostbuf=host)
        f_buf = cl.Buffer(ctx, flags.WRITE_ONLY | flags.USE_HOST_PTR, hostbuf=out)
        n1, n2, n3 = self.shape
        offset = None
        if self.halo:
            # the inner planes only (the 3-D launches' last axis is the plane), and 0 on the other two: on the default
            # cube's compression (194^3 nodes, slabs of 6 inner planes) the halo was a quarter of each slab's work
            launches = [(k, g[:2] + (n1 - 2,), local, args) for k, g, local, args in launches]
            offset = (0, 0, 1)
            planes = out.reshape(m, 3, n1, n2 * n3)
            planes[:, :, 0] = 0
            planes[:, :, n1 - 1] = 0
            del planes
        for first in range(0, m, step):
            for k, global_size, local_size, (owner, mats) in launches:
                k(queue, global_size, local_size, owner, mats, u_buf, f_buf, np.int32(n1), np.int32(n2),
                  np.int32(n3), np.int32(first), global_offset=offset)
        # mapping the result makes the host array current (a no-op on a CPU device)
        view, _ = cl.enqueue_map_buffer(queue, f_buf, cl.map_flags.READ, 0, out.shape, out.dtype)
        del view
        queue.finish()
        u_buf.release()
        f_buf.release()
        return out if native else out.astype(np.float64)


class StiffnessOperator(_Gather):
    """``K u`` of a :class:`~implicit_scaffold.measure.mechanics.VoxelModel` on the device.

    Parameters
    ----------
    model : VoxelModel
    double : bool, optional
        Compute in double (default: when the device can).
    """

    def __init__(self, model, *, double: bool | None = None, _flags=None):
        self.model = model
        # the solid flags the device reads (an aligned uint8 copy), and those of the slabs (:meth:`slab`) by their
        # planes: shared with the operator in the other float (:meth:`single`), whose flags are the same bytes
        # (on the 128^3 benchmark scaffold each copy of the grid's was 3.3 bytes a solid voxel, the slabs' 3.8)
        flags, self._slab_flags = (model.solid, {}) if _flags is None else _flags
        super().__init__(model.shape, flags, model.ke, double=has_double() if double is None else double,
                         per_element=False)

    def single(self) -> "StiffnessOperator":
        """The same operator in float (a preconditioner's, and the CG's iterations': half the time
        and memory of double); one instance, shared by every caller, which reads this one's solid flags."""
        if not self.double:
            return self
        if getattr(self, "_single", None) is None:
            self._single = StiffnessOperator(self.model, double=False,
                                             _flags=(self._owner_host.reshape(self.shape), self._slab_flags))
        return self._single

    def __call__(self, u: np.ndarray, element_extra: np.ndarray | None = None) -> np.ndarray:
        """K u; with `element_extra` (a one-off right-hand side) the NumPy reference does it."""
        if element_extra is not None:
            from .mechanics import apply_stiffness

            return apply_stiffness(self.model, u, element_extra)
        return super().__call__(u)

    def live_product(self, u: np.ndarray, live: np.ndarray, w_in, w_out, dtype=np.float64,
                     slab_nodes: int | None = None, out: np.ndarray | None = None) -> np.ndarray:
        """``w_out K (w_in u)`` on the nodes `live` from values `u` on them, (m, 3, len(live)) in `dtype`:
        bit for bit ``take(self(put(u, live, N, w_in)), live, w_out, dtype)``, a slab of node planes at a
        time (:data:`SLAB_NODES` nodes, plus a plane on either side), so that no vector of the whole
        grid is made (a case's in double is 24 bytes a node, and its product as many: on the 128^3
        benchmark scaffold 160 bytes a solid voxel, which the CG's products held at every step).

        Parameters
        ----------
        u : (m, 3, L) float ndarray
        live : (L,) increasing int ndarray
            Flat node indices.
        w_in, w_out : (1, L) or (3, L) float ndarrays
            Weights of `u`'s values and of the product's (0 and 1: the free unknowns).
        dtype : numpy float type
        slab_nodes : int, optional
            The slabs' nodes (default :data:`SLAB_NODES`).
        out : (m, 3, L) ndarray of `dtype`, optional
            Written with the result (and returned) instead of a new array.
        """
        from .fused import put, put_add, take

        n1, n2, n3 = self.shape
        plane = n2 * n3
        thick = max(1, min(n1, (SLAB_NODES if slab_nodes is None else slab_nodes) // plane))
        live = np.asarray(live)
        # where each node plane's live nodes begin in `live`
        starts = plane_starts(live, n1, plane)
        w_in = np.asarray(w_in).reshape(-1, live.size)
        w_out = np.asarray(w_out).reshape(-1, live.size)
        if out is None:
            out = aligned_empty(u.shape[:2] + (live.size,), dtype)
        for i0 in range(0, n1, thick):
            i1 = min(n1, i0 + thick)
            if starts[i1] == starts[i0]:
                continue  # no live node to give a value to
            planes, op = self.slab(i0, i1)
            slab = None
            # u spread over the slab's planes (the grid's i0 - 1 .. i1, wrapped), a run of consecutive
            # planes at a time: one run, but where the slab wraps round the grid's ends
            for p, q in plane_runs(planes):
                k0, k1 = starts[planes[p]], starts[planes[q - 1] + 1]
                idx = live[k0:k1] - (int(planes[p]) - p) * plane
                if slab is None and k1 > k0:  # every node of the slab written: 0 but on idx
                    slab = put(u[:, :, k0:k1], idx, planes.size * plane, w_in[:, k0:k1], self.dtype)
                elif slab is None:
                    slab = aligned_empty(u.shape[:2] + (planes.size * plane,), self.dtype)
                    slab.fill(0)
                elif k1 > k0:
                    put_add(slab, u[:, :, k0:k1], idx, w_in[:, k0:k1])
            f = op(slab)
            del slab
            # the slab's inner planes are the grid's i0 .. i1 - 1, whose neighbours it holds
            k0, k1 = starts[i0], starts[i1]
            take(f, live[k0:k1] - (i0 - 1) * plane, w_out[:, k0:k1], out=out[:, :, k0:k1])
            del f
        return out

    def slab(self, i0: int, i1: int):
        """(planes, operator): the node planes of the slab of planes ``i0 .. i1 - 1`` with one more on either
        side (wrapped round a periodic grid's ends), and the operator of their voxels (planes of the same
        indices), whose product is this one's on the slab's inner planes (computed there alone; 0 on the first
        and last, which it reads); made once, and kept with this operator: the slabs' flags copy the solid's, a
        byte a voxel and two planes a slab more."""
        cache = self.__dict__.setdefault("_slabs", {})
        if (i0, i1) not in cache:
            planes = np.arange(i0 - 1, i1 + 1) % self.shape[0]
            flags = self._slab_flags.get((i0, i1))
            if flags is None:  # aligned uint8, as the device reads them: no copy of its own in _Gather
                flags = self._slab_flags[(i0, i1)] = aligned_copy(self.model.solid[planes], np.uint8)
            cache[(i0, i1)] = planes, _Gather(flags.shape, flags, self._mats_host, double=self.double,
                                              per_element=False, halo=True)
        return cache[(i0, i1)]


class LevelOperator(_Gather):
    """``A u`` of a coarse multigrid level (:class:`~implicit_scaffold.measure.multigrid.Level`) on
    the device, in the float of its matrices."""

    def __init__(self, level):
        super().__init__(level.shape, level.index, level.mats, double=level.mats.dtype == np.float64,
                         per_element=True)

    def host_mats(self, shape) -> np.ndarray:
        """The host array the device reads the level's matrices from (to keep as the level's own)."""
        return self._mats_host.reshape(shape)


class PatternLevelOperator(LevelOperator):
    """``A u`` of the first coarse multigrid level on the device, its pattern elements by
    ``pattern_rows`` / ``pattern_ends`` and the others by ``stiffness_apply`` (added after).

    An element of the first level with no fixed unknown and full length along every axis has the
    matrix ``sum_c solid_c M_c`` over its eight children (fine voxels), with the same eight
    ``M_c`` everywhere: the product then needs only the element's 8 child bits and runs in full
    vectors, like the fine operator (``stiffness_apply`` gathers a matrix per node).

    Parameters
    ----------
    level : Level
        The first coarse level (its `index` and `mats` cover every element, as for
        :class:`LevelOperator`).
    pattern : (n1, n2, n3) uint8 ndarray
        Each element's child bits (``a + 2b + 4c``) when its matrix is ``sum_c solid_c M_c``, else 0.
    children : (8, 24, 24) float ndarray, GPa mm
        The matrices ``M_c`` (cast to the float of `level.mats`).
    """

    def __init__(self, level, pattern: np.ndarray, children: np.ndarray):
        super().__init__(level)
        pattern = np.asarray(pattern, np.uint8)
        self._code_host, self.code = _shared(pattern, np.uint8)
        self._children_host, self.children = _shared(children, self.dtype)
        # the other elements' matrices by the per-element kernel, added over the pattern's product;
        # none (a periodic solve on even axes) saves its launch
        rest = np.where(pattern.reshape(level.index.shape) == 0, level.index, -1)
        self.any_rest = bool((rest >= 0).any())
        self._rest_host, self.rest = _shared(rest if self.any_rest else np.zeros(1, np.int32), np.int32)

    #: fewer cases a launch than this run the per-element kernel alone: the 27 stencil blocks cost
    #: the same for any number of cases (64^3 first level of the 128^3 benchmark, the machine shared,
    #: ms a call, per-element against pattern: one case 72.5 against 79.6, two 86.8 against 83.6,
    #: three 105.8 against 91.5, six 160 against 120)
    MIN_CASES = 2

    def _launches(self, ncase: int) -> list:
        if ncase < self.MIN_CASES:
            return super()._launches(ncase)
        opts = defines(ncase, self.double)
        out = self._rows("pattern", opts, (self.code, self.children))
        if self.any_rest:
            out.append((opencl.kernel("mechanics", "stiffness_apply", ADD=1, **opts), (self.n,), None,
                        (self.rest, self.mats)))
        return out


class StencilLevelOperator(_Gather):
    """``A u`` of a coarse multigrid level on the device from its assembled node stencils
    (:func:`~implicit_scaffold.measure.multigrid.node_stencils`, ``stencil_rows`` /
    ``stencil_ends``), in the float of its matrices.

    Each work item reads its node's 126 stencil words (the blocks of the node and of its 13 neighbours
    after it) and the 13 other blocks, transposed, from its neighbours' words (the matrix is symmetric),
    and its 27 neighbours' values, at consecutive addresses along a row (full vectors, as the fine
    operator), where :class:`LevelOperator` gathers one 24 x 24 matrix per element around each node. The
    stencils take 126 words a node, the element matrices 576 an element."""

    def __init__(self, level):
        from .multigrid import node_stencils

        # by row: entry x of node (r, k) at (126 r + x) n3 + k (the kernel reads a row's block in order;
        # entry-major, 243 streams a vector, the 32^3 level of the 128^3 benchmark took 7.4 ms for six cases),
        # made so (aligned, in the level's float): the device reads that one array in place
        by_row, live = node_stencils(level)
        super().__init__(level.shape, live, by_row, double=level.mats.dtype == np.float64, per_element=False)

    def _launches(self, ncase: int) -> list:
        return self._rows("stencil", defines(ncase, self.double), (self.owner, self.mats))


if __name__ == "__main__":  # the child of prebuild: build each variant given as JSON, with the device's defines
    import json

    for _given in json.loads(sys.argv[1]):
        opencl.program("mechanics", **_given, VOTE=int(has_vote()))
