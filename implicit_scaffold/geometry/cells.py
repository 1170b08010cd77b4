"""Voronoi cells bounded by a box, with ordered faces and their neighbours (stage 3).

voro++ (through ``pyvoro2``) computes each cell exactly. The two copies of a face
shared by two cells are made identical (the lower-numbered cell's copy, reversed
for the other), so that anything built on a face, a window rim, is the same for
both cells.

With radii the cells are power (Laguerre) cells: ``x`` belongs to the seed that
minimises ``|x - s_i|² - r_i²``. A seed may then lie outside its own cell, and a
seed outshone by its neighbours has no cell at all (it is dropped).
"""
from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass

import numpy as np

from ..errors import ScaffoldError


@dataclass(frozen=True)
class Cells:
    """A bounded Voronoi tessellation, flattened into arrays.

    Attributes
    ----------
    seeds : (n, 3) float64 ndarray, mm
        The seed of each cell (for power cells, only the seeds whose cell is not empty).
    lo, hi : (3,) float64 ndarray, mm
        The bounding box.
    volumes : (n,) float64 ndarray, mm³
    centroids : (n, 3) float64 ndarray, mm
        True (volume) centroids of the cells.
    face_cell : (nf,) int64 ndarray
        Cell that owns each face; every cell lists its own faces.
    face_neighbor : (nf,) int64 ndarray
        Cell across the face, or -1 for a box wall.
    face_start : (nf + 1,) int64 ndarray
        Face ``f`` has vertices ``face_vertices[face_start[f]:face_start[f + 1]]``.
    face_vertices : (m, 3) float64 ndarray, mm
        Polygon vertices, counter-clockwise seen from outside the owning cell.
    face_normals : (nf, 3) float64 ndarray
        Unit outward normals.
    face_areas : (nf,) float64 ndarray, mm²
    face_centroids : (nf, 3) float64 ndarray, mm
        Area centroids.
    radii : (n,) float64 ndarray, mm, or None
        The power radii of the cells' seeds; None for plain Voronoi cells.
    seed_index : (n,) int64 ndarray or None
        For power cells, the index of each cell's seed among the seeds given (seeds
        whose power cell is empty are left out); None for plain Voronoi cells, where
        cell ``i`` is seed ``i``.
    """

    seeds: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    volumes: np.ndarray
    centroids: np.ndarray
    face_cell: np.ndarray
    face_neighbor: np.ndarray
    face_start: np.ndarray
    face_vertices: np.ndarray
    face_normals: np.ndarray
    face_areas: np.ndarray
    face_centroids: np.ndarray
    radii: np.ndarray | None = None
    seed_index: np.ndarray | None = None

    @property
    def n(self) -> int:
        """Number of cells."""
        return len(self.seeds)

    def face(self, f: int) -> np.ndarray:
        """Vertices of face `f`, ``(k, 3)`` mm."""
        return self.face_vertices[self.face_start[f]:self.face_start[f + 1]]

    def faces_per_cell(self, *, walls: bool = False) -> np.ndarray:
        """Number of faces of each cell; box-wall faces count only if `walls`."""
        keep = np.ones(len(self.face_cell), bool) if walls else self.face_neighbor >= 0
        return np.bincount(self.face_cell[keep], minlength=self.n)

    def subset(self, keep) -> "Cells":
        """The cells where `keep` (bool, one per cell) holds, numbered ``0..k-1`` in their order.

        Each keeps its faces in their order, so whatever is built face by face on the
        subset (rims, cages, quads) is, value for value and in the same order, what is
        built on those faces of the whole. ``face_neighbor`` keeps the whole's numbering.
        """
        keep = np.asarray(keep, bool)
        new_id = np.cumsum(keep) - 1
        faces = keep[self.face_cell]
        counts = np.diff(self.face_start)
        verts = np.repeat(faces, counts)
        return Cells(seeds=self.seeds[keep], lo=self.lo, hi=self.hi, volumes=self.volumes[keep],
                     centroids=self.centroids[keep], face_cell=new_id[self.face_cell[faces]],
                     face_neighbor=self.face_neighbor[faces],
                     face_start=np.concatenate([[0], np.cumsum(counts[faces])]),
                     face_vertices=self.face_vertices[verts], face_normals=self.face_normals[faces],
                     face_areas=self.face_areas[faces], face_centroids=self.face_centroids[faces],
                     radii=None if self.radii is None else self.radii[keep],
                     seed_index=None if self.seed_index is None else self.seed_index[keep])

    def x_extents(self) -> tuple[np.ndarray, np.ndarray]:
        """The least and greatest x of each cell's vertices, mm."""
        counts = np.diff(self.face_start)
        cell_of_vertex = np.repeat(self.face_cell, counts)
        x = self.face_vertices[:, 0]
        lo = np.full(self.n, np.inf)
        hi = np.full(self.n, -np.inf)
        np.minimum.at(lo, cell_of_vertex, x)
        np.maximum.at(hi, cell_of_vertex, x)
        return lo, hi

    def interior_cells(self, margin: float) -> np.ndarray:
        """Boolean mask of the cells whose seeds lie at least `margin` mm from every wall."""
        return np.all((self.seeds - self.lo >= margin) & (self.hi - self.seeds >= margin), axis=1)


