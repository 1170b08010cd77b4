"""The voxel finite-element operator on the OpenCL device (``kernels/mechanics.cl``).

:func:`~implicit_scaffold.mechanics.apply_stiffness` is its NumPy reference; the tests hold
them together. The conjugate gradients stay on the host in float64 (the FFT preconditioner
is NumPy/SciPy); only ``K p`` runs here, in double when the device has ``cl_khr_fp64``.
"""
from __future__ import annotations

import numpy as np

from . import opencl


def has_double() -> bool:
    """Whether the active device computes in double precision."""
    ctx, _ = opencl.context()
    return "cl_khr_fp64" in ctx.devices[0].extensions


class _Gather:
    """``f = A u`` by the gather kernel of ``kernels/mechanics.cl`` on a periodic node grid."""

    def __init__(self, shape, owner, mats, *, double: bool, per_element: bool):
        self.shape = tuple(int(v) for v in shape)
        self.double = bool(double)
        self.dtype = np.float64 if self.double else np.float32
        self.per_element = int(per_element)
        self.owner = opencl.to_device(owner.ravel(), np.int32 if per_element else np.uint8)
        self.mats = opencl.to_device(mats, self.dtype)
        self.n = int(np.prod(self.shape))
        self._buffers = {}

    def _io(self, m):
        import pyopencl as cl

        if m not in self._buffers:
            ctx, _ = opencl.context()
            nbytes = m * 3 * self.n * np.dtype(self.dtype).itemsize
            self._buffers[m] = (cl.Buffer(ctx, cl.mem_flags.READ_ONLY, nbytes),
                                cl.Buffer(ctx, cl.mem_flags.WRITE_ONLY, nbytes))
        return self._buffers[m]

    def __call__(self, u: np.ndarray) -> np.ndarray:
        """A u for (m, 3, N) nodal values, in float64 (or in the operator's own float when
        `u` comes in it)."""
        import pyopencl as cl

        m = u.shape[0]
        _, queue = opencl.context()
        k = opencl.kernel("mechanics", "stiffness_apply", NCASE=m, USE_DOUBLE=int(self.double),
                          PER_ELEMENT=self.per_element)
        u_buf, f_buf = self._io(m)
        native = u.dtype == self.dtype
        host = np.ascontiguousarray(u, self.dtype)
        cl.enqueue_copy(queue, u_buf, host)
        n1, n2, n3 = self.shape
        k(queue, (self.n,), None, self.owner, self.mats, u_buf, f_buf, np.int32(n1), np.int32(n2), np.int32(n3))
        out = np.empty(host.shape, self.dtype)
        cl.enqueue_copy(queue, out, f_buf)
        return out if native else out.astype(np.float64)


class StiffnessOperator(_Gather):
    """``K u`` of a :class:`~implicit_scaffold.mechanics.VoxelModel` on the device.

    Parameters
    ----------
    model : VoxelModel
    double : bool, optional
        Compute in double (default: when the device can).
    """

    def __init__(self, model, *, double: bool | None = None):
        self.model = model
        super().__init__(model.shape, model.solid, model.ke, double=has_double() if double is None else double,
                         per_element=False)

    def single(self) -> "StiffnessOperator":
        """The same operator in float (a preconditioner's: half the time and memory of double)."""
        return self if not self.double else StiffnessOperator(self.model, double=False)

    def __call__(self, u: np.ndarray, element_extra: np.ndarray | None = None) -> np.ndarray:
        """K u; with `element_extra` (a one-off right-hand side) the NumPy reference does it."""
        if element_extra is not None:
            from .mechanics import apply_stiffness

            return apply_stiffness(self.model, u, element_extra)
        return super().__call__(u)


class LevelOperator(_Gather):
    """``A u`` of a coarse multigrid level (:class:`~implicit_scaffold.multigrid.Level`) on
    the device, in the float of its matrices."""

    def __init__(self, level):
        super().__init__(level.shape, level.index, level.mats, double=level.mats.dtype == np.float64,
                         per_element=True)
