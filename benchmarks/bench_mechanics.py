"""Issue 14 benchmark: the stiffness of a Voronoi scaffold from its voxels.

    python benchmarks/bench_mechanics.py [--sizes 64 128 200] [--runs 3] [--cases-per-block 1] [--fit] [--mugrid]
                                         [--convergence] [--coarsen MM]
                                         [--across 4 5 6 8 [--across-size 1.6] [--across-porosity 0.7]
                                          [--across-seed 0]]
                                         [--preconditioners multigrid,fft] [--peers-up-to 64] [--peer-runs 1]
                                         [--femur] [--femur-tol 1e-6] [--femur-maxiter N] [--split]
                                         [--tol 1e-6] [--accuracy 1e-6]
                                         [--tolerances 1e-2 1e-3 1e-4 1e-5 1e-6] [--accuracies 1e-5 1e-6 1e-7]
                                         [--tolerance-size 128]
                                         [--bone 128 [--bone-tolerances 1e-3 1e-4 1e-6] [--bone-accuracies 1e-6]]
                                         [--ct 2]

- **solve**: all six load cases of periodic homogenization (``--cases-per-block`` at a time, PCG with each
  preconditioner asked for, side by side: the multigrid V-cycle, the default, and the FFT
  reference-medium one; the element operator on the OpenCL device in double) of
  a paper-style Voronoi scaffold at porosity 0.7 (about 30 % solid), N^3 voxels of 0.04 mm
  (pore size 0.6 mm), in a fresh process per run (peak memory is that run's own). The
  scaffold is built once per size, outside the timed region. Medians of --runs runs. "solve B/solid
  voxel" is the solve's peak above what the process held once the libraries a solve loads were in
  (numba's compiled passes, every level's OpenCL kernels: a solve of the sample's 32^3 corner first,
  as --memory's rows), "libraries MiB" what they took (once a process). Each CG stops
  at the relative residual --tol or, sooner, at the energy accuracy --accuracy (default
  ``mechanics.ACCURACY``, as the commands run; ``--accuracy 0``: the residual alone, as muGrid's CG stops).
- **mugrid** (``--mugrid``, when ``pip install muGrid`` is there): the same six load cases
  on the same voxels with muGrid's fused Q1 stiffness operator, its Green-Jacobi FFT
  preconditioner and its CG, void as lambda = mu = 0, to the same tolerance; every tensor
  component compared and the time ratio printed.
- **fit** (``--fit``): struts-style open-cell Voronoi lattices at solid fractions 0.1-0.4,
  E/Es = C rho^n fitted by least squares in log-log (E the mean of Ex, Ey, Ez); Roberts &
  Garboczi (2001) report 0.93 rho^2.04 for random open-cell Voronoi foams, the issue asks
  n in 1.8-2.3.
- **across** (``--across 4 5 6 8``): convergence with the voxel. A ``--across-size`` cube (0.6 mm
  pores, ``--across-porosity``, ``--across-seed``) generated at voxels of its median wall over N and
  over 2N (each generated at its own voxel, not sampled), compressed between platens and
  homogenized (periodic; ``--across-kinematic`` adds kinematic): each modulus's change from h to
  h/2 (issue 14 asks under 3 % at the default voxel), then every voxel's figures.
- **femur** (``--femur``): the 20 mm femoral shaft scaffold (jigsaw_femur.stl cut at z = 210 and
  230 mm, pore size 0.6 mm, porosity 0.7) at 0.1 mm, compressed along its axis (z) between
  lubricated platens in Ti-6Al-4V and in PCL, each in a fresh process: the apparent modulus over
  the box's cross-section (the command's figure) and over the bone's mean cross-section (its
  volume over its length: the shaft is round, the box is not), beside bone's bands. Needs
  ../shared/data.

- **tolerances** (``--tolerances``): the solve above at each CG tolerance (``--mechanics-tol``, the residual
  alone), and with ``--accuracies`` at the default tolerance with each energy accuracy (the default stop's),
  medians of --runs, against one solve of the same voxels to 1e-10: its seconds and iterations, the
  solver's estimate of its energy error, and how far its tensor and its Young's moduli lie from the
  reference's (what a looser stop saves and costs).

- **bone** (``--bone N``): real bone, the central N^3 of the lumbar trabecular micro-CT in
  ../shared/data (``bonejheadless_lumbar_trabecular_ROI_1_06219.nrrd``, 51.3 um voxels, read as
  ``implicit-scaffold mechanics`` reads it), compressed along z between lubricated platens and
  homogenized with kinematic conditions (the sample is not periodic) at each of
  ``--bone-tolerances`` and ``--bone-accuracies`` (as ``--accuracies``), each against one solve of the same voxels to 1e-10: seconds, CG iterations,
  how far the apparent modulus and the tensor lie from the reference's (what ``--mechanics-tol``
  saves and costs where the struts are bone's, not a Voronoi lattice's).

- **ct** (``--ct F``): a CT as users bring it, the data folder's DICOM series (``totalseg_example_ct_dicom``)
  from 200 HU up, F times coarser (each F^3 block solid from half up; 1: as read): compression along z and
  kinematic homogenization with its pieces that share no node solved apart (each on its own box, the
  small ones together exactly) and as one system, medians of --runs in fresh processes, the tensors and
  moduli compared.

- **split** (``--split``): one more run of each size's solve with a timer around every OpenCL
  product, grouped by operator (the fine one in float or double, each coarse level) and the
  number of load cases a call, the rest of the solve's seconds, and its user and system CPU
  seconds (system time: mostly fresh pages the kernel zeroes).

Timings on a shared 2-core machine are noisy (other jobs run beside): read them as such.
"""
from __future__ import annotations

import argparse
import atexit
import shutil
import statistics
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import median_runs, run_isolated, table  # noqa: E402

BUILD = """
import numpy as np
import implicit_scaffold
from implicit_scaffold.measure.mechanics import crop
r = implicit_scaffold.generate(size={size!r}, voxel={voxel!r}, pore_size={pore!r}, porosity={porosity!r},
                               style={style!r}, seed={seed!r}, mesh=False, morphometry=False)
inside = r.patient_sdf < 0
box = tuple(slice(i.min(), i.max() + 1) for i in np.nonzero(inside))
solid = (r.field < 0)[box]
np.save({out!r}, solid)
_out = {{'grid': 'x'.join(map(str, solid.shape)), 'solid_fraction': float(solid.mean())}}
"""

OURS = """
import time
import numpy as np
from implicit_scaffold.measure import mechanics as M, mechanics_cl as MC
from implicit_scaffold import opencl
solid = np.load({solid!r})
mat = M.material('ti64')
from implicit_scaffold.run.memory import process_memory, release
start = process_memory() / 2**20  # the interpreter, NumPy, SciPy and the OpenCL runtime
# the operators' kernels built outside the clock (double and the cycle's fine level one case a launch,
# the coarse levels the block's), and the libraries a solve loads (numba's compiled passes, every level's
# kernels) outside the solve's memory: a solve of a 32^3 corner first, as --memory's rows are measured
for nc, d in ((1, 1), (1, 0), ({block!r}, 0)):
    opencl.program('mechanics', **MC.defines(nc, d))
M.homogenize(np.ascontiguousarray(solid[:32, :32, :32]), {voxel!r}, mat, boundary='periodic', tol={tol!r},
             backend='opencl', preconditioner={preconditioner!r}, cases_per_block={block!r}, accuracy={accuracy!r})
before = release() / 2**20
t = time.perf_counter()
hom = M.homogenize(solid, {voxel!r}, mat, boundary='periodic', tol={tol!r}, backend='opencl', maxiter={maxiter!r},
                   preconditioner={preconditioner!r}, cases_per_block={block!r}, accuracy={accuracy!r})
_out = {{'seconds': time.perf_counter() - t, 'iterations': hom.iterations, 'residual': hom.residual,
         'C': hom.stiffness.tolist(), 'solid_voxels': int(solid.sum()), 'rss_before_mb': before,
         'libraries_mb': before - start,
         'energy_error': hom.energy_error}}
"""

