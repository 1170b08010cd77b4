"""Stiffness of a scaffold from its own voxels: a matrix-free voxel finite-element solver.

One trilinear hexahedron per solid voxel (exact 2x2x2 Gauss stiffness); void voxels carry
no unknowns (a node is an unknown only when a solid voxel touches it). The system is
solved by preconditioned conjugate gradients, all load cases as one block, with an
FFT-based reference-medium preconditioner: the inverse of the same finite-element operator
on the full (all-solid) periodic grid, which Fourier diagonalises. It is the preconditioner
of the "Fourier-accelerated nodal solvers" (Leuschner & Fritzen 2018, Comput Mech 62:359;
Ladecký et al. 2023, Appl Math Comput 446:127835), whose iteration count depends on the
geometry, not on the voxel size.

Three problems:

- periodic homogenization (six unit strains, the fluctuation periodic): the effective 6x6
  stiffness of a periodic or box sample;
- kinematic homogenization (uniform displacement ``u = E x`` on the box's faces) where the
  sample is not periodic (a patient-shaped scaffold, a bone);
- uniaxial compression between rigid bonded platens (ISO 13314's setting): apparent modulus.

Units: mm and GPa (so forces are in kN and energies in J... scaled consistently; only the
ratios are reported). Voigt order xx, yy, zz, yz, xz, xy with engineering shear strains.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from .errors import ScaffoldError

VOIGT = ("xx", "yy", "zz", "yz", "xz", "xy")
#: corner a of a voxel is at offset (a & 1, a >> 1 & 1, a >> 2 & 1) voxels from its low corner
CORNERS = np.array([(a & 1, (a >> 1) & 1, (a >> 2) & 1) for a in range(8)], dtype=np.int64)
#: a stiffness below this share of the largest diagonal term is "no load path" (round-off of a
#: solve to 1e-8 gives about 1e-8 of the largest term, well under it)
NO_LOAD_PATH = 1e-6


# ----------------------------------------------------------------------------- materials


@dataclass(frozen=True)
class Material:
    """An isotropic linear-elastic material: Young's modulus (GPa), Poisson's ratio, source."""

    name: str
    E_gpa: float
    nu: float
    source: str = ""


#: Dense (fully solid) material constants of the printable biomaterials. Values vary with the
#: process and grade: these are the handbook figures the sources give, for comparison only.
MATERIALS = {
    "ti64": Material("Ti-6Al-4V", 113.8, 0.342,
                     "Boyer, Welsch & Collings, Materials Properties Handbook: Titanium Alloys, ASM 1994 "
                     "(annealed Ti-6Al-4V, E 110-114 GPa, nu 0.34)"),
    "pcl": Material("PCL", 0.40, 0.30,
                    "Woodruff & Hutmacher 2010, Prog Polym Sci 35:1217 (E 0.21-0.44 GPa); nu assumed 0.30"),
    "pla": Material("PLA", 3.5, 0.36,
                    "Farah, Anderson & Langer 2016, Adv Drug Deliv Rev 107:367 (PLLA E about 3.5 GPa, nu 0.36)"),
    "peek": Material("PEEK", 3.6, 0.40,
                     "Kurtz & Devine 2007, Biomaterials 28:4845 (E 3-4 GPa, nu about 0.4)"),
    "ha": Material("hydroxyapatite", 114.0, 0.28,
                   "Katz & Ukraincik 1971, J Biomech 4:221 (dense HA, E about 114 GPa, nu about 0.27-0.28)"),
    "tcp": Material("beta-TCP", 90.0, 0.28,
                    "Liang, Rulis & Ching 2010, Acta Biomater 6:3763 (dense beta-TCP, E about 90 GPa); "
                    "nu taken as HA's"),
    "cocr": Material("CoCrMo (ASTM F75)", 210.0, 0.30,
                     "Niinomi 2008, J Mech Behav Biomed Mater 1:30 (CoCr alloys, E 200-230 GPa, nu 0.3)"),
    "ta": Material("tantalum", 186.0, 0.34,
                   "CRC Handbook of Chemistry and Physics (Ta, E 186 GPa, nu 0.34)"),
}

#: Apparent moduli of bone (GPa) the scaffold is compared against.
BONE_BANDS = {
    "trabecular": (0.1, 2.0, "Morgan, Bayraktar & Keaveny 2003, J Biomech 36:897 (0.1-3 GPa by site); "
                             "Gibson & Ashby, Cellular Solids, 2nd ed. 1997"),
    "cortical": (15.0, 20.0, "Reilly & Burstein 1975, J Biomech 8:393 (femoral cortex, longitudinal "
                             "17 GPa, transverse 11.5 GPa)"),
}


def material(name: str | None = None, *, E: float | None = None, nu: float | None = None) -> Material:
    """The material of a solve, from the table or from E and nu.

    Parameters
    ----------
    name : str, optional
        A key of :data:`MATERIALS` (``ti64 pcl pla peek ha tcp cocr ta``).
    E : float, GPa, optional
        Young's modulus (instead of a name, or overriding its modulus).
    nu : float, optional
        Poisson's ratio, in (-1, 0.5).

    Raises
    ------
    ScaffoldError
        An unknown name, a non-positive modulus, or nu outside (-1, 0.5).
    """
    if name is None and E is None:
        name = "ti64"
    if name is not None:
        key = str(name).lower()
        if key not in MATERIALS:
            raise ScaffoldError(f"unknown material {name!r}; use one of {', '.join(MATERIALS)} or --E GPA --nu V")
        base = MATERIALS[key]
    else:
        base = Material("custom", float("nan"), 0.3, "given on the command line")
    E_gpa = base.E_gpa if E is None else float(E)
    nu_v = base.nu if nu is None else float(nu)
    if not (np.isfinite(E_gpa) and E_gpa > 0):
        raise ScaffoldError(f"--E must be a positive modulus in GPa, got {E!r}")
    if not (np.isfinite(nu_v) and -1.0 < nu_v < 0.5):
        raise ScaffoldError(f"--nu must lie in (-1, 0.5) (0.5 is incompressible, which a displacement "
                            f"solver cannot take), got {nu!r}")
    if (E is not None or nu is not None) and name is not None:
        return Material(base.name + " (modified)", E_gpa, nu_v, base.source + "; modified on the command line")
    return Material(base.name, E_gpa, nu_v, base.source)


# ----------------------------------------------------------------------------- the element


def isotropic_tensor(E: float, nu: float) -> np.ndarray:
    """(6, 6) float ndarray, GPa: the isotropic stiffness in Voigt notation (engineering shear)."""
    lam = E * nu / ((1 + nu) * (1 - 2 * nu))
    mu = E / (2 * (1 + nu))
    C = np.zeros((6, 6))
    C[:3, :3] = lam
    C[np.arange(3), np.arange(3)] = lam + 2 * mu
    C[np.arange(3, 6), np.arange(3, 6)] = mu
    return C


def strain_matrix(h: float, xi) -> np.ndarray:
    """(6, 24) float ndarray, 1/mm: strain of a cube voxel of side `h` at natural point `xi` in [-1, 1]^3.

    Degrees of freedom are ordered corner-major (3 a + c for corner a, component c).
    """
    s = 2 * CORNERS - 1  # corner signs in natural coordinates
    xi = np.asarray(xi, float)
    B = np.zeros((6, 24))
    for a in range(8):
        f = 1 + s[a] * xi  # the three linear factors of N_a
        dN = np.array([s[a, 0] * f[1] * f[2], f[0] * s[a, 1] * f[2], f[0] * f[1] * s[a, 2]]) / 8 * (2 / h)
        c = 3 * a
        B[0, c], B[1, c + 1], B[2, c + 2] = dN
        B[3, c + 1], B[3, c + 2] = dN[2], dN[1]  # 2 eps_yz = du_y/dz + du_z/dy
        B[4, c + 0], B[4, c + 2] = dN[2], dN[0]
        B[5, c + 0], B[5, c + 1] = dN[1], dN[0]
    return B


def element_stiffness(E: float, nu: float, h: float) -> np.ndarray:
    """(24, 24) float ndarray, GPa mm: stiffness of a cube voxel of side `h`.

    2x2x2 Gauss points integrate it exactly: the integrand is at most quadratic per direction.
    """
    D = isotropic_tensor(E, nu)
    g = 1 / np.sqrt(3)
    K = np.zeros((24, 24))
    for p in CORNERS:
        B = strain_matrix(h, (2 * p - 1) * g)
        K += B.T @ D @ B
    return K * (h / 2) ** 3


def macro_displacements(h: float) -> np.ndarray:
    """(6, 24) float ndarray, mm: the corner displacements ``E x`` of each unit Voigt strain."""
    x = CORNERS * h
    return np.stack([x @ strain_tensor(k).T for k in range(6)]).reshape(6, 24)


# ----------------------------------------------------------------------------- the voxel model


@dataclass
class VoxelModel:
    """Solid voxels on a periodic node grid (a box sample is padded by one void layer).

    Attributes
    ----------
    shape : (3,) ints
        The node grid (= the element grid, periodic).
    solid : (n1, n2, n3) bool ndarray
        Solid elements, element (i, j, k) spanning nodes (i..i+1, j..j+1, k..k+1) mod shape.
    conn : (8, ns) int64 ndarray
        Flat node index of each corner of each solid element.
    ke : (24, 24) float ndarray
    h : float, mm
    """

    shape: tuple
    solid: np.ndarray
    conn: np.ndarray
    ke: np.ndarray
    h: float
    material: Material
    active: np.ndarray = field(init=False)

    def __post_init__(self):
        n = int(np.prod(self.shape))
        self.active = np.bincount(self.conn.ravel(), minlength=n) > 0


def voxel_model(solid, h: float, mat: Material, *, periodic: bool) -> VoxelModel:
    """The finite-element model of a solid voxel mask.

    Parameters
    ----------
    solid : (n1, n2, n3) bool ndarray
    h : float, mm
    mat : Material
    periodic : bool
        True: the node grid wraps (periodic homogenization). False: one void layer is added at
        the high end of every axis, so the (n+1)^3 nodes of a box sample never wrap.
    """
    solid = np.asarray(solid, bool)
    if not periodic:
        solid = np.pad(solid, ((0, 1),) * 3)
    shape = solid.shape
    idx = np.array(np.nonzero(solid), dtype=np.int64)  # (3, ns)
    conn = np.empty((8, idx.shape[1]), np.int64)
    dims = np.array(shape, np.int64)[:, None]
    for a, off in enumerate(CORNERS):
        p = (idx + off[:, None]) % dims
        conn[a] = np.ravel_multi_index(tuple(p), shape)
    return VoxelModel(shape, solid, conn, element_stiffness(mat.E_gpa, mat.nu, h), float(h), mat)


def gather(model: VoxelModel, u: np.ndarray) -> np.ndarray:
    """(m, 24, ns) element displacements from nodal ones `u` of shape (m, 3, N)."""
    m = u.shape[0]
    ue = u[:, :, model.conn]  # (m, 3, 8, ns)
    return ue.transpose(0, 2, 1, 3).reshape(m, 24, -1)


def apply_stiffness(model: VoxelModel, u: np.ndarray, element_extra: np.ndarray | None = None) -> np.ndarray:
    """K u, matrix-free: the NumPy reference of the element operator.

    Parameters
    ----------
    u : (m, 3, N) float ndarray, mm
        Nodal displacements of m load cases on the flat node grid.
    element_extra : (m, 24) float ndarray, optional
        A displacement added to every solid element (the macroscopic ``E x`` of periodic
        homogenization, which is not periodic and so not nodal).

    Returns
    -------
    (m, 3, N) float ndarray
    """
    m, _, n = u.shape
    ue = gather(model, u)
    if element_extra is not None:
        ue = ue + element_extra[:, :, None]
    fe = np.matmul(model.ke, ue)  # (m, 24, ns)
    fe = fe.reshape(m, 8, 3, -1)
    out = np.empty_like(u)
    flat = model.conn.ravel()
    for c in range(m):
        for d in range(3):
            out[c, d] = np.bincount(flat, weights=fe[c, :, d, :].ravel(), minlength=n)
    return out


# ----------------------------------------------------------------------------- preconditioner


def reference_symbol_inverse(shape, ke: np.ndarray) -> np.ndarray:
    """(n1, n2, n3//2+1, 3, 3) float32: the inverse Fourier symbol of the full-grid operator.

    The all-solid periodic operator is a convolution with a 27-point stencil of 3x3 blocks,
    ``S[d] = sum over corners A - B = d of Ke[B, A]``; its symbol at a frequency is the 3x3
    matrix ``sum_d S[d] exp(2 pi i q.d / n)``. The zero frequency (rigid translation) is
    singular and gets 0: the preconditioner is the pseudo-inverse.
    """
    q = [np.fft.fftfreq(n) for n in shape[:2]] + [np.fft.rfftfreq(shape[2])]
    grids = np.meshgrid(*q, indexing="ij", sparse=True)
    blocks = ke.reshape(8, 3, 8, 3)
    sym = np.zeros(tuple(len(v) for v in q) + (3, 3), complex)
    stencil = {}
    for b in range(8):
        for a in range(8):
            d = tuple(CORNERS[a] - CORNERS[b])
            stencil[d] = stencil.get(d, 0) + blocks[b, :, a, :]
    for d, S in stencil.items():
        phase = np.exp(2j * np.pi * (grids[0] * d[0] + grids[1] * d[1] + grids[2] * d[2]))
        sym += phase[..., None, None] * S
    sym = sym.real  # the stencil is centro-symmetric (S[-d] = S[d]): the symbol is real
    sym[0, 0, 0] = np.eye(3)
    inv = np.linalg.inv(sym)
    inv[0, 0, 0] = 0.0
    return inv.astype(np.float32)


def fft_preconditioner(model: VoxelModel, free: np.ndarray):
    """M r = P F^-1 Khat^-1 F P r, P the mask of the free nodes: SPD on the free nodes."""
    import scipy.fft as sfft

    inv = reference_symbol_inverse(model.shape, model.ke)
    shape = model.shape

    def apply(r):
        out = np.empty_like(r)
        for c in range(r.shape[0]):
            rh = sfft.rfftn((r[c] * free).reshape((3,) + shape), axes=(1, 2, 3), workers=-1)
            zh = np.einsum("...ij,j...->i...", inv, rh)
            out[c] = sfft.irfftn(zh, s=shape, axes=(1, 2, 3), workers=-1).reshape(3, -1) * free
        return out

    return apply


def pcg(apply, precond, b: np.ndarray, free: np.ndarray, *, scale: np.ndarray, tol: float = 1e-8,
        maxiter: int = 2000):
    """Preconditioned conjugate gradients on m systems at once (a block of load cases).

    Parameters
    ----------
    apply : callable
        (m, 3, N) -> K x (m, 3, N).
    precond : callable
    b : (m, 3, N) float ndarray
        Right-hand sides, zero on fixed nodes.
    free : (N,) bool ndarray
        The unknowns; K x is masked to them.
    scale : (m,) floats
        The norm a residual is measured against (the load's scale, so that a zero load is
        converged at once).
    tol : float
        Stop when every ``|r| / scale`` is below it.

    Returns
    -------
    x, iterations, relative residuals (m,)
    """
    x = np.zeros_like(b)
    r = b * free
    z = precond(r)
    p = z.copy()
    rz = np.einsum("mcn,mcn->m", r, z)
    res = np.linalg.norm(r.reshape(len(b), -1), axis=1) / scale
    it = 0
    while np.any(res > tol) and it < maxiter:
        q = apply(p) * free
        pq = np.einsum("mcn,mcn->m", p, q)
        live = (res > tol) & (pq > 0)
        alpha = np.where(live, rz / np.where(pq > 0, pq, 1), 0.0)
        x += alpha[:, None, None] * p
        r -= alpha[:, None, None] * q
        z = precond(r)
        rz_new = np.einsum("mcn,mcn->m", r, z)
        beta = np.where(live, rz_new / np.where(rz != 0, rz, 1), 0.0)
        p = z + beta[:, None, None] * p
        rz = rz_new
        res = np.where(live, np.linalg.norm(r.reshape(len(b), -1), axis=1) / scale, res)
        it += 1
    return x, it, res


# ----------------------------------------------------------------------------- homogenization


@dataclass
class Homogenization:
    """The effective stiffness of a sample and how it was solved."""

    stiffness: np.ndarray  # (6, 6) GPa
    boundary_conditions: str
    solid_fraction: float
    iterations: int
    residual: float
    seconds: float
    backend: str = "numpy"


def _operator(model, backend):
    if backend == "numpy":
        return lambda u, extra=None: apply_stiffness(model, u, extra)
    if backend == "opencl":
        from .mechanics_cl import StiffnessOperator

        return StiffnessOperator(model)
    raise ValueError(f"backend must be 'numpy' or 'opencl', got {backend!r}")


def check_solid(solid) -> np.ndarray:
    """`solid` as a 3-D bool array with at least one solid voxel, or a ScaffoldError."""
    solid = np.asarray(solid)
    if solid.ndim != 3 or min(solid.shape) < 1:
        raise ScaffoldError(f"a mechanics sample is a 3-D voxel volume, got shape {solid.shape}")
    solid = solid.astype(bool)
    if not solid.any():
        raise ScaffoldError("the volume holds no solid voxel: nothing carries load")
    return solid


def homogenize(solid, h: float, mat: Material, *, boundary: str = "periodic", tol: float = 1e-8,
               maxiter: int = 2000, backend: str = "numpy") -> Homogenization:
    """The effective 6x6 stiffness of a voxel sample (Voigt, GPa).

    Parameters
    ----------
    solid : (n1, n2, n3) bool ndarray
    h : float, mm
    mat : Material
    boundary : {"periodic", "kinematic"}
        Periodic fluctuations (a periodic or box sample) or uniform displacement ``u = E x`` on
        the faces of the box (a sample that is not periodic).
    tol : float
        Relative residual of the CG solves.
    backend : {"numpy", "opencl"}
        Where the element operator runs.
    """
    t0 = time.perf_counter()
    solid = check_solid(solid)
    if boundary not in ("periodic", "kinematic"):
        raise ValueError(f"boundary must be 'periodic' or 'kinematic', got {boundary!r}")
    periodic = boundary == "periodic"
    model = voxel_model(solid, h, mat, periodic=periodic)
    n = int(np.prod(model.shape))
    ns = model.conn.shape[1]
    u0e = macro_displacements(h)  # (6, 24)
    op = _operator(model, backend)
    if periodic:
        free = model.active.astype(float)
        b = -op(np.zeros((6, 3, n)), u0e)
        extra = u0e
        base = np.zeros((6, 3, n))
    else:
        # u = E x at every node; the box's faces keep it, the inside nodes are solved for
        idx = np.array(np.unravel_index(np.arange(n), model.shape), float) * h  # (3, N)
        base = np.stack([(strain_tensor(k) @ idx) for k in range(6)])  # (6, 3, N)
        inner = np.ones(model.shape, bool)
        inner[0, :, :] = inner[-1, :, :] = inner[:, 0, :] = inner[:, -1, :] = False
        inner[:, :, 0] = inner[:, :, -1] = False
        free = (model.active & inner.ravel()).astype(float)
        b = -op(base)
        extra = None
    scale = np.sqrt(ns) * np.linalg.norm(model.ke @ u0e.T, axis=0)
    precond = fft_preconditioner(model, free)
    x, iterations, res = pcg(op, precond, b * free, free, scale=scale, tol=tol, maxiter=maxiter)
    u = base + x
    ue_sum = gather(model, u).sum(axis=2)  # (6, 24)
    if extra is not None:
        ue_sum = ue_sum + ns * extra
    Bc = strain_matrix(h, (0.0, 0.0, 0.0))
    total = solid.size  # the sample's voxels (before the padding layer)
    mean_strain = (Bc @ ue_sum.T) / total  # (6 strain, 6 cases)
    C = isotropic_tensor(mat.E_gpa, mat.nu) @ mean_strain
    C = 0.5 * (C + C.T)  # symmetric up to the solver's tolerance
    return Homogenization(C, boundary, float(solid.mean()), int(iterations), float(res.max()),
                          time.perf_counter() - t0, backend)


def strain_tensor(k: int) -> np.ndarray:
    """(3, 3) float ndarray: the unit Voigt strain `k` as a tensor (engineering shear strain 1)."""
    eps = np.zeros((3, 3))
    if k < 3:
        eps[k, k] = 1.0
    else:
        i, j = [(1, 2), (0, 2), (0, 1)][k - 3]
        eps[i, j] = eps[j, i] = 0.5
    return eps
