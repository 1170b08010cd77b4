"""Stiffness of a scaffold from its own voxels: a matrix-free voxel finite-element solver.

One trilinear hexahedron per solid voxel (exact 2x2x2 Gauss stiffness); void voxels carry
no unknowns (a node is an unknown only when a solid voxel touches it). The system is
solved by preconditioned conjugate gradients, the load cases in blocks (:func:`homogenize`). Two
preconditioners (:func:`make_preconditioner`):

- ``multigrid`` (the default): a V-cycle over Galerkin coarse grids of the solid itself
  (:mod:`~implicit_scaffold.measure.multigrid`, ParOSol's approach for bone micro-FE). Its count
  stays flat where struts are thin: a 30 % solid Voronoi scaffold at 0.04 mm took 23, 28
  and 34 iterations at 32^3, 64^3 and 128^3 (six load cases) with degree-3 smoothing on every
  coarse level; with degree 1 on the first one (cheaper cycles) and the CG's first products in
  float, 40 at 128^3 and 46 at 200^3.
- ``fft``: the inverse of the same finite-element operator on the full (all-solid)
  periodic grid, which Fourier diagonalises, with Green-Jacobi scaling ("Fourier-accelerated
  nodal solvers": Leuschner & Fritzen 2018, Comput Mech 62:359; Ladecky et al. 2023). Flat
  as a pore cell is refined (a 20 % spherical pore: 20 and 25 iterations at 16 and 32
  voxels across), but it grows on thin struts, where the void's infinite contrast is felt
  (the same scaffold: 154 iterations at 32^3, 288 at 64^3; muGrid's own Green-Jacobi FFT
  solver needs 280-292 per load case on the same 64^3 voxels).

Three problems:

- periodic homogenization (six unit strains, the fluctuation periodic): the effective 6x6
  stiffness of a periodic or box sample;
- kinematic homogenization (uniform displacement ``u = E x`` on the box's faces) where the
  sample is not periodic (a patient-shaped scaffold, a bone);
- uniaxial compression between rigid bonded platens (ISO 13314's setting): apparent modulus.

Pieces that share no node are independent systems: the kinematic homogenization and the compression
solve each on its own box (:func:`independent_pieces`), the small ones together with an exact
preconditioner (:func:`direct_preconditioner`), where the multigrid's coarse grids would tie them together
(the data folder's CT at 1.95 mm: 191 homogenization iterations apart against 574 as one system).

Units: mm and GPa (so forces are in kN: GPa times mm^2). Voigt order xx, yy, zz, yz, xz, xy with engineering shear strains.
"""
from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import ScaffoldError, round_down
from ..run.memory import keeping_freed_memory

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


#: Dense (fully solid) material constants of the printable biomaterials, and of bone tissue. Values
#: vary with the process and grade: these are the handbook figures the sources give, for comparison only.
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
    # not printed: the tissue of a bone measured from its micro-CT, whose apparent modulus then stands
    # beside the bone bands as the bone's own
    "bone": Material("trabecular bone tissue", 18.0, 0.30,
                     "Bayraktar et al. 2004, J Biomech 37:27 (human femoral trabecular tissue, E 18.0 +- 2.8 GPa); "
                     "nu 0.3 as micro-FE studies take it"),
}

#: Apparent moduli of bone (GPa) the scaffold is compared against.
BONE_BANDS = {
    "trabecular": (0.1, 2.0, "Morgan, Bayraktar & Keaveny 2003, J Biomech 36:897 (0.1-3 GPa by site); "
                             "Gibson & Ashby, Cellular Solids, 2nd ed. 1997"),
    "cortical": (15.0, 20.0, "Reilly & Burstein 1975, J Biomech 8:393 (femoral cortex, longitudinal "
                             "17 GPa, transverse 11.5 GPa)"),
}


@dataclass(frozen=True)
class DensityModulus:
    """Trabecular bone's on-axis apparent modulus against its apparent density: ``E = a ρ^b``.

    Attributes
    ----------
    site : str
    a_mpa : float, MPa
        The leading coefficient (ρ in g/cm³).
    b : float
        The exponent.
    source : str
    """

    site: str
    a_mpa: float
    b: float
    source: str = ""

    def modulus_gpa(self, density) -> np.ndarray:
        """Apparent modulus (GPa, float64) at apparent densities `density` (g/cm³; below 0 counts as 0)."""
        rho = np.clip(np.asarray(density, np.float64), 0.0, None)
        return 1e-3 * self.a_mpa * rho ** self.b

    def describe(self) -> str:
        return f"E = {self.a_mpa:g} rho^{self.b:g} MPa ({self.site}; {self.source})"


_MORGAN_2003 = ("Morgan, Bayraktar & Keaveny 2003, J Biomech 36:897-904, power-law regressions of on-axis "
                "modulus against apparent density (g/cm3)")

#: Site-specific density-modulus relations of human trabecular bone (Morgan, Bayraktar &
#: Keaveny 2003, J Biomech 36:897-904, doi:10.1016/s0021-9290(03)00071-x): 142 specimens, vertebra
#: (n = 61), proximal tibia (31), greater trochanter (23), femoral neck (27); the exponents range
#: 1.49-2.18 (abstract), the sites differ in their leading coefficients. ``--site`` picks one.
BONE_DENSITY_MODULUS = {
    "pooled": DensityModulus("pooled (all four sites)", 8920.0, 1.83, _MORGAN_2003),
    "vertebra": DensityModulus("vertebra", 4730.0, 1.56, _MORGAN_2003),
    "proximal-tibia": DensityModulus("proximal tibia", 15520.0, 1.93, _MORGAN_2003),
    "greater-trochanter": DensityModulus("greater trochanter", 15010.0, 2.18, _MORGAN_2003),
    "femoral-neck": DensityModulus("femoral neck", 6850.0, 1.49, _MORGAN_2003),
}


def density_modulus(site: str = "pooled") -> DensityModulus:
    """The density-modulus relation of `site` (a :data:`BONE_DENSITY_MODULUS` key); ScaffoldError otherwise."""
    key = str(site).strip().lower().replace("_", "-").replace(" ", "-")
    if key not in BONE_DENSITY_MODULUS:
        raise ScaffoldError(f"unknown --site {site!r}; use one of {', '.join(BONE_DENSITY_MODULUS)} "
                            "(Morgan et al. 2003)")
    return BONE_DENSITY_MODULUS[key]


def material(name: str | None = None, *, E: float | None = None, nu: float | None = None) -> Material:
    """The material of a solve, from the table or from E and nu.

    Parameters
    ----------
    name : str, optional
        A key of :data:`MATERIALS` (``ti64 pcl pla peek ha tcp cocr ta bone``).
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


#: the CG's relative residual by default, where the energy accuracy :data:`ACCURACY` has not stopped it
#: sooner (:func:`measure`); alone, the benchmark's 128^3 scaffold: its tensor within 1.5e-11 of a solve
#: to 1e-10 in the energy form, 2.6e-7 as the mean stress; far below the voxel discretisation's error
#: (README, Mechanics, the stop)
TOL = 1e-6
#: the tolerances a user may ask for (``--mechanics-tol``): below 1e-12 the residual meets double
#: precision's rounding; at 1e-2 a compression of a 128^3 crop of the lumbar trabecular micro-CT
#: in ../shared/data gave its modulus 1.2 % off (3.7e-4 at 1e-3; a throw-away script), as much as the
#: voxels' own error (``bench_mechanics.py --bone 128``: 5.5e-5 at 1e-3 on the central crop)
TOL_RANGE = (1e-12, 1e-3)


def solve_goal(tol: float | None) -> float:
    """The relative residual a solve of :func:`measure` stops at, at the latest: `tol` as given, or
    :data:`TOL` for the default stop (None, where the energy accuracy may stop it sooner)."""
    return TOL if tol is None else float(tol)


def solve_accuracy(tol: float | None) -> float | None:
    """The energy accuracy a solve of :func:`measure` stops at when it comes first: :data:`ACCURACY` for the
    default stop (`tol` None), none when a tolerance is given (the residual alone)."""
    return ACCURACY if tol is None else None


def check_tol(tol) -> float | None:
    """The CG's relative residual `tol` as a float, or None: the default stop (:func:`measure`).

    Raises
    ------
    ScaffoldError
        `tol` outside :data:`TOL_RANGE`, in one line.
    """
    if tol is None:
        return None
    lo, hi = TOL_RANGE
    try:
        value = float(tol)
    except (TypeError, ValueError):
        value = float("nan")
    if not lo <= value <= hi:
        raise ScaffoldError(f"--mechanics-tol must be a relative residual in [{lo:g}, {hi:g}] (e.g. 1e-4), got {tol!r}")
    return value


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

    Nothing per solid voxel is kept beyond the mask: the element connectivity (8 flat indices,
    64 bytes a solid voxel) is made on demand (:attr:`conn`, for the NumPy reference operator),
    and the solver's per-node sums (right-hand side, diagonal, mean strain) read the mask
    shifted to each corner (:meth:`corner`).

    Attributes
    ----------
    shape : (3,) ints
        The node grid (= the element grid, periodic).
    solid : (n1, n2, n3) bool ndarray
        Solid elements, element (i, j, k) spanning nodes (i..i+1, j..j+1, k..k+1) mod shape.
    ke : (24, 24) float ndarray
    h : float, mm
    active : (N,) bool ndarray
        The nodes a solid voxel touches (the unknowns).
    corner_code : (N,) uint8 ndarray
        Each node's corner bits: bit a set where the node is corner a of a solid voxel.
    """

    shape: tuple
    solid: np.ndarray
    ke: np.ndarray
    h: float
    material: Material
    active: np.ndarray = field(init=False)
    corner_code: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        # each node's 8 corner bits: bit a set where the node is corner a of a solid voxel (element_loads' table
        # index, made once: 8 shifted copies of the mask a call, 8 calls a homogenization, took 0.28 s at 128^3)
        code = np.zeros(self.shape, np.uint8)
        for a in range(8):
            code |= self.corner(a).view(np.uint8) << np.uint8(a)
        self.corner_code = code.ravel()
        self.active = self.corner_code != 0

    @property
    def solid_voxels(self) -> int:
        return int(np.count_nonzero(self.solid))

    def corner(self, a: int) -> np.ndarray:
        """(n1, n2, n3) bool ndarray: the nodes that are corner `a` of a solid voxel (node
        ``p`` is corner ``a`` of the voxel at ``p - CORNERS[a]``)."""
        return np.roll(self.solid, tuple(int(o) for o in CORNERS[a]), axis=(0, 1, 2))

    @property
    def conn(self) -> np.ndarray:
        """(8, ns) int64 ndarray: flat node index of each corner of each solid element (made on
        each call: the NumPy reference's, not the solver's)."""
        idx = np.array(np.nonzero(self.solid), dtype=np.int64)  # (3, ns)
        conn = np.empty((8, idx.shape[1]), np.int64)
        dims = np.array(self.shape, np.int64)[:, None]
        for a, off in enumerate(CORNERS):
            conn[a] = np.ravel_multi_index(tuple((idx + off[:, None]) % dims), self.shape)
        return conn


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
    return VoxelModel(solid.shape, np.ascontiguousarray(solid), element_stiffness(mat.E_gpa, mat.nu, h), float(h), mat)


def gather(model: VoxelModel, u: np.ndarray) -> np.ndarray:
    """(m, 24, ns) element displacements from nodal ones `u` of shape (m, 3, N)."""
    m = u.shape[0]
    ue = u[:, :, model.conn]  # (m, 3, 8, ns)
    return ue.transpose(0, 2, 1, 3).reshape(m, 24, -1)


def element_strains(model: VoxelModel, u: np.ndarray) -> np.ndarray:
    """(6, ns) Voigt strains at the centres of the solid voxels (in ``np.nonzero(model.solid)``'s
    order) from nodal displacements `u` (3, N), as ``strain_matrix(h, 0) @ gather(model, u[None])[0]``
    without the (24, ns) gather."""
    B = strain_matrix(model.h, (0.0, 0.0, 0.0))
    grid = u.reshape((3,) + tuple(model.shape))
    eps = np.zeros((6, model.solid_voxels))
    for a in range(8):
        ua = np.roll(grid, tuple(-int(o) for o in CORNERS[a]), axis=(1, 2, 3))[:, model.solid]  # (3, ns)
        eps += B[:, 3 * a: 3 * a + 3] @ ua
    return eps


def corner_sums(model: VoxelModel, u: np.ndarray, live: np.ndarray | None = None) -> np.ndarray:
    """(m, 24) sums over the solid voxels of their element displacements (corner-major, as
    ``gather(model, u).sum(axis=2)``), from nodal ones `u` (m, 3, N), without the (m, 24, ns) gather;
    with `live` (flat node indices, every node a solid voxel touches among them), from `u` (m, 3, len(live))
    on those nodes only."""
    m = u.shape[0]
    flat = u.reshape(m * 3, -1)
    out = np.empty((m, 8, 3))
    for a in range(8):
        corner = model.corner(a).ravel()
        out[:, a, :] = (flat @ (corner if live is None else corner[live]).astype(flat.dtype)).reshape(m, 3)
    return out.reshape(m, 24)


def affine_corner_sums(model: VoxelModel, cases) -> np.ndarray:
    """(m, 24) :func:`corner_sums` of the displacements ``E x`` of the unit Voigt strains `cases` (as
    :func:`_affine` gives them, x the node index times h, which never wraps on a box sample's padded grid),
    without a whole-grid vector: over the solid voxels, corner a sums ``E h (i + CORNERS[a])``."""
    index = np.nonzero(model.solid)
    ns = index[0].size
    total = np.array([float(np.sum(i, dtype=np.int64)) for i in index])  # (3,) the voxels' summed indices
    out = np.empty((len(cases), 8, 3))
    for c, k in enumerate(cases):
        eps = strain_tensor(k)
        for a in range(8):
            out[c, a] = model.h * eps @ (total + ns * CORNERS[a])
    return out.reshape(len(cases), 24)


def element_loads(model: VoxelModel, fe: np.ndarray, nodes: np.ndarray | None = None) -> np.ndarray:
    """(m, 3, N) nodal sums of one element force vector per load case, the same in every solid
    voxel (``fe``: (m, 24), corner-major), as ``apply_stiffness`` assembles a uniform ``element_extra``;
    with `nodes` (flat node indices), (m, 3, len(nodes)): those nodes' sums only."""
    from .fused import lookup

    m = fe.shape[0]
    # a node's load is the sum of fe's corner blocks over the corners it is of solid voxels: one of
    # 256 values per case and component, by its 8 corner bits (one lookup pass, not 8 masked adds
    # a case and component: 0.19 s a case on the 128^3 benchmark scaffold, and the solver makes
    # each case's again to check its residual)
    bits = (np.arange(256)[:, None] >> np.arange(8)) & 1  # (256, 8)
    table = np.einsum("ka,mad->mdk", bits.astype(float), np.asarray(fe, float).reshape(m, 8, 3))
    return lookup(table, model.corner_code if nodes is None else model.corner_code[nodes])


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


def diagonal(model: VoxelModel) -> np.ndarray:
    """(3, N) float ndarray: the diagonal of K (0 on nodes no solid voxel touches)."""
    return element_loads(model, np.diag(model.ke)[None])[0]


def fft_preconditioner(model: VoxelModel, free: np.ndarray, *, single: bool = False, jacobi: bool = True):
    """M r = P F^-1 Khat^-1 F P r, P the mask of the free nodes: SPD on the free nodes.

    `single` runs the FFTs in float32 (twice as fast; enough for a CG to 1e-6, whose
    preconditioner need only be close to K^-1, but it blurs M's symmetry below 1e-7).
    """
    import scipy.fft as sfft

    inv = reference_symbol_inverse(model.shape, model.ke)
    real = np.float32 if single else np.float64
    # the symbol's inverse is symmetric: its 6 distinct entries, each a full frequency grid
    pairs = [(0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)]
    blocks = {pq: np.ascontiguousarray(inv[..., pq[0], pq[1]], real) for pq in pairs}
    del inv
    shape = model.shape
    # Green-Jacobi scaling (Ladecky et al. 2023): D^-1/2 K_ref^-1 D^-1/2 with D the ratio of
    # K's diagonal to the reference's, so that nodes with few solid voxels around them (a thin
    # strut's surface) are not over-corrected
    weight = free * np.sqrt(np.diag(model.ke).reshape(8, 3).sum(axis=0)[:, None] / np.maximum(diagonal(model), 1e-300))
    if not jacobi:
        weight = free * np.ones((3, 1))

    def apply(r):
        out = np.empty_like(r)
        for c in range(r.shape[0]):
            x = (r[c] * weight).astype(real, copy=False).reshape((3,) + shape)
            # one thread: SciPy's pocketfft pool (workers > 1) joins its threads at every fork, and a
            # fork after it hung there (a slab export's worker start, in CI: 12 minutes, std::thread::join)
            rh = sfft.rfftn(x, axes=(1, 2, 3))
            del x
            z0 = blocks[0, 0] * rh[0] + blocks[0, 1] * rh[1] + blocks[0, 2] * rh[2]
            z1 = blocks[0, 1] * rh[0] + blocks[1, 1] * rh[1] + blocks[1, 2] * rh[2]
            rh[2] = blocks[0, 2] * rh[0] + blocks[1, 2] * rh[1] + blocks[2, 2] * rh[2]
            rh[0], rh[1] = z0, z1
            del z0, z1
            out[c] = sfft.irfftn(rh, s=shape, axes=(1, 2, 3)).reshape(3, -1) * weight
        return out

    return apply


def stiffness_matrix(model: VoxelModel, free: np.ndarray):
    """``F K F`` on the free unknowns, assembled: a scipy CSR matrix and the unknowns' flat indices
    (``d * N + node``, the (3, N) layout of the solver's vectors), for a small model only (576 entries
    a solid voxel before they are summed).

    Parameters
    ----------
    model : VoxelModel
    free : (N,) or (3, N) array of 0 and 1
    """
    from scipy.sparse import coo_matrix

    n = int(np.prod(model.shape))
    dofs = np.flatnonzero(np.broadcast_to(np.asarray(free).reshape(-1, n), (3, n)).ravel() > 0)
    where = np.full(3 * n, -1, np.int64)
    where[dofs] = np.arange(dofs.size)
    conn = model.conn  # (8, ns)
    # local unknown 3 a + d of a voxel is unknown d N + conn[a] of the grid
    local = where[(np.arange(3)[None, :, None] * n + conn[:, None, :]).reshape(8, 3, -1)]  # (8, 3, ns)
    del conn, where
    K = None
    # summed a pair of corners at a time: the 576 entries a voxel, all at once, peaked at 186 MiB
    # for 10,084 voxels (the summed matrix: 37 MB)
    for a in range(8):
        for b in range(8):
            rows = np.broadcast_to(local[a][:, None, :], (3, 3, local.shape[2]))
            cols = np.broadcast_to(local[b][None, :, :], rows.shape)
            keep = (rows >= 0) & (cols >= 0)
            values = np.broadcast_to(model.ke[3 * a:3 * a + 3, 3 * b:3 * b + 3, None], rows.shape)[keep]
            part = coo_matrix((values, (rows[keep], cols[keep])), shape=(dofs.size, dofs.size)).tocsr()
            K = part if K is None else K + part
    return K, dofs