SPLIT = """
import collections, resource, time
import numpy as np
from implicit_scaffold.measure import mechanics as M, mechanics_cl as MC
from implicit_scaffold import opencl
solid = np.load({solid!r})
mat = M.material('ti64')
for nc, d in ((1, 1), (1, 0), ({block!r}, 0)):
    opencl.program('mechanics', **MC.defines(nc, d))
stats = collections.defaultdict(lambda: [0, 0.0])
product = MC._Gather.__call__
def timed(self, u):
    t = time.perf_counter()
    out = product(self, u)
    key = ('fine, ' + ('double' if self.double else 'float') if isinstance(self, MC.StiffnessOperator)
           else 'level ' + 'x'.join(map(str, self.shape)) + (' (stencils)' if isinstance(self, MC.StencilLevelOperator)
                                                            else ''), int(u.shape[0]))
    stats[key][0] += 1
    stats[key][1] += time.perf_counter() - t
    return out
MC._Gather.__call__ = timed
r0 = resource.getrusage(resource.RUSAGE_SELF)
t = time.perf_counter()
hom = M.homogenize(solid, {voxel!r}, mat, boundary='periodic', tol={tol!r}, backend='opencl',
                   cases_per_block={block!r}, accuracy={accuracy!r})
r1 = resource.getrusage(resource.RUSAGE_SELF)
_out = {{'seconds': time.perf_counter() - t, 'iterations': hom.iterations, 'user': r1.ru_utime - r0.ru_utime,
         'system': r1.ru_stime - r0.ru_stime, 'products': [[k[0], k[1], v[0], v[1]] for k, v in stats.items()]}}
"""

MUGRID = """
import time
import numpy as np
import muGrid
from muGrid import Solvers, Preconditioners
solid = np.load({solid!r})
h = {voxel!r}
E, nu, tol = 113.8, 0.342, {tol!r}
t = time.perf_counter()
lam_s, mu_s = E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))
engine = muGrid.FFTEngine(list(solid.shape), nb_ghosts_left=[1, 1, 1], nb_ghosts_right=[1, 1, 1])
fc = engine.real_space_collection
op = muGrid.IsotropicStiffnessOperator3D([h, h, h])
lam = fc.real_field('lambda', 1); mu = fc.real_field('mu', 1)
lam.p[...] = np.where(solid, lam_s, 0.0).reshape(lam.p.shape)
mu.p[...] = np.where(solid, mu_s, 0.0).reshape(mu.p.shape)
engine.communicate_ghosts(lam); engine.communicate_ghosts(mu)
u = fc.real_field('u', 3); rhs = fc.real_field('rhs', 3)
prec = Preconditioners.make_green_jacobi_preconditioner(engine, op, lam, mu, 3, reference_lambda=lam_s,
        reference_mu=mu_s, element=muGrid.FEMElement.q1, grid_spacing=[h, h, h])
def hessp(x, Ax):
    engine.communicate_ghosts(x)
    op.apply(x, lam, mu, Ax)
C = np.zeros((6, 6)); its = []
for k, (i, j) in enumerate([(0, 0), (1, 1), (2, 2), (1, 2), (0, 2), (0, 1)]):
    Eb = np.zeros((3, 3)); Eb[i, j] = Eb[j, i] = 1.0 if i == j else 0.5
    rhs.p[...] = 0; u.p[...] = 0
    op.apply_macro_rhs(lam, mu, Eb.ravel().tolist(), rhs)
    rhs.p[...] *= -1
    count = [0]
    def cb(*a, **kw): count[0] += 1
    Solvers.conjugate_gradients(engine.communicator, fc, rhs, u, hessp=hessp, prec=prec, rtol=tol, maxiter=5000,
                                callback=cb, atol=tol * np.sqrt(solid.size) * E * h ** 2)
    its.append(count[0])
    engine.communicate_ghosts(u)
    s = np.asarray(op.average_stress(u, lam, mu, Eb.ravel().tolist())).reshape(3, 3) / solid.size / h ** 3
    C[:, k] = [s[0, 0], s[1, 1], s[2, 2], s[1, 2], s[0, 2], s[0, 1]]
_out = {{'seconds': time.perf_counter() - t, 'iterations': int(max(its)), 'C': C.tolist()}}  # per load case, as ours
"""

FIT = """
import numpy as np
from implicit_scaffold.measure import mechanics as M
solid = np.load({solid!r})
mat = M.material('ti64')
hom = M.homogenize(solid, {voxel!r}, mat, boundary={boundary!r}, tol=1e-6, backend='opencl')
c = M.engineering_constants(hom.stiffness)
_out = {{'rho': float(solid.mean()), 'E_rel': float(np.mean(list(c['youngs_modulus_gpa'].values())) / mat.E_gpa),
         'iterations': hom.iterations}}
"""


PERIODIC_FIT = """
import numpy as np
from implicit_scaffold.measure import mechanics as M
from implicit_scaffold.geometry.cells import voronoi_cells
from implicit_scaffold.run.grid import Grid
from implicit_scaffold.fields.lattice import struts_field
from implicit_scaffold.geometry.skeleton import voronoi_edges
L, n, m, seed = {size!r}, {cells!r}, {voxels!r}, {seed!r}
rng = np.random.default_rng(seed)
seeds = rng.uniform(0.0, L, (n, 3))
# the seeds and their 26 periodic images: the cells of the middle copy are the periodic tessellation's
shifts = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)], float) * L
cells = voronoi_cells((seeds[None] + shifts[:, None]).reshape(-1, 3), (-L,) * 3, (2 * L,) * 3)
edges = voronoi_edges(cells)
mid = edges.mean(axis=1)
edges = edges[np.all((mid > -0.5 * L) & (mid < 1.5 * L), axis=1)]
h = L / m
# voxel centres (i + 1/2) h: the grid is one period, its solid periodic
grid = Grid((h / 2,) * 3, h, (m, m, m))
length = float(np.linalg.norm(edges[:, 1] - edges[:, 0], axis=1).sum()) / 27
F = struts_field(edges, grid, cutoff=3 * np.sqrt(0.5 * L ** 3 / (np.pi * length)), blend=0.0)
mat = M.material('ti64')
out = []
for rho in {rhos!r}:
    solid = F < np.quantile(F, rho)
    hom = M.homogenize(solid, h, mat, boundary='periodic', tol=1e-6, backend='opencl')
    c = M.engineering_constants(hom.stiffness)
    out.append((float(solid.mean()), float(np.mean(list(c['youngs_modulus_gpa'].values())) / mat.E_gpa),
                hom.iterations))
_out = {{'points': out, 'strut_radius_voxels_at_0.1': float(np.quantile(F, 0.1) / h)}}
"""


