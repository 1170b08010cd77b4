"""Mesh simplification bounded by a tolerance, and the measure of what it moved (stage 7b).

Marching cubes gives about two triangles per surface voxel, most of them on flat
stretches. :func:`simplify_mesh` removes them with manifold3d's ``Manifold.simplify``:
edge collapses that keep the mesh a closed 2-manifold, whose vertices are a subset of
the input's and whose surface, the library says, moves by less than the tolerance.
Measured, it does not hold everywhere: somewhere the surface moves by a voxel or more,
in places where a thin strut is removed or a small tunnel closed (the genus drops) and in
others where the genus stays.
So it is off by default (:data:`DEFAULT_TOLERANCE_MM`) and the report gives what was
measured. Measured on the
default cube (``benchmarks/bench_core.py --only simplify``): quadric decimation (VTK's
``vtkQuadricDecimation`` and ``vtkDecimatePro``, pymeshlab's quadric edge collapse)
removes more triangles but moved the surface by 0.10-0.13 mm (two voxels) somewhere,
and VTK's left it open; fast-simplification 0.2.0 left it open too.

The library's promise is checked, not trusted: :func:`surface_deviation` measures the
distance from points to a triangle surface exactly (a spatial hash of the triangles,
exact point-triangle distances within a reach), and :func:`simplification_error` uses
it in both directions: each vertex of the input to the simplified surface, and the
simplified triangles' vertices, edge midpoints and centroids to the input surface.
"""
from __future__ import annotations

import math

import numpy as np

from ..errors import ScaffoldError

__all__ = ["DEFAULT_TOLERANCE_MM", "SIMPLIFY_BYTES_PER_TRIANGLE", "check_tolerance", "euler_characteristic",
           "shared_positions", "simplification_error", "simplify_mesh", "surface_deviation"]

#: The default tolerance: none (every triangle kept). manifold3d 3.5.4 moved the default
#: cube's surface by more than a quarter voxel at every tolerance measured from 0.05 voxel
#: up (a voxel or more somewhere; a few thin struts removed, small tunnels closed), and only
#: at 0.02 voxel stayed within it, for 10 % fewer triangles (benchmarks/bench_core.py --only
#: simplify). So simplification is asked for, with ``--tolerance``, and the report says what
#: it moved.
DEFAULT_TOLERANCE_MM = 0.0
#: Peak bytes per input triangle the simplification adds (manifold3d's halfedge structure,
#: its output and the float64 copies): a process that read the default cube's mesh (5.2 M
#: triangles) and simplified it peaked at 3,840 MB RSS, about 650 bytes per triangle beyond
#: the mesh; rounded up.
SIMPLIFY_BYTES_PER_TRIANGLE = 700