#: the share of the largest diagonal entry added to the diagonal of the direct preconditioner
DIRECT_SHIFT = 1e-10


def direct_preconditioner(model: VoxelModel, free: np.ndarray):
    """The exact inverse of ``F K F`` (a sparse LU of :func:`stiffness_matrix`): the CG then ends in a
    step or two. For small models (:data:`DIRECT_VOXELS`): many small pieces solved together, whose
    union a V-cycle serves badly (its coarse grids tie pieces that share no node).

    A system that keeps rigid motions (the platens' sliding ones, which carry no force) is factored
    with its diagonal raised by :data:`DIRECT_SHIFT` of its largest entry: CG sees the inverse of an
    SPD matrix, and its iterates keep out of those motions (a consistent system's right-hand side has
    none of them)."""
    from scipy.sparse import identity
    from scipy.sparse.linalg import splu

    K, dofs = stiffness_matrix(model, free)
    K = K + identity(K.shape[0], format="csr") * (DIRECT_SHIFT * K.diagonal().max())
    lu = splu(K.tocsc())  # COLAMD: on 1,500 voxels of small pieces 0.63 s against MMD_AT_PLUS_A's 1.98 s
    del K

    def apply(r):
        m = r.shape[0]
        flat = r.reshape(m, -1)
        out = np.zeros(r.shape, np.float64)
        view = out.reshape(m, -1)
        for c in range(m):
            view[c, dofs] = lu.solve(np.asarray(flat[c, dofs], np.float64))
        return out.astype(r.dtype, copy=False)

    return apply


#: a solve to a tolerance of at least this runs its preconditioner in float, and a homogenization
#: its first CG products too (then the true residuals in double): float's rounding, some 1e-7 of a
#: product, stays under it
FLOAT_TOL = 1e-7


def make_preconditioner(kind: str, model: VoxelModel, op, free: np.ndarray, tol: float,
                        slab_nodes: int | None = None):
    """The conjugate gradients' preconditioner for the system ``F K F`` of `model`.

    Parameters
    ----------
    kind : {"multigrid", "fft", "direct"}
        ``multigrid``: a V-cycle over Galerkin coarse grids of the solid itself
        (:class:`~implicit_scaffold.measure.multigrid.Multigrid`), whose iteration count stays nearly
        flat on thin struts; ``fft``: the reference-medium inverse
        (:func:`fft_preconditioner`), whose count grows there; ``direct``: the exact inverse, for
        small models (:func:`direct_preconditioner`).
    free : (N,) or (3, N) array of 0 and 1
        The unknowns.
    tol : float
        The solve's tolerance (from :data:`FLOAT_TOL` the preconditioner runs in float32: it need only be
        close to ``K^-1``, and CG to 1e-6 does not feel its rounding).
    slab_nodes : int, optional
        The multigrid's fine level by slabs of this many nodes (``Multigrid``'s `slab_nodes`).
    """
    if kind == "multigrid":
        from .multigrid import COARSEST_UNKNOWNS, Multigrid

        # a grid too thin to coarsen (an axis under 4 nodes, too many unknowns to solve
        # exactly) would get smoothing only: the FFT one serves it better
        if min(model.shape) >= 4 or 3 * np.prod(model.shape) <= COARSEST_UNKNOWNS:
            if tol >= FLOAT_TOL and hasattr(op, "single"):
                return Multigrid(model, op.single(), free, dtype=np.float32, slab_nodes=slab_nodes)
            return Multigrid(model, op, free, slab_nodes=slab_nodes)
        kind = "fft"
    if kind == "fft":
        return fft_preconditioner(model, free, single=tol >= FLOAT_TOL)
    if kind == "direct":
        return direct_preconditioner(model, free)
    raise ValueError(f"preconditioner must be 'multigrid', 'fft' or 'direct', got {kind!r}")


#: the solves run with BLAS on one thread (:func:`_one_blas_thread`); False: BLAS's own thread count
ONE_BLAS_THREAD = True


def _one_blas_thread(solve):
    """`solve` with BLAS (OpenBLAS's threads) held to the calling thread while it runs.

    The solve's BLAS calls are small (the coarsest level's pseudo-inverse once a V-cycle, the eigenvalue
    estimates' dot products), but after each one OpenBLAS's worker threads spin, waiting for more, on the
    cores the OpenCL operator runs on next: on the 128^3 benchmark scaffold (six cases, one run each, the
    machine shared) the fine product's median in the solve took 16.5 ms against 11.6 with BLAS on one
    thread (8.5 and 9.2 ms by itself in the same processes), and the solve 20.1 s against 15.6."""
    @functools.wraps(solve)
    def run(*args, **kwargs):
        if not ONE_BLAS_THREAD:
            return solve(*args, **kwargs)
        from threadpoolctl import threadpool_limits

        with threadpool_limits(1, user_api="blas"):
            return solve(*args, **kwargs)

    return run


def _keeping_freed_memory(solve):
    """`solve` (compress, homogenize, measure) inside :func:`~implicit_scaffold.run.memory.keeping_freed_memory`:
    what its steps free is kept for the next ones' arrays (on this project's virtual machine the default cube's
    ``measure`` took 155.1 and 162.2 s against 180.5 and 165.9, measured while NumPy still asked for huge pages:
    see :func:`~implicit_scaffold.run.memory.keeping_freed_memory` for what it gains without them). Not with fewer load cases a block than
    :data:`CASES_PER_BLOCK` (a budget too short for six): there the kept blocks that the next arrays could not
    reuse raised the 200^3 benchmark scaffold's peak from 842 to 993 MiB (one case a block, 226 to 292 bytes a
    solid voxel), for no time gained (78.8 against 76.2 s)."""
    @functools.wraps(solve)
    def run(*args, **kwargs):
        with keeping_freed_memory(kwargs.get("cases_per_block", CASES_PER_BLOCK) >= CASES_PER_BLOCK):
            return solve(*args, **kwargs)

    return run


def _norms(v: np.ndarray) -> np.ndarray:
    """(m,) Euclidean norms of the m load cases of `v` (m, 3, N), without a squared copy."""
    flat = v.reshape(len(v), -1)
    return np.sqrt(np.einsum("mk,mk->m", flat, flat))


#: :func:`pcg` makes a case's right-hand side again (its true residual) this many live nodes at a time
LOAD_CHUNK = 1 << 18


def pcg(apply, precond, b: np.ndarray, free: np.ndarray, *, scale: np.ndarray, tol: float = 1e-8,
        maxiter: int = 2000, progress=None, fast=None, rhs=None, cross: bool = False,
        energy: np.ndarray | None = None, accuracy: float | None = None, info: dict | None = None,
        whole: bool = True, slab_nodes: int | None = None, periodic: bool = False):
    """Preconditioned conjugate gradients on m systems at once (a block of load cases).

    Each system is its own CG (its own step lengths), run in step with the others so that one
    product serves them all; a converged one stops moving. The CG's vectors are kept on the
    live nodes only (those with a free unknown: at 30 % solid some 44 % of the grid), and
    updated in place by fused compiled passes (:mod:`~implicit_scaffold.measure.fused`): x, r, p and
    K p or the preconditioned residual. A product spreads p over the whole grid for `apply`
    and keeps K p's live nodes; a preconditioner with a ``compact(live)`` method
    (:class:`~implicit_scaffold.measure.multigrid.Multigrid`) takes and gives live-node vectors itself,
    another gets and gives whole-grid ones. The product and the step run one case at a time (a
    converged case gets no product), and the preconditioned residual is folded into p case by case
    as the preconditioner hands it over: besides x, r and p the CG holds one case's vector, not
    the block's (with the V-cycle's fine level a case at a time, six cases a block of the 128^3
    scaffold peaked 1,281 bytes per solid voxel above the start, against 2,144 before).

    Parameters
    ----------
    apply : callable
        (m, 3, N) -> K x (m, 3, N).
    precond : callable
    b : (m, 3, N) float ndarray, or callable
        Right-hand sides, zero on fixed nodes. Not kept: pass it without holding a reference
        of your own, and its memory is released once its live nodes are read. Or ``b(nodes)`` ->
        (m, 3, len(nodes)): their values on the flat node indices asked for (the live nodes), which
        spares the whole grid's (m, 3, N).
    free : (N,) or (3, N) float ndarray of 0 and 1
        The unknowns (per node, or per node and component); K x is masked to them.
    scale : (m,) floats
        The norm a residual is measured against (the load's scale, so that a zero load is
        converged at once).
    tol : float
        Stop when every ``|r| / scale`` is below it.
    progress : callable, optional
        Called after every iteration with (iteration, largest relative residual of the cases that stepped);
        when it has a true ``takes_energy`` attribute, also with their largest estimated relative energy
        error (inf before their estimates' steps; None without `accuracy`): :func:`_call_progress`.
    fast : callable, optional
        A cheaper approximation of `apply` (the OpenCL operator in float: half the time of
        double) for the first iterations, to :func:`fast_goal` (or until a case
        stalls on its rounding, :data:`FAST_STALL`). Then each case's residual ``F (b - K x)``
        is computed anew with `apply` and `rhs` and replaces the recurrence's, and a case still
        above `tol` restarts from there (p = z) on `apply`'s products, unless (with `accuracy`) that
        true residual's own estimate, ``r.z`` over the fast CG's smallest Ritz value, meets it.
    rhs : callable, optional
        ``rhs(c)`` -> (1, 3, N), or a callable as `b` may be: the right-hand side of case `c` of `b`
        again (needed with `fast`: `b` itself is not kept).
    cross : bool
        Also return ``x_i . r_j`` (m, m) of the solutions and the final residuals (free unknowns):
        the first-order term of a quadratic form's error, which :func:`homogenize` takes out.
    energy : (m,) floats, optional
        With `accuracy`: the strain energy ``w.K w`` of each case's lifting ``w`` (the right-hand side
        is ``b = -F K w``, and the total displacement ``w + x``), whose total energy is
        ``w.K w - x.K x``.
    accuracy : float, optional
        Also stop a case once its solution's energy error ``e.K e``, estimated by :func:`energy_error`,
        is at most `accuracy` times its total energy (whichever of this and `tol` comes first).
    info : dict, optional
        Filled with ``energy_error`` (m,): each case's estimated energy error over its total energy at
        the stop (inf before :data:`ENERGY_STEPS` steps since its last start, NaN without `energy`).
    whole : bool
        Return x over the whole grid (m, 3, N); False: as the CG holds it, on the live nodes, with them:
        ``(x (m, 3, L), live (L,))``, which spares the whole grid's x in double (on the 128^3 benchmark
        scaffold 84 bytes a solid voxel a case, at the solve's end).
    slab_nodes : int, optional
        The float products (`fast`'s) by slabs of this many nodes' planes (the OpenCL operator's
        ``live_product``) on a grid of at most
        :data:`~implicit_scaffold.measure.mechanics_cl.FLOAT_SLABS_FROM` nodes (above it they run by slabs of
        :data:`~implicit_scaffold.measure.mechanics_cl.FLOAT_SLAB_NODES` anyway); default: over the whole grid.
    periodic : bool
        The system is periodic (every solid voxel's corners free): singular, its null space the translations,
        which each preconditioned residual is kept off (its mean taken out per component).

    Returns
    -------
    x (m, 3, N) (or (x on the live nodes, live)), iterations, relative residuals (m,)[, x . r (m, m)]
    """
    if fast is not None and rhs is None:
        raise ValueError("pcg with a fast operator needs rhs, to compute the true residuals")
    from .fused import center, cg_update, put, take, take_dot, wdot, xpby
    from .mechanics_cl import FLOAT_SLAB_NODES, FLOAT_SLABS_FROM, reusing

    n = np.shape(free)[-1]
    w = np.asarray(free).reshape(-1, n)  # not copied: a float32 mask stays 4 bytes a node
    live = np.flatnonzero(w.any(axis=0))
    if n < 2**31:  # int32 indices, half int64's bytes (128^3 benchmark scaffold: 6 bytes a solid voxel)
        live = live.astype(np.int32)
    # in the mask's own float: a float32 mask (the solver's) stays 4 bytes an unknown here too, and the
    # compiled passes widen it exactly as they read it; the V-cycle shares this copy (compact's weights)
    wl = np.ascontiguousarray(w[:, live], w.dtype if w.dtype.kind == "f" else np.float64)
    # a mask per node is 1 on every live node: its live part is the weight of ones
    ones = wl if len(wl) == 1 else np.ones((1, live.size), wl.dtype)

    def on_live(src, out=None, add: bool = False) -> np.ndarray:
        """F src on the live nodes, from a whole-grid array or from a callable of the nodes; into `out` (a
        case's (1, 3, len(live)) in double) when given, or added to it with `add`, from a callable a chunk of
        :data:`LOAD_CHUNK` nodes at a time: a case's loads on every live node and their indices were two
        temporaries of the true residual's (on the 128^3 benchmark scaffold 47 bytes a solid voxel beside x, r
        and p)."""
        if not callable(src):
            if add:
                out += take(src, live, wl, out.dtype)
                return out
            return take(src, live, wl, out=out)
        if out is None:
            out = np.asarray(src(live), np.float64)
            out *= wl
            return out
        for a in range(0, live.size, LOAD_CHUNK):
            b = min(live.size, a + LOAD_CHUNK)
            part = np.asarray(src(live[a:b]), np.float64)
            part *= wl[:, a:b]
            if add:
                out[:, :, a:b] += part
            else:
                out[:, :, a:b] = part
        return out

    def on_live_product(product, v, w_out, spread=None, dtype=np.float64, dot_weight=None):
        """``w_out K v`` on the live nodes in double, from live-node values `v` (spread in `spread`, default
        the values' own float). A double OpenCL product by slabs of the grid (its ``live_product``): its
        whole-grid input and output held 48 bytes a node, above the float cycle's at the homogenization's
        switch to double and at every step of a compression (128^3 benchmark scaffold, a throw-away
        script: one case a block peaked 483 bytes a solid voxel, 394 by slabs; a compression 636 and 572),
        for some 10 ms more a product there (49 against 39). Float ones over the whole grid (by slabs of 2^18
        they took 27 ms against 21) but on a grid of more than
        :data:`~implicit_scaffold.measure.mechanics_cl.FLOAT_SLABS_FROM` nodes, whose V-cycle runs by slabs too,
        or by `slab_nodes` (pcg's) where given. A float product's result in `dtype` (default double).

        With `dot_weight`: ``(K v, v . K v)`` (weighed by it, as ``wdot`` sums it), summed in the pass that takes
        the product's live nodes where the product is a whole grid's."""
        def dotted(q):
            return q if dot_weight is None else (q, wdot(v, q, dot_weight))

        if hasattr(product, "live_product"):
            if product.double:
                return dotted(product.live_product(v, live, ones, w_out, np.float64))
            if n > FLOAT_SLABS_FROM:  # by larger slabs, on a large grid
                return dotted(product.live_product(v, live, ones, w_out, dtype, FLOAT_SLAB_NODES))
            if slab_nodes is not None:
                return dotted(product.live_product(v, live, ones, w_out, dtype, slab_nodes))
        else:
            dtype = np.float64
        out = product(put(v, live, n, ones, spread))
        if dot_weight is not None:
            return take_dot(out, live, w_out, v, dot_weight, dtype)
        return take(out, live, w_out, dtype)

    r = on_live(b)  # F b on the live nodes
    del b
    m = len(r)
    # the search directions in the fast products' float (with them only: a tolerance of 1e-7 or more):
    # the product reads p in it anyway, and x and r move by alpha p and alpha K p of the same rounded
    # p, so the two stay consistent; half p's bytes, which the double products after the switch
    # would otherwise add to the peak (128^3 benchmark scaffold: 965 against 1,022 MiB)
    p = np.empty_like(r, dtype=np.float64 if fast is None else getattr(fast, "dtype", np.float64))
    compact = getattr(precond, "compact", None)
    if compact is not None:
        # the preconditioned residual in p's float: p = z + beta p rounds it to that anyway, and r.z
        # is summed in double (wdot); one case's z on the live nodes, half its bytes in float32
        pre = compact(live, p.dtype, weights=wl)
    else:
        def pre(v, sink):
            z = take(precond(put(v, live, n, ones)), live, ones)
            for c in range(len(z)):
                sink(c, z[c:c + 1], None)
    # the preconditioned residual z is handed over one case at a time (pre's sink) and folded into
    # p at once, so that the block's z is never held beside x, r and p
    rz = np.zeros(m)

    # the dot products by a compiled pass (wdot, in double whatever z's float), not np.vdot: a BLAS
    # call leaves OpenBLAS's threads spinning, and beside them the OpenCL operator ran 1.8 times
    # slower (64^3 scaffold, one case a block: 34 s of CPU against 23)
    def r_dot(c, z, given=None) -> float:
        # `given`: the preconditioner summed it as it made z (the same bits)
        return float(wdot(r[c:c + 1], z, ones)[0]) if given is None else given

    # a periodic system is singular, its null space the translations (constant on the live nodes). A V-cycle's
    # z = B r is not orthogonal to them, and in a float product K t is rounding, not 0: on the default cube's
    # STL (193^3, periodic) a shear case's z gathered so much translation that its float CG met p.Kp <= 0 at
    # its third step and restarted in double. z less its mean per component (the preconditioner Pi B Pi, Pi the
    # projection off the translations: the same on the range of K, where r lies) kept every case in float: the
    # homogenization 88.9 s against 74.0 s (40 and 42 iterations); the 128^3 benchmark scaffold's 19 iterations
    # stay 19, two passes over z a case and step more (some 2 ms there)
    singular = bool(periodic)

    def projected(z, given):
        """`z` off the translations (in place), where the system is singular. r.z as given: r lies off them (its sum
        is rounding), so r.z is r.(z less its mean) but for that rounding, and a pass over r and z less a step."""
        if singular:
            center(z)
        return z, given

    def first(c, z, given=None):
        z, given = projected(z, given)
        p[c] = z[0]
        rz[c] = r_dot(c, z, given)

    with reusing():  # the cycle's whole-grid vectors, case after case, from one pool
        pre(r, first)
    x = np.zeros_like(r)
    res = _norms(r) / scale
    it = 0
    # each case's CG scalars since its last (re)start (energy_error's), and the sum of its steps' energies
    # alpha rho = |x_{k+1} - x_k|_K^2 over the whole solve (the solved part's energy x.K x: x starts from 0)
    rhos = [[rz[c]] for c in range(m)]
    pqs = [[] for _ in range(m)]
    solved = np.zeros(m)
    total = None if energy is None else np.asarray(energy, float).reshape(m)
    by_energy = accuracy is not None and total is not None  # the energy stop is on

    # a case's estimate once the true residual has replaced the fast products' (NaN: none, or it restarted)
    final = np.full(m, np.nan)

    def absolute_error() -> np.ndarray:
        """(m,) each case's estimated energy error e.K e (NaN: no energy given)."""
        out = np.full(m, np.nan)
        if total is not None:
            for c in range(m):
                out[c] = final[c] if not np.isnan(final[c]) else energy_error(rhos[c], pqs[c])
        return out

    def relative_error() -> np.ndarray:
        """(m,) each case's estimated energy error over its total energy (NaN: no energy given)."""
        if total is None:
            return np.full(m, np.nan)
        return absolute_error() / np.maximum(total - solved, 1e-300)

    def met() -> np.ndarray:
        """(m,) the cases whose energy error is estimated at most `accuracy` of their energy."""
        return relative_error() <= accuracy if by_energy else np.zeros(m, bool)

    def iterate(product, goal: float, stall: int = 0):
        """CG steps until every case is below `goal` (or maxiter); with `stall`, a case also stops
        once its residual has not reached a new low for that many steps (the fast products'
        rounding floor)."""
        # K p and the step one load case at a time (each case is its own CG): the whole-grid
        # vectors (p spread, K p) and q are one case's, not the block's (the OpenCL operator in
        # double runs a case a launch anyway), and a converged case costs no product
        nonlocal rz, res, it
        spread = getattr(product, "dtype", None)  # p spread in the operator's own float: no cast there
        best, stale = res.copy(), np.zeros(m, int)
        # a case whose direction has no positive curvature (p.Kp <= 0) stops here: its r and so its next p
        # would be the same again, to maxiter. The float products' rounding did it on periodic grids with an
        # odd axis (10 x 9 x 12 voxels: the residual held at 2.2e-2 for 2,000 iterations, where double
        # products converged in 15); after the float products the double ones restart it (p = z)
        halted = np.zeros(m, bool)
        while it < maxiter:
            going = (res > goal) & ((stale < stall) if stall else True) & ~met() & ~halted
            if not going.any():
                break
            live_cases = np.zeros(m, bool)
            rr = np.zeros(m)
            for c in np.flatnonzero(going):
                one = slice(c, c + 1)
                # masked to the free unknowns below; a float product's q in its float, in which it was made (half
                # the bytes of double: on the 128^3 benchmark scaffold 18 bytes a solid voxel, and its buffer is the
                # one the V-cycle's result of the same size was in), which wdot and cg_update widen exactly; p.q summed
                # in the pass that takes it (take_dot, wdot's bits)
                q, pq = on_live_product(product, p[one], ones, spread, np.float64 if spread is None else spread,
                                        dot_weight=wl)
                pq = pq[0]
                if pq > 0:
                    live_cases[c] = True
                    rr[c] = cg_update(x[one], p[one], r[one], q, wl, [rz[c] / pq])[0]  # x += alpha p, r -= alpha F q
                    pqs[c].append(pq)
                    solved[c] += rz[c] * rz[c] / pq  # alpha rho
                else:
                    halted[c] = True
                del q
            rz_new = np.zeros(m)

            def step(c, z, given=None):
                z, given = projected(z, given)
                rz_new[c] = r_dot(c, z, given)
                if live_cases[c]:
                    rhos[c].append(rz_new[c])
                beta = rz_new[c] / rz[c] if live_cases[c] and rz[c] != 0 else 0.0
                xpby(z, p[c:c + 1], [beta])  # p = z + beta p

            pre(r, step)
            rz = rz_new
            res = np.where(live_cases, np.sqrt(rr) / scale, res)
            stale = np.where(live_cases & (res >= best), stale + 1, np.where(live_cases, 0, stale))
            best = np.minimum(best, res)
            it += 1
            if progress is not None:
                # the cases that stepped: one that has stopped (met, stalled on the fast products' rounding,
                # halted) keeps its last figures, which stood for the block's to its end (a kinematic
                # homogenization of the L3 vertebra's scaffold: a residual of 6.3e-5 and an estimate of 3.2e-5,
                # frozen for 20 iterations, whose pace said some 100 iterations more, then 4 minutes)
                moved = live_cases if live_cases.any() else np.ones(m, bool)
                _call_progress(progress, it, float(res[moved].max()),
                               energy=float(relative_error()[moved].max()) if by_energy else None)

    with reusing():
        if fast is None:
            iterate(apply, tol)
        else:
            # with an energy accuracy, the fast products go on until it is met (or they stall on their
            # rounding): a looser residual goal would hand over to double before the estimate has a say
            iterate(fast, tol if by_energy else fast_goal(tol), FAST_STALL)
    if fast is not None:
        # the recurrence's r drifted from F (b - K x) by the fast products' rounding (on the 128^3
        # benchmark scaffold, float: up to 1.16e-6 where r said under 1e-6); each case's true
        # residual replaces it, and a case above tol goes on with `apply`. Out of the pool: its
        # idle buffers are gone before the right-hand sides' whole grids are made
        for c in range(m):
            one = slice(c, c + 1)
            if hasattr(apply, "live_product") and apply.double:
                # F K x written into r, then negated and F b added: the same bits as F b - F K x (a - b is
                # a + (-b)), without K x's own vector in double beside x, r and F b's (on the 128^3 benchmark
                # scaffold, one case a block, 35 bytes a solid voxel of the solve's peak)
                apply.live_product(x[one], live, ones, wl, np.float64, out=r[one])
                x_kx = float(wdot(x[one], r[one], ones)[0])
                np.negative(r[one], out=r[one])
                on_live(rhs(c), out=r[one], add=True)
            else:
                kx = on_live_product(apply, x[one], wl)
                x_kx = float(wdot(x[one], kx, ones)[0])
                on_live(rhs(c), out=r[one])
                r[one] -= kx
                del kx
            if total is not None:
                # the energy the solution has taken, -2 J(x) = 2 x.b - x.K x = 2 x.r + x.K x, in double from the
                # true residual: the fast steps' sum of alpha rho is -2 J only while their recurrence holds,
                # and a case that restarts adds its new steps' to its start's own (its J falls by alpha rho / 2 a
                # step). Summed on, a shear case of the default cube's STL (193^3, periodic) whose float CG met
                # p.Kp <= 0 at its third step took 27,411 of a total energy of 9,010 (the others 7,290 of it):
                # its relative error read 3.9e293, and it ran on to its residual, the block 73 iterations (40 now)
                solved[c] = 2.0 * float(wdot(x[one], r[one], ones)[0]) + x_kx
        res = _norms(r) / scale
        # a case still above tol restarts (p = z): its directions and steps belong to the recurrence's
        # r. Kept (residual replacement), a drift of 1e-3 stalled the CG, its next beta some 1e10,
        # and on a 64^3 scaffold under platens one of 3.3 times (2.9e-6 against 8.7e-7) took 238
        # more iterations where the restart took a few.
        # With an energy accuracy, a case is done when the true residual's own estimate meets it:
        # r.z / theta (theta the fast CG's smallest Ritz value), the first bound of energy_error. The
        # fast CG's estimate reads its recurrence's r, which can lie far under the true one: on the
        # jigsaw femur at 1.5 mm (kinematic) it said 5.2e-7 where C33 was 4.3e-4 off
        true_rz = np.zeros(m)

        def again_from(c, z, given=None):
            first(c, z, given)  # p = z and rz (z off the translations where singular), for a case that restarts
            true_rz[c] = rz[c]

        if by_energy or (res > tol).any():
            with reusing():
                # the whole block preconditioned, as every iteration does (a block of another size
                # would build the coarse levels' kernels for it)
                pre(r, again_from)
        done = np.zeros(m, bool)
        if by_energy:
            for c in range(m):
                theta = smallest_ritz(rhos[c], pqs[c])
                if theta > 0 and true_rz[c] > 0:
                    final[c] = true_rz[c] / theta  # absolute, as energy_error's
                done[c] = final[c] / max(total[c] - solved[c], 1e-300) <= accuracy
        again = (res > tol) & ~done
        with reusing():
            if again.any():
                for c in np.flatnonzero(again):
                    final[c] = np.nan
                    rhos[c], pqs[c] = [rz[c]], []  # a new CG: its scalars estimate its own error
            iterate(apply, tol)  # a done case stays met (its scalars are kept): no product
    p = None  # released (the nested steps read it no more)
    if info is not None:
        info["energy_error"] = relative_error()
        info["energy_error_abs"] = absolute_error()
        # each case met a stop: its residual, or its energy accuracy (not: maxiter, or no further descent)
        info["met"] = (res <= tol) | ((info["energy_error"] <= accuracy) if by_energy else False)
    # r is F (b - K x) on the live nodes: the true residual just computed, or the recurrence's in
    # double (whose drift from it is rounding)
    out = (np.einsum("idn,jdn->ij", x, r),) if cross else ()
    r = None
    return (put(x, live, n, ones) if whole else (x, live), it, res) + out


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
    energy_error: float = float("nan")  # the largest case's estimated relative energy error (pcg's info)
    dropped_voxels: int = 0  # solid voxels of pieces that reach no face of the box, left out (held_pieces)
    pieces: int = 1  # the pieces that share no node, each an independent system (independent_pieces)
    converged: bool = True  # every case's CG (every piece's) met its residual tolerance or its energy accuracy