MEMORY = """
import numpy as np
from implicit_scaffold.measure import mechanics as M
from implicit_scaffold.run.memory import peak_memory, release
n, phi, maxiter = {n!r}, {phi!r}, {maxiter!r}
if {source!r}:
    solid = np.load({source!r})
else:
    g = (np.arange(n) + 0.5) / n * 2 * np.pi
    x, y, z = np.meshgrid(g, g, g, indexing='ij', sparse=True)
    f = np.sin(x) * np.cos(y) + np.sin(y) * np.cos(z) + np.sin(z) * np.cos(x)  # a gyroid: one connected solid
    solid = f < np.quantile(f, phi)
    del f, x, y, z
mat = M.material('ti64')
M.measure(np.ones((4, 4, 5), bool), 0.05, mat, boundary={boundary!r}, backend='opencl',
          preconditioner={preconditioner!r})  # the kernels built and the libraries loaded outside the count
before = release()
if {what!r} == 'compress':
    M.compress(solid, 0.05, mat, axis=2, tol=1e-6, backend='opencl', preconditioner={preconditioner!r},
               maxiter=maxiter)
elif {what!r} == 'homogenize':
    M.homogenize(solid, 0.05, mat, boundary={boundary!r}, tol=1e-6, backend='opencl',
                 preconditioner={preconditioner!r}, cases_per_block={block!r}, maxiter=maxiter)
else:
    M.measure(solid, 0.05, mat, boundary={boundary!r}, backend='opencl', preconditioner={preconditioner!r},
              cases_per_block={block!r})
peak = peak_memory()
# a compression's nodes are the box's (one more per axis), whatever the rows' boundary
nodes = int(np.prod([s + (0 if {boundary!r} == 'periodic' and {what!r} != 'compress' else 1) for s in solid.shape]))
live = M.live_nodes(solid)  # the box's, as the checks before a solve count them
_out = {{'solid_voxels': int(solid.sum()), 'nodes': nodes, 'live_nodes': live, 'solve_bytes': peak - before,
         'estimate': M.solve_memory(solid.shape, int(solid.sum()), boundary={boundary!r},
                                    preconditioner={preconditioner!r}, cases_per_block={block!r}, live=live)}}
"""


COARSEN = """
import numpy as np
import implicit_scaffold
from implicit_scaffold.measure import mechanics as M
r = implicit_scaffold.generate(size={size!r}, voxel={voxel!r}, pore_size=0.6, porosity=0.7, seed=0, mesh=False,
                               morphometry=False)
s = M.solid_for_solve(r.field, r.grid, voxel={sample!r}, boundary='periodic', max_memory='16G')
mat = M.material('ti64')
c = M.compress(s.solid, s.voxel, mat, axis=2, tol=1e-6, backend='opencl')
hom = M.homogenize(s.solid, s.voxel, mat, boundary='periodic', tol=1e-6, backend='opencl')
e = M.engineering_constants(hom.stiffness)['youngs_modulus_gpa']
_out = {{'voxel': r.grid.spacing, 'sample': s.voxel, 'wall': r.report['wall_thickness_mm']['median'],
         'grid': 'x'.join(map(str, s.solid.shape)), 'solid_fraction': float(s.solid.mean()),
         'compression_gpa': c.apparent_modulus_gpa, 'Ez_gpa': e['z'], 'Ex_gpa': e['x']}}
"""


ACROSS = """
import time
import numpy as np
import implicit_scaffold
from implicit_scaffold.measure import mechanics as M
t = time.perf_counter()
r = implicit_scaffold.generate(size={size!r}, voxel={voxel!r}, pore_size=0.6, porosity={porosity!r}, seed={seed!r},
                               mesh=False, morphometry=False)
inside = r.patient_sdf < 0
box = tuple(slice(i.min(), i.max() + 1) for i in np.nonzero(inside))
solid = (r.field < 0)[box]
mat = M.material('ti64')
c = M.compress(solid, r.grid.spacing, mat, axis=2, tol=1e-6, backend='opencl')
hom = M.homogenize(solid, r.grid.spacing, mat, boundary='periodic', tol=1e-6, backend='opencl')
e = M.engineering_constants(hom.stiffness)['youngs_modulus_gpa']
k = {{'x': 0.0, 'y': 0.0, 'z': 0.0}}
if {kinematic!r}:
    kin = M.homogenize(solid, r.grid.spacing, mat, boundary='kinematic', tol=1e-6, backend='opencl')
    k = M.engineering_constants(kin.stiffness)['youngs_modulus_gpa']
# the solid share of the first and second planes inside the cube's six faces (a window on a face
# as open as its channel: the first no more solid than the second)
face = [[float(np.take(solid, k, axis=a).mean()) for a in range(3) for k in ks] for ks in ((0, -1), (1, -2))]
_out = {{'voxel': r.grid.spacing, 'wall': r.report['wall_thickness_mm']['median'],
         'grid': 'x'.join(map(str, solid.shape)), 'solid_fraction': float(solid.mean()),
         'face_planes': [float(np.mean(f)) for f in face],
         'compression_gpa': c.apparent_modulus_gpa, 'periodic': [e['x'], e['y'], e['z']],
         'kinematic': [k['x'], k['y'], k['z']], 'iterations': [hom.iterations, c.iterations],
         'seconds': time.perf_counter() - t}}
"""


FEMUR_BUILD = """
import numpy as np
import implicit_scaffold
from implicit_scaffold.io.patient_io import load_patient
patient = load_patient({femur!r}, cut_planes=(0, 0, 210, 0, 0, 1, 0, 0, 230, 0, 0, 1))
r = implicit_scaffold.generate(patient=patient, pore_size=0.6, porosity=0.7, voxel=0.1, seed=0, mesh=False,
                               morphometry=False)
inside = r.patient_sdf < 0
box = tuple(slice(i.min(), i.max() + 1) for i in np.nonzero(inside))
solid = (r.field < 0)[box]
np.save({out!r}, solid)
length = solid.shape[2] * r.grid.spacing
_out = {{'grid': 'x'.join(map(str, solid.shape)), 'voxel': r.grid.spacing, 'solid_voxels': int(solid.sum()),
        'porosity': r.report['porosity_voxel'], 'bone_mm3': float(patient.volume),
        'box_area_mm2': float(solid.shape[0] * solid.shape[1] * r.grid.spacing ** 2),
        'bone_area_mm2': float(patient.volume) / length}}
"""

FEMUR_SOLVE = """
import numpy as np
from implicit_scaffold.measure import mechanics as M
solid = np.load({solid!r})
c = M.compress(solid, {voxel!r}, M.material({material!r}), axis=2, tol={tol!r}, backend='opencl', maxiter={maxiter!r},
               preconditioner={preconditioner!r}, accuracy={accuracy!r})
_out = {{'modulus_gpa': c.apparent_modulus_gpa, 'iterations': c.iterations, 'residual': c.residual,
        'energy_error': c.energy_error,
        'seconds': c.seconds, 'dropped_voxels': c.dropped_voxels, 'verdict': M.bone_verdict(c.apparent_modulus_gpa)}}
"""