def euler_characteristic(mesh) -> int:
    """V - E + F of a closed triangle mesh (E = 3F/2): 2 - 2 genus for one closed body."""
    return int(len(mesh.vertices) - len(mesh.faces) // 2)


def check_tolerance(value) -> float:
    """`value` as a tolerance >= 0 in mm (0 turns simplification off; None: the default,
    :data:`DEFAULT_TOLERANCE_MM`); else a :class:`ScaffoldError` naming ``--tolerance``."""
    if value is None:
        return DEFAULT_TOLERANCE_MM
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ScaffoldError(f"--tolerance must be a distance in mm (0 keeps every triangle), got {value!r}") from None
    if not (math.isfinite(v) and v >= 0):
        raise ScaffoldError(f"--tolerance must be a distance >= 0 mm (0 keeps every triangle), got {value!r}")
    return v


def simplify_mesh(mesh, tolerance: float):
    """Fewer triangles, the surface moved by less than `tolerance` (manifold3d).

    Parameters
    ----------
    mesh : trimesh.Trimesh
        A closed, consistently wound triangle mesh (what :func:`~implicit_scaffold.mesh.marching.mesh_field` gives), mm.
    tolerance : float, mm
        What manifold3d's ``Manifold.simplify`` is given: it collapses edges so that, by its
        own account, the surface moves less than that. Measured, it does not always hold
        (thin struts removed, small tunnels closed): see :func:`simplification_error`.

    Returns
    -------
    trimesh.Trimesh
        Closed and 2-manifold (its genus may be lower), its vertices a subset of the input's (float64, the same
        bits), wound as the input. The same input gives the same arrays.

    Raises
    ------
    ScaffoldError
        manifold3d is not installed (the message names the package).
    RuntimeError
        manifold3d refused the mesh as not a closed manifold (a bug: the mesher's
        output is closed).
    """
    import trimesh

    try:
        import manifold3d
    except ImportError:  # pragma: no cover - a dependency; a broken install
        raise ScaffoldError("simplifying the mesh needs manifold3d: pip install manifold3d, "
                            "or pass --tolerance 0 to keep every triangle") from None
    vertices = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
    faces = np.ascontiguousarray(mesh.faces, dtype=np.uint64)
    solid = manifold3d.Manifold(manifold3d.Mesh64(vert_properties=vertices, tri_verts=faces))
    status = solid.status()
    if status != manifold3d.Error.NoError:
        raise RuntimeError(f"manifold3d refused the mesh ({status.name}): it is not a closed manifold; "
                           "please report the run (a bug), or pass --tolerance 0")
    del faces
    out = solid.simplify(float(tolerance)).to_mesh64()
    del solid
    v = np.array(out.vert_properties[:, :3], dtype=np.float64)
    f = np.array(out.tri_verts, dtype=np.int64)
    return trimesh.Trimesh(v, f, process=False)


def shared_positions(mesh) -> int:
    """The vertices of `mesh` at a position another vertex also holds (0 for marching cubes' output).

    An edge collapse can bring two sheets of the surface together: manifold3d keeps their
    vertices apart by index, so the mesh is closed and 2-manifold as it holds it, but a file
    that stores positions alone (STL), and every slicer, merges them, and reads the edges
    there as shared by four triangles (the femur in three pieces at ``--tolerance 0.05``,
    0.8 mm voxels: two such edges). Counted by sorting the positions' exact bits.
    """
    v = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
    if len(v) < 2:
        return 0
    rows = v.view(np.dtype((np.void, 24))).ravel()
    _, counts = np.unique(rows, return_counts=True)
    return int(counts[counts > 1].sum())


# ----------------------------------------------------------------------------- the measure


def surface_deviation(points, vertices, faces, reach: float, *, cell_scale: float = 1.0) -> np.ndarray:
    """Distance from each point to the triangle surface ``(vertices, faces)``, exact up to `reach`.

    Parameters
    ----------
    points : (n, 3) float ndarray, mm
    vertices : (v, 3) float ndarray, mm
    faces : (f, 3) int ndarray
    reach : float, mm
        Distances up to this are exact; a point farther from every triangle gets ``inf``.

    Returns
    -------
    (n,) float64 ndarray, mm

    Notes
    -----
    The triangles are hashed into cubic cells by their bounding boxes grown by `reach`,
    so every triangle within `reach` of a point is listed in the point's cell; the
    point's distance is the least exact point-triangle distance (Ericson's Voronoi-region
    test) over that list. Linear in the points and triangles for a surface of even
    triangle size; memory: about 24 bytes per (cell, triangle) pair.
    """
    points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    vertices = np.ascontiguousarray(vertices, dtype=np.float64).reshape(-1, 3)
    faces = np.ascontiguousarray(faces, dtype=np.int64).reshape(-1, 3)
    reach = float(reach)
    if not (math.isfinite(reach) and reach > 0):
        raise ValueError(f"reach must be a positive distance, got {reach!r}")
    out = np.full(len(points), np.inf)
    if not len(points) or not len(faces):
        return out
    tri = vertices[faces]
    lo = tri.min(axis=1) - reach
    hi = tri.max(axis=1) + reach
    extent = float(np.mean(np.max(hi - lo, axis=1)))
    cell = max(extent, 2 * reach) * cell_scale
    origin = np.minimum(lo.min(axis=0), points.min(axis=0))
    top = np.maximum(hi.max(axis=0), points.max(axis=0))
    dims = np.floor((top - origin) / cell).astype(np.int64) + 1
    if float(np.prod(dims.astype(np.float64))) >= 2.0 ** 62:
        raise ValueError("the points and triangles span too many cells; use a larger reach")
    k = _kernels()
    i0 = np.floor((lo - origin) / cell).astype(np.int64)
    i1 = np.floor((hi - origin) / cell).astype(np.int64)
    del lo, hi
    counts = np.prod(i1 - i0 + 1, axis=1)
    keys = np.empty(int(counts.sum()), np.int64)
    ids = np.empty(len(keys), np.int64)
    k["fill"](i0, i1, dims, np.concatenate([[0], np.cumsum(counts)]), keys, ids)
    del i0, i1, counts
    order = np.argsort(keys, kind="stable")
    keys = keys[order]
    ids = ids[order]
    del order
    cell_of = np.floor((points - origin) / cell).astype(np.int64)
    pkey = (cell_of[:, 0] * dims[1] + cell_of[:, 1]) * dims[2] + cell_of[:, 2]
    del cell_of
    # the points in cell order: neighbours read the same triangles
    by_cell = np.argsort(pkey, kind="stable")
    pkey = pkey[by_cell]
    start = np.searchsorted(keys, pkey, side="left")
    stop = np.searchsorted(keys, pkey, side="right")
    del keys, pkey
    found = np.full(len(points), np.inf)
    k["nearest"](points[by_cell], tri, ids, start, stop, reach * reach, found)
    out[by_cell] = found
    return out


def simplification_error(before, after, reach: float) -> dict:
    """How far the surface moved between `before` and `after` (two meshes of one solid), mm.

    Parameters
    ----------
    before, after : trimesh.Trimesh
    reach : float, mm
        Distances are exact up to this; beyond it they are reported as ``inf``.

    Returns
    -------
    dict
        ``to_simplified_mm``: the largest distance from a vertex of `before` to the
        surface of `after`; ``to_original_mm``: the largest distance from a vertex, an
        edge midpoint or a centroid of a triangle of `after` to the surface of `before`;
        ``max_mm``: the larger of the two.
    """
    va, fa = np.asarray(before.vertices, np.float64), np.asarray(before.faces, np.int64)
    vb, fb = np.asarray(after.vertices, np.float64), np.asarray(after.faces, np.int64)
    there = _deviation(va, vb, fb, reach)
    t = vb[fb]
    samples = np.concatenate([vb, t.mean(axis=1), (t[:, 0] + t[:, 1]) / 2, (t[:, 1] + t[:, 2]) / 2,
                              (t[:, 2] + t[:, 0]) / 2])
    del t
    back = _deviation(samples, va, fa, reach)
    a = float(there.max()) if len(there) else 0.0
    b = float(back.max()) if len(back) else 0.0
    return {"to_simplified_mm": a, "to_original_mm": b, "max_mm": max(a, b)}


def _deviation(points, vertices, faces, reach: float, wider: float = 8.0) -> np.ndarray:
    """:func:`surface_deviation` within `reach`, then the few points beyond it again within
    ``wider * reach`` (a small reach keeps the hash small; the far points are rare)."""
    d = surface_deviation(points, vertices, faces, reach)
    far = np.flatnonzero(np.isinf(d))
    if len(far):
        d[far] = surface_deviation(points[far], vertices, faces, wider * reach)
    return d


_KERNELS = None


def _kernels():
    """The compiled loops of :func:`surface_deviation` (numba), built on first use and cached on disk."""
    # a helper called by another kernel is a module global, not a closure cell (see tiles._key_kernels)
    global _KERNELS, _dist2
    if _KERNELS is not None:
        return _KERNELS
    import numba as nb

    from ..run.threads import by_rows

    @nb.njit(cache=True, nogil=True)
    def fill(i0, i1, dims, offsets, keys, ids):  # pragma: no cover - compiled
        for t in range(i0.shape[0]):
            n = offsets[t]
            for x in range(i0[t, 0], i1[t, 0] + 1):
                for y in range(i0[t, 1], i1[t, 1] + 1):
                    for z in range(i0[t, 2], i1[t, 2] + 1):
                        keys[n] = (x * dims[1] + y) * dims[2] + z
                        ids[n] = t
                        n += 1

    @nb.njit(cache=True, nogil=True)
    def _dist2(p, t):  # pragma: no cover - compiled
        # the closest point of triangle t (3, 3) to p by its Voronoi regions (Ericson, 5.1.5)
        ax, ay, az = t[0, 0], t[0, 1], t[0, 2]
        abx, aby, abz = t[1, 0] - ax, t[1, 1] - ay, t[1, 2] - az
        acx, acy, acz = t[2, 0] - ax, t[2, 1] - ay, t[2, 2] - az
        apx, apy, apz = p[0] - ax, p[1] - ay, p[2] - az
        d1 = abx * apx + aby * apy + abz * apz
        d2 = acx * apx + acy * apy + acz * apz
        if d1 <= 0.0 and d2 <= 0.0:
            return apx * apx + apy * apy + apz * apz
        bpx, bpy, bpz = p[0] - t[1, 0], p[1] - t[1, 1], p[2] - t[1, 2]
        d3 = abx * bpx + aby * bpy + abz * bpz
        d4 = acx * bpx + acy * bpy + acz * bpz
        if d3 >= 0.0 and d4 <= d3:
            return bpx * bpx + bpy * bpy + bpz * bpz
        vc = d1 * d4 - d3 * d2
        if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
            v = d1 / (d1 - d3)
            qx, qy, qz = apx - v * abx, apy - v * aby, apz - v * abz
            return qx * qx + qy * qy + qz * qz
        cpx, cpy, cpz = p[0] - t[2, 0], p[1] - t[2, 1], p[2] - t[2, 2]
        d5 = abx * cpx + aby * cpy + abz * cpz
        d6 = acx * cpx + acy * cpy + acz * cpz
        if d6 >= 0.0 and d5 <= d6:
            return cpx * cpx + cpy * cpy + cpz * cpz
        vb = d5 * d2 - d1 * d6
        if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
            w = d2 / (d2 - d6)
            qx, qy, qz = apx - w * acx, apy - w * acy, apz - w * acz
            return qx * qx + qy * qy + qz * qz
        va = d3 * d6 - d5 * d4
        if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
            w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
            qx = bpx - w * (t[2, 0] - t[1, 0])
            qy = bpy - w * (t[2, 1] - t[1, 1])
            qz = bpz - w * (t[2, 2] - t[1, 2])
            return qx * qx + qy * qy + qz * qz
        denom = 1.0 / (va + vb + vc)
        v = vb * denom
        w = vc * denom
        qx = apx - abx * v - acx * w
        qy = apy - aby * v - acy * w
        qz = apz - abz * v - acz * w
        return qx * qx + qy * qy + qz * qz

    @nb.njit(cache=True, nogil=True)
    def nearest_rows(points, tri, ids, start, stop, reach2, out, lo, hi):  # pragma: no cover - compiled
        for i in range(lo, hi):
            best = np.inf
            for j in range(start[i], stop[i]):
                d = _dist2(points[i], tri[ids[j]])
                if d < best:
                    best = d
            if best <= reach2:
                out[i] = np.sqrt(best)

    _KERNELS = {"fill": fill, "nearest": by_rows(nearest_rows)}
    return _KERNELS