def _operator(model, backend):
    if backend == "numpy":
        return lambda u, extra=None: apply_stiffness(model, u, extra)
    if backend == "opencl":
        from .mechanics_cl import StiffnessOperator

        return StiffnessOperator(model)
    raise ValueError(f"backend must be 'numpy' or 'opencl', got {backend!r}")


#: the fast products go on to this many times the tolerance, then each case restarts from its true
#: residual in double. Their rounding floors the residual, higher on larger grids: on the 200^3
#: benchmark scaffold, float stalled near 1.3e-6 (a goal of half the tolerance: 58 iterations,
#: 215.3 s; of 100 times it: 46, 185.8 s, the last 22 in double); on the 128^3 one it reached
#: 5e-7 (41 iterations, 42.1 s, against 40 and 44.3 s for 100 times), one run each
FAST_GOAL = 100.0
#: a case leaves the fast products when its residual has not reached a new low for this many
#: iterations (their rounding's floor: a block under lubricated platens stalled near 3e-4 in float)
FAST_STALL = 5
#: the fast products' goal is never above this, unless the tolerance is: a tolerance of 1e-4 or looser
#: is met in float (whose rounding floor lies far below: near 1.3e-6 on the 200^3 scaffold). 128^3
#: benchmark scaffold at 1e-3: 19.3 s, its tensor (as the mean stress) 7.4e-5 off, against 20.6 s and
#: 3.6e-4 with the goal at 100 times the tolerance (README, Mechanics, Tolerance)
FAST_FLOOR = 1e-4


#: :func:`energy_error` gives no estimate before this many CG steps (from the last start): the smallest
#: Ritz value of fewer lies too far above the operator's smallest eigenvalue
ENERGY_STEPS = 4
#: the default energy accuracy of a solve (:func:`measure`): each solution's energy error ``e.K e`` at most
#: this share of its total energy, so the stiffness tensor's entries and the apparent modulus (energies,
#: second order in the error) within it: under the last of the four digits the report prints, beside a voxel
#: discretisation error of percents. Against solves to 1e-10 (``bench_mechanics.py --accuracies`` /
#: ``--bone-accuracies``; README, Mechanics, the default stop measured), at 1e-5: the 128^3 benchmark
#: scaffold's tensor 1.8e-6 off in 15 iterations (1e-6: 2.2e-7 in 18); the lumbar micro-CT's central 128^3,
#: its compression 6.8e-7 off in 42 (5.9e-8 in 52), its kinematic tensor 2.1e-6 in 39 (1.7e-7 in 49); the data
#: folder's CT at its own voxel compressed 9.6e-7 off in 194 (a throw-away script). Not 1e-4, which took the
#: default cube's mechanics (``generate --mechanics``) 61.9 s against 101.3 at 1e-5 and 136.7 at 1e-6: there
#: that CT's compression stopped 4.8e-4 off under an estimate of 1.0e-4, two of its pieces at the estimate's
#: first steps (4 iterations), 2.7e-4 and 1.6e-3 off under estimates of 3.4e-5 and 3.8e-5
ACCURACY = 1e-5


#: the node of :func:`energy_error`'s Gauss-Radau bound, as a share of the smallest Ritz value (an upper
#: bound while the node lies under the operator's smallest eigenvalue, which that Ritz value overestimates)
RADAU_SHARE = 0.25


def gauss_radau(rho, pq, mu: float) -> float:
    """The Gauss-Radau upper bound of a CG iterate's energy error ``e.K e``, with its node at `mu`.

    Parameters
    ----------
    rho, pq : sequences of k + 1 and k floats
        As :func:`energy_error`'s.
    mu : float
        The prescribed node: a bound when ``0 < mu <= lambda_min(M K)``.

    Notes
    -----
    Meurant and Tichy's recurrence (Numer. Algorithms 82 (2019) 937-968; Golub and Meurant 2010, ch. 12):
    ``D_0 = rho_0 / mu``, ``D_{j+1} = rho_{j+1} g / (mu g + rho_{j+1})`` with ``g = D_j - alpha_j rho_j``.
    """
    rho = np.asarray(rho, float)
    pq = np.asarray(pq, float)
    D = rho[0] / mu
    for j in range(pq.size):
        g = D - rho[j] * rho[j] / pq[j]
        if not g > 0:  # the bound's own error share gone: mu lies above the smallest eigenvalue, no bound
            return float("inf")
        D = rho[j + 1] * g / (mu * g + rho[j + 1])
    return float(D)


def energy_error(rho, pq) -> float:
    """The energy error ``e.K e`` of a preconditioned CG iterate, estimated from the CG's own scalars.

    Parameters
    ----------
    rho : sequence of k + 1 floats
        ``r_j.z_j`` (the residual times the preconditioned residual) at the start and after each step;
        the last is the iterate's.
    pq : sequence of k floats
        ``p_j.K p_j`` of each step's search direction.

    Returns
    -------
    float
        In the system's energy units; inf before :data:`ENERGY_STEPS` steps.

    Notes
    -----
    Two bounds that hold when the smallest eigenvalue of ``M K`` (``M`` the preconditioner) is known, with
    it estimated by the smallest eigenvalue (Ritz value) ``theta`` of the Lanczos matrix that CG's step
    lengths ``alpha_j = rho_j / pq_j`` and ``beta_j = rho_{j+1} / rho_j`` make (Golub and Meurant, Matrices,
    Moments and Quadrature, 2010, ch. 12), which lies above it and falls towards it as CG finds the slow
    modes; the smaller of the two is returned:

    - ``e.K e = r.K^-1 r <= r.M r / lambda_min``, here ``rho_k / theta``;
    - the Gauss-Radau bound (:func:`gauss_radau`) with its node at :data:`RADAU_SHARE` ``theta``, which
      follows how the error spreads over the modes (``rho_k / theta`` counts all of it in the slowest).

    A stop on the energy error against the energy is Arioli's (Numer. Math. 97 (2004) 1-24): the
    figures are energies, whose error is ``e.K e``. On the recorded iterations of solves to 1e-11 (README,
    Mechanics, the default stop measured), for 1e-6 asked: the central 128^3 of the lumbar trabecular
    micro-CT in ../shared/data under platens, first within it at iteration 54, stopped at 115 by the first
    bound and 61 by the second (7.8e-7 off); a 64^3 crop of it, first within at 422, at 452 and 453; the
    64^3 scaffold, first within at 22, at 25 and 26. Not an extrapolation of the steps' own energies
    ``alpha_j rho_j`` (a geometric series at their slowest recent ratio), which stopped that 64^3 crop at
    380 iterations with the modulus 6.6e-5 off (a plateau of the residual hid a slow mode); nor the
    Gauss-Radau node nearer ``theta`` (0.9 of it stopped the 128^3 crop at 42 iterations, 3.9e-6 off).
    """
    rho = np.asarray(rho, float)
    pq = np.asarray(pq, float)
    # r.z <= 0 (or p.K p <= 0): the preconditioner (or the operator) is not positive definite, and
    # no bound holds (read as 0, such an r.z once stopped a compression at a modulus 205 times off)
    if rho.size != pq.size + 1 or not np.all(rho > 0):
        return float("inf")
    theta = smallest_ritz(rho, pq)
    if not theta > 0:
        return float("inf")
    return min(float(rho[-1]) / theta, gauss_radau(rho, pq, RADAU_SHARE * theta))


def smallest_ritz(rho, pq) -> float:
    """The smallest eigenvalue of the Lanczos matrix that a preconditioned CG's scalars make (its estimate
    of the smallest eigenvalue of ``M K``, from above); 0 before :data:`ENERGY_STEPS` steps or after a
    breakdown. `rho`, `pq` as :func:`energy_error`'s (`rho`'s last entry is not used)."""
    from scipy.linalg import eigvalsh_tridiagonal

    rho = np.asarray(rho, float)
    pq = np.asarray(pq, float)
    k = pq.size
    if k < ENERGY_STEPS or rho.size < k or not (np.all(pq > 0) and np.all(rho[:k] > 0)):
        return 0.0
    alpha = rho[:k] / pq
    beta = rho[1:k] / rho[:k - 1]
    diag = 1.0 / alpha
    diag[1:] += beta / alpha[:-1]
    theta = float(eigvalsh_tridiagonal(diag, np.sqrt(beta) / alpha[:-1], select="i", select_range=(0, 0))[0])
    return max(theta, 0.0)


def fast_goal(tol: float) -> float:
    """Where :func:`pcg`'s fast products hand over to double: :data:`FAST_GOAL` times `tol`, but no
    higher than :data:`FAST_FLOOR` or `tol` itself, whichever is higher (a tolerance of 1e-4 or looser
    is met in float, then checked on the true residual)."""
    return max(tol, min(FAST_GOAL * tol, FAST_FLOOR))


def _fast(op, tol: float):
    """The float operator for the CG's iterations (:func:`pcg`'s `fast`), or None: an OpenCL
    operator in double and a tolerance of at least :data:`FLOAT_TOL`."""
    if tol >= FLOAT_TOL and getattr(op, "double", False) and hasattr(op, "single"):
        return op.single()
    return None


def check_solid(solid) -> np.ndarray:
    """`solid` as a 3-D bool array with at least one solid voxel, or a ScaffoldError."""
    solid = np.asarray(solid)
    if solid.ndim != 3 or min(solid.shape) < 1:
        raise ScaffoldError(f"a mechanics sample is a 3-D voxel volume, got shape {solid.shape}")
    solid = solid.astype(bool)
    if not solid.any():
        raise ScaffoldError("the volume holds no solid voxel: nothing carries load")
    return solid


#: load cases per CG block of :func:`homogenize` by default: all six, whose products then run
#: with each matrix entry read once for the six (``bench_mechanics.py``, the machine loaded
#: by other work: on the 64^3 scaffold 32.9 s against 56.9 s for six blocks of one, medians of 3;
#: on the 128^3 one 309.2 s against 335.3 s, one run each), at the price of six cases' vectors
#: (:func:`solve_memory`); a budget too short for them takes smaller blocks (:func:`block_for`)
CASES_PER_BLOCK = 6