def femur(tmp: Path, tol: float, maxiter: int, preconditioner: str, accuracy: float | None) -> None:
    """The femoral shaft scaffold at 0.1 mm, compressed along its axis in Ti-6Al-4V and PCL."""
    from _common import DATA

    path = tmp / "femur_solid.npy"
    info = run_isolated(FEMUR_BUILD.format(femur=str(DATA / "jigsaw_femur.stl"), out=str(path)), timeout=7200)
    print(f"femoral shaft scaffold: {info['grid']} voxels of {info['voxel']} mm, {info['solid_voxels']:,} solid, "
          f"porosity {info['porosity']:.4f}; bone {info['bone_mm3']:.0f} mm3, mean cross-section "
          f"{info['bone_area_mm2']:.1f} mm2 in a box of {info['box_area_mm2']:.1f} mm2", flush=True)
    rows = []
    for material in ("ti64", "pcl"):
        r = run_isolated(FEMUR_SOLVE.format(solid=str(path), voxel=info["voxel"], material=material, tol=tol,
                                           maxiter=maxiter, preconditioner=preconditioner, accuracy=accuracy),
                         timeout=7200)
        per_bone = r["modulus_gpa"] * info["box_area_mm2"] / info["bone_area_mm2"]
        rows.append([material, f"{r['modulus_gpa']:.4g}", f"{per_bone:.4g}", r["iterations"], f"{r['residual']:.1e}",
                     _error(r["energy_error"]), f"{r['seconds']:.1f}", f"{r['peak_rss_mb']:.0f}", r["dropped_voxels"], r["verdict"]])
        # each material as it comes: a solve is long, and a run cut short keeps what it measured
        print(f"  {material}: E {r['modulus_gpa']:.4g} GPa over the box, {per_bone:.4g} over the bone's section; "
              f"{r['iterations']} CG its, residual {r['residual']:.1e}, {r['seconds']:.1f} s", flush=True)
    print(table(rows, ["material", "E over box GPa", "E over bone section GPa", "CG its", "residual",
                       "energy error (est.)", "s",
                       "peak MiB", "voxels off the load path", "verdict (box figure)"]))


def coarsen(size: float) -> None:
    """The moduli at the run's voxel, at half of it, and sampled from the finer field at coarser voxels."""
    coarse = run_isolated(COARSEN.format(size=size, voxel=None, sample=None), timeout=3600)
    h = coarse["voxel"]
    ref = run_isolated(COARSEN.format(size=size, voxel=h / 2, sample=None), timeout=3600)
    rows = [coarse, ref] + [run_isolated(COARSEN.format(size=size, voxel=h / 2, sample=round(f * h, 6)), timeout=3600)
                            for f in (1.0, 1.5, 2.0)]
    out = []
    for r in rows:
        how = "generated" if r["sample"] == r["voxel"] else f"sampled from the {r['voxel']:.4g} mm field"
        out.append([f"{r['sample']:.4g}", how, f"{r['wall'] / r['sample']:.2f}", r["grid"],
                    f"{r['solid_fraction']:.4f}",
                    f"{r['compression_gpa']:.4g} ({100 * (r['compression_gpa'] / ref['compression_gpa'] - 1):+.1f} %)",
                    f"{r['Ez_gpa']:.4g} ({100 * (r['Ez_gpa'] / ref['Ez_gpa'] - 1):+.1f} %)",
                    f"{r['Ex_gpa']:.4g} ({100 * (r['Ex_gpa'] / ref['Ex_gpa'] - 1):+.1f} %)"])
    print()
    print(table(out, ["voxel mm", "solid from", "voxels across median wall", "grid", "solid",
                      "platens E_z GPa (vs h/2)", "periodic E_z GPa", "periodic E_x GPa"]))


def across(size: float, walls, porosity: float, seed: int, kinematic: bool = False) -> None:
    """The moduli of a cube generated at each voxel ``wall / N`` and at half of it (``wall / 2N``).

    Every row is generated at its own voxel (not sampled from a finer field); the median wall is
    the run's own (``wall_thickness_mm``, which comes from the cells, not the voxels).
    """
    def run(voxel):
        return run_isolated(ACROSS.format(size=size, voxel=voxel, porosity=porosity, seed=seed, kinematic=kinematic),
                            timeout=7200)

    first = run(None)  # generate's default voxel, 4 across: the wall
    wall = first["wall"]
    runs = {}
    for n in sorted({m for w in walls for m in (w, 2 * w)}):
        h = round(wall / n, 7)
        runs[n] = first if abs(first["voxel"] - h) < 1e-6 else run(h)
        r = runs[n]
        print(f"  {n:g} across: {r['voxel']:.5g} mm, {r['grid']}, solid {r['solid_fraction']:.4f}, platens "
              f"{r['compression_gpa']:.4g} GPa, periodic {r['periodic']}"
              + (f", kinematic {r['kinematic']}" if kinematic else "") + f", {r['seconds']:.0f} s",
              file=sys.stderr, flush=True)

    def change(a, b):
        return f"{100 * (a / b - 1):+.2f} %"

    kinds = ("periodic", "kinematic") if kinematic else ("periodic",)
    out = []
    for n in walls:
        a, b = runs[n], runs[2 * n]
        platens = a["compression_gpa"], b["compression_gpa"]
        out.append([f"{n:g}", f"{a['voxel']:.5f}", a["grid"], f"{a['solid_fraction']:.4f}",
                    f"{platens[0]:.4g} / {platens[1]:.4g} ({change(*platens)})"]
                   + [f"{a[kind][i]:.4g} ({change(a[kind][i], b[kind][i])})"
                      for kind in kinds for i in range(3)])
    print()
    print(f"{size:g} mm cube, 0.6 mm pores, porosity {porosity:g}, seed {seed}, Ti-6Al-4V; median wall {wall:.5f} mm; "
          "each row's change is from its voxel h to h/2 (both generated)")
    print(table(out, ["N across wall", "h mm", "grid", "solid", "platens E_z GPa at h / h/2 (change)",
                      *[f"{kind} E_{x} GPa at h (change)" for kind in kinds for x in "xyz"]]))
    # every voxel's figures, finest last: whether they settle as h falls
    print()
    print(table([[f"{n:g}", f"{r['voxel']:.5f}", r["grid"], f"{r['solid_fraction']:.4f}",
                  f"{r['face_planes'][0]:.3f} / {r['face_planes'][1]:.3f}", f"{r['compression_gpa']:.4g}"]
                 + [f"{r[kind][i]:.4g}" for kind in kinds for i in range(3)] + [f"{r['seconds']:.0f}"]
                 for n, r in sorted(runs.items())],
                ["N across wall", "h mm", "grid", "solid", "faces' 1st / 2nd plane solid", "platens E_z GPa",
                 *[f"{kind} E_{x} GPa" for kind in kinds for x in "xyz"], "s (build and solves)"]))