#: peak bytes per seed while voro++ builds the cells (measured over the process's start:
#: 20.8 KB at 20,000 seeds, 15.6 KB at 40,000 in two chunks; rounded up)
BYTES_PER_SEED = 24 * 1024
#: bytes per seed that the cells, the paper skeleton and its packed primitives hold through
#: the lattice stage (measured at 40,000 seeds: cells 120 MiB, skeleton 710 MiB, packed
#: primitives 690 MiB; 39 KB per seed), rounded up
HELD_BYTES_PER_SEED = 40 * 1024
#: of that, the cells' arrays alone (3.1 KB per seed measured), rounded up: what a tiled run
#: holds for the whole tessellation, the rest being built slab by slab
CELLS_BYTES_PER_SEED = 4 * 1024
#: bytes per seed while :func:`voronoi_cells` makes the arrays of cells built in chunks (their
#: polygons copied, old and new at once), after voro++'s chunks are gone (measured: 6.75 KB per
#: seed, 2,845 MiB above the seeds stage for the DICOM CT's 431,627 seeds), rounded up
CELLS_PEAK_BYTES_PER_SEED = 7 * 1024


def check_seed_memory(n: int, pore_size: float | None = None, available: int | None = None, *,
                      chunked: bool = True, seeds_given: bool = True, count_at=None) -> int:
    """Raise a :class:`ScaffoldError` before building cells for more seeds than memory holds.

    Parameters
    ----------
    n : int
        Number of seeds.
    pore_size : float, mm, optional
        The target pore size that gave `n`, to suggest one that fits.
    available : int, optional
        Bytes free (default: what the machine has free now); e.g. what ``--max-memory`` leaves.
    chunked : bool
        Whether the cells are built in chunks (:func:`_voro_cells`; the pipeline always
        builds them so), or at once.
    seeds_given : bool
        Whether the count came from ``--seeds`` (a refusal then suggests fewer); a graded
        run's count comes from its pore-size field.
    count_at : callable, optional
        The seed count at another pore size (mm), for the pore size a refusal suggests; by
        default ``n * (pore_size / pore)**3``. Seeds drawn in a patient's margin (one cell
        wide around it) scale otherwise: a shell's as ``pore**-2``, a speckle's not at all, and
        in a thresholded CT's thin bones they can be most of the seeds.

    Returns
    -------
    int
        The estimate, bytes.
    """
    from ..run.memory import available_memory

    # voro++'s cells of one chunk (and its margins' seeds) at a time beside the arrays of all of
    # them, then the arrays' copies
    need = _seed_memory(n, chunked)
    have = available_memory() if available is None else int(available)
    if need > have:
        if have < 64 * 2**20:  # the budget is spent before the cells: only a larger one helps
            from ..run.memory import amount, format_size, process_memory

            raise ScaffoldError(f"{n:,} seeds need about {amount(need)} to build their cells, beyond what "
                                f"this run holds already: pass --max-memory {format_size(process_memory() + need)} "
                                "or more")
        from ..run.memory import amount, format_size, process_memory

        most = have // (BYTES_PER_SEED + CELLS_BYTES_PER_SEED)
        if chunked and most > 2 * CHUNK_SEEDS:
            most = min((have - 2 * CHUNK_SEEDS * BYTES_PER_SEED) // CELLS_BYTES_PER_SEED,
                       have // CELLS_PEAK_BYTES_PER_SEED)
        fix = (f"use a larger --pore-size (e.g. {_fitting_pore_size(count_at or (lambda pore: n * (pore_size / pore) ** 3), pore_size, have, chunked):.3g} mm)"
               if pore_size else f"use fewer --seeds (at most {max(2, int(most)):,})" if seeds_given
               else "use larger pores")
        raise ScaffoldError(f"{n:,} seeds need about {amount(need)} to build their cells but only "
                            f"{amount(have)} is free within --max-memory; pass --max-memory "
                            f"{format_size(process_memory() + need)} or more, or {fix}")
    return need


def _seed_memory(n: int, chunked: bool) -> int:
    """Bytes that building the cells of `n` seeds takes (:func:`check_seed_memory`'s estimate)."""
    need = (min(int(n), 2 * CHUNK_SEEDS) if chunked else int(n)) * BYTES_PER_SEED + int(n) * CELLS_BYTES_PER_SEED
    return max(need, int(n) * CELLS_PEAK_BYTES_PER_SEED) if chunked else need


def _fitting_pore_size(count_at, pore_size: float, have: int, chunked: bool) -> float:
    """The smallest pore size (mm, within 1e-9 of it) from `pore_size` up whose seeds' cells
    take at most 0.9 of `have` bytes, ``count_at(pore)`` seeds at a pore size (non-increasing)."""

    def fits(pore: float) -> bool:
        return _seed_memory(int(math.ceil(count_at(pore))), chunked) <= 0.9 * have

    lo, hi = pore_size, pore_size * 2
    while not fits(hi):
        lo, hi = hi, hi * 2
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if fits(mid) else (mid, hi)
    return hi


#: polygon vertices whose properties are computed at once (bounds the temporaries, ~0.3 GB)
_PROPERTY_CHUNK = 2_000_000


def polygon_properties(vertices: np.ndarray, start: np.ndarray):
    """Newell normals, areas and area centroids of many planar polygons.

    Parameters
    ----------
    vertices : (m, 3) float ndarray, mm
    start : (k + 1,) int ndarray
        Polygon ``i`` is ``vertices[start[i]:start[i + 1]]``.

    Returns
    -------
    normals : (k, 3) float64 ndarray
        Unit normals, right-handed with the vertex order.
    areas : (k,) float64 ndarray, mm²
    centroids : (k, 3) float64 ndarray, mm
    """
    start = np.asarray(start, np.int64)
    if len(vertices) <= _PROPERTY_CHUNK:
        return _polygon_properties(vertices, start)
    # polygon by polygon the same values, in bounded memory: chunks of whole polygons
    cuts = np.unique(np.concatenate([[0], np.searchsorted(start, np.arange(_PROPERTY_CHUNK, len(vertices),
                                                                                _PROPERTY_CHUNK)),
                                     [len(start) - 1]]))
    parts = [_polygon_properties(vertices[start[a]:start[b]], start[a:b + 1] - start[a])
             for a, b in zip(cuts[:-1], cuts[1:])]
    return tuple(np.concatenate([q[i] for q in parts]) for i in range(3))


def _polygon_properties(vertices: np.ndarray, start: np.ndarray):
    counts = np.diff(start)
    poly = np.repeat(np.arange(len(counts)), counts)
    nxt = np.arange(len(vertices)) + 1
    nxt[start[1:] - 1] = start[:-1]
    a = vertices
    b = vertices[nxt]
    # fan triangles from each polygon's first vertex
    first = vertices[start[:-1]][poly]
    tri = np.cross(a - first, b - first) / 2
    k = len(counts)
    # sums in vertex order per polygon (bincount adds as np.add.at does, 5x faster)
    vec = np.stack([np.bincount(poly, weights=tri[:, j], minlength=k) for j in range(3)], axis=1)
    areas = np.linalg.norm(vec, axis=1)
    normals = vec / np.where(areas > 0, areas, 1)[:, None]
    w = np.einsum("ij,ij->i", tri, normals[poly])
    part = w[:, None] * (first + a + b) / 3
    cen = np.stack([np.bincount(poly, weights=part[:, j], minlength=k) for j in range(3)], axis=1)
    centroids = cen / np.where(areas > 0, areas, 1)[:, None]
    return normals, areas, centroids


def _gather_polygons(vertices: np.ndarray, start: np.ndarray, source: np.ndarray, reverse=None):
    """Polygons ``source[i]`` of ``(vertices, start)`` in turn, each reversed where `reverse` holds.

    Returns
    -------
    vertices : (m', 3) ndarray
    start : (len(source) + 1,) int64 ndarray
    """
    source = np.asarray(source, np.int64)
    start = np.asarray(start, np.int64)
    counts = np.diff(start)[source]
    out_start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    out = np.empty((int(out_start[-1]),) + vertices.shape[1:], vertices.dtype)
    # whole polygons about _PROPERTY_CHUNK vertices at a time: the indices take some 40 bytes a
    # vertex, beside the 24 of the vertices themselves (431,627 cells: 1.7 GB more at once)
    cuts = np.unique(np.concatenate([[0], np.searchsorted(out_start, np.arange(_PROPERTY_CHUNK, out_start[-1],
                                                                               _PROPERTY_CHUNK)), [len(source)]]))
    for a, b in zip(cuts[:-1], cuts[1:]):
        c = counts[a:b]
        k = np.arange(out_start[a], out_start[b], dtype=np.int64) - np.repeat(out_start[a:b], c)
        if reverse is not None:
            k = np.where(np.repeat(np.asarray(reverse[a:b], bool), c), np.repeat(c, c) - 1 - k, k)
        k += np.repeat(start[source[a:b]], c)
        out[out_start[a]:out_start[b]] = vertices[k]
    return out, out_start


def check_radii(radii, n: int) -> np.ndarray:
    """`radii` as a ``(n,)`` float64 array of finite lengths >= 0 mm, or a ScaffoldError."""
    try:
        r = np.asarray(radii, dtype=np.float64)
    except (TypeError, ValueError):
        raise ScaffoldError("power radii must be numbers (mm), one per seed") from None
    if r.shape != (n,):
        raise ScaffoldError(f"power radii must be one length per seed: got shape {r.shape} for {n} seeds")
    bad = ~(np.isfinite(r) & (r >= 0))
    if bad.any():
        i = int(np.argmax(bad))
        raise ScaffoldError(f"power radius {float(r[i]):g} of seed {i} is not a finite length >= 0 mm; "
                            "give every seed a radius >= 0")
    return r


#: seeds whose cells voro++ builds at once: its cells come back as Python objects, about
#: 54 KB per seed at the peak (BYTES_PER_SEED), so more seeds are built in chunks along x
CHUNK_SEEDS = 20000


@contextlib.contextmanager
def _collector_paused():
    """Python's cyclic garbage collector off for a block: voro++'s cells come back as many small
    dicts and lists, whose allocation sets off full collections of every object the process
    holds (45 ms each, half of the cells of 500 seeds), though none of them forms a cycle:
    counting references frees them."""
    import gc

    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()


def _flatten(raw) -> dict:
    """voro++'s cells (pyvoro2's dicts, in any order) as arrays, faces grouped by cell in id order.

    Returns ``ids`` (the cells' ids, ascending), ``volumes``, ``vertex_means`` (per cell),
    ``polygons`` (every face's vertices in turn), ``counts`` (vertices per face), ``owner``
    and ``neighbor`` (per face; -1 and below for a box wall).
    """
    raw = sorted(raw, key=lambda c: c["id"])
    ids = np.array([c["id"] for c in raw], dtype=np.int64)
    volumes = np.array([c["volume"] for c in raw], dtype=np.float64)
    verts_all, idx_all, counts, owner, neighbor, means = [], [], [], [], [], []
    base = 0
    for c in raw:
        v = np.asarray(c["vertices"], dtype=np.float64).reshape(-1, 3)
        verts_all.append(v)
        means.append(v.mean(axis=0) if len(v) else np.zeros(3))
        for face in c["faces"]:
            idx = face["vertices"]
            idx_all.extend(i + base for i in idx)
            counts.append(len(idx))
            owner.append(c["id"])
            neighbor.append(face["adjacent_cell"])
        base += len(v)
    polygons = (np.concatenate(verts_all)[np.asarray(idx_all, dtype=np.int64)] if idx_all
                else np.zeros((0, 3)))
    return {"ids": ids, "volumes": volumes, "vertex_means": np.asarray(means).reshape(-1, 3),
            "polygons": polygons, "counts": np.asarray(counts, dtype=np.int64),
            "owner": np.asarray(owner, dtype=np.int64),
            "neighbor": np.maximum(np.asarray(neighbor, dtype=np.int64), -1)}


def _voro_cells(seeds, lo, hi, radii, *, chunked: bool = True) -> dict:
    """Every seed's cell by voro++, as :func:`_flatten`'s arrays over all seeds (in id order),
    with ``kept`` (bool per seed): the seeds that have a (non-empty) cell.

    Up to :data:`CHUNK_SEEDS` seeds are computed at once. More are cut into chunks of
    that many consecutive seeds in x order, each computed with the seeds within a margin
    of it (at most :data:`CHUNK_SEEDS` / 2 of them on either side, so that voro++ never holds
    more than twice a chunk's cells). A cell is kept when it is provably the whole
    tessellation's: no seed beyond the margin cuts it (:func:`_loose_cells`). When many of a
    chunk's cells fail, the chunk is computed again with twice the margin while that fits;
    the few that still fail (seeds drawn in a patient: its surface cells reach the box's
    walls, cut by seeds anywhere along the surface) are computed again with the seeds that
    cut them (:func:`_settle`), until none does. The chunks depend on the seeds alone, never
    on the memory, so the same seeds always give the same cells.
    """
    import pyvoro2

    n = len(seeds)
    box = pyvoro2.Box(tuple(zip(lo, hi)))
    kw = {"mode": "power", "radii": radii} if radii is not None else {}

    def compute(sel, keep):
        # voro++ returns every cell of `sel`: only those in `keep` (ids) are kept
        extra = {"mode": "power", "radii": radii[sel]} if radii is not None else {}
        raw = pyvoro2.compute(seeds[sel], domain=box, output="cells", ids=sel.tolist(), return_adjacency=False,
                              **extra)
        return [c for c in raw if c["id"] in keep and (radii is None or (c["faces"] and c["volume"] > 0))]

    if n <= CHUNK_SEEDS or not chunked:
        raw = pyvoro2.compute(seeds, domain=box, output="cells", return_adjacency=False, **kw)
        if radii is not None:
            raw = [c for c in raw if c["faces"] and c["volume"] > 0]
        parts = [_flatten(raw)]
    else:
        from scipy.spatial import cKDTree

        tree = cKDTree(seeds)
        order = np.argsort(seeds[:, 0], kind="stable")
        xs = seeds[order, 0]
        # the seeds' own spacing, from their nearest neighbours (drawn in a patient, they fill
        # less than their box): a uniform (Poisson) density's mean is 0.554 of it
        spacing = float(np.mean(tree.query(seeds, k=2)[0][:, 1])) / 0.554
        side = CHUNK_SEEDS // 2
        parts = []
        for c0 in range(0, n, CHUNK_SEEDS):
            c1 = min(c0 + CHUNK_SEEDS, n)
            mine = set(order[c0:c1].tolist())
            a, b = xs[c0], xs[c1 - 1]
            margin = 2 * spacing
            while True:
                i0, i1 = np.searchsorted(xs, a - margin), np.searchsorted(xs, b + margin, side="right")
                reach_lo, reach_hi = a - margin if i0 > 0 else -np.inf, b + margin if i1 < n else np.inf
                # at most `side` seeds on either side: beyond, the x of the last seed taken bounds the
                # reach (the seeds left out lie at or beyond it), and a wider margin gains nothing
                full = c0 - i0 > side or i1 - c1 > side
                if c0 - i0 > side:
                    i0 = c0 - side
                    reach_lo = xs[i0]
                if i1 - c1 > side:
                    i1 = c1 + side
                    reach_hi = xs[i1 - 1]
                raw = compute(np.sort(order[i0:i1]), mine)
                loose = _loose_cells(raw, seeds, radii, tree, reach_lo, reach_hi)
                if not loose or full or len(loose) * LOOSE_SHARE <= len(raw):
                    break
                margin *= 2
            if loose:
                settled = [c for i, c in enumerate(raw) if i not in loose]
                raw = settled + _settle([raw[i] for i in sorted(loose)], seeds, radii, tree, compute)
            parts.append(_flatten(raw))
            del raw
    ids = np.concatenate([q["ids"] for q in parts])
    kept = np.zeros(n, bool)
    kept[ids] = True
    if len(parts) == 1:
        return {"kept": kept, **parts[0]}
    cell_order = np.argsort(ids, kind="stable")
    volumes = np.concatenate([q.pop("volumes") for q in parts])[cell_order]
    means = np.concatenate([q.pop("vertex_means") for q in parts])[cell_order]
    counts = np.concatenate([q.pop("counts") for q in parts])
    owner = np.concatenate([q.pop("owner") for q in parts])
    neighbor = np.concatenate([q.pop("neighbor") for q in parts])
    polygons = np.concatenate([q.pop("polygons") for q in parts])
    del parts
    # faces grouped by their cell, cells in id order, each cell's faces as voro++ gave them
    faces = np.argsort(owner, kind="stable")
    polygons, start = _gather_polygons(polygons, np.concatenate([[0], np.cumsum(counts)]), faces)
    return {"kept": kept, "volumes": volumes, "vertex_means": means, "polygons": polygons,
            "counts": np.diff(start), "owner": owner[faces], "neighbor": neighbor[faces]}


def _cutters(v, own, seeds, radii, tree, *, k: int = 1) -> tuple[np.ndarray, list]:
    """Which vertices `v` of cells are cut by some seed, and by which.

    A seed ``t`` cuts the cell of seed ``s`` only if some vertex ``v`` is nearer to it, in
    power distance, than to ``s``: ``|v - t|² - w_t < |v - s|² - w_s`` (``w = r²``, 0 for
    plain Voronoi cells). A cell none of whose vertices is so cut is the whole tessellation's.

    Parameters
    ----------
    v : (m, 3) float64 ndarray, mm
        Vertices.
    own : (m,) int64 ndarray
        The seed of each vertex's cell.
    seeds, radii, tree : the whole tessellation's seeds, radii (or None) and their k-d tree
    k : int
        For plain cells, the nearest `k` seeds are tried at each vertex (power cells: every
        seed in the vertex's ball).

    Returns
    -------
    cut : (m,) bool ndarray
    by : list of int ndarray
        For each cut vertex in turn, seeds that cut it (the nearest; at least one).
    """
    d2 = np.einsum("ij,ij->i", v - seeds[own], v - seeds[own])
    # rounding: a seed on the ball itself (the vertex's own seeds) does not cut
    tol = 1e-9 * (1.0 + float(np.abs(v).max(initial=0.0)))
    if radii is None:
        r = np.sqrt(d2)
        dist, idx = tree.query(v, k=k)
        dist, idx = dist.reshape(len(v), -1), idx.reshape(len(v), -1)
        near = dist < (r - tol)[:, None]
        cut = near[:, 0]
        return cut, [idx[i][near[i]] for i in np.nonzero(cut)[0]]
    w_max = float(np.max(radii) ** 2)
    d2 = d2 - radii[own] ** 2
    r = np.sqrt(np.maximum(d2 + w_max, 0.0))
    cut = np.zeros(len(v), bool)
    by = []
    for i, near in enumerate(tree.query_ball_point(v, r + tol)):
        near = np.asarray(near, dtype=np.int64)
        if not near.size:
            continue
        power = np.einsum("ij,ij->i", seeds[near] - v[i], seeds[near] - v[i]) - radii[near] ** 2
        inside = power < float(d2[i]) - tol * (1.0 + abs(float(d2[i])))
        if inside.any():
            cut[i] = True
            by.append(near[inside][np.argsort(power[inside], kind="stable")[:max(k, 1)]])
    return cut, by


def _cell_vertices(raw) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The vertices of the cells `raw` (pyvoro2's dicts), each one's cell (its index in `raw`) and seed."""
    counts = np.array([len(c["vertices"]) for c in raw], dtype=np.int64)
    v = (np.concatenate([np.asarray(c["vertices"], dtype=np.float64).reshape(-1, 3) for c in raw])
         if raw else np.zeros((0, 3)))
    cell = np.repeat(np.arange(len(raw)), counts)
    own = np.repeat(np.array([c["id"] for c in raw], dtype=np.int64), counts)
    return v, cell, own


def _loose_cells(raw, seeds, radii, tree, reach_lo: float, reach_hi: float) -> set:
    """The cells of `raw` (a chunk computed with every seed in the x range ``[reach_lo, reach_hi]``)
    that a seed outside that range may cut, as indices into `raw`.

    A vertex whose ball of radius ``sqrt(|v - s|² - w_s + max w)`` stays within the range is
    settled; the others (cells that reach into empty space, at the patient's surface) are
    checked against every seed with a k-d tree of them all (:func:`_cutters`).
    """
    if not raw:
        return set()
    v, cell, own = _cell_vertices(raw)
    d2 = np.einsum("ij,ij->i", v - seeds[own], v - seeds[own])
    w_max = 0.0
    if radii is not None:
        w_max = float(np.max(radii) ** 2)
        d2 = d2 - radii[own] ** 2
    r = np.sqrt(np.maximum(d2 + w_max, 0.0))
    cross = np.nonzero((v[:, 0] - r < reach_lo) | (v[:, 0] + r > reach_hi))[0]
    if cross.size == 0:
        return set()
    cut, _ = _cutters(v[cross], own[cross], seeds, radii, tree)
    return set(cell[cross[cut]].tolist())


#: a chunk whose failing cells are at most this share of it keeps its margin, and those cells are
#: computed again with the seeds that cut them (:func:`_settle`)
LOOSE_SHARE = 8
#: seeds tried at each cut vertex of a cell computed again (:func:`_settle`)
CUTTERS_PER_VERTEX = 8
#: a cell computed again this many times, still cut, is computed with every seed within twice its
#: reach (the seeds that can cut it, whatever the others)
SETTLE_ROUNDS = 16


def _settle(loose, seeds, radii, tree, compute) -> list:
    """The cells `loose` (pyvoro2's dicts, computed with too few seeds) as the whole tessellation's.

    Each round computes them again with their seeds, the neighbours across their faces (the
    seeds that made them) and the nearest seeds that cut a vertex (:func:`_cutters`): a cell
    is then the cell of those seeds, inside the one before and without the vertices that were
    cut. A cell none of whose vertices any seed cuts is the whole's, and kept; the others go
    round again. Every round adds a seed to every cell still cut, so the rounds end; after
    :data:`SETTLE_ROUNDS`, a cell is computed with every seed within twice its farthest vertex
    from its seed, which holds every seed that can cut it. The cells go to voro++ in batches
    of at most twice :data:`CHUNK_SEEDS` seeds, as the chunks do.
    """
    done = []
    rounds = 0
    while loose:
        rounds += 1
        v, cell, own = _cell_vertices(loose)
        cut, by = _cutters(v, own, seeds, radii, tree, k=CUTTERS_PER_VERTEX)
        still = np.zeros(len(loose), bool)
        still[cell[cut]] = True
        done += [c for c, s in zip(loose, still) if not s]
        need = {}  # per cell still cut: its seed, its faces' neighbours and the seeds that cut it
        for i, t in zip(cell[cut], by):
            need.setdefault(int(i), set()).update(t.tolist())
        if rounds >= SETTLE_ROUNDS:
            for i in need:
                mine = own[cell == i]
                far = float(np.linalg.norm(v[cell == i] - seeds[mine[0]], axis=1).max())
                if radii is not None:
                    far = float(np.sqrt(far ** 2 + np.max(radii) ** 2))
                need[i].update(tree.query_ball_point(seeds[mine[0]], 2 * far + 1e-9 * (1 + far)))
        batches, sel, ids = [], set(), set()
        for i in sorted(need):
            c = loose[i]
            mine = need[i] | {c["id"]} | {f["adjacent_cell"] for f in c["faces"] if f["adjacent_cell"] >= 0}
            if ids and len(sel | mine) > 2 * CHUNK_SEEDS:
                batches.append((sel, ids))
                sel, ids = set(), set()
            sel |= mine
            ids.add(c["id"])
        if ids:
            batches.append((sel, ids))
        loose = [c for sel, ids in batches for c in compute(np.array(sorted(sel), dtype=np.int64), ids)]
    return done


def voronoi_cells(seeds, lo, hi, *, radii=None, chunked: bool = True) -> Cells:
    """The Voronoi cells of `seeds`, clipped to the box ``[lo, hi]``.

    Parameters
    ----------
    seeds : (n, 3) float ndarray, mm
        Distinct points inside the box.
    lo, hi : (3,) array_like of float, mm
    radii : (n,) array_like of float, mm, optional
        Power radii, finite and >= 0: the power (Laguerre) cells, where ``x`` belongs
        to the seed minimising ``|x - s_i|² - r_i²`` (weights ``w_i = r_i²``; adding
        the same constant to every weight changes nothing). Seeds with an empty cell
        are left out of the result (see ``Cells.seed_index``). Without, the plain
        Voronoi cells.
    chunked : bool
        Build more than :data:`CHUNK_SEEDS` seeds' cells in chunks (:func:`_voro_cells`:
        voro++'s cells, as Python objects, for at most twice that many seeds at a time);
        False builds every cell at once. The cells are the same either way up to rounding:
        the same faces, neighbours and vertex counts, with volumes, areas and centroids
        within a few units in the last place (voro++ cuts a cell by its neighbours in an
        order that depends on the seeds it was given, which moves the vertices' last bits
        and each cell's order of faces). The chunks depend on the seeds alone.

    Returns
    -------
    Cells
    """
    seeds = np.ascontiguousarray(seeds, dtype=np.float64)
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    n = len(seeds)
    if n < 2:
        raise ScaffoldError(f"a Voronoi lattice needs at least 2 seeds, got {n}; pass --seeds 2 or more")
    if np.any(seeds < lo) or np.any(seeds > hi):
        raise ScaffoldError("every seed must lie inside the bounding box")
    weighted = radii is not None
    if weighted:
        radii = check_radii(radii, n)
    with _collector_paused():
        flat = _voro_cells(seeds, lo, hi, radii, chunked=chunked)
    seed_index = renumber = None
    if weighted:
        # voro++ leaves out the seeds whose power cell is empty: the others are renumbered 0..n'-1
        seed_index = np.nonzero(flat["kept"])[0].astype(np.int64)
        if len(seed_index) < 2:
            raise ScaffoldError(f"only {len(seed_index)} of {n} seeds keep a power cell; the radii differ too "
                                "much for the seeds' spacing, give closer radii")
        renumber = np.full(n, -1, np.int64)
        renumber[seed_index] = np.arange(len(seed_index))
        seeds, radii, n = seeds[seed_index], radii[seed_index], len(seed_index)
    elif not flat["kept"].all():
        raise ScaffoldError(f"voro++ returned {int(flat['kept'].sum())} cells for {n} seeds; are two seeds identical?")

    volumes = flat.pop("volumes")
    all_verts, counts, owner, neighbor = flat.pop("polygons"), flat.pop("counts"), flat.pop("owner"), flat.pop("neighbor")
    if weighted:
        owner = renumber[owner]
        neighbor = np.where(neighbor >= 0, renumber[np.maximum(neighbor, 0)], -1)
    # the point faces are oriented and pyramids summed from: the seed lies inside its Voronoi
    # cell, but not always inside its power cell; the mean of a cell's vertices always does
    ref = flat.pop("vertex_means") if weighted else seeds
    del flat
    start = np.concatenate([[0], np.cumsum(counts)])
    # drop repeated vertices: voro++ can emit edges of zero length
    prev = np.arange(len(all_verts)) - 1
    prev[start[:-1]] = start[1:] - 1
    scale = 1e-12 * (1 + np.abs(all_verts).max())
    keep = np.empty(len(all_verts), bool)
    for a in range(0, len(all_verts), _PROPERTY_CHUNK):  # in blocks: the differences take 32 bytes a vertex
        b = a + _PROPERTY_CHUNK
        keep[a:b] = np.linalg.norm(all_verts[a:b] - all_verts[prev[a:b]], axis=1) > scale
    del prev
    face_of = np.repeat(np.arange(len(counts)), counts)
    counts = np.bincount(face_of[keep], minlength=len(counts))
    all_verts = all_verts[keep]
    start = np.concatenate([[0], np.cumsum(counts)])
    good = counts >= 3
    verts, start = _gather_polygons(all_verts, start, np.nonzero(good)[0])
    owner, neighbor = owner[good], neighbor[good]
    del all_verts

    # make both copies of a shared face identical: the lower cell's copy wins
    key = owner * np.int64(n) + np.maximum(neighbor, 0)
    interior = np.nonzero(neighbor >= 0)[0]
    by_key = interior[np.argsort(key[interior], kind="stable")]
    twin = np.full(len(owner), -1, np.int64)
    higher = np.nonzero((neighbor >= 0) & (neighbor < owner))[0]
    want = neighbor[higher] * np.int64(n) + owner[higher]
    at = np.minimum(np.searchsorted(key[by_key], want), max(len(by_key) - 1, 0))
    found = (key[by_key[at]] == want) if len(by_key) else np.zeros(len(want), bool)
    twin[higher[found]] = by_key[at[found]]
    source = np.arange(len(owner))
    source[twin >= 0] = twin[twin >= 0]
    verts, start = _gather_polygons(verts, start, source, reverse=twin >= 0)
    counts = np.diff(start)
    normals, areas, fcen = polygon_properties(verts, start)
    # the twin's properties, bit for bit: a rim built on either copy is the same
    copy = np.nonzero(twin >= 0)[0]
    normals[copy], areas[copy], fcen[copy] = -normals[twin[copy]], areas[twin[copy]], fcen[twin[copy]]
    # orient every face outward from its cell's seed (or its vertex mean)
    flip = np.einsum("ij,ij->i", normals, fcen - ref[owner]) < 0
    if np.any(flip):
        verts, start = _gather_polygons(verts, start, np.arange(len(owner)), reverse=flip)
        normals[flip] *= -1
    keep = areas > 1e-14 * float(np.max(hi - lo)) ** 2
    if not np.all(keep):
        sel = np.nonzero(keep)[0]
        verts, start = _gather_polygons(verts, start, sel)
        owner, neighbor, normals, areas, fcen = owner[sel], neighbor[sel], normals[sel], areas[sel], fcen[sel]

    # volume centroid: pyramids from the seed (or the vertex mean) over every face
    h = np.einsum("ij,ij->i", normals, fcen - ref[owner])
    pyr_vol = areas * h / 3
    pyr_cen = ref[owner] + 0.75 * (fcen - ref[owner])
    vol = np.bincount(owner, weights=pyr_vol, minlength=n)
    cen = np.stack([np.bincount(owner, weights=pyr_vol * pyr_cen[:, a], minlength=n) for a in range(3)], 1)
    if weighted:
        # a sliver power cell can lose every face to the area floor: its centroid is its vertex mean
        flat = ~(vol > 0)
        vol[flat] = 1.0
        cen[flat] = ref[flat]
    centroids = cen / vol[:, None]
    return Cells(seeds=seeds, lo=lo, hi=hi, volumes=volumes, centroids=centroids,
                 face_cell=owner, face_neighbor=neighbor, face_start=start, face_vertices=verts,
                 face_normals=normals, face_areas=areas, face_centroids=fcen, radii=radii, seed_index=seed_index)