@_keeping_freed_memory
def homogenize(solid, h: float, mat: Material, *, boundary: str = "periodic", tol: float = 1e-8,
               maxiter: int = 2000, backend: str = "numpy", preconditioner: str = "multigrid",
               progress=None, cases_per_block: int = CASES_PER_BLOCK,
               accuracy: float | None = None) -> Homogenization:
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
    preconditioner : {"multigrid", "fft"}
        See :func:`make_preconditioner`.
    progress : callable, optional
        (iteration, residual) after every CG iteration.
    accuracy : float, optional
        Also stop a load case once its energy error is estimated at most this share of its energy
        (:func:`pcg`): each diagonal entry ``C_ii`` then lies within that share above the converged one
        (Notes), the others within it of ``sqrt(C_ii C_jj)``.
    cases_per_block : int
        The six load cases are solved this many at a time (1-6), with one preconditioner: the
        solve's vectors are held for one block's cases only (:data:`CASES_PER_BLOCK`).

    Notes
    -----
    The tensor is the energy form ``C_ij = u_i.K u_j / V`` of the total displacements ``u_i`` (the unit
    strain's plus the solved part ``x_i``), computed as the mean stress ``w_i.K u_j / V`` (``w_i`` the unit
    strain's displacements; linear in the solution) less ``x_i.r_j / V`` (``r_j`` the final residual on the
    free unknowns, :func:`pcg`'s `cross`). The exact ``u_j`` leaves no force on the free unknowns, so an
    iterate with the error ``e`` gives ``C_ij + e_i.K e_j / V``: second order in the solver's error, where
    the mean stress alone is first order. Load cases of different blocks (``cases_per_block`` under 6)
    are never held together: their entries keep the mean stress.

    Under kinematic conditions, pieces that share no node are solved apart, each on its own box
    (:func:`independent_pieces`; the small ones together, exactly): the tensor is the sum of theirs, each
    over the sample's volume; `iterations` is the slowest solve's.
    """
    t0 = time.perf_counter()
    solid = check_solid(solid)
    if boundary not in ("periodic", "kinematic"):
        raise ValueError(f"boundary must be 'periodic' or 'kinematic', got {boundary!r}")
    periodic = boundary == "periodic"
    fraction, total = float(solid.mean()), solid.size  # the sample's, floating pieces included
    held = held_pieces(solid)
    dropped = int(np.count_nonzero(solid)) - int(np.count_nonzero(held))
    if dropped:
        solid = held
    del held
    if not solid.any():
        # nothing reaches a face: no load path in any direction (engineering_constants notes the zeros)
        return Homogenization(np.zeros((6, 6)), boundary, fraction, 0, 0.0, time.perf_counter() - t0, backend,
                              dropped_voxels=dropped)
    labels, crops = (None, []) if periodic else independent_pieces(solid)
    if not crops:
        del labels  # 4 bytes a voxel, not held through the solve
        C, iterations, res, err, _, met = _homogenize_held(solid, h, mat, periodic, total, tol, maxiter, backend,
                                                           preconditioner, progress, cases_per_block, accuracy)
        return Homogenization(C, boundary, fraction, iterations, res, time.perf_counter() - t0, backend, err,
                              dropped, converged=met)
    # pieces that share no node are independent systems: each solved on its own box, whose grid and
    # coarse levels hold it alone, the tensor the sum of theirs (each over the whole box's volume)
    C, iterations, res, errors, converged = np.zeros((6, 6)), 0, 0.0, np.zeros(6), True
    tell = _counting(progress, len(crops), "piece")
    for box, ids, small in crops:
        Cp, its, r, _, e, met = _homogenize_held(np.isin(labels[box], ids), h, mat, False, total, tol, maxiter,
                                                 backend, "direct" if small else preconditioner, tell,
                                                 cases_per_block, accuracy)
        C += Cp
        if tell is not None:
            tell.next()
        iterations, res, converged = max(iterations, its), max(res, r), converged and met
        # each case's energy errors add up, over the sample's energy C_kk V. A piece that hangs from a
        # face keeps almost none of its energy: its own relative error, over nearly 0, says nothing
        # (1e297 on the data folder's CT). An exact solve ends by its residual within a step or two,
        # before the estimate has its steps (inf): its error is second order in that residual
        if not small:
            errors += e
    err = float(np.max(errors / np.maximum(np.diag(C) * total * h ** 3, 1e-300)))
    return Homogenization(C, boundary, fraction, iterations, res, time.perf_counter() - t0, backend, err, dropped,
                          pieces=sum(len(ids) for _, ids, _ in crops), converged=converged)


def _call_progress(progress, *args, energy: float | None = None, part: tuple = ()) -> None:
    """``progress(*args)``, with `energy` (a solve's estimated relative energy error) added as the last
    argument when `progress` asks for it (a true ``takes_energy`` attribute, as
    :meth:`~implicit_scaffold.progress.Progress.solver`'s callback has): a caller's callback of the
    iteration and the residual alone is called as before. `part`, the solves of which this is one
    (``(what, k, n)`` from the outermost, :func:`_counting`'s), goes as ``part=`` to a callback with a true
    ``takes_part`` attribute."""
    if getattr(progress, "takes_energy", False):
        if part and getattr(progress, "takes_part", False):
            progress(*args, energy, part=part)
        else:
            progress(*args, energy)
    else:
        progress(*args)


def _counting(progress, parts: int = 1, what: str = "block"):
    """`progress` (iteration, residual[, energy error]) over solves one after another, their iterations
    counted on from one solve to the next (``.next()`` between them); None for None. With `parts` > 1 each
    call also names its solve, ``(what, k, parts)`` (k from 1), before the parts of the solve's own
    (:func:`_call_progress`): the blocks of load cases, the pieces."""
    if progress is None:
        return None
    state = {"done": 0, "last": 0, "k": 1}

    def counted(it, r, energy=None, part=()):
        state["last"] = max(state["last"], it)
        mine = ((what, state["k"], int(parts)),) if parts > 1 else ()
        _call_progress(progress, state["done"] + it, r, energy=energy, part=mine + tuple(part))

    def next_solve():
        state["done"] += state["last"]
        state["last"] = 0
        state["k"] += 1

    counted.next = next_solve
    counted.takes_energy = True
    counted.takes_part = True
    return counted


def one_case_slabs(node_shape, block: int) -> int | None:
    """The slabs (nodes) of a homogenization's float products and of its V-cycle's fine level on a node grid of
    `node_shape` with `block` load cases a CG block: :data:`~implicit_scaffold.measure.mechanics_cl.
    ONE_CASE_SLAB_NODES` for one case a block (the memory-lean choice) on a grid of at most
    :data:`~implicit_scaffold.measure.mechanics_cl.FLOAT_SLABS_FROM` nodes; None: the default (the whole grid,
    or slabs of :data:`~implicit_scaffold.measure.mechanics_cl.FLOAT_SLAB_NODES` above that)."""
    from .mechanics_cl import FLOAT_SLABS_FROM, ONE_CASE_SLAB_NODES

    if block == 1 and int(np.prod(node_shape, dtype=np.int64)) <= FLOAT_SLABS_FROM:
        return ONE_CASE_SLAB_NODES
    return None


@_one_blas_thread
def _homogenize_held(solid, h, mat, periodic, total, tol, maxiter, backend, preconditioner, progress,
                     cases_per_block, accuracy):
    """:func:`homogenize` of held pieces, its tensor over `total` voxels' volume: (C, iterations, the
    largest relative residual, the largest estimated relative energy error, each case's estimated
    energy error e.K e (6,), whether every case met its residual tolerance or its energy accuracy)."""
    model = voxel_model(solid, h, mat, periodic=periodic)
    ns = model.solid_voxels
    u0e = macro_displacements(h)  # (6, 24)
    op = _operator(model, backend)
    # the free mask in float32 (0 and 1 exactly), which the float32 V-cycle shares rather than copies
    if periodic:
        free = model.active.astype(np.float32)
    else:
        # u = E x at every node; the box's faces keep it, the inside nodes are solved for
        inner = np.zeros(model.shape, bool)
        inner[1:-1, 1:-1, 1:-1] = True
        free = (model.active & inner.ravel()).astype(np.float32)
        del inner
    scale = np.sqrt(ns) * np.linalg.norm(model.ke @ u0e.T, axis=0)
    block = max(1, min(6, int(cases_per_block)))
    slab_nodes = one_case_slabs(model.shape, block)
    precond = make_preconditioner(preconditioner, model, op, free, tol, slab_nodes)
    fast = _fast(op, tol)
    ue_sum = np.empty((6, 24))
    cross = np.zeros((6, 6))  # x_i . r_j within each block (Notes: the energy form)
    iterations, res, err, err_abs = 0, np.zeros(6), np.full(6, np.nan), np.full(6, np.nan)
    met = np.zeros(6, bool)
    # each unit strain's lifting energy (u = E x: every solid voxel holds the same corner displacements,
    # up to a translation), the total a case's solved part relaxes
    lifting = ns * np.einsum("ka,ab,kb->k", u0e, model.ke, u0e)
    # the blocks' iterations counted on from one to the next, each block named
    tell = _counting(progress, -(-6 // block), "block")
    for k0 in range(0, 6, block):
        cases = range(k0, min(6, k0 + block))
        # the right-hand side is handed to pcg with no reference kept here, so that it is
        # released once pcg has read its live nodes
        if periodic:
            # the macroscopic strain's element forces Ke E x, the same in every solid voxel, summed
            # on the nodes pcg asks for (its live nodes): six cases on the whole 128^3 grid took
            # 0.73 s, mostly the fresh pages of their 302 MB
            def loads(ks):
                return lambda nodes: element_loads(model, -(model.ke @ u0e[list(ks)].T).T, nodes)
        else:
            def loads(ks):
                return _kinematic_loads(op, model, h, ks)
        info = {}
        (x, live), its, r, xr = pcg(op, precond, loads(cases), free, scale=scale[list(cases)], tol=tol,
                                    maxiter=maxiter, progress=tell, fast=fast, rhs=lambda c: loads([cases[c]]),
                                    cross=True, energy=lifting[list(cases)], accuracy=accuracy, info=info,
                                    whole=False, slab_nodes=slab_nodes, periodic=periodic)
        if tell is not None:
            tell.next()
        cross[np.ix_(list(cases), list(cases))] = xr
        err[list(cases)] = info["energy_error"]
        err_abs[list(cases)] = info["energy_error_abs"]
        met[list(cases)] = info["met"]
        # the solved part's sums on its live nodes (the whole grid's x in double would be the solve's peak);
        # u = E x + the solved part on a box, whose E x sums in closed form; periodic: E x's is added below
        ue_sum[list(cases)] = corner_sums(model, x, live)
        if not periodic:
            ue_sum[list(cases)] += affine_corner_sums(model, cases)
        del x, live
        iterations, res[list(cases)] = max(iterations, its), r
    del precond
    if periodic:
        ue_sum += ns * u0e
    Bc = strain_matrix(h, (0.0, 0.0, 0.0))
    mean_strain = (Bc @ ue_sum.T) / total  # (6 strain, 6 cases)
    C = isotropic_tensor(mat.E_gpa, mat.nu) @ mean_strain
    C = C - cross / (total * h ** 3)  # the energy form (Notes)
    C = 0.5 * (C + C.T)  # symmetric up to the solver's tolerance
    # a case that met the residual tolerance before the estimate had its steps (inf) counts no error:
    # it is second order in that residual
    err_abs = np.where(np.isfinite(err_abs) | (res > tol), err_abs, 0.0)
    return C, int(iterations), float(res.max()), float(err.max()), err_abs, bool(met.all())


#: the kinematic homogenization and the compression solve each piece of more solid voxels than this on
#: its own box, and the smaller ones together, exactly (:func:`direct_preconditioner`), up to
#: :data:`DIRECT_BATCH` at a time. A sparse LU's fill grows with a piece's size: 20 KB a voxel for a solid
#: cube of 512 voxels (alone, or eight of them together), 40 KB for one of 2,028
DIRECT_VOXELS = 500
#: solid voxels of small pieces solved together: at most some 80 MB of LU factors (the assembled matrix
#: some 4 KB a voxel more)
DIRECT_BATCH = 4000


def independent_pieces(solid: np.ndarray, small: int | None = None, batch: int | None = None):
    """The pieces of a kinematic sample that share no node (26-connected), and the boxes to solve them in.

    A piece's box keeps one void layer on each side that is not on the sample's face, so its nodes
    there are free, as in the sample: only the sample's faces are held (``u = E x``, which a box moves
    by a rigid translation: the same strains). Pieces of at most `small` solid voxels share boxes, in
    their labels' order (near one another), at most `batch` solid voxels a box (defaults:
    :data:`DIRECT_VOXELS`, :data:`DIRECT_BATCH`).

    Returns
    -------
    labels : int32 ndarray of the sample's shape
        The pieces, 1..count (0: void).
    crops : list of (slices into the sample, the labels solved there, small)
        The largest piece first; [] for a sample of one piece. A crop's solid is
        ``np.isin(labels[box], ids)`` (made when it is solved: the crops' masks together may
        outweigh the sample many times).
    """
    from scipy import ndimage

    from ..run.pieces import label_pieces

    small = DIRECT_VOXELS if small is None else small
    batch = DIRECT_BATCH if batch is None else batch
    labels, count = label_pieces(solid, connectivity=26)
    if count <= 1:
        return labels, []
    sizes = np.bincount(labels.ravel(), minlength=count + 1)[1:]
    boxes = ndimage.find_objects(labels)

    def padded(box):
        return tuple(slice(max(b.start - 1, 0), min(b.stop + 1, n)) for b, n in zip(box, solid.shape))

    crops = [(padded(boxes[p]), np.array([p + 1]), False) for p in np.argsort(-sizes, kind="stable")
             if sizes[p] > small]
    # the small ones in batches of consecutive labels (numbered in C order of their first voxel: near
    # one another), each batch of at most `batch` solid voxels or of one piece
    groups, total = [[]], 0
    for p in np.flatnonzero(sizes <= small):
        if groups[-1] and total + sizes[p] > batch:
            groups.append([])
            total = 0
        groups[-1].append(p)
        total += sizes[p]
    for group in groups if groups[0] else []:
        box = tuple(slice(min(boxes[p][a].start for p in group), max(boxes[p][a].stop for p in group))
                    for a in range(3))
        crops.append((padded(box), np.array(group) + 1, True))
    return labels, crops


def _kinematic_loads(op, model, h: float, cases):
    """(m, 3, N) right-hand sides ``-K (E x)`` of the unit Voigt strains `cases`, made a case at a time
    (one case's ``E x`` and product at once, not the block's: three (m, 3, N) arrays in float64 were
    the kinematic solve's peak). With an operator that multiplies by slabs (``live_product``), a callable
    of the nodes pcg asks for instead: ``E x`` on the nodes solid voxels touch and its product there
    (the same values bit for bit: no whole-grid vector; the whole grid's held 48 bytes a node before the
    solve)."""
    shape = model.shape
    if not hasattr(op, "live_product"):
        out = np.empty((len(cases), 3, int(np.prod(shape))))
        for c, k in enumerate(cases):
            np.negative(op(_affine(shape, h, [k]))[0], out=out[c])
        return out
    cases = list(cases)

    def at(nodes: np.ndarray) -> np.ndarray:
        touched = np.flatnonzero(model.active)
        pos = np.clip(np.searchsorted(touched, nodes), 0, max(touched.size - 1, 0))
        hit = touched[pos] == nodes if touched.size else np.zeros(nodes.size, bool)
        ones = np.ones((1, touched.size))
        coords = [c * h for c in np.unravel_index(touched, shape)]
        out = np.zeros((len(cases), 3, nodes.size))
        for c, k in enumerate(cases):
            u = np.zeros((1, 3, touched.size))
            add_strain(u[0], coords, strain_tensor(k))
            f = op.live_product(u, touched, ones, ones)
            del u
            out[c][:, hit] = -f[0][:, pos[hit]]
            del f
        return out

    return at


def node_axes(shape, h: float) -> list:
    """The node coordinates along each axis of a node grid of `shape` (index times `h`, mm), shaped to
    broadcast over it."""
    return [np.arange(n, dtype=float).reshape([-1 if a == ax else 1 for a in range(3)]) * h
            for ax, n in enumerate(shape)]


def add_strain(u: np.ndarray, coords, eps: np.ndarray) -> None:
    """Add the displacements ``E x`` of the strain tensor `eps` (3, 3) to `u` (3, ...) in place, x the
    coordinates `coords` (three arrays that broadcast over ``u[d]``, mm): no whole-grid temporary."""
    for d in range(3):
        for j in range(3):
            if eps[d, j]:
                u[d] += eps[d, j] * coords[j]


def _affine(shape, h: float, cases) -> np.ndarray:
    """(m, 3, N) nodal displacements ``E x`` of the unit Voigt strains `cases` (x = node index times `h`)."""
    axes = node_axes(shape, h)
    out = np.zeros((len(cases), 3) + tuple(shape))
    for c, k in enumerate(cases):
        add_strain(out[c], axes, strain_tensor(k))
    return out.reshape(len(cases), 3, -1)


def strain_tensor(k: int) -> np.ndarray:
    """(3, 3) float ndarray: the unit Voigt strain `k` as a tensor (engineering shear strain 1)."""
    eps = np.zeros((3, 3))
    if k < 3:
        eps[k, k] = 1.0
    else:
        i, j = [(1, 2), (0, 2), (0, 1)][k - 3]
        eps[i, j] = eps[j, i] = 0.5
    return eps


# ----------------------------------------------------------------------------- platen compression


@dataclass
class Compression:
    """A uniaxial compression between rigid bonded platens (ISO 13314's setting)."""

    axis: int
    apparent_modulus_gpa: float
    strain: float
    von_mises_strain: np.ndarray  # (n1, n2, n3) float32, 0 in void and in parts carrying no load
    iterations: int
    residual: float
    seconds: float
    dropped_voxels: int  # solid voxels not joined to both platens (they carry no load)
    energy_error: float = float("nan")  # the estimated relative energy error (pcg's info)
    pieces: int = 1  # the pieces that share no node, each an independent system (independent_pieces)
    converged: bool = True  # every piece's CG met its residual tolerance or its energy accuracy


def _face_labels(labels: np.ndarray, axis: int, end: int) -> np.ndarray:
    """The labels (> 0) of the pieces with a voxel on the box's face normal to `axis` at `end` (0 or -1)."""
    out = np.unique(np.take(labels, end, axis=axis))
    return out[out > 0]


def load_path(solid: np.ndarray, axis: int) -> np.ndarray:
    """The solid voxels face-connected to both faces of the box normal to `axis`.

    A piece touching one platen or none carries no load (it is free at one end at least);
    six-connectivity, since voxels that share only an edge or a corner form a hinge.
    """
    from ..run.pieces import label_pieces

    labels, count = label_pieces(solid)
    if count == 0:
        return np.zeros_like(solid)
    both = np.intersect1d(_face_labels(labels, axis, 0), _face_labels(labels, axis, -1))
    return np.isin(labels, both)


def held_pieces(solid: np.ndarray) -> np.ndarray:
    """The solid voxels face-connected to some face of the box: what a homogenization holds.

    A piece that reaches no face is held by nothing, under either boundary condition (kinematic:
    the faces' displacements; periodic: the images across the faces). Under any macroscopic
    strain it moves as a rigid body, with no energy, so it adds nothing to the converged tensor;
    left in, its six rigid motions are null modes of the system, and a solve stopped early counts
    its unrelaxed energy (on a 200 x 200 x 41 crop of the TotalSegmentator CT above 200 HU, 696
    such voxels: Exx 1.1740 GPa with them, 1.1715 without, both after 120 iterations; the CG's
    pace was the same). Six-connectivity, as :func:`load_path`.
    """
    from ..run.pieces import label_pieces

    labels, count = label_pieces(solid)
    if count == 0:
        return np.zeros_like(solid)
    faces = np.unique(np.concatenate([_face_labels(labels, a, e) for a in range(3) for e in (0, -1)]))
    if faces.size == count:
        return np.asarray(solid, bool)
    return np.isin(labels, faces)


def von_mises_strain(strain: np.ndarray) -> np.ndarray:
    """(ns,) equivalent strain ``sqrt(2/3 e':e')`` of Voigt strains (6, ns) (engineering shear)."""
    tr = strain[:3].sum(axis=0) / 3
    dev = strain[:3] - tr
    shear = strain[3:] / 2
    return np.sqrt(2 / 3 * ((dev ** 2).sum(axis=0) + 2 * (shear ** 2).sum(axis=0)))


@_keeping_freed_memory
def compress(solid, h: float, mat: Material, *, axis: int = 2, strain: float = 1e-3, bonded: bool = False,
             tol: float = 1e-8, maxiter: int = 2000, backend: str = "numpy",
             preconditioner: str = "multigrid", progress=None, accuracy: float | None = None) -> Compression:
    """Compress a voxel sample between two rigid platens on its faces normal to `axis`.

    The lower platen holds its nodes' axial displacement at 0, the upper one moves them by
    ``strain * L``; the other faces are free. By default the platens are lubricated (the
    nodes slide on them), so a homogeneous block gives its material's own modulus, the
    ideal ISO 13314 test; ``bonded=True`` holds them laterally too (no slip, the stiff end
    of the friction range). The apparent modulus is the platen force (the platens' work ``u.K u``
    over their travel) over the box's cross-section, over the strain. The CG corrects the lifting of
    less energy of two that meet the platens: their planes alone, or the homogeneous block's solution
    (the axial strain and the material's lateral strain, none under bonded platens). The sliding
    system keeps the rigid in-plane motions: it
    is singular but consistent, which CG solves (they carry no force). With `accuracy` the CG
    also stops once the solution's energy error is estimated at most that share of its energy
    (:func:`pcg`): the modulus, the platens' work, is then that close above the converged one.
    Pieces that share no node are solved apart (as :func:`homogenize`'s), the force the sum of theirs.

    Raises
    ------
    ScaffoldError
        No solid, or no piece of solid joins the two platens.
    """
    t0 = time.perf_counter()
    solid = check_solid(solid)
    if axis not in (0, 1, 2):
        raise ScaffoldError(f"the compression axis is x, y or z (0, 1, 2), got {axis!r}")
    kept = load_path(solid, axis)
    if not kept.any():
        raise ScaffoldError(f"the solid does not connect the two platens along {'xyz'[axis]}: no load path, "
                            "nothing to compress")
    area = np.prod([solid.shape[a] for a in range(3) if a != axis]) * h * h
    labels, crops = independent_pieces(kept)
    if not crops:
        del labels
        force, field_vm, iterations, res, err, converged = _compress_kept(kept, h, mat, axis, strain, bonded, tol,
                                                                          maxiter, backend, preconditioner, progress,
                                                                          accuracy)
    else:
        # pieces that share no node carry their loads apart: each solved on its own box (its full height),
        # the platens' force the sum of theirs
        force, field_vm, iterations, res, err = 0.0, np.zeros(solid.shape, np.float32), 0, 0.0, 0.0
        converged = True
        tell = _counting(progress, len(crops), "piece")
        for box, ids, small in crops:
            f, field, its, r, e, met = _compress_kept(np.isin(labels[box], ids), h, mat, axis, strain, bonded, tol,
                                                 maxiter, backend, "direct" if small else preconditioner, tell,
                                                 accuracy)
            force += f
            field_vm[box] += field  # 0 outside the piece's own voxels
            if tell is not None:
                tell.next()
            iterations, res, converged = max(iterations, its), max(res, r), converged and met
            # every piece here joins both platens and carries load, so its own ratio is sound and the
            # largest bounds the sum's; an exact solve's inf (too few steps) counts no error, as homogenize's
            err = max(err, e) if np.isfinite(e) or not small else err
    return Compression(axis, float(force / area / strain), strain, field_vm, int(iterations), float(res),
                       time.perf_counter() - t0, int(solid.sum() - kept.sum()), float(err),
                       sum(len(ids) for _, ids, _ in crops) or 1, bool(converged))


def platen_unknowns(model: VoxelModel, axis: int, bonded: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The unknowns of a compression between platens on the box's faces normal to `axis` (:func:`compress`):
    (free (3, N) bool, the upper platen's node plane (N,) bool). The platens hold their nodes' displacement
    along `axis`; bonded ones, every component.

    `model` is a box sample's (:func:`voxel_model`, not periodic): its first and last node planes are the
    faces. The planes are masks: a flat index of every node would take 8 bytes a node."""
    shape = model.shape
    bottom, top = np.zeros(shape, bool), np.zeros(shape, bool)
    plane = [slice(None)] * 3
    plane[axis] = 0
    bottom[tuple(plane)] = True
    plane[axis] = shape[axis] - 1
    top[tuple(plane)] = True
    bottom, top = bottom.ravel(), top.ravel()
    platen = bottom | top
    free = np.repeat(model.active[None], 3, axis=0)
    free[axis] &= ~platen
    if bonded:
        free &= ~platen
    return free, top


def _platen_planes(op, model: VoxelModel, axis: int, top: np.ndarray, travel: float, free: np.ndarray):
    """The lifting of the upper platen's plane alone (its nodes moved by `travel` along `axis`, every other node
    still): (its energy ``w.K w``, pcg's right-hand side ``-F K w``, a callable of the nodes with an operator
    that multiplies by slabs, else a whole-grid array).

    ``K w`` is 0 but on the nodes of the upper platen's plane and the plane under it: with ``live_product`` it
    is taken on those alone, by slabs (the whole grid's ``w`` and ``K w`` held 48 bytes a node before the
    solve, its peak there: a 128^3 crop of the lumbar micro-CT, traced with the V-cycle's fine level forced
    to slabs of 2^18 nodes, 269 MiB, 267 in the CG's iterations)."""
    shape = model.shape
    if not hasattr(op, "live_product"):
        base = np.zeros((1, 3, int(np.prod(shape))))
        base[0, axis, top] = travel
        kb = op(base)
        energy = float(np.einsum("cdn,cdn->", base, kb))  # not np.vdot: see pcg's dot products
        del base
        np.negative(kb, out=kb)
        kb *= free  # in place (a whole-grid vector: 320 MB on the femoral shaft's grid)
        return energy, kb
    near = np.zeros(shape, bool)
    plane = [slice(None)] * 3
    plane[axis] = slice(shape[axis] - 2, None)
    near[tuple(plane)] = True
    near = np.flatnonzero(near.ravel() & model.active)
    on_top = np.flatnonzero(top[near])
    u_near = np.zeros((1, 3, near.size))
    u_near[0, axis, on_top] = travel
    ones = np.ones((1, near.size))
    k_near = op.live_product(u_near, near, ones, ones)
    energy = float(np.einsum("cdn,cdn->", u_near, k_near))
    del u_near

    def loads(nodes: np.ndarray) -> np.ndarray:
        out = np.zeros((1, 3, nodes.size))
        at = np.clip(np.searchsorted(nodes, near), 0, max(nodes.size - 1, 0))
        hit = nodes[at] == near if nodes.size else np.zeros(near.size, bool)
        out[:, :, at[hit]] = -k_near[:, :, hit]
        return out  # masked to the free unknowns by pcg

    return energy, loads


@_one_blas_thread
def _compress_kept(kept, h, mat, axis, strain, bonded, tol, maxiter, backend, preconditioner, progress, accuracy):
    """:func:`compress` of the pieces that join both platens: (the upper platen's force in kN, the von
    Mises strain field of `kept`'s shape, iterations, the relative residual, the estimated energy error,
    whether the CG met its residual tolerance or its energy accuracy)."""
    model = voxel_model(kept, h, mat, periodic=False)
    shape = model.shape
    length = (shape[axis] - 1) * h
    free, top = platen_unknowns(model, axis, bonded)
    # float32 (0 and 1 exactly), which the float32 V-cycle shares rather than copies: in float64 the
    # mask and the cycle's copy held 36 bytes a node, 936 MiB on the whole lumbar micro-CT's grid
    free = free.astype(np.float32)
    op = _operator(model, backend)
    ns = model.solid_voxels
    macro = macro_displacements(h)
    scale = np.sqrt(ns) * np.atleast_1d(np.linalg.norm(model.ke @ (macro[axis] * strain)))
    precond = make_preconditioner(preconditioner, model, op, free, tol)
    # no fast products here: in float this system's residual stalls some 3 times over the
    # recurrence's, and the restart in double costs more than float saves (64^3 benchmark
    # scaffold along z: 44 iterations, 2.4 and 3.0 s, against 40 and 2.2 and 2.3 s in double);
    # and to a loose tolerance in float the modulus is further off (a 128^3 crop of the lumbar
    # micro-CT at 1e-4: 2.1e-3 against 2.5e-6 in double; the default cube's 96^3 corner at an energy
    # accuracy of 1e-4: 73 iterations and 3.8e-4 off, under an estimate of 6.4e-6, against 45 and 2.8e-5)
    # Two liftings meet the platens: their planes alone (the upper one's nodes moved by -s L, every other
    # node still) and the homogeneous block's solution (u = E x, E = diag(nu s, nu s, -s) along the axis; no
    # lateral part under bonded platens, which hold it). The CG corrects the one of less energy: the
    # solution's energy is the least of every field that meets the platens, so a lifting's energy error is
    # its energy less the solution's. The block's is the nearer on a scaffold cut flat at its ends (the
    # default cube's 96^3 corner to an energy accuracy of 1e-4: 32 iterations against 45 from the planes;
    # the lumbar micro-CT's central 128^3: 23 against 27; the whole cube: 60 against 97, 29.8 s against
    # 42.3) and the solution itself on a dense block; the planes' where the platens touch little and much
    # solid hangs off the load path (the data folder's CT at its own voxel: a piece of ribs from the block's
    # stood at an energy error of 3.5e-2 after 737 iterations). The block's loads are an element's own in
    # every solid voxel (an affine field differs from voxel to voxel by a translation), looked up on the live
    # nodes pcg asks for, and its energy is the voxels' sum in closed form.
    lateral = 0.0 if bonded else mat.nu
    stretch = np.full(3, lateral * strain)
    stretch[axis] = -strain
    ue = -strain * macro[axis] + lateral * strain * sum(macro[a] for a in range(3) if a != axis)
    block_energy = ns * float(ue @ model.ke @ ue)
    planes_energy, planes_loads = _platen_planes(op, model, axis, top, -strain * length, free)
    from_block = block_energy <= planes_energy
    if from_block:
        del planes_loads
        fe = -(model.ke @ ue)[None]
        hand = [lambda nodes: element_loads(model, fe, nodes)]  # masked to the free unknowns by pcg
    else:
        # handed to pcg with no name left on it here, so that pcg releases a whole-grid one once it has read
        # its live nodes
        hand = [planes_loads]
        del planes_loads
    lifting = np.array([block_energy if from_block else planes_energy])
    info = {}
    x, iterations, res = pcg(op, precond, hand.pop(), free, scale=scale, tol=tol, maxiter=maxiter,
                             progress=progress, energy=lifting, accuracy=accuracy, info=info)
    del precond  # the levels' matrices and the cycle's masks, before the whole-grid vectors below
    u = x  # the lifting added in place (x is 0 on the fixed unknowns)
    if from_block:
        add_strain(u[0].reshape((3,) + tuple(shape)), node_axes(shape, h), np.diag(stretch))
    else:
        u[0, axis, top] = -strain * length
    # the platens' work is u.K u, above the converged one by the solution's energy error e.K e (u's error
    # lies on the free unknowns, where K u* is 0): second order in it, whatever the CG started from (the
    # upper platen's reaction times its travel is that only where the CG's iterate keeps Galerkin's
    # orthogonality to its start)
    work = float(np.einsum("cdn,cdn->", u, op(u)))  # not np.vdot: see pcg's dot products
    force = work / (strain * length)  # kN on the upper platen, compression positive
    eps = element_strains(model, u[0])  # (6, ns)
    field_vm = np.zeros(shape, np.float32)
    field_vm[model.solid] = von_mises_strain(eps)
    field_vm = field_vm[: kept.shape[0], : kept.shape[1], : kept.shape[2]]
    return float(force), field_vm, int(iterations), float(res.max()), float(info["energy_error"][0]), bool(info["met"].all())


# ----------------------------------------------------------------------------- moduli


def engineering_constants(C: np.ndarray, solid: float | None = None) -> dict:
    """Young's and shear moduli, Poisson's ratios and the universal anisotropy index of a tensor.

    A direction with no load path (its stiffness below :data:`NO_LOAD_PATH` of the largest, or of
    `solid`, the solid material's own largest stiffness entry, GPa, when that is larger: a sample with no
    load path anywhere has only the solver's rounding, some 1e-12 GPa, which is no stiffness)
    gets modulus 0 and a note; the rest come from the compliance of the remaining block. A
    block that still cannot be inverted gives every modulus 0 and a note, not an error.

    Parameters
    ----------
    C : (6, 6) float ndarray, GPa

    Returns
    -------
    dict
        ``youngs_modulus_gpa`` {x, y, z}, ``shear_modulus_gpa`` {yz, xz, xy}, ``poisson_ratio``
        {xy, xz, yz, yx, zx, zy} (nu_ij = -eps_j / eps_i under stress along i),
        ``anisotropy_index`` (Ranganathan & Ostoja-Starzewski 2008, 0 when isotropic; None when
        the tensor cannot be inverted), ``notes``.
    """
    C = np.asarray(C, float)
    diag = np.diag(C)
    top = max(diag.max() if diag.size else 0.0, float(solid or 0.0))
    keep = np.flatnonzero(diag > NO_LOAD_PATH * top) if top > 0 else np.array([], int)
    notes = []
    S = np.zeros((6, 6))
    dropped = [VOIGT[i] for i in range(6) if i not in keep]
    if dropped:
        notes.append(f"no load path for {', '.join(dropped)}: those moduli are 0")
    ok = keep.size > 0
    if ok:
        sub = C[np.ix_(keep, keep)]
        if np.linalg.cond(sub) > 1e12:
            ok = False
        else:
            S[np.ix_(keep, keep)] = np.linalg.inv(sub)
    if not ok:
        notes.append("the stiffness tensor cannot be inverted: every modulus reported as 0")
        S[:] = 0
    inv = lambda v: float(1 / v) if v > 0 else 0.0  # noqa: E731
    youngs = {a: inv(S[i, i]) for i, a in enumerate("xyz")}
    shear = {VOIGT[i]: inv(S[i, i]) for i in range(3, 6)}
    poisson = {}
    for i, a in enumerate("xyz"):
        for j, b in enumerate("xyz"):
            if i != j:
                poisson[a + b] = float(-S[i, j] / S[i, i]) if S[i, i] > 0 else 0.0
    anis = None
    if ok and keep.size == 6:
        Kv = (C[:3, :3].sum()) / 9
        Gv = (np.trace(C[:3, :3]) - (C[0, 1] + C[0, 2] + C[1, 2]) + 3 * np.trace(C[3:, 3:])) / 15
        Kr = 1 / S[:3, :3].sum()
        Gr = 15 / (4 * np.trace(S[:3, :3]) - 4 * (S[0, 1] + S[0, 2] + S[1, 2]) + 3 * np.trace(S[3:, 3:]))
        anis = float(5 * Gv / Gr + Kv / Kr - 6)
    return {"youngs_modulus_gpa": youngs, "shear_modulus_gpa": shear, "poisson_ratio": poisson,
            "anisotropy_index": anis, "notes": notes}


def hashin_shtrikman_upper(E: float, nu: float, solid_fraction: float) -> tuple[float, float]:
    """Hashin-Shtrikman upper bounds (bulk K, shear G, GPa) of a solid with pores (Hashin &
    Shtrikman 1963, J Mech Phys Solids 11:127, with the second phase void). The lower bound is 0."""
    K1, G1 = E / (3 * (1 - 2 * nu)), E / (2 * (1 + nu))
    phi, p = solid_fraction, 1 - solid_fraction
    K = 4 * G1 * K1 * phi / (4 * G1 + 3 * K1 * p)
    G = G1 + p / (-1 / G1 + 6 * phi * (K1 + 2 * G1) / (5 * G1 * (3 * K1 + 4 * G1)))
    return float(K), float(G)


def voigt_averages(C: np.ndarray) -> tuple[float, float]:
    """Voigt averages (bulk, shear, GPa) of a stiffness tensor: its mean over orientations."""
    C = np.asarray(C, float)
    K = C[:3, :3].sum() / 9
    G = (np.trace(C[:3, :3]) - (C[0, 1] + C[0, 2] + C[1, 2]) + 3 * np.trace(C[3:, 3:])) / 15
    return float(K), float(G)


# ----------------------------------------------------------------------------- report


def choose_boundary(solid: np.ndarray) -> str:
    """``periodic`` for a box sample, ``kinematic`` for a shaped one.

    A box sample (a cube cut from a lattice, a generated box scaffold) shows its solid on
    every face of its box at about the volume's solid fraction; a patient-shaped sample or a
    bone touches its bounding box only in places. Half the volume's fraction on every face
    tells them apart.
    """
    phi = solid.mean()
    faces = [np.take(solid, i, axis=a).mean() for a in range(3) for i in (0, -1)]
    return "periodic" if min(faces) >= 0.5 * phi else "kinematic"


#: the platens' contact (the solid of the sample's end planes along the compression axis, the smaller
#: end's) under this share of the sample's mean solid cross-section: the apparent modulus is the contacts'
#: (a whole femur between platens along its axis: 0.623, 1.22 and 0.146 GPa at 1.5, 1 and 0.75 mm voxels),
#: and the report says so in place of a verdict. A cut sample's ends hold about its mean section
CONTACT_SHARE = 0.25


def platen_contact(solid: np.ndarray, axis: int, h: float) -> dict:
    """The solid the compression's platens touch, beside the sample's mean solid cross-section.

    Returns
    -------
    dict
        ``bottom_mm2``, ``top_mm2``: the solid area of the sample's first and last planes along `axis`;
        ``mean_section_mm2``: its solid volume over its length; ``share``: the smaller end's over that.
    """
    ends = [int(np.count_nonzero(np.take(solid, i, axis=axis))) * h * h for i in (0, -1)]
    mean = int(np.count_nonzero(solid)) * h ** 3 / (solid.shape[axis] * h)
    return {"bottom_mm2": ends[0], "top_mm2": ends[1], "mean_section_mm2": mean,
            "share": min(ends) / mean if mean > 0 else 0.0}


def bone_verdict(modulus_gpa: float) -> str:
    """A plain-words verdict on stress shielding for an apparent modulus (GPa)."""
    t_lo, t_hi, _ = BONE_BANDS["trabecular"]
    c_lo, c_hi, _ = BONE_BANDS["cortical"]
    e = f"{modulus_gpa:.3g} GPa"
    if modulus_gpa <= 0:
        return "no load path along the test axis: the scaffold carries no load there"
    if modulus_gpa < t_lo:
        return f"{e} is softer than trabecular bone ({t_lo}-{t_hi} GPa): no stress shielding, but it may not carry load"
    if modulus_gpa <= t_hi:
        return f"{e} lies in trabecular bone's band ({t_lo}-{t_hi} GPa): little risk of stress shielding"
    if modulus_gpa < c_lo:
        return (f"{e} is stiffer than trabecular bone ({t_lo}-{t_hi} GPa) and softer than cortical bone "
                f"({c_lo}-{c_hi} GPa): it would shield cancellous bone from stress, not cortical bone")
    if modulus_gpa <= c_hi:
        return (f"{e} lies in cortical bone's band ({c_lo}-{c_hi} GPa): right for a cortical defect, "
                "too stiff for cancellous bone")
    return f"{e} is stiffer than cortical bone ({c_lo}-{c_hi} GPa): a risk of stress shielding"


def most_strained(field_vm: np.ndarray, h: float, origin=(0.0, 0.0, 0.0), count: int = 10) -> list[dict]:
    """The `count` voxels of highest equivalent strain: index, centre (mm) and strain; `origin` is the centre
    of voxel [0, 0, 0] (mm, as :class:`SolveSample` holds it)."""
    flat = field_vm.ravel()
    count = min(count, int((flat > 0).sum()))
    if count == 0:
        return []
    top = np.argpartition(flat, -count)[-count:]
    top = top[np.argsort(flat[top])[::-1]]
    out = []
    for t in top:
        ijk = np.unravel_index(t, field_vm.shape)
        out.append({"index": [int(v) for v in ijk],
                    "centre_mm": [round(float(o + i * h), 6) for o, i in zip(origin, ijk)],
                    "von_mises_strain": float(flat[t])})
    return out


@_keeping_freed_memory
def measure(solid, h: float, mat: Material, *, boundary: str = "auto", axis: int = 2, tol: float | None = None,
            backend: str = "numpy", origin=(0.0, 0.0, 0.0),
            preconditioner: str = "multigrid", progress=None,
            cases_per_block: int = CASES_PER_BLOCK) -> tuple[dict, Compression]:
    """Every mechanical figure of a voxel sample, as the report's ``mechanics`` section.

    Parameters
    ----------
    solid : (n1, n2, n3) bool ndarray
    h : float, mm
    mat : Material
    boundary : {"auto", "periodic", "kinematic"}
        ``auto``: :func:`choose_boundary`.
    axis : int
        The compression axis (0, 1, 2 for x, y, z).
    tol : float, optional
        Relative residual of the CG solves (the report's ``solver.tolerance``). None, the default:
        :data:`TOL`, or sooner the energy accuracy :data:`ACCURACY` (the report's ``solver.accuracy``), which
        stops where the figures have converged; a tolerance given is the stop alone.
    origin : (3,) floats, mm
        The centre of ``solid[0, 0, 0]``: where the most strained voxels are placed.
    preconditioner : {"multigrid", "fft"}
        See :func:`make_preconditioner`.
    progress : callable, optional
        (solve name, iteration, residual) after every CG iteration of each solve.
    cases_per_block : int
        The homogenization's load cases per CG block (:func:`homogenize`).

    Returns
    -------
    dict, Compression
        The keys of issue 14 (``stiffness_tensor_gpa`` ... ``solver``), the bone bands and the
        verdict; the compression with its strain field (for the report's picture).
    """
    solid = check_solid(solid)
    if boundary == "auto":
        boundary = choose_boundary(solid)
    # compression first: it refuses a solid with no load path
    def named(name):
        if progress is None:
            return None

        def one(it, res, energy=None, part=()):
            _call_progress(progress, name, it, res, energy=energy, part=part)

        one.takes_energy = True
        one.takes_part = True
        return one

    accuracy = solve_accuracy(tol)
    tol = solve_goal(tol)
    if backend == "opencl":
        from .mechanics_cl import prebuild, solve_variants

        prebuild(solve_variants(cases_per_block, solid.shape, boundary))
    comp = compress(solid, h, mat, axis=axis, tol=tol, backend=backend, preconditioner=preconditioner,
                    progress=named("compression"), accuracy=accuracy)
    hom = homogenize(solid, h, mat, boundary=boundary, tol=tol, backend=backend, preconditioner=preconditioner,
                     progress=named("homogenization"), cases_per_block=cases_per_block, accuracy=accuracy)
    errors = [e for e in (hom.energy_error, comp.energy_error) if np.isfinite(e)]
    consts = engineering_constants(hom.stiffness, float(np.diag(isotropic_tensor(mat.E_gpa, mat.nu)).max()))
    K_hs, G_hs = hashin_shtrikman_upper(mat.E_gpa, mat.nu, hom.solid_fraction)
    bc_text = {"periodic": "periodic (the sample repeats: periodic fluctuations about a uniform strain)",
               "kinematic": "kinematic (uniform displacement u = E x on the faces of the box)"}[boundary]
    notes = list(consts["notes"])
    if comp.dropped_voxels:
        notes.append(f"{comp.dropped_voxels} solid voxels do not join both platens and carry no load in compression")
    if hom.dropped_voxels:
        notes.append(f"{hom.dropped_voxels} solid voxels lie in pieces that reach no face of the box: held by nothing, "
                     "they carry no load and were left out of the homogenization")
    solves = {name: {"iterations": int(sol.iterations), "residual": float(sol.residual),
                     "energy_error": float(sol.energy_error) if np.isfinite(sol.energy_error) else None,
                     "stopped_by": stopped_by(sol, tol, accuracy)}
              for name, sol in (("homogenization", hom), ("compression", comp))}
    unmet = [name for name, sol in solves.items() if sol["stopped_by"] is None]
    warning = None
    if unmet:
        def short(name):
            sol = solves[name]
            text = f"the {name}'s CG stopped at residual {sol['residual']:.2g}, above the tolerance {tol:g}"
            if accuracy is not None:
                err = "unknown" if sol["energy_error"] is None else f"{sol['energy_error']:.2g}"
                text += f", with its energy error ({err}) above the accuracy {accuracy:g}"
            return text

        warning = ("; ".join(short(name) for name in unmet) + ": no further descent (the products' rounding) or the "
                   "iteration limit; the figures are as converged as that residual")
        notes.append(warning)
    for name, pieces in (("compression", comp.pieces), ("homogenization", hom.pieces)):
        if pieces > 1:
            notes.append(f"the {name} solved its {pieces} pieces that share no node apart, each on its own box "
                         "(independent systems: the same figures, in fewer iterations); its iterations are the "
                         "slowest piece's")
    contacts = [platen_contact(solid, a, h) for a in range(3)]  # the compression's, and the kinematic faces'
    contact = contacts[axis]
    verdict = bone_verdict(comp.apparent_modulus_gpa)
    contact_warning = None
    if comp.apparent_modulus_gpa > 0 and contact["share"] < CONTACT_SHARE:
        contact_warning = (f"the platens touch {contact['bottom_mm2']:.3g} and {contact['top_mm2']:.3g} mm2 of solid, "
                           f"{100 * contact['share']:.2g} % of the sample's mean solid cross-section "
                           f"({contact['mean_section_mm2']:.3g} mm2): the compression's modulus is its contacts', not "
                           f"the sample's; cut the sample flat at its ends along {'xyz'[axis]} (generate's --clip or "
                           "--cut-planes cut a patient so), or compress it along another axis (--axis)")
        notes.append(contact_warning)
        verdict = f"not judged: the platens touch {100 * contact['share']:.2g} % of the sample's mean cross-section"
    if boundary == "kinematic":
        # the box's faces hold u = E x: an axis whose faces the solid barely touches is loaded through those contacts
        shares = {"xyz"[a]: contacts[a]["share"] for a in range(3)}
        thin = [a for a, v in shares.items() if v < CONTACT_SHARE]
        if thin:
            notes.append("the kinematic conditions hold the box's faces, which the solid touches with "
                         + ", ".join(f"{100 * shares[a]:.2g} %" for a in thin) + " of its mean solid cross-section "
                         + f"along {', '.join(thin)}: the moduli along {'that axis' if len(thin) == 1 else 'those axes'} "
                         "are those contacts' as much as the sample's")
    report = {
        "stiffness_tensor_gpa": [[float(v) for v in row] for row in hom.stiffness],
        "voigt_order": list(VOIGT),
        "youngs_modulus_gpa": consts["youngs_modulus_gpa"],
        "shear_modulus_gpa": consts["shear_modulus_gpa"],
        "poisson_ratio": consts["poisson_ratio"],
        "anisotropy_index": consts["anisotropy_index"],
        "solid_fraction": hom.solid_fraction,
        "boundary_conditions": bc_text,
        "material": {"name": mat.name, "E_gpa": mat.E_gpa, "nu": mat.nu, "source": mat.source},
        "compression": {"axis": "xyz"[axis], "apparent_modulus_gpa": comp.apparent_modulus_gpa,
                        "platens": "rigid, lubricated (ISO 13314 setting)", "applied_strain": comp.strain,
                        "platen_contact": contact, "warning": contact_warning,
                        "most_strained_voxels": most_strained(comp.von_mises_strain, h, origin)},
        "solver": {"iterations": {"homogenization": hom.iterations, "compression": comp.iterations},
                   "pieces": {"homogenization": hom.pieces, "compression": comp.pieces},
                   "residual": max(hom.residual, comp.residual), "tolerance": float(tol),
                   "accuracy": accuracy, "energy_error": max(errors) if errors else None,
                   "solves": solves, "converged": not unmet, "warning": warning,
                   "seconds": round(hom.seconds + comp.seconds, 4),
                   "method": "matrix-free voxel FE (trilinear hexahedra), block PCG, "
                             + {"multigrid": "geometric multigrid (Galerkin) preconditioner",
                                "fft": "FFT reference-medium preconditioner"}[preconditioner],
                   "preconditioner": preconditioner, "backend": backend, "voxel_mm": float(h),
                   "grid_shape": list(solid.shape)},
        "hashin_shtrikman_upper_gpa": {"bulk": K_hs, "shear": G_hs},
        "bone_bands_gpa": {k: {"low": lo, "high": hi, "source": src} for k, (lo, hi, src) in BONE_BANDS.items()},
        "stress_shielding": verdict,
        "notes": notes,
    }
    return report, comp


def stopped_by(solve, tol: float, accuracy: float | None) -> str | None:
    """What ended a solve's CG (a :class:`Homogenization` or :class:`Compression`): ``"residual"`` (every
    case's relative residual at most `tol`), ``"energy"`` (some case stopped on its energy error, at most
    `accuracy`, and every other on its residual), or None: not every case met a stop (the iteration limit,
    or no further descent: a search direction of no positive curvature, the products' rounding)."""
    if not solve.converged:
        return None
    return "residual" if solve.residual <= tol or accuracy is None else "energy"


# ----------------------------------------------------------------------------- memory and the voxel of a solve


#: What :func:`measure` holds at its peak over what the process held before it: the larger of the
#: homogenization's and the platen compression's (one load case, in double), each a fixed part
#: (:data:`SOLVE_FIXED_BYTES`: the multigrid's compiled kernels, the device's programs) and parts
#: - per node of the solve's grid (masks, the inverse diagonal, the first coarse level);
#: - per node of the V-cycle's fine level held at a time (:func:`cycle_nodes`: its float vectors span the
#:   whole grid up to :data:`~implicit_scaffold.measure.mechanics_cl.FLOAT_SLABS_FROM` nodes, and a slab of
#:   some :data:`~implicit_scaffold.measure.mechanics_cl.FLOAT_SLAB_NODES` with its halo above it);
#: - per live node (a node a solid voxel touches), and for the homogenization per live node and load case
#:   of a CG block (the CG's vectors: x and r in double, p in float, on the live nodes only);
#: - per solid voxel (the coarse levels' matrices).
#: Fitted by a linear program (the least sum of estimates with each at least 1.2 times its row) and
#: rounded up, on the fresh-process peaks above the start (kernels loaded before: VmHWM over the resident
#: set) of gyroids at 30 and 60 % solid and of the central N^3 of the lumbar trabecular micro-CT (kinematic
#: and platens), ``python benchmarks/bench_mechanics.py --sizes --memory 64 96 128 --memory-solves
#: homogenize --preconditioners multigrid --memory-blocks 1,6``, the same with ``--memory-solves compress
#: --memory-blocks 1``, ``--memory 272 --memory-solves compress,homogenize --memory-blocks 1 --maxiter 5``
#: and ``--memory-bone 128 200 300 --memory-solves compress,homogenize --memory-blocks 1 --maxiter 5``
#: (2026-12-06, 8774f57; MiB above the start, the estimate in brackets; 64^3 and 96^3: 1.2-3.1 times):
#:
#: ============  ==============  ===============  ===============  ===============  ===============
#: grid          solid           1 case periodic  1 case kinem.    6 cases periodic 6 cases kinem.
#: ============  ==============  ===============  ===============  ===============  ===============
#: 128^3         0.30            201.6 (369.4)    265.7 (386.9)    518.7 (626.6)    562.9 (705.9)
#: 128^3         0.60            271.4 (417.9)    420.1 (526.9)    687.3 (917.6)    786.9 (1146.7)
#: 272^3         0.30            1785.4 (2163.5)  2022.7 (2764.5)
#: 272^3         0.60            2165.8 (2623.3)  3400.5 (4100.7)
#: 128^3 bone    0.29                             300.1 (395.7)
#: 200^3 bone    0.25                             952.6 (1153.3)
#: 300^3 bone    0.24                             2903.1 (3501.4)
#: ============  ==============  ===============  ===============  ===============  ===============
#:
#: The compression (platens): 128^3 gyroids 271.1 (397.9) and 365.2 (487.8), 272^3 2258.8 (2725.2) and
#: 2970.2 (3585.2); the micro-CT's 128^3, 200^3 and 300^3 298.5 (399.2), 988.2 (1191.7) and 2850.1 (3438.3).
#: The estimate before (per node and per node and case, no live or cycle part) lay 1.40-1.64 times over the
#: micro-CT's rows and refused the whole micro-CT under the default 4 GiB (4.3 GiB asked beside 220 MiB
#: held); the fine level's slabs above 2^24 nodes (the 272^3 and 300^3 rows) hold less a node than whole
#: grids, which an estimate per node alone could not follow. One row was measured again: the first
#: kinematic six-case 64^3 run built a kernel variant inside its count (272.0 MiB; the first program a
#: process compiles loads the runtime's compiler, some 150 MiB), 112.4 MiB with the build cached. Measured
#: again on aa6d110 (README, "The estimate refitted"), the one-case rows moved by up to 20.9 MiB (the 128^3
#: 30 % compression: 292.0 against 271.1); the least ratio there was 1.199 (272^3, 30 %, compression:
#: 2,273.3 against 2,725.2). The fit counted a slab as 2^22 nodes; :func:`cycle_nodes` now counts its whole planes
#: and two halo planes, as :func:`~implicit_scaffold.measure.multigrid.fine_slab_planes` makes them, which raises
#: the 272^3 and 300^3 estimates by at most 1.6 MiB (2,725.2 to 2,726.8).
#: Since one case a block runs by slabs (:func:`one_case_slabs`), with the coarse levels' half stencils and the
#: leaner set-up, the one-case homogenizations hold less than the fit saw: ``--memory 128 --memory-solves
#: homogenize --memory-blocks 1`` (2026-12-07) 149.8, 219.1, 216.2 and 338.3 MiB (periodic 0.30, 0.60, kinematic
#: 0.30, 0.60) against 201.6, 271.4, 265.7 and 420.1 above, the estimates 397.9-526.9 MiB (1.56-2.66 times; the
#: compression's part is the larger there). The parts are left as fitted: the estimate stays above every row.
SOLVE_FIXED_BYTES = {"multigrid": 100 * 2**20, "fft": 120 * 2**20}
SOLVE_BYTES_PER_NODE = {"multigrid": {"periodic": 76, "kinematic": 67},
                        "fft": {"periodic": 700, "kinematic": 950}}
SOLVE_BYTES_PER_CYCLE_NODE = {"multigrid": {"periodic": 33, "kinematic": 3},
                              "fft": {"periodic": 0, "kinematic": 0}}
SOLVE_BYTES_PER_LIVE_NODE_CASE = {"multigrid": {"periodic": 79, "kinematic": 98},
                                  "fft": {"periodic": 0, "kinematic": 0}}
SOLVE_BYTES_PER_SOLID_VOXEL = {"multigrid": {"periodic": 0, "kinematic": 133},
                               "fft": {"periodic": 1900, "kinematic": 1900}}
#: The platen compression's part (:func:`compress`), which :func:`measure` runs first, on the box's nodes
#: (one more per axis than the voxels): per node, per node of the V-cycle's fine level held at a time, per
#: live node and per solid voxel (the fit above). Before the compression's mask went to float32 and its
#: lifting was dropped after the right-hand side, the whole micro-CT's compression held 5.7 GiB against the
#: former estimate's 4.1: the overshoot of ``--max-memory 4.4G`` in README, "The whole micro-CT as a user
#: runs it, again".
COMPRESS_BYTES_PER_NODE = {"multigrid": 88, "fft": 0}
COMPRESS_BYTES_PER_CYCLE_NODE = {"multigrid": 13, "fft": 0}
COMPRESS_BYTES_PER_LIVE_NODE = {"multigrid": 34, "fft": 0}
COMPRESS_BYTES_PER_SOLID_VOXEL = {"multigrid": 115, "fft": 0}
#: live nodes per solid voxel where the solid is not at hand (a field's sample before it is sampled): a rod
#: :data:`MIN_VOXELS_PER_WALL` voxels across touches (3.5 / 2.5)^2 = 1.96 nodes a voxel, a plate 1.4; the
#: lumbar micro-CT 1.36, the 128^3 and 200^3 Voronoi scaffolds of the README's benchmark (30 % solid) 1.51 and 1.50
LIVE_NODES_PER_SOLID_VOXEL = 2.0
#: What a solve's libraries add to a process that has not loaded them before its start: numba's compiled
#: level kernels (67 MiB) and the OpenCL context with its runtime (126 MiB), each measured in a fresh
#: process as the resident set after ``malloc_trim`` (the mechanics program and its first products, 90 MiB
#: more, are inside :data:`SOLVE_FIXED_BYTES`)
SOLVE_LOAD_BYTES = {"numba": 70 * 2**20, "opencl": 130 * 2**20}
#: the sampled field (float32), its copy for the level (:func:`keep_volume`) and the solid (bool)
#: of a solve, per voxel of its grid
SAMPLE_BYTES_PER_VOXEL = 9
#: what a refusal's budget and voxel leave beside the estimate: 8 MiB and this share of what the
#: process holds, which moves by some MiB from one run to the next (heap fragments, library pages)
HELD_MARGIN_SHARE = 0.02


def held_margin(held: int) -> int:
    """Bytes a refusal's budget and voxel leave beside the estimate when the process holds `held`."""
    return int(8 * 2**20 + HELD_MARGIN_SHARE * held)
#: the field a scan or a sampling pass reads at once (bytes): a few planes of a large grid
SAMPLE_CHUNK_BYTES = 64 * 2**20
#: Voxels across the median Voronoi wall (the report's ``wall_thickness_mm``): generate's own
#: default voxel (``pipeline.VOXELS_PER_WALL``). Coarser, the report warns. Measured on a 1.6 mm
#: cube, 0.6 mm pores, porosity 0.7, Ti-6Al-4V, generated at 4 across and at 8 (h/2): the
#: platens' modulus +0.96 % (seed 0) and -0.06 % (seed 1), the periodic moduli at most +2.94 %
#: (``python benchmarks/bench_mechanics.py --sizes --across 4 5 6 8``); the field built at 8
#: across and sampled at 4, +2.6 % (``--coarsen 1.6``); at 2.67 across, +9.1 %; at 2, -6.9 %.
#: (Before the blend read the lattice mirrored in the cells' walls, a film on the cube's faces
#: made the modulus climb with every refinement: -3.8 % at 4 across, -9.5 % at 8. README, "The
#: voxel of a solve and its memory".)
CONVERGED_VOXELS_PER_WALL = 4.0
#: below this many voxels across the median wall the default voxel refuses instead of coarsening
#: (the 2.67- and 2-across samples above were 4.7-9.1 % and 1.2-6.9 % off; before the mirror, 2 across was 10-16 % off)
MIN_VOXELS_PER_WALL = 2.5


def live_nodes(solid) -> int:
    """The nodes a solid voxel touches on a box sample's node grid (one more per axis than `solid`)."""
    solid = np.asarray(solid, bool)
    n1, n2, n3 = solid.shape
    touched = np.zeros((n1 + 1, n2 + 1, n3 + 1), bool)
    for a, b, c in CORNERS:
        touched[a:a + n1, b:b + n2, c:c + n3] |= solid
    return int(np.count_nonzero(touched))


def _load_bytes() -> int:
    """:data:`SOLVE_LOAD_BYTES` of the libraries this process has not loaded yet (the device programs a
    measure compiles are compiled in a child: :func:`~implicit_scaffold.measure.mechanics_cl.prebuild`)."""
    from .. import opencl
    from .multigrid import kernels_loaded

    return ((0 if kernels_loaded() else SOLVE_LOAD_BYTES["numba"])
            + (0 if opencl.active() else SOLVE_LOAD_BYTES["opencl"]))


def cycle_nodes(node_shape) -> int:
    """The nodes whose float vectors the V-cycle's fine level holds at a time on a node grid of `node_shape`:
    all of them, or a slab's with its two halo planes where the fine level runs by slabs (a grid of more than
    :data:`~implicit_scaffold.measure.mechanics_cl.FLOAT_SLABS_FROM` nodes:
    :func:`~implicit_scaffold.measure.multigrid.fine_slab_planes`)."""
    from .multigrid import fine_slab_planes

    n1, n2, n3 = (int(v) for v in node_shape)
    thick = fine_slab_planes(node_shape)
    return n1 * n2 * n3 if thick >= n1 else (thick + 2) * n2 * n3


def solve_memory(shape, solid_voxels: int, *, boundary: str = "periodic", preconditioner: str = "multigrid",
                 cases_per_block: int = 1, live: int | None = None) -> int:
    """Bytes :func:`measure` holds at its peak over what the process held before it (an estimate).

    Parameters
    ----------
    shape : (3,) ints
        The sample's voxels (a kinematic or platen sample's node grid has one more per axis).
    solid_voxels : int
    boundary : {"periodic", "kinematic"}
    preconditioner : {"multigrid", "fft"}
    cases_per_block : int
        The homogenization's load cases per CG block (1-6); the default, 1, is the least a solve
        needs, which the checks before a solve hold it to (:func:`check_solve`, :func:`solid_for_solve`:
        a larger budget then takes larger blocks, :func:`block_for`).
    live : int, optional
        The nodes a solid voxel touches (:func:`live_nodes`); default :data:`LIVE_NODES_PER_SOLID_VOXEL`
        per solid voxel.

    Returns
    -------
    int, bytes
        The larger of the compression's and the homogenization's need, plus :data:`SOLVE_FIXED_BYTES` and
        the libraries' load (:data:`SOLVE_LOAD_BYTES`, of those not loaded yet). The homogenization:
        :data:`SOLVE_BYTES_PER_NODE` per node, :data:`SOLVE_BYTES_PER_CYCLE_NODE` per node of the V-cycle's
        fine level at a time (:func:`cycle_nodes`), :data:`SOLVE_BYTES_PER_LIVE_NODE_CASE` per live node and
        load case of a block, :data:`SOLVE_BYTES_PER_SOLID_VOXEL` per solid voxel; the compression (on the
        box's nodes, one more per axis): :data:`COMPRESS_BYTES_PER_NODE`, :data:`COMPRESS_BYTES_PER_CYCLE_NODE`,
        :data:`COMPRESS_BYTES_PER_LIVE_NODE` and :data:`COMPRESS_BYTES_PER_SOLID_VOXEL`.
    """
    node_shape = [int(s) + (boundary != "periodic") for s in shape]
    box_shape = [int(s) + 1 for s in shape]
    nodes = int(np.prod(node_shape, dtype=np.int64))
    box_nodes = int(np.prod(box_shape, dtype=np.int64))
    count = int(solid_voxels)
    live = min(box_nodes, int(LIVE_NODES_PER_SOLID_VOXEL * count)) if live is None else int(live)
    block = max(1, min(6, int(cases_per_block)))
    homogenization = (SOLVE_BYTES_PER_NODE[preconditioner][boundary] * nodes
                      + SOLVE_BYTES_PER_CYCLE_NODE[preconditioner][boundary] * cycle_nodes(node_shape)
                      + SOLVE_BYTES_PER_LIVE_NODE_CASE[preconditioner][boundary] * block * live
                      + SOLVE_BYTES_PER_SOLID_VOXEL[preconditioner][boundary] * count)
    compression = (COMPRESS_BYTES_PER_NODE[preconditioner] * box_nodes
                   + COMPRESS_BYTES_PER_CYCLE_NODE[preconditioner] * cycle_nodes(box_shape)
                   + COMPRESS_BYTES_PER_LIVE_NODE[preconditioner] * live
                   + COMPRESS_BYTES_PER_SOLID_VOXEL[preconditioner] * count)
    return int(SOLVE_FIXED_BYTES[preconditioner] + _load_bytes() + max(homogenization, compression))


def block_for(allowance: int, shape, solid_voxels: int, *, boundary: str = "periodic",
              preconditioner: str = "multigrid", live: int | None = None) -> int:
    """The most load cases per CG block (6, 3, 2 or 1: equal blocks) whose solve fits `allowance` bytes
    (:func:`solve_memory`); 1 when none does (the caller refuses on that)."""
    for block in (6, 3, 2):
        if solve_memory(shape, solid_voxels, boundary=boundary, preconditioner=preconditioner,
                        cases_per_block=block, live=live) <= allowance:
            return block
    return 1


def solid_box(field, *, level: float = 0.0, chunk_bytes: int = SAMPLE_CHUNK_BYTES):
    """The bounding box and count of a field's solid voxels (below `level`), read a few planes at a time.

    Parameters
    ----------
    field : (nx, ny, nz) float ndarray or numpy.memmap, mm
    level : float, mm

    Returns
    -------
    lo, hi : (3,) int ndarray, or None when nothing is solid
        The box ``[lo, hi)`` in voxel indices.
    count : int
    """
    nx, ny, nz = field.shape
    rows = max(1, int(chunk_bytes) // (5 * ny * nz))  # the planes read (float32) and their mask
    lo, hi, count = np.array(field.shape), np.zeros(3, np.int64), 0
    for x0 in range(0, nx, rows):
        solid = np.asarray(field[x0:x0 + rows]) < level
        found = int(np.count_nonzero(solid))
        if not found:
            continue
        count += found
        for a, axes in enumerate(((1, 2), (0, 2), (0, 1))):
            idx = np.flatnonzero(solid.any(axis=axes)) + (x0 if a == 0 else 0)
            lo[a], hi[a] = min(lo[a], idx[0]), max(hi[a], idx[-1] + 1)
    return (lo, hi, count) if count else (None, None, 0)


def sample_field(field, grid, lo, hi, voxel: float, *, chunk_bytes: int = SAMPLE_CHUNK_BYTES):
    """A field over the voxels ``[lo, hi)`` of its grid, at another voxel, read a few planes at a time.

    The grid of voxel `voxel` of as many voxels along each axis as the box's length holds, rounded
    (:func:`_shape_at`), centred on the box, gets the field's trilinear value at each of its voxel
    centres (:func:`~implicit_scaffold.fields.field.sample`: the nearest edge value beyond the grid). At the field's
    own voxel, the values are the field's own. A batch of the new grid's planes reads only
    the field's planes around it, so the whole field is never held (a slab run's field is a
    memmap of its store on disk); every value is computed from its eight neighbours and its
    weights from the whole grid's coordinates, so the bits are the same whatever the batches
    and whether the field is an array or a memmap.

    Parameters
    ----------
    field : (nx, ny, nz) float ndarray or numpy.memmap, mm
    grid : Grid
        The field's grid.
    lo, hi : (3,) ints
        The box of the field's voxels to cover, ``[lo, hi)``.
    voxel : float, mm
    chunk_bytes : int
        About what a batch reads and makes.

    Returns
    -------
    values : (m1, m2, m3) float32 ndarray, mm
    out_grid : Grid
        The grid of `values`.
    """
    from ..run.grid import Grid

    lo, hi = np.asarray(lo, np.int64), np.asarray(hi, np.int64)
    h0 = float(grid.spacing)
    if float(voxel) == h0:
        out_grid = Grid(tuple(float(grid.origin[a] + lo[a] * h0) for a in range(3)), h0,
                        tuple(int(v) for v in hi - lo))
        values = np.empty(out_grid.shape, np.float32)
        rows = max(1, int(chunk_bytes) // (4 * int(np.prod(out_grid.shape[1:]))))
        for x0 in range(0, out_grid.shape[0], rows):
            x1 = min(x0 + rows, out_grid.shape[0])
            values[x0:x1] = field[lo[0] + x0:lo[0] + x1, lo[1]:hi[1], lo[2]:hi[2]]
        return values, out_grid
    corner = np.asarray(grid.origin) + (lo - 0.5) * h0
    shape = np.asarray(_shape_at(hi - lo, h0, float(voxel)))
    # centred on the box: its first and last voxels' outer faces within half a voxel of the box's
    origin = corner + ((hi - lo) * h0 - (shape - 1) * float(voxel)) / 2
    out_grid = Grid(tuple(float(v) for v in origin), float(voxel), tuple(int(v) for v in shape))
    values = np.empty(out_grid.shape, np.float32)
    # per axis, the field's plane below each new centre and the weight of the one above, from the
    # whole grid's coordinates: a value's arithmetic is its own whatever the batch it falls in
    # (field.sample's map_coordinates on a batch would take coordinates relative to the batch,
    # whose rounding moves with it), so an array and a slab store give the same bits
    low, weight = [], []
    for a, coords in enumerate(out_grid.axes()):
        f = np.clip((coords - grid.origin[a]) / h0, 0, grid.shape[a] - 1)
        i0 = np.minimum(np.floor(f).astype(np.int64), max(grid.shape[a] - 2, 0))
        low.append(i0)
        weight.append(f - i0)
    (y0, y1), (z0, z1) = [(int(low[a][0]), min(int(low[a][-1]) + 2, grid.shape[a])) for a in (1, 2)]
    iy, iz = low[1] - y0, low[2] - z0
    jy, jz = np.minimum(iy + 1, y1 - y0 - 1), np.minimum(iz + 1, z1 - z0 - 1)
    wy, wz = weight[1][None, :, None], weight[2][None, None, :]
    # a batch of new planes reads its field planes (float32) and holds two interpolated stages (float64)
    per_plane = (4 * (y1 - y0) * (z1 - z0) * max(1.0, float(voxel) / h0)
                 + 8 * out_grid.shape[1] * (2 * (z1 - z0) + out_grid.shape[2]))
    rows = max(1, int(chunk_bytes // per_plane))
    for c0 in range(0, out_grid.shape[0], rows):
        c1 = min(c0 + rows, out_grid.shape[0])
        x0, x1 = int(low[0][c0]), min(int(low[0][c1 - 1]) + 2, grid.shape[0])
        part = np.asarray(field[x0:x1, y0:y1, z0:z1], np.float32)
        ix = low[0][c0:c1] - x0
        jx = np.minimum(ix + 1, x1 - x0 - 1)
        wx = weight[0][c0:c1, None, None]
        along_x = (1 - wx) * part[ix] + wx * part[jx]
        del part
        along_y = (1 - wy) * along_x[:, iy] + wy * along_x[:, jy]
        del along_x
        values[c0:c1] = (1 - wz) * along_y[:, :, iz] + wz * along_y[:, :, jz]
    return values, out_grid


@dataclass
class SolveSample:
    """The solid a solve runs on, at the voxel chosen for it, and why that voxel.

    Attributes
    ----------
    solid : (n1, n2, n3) bool ndarray
        Cropped to its solid voxels' box.
    voxel : float, mm
    origin : (3,) floats, mm
        The centre of ``solid[0, 0, 0]``.
    report : dict
        The ``voxel`` entry of the report's ``mechanics`` section: ``voxel_mm``, ``source_voxel_mm``,
        ``note``, ``warning`` (None or a sentence), ``memory_estimate_bytes`` (:func:`solve_memory` with one
        load case per block, the least the solve needs, which the budget was checked against),
        ``cases_per_block`` (the most the budget holds, :func:`block_for`: the solve's), ``max_memory_bytes``.
    selection : str or None
        A volume's: how its solid was chosen (a label, a CT threshold, or its non-zero voxels).
    """

    solid: np.ndarray
    voxel: float
    origin: tuple
    report: dict
    selection: str | None = None


def keep_volume(values: np.ndarray, solid_voxels: float) -> np.float32:
    """The level below which `solid_voxels` of `values` lie (rounded to a whole voxel, at least one).

    A field sampled at a coarser voxel loses thin walls where no coarse centre falls in them (on a
    Voronoi scaffold at 0.049 mm sampled from its 0.024 mm field: solid 0.2915 against 0.3001
    built at 0.049 mm, ``bench_mechanics.py --coarsen 1.6``); as the run meets its porosity by
    offsetting the surface, the sample keeps the run's solid volume by its own offset.

    Returns
    -------
    numpy.float32, mm
        The smallest float32 above the ``k``-th smallest value: ``values < level`` holds ``k``
        voxels (ties aside).
    """
    k = int(np.clip(np.rint(solid_voxels), 1, values.size))
    kth = np.partition(values.ravel(), k - 1)[k - 1]
    return np.nextafter(np.float32(kth), np.float32(np.inf))


def _round_up(h: float) -> float:
    """`h` rounded up to three significant digits (a voxel a report can print)."""
    step = 10.0 ** (np.floor(np.log10(h)) - 2)
    return float(np.round(np.ceil(h / step - 1e-9) * step, 12))


def _shape_at(n, h0: float, h: float) -> tuple:
    """The voxels of the grid of voxel `h` over a box of `n` voxels of `h0`: the nearest whole number along
    each axis (at least one), so that the sample's box lies within half a voxel of the box a side.

    Not the covering grid (rounded up): a periodic sample then gained up to a voxel's layer beyond its
    period, of the edge's values, which broke the sample's repetition and, with the solid volume kept,
    thinned every strut (a 3 mm cube of 59 voxels of 0.0511 mm at 0.075 mm: 41 voxels, 3.075 mm;
    solid fraction 0.2055 against the field's 0.2185)."""
    return tuple(int(max(np.floor(int(k) * h0 / h + 0.5), 1)) for k in n)


def sample_memory(n, solid_voxels: int, h0: float, h: float, *, boundary: str = "kinematic",
                  preconditioner: str = "multigrid") -> int:
    """Bytes a solve at voxel `h` of a box of `n` voxels of `h0` holding `solid_voxels` needs (an estimate):
    :func:`solve_memory` and the sampled grid, the solid fraction taken to hold at `h`."""
    shape = _shape_at(n, h0, h)
    cells = int(np.prod(shape, dtype=np.int64))
    solid = solid_voxels if h == h0 else int(np.ceil(solid_voxels / np.prod(n, dtype=np.float64) * cells))
    return solve_memory(shape, solid, boundary=boundary, preconditioner=preconditioner) + SAMPLE_BYTES_PER_VOXEL * cells


def finest_voxel(n, solid_voxels: int, h0: float, allowance: float, *, boundary: str = "kinematic",
                 preconditioner: str = "multigrid") -> float | None:
    """The finest voxel, `h0` or coarser (three significant digits), whose solve fits `allowance` bytes
    (:func:`sample_memory`); None when not even a grid two voxels long fits."""
    def need(h):
        return sample_memory(n, solid_voxels, h0, h, boundary=boundary, preconditioner=preconditioner)

    if need(h0) <= allowance:
        return h0
    room = allowance - SOLVE_FIXED_BYTES[preconditioner]
    if room <= 0:
        return None
    # the variable part falls as h^-3: start there, then step up to what the rounding of the grid leaves
    h = _round_up(h0 * max(1.0, ((need(h0) - SOLVE_FIXED_BYTES[preconditioner]) / room) ** (1 / 3)))
    longest = max(int(k) for k in n) * h0
    while need(h) > allowance:
        if h > longest / 2:
            return None
        h = _round_up(h * 1.02)
    return h


def _refusal(h: float, need: int, held: int, total: int, fit: float | None, option: str,
             why: str = "") -> ScaffoldError:
    """The one line that refuses a solve: what it needs, the budget that would do, the voxel that would fit."""
    from ..run.memory import format_size

    named = held + need + held_margin(held)
    return ScaffoldError.for_budget(
        f"the mechanics solve at {h:.4g} mm needs about {format_size(need)} beside the {format_size(held)} "
        f"held, over --max-memory {format_size(total)}{why}; use --max-memory {format_size(named)}"
        + (f" or {option} {fit:.4g}" if fit is not None else ""), named)


def check_solve(solid, h: float, *, max_memory=None, boundary: str = "auto", preconditioner: str = "multigrid",
                option: str = "--voxel") -> dict:
    """Check, before the solve, that a solid held as voxels (a mesh's or a volume's) can be solved in the budget.

    Parameters
    ----------
    solid : (n1, n2, n3) bool ndarray
    h : float, mm
    max_memory : str or int, optional
    boundary, preconditioner : as :func:`solid_for_solve`
    option : str
        The option that sets the sample's voxel, as the refusal names it.

    Returns
    -------
    dict
        The ``voxel`` entry of the report (as :class:`SolveSample`'s).

    Raises
    ------
    ScaffoldError
        The solve does not fit: one line naming the ``--max-memory`` that would do and the voxel that would fit.
    """
    from ..run.memory import budget, release

    total = budget(max_memory)
    held = release()
    bc = "kinematic" if boundary == "auto" else boundary
    count = int(np.count_nonzero(solid))
    live = live_nodes(solid)
    need = solve_memory(solid.shape, count, boundary=bc, preconditioner=preconditioner, live=live)
    if need > total - held:
        fit = finest_voxel(solid.shape, count, h, total - held - held_margin(held), boundary=bc,
                           preconditioner=preconditioner)
        raise _refusal(h, need, held, total, fit, option)
    block = block_for(total - held - held_margin(held), solid.shape, count, boundary=bc, preconditioner=preconditioner,
                      live=live)
    return {"voxel_mm": float(h), "source_voxel_mm": float(h), "warning": None,
            "note": f"mechanics voxel {h:.4g} mm: the sample's own voxel: its solve fits the budget",
            "memory_estimate_bytes": int(need), "cases_per_block": block, "max_memory_bytes": int(total)}


#: the most voxels :func:`resolution_warning` measures the local thickness on (a box about the solid's
#: middle in a larger sample): the maximal spheres take some 10 bytes a voxel
THICKNESS_VOXELS = 2**24


def _middle_box(solid: np.ndarray, voxels: int) -> tuple:
    """A box of at most `voxels` voxels of `solid`'s shape, about the solid's median voxel (each axis's
    median of the solid's voxels, from the counts per plane: no index array)."""
    shape = np.array(solid.shape)
    scale = min(1.0, (voxels / max(1, solid.size)) ** (1 / 3))
    side = np.maximum(1, np.floor(shape * scale).astype(int))
    box = []
    for a in range(3):
        counts = np.count_nonzero(solid, axis=tuple(b for b in range(3) if b != a))
        middle = int(np.searchsorted(np.cumsum(counts), counts.sum() / 2))
        lo = int(np.clip(middle - side[a] // 2, 0, shape[a] - side[a]))
        box.append(slice(lo, lo + int(side[a])))
    return tuple(box)


def resolution_warning(solid: np.ndarray, h: float, kind: str = "mesh") -> str | None:
    """A warning when a sample's struts are too few voxels across for its moduli, else None.

    The measure is the median local thickness of the solid (maximal spheres,
    :func:`~implicit_scaffold.measure.morphometry.local_thickness`, as ``analyze`` reports it; a plate
    ``T`` voxels thick reads ``T``, or ``T + 1`` for odd ``T``), over a box of at most
    :data:`THICKNESS_VOXELS` voxels about the solid's middle; below :data:`CONVERGED_VOXELS_PER_WALL`
    voxels the voxel model is stiffer or softer than its shape by several percent (generate's walls: at 2
    voxels across 10-16 % off, at 4 2-8 %) and its CG needs more iterations.

    Parameters
    ----------
    solid : (nx, ny, nz) bool ndarray
    h : float, mm
    kind : {"mesh", "volume", "field"}
        What the voxels came from: a mesh voxelised at `h`, a volume (a scan, maybe resampled), or a signed
        distance sampled at `h`.
    """
    from .morphometry import local_thickness

    part = np.ascontiguousarray(solid[_middle_box(solid, THICKNESS_VOXELS)])
    if not part.any():
        return None
    wall = float(np.median(local_thickness(part, h)[part]))
    across = wall / h
    if across >= CONVERGED_VOXELS_PER_WALL:
        return None
    finer = {"volume": "a finer --voxel, down to the scan's own, resolves them (finer than the scan adds no detail)",
             "field": "a finer --mechanics-voxel, down to the field's own, resolves them"}.get(
        kind, "a finer --voxel resolves them")
    return (f"the solid's median strut is {across:.1f} voxels across ({wall:.3g} mm local thickness at the "
            f"{h:.4g} mm voxel), fewer than {CONVERGED_VOXELS_PER_WALL:g}: its moduli may lie several % off "
            f"(generate's walls at 2 voxels across: 10-16 %, at 4: 2-8 %) and the solve takes more "
            f"iterations; {finer}")


def plan_voxel(n, solid_voxels: int, h0: float, *, max_memory=None, voxel: float | None = None,
               wall: float | None = None, boundary: str = "auto", preconditioner: str = "multigrid",
               option: str = "--mechanics-voxel", source: str = "run", held_extra: int = 0) -> tuple[float, str, int, int]:
    """The voxel a solve of a solid sampled from a field of voxel `h0` runs at, or its refusal, decided
    from sizes alone: :func:`solid_for_solve` decides with it after a run, and a run that will
    measure what it builds decides with it before the build, from the grid it plans (issue 14).

    Parameters
    ----------
    n : (3,) ints
        The solid's box, in voxels of `h0`.
    solid_voxels : int
        Its solid voxels (an estimate before a build).
    h0 : float, mm
        The field's voxel.
    max_memory, voxel, wall, boundary, preconditioner, option, source
        As :func:`solid_for_solve`.
    held_extra : int, bytes
        What the process will hold beside what it holds now when the solve starts (a build's
        arrays, when the check comes before the build).

    Returns
    -------
    h : float, mm
    why : str
        Why that voxel, for the report's note.
    total, held : int, bytes
        The budget and what the process holds now.

    Raises
    ------
    ScaffoldError
        The solve at `voxel`, or at the finest voxel the default allows, does not fit: one line
        naming the ``--max-memory`` that would do and the voxel that would fit.
    """
    from ..errors import positive_mm
    from ..run.memory import budget, format_size, release

    total = budget(max_memory)
    held = release() + int(held_extra)
    allowance = total - held
    n = tuple(int(k) for k in n)
    count = int(solid_voxels)
    bc = "kinematic" if boundary == "auto" else boundary

    def need(h):
        return sample_memory(n, count, h0, h, boundary=bc, preconditioner=preconditioner)

    # the run's own voxel when it fits; else the finest that fits with the margin (a refusal names it)
    fit = h0 if need(h0) <= allowance else finest_voxel(n, count, h0, allowance - held_margin(held), boundary=bc,
                                                        preconditioner=preconditioner)

    floor = None if wall is None else wall / MIN_VOXELS_PER_WALL
    # a voxel too coarse for the walls is not offered: it would be refused in turn
    offer = fit if fit is not None and (floor is None or fit <= floor) else None

    def refuse(h, why=""):
        raise _refusal(h, need(h), held, total, offer, option, why)

    if voxel is not None:
        h = positive_mm("mechanics-voxel", voxel, example="0.05")
        if wall is not None and wall / h < MIN_VOXELS_PER_WALL:
            # walls under 2.5 voxels break or fuse in the sample: a 3 mm cube's moduli at 1 voxel across its
            # 0.2 mm walls came out 250 times too low, with no word
            raise ScaffoldError(f"{option} {h:.4g} mm leaves {wall / h:.3g} voxels across the {wall:.3g} mm median "
                                f"wall, fewer than {MIN_VOXELS_PER_WALL:g}: the sample's walls would break or fuse; "
                                f"use {option} {round_down(wall / CONVERGED_VOXELS_PER_WALL)} (4 voxels across) "
                                f"or at most {round_down(wall / MIN_VOXELS_PER_WALL)}")
        if need(h) > allowance:
            refuse(h)
        return h, f"the voxel asked for ({option})", total, held
    if fit == h0:
        return h0, f"the {source}'s own voxel: its solve fits the budget", total, held
    if fit is None or (floor is not None and fit > floor):
        target = h0 if wall is None else max(h0, wall / CONVERGED_VOXELS_PER_WALL)
        refuse(target, "" if fit is None else
               f" (the finest voxel that fits, {fit:.4g} mm, leaves fewer than {MIN_VOXELS_PER_WALL:g} "
               f"voxels across the {wall:.3g} mm median wall)")
    return fit, (f"the finest voxel whose solve fits --max-memory {format_size(total)} (the {source}'s "
                 f"{h0:.4g} mm would need about {format_size(held + need(h0) + held_margin(held))})"), total, held


def solid_for_solve(field, grid, *, max_memory=None, voxel: float | None = None, wall: float | None = None,
                    boundary: str = "auto", preconditioner: str = "multigrid",
                    option: str = "--mechanics-voxel", source: str = "run") -> SolveSample:
    """The solid a solve runs on: at `voxel`, or at the finest voxel whose solve fits the budget.

    The memory is checked before anything is sampled or solved: the budget (``--max-memory``)
    less what the process holds now must hold :func:`solve_memory` and the sampled grid.

    Parameters
    ----------
    field : (nx, ny, nz) float ndarray or numpy.memmap, mm
        A signed distance, negative in the solid (a slab run's on disk).
    grid : Grid
    max_memory : str or int, optional
        The budget (:func:`~implicit_scaffold.run.memory.budget`; default 4 GiB or 80 % of the free memory).
    voxel : float, mm, optional
        The solve's voxel; default: the field's own when its solve fits, else the finest that fits.
    wall : float, mm, optional
        The median wall thickness: the default refuses to coarsen to fewer than
        :data:`MIN_VOXELS_PER_WALL` voxels across it, and warns below :data:`CONVERGED_VOXELS_PER_WALL`.
    boundary : {"auto", "periodic", "kinematic"}
        For the estimate (``auto`` counts the kinematic grid, one node more per axis).
    option : str
        The option that sets the voxel, as the refusal names it.
    source : str
        What the field is, as the note names it ("run", "field").

    Raises
    ------
    ScaffoldError
        No solid; or the solve at `voxel` (or at the finest voxel the default allows) does not fit:
        one line naming the ``--max-memory`` that would do and the voxel that would fit.
    """
    from ..run.memory import format_size

    lo, hi, count = solid_box(field)
    if count == 0:
        raise ScaffoldError("the scaffold holds no solid voxel: nothing carries load")
    h0 = float(grid.spacing)
    n = hi - lo
    bc = "kinematic" if boundary == "auto" else boundary
    h, why, total, held = plan_voxel(n, count, h0, max_memory=max_memory, voxel=voxel, wall=wall, boundary=boundary,
                                     preconditioner=preconditioner, option=option, source=source)
    allowance = total - held

    def need(h):
        return sample_memory(n, count, h0, h, boundary=bc, preconditioner=preconditioner)

    warning = None
    for _ in range(8):
        values, sampled = sample_field(field, grid, lo, hi, h)
        # the field's solid fraction over its box (the sample's box may be up to half a voxel a side
        # shorter or longer: its solid volume follows)
        level = keep_volume(values, count / np.prod(n, dtype=np.float64) * values.size) if h != h0 else np.float32(0)
        box_lo, box_hi, solid_count = solid_box(values, level=level)
        if not solid_count:
            raise ScaffoldError(f"at the mechanics voxel {h:.4g} mm no voxel centre lies in the solid; use a finer "
                                f"{option}")
        solid = np.ascontiguousarray(values[tuple(slice(a, b) for a, b in zip(box_lo, box_hi))] < level)
        del values
        origin = tuple(float(sampled.origin[a] + box_lo[a] * h) for a in range(3))
        live = live_nodes(solid)
        estimate = solve_memory(solid.shape, solid_count, boundary=bc, preconditioner=preconditioner, live=live)
        # the estimate took the solid fraction of the field's voxels; the sampled one may hold more
        if voxel is not None or h == h0 or estimate + solid.size <= allowance:
            break
        h = _round_up(h * 1.05)
    converged = None if wall is None else max(h0, wall / CONVERGED_VOXELS_PER_WALL)
    if converged is not None and h > converged * (1 + 1e-9):
        # coarser than the run and than generate's default voxel: the moduli move by more than a few %
        # the way out: the voxel asked for is the user's to make finer; the budget's, a larger budget
        fix = (f"{option} {round_down(converged)} resolves them" if voxel is not None else
               f"--max-memory {format_size(held + need(converged) + held_margin(held))} solves at {converged:.4g} mm")
        warning = (f"the mechanics voxel {h:.4g} mm leaves {wall / h:.1f} voxels across the {wall:.3g} mm median "
                   f"wall, fewer than generate's {CONVERGED_VOXELS_PER_WALL:g} (a 1.6 mm cube sampled at 2: "
                   f"10-16 % off, at 4: 2-8 %); {fix}")
    note = f"mechanics voxel {h:.4g} mm: {why}"
    if h != h0:
        note += (f"; the field sampled (trilinear) at its voxel centres, solid below {float(level):+.4g} mm so that "
                 f"it keeps the {source}'s solid fraction")
    # the load cases per block: as many as the budget holds beside the sampled grid (freed before the solve)
    block = block_for(allowance - held_margin(held), solid.shape, solid_count, boundary=bc,
                      preconditioner=preconditioner, live=live)
    report = {"voxel_mm": h, "source_voxel_mm": h0, "note": note, "warning": warning, "level_mm": float(level),
              "memory_estimate_bytes": int(estimate), "cases_per_block": block, "max_memory_bytes": int(total)}
    return SolveSample(solid, h, origin, report)


def measure_sample(sample: SolveSample, mat: Material, *, boundary: str = "auto", axis: int = 2,
                   progress=None, tol: float | None = None) -> tuple[dict, "Compression"]:
    """:func:`measure` on a :class:`SolveSample`: the report's ``mechanics`` section, whose ``voxel``
    entry says which voxel and why (with the process's peak memory so far), and the compression.

    A sample coarser than the converged voxel warns (:class:`~implicit_scaffold.errors.ScaffoldWarning`), and
    its note says so too.
    """
    import warnings

    from ..errors import ScaffoldWarning
    from ..run.memory import peak_memory

    report, comp = measure(sample.solid, sample.voxel, mat, boundary=boundary, axis=axis, backend="opencl",
                           origin=sample.origin, progress=progress, tol=tol,
                           cases_per_block=sample.report.get("cases_per_block", 6))
    # the process's peak so far, beside the estimate checked before the solve (the solve's is the larger
    # part of it unless the build before peaked higher)
    report["voxel"] = {**sample.report, "process_peak_bytes": peak_memory()}
    report["notes"].append(sample.report["note"])
    if sample.report["warning"]:
        report["notes"].append(sample.report["warning"])
        warnings.warn(sample.report["warning"], ScaffoldWarning, stacklevel=2)
    for warning in (report["solver"]["warning"], report["compression"]["warning"]):  # in the notes already
        if warning:
            warnings.warn(warning, ScaffoldWarning, stacklevel=2)
    return report, comp


# ----------------------------------------------------------------------------- inputs


def load_sample(path, *, voxel: float | None = None, spacing=None, mechanics_voxel: float | None = None,
                max_memory=None, boundary: str = "auto", label=None, threshold=None) -> tuple[SolveSample, str]:
    """The solid of a file at the voxel of its solve, as ``analyze`` reads it, plus a ``.npy`` signed-distance field.

    The solve's memory is checked before anything is solved (:func:`solid_for_solve`,
    :func:`check_solve`), and a binary STL's read before it is read
    (:func:`~implicit_scaffold.measure.morphometry.check_mesh_read`).

    Parameters
    ----------
    path : str or Path
        A closed mesh (voxelised at `voxel`), a volume (binary: solid = non-zero; a label map's
        `label`; a CT's intensities from `threshold` up), or a ``.npy`` field (solid = negative;
        its voxel from `voxel` or the JSON report written beside it).
    voxel, spacing, label, threshold : see :func:`~implicit_scaffold.measure.morphometry.analyze_file`.
    mechanics_voxel : float, mm, optional
        A ``.npy`` field's solve voxel (trilinear samples of the field); default: its own voxel
        when its solve fits `max_memory`, else the finest that fits. A mesh or a volume is
        solved at its `voxel`.
    max_memory : str or int, optional
        The budget (default 4 GiB, or 80 % of the free memory when less).
    boundary : {"auto", "periodic", "kinematic"}

    Returns
    -------
    sample : SolveSample
        The solid cropped to its solid voxels' box (a mesh's margin layer removed).
    kind : str
    """
    from pathlib import Path

    from ..run.grid import Grid
    from .morphometry import read_scaffold

    from ..run.memory import budget
    from .morphometry import report_beside

    path = Path(path)
    # no region is measured here: the run's patient is not built again. A mesh's read is checked against the
    # budget too: trimesh's read of the default cube's STL held 3.3 GiB before the solve's check
    sample = read_scaffold(path, voxel=voxel, spacing=spacing, label=label, threshold=threshold, region=False,
                           max_memory=budget(max_memory))
    beside = report_beside(path)  # the run's report, read once: the generator's walls, the grid a mesh was read on
    if sample.field is not None:
        grid = Grid(tuple(float(v) for v in sample.origin), float(sample.voxel), sample.field.shape)
        # the generator's median wall, from the run's report beside the field (generate --mechanics passes its own)
        wall = ((beside or {}).get("wall_thickness_mm") or {}).get("median")
        wall = float(wall) if isinstance(wall, (int, float)) and wall > 0 else None
        try:
            solved = solid_for_solve(sample.field, grid, max_memory=max_memory, voxel=mechanics_voxel, wall=wall,
                                     boundary=boundary, source="field")
        except ScaffoldError as exc:
            if "no solid voxel" in str(exc):
                raise ScaffoldError(f"{path.name} holds no solid voxel: nothing carries load") from None
            raise
        if wall is None and solved.report.get("warning") is None:
            # no report to name the walls: measured on the sample, as a mesh's or a scan's
            solved.report["warning"] = resolution_warning(solved.solid, solved.voxel, "field")
        return solved, sample.kind
    if mechanics_voxel is not None:
        raise ScaffoldError("--mechanics-voxel samples a .npy signed distance; a mesh or a volume is voxelised "
                        "or resampled at --voxel")
    solid = sample.solid
    if not solid.any():
        raise ScaffoldError(f"{path.name} holds no solid voxel: nothing carries load")
    report = check_solve(solid, sample.voxel, max_memory=max_memory, boundary=boundary, option="--voxel")
    box = tuple(slice(int(i.min()), int(i.max()) + 1) for i in np.nonzero(solid))
    origin = tuple(float(sample.origin[a] + box[a].start * sample.voxel) for a in range(3))
    read = solid.shape
    solid = np.ascontiguousarray(solid[box])
    # where the voxel came from, and the box solved: the platens and the homogenization's faces are the solid's
    # bounding box, which the note names where it is smaller than what was read (a plate in a larger volume is
    # compressed through its own thickness)
    what = {"mesh": "the mesh voxelised at --voxel" if voxel is not None or beside is None
            else "the mesh voxelised on its run's grid (the report beside it)",
            "volume": f"the volume resampled {sample.resampled}" if sample.resampled else "the volume's own voxel"}
    note = f"mechanics voxel {sample.voxel:.4g} mm: {what.get(sample.kind, 'the sample' + chr(39) + 's own voxel')}"
    if sample.axes:
        note += f"; {sample.axes}"
    if solid.shape != read:
        note += (f"; the sample is the solid's bounding box, {' x '.join(map(str, solid.shape))} of the "
                 f"{' x '.join(map(str, read))} voxels read (the platens touch its ends)")
    report["note"] = note
    # a field's walls are the generator's (solid_for_solve); a mesh's or a scan's are measured
    report["warning"] = resolution_warning(solid, float(sample.voxel), sample.kind)
    return SolveSample(solid, float(sample.voxel), origin, report, sample.selection), sample.kind


def crop(solid: np.ndarray) -> np.ndarray:
    """`solid` cut to the bounding box of its solid voxels."""
    box = tuple(slice(int(i.min()), int(i.max()) + 1) for i in np.nonzero(solid))
    return np.ascontiguousarray(solid[box])