def memory(sizes, preconditioners, solves, blocks, *, bones=(), tmp: Path | None = None, maxiter: int = 2000) -> None:
    """The solver's own memory on small gyroids (and the micro-CT's central N^3 of `bones`, kinematic
    boundaries), beside the estimate ``mechanics.solve_memory`` checks."""
    from _common import DATA

    samples = [(n, phi, None) for n in sizes for phi in (0.3, 0.6)]
    for n in bones:
        path = tmp / f"bone_{n}.npy"
        run_isolated(BONE_BUILD.format(ct=str(DATA / BONE_CT), voxel=BONE_VOXEL, n=n, out=str(path)))
        samples.append((n, "bone", str(path)))
    rows = []
    for pc, block in [(pc, b) for pc in preconditioners for b in blocks]:
        for boundary in ("periodic", "kinematic"):
            for what in solves:
                for n, phi, source in samples:
                    if what == "compress" and boundary == "kinematic":
                        continue  # compression has its own boundary: the periodic rows are it
                    if source is not None and boundary == "periodic" and what != "compress":
                        continue  # bone is not periodic
                    r = run_isolated(MEMORY.format(n=n, phi=phi, boundary=boundary, preconditioner=pc,
                                                   what=what, block=block, source=source, maxiter=maxiter),
                                     timeout=3600)
                    rows.append([pc, block, boundary if what != "compress" else "platens", what,
                                 f"{n}^3" + (" bone" if source else ""),
                                 f"{r['solid_voxels'] / n ** 3:.2f}", r["solid_voxels"], r["nodes"], r["live_nodes"],
                                 f"{r['solve_bytes'] / 2 ** 20:.1f}", f"{r['solve_bytes'] / r['solid_voxels']:.0f}",
                                 f"{r['estimate'] / 2 ** 20:.1f}", f"{r['estimate'] / r['solve_bytes']:.2f}"])
                    print(" | ".join(map(str, rows[-1])), file=sys.stderr, flush=True)
    print(table(rows, ["preconditioner", "cases per block", "boundary", "solve", "grid", "solid", "solid voxels", "nodes",
                       "live nodes",
                       "peak above start MiB", "B/solid voxel", "estimate MiB", "estimate/measured"]))


def split(path: Path, n: int, voxel: float, tol: float, block: int, accuracy: float | None) -> None:
    """One solve of `path` with every OpenCL product timed (``--split``), printed as a table."""
    r = run_isolated(SPLIT.format(solid=str(path), voxel=voxel, tol=tol, block=block, accuracy=accuracy))
    rows = [[name, cases, calls, f"{s:.2f}", f"{1000 * s / calls:.1f}"]
            for name, cases, calls, s in sorted(r["products"], key=lambda p: -p[3])]
    rest = r["seconds"] - sum(p[3] for p in r["products"])
    rows.append(["everything else (vector passes, transfers, set-up)", "", "", f"{rest:.2f}", ""])
    print(f"{n}^3: {r['seconds']:.1f} s, {r['iterations']} iterations, CPU {r['user']:.1f} s user, "
          f"{r['system']:.1f} s system")
    print(table(rows, ["operator", "cases a call", "calls", "s", "ms a call"]))


def build(tmp: Path, n: int, *, voxel: float, porosity: float, style: str = "paper", pore: float = 0.6,
          seed: int = 0) -> tuple[Path, dict]:
    out = tmp / f"solid_{style}_{n}_{porosity}.npy"
    info = run_isolated(BUILD.format(size=round(n * voxel, 6), voxel=voxel, pore=pore, porosity=porosity,
                                     style=style, seed=seed, out=str(out)), timeout=3600)
    return out, info


#: the tolerance of the reference solve of --tolerances
REFERENCE_TOL = 1e-10


def stops(tols, accuracies) -> list:
    """(label, tolerance, accuracy) of each solve of --tolerances / --accuracies (and the bone's): a
    tolerance alone, or the default tolerance with an energy accuracy (``mechanics.measure``'s stop)."""
    from implicit_scaffold.measure.mechanics import TOL

    return ([(f"{t:g}", t, None) for t in tols or ()]
            + [(f"{TOL:g} or energy {a:g}", TOL, a) for a in accuracies or ()])


def _error(value) -> str:
    return "" if value is None or not np.isfinite(value) else f"{value:.1e}"


def tolerances(tmp: Path, n: int, voxel: float, solves, runs: int, block: int) -> None:
    """The multigrid solve of the N^3 scaffold at each stop of `solves` (:func:`stops`), against one to
    :data:`REFERENCE_TOL`."""
    from implicit_scaffold.measure.mechanics import engineering_constants

    path, info = build(tmp, n, voxel=voxel, porosity=0.7)

    def solve(tol, count, accuracy=None):
        return median_runs(OURS.format(solid=str(path), voxel=voxel, tol=tol, maxiter=5000,
                                       preconditioner="multigrid", block=block, accuracy=accuracy), count, warmup=0)

    ref, _ = solve(REFERENCE_TOL, 1)
    C_ref = np.array(ref["C"])
    E_ref = np.array(list(engineering_constants(C_ref)["youngs_modulus_gpa"].values()))
    print(f"  {n}^3 reference to {REFERENCE_TOL:g}: {ref['seconds']:.1f} s, {ref['iterations']} iterations, "
          f"residual {ref['residual']:.1e}", file=sys.stderr, flush=True)
    rows = []
    for label, tol, accuracy in solves:
        med, results = solve(tol, runs, accuracy)
        # the tensor of the first run (every run solves the same voxels to the same iterate)
        C = np.array(results[0]["C"])
        E = np.array(list(engineering_constants(C)["youngs_modulus_gpa"].values()))
        rows.append([label, f"{med['seconds']:.1f}", ", ".join(f"{r['seconds']:.1f}" for r in results),
                     med["iterations"], f"{med['residual']:.1e}", _error(results[0]["energy_error"]),
                     f"{np.abs(C - C_ref).max() / np.abs(C_ref).max():.1e}",
                     f"{np.abs(E / E_ref - 1).max():.1e}", f"{med['peak_rss_mb']:.0f}"])
        print(f"  {n}^3 {label} done: {med['seconds']:.1f} s", file=sys.stderr, flush=True)
    print(f"\n{info['grid']} scaffold, solid fraction {info['solid_fraction']:.3f}, six load cases (periodic); "
          f"reference: one solve to {REFERENCE_TOL:g} ({ref['seconds']:.1f} s, {ref['iterations']} iterations)")
    print(table(rows, ["stop", "s (median)", "runs (s)", "CG its", "residual", "energy error (est.)",
                       "max |dC|/max|C|", "max |dE/E| (x, y, z)", "peak MiB"]))


#: the micro-CT of --bone (../shared/data) and its voxel (mm): the header states none, the source's
#: scripts use 51.3 um
BONE_CT = "bonejheadless_lumbar_trabecular_ROI_1_06219.nrrd"
BONE_VOXEL = 0.0513

BONE_BUILD = """
import numpy as np
from implicit_scaffold.measure.morphometry import read_scaffold
s = read_scaffold({ct!r}, spacing={voxel!r})
n = {n!r}
lo = [(d - n) // 2 for d in s.solid.shape]
solid = np.ascontiguousarray(s.solid[lo[0]:lo[0] + n, lo[1]:lo[1] + n, lo[2]:lo[2] + n])
np.save({out!r}, solid)
_out = {{'grid': 'x'.join(map(str, solid.shape)), 'of': 'x'.join(map(str, s.solid.shape)),
        'voxel': float(s.voxel), 'solid_fraction': float(solid.mean())}}
"""

BONE_SOLVE = """
import time
import numpy as np
from implicit_scaffold.measure import mechanics as M
solid = np.load({solid!r})
mat = M.material('ti64')
t = time.perf_counter()
c = M.compress(solid, {voxel!r}, mat, axis=2, tol={tol!r}, backend='opencl', maxiter=5000, accuracy={accuracy!r})
tc = time.perf_counter() - t
t = time.perf_counter()
hom = M.homogenize(solid, {voxel!r}, mat, boundary='kinematic', tol={tol!r}, backend='opencl', maxiter=5000,
                   accuracy={accuracy!r})
_out = {{'seconds': tc + time.perf_counter() - t, 'compression_s': tc, 'homogenization_s': time.perf_counter() - t,
        'modulus': c.apparent_modulus_gpa, 'compression_its': c.iterations, 'iterations': hom.iterations,
        'C': hom.stiffness.tolist(), 'energy_errors': [c.energy_error, hom.energy_error]}}
"""


def bone(tmp: Path, n: int, solves, runs: int) -> None:
    """Compression and kinematic homogenization of the micro-CT's central N^3 at each tolerance,
    against one solve to :data:`REFERENCE_TOL` (``--bone``)."""
    from _common import DATA

    path = tmp / f"bone_{n}.npy"
    info = run_isolated(BONE_BUILD.format(ct=str(DATA / BONE_CT), voxel=BONE_VOXEL, n=n, out=str(path)))
    voxel = info["voxel"]

    def solve(tol, count, accuracy=None):
        return median_runs(BONE_SOLVE.format(solid=str(path), voxel=voxel, tol=tol, accuracy=accuracy), count,
                           warmup=0)

    ref, _ = solve(REFERENCE_TOL, 1)
    C_ref = np.array(ref["C"])
    print(f"  bone {n}^3 reference to {REFERENCE_TOL:g}: compression {ref['compression_s']:.1f} s, "
          f"{ref['compression_its']} its; homogenization {ref['homogenization_s']:.1f} s, {ref['iterations']} its",
          file=sys.stderr, flush=True)
    rows = []
    for label, tol, accuracy in solves:
        med, results = solve(tol, runs, accuracy)
        first = results[0]  # every run solves the same voxels to the same iterate
        C = np.array(first["C"])
        rows.append([label, f"{statistics.median(r['compression_s'] for r in results):.1f}",
                     first["compression_its"], f"{abs(first['modulus'] / ref['modulus'] - 1):.1e}",
                     f"{statistics.median(r['homogenization_s'] for r in results):.1f}", first["iterations"],
                     f"{np.abs(C - C_ref).max() / np.abs(C_ref).max():.1e}",
                     " / ".join(_error(e) or "-" for e in first["energy_errors"]), f"{med['peak_rss_mb']:.0f}"])
        print(f"  bone {n}^3 {label} done: {med['seconds']:.1f} s", file=sys.stderr, flush=True)
    print(f"\nlumbar trabecular micro-CT, central {info['grid']} of {info['of']} voxels of {voxel:g} mm, solid "
          f"fraction {info['solid_fraction']:.3f}, Ti-6Al-4V; compression along z (lubricated platens) and "
          f"kinematic homogenization (six cases), one process per tolerance, runs: {runs}; reference: one solve to "
          f"{REFERENCE_TOL:g} (compression {ref['compression_s']:.1f} s, {ref['compression_its']} its, "
          f"E {ref['modulus']:.4g} GPa; homogenization {ref['homogenization_s']:.1f} s, {ref['iterations']} its)")
    print(table(rows, ["stop", "compression s", "CG its", "|dE/E|", "homogenization s", "CG its",
                       "max |dC|/max|C|", "energy errors (est.)", "peak MiB"]))


#: the data folder's CT of --ct (DICOM), and the intensity bone starts at (HU)
CT_DICOM = "totalseg_example_ct_dicom"
CT_THRESHOLD = 200

CT_BUILD = """
import numpy as np
from implicit_scaffold.measure.morphometry import read_scaffold
s = read_scaffold({ct!r}, threshold={threshold!r})
solid, f = s.solid, {factor!r}
if f > 1:  # the mean of each f^3 block, solid from half up: the CT as a scanner f times coarser sees it
    n = [d // f * f for d in solid.shape]
    solid = solid[:n[0], :n[1], :n[2]].reshape(n[0] // f, f, n[1] // f, f, n[2] // f, f).mean(axis=(1, 3, 5)) >= 0.5
np.save({out!r}, np.ascontiguousarray(solid))
_out = {{'grid': 'x'.join(map(str, solid.shape)), 'voxel': float(s.voxel) * f, 'solid_fraction': float(solid.mean())}}
"""

CT_SOLVE = """
import time
import numpy as np
from implicit_scaffold.measure import mechanics as M
if not {apart!r}:  # the sample as one system (the solver before pieces were solved apart)
    M.independent_pieces = lambda solid, *a, **k: (None, [])
solid = np.load({solid!r})
mat = M.material('ti64')
t = time.perf_counter()
c = M.compress(solid, {voxel!r}, mat, axis=2, tol=1e-6, backend='opencl', maxiter=5000, accuracy=M.ACCURACY)
tc = time.perf_counter() - t
t = time.perf_counter()
hom = M.homogenize(solid, {voxel!r}, mat, boundary='kinematic', tol=1e-6, backend='opencl', maxiter=5000,
                   accuracy=M.ACCURACY)
_out = {{'seconds': tc + time.perf_counter() - t, 'compression_s': tc, 'homogenization_s': time.perf_counter() - t,
        'modulus': c.apparent_modulus_gpa, 'compression_its': c.iterations, 'iterations': hom.iterations,
        'pieces': [c.pieces, hom.pieces], 'C': hom.stiffness.tolist()}}
"""


def ct(tmp: Path, factor: int, runs: int) -> None:
    """The data folder's CT (``--ct F``): compression along z and kinematic homogenization with the pieces
    that share no node solved apart (each on its own box) and as one system, in fresh processes."""
    from _common import DATA

    path = tmp / f"ct_{factor}.npy"
    info = run_isolated(CT_BUILD.format(ct=str(DATA / CT_DICOM), threshold=CT_THRESHOLD, factor=factor,
                                        out=str(path)))
    rows, found = [], {}
    for apart in (True, False):
        med, results = median_runs(CT_SOLVE.format(apart=apart, solid=str(path), voxel=info["voxel"]), runs,
                                   warmup=0)
        first = results[0]
        found[apart] = first
        rows.append(["apart" if apart else "one system", " / ".join(map(str, first["pieces"])),
                     f"{statistics.median(r['compression_s'] for r in results):.1f}", first["compression_its"],
                     f"{first['modulus']:.6g}", f"{statistics.median(r['homogenization_s'] for r in results):.1f}",
                     first["iterations"], f"{med['seconds']:.1f}", ", ".join(f"{r['seconds']:.1f}" for r in results),
                     f"{med['peak_rss_mb']:.0f}"])
        print(f"  CT {'apart' if apart else 'one system'} done: {med['seconds']:.1f} s", file=sys.stderr, flush=True)
    a, b = np.array(found[True]["C"]), np.array(found[False]["C"])
    scale = np.sqrt(np.outer(np.diag(b), np.diag(b)))
    print(f"\n{CT_DICOM} (data folder) from {CT_THRESHOLD} HU, {info['grid']} voxels of {info['voxel']:.4g} mm"
          + (f" (each {factor}^3 block solid from half up)" if factor > 1 else "")
          + f", solid fraction {info['solid_fraction']:.4f}, Ti-6Al-4V; compression along z (lubricated platens) "
          f"and kinematic homogenization (six cases), each to the default stop; runs: {runs}")
    print(table(rows, ["pieces", "pieces (comp. / hom.)", "compression s", "CG its", "E GPa", "homogenization s",
                       "CG its", "s (median)", "runs (s)", "peak MiB"]))
    print(f"apart against one system: max |dC_ij| / sqrt(C_ii C_jj) {np.max(np.abs(a - b) / scale):.1e}, "
          f"|dE/E| {abs(found[True]['modulus'] / found[False]['modulus'] - 1):.1e}; time ratio "
          f"{float(rows[1][7]) / float(rows[0][7]):.2f}x")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="*", default=[64, 128], help="grid sizes N (none: skip the timing)")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--tol", type=float, default=1e-6)
    ap.add_argument("--accuracy", type=float, default=None,
                    help="the solves' energy accuracy beside --tol (default mechanics.ACCURACY, as the commands "
                         "run them; 0: the tolerance alone)")
    ap.add_argument("--maxiter", type=int, default=2000,
                    help="stop the CG there (a capped run gives the time per iteration and the memory, "
                         "not a converged tensor: its residual says so)")
    ap.add_argument("--cases-per-block", type=int, default=None,
                    help="load cases per CG block (default mechanics.CASES_PER_BLOCK)")
    ap.add_argument("--fit", action="store_true")
    ap.add_argument("--fit-boundary", choices=["periodic", "kinematic"], default="periodic",
                    help="the fit's boundary conditions: the samples are cut from a non-periodic tessellation, "
                         "so periodic leaves struts dangling at the faces (soft) and kinematic holds them (stiff)")
    ap.add_argument("--fit-tessellation", choices=["cut", "periodic"], default="cut",
                    help="cut: struts of generate's box (a non-periodic tessellation, cut at the faces); periodic: "
                         "the Voronoi tessellation of 8 seeds in a 1 mm cube and their periodic images, whose "
                         "struts (capsules on the edges, no blend) are periodic, homogenized with periodic "
                         "conditions (the open-cell foam of Roberts & Garboczi)")
    ap.add_argument("--fit-seeds", type=int, default=3, help="periodic tessellations fitted together")
    ap.add_argument("--fit-voxels", type=int, default=64, help="voxels along the periodic cube's side")
    ap.add_argument("--mugrid", action="store_true")
    ap.add_argument("--convergence", action="store_true",
                    help="a 2 mm cube at generate's default voxel and at half of it")
    ap.add_argument("--coarsen", type=float, default=None, metavar="MM",
                    help="a MM cube at generate's default voxel h and at h/2, and the h/2 field sampled at h, "
                         "1.5 h and 2 h (the mechanics voxel of a run whose solve does not fit)")
    ap.add_argument("--across", type=float, nargs="*", default=None, metavar="N",
                    help="convergence with the voxel: a --across-size cube generated at voxels of the median wall "
                         "over N and over 2N, the platens' and the homogenization moduli and their change from h "
                         "to h/2 (e.g. --across 4 5 6 8)")
    ap.add_argument("--across-size", type=float, default=1.6, metavar="MM")
    ap.add_argument("--across-porosity", type=float, default=0.7)
    ap.add_argument("--across-seed", type=int, default=0)
    ap.add_argument("--across-kinematic", action="store_true",
                    help="--across also homogenizes with kinematic boundaries (a third solve per voxel)")
    ap.add_argument("--memory", type=int, nargs="*", default=None, metavar="N",
                    help="the solver's memory: peak above the process's resident set before it, per node and per "
                         "solid voxel, of compression and homogenization of N^3 gyroids (solid fractions 0.3, 0.6), "
                         "in fresh processes, beside mechanics.solve_memory's estimate")
    ap.add_argument("--memory-solves", default="compress,homogenize,measure",
                    help="--memory's solves: compress (one load case), homogenize (six), measure (both, as the "
                         "commands run them)")
    ap.add_argument("--memory-bone", type=int, nargs="*", default=[], metavar="N",
                    help="--memory also on the central N^3 of the lumbar trabecular micro-CT (kinematic boundaries)")
    ap.add_argument("--memory-blocks", default="1,6",
                    help="--memory's load cases per CG block (comma-separated)")
    ap.add_argument("--tolerances", type=float, nargs="*", default=None, metavar="R",
                    help="the solve at each of these CG tolerances against one to 1e-10")
    ap.add_argument("--accuracies", type=float, nargs="*", default=None, metavar="A",
                    help="as --tolerances, the default tolerance with each of these energy accuracies")
    ap.add_argument("--tolerance-size", type=int, default=128, metavar="N", help="the grid of --tolerances")
    ap.add_argument("--bone", type=int, default=None, metavar="N",
                    help="the central N^3 of the lumbar trabecular micro-CT in ../shared/data: compression and "
                         "kinematic homogenization at each --bone-tolerances, against one solve to 1e-10")
    ap.add_argument("--bone-tolerances", type=float, nargs="*", default=[1e-3, 1e-4, 1e-6], metavar="R")
    ap.add_argument("--bone-accuracies", type=float, nargs="*", default=[], metavar="A",
                    help="as --bone-tolerances, the default tolerance with each of these energy accuracies")
    ap.add_argument("--split", action="store_true", help="one more run of each size with every OpenCL product timed")
    ap.add_argument("--ct", type=int, default=None, metavar="F",
                    help="the data folder's CT (DICOM, from 200 HU), F times coarser (1: as read): its pieces "
                         "solved apart and as one system")
    ap.add_argument("--femur", action="store_true", help="the femoral shaft scaffold at 0.1 mm in Ti-6Al-4V and PCL")
    ap.add_argument("--femur-tol", type=float, default=1e-6,
                    help="the femur solves' CG tolerance (with --accuracy beside it, as the main solve)")
    ap.add_argument("--femur-maxiter", type=int, default=5000,
                    help="stop the femur solves' CG there (a capped run: its residual says how far it got)")
    ap.add_argument("--preconditioners", default="multigrid,fft",
                    help="comma-separated: ours with each (multigrid, fft), side by side in the same run")
    ap.add_argument("--peer-runs", type=int, default=1,
                    help="runs of the FFT preconditioner and of muGrid (each takes minutes: the median of "
                         "--runs is for ours)")
    ap.add_argument("--peers-up-to", type=int, default=64,
                    help="run the FFT preconditioner and muGrid only up to this N (theirs take hundreds of "
                         "iterations; 128^3 would take half an hour each)")
    args = ap.parse_args(argv)
    if args.cases_per_block is None:
        from implicit_scaffold.measure.mechanics import CASES_PER_BLOCK

        args.cases_per_block = CASES_PER_BLOCK
    if args.accuracy is None:
        from implicit_scaffold.measure.mechanics import ACCURACY

        args.accuracy = ACCURACY
    accuracy = args.accuracy or None
    voxel = 0.04
    tmp = Path(tempfile.mkdtemp(prefix="bench_mechanics_"))
    # its built scaffolds (up to some 100 MB) were left in /tmp by every run
    atexit.register(shutil.rmtree, tmp, True)
    rows = []
    for n in args.sizes:
        path, info = build(tmp, n, voxel=voxel, porosity=0.7)
        first = None
        for pc in args.preconditioners.split(","):
            if pc != "multigrid" and n > args.peers_up_to:
                continue
            med, runs = median_runs(OURS.format(solid=str(path), voxel=voxel, tol=args.tol, maxiter=args.maxiter,
                                                preconditioner=pc, block=args.cases_per_block, accuracy=accuracy),
                                    args.runs if pc == "multigrid" else args.peer_runs, warmup=0)
            # the solve's own memory: the peak above what the process held before it started
            per_voxel = (med["peak_rss_mb"] - med["rss_before_mb"]) * 2 ** 20 / med["solid_voxels"]
            name = {"multigrid": "multigrid", "fft": "FFT"}[pc]
            ratio = "" if first is None else f"; ratio {med['seconds'] / first['seconds']:.2f}x the first row's"
            solver = f"ours (OpenCL operator, {name}-PCG{ratio})" + (" capped" if med["iterations"] >= args.maxiter else "")
            rows.append([f"{info['grid']}", f"{info['solid_fraction']:.3f}", solver,
                         f"{med['seconds']:.1f}", med["iterations"], f"{med['residual']:.1e}",
                         _error(runs[0]["energy_error"]), f"{med['peak_rss_mb']:.0f}",
                         f"{med['libraries_mb']:.0f}", f"{per_voxel:.0f}",
                         ", ".join(f"{r['seconds']:.1f}" for r in runs)])
            if first is None:
                first, first_runs = med, runs
            print(f"  {n}^3 {pc} done: {med['seconds']:.1f} s", file=sys.stderr, flush=True)
        if args.split:
            split(path, n, voxel, args.tol, args.cases_per_block, accuracy)
        if args.mugrid and n <= args.peers_up_to:
            try:
                mg, mruns = median_runs(MUGRID.format(solid=str(path), voxel=voxel, tol=args.tol), args.peer_runs,
                                        warmup=0)
            except RuntimeError as exc:
                print(f"  mugrid failed at {n}^3: {str(exc).splitlines()[-1]}", file=sys.stderr)
            else:
                ours_C, mg_C = np.array(first_runs[0]["C"]), np.array(mg["C"])
                dev = np.abs(ours_C - mg_C).max() / np.abs(mg_C).max()
                ratio = first["seconds"] / mg["seconds"]
                rows.append([f"{info['grid']}", "", f"muGrid (ratio ours/mugrid {ratio:.2f}; "
                             f"max |dC|/max|C| {dev:.2e})", f"{mg['seconds']:.1f}", mg["iterations"], "", "",
                             f"{mg['peak_rss_mb']:.0f}", "", "", ", ".join(f"{r['seconds']:.1f}" for r in mruns)])
    if rows:
        print(table(rows, ["grid", "solid", "solver", "s (median)", "CG its", "residual", "energy error (est.)",
                           "peak MiB", "libraries MiB", "solve B/solid voxel", "runs (s)"]))
    if args.fit and args.fit_tessellation == "periodic":
        pts = []
        for seed in range(args.fit_seeds):
            r = run_isolated(PERIODIC_FIT.format(size=1.0, cells=8, voxels=args.fit_voxels, seed=seed,
                                                 rhos=(0.1, 0.15, 0.2, 0.25, 0.3, 0.4)), timeout=7200)
            print(f"seed {seed}: strut radius at rho 0.1 {r['strut_radius_voxels_at_0.1']:.2f} voxels; "
                  + ", ".join(f"rho {a:.3f} E/Es {b:.4g}" for a, b, _ in r["points"]), flush=True)
            pts += [tuple(p) for p in r["points"]]
        args.fit_boundary = "periodic tessellation, periodic"
    elif args.fit:
        pts = []
        for porosity in (0.9, 0.85, 0.8, 0.75, 0.7, 0.6):
            path, info = build(tmp, 48, voxel=0.025, porosity=porosity, style="struts", pore=0.6, seed=2)
            r = run_isolated(FIT.format(solid=str(path), voxel=0.025, boundary=args.fit_boundary), timeout=3600)
            pts.append((r["rho"], r["E_rel"], r["iterations"]))
    if args.fit:
        rho, erel = np.array([p[0] for p in pts]), np.array([p[1] for p in pts])
        sel = (rho >= 0.095) & (rho <= 0.405) & (erel > 0)  # the quantile leaves rho a hair under its target
        slope, intercept = np.polyfit(np.log(rho[sel]), np.log(erel[sel]), 1)
        print()
        print(table([[f"{a:.3f}", f"{b:.4g}", c] for a, b, c in pts], ["solid fraction rho", "E/Es", "CG its"]))
        print(f"{args.fit_boundary} boundary conditions; fit over rho in 0.1-0.4: E/Es = {np.exp(intercept):.3f} rho^{slope:.3f} "
              f"(Roberts & Garboczi 2001: 0.93 rho^2.04; the issue asks n in 1.8-2.3)")
    if args.convergence:
        def converge(voxel):
            r = run_isolated(ACROSS.format(size=2.0, voxel=voxel, porosity=0.7, seed=0, kinematic=False),
                             timeout=7200)
            return {**r, "Ex_gpa": r["periodic"][0], "Ez_gpa": r["periodic"][2]}

        coarse = converge(None)
        fine = converge(coarse["voxel"] / 2)
        rows = [[f"{r['voxel']:.4f}", r["grid"], f"{r['solid_fraction']:.4f}", f"{r['compression_gpa']:.4g}",
                 f"{r['Ez_gpa']:.4g}", f"{r['Ex_gpa']:.4g}", r["iterations"]] for r in (coarse, fine)]
        print()
        print(table(rows, ["voxel mm", "grid", "solid", "platens E_z GPa", "periodic E_z GPa", "periodic E_x GPa",
                           "CG its (hom, comp)"]))
        for key in ("compression_gpa", "Ez_gpa", "Ex_gpa"):
            print(f"  {key}: h -> h/2 changes by {100 * (coarse[key] / fine[key] - 1):+.2f} %")
    if args.coarsen:
        coarsen(args.coarsen)
    if args.across:
        across(args.across_size, args.across, args.across_porosity, args.across_seed, args.across_kinematic)
    if args.memory is not None or args.memory_bone:
        memory(args.memory or [], args.preconditioners.split(","), args.memory_solves.split(","),
               [int(b) for b in args.memory_blocks.split(",")], bones=args.memory_bone, tmp=tmp,
               maxiter=args.maxiter)
    if args.tolerances or args.accuracies:
        tolerances(tmp, args.tolerance_size, voxel, stops(args.tolerances, args.accuracies), args.runs,
                   args.cases_per_block)
    if args.bone:
        bone(tmp, args.bone, stops(args.bone_tolerances, args.bone_accuracies), args.runs)
    if args.femur:
        femur(tmp, args.femur_tol, args.femur_maxiter, args.preconditioners.split(",")[0], accuracy)
    if args.ct:
        ct(tmp, args.ct, args.runs)
    return 0


if __name__ == "__main__":
    sys.exit(main())
