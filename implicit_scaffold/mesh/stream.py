"""Marching cubes slab by slab, streamed to binary STL or PLY in bounded memory (stage 7, large grids).

:func:`write_mesh_slabs` meshes the solid ``field < level`` of a field source (an
:class:`~implicit_scaffold.run.tiles.ArraySlabs` or a :class:`~implicit_scaffold.run.tiles.FieldFile`)
one slab of cube layers along x at a time and appends each slab's triangles to the
file, so no more than one slab's field and triangles are held at once.

How slabs join without cracks
-----------------------------
Slab ``[x0, x1)`` meshes the cube layers between planes ``x0`` and ``x1``; the next
slab starts at plane ``x1``, so two slabs share that plane, and their vertices on it
must be the same bits. They are, because every value of the prepared copy (see
:mod:`implicit_scaffold.mesh.marching`) is the whole grid's value:

- clamping and nudging act voxel by voxel; only the grid's outer layer is forced
  outside (planes ``0`` and ``nx - 1`` only in the slabs that hold them);
- a round of face-tie breaking changes a voxel of plane ``i`` from the values of
  planes ``i`` and ``i + 1`` only, with a factor hashed from the voxel's index in the
  whole grid; after the ``TIE_ROUNDS`` rounds at most, plane ``i`` depends on planes
  ``i .. i + TIE_ROUNDS``. A slab therefore reads and breaks ties on
  ``1 + TIE_ROUNDS`` planes beyond ``x1`` (fewer at the grid's end) and none before ``x0``;
- a vertex on a grid plane has an exact integer x index, to which the slab's offset is
  added in float64 before scaling by the spacing and adding the origin.

The cubes on either side of the shared plane then decide every face in it the same
way, so the surface closes across it. The checks are exact and bounded too: vertices
on the shared plane are matched (by their coordinate bits) with the previous slab's
and take its global numbers. An edge with an end off the slab's first and last planes
has all its uses in the slab, which checks it (a compiled pass over each vertex's
outgoing edges: linear time, no sort); an edge lying in a shared plane is checked with
both slabs' uses of it, its ends named by their bits. So every edge is checked once,
with all its uses.

Two slabs at once
-----------------
Marching cubes holds Python's lock, so a large grid is meshed by two worker processes,
a slab each: each reads its planes, meshes them and checks its own edges, then hands
the parent only what lies on its first and last planes. The parent takes the slabs in
order: it numbers their vertices, checks the shared planes, and tells each worker where
its records go in the file (the triangles, and for PLY the new vertices, before it), so
the file gets the bytes one process writes, and it adds the slabs' sums in order.
"""
from __future__ import annotations

import contextlib
import os
import tempfile
from dataclasses import dataclass

import numpy as np

from ..errors import ScaffoldError
from ..run.executor import InProcess, Processes, free_cpus, start_method
from ..run.memory import available_memory, keep_freed_memory
from ..io.files import atomic_path, check_writable, folder_of, new_temp, remove_quietly
from .marching import (FACE_CHUNK, TIE_ROUNDS, break_face_ties, check_level, check_meshable, compiled_kernels,
                   face_measures, force_outside, index_to_mm, marching_cubes_surface, nothing_to_mesh, prepare_planes)
from .writers import STL_HEADER, ply_header, stl_buffer, stl_chunk
from ..run.tiles import ArraySlabs, FieldFile, plan_slabs

__all__ = ["MESH_BYTES_PER_TRIANGLE", "MESH_SLAB_BYTES_PER_VOXEL", "STREAM_FORMATS", "mesh_slab_bytes_per_voxel",
           "write_mesh_slabs"]

#: Mesh file formats :func:`write_mesh_slabs` writes, by extension.
from ..io.formats import MESH_STREAMED as STREAM_FORMATS  # noqa: E402

#: Peak bytes the mesh stage adds (all its processes, two slabs in flight) per voxel of
#: ``max_voxels``: ``max_voxels = room // MESH_SLAB_BYTES_PER_VOXEL`` keeps it within
#: ``room``. Measured on the B2 field (10 mm cube, 0.5 mm pores, 0.02 mm voxels: 0.40
#: triangles per voxel), one slab in flight, as VmHWM less the RSS at the start: 27.9,
#: 26.7 and 23.2 bytes per voxel for slabs of 79, 159 and 320 planes of 502 x 502. It is
#: the slab's float32 field (4) and, mostly, scikit-image's marching cubes, which peaks
#: at 50-80 bytes per triangle (about twice its outputs); so it grows with the triangles
#: per voxel: about ``4 + 80 * triangles_per_voxel`` per slab in flight. Two in flight
#: at B2: 56, rounded up to cover each worker process's own 50 MB (USS; its RSS shows
#: about 140 MB, most of it pages shared with the parent) from slabs of 13 M voxels up.
MESH_SLAB_BYTES_PER_VOXEL = 64
#: Peak bytes per triangle of one slab's marching cubes and arrays (the upper end of the 50-80
#: measured above); with the triangles per voxel of the field at hand it gives
#: :func:`mesh_slab_bytes_per_voxel`, which a field denser in surface than B2 needs.
MESH_BYTES_PER_TRIANGLE = 80


def mesh_slab_bytes_per_voxel(source, *, level: float = 0.0, samples: int = 8) -> float:
    """Peak bytes per voxel of ``max_voxels`` for :func:`write_mesh_slabs` on this field.

    The triangles per voxel are estimated from a few planes: each edge between voxels
    whose sides of the level differ holds one vertex, and a closed triangle mesh has
    about twice as many triangles as vertices. Two slabs may be in flight; never below
    :data:`MESH_SLAB_BYTES_PER_VOXEL`.

    Parameters
    ----------
    source : ArraySlabs or FieldFile
    level : float, mm
    samples : int
        Planes sampled (evenly along x).

    Returns
    -------
    float
    """
    nx = source.grid.shape[0]
    crossings = voxels = 0
    for x in np.unique(np.linspace(0, max(nx - 2, 0), samples).astype(np.int64)):
        solid = source.read(int(x), min(int(x) + 2, nx)) < level
        a = solid[0]
        crossings += int(np.count_nonzero(a[1:] != a[:-1])) + int(np.count_nonzero(a[:, 1:] != a[:, :-1]))
        if len(solid) > 1:
            crossings += int(np.count_nonzero(a != solid[1]))
        voxels += a.size
    per_voxel = 2.0 * crossings / max(voxels, 1)
    return max(float(MESH_SLAB_BYTES_PER_VOXEL), 2 * (4 + MESH_BYTES_PER_TRIANGLE * per_voxel) + 8)

#: Planes a slab reads beyond its last cube layer: that layer's far plane, and the
#: planes tie breaking looks ahead (module notes).
_AHEAD = 1 + TIE_ROUNDS
#: the two-sided halo that the slabs are planned with: a slab reads at least 1 + 2 * this planes
MESH_HALO_PLANES = (_AHEAD + 1) // 2
#: Global vertex numbers are PLY's int32.
_KEY_BASE = 2 ** 31
#: Bytes kept for the PLY header, written last: room for counts of 20 digits.
_PLY_HEADER_SIZE = len(ply_header(10 ** 19, 10 ** 19))
#: Slabs in flight at most (worker processes); the memory constant above counts on it.
_MAX_WORKERS = 2
#: Grids below this many voxels are meshed in this process: there, starting workers
#: costs about what they save.
_PARALLEL_MIN_VOXELS = 1 << 24


def write_mesh_slabs(source, path, *, level: float = 0.0, max_voxels: int, progress=None,
                     workers: int | None = None) -> dict:
    """Mesh the solid ``field < level`` of `source` slab by slab into a binary STL or PLY file.

    The file is what :func:`~implicit_scaffold.mesh.writers.write_mesh` writes for the whole
    grid's :func:`~implicit_scaffold.mesh.marching.mesh_field` of the same float32 values (same
    header text, same records; a PLY header's comment is padded with spaces to a fixed
    size): the same triangles, with vertices off the shared planes up to a float32
    rounding of their x index; with one slab, the same bytes for STL and the same
    vertices and faces for PLY. The slabs, and so the bytes, depend on `max_voxels`
    only, not on `workers`. Unlike :func:`~implicit_scaffold.mesh.marching.mesh_field`, an open
    surface (a bug) does not raise: the summary says so.

    Parameters
    ----------
    source : ArraySlabs or FieldFile
        A field source: ``.grid`` (a :class:`~implicit_scaffold.run.grid.Grid`) and
        ``.read(x0, x1)`` giving planes ``[x0, x1)`` as ``(x1 - x0, ny, nz)`` float32, mm.
    path : str or os.PathLike
        ``.stl`` (binary) or ``.ply`` (binary little-endian); written through a hidden
        temporary file renamed at the end, so an error or Ctrl-C leaves nothing.
    level : float, mm
        Iso-level: the solid is ``field < level``.
    max_voxels : int
        Voxels of field one slab may read, its look-ahead planes included: at least
        19 planes (one cube layer, its far plane and 17 planes of look-ahead, planned
        as a two-sided halo of 9 by :func:`~implicit_scaffold.run.tiles.plan_slabs`).
    progress : callable, optional
        ``progress(done, total)`` after each slab, counted in slabs, in order.
    workers : {None, 1, 2}
        Slabs meshed at once, each in a worker process (marching cubes holds Python's
        lock, so threads would not help). None: 2 when the grid has at least 2**24 voxels
        in 2 slabs or more, this process may use 2 CPUs, the memory free holds
        ``MESH_SLAB_BYTES_PER_VOXEL * max_voxels`` bytes and the source is a
        :class:`~implicit_scaffold.run.tiles.FieldFile` (or, where processes fork, an
        :class:`~implicit_scaffold.run.tiles.ArraySlabs`); else 1, in this process.

    Returns
    -------
    dict
        ``triangles`` (int), ``vertices`` (int, those on the planes shared by two slabs
        counted once), ``volume_mm3`` (float, signed enclosed volume by the divergence
        theorem), ``surface_area_mm2`` (float), ``watertight`` and ``winding_consistent``
        (bool: every edge used by exactly two triangles / in opposite directions, checked
        across the slabs), ``slabs`` (int), ``workers`` (int, processes that meshed).

    Raises
    ------
    ScaffoldError
        Unknown extension or a folder that cannot be written (before any work); a grid
        too small to mesh, a bad level, `max_voxels` below one slab, a field holding
        NaN, or no solid away from the grid's outer layer; more triangles than STL can
        count or vertices than PLY can number; bad `workers`; a worker process killed
        (e.g. by the system, out of memory).

    Notes
    -----
    Memory: per slab in flight, the slab's field (4 bytes per voxel read) while it is
    prepared and meshed, then scikit-image's marching cubes (its peak: 50-80 bytes per
    triangle) and this module's per-triangle arrays (the slab's vertices and faces, the
    face measures, the edge check's lists: less than that peak). The parent holds only
    the planes' vertices and edges. With two slabs in flight the stage adds at most
    ``MESH_SLAB_BYTES_PER_VOXEL * max_voxels`` bytes at B2's 0.4 triangles per voxel
    (see that constant for how it was measured and how it grows with the triangles).
    A worker process keeps what its slabs free for its next slab
    (:func:`~implicit_scaffold.run.memory.keep_freed_memory`) rather than fault it in again,
    so it holds its largest slab's peak until the stage ends, and the two workers' peaks
    meet: on B2 (morphometry off) the workers' largest resident set went from 0.88 to
    0.97 GiB and the mesh stage from 31.0 s to 16.0 s (2026-12-04, machine shared, load 6).
    """
    final = check_writable(path, formats=STREAM_FORMATS)
    grid = source.grid
    nx, ny, nz = (int(n) for n in grid.shape)
    check_meshable((nx, ny, nz))
    level = check_level(level)
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, (int, np.integer))
                                or not 1 <= workers <= _MAX_WORKERS):
        raise ScaffoldError(f"workers must be 1 or {_MAX_WORKERS} (slabs meshed at once), or None to choose "
                            f"by size; got {workers!r}")
    # slabs of cube layers (nx - 1 of them), each reading _AHEAD planes past its last
    # layer and none before: a two-sided halo of half that keeps it within max_voxels
    slabs = plan_slabs((nx - 1, ny, nz), max_voxels=max_voxels, halo=(_AHEAD + 1) // 2)
    spec = _worker_source(source)
    if workers is None:
        # a second slab in flight only where it fits in the memory free now (a safety net:
        # the caller sizes max_voxels with MESH_SLAB_BYTES_PER_VOXEL)
        workers = _MAX_WORKERS if (spec is not None and len(slabs) > 1 and nx * ny * nz >= _PARALLEL_MIN_VOXELS
                                   and free_cpus() >= _MAX_WORKERS
                                   and available_memory() > MESH_SLAB_BYTES_PER_VOXEL * int(max_voxels)) else 1
    elif workers > 1 and spec is None:
        raise ScaffoldError("slabs can be meshed in worker processes only from a FieldFile (or an ArraySlabs "
                            "where processes fork); pass workers=1")
    workers = min(workers, len(slabs))
    ply = final.suffix.lower() == ".ply"
    stitch = _Stitch(ply)
    with atomic_path(final) as tmp, contextlib.ExitStack() as stack:
        out = os.open(tmp, os.O_RDWR)
        stack.callback(os.close, out)
        # PLY's faces wait in a file beside the output and follow the vertices at the end
        faces_path = None
        if ply and workers > 1:
            faces_path = new_temp(final)  # named, for the workers; removed however the run ends
            stack.callback(remove_quietly, faces_path)
            faces = os.open(faces_path, os.O_RDWR)
        elif ply:
            faces = os.dup(stack.enter_context(tempfile.TemporaryFile(dir=folder_of(final))).fileno())
        if ply:
            stack.callback(os.close, faces)
        # STL: the count is patched at the end; PLY: the header is written last, over
        # the room kept for it
        _write_at(out, b"\0" * _PLY_HEADER_SIZE if ply else STL_HEADER + b"\0" * 4, 0)
        target = _Target(out_path=str(tmp), faces_path=faces_path, out=out, faces=faces if ply else None, ply=ply)
        if workers > 1:
            if start_method() == "fork":
                # loaded once here, the workers share scikit-image's and the kernels' code
                # pages with this process instead of loading (or compiling) their own
                from skimage.measure import marching_cubes  # noqa: F401
                compiled_kernels()
            job = _SlabJob(spec, level, _Target(str(tmp), faces_path, None, None, ply))
            executor = Processes(workers, name="implicit_scaffold-mesh")
        else:
            job, executor = _SlabJob(source, level, target), InProcess()

        def place(meshed):
            # in slab order: number the slab's vertices, check the plane it shares with the last
            if meshed is None:
                return stitch.skip()
            return stitch.add(meshed)

        with contextlib.closing(executor.map(_mesh_task, slabs, job, answer=place)) as results:
            for done, sums in enumerate(results, start=1):
                if sums is not None:
                    stitch.measured(*sums)  # in slab order, so that the totals do not depend on the workers
                if progress is not None:
                    progress(done, len(slabs))
        stitch.finish()
        if not stitch.solid:
            raise nothing_to_mesh(level)
        if ply:
            _copy_at(faces, out, _PLY_HEADER_SIZE + 24 * stitch.nverts, 13 * stitch.triangles)
            _write_at(out, ply_header(stitch.nverts, stitch.triangles, size=_PLY_HEADER_SIZE), 0)
        else:
            _write_at(out, np.array([stitch.triangles], dtype="<u4").tobytes(), len(STL_HEADER))
    return {
        "triangles": int(stitch.triangles),
        "vertices": int(stitch.nverts),
        "volume_mm3": float(stitch.volume),
        "surface_area_mm2": float(stitch.area),
        "watertight": stitch.watertight,
        "winding_consistent": stitch.winding_consistent,
        "bodies": stitch.bodies(),
        "slabs": len(slabs),
        "workers": int(workers),
    }


# ----------------------------------------------------------------------------- one slab


@dataclass
class _Meshed:
    """What the stitching needs of a meshed slab (small: its planes' vertices and edges).

    ``first_*``: the vertices on the slab's first plane, in local order (keys: their
    (y, z) bits, :func:`_plane_keys`); ``last_*``: those on its last plane, sorted by key;
    ``*_edges``: the directed edges lying in that plane, ``(m, 2)`` keys of their ends;
    ``*pieces``: the slab's surface pieces (vertices joined by the triangles' edges).
    """

    triangles: int
    vertices: int
    watertight: bool
    winding_consistent: bool
    first_keys: np.ndarray
    first_local: np.ndarray
    first_edges: np.ndarray
    last_keys: np.ndarray
    last_local: np.ndarray
    last_edges: np.ndarray
    #: the slab's connected pieces of surface, and the piece of each first- and last-plane
    #: vertex (in first_local's and last_local's order)
    pieces: int = 0
    first_pieces: np.ndarray | None = None
    last_pieces: np.ndarray | None = None


@dataclass
class _Place:
    """Where a slab's records go: triangles (and, PLY, new vertices) before it; its
    first-plane vertices that take the previous slab's numbers (local, global)."""

    triangles: int
    base: int
    matched_local: np.ndarray
    matched_numbers: np.ndarray


@dataclass
class _Target:
    """The output file (and PLY's faces file), by path for workers and as open descriptors."""

    out_path: str
    faces_path: str | None
    out: int
    faces: int | None
    ply: bool


def _slab_surface(source, x0: int, x1: int, level: float):
    """Marching cubes of the cube layers ``[x0, x1)``: ``(verts, faces)`` or None (no solid).

    ``verts`` ``(V, 3)`` float32, voxel index coordinates with x counted from plane
    `x0`; ``faces`` ``(F, 3)`` int32, wound outward.
    """
    grid = source.grid
    nx, ny, nz = (int(n) for n in grid.shape)
    end = min(x1 + _AHEAD, nx)
    planes = source.read(x0, end)
    if tuple(planes.shape) != (end - x0, ny, nz):
        raise ScaffoldError(f"the field source gave planes of shape {tuple(planes.shape)} for planes "
                            f"{x0}..{end - 1} of a {nx}x{ny}x{nz} grid; it does not match its grid")
    # prepared in place: the slab's own float32 copy
    work = np.require(planes, np.float32, ["C", "O", "W"])
    del planes
    prepare_planes(work, work, level, float(grid.spacing), x0)
    force_outside(work, first_x=x0 == 0, last_x=end == nx)
    break_face_ties(work, offset=x0 * ny * nz)
    cubes = work[:x1 - x0 + 1]
    if not cubes.min() < 0:
        return None
    # int32 corner numbers (scikit-image's own): half the bytes of the slab's largest array
    return marching_cubes_surface(cubes, index=np.int32, x0=x0)


def _mesh_slab(source, x0: int, x1: int, level: float):
    """Mesh slab ``[x0, x1)``, check its own edges and find its surface pieces:
    ``(verts, faces, _Meshed, piece of each vertex)`` or None."""
    surface = _slab_surface(source, x0, x1, level)
    if surface is None:
        return None
    verts, faces = surface
    del surface
    x = verts[:, 0]
    first = np.flatnonzero(x == 0)
    last = np.flatnonzero(x == np.float32(x1 - x0))
    plane = np.zeros(len(verts), np.int8)
    plane[first] = 1
    plane[last] = 2
    # edges in the first or last plane may have uses in the next or previous slab:
    # the stitching checks them with those; the slab checks all its others
    watertight, winding, first_edges, last_edges = compiled_kernels()["edge_check"](faces, len(verts), plane)
    del plane
    first_keys = _plane_keys(verts[first])
    last_keys = _plane_keys(verts[last])
    order = np.argsort(last_keys, kind="stable")
    meshed = _Meshed(
        triangles=len(faces), vertices=len(verts), watertight=bool(watertight), winding_consistent=bool(winding),
        first_keys=first_keys, first_local=first,
        first_edges=first_keys[np.searchsorted(first, first_edges)].reshape(-1, 2),
        last_keys=last_keys[order], last_local=last[order],
        last_edges=last_keys[np.searchsorted(last, last_edges)].reshape(-1, 2))
    pieces, labels = _surface_pieces(faces, len(verts))
    meshed.pieces, meshed.first_pieces, meshed.last_pieces = pieces, labels[first], labels[meshed.last_local]
    return verts, faces, meshed, labels


def _surface_pieces(faces: np.ndarray, nverts: int) -> tuple[int, np.ndarray]:
    """The pieces of a slab's surface: vertices joined by the triangles' edges (marching
    cubes' surface is a manifold, so pieces that share a vertex share an edge).

    Returns
    -------
    (int, (nverts,) int64 ndarray)
        How many, and each vertex's, numbered in order of each piece's least vertex.
    """
    labels, count = compiled_kernels()["vertex_pieces"](faces, nverts)
    return int(count), labels


def _write_slab(verts, faces, x0: int, grid, place: _Place, target: _Target,
                labels: np.ndarray | None = None) -> tuple:
    """Write a slab's records where `place` says; its ``(area, volume)`` sums, mm² and mm³, and
    the volume of each of its surface pieces (`labels`: each vertex's piece)."""
    centre = (grid.lo + grid.hi) / 2  # one reference point for every slab's volume
    nf = len(faces)
    if target.ply:
        new = np.ones(len(verts), bool)
        new[place.matched_local] = False
        numbers = np.empty(len(verts), np.int64)
        numbers[new] = np.arange(place.base, place.base + len(verts) - len(place.matched_local))
        numbers[place.matched_local] = place.matched_numbers
        vertices = index_to_mm(verts, grid, x0)
        _write_at(target.out, np.ascontiguousarray(vertices[new], dtype="<f8"), _PLY_HEADER_SIZE + 24 * place.base)
        del new
        a, v = face_measures(vertices, faces, ref=centre)
        del vertices
        buf = np.empty(13 * min(nf, FACE_CHUNK), np.uint8)
        for f0 in range(0, nf, FACE_CHUNK):
            f1 = min(f0 + FACE_CHUNK, nf)
            compiled_kernels()["ply_faces"](faces, numbers, f0, f1, buf)
            _write_at(target.faces, buf[:13 * (f1 - f0)], 13 * (place.triangles + f0))
    else:
        a = np.empty(nf)
        v = np.empty(nf)
        buf = stl_buffer(min(nf, FACE_CHUNK))
        offset = len(STL_HEADER) + 4 + 50 * place.triangles
        for f0 in range(0, nf, FACE_CHUNK):
            f1 = min(f0 + FACE_CHUNK, nf)
            records = stl_chunk(verts, faces, f0, f1, buf, grid=grid, x0=x0, ref=centre, area=a, vol=v)
            _write_at(target.out, records, offset + 50 * f0)
    # summed over the whole slab (NumPy's pairwise sum), as the summary always has
    pieces = None if labels is None else np.bincount(labels[faces[:, 0]], weights=v,
                                                     minlength=int(labels.max(initial=-1)) + 1)
    return float(a.sum()), float(v.sum()), pieces


def _write_at(fd: int, data, offset: int) -> None:
    """All of `data` (bytes or a contiguous array) into file `fd` at byte `offset`."""
    view = memoryview(data).cast("B")
    while view:
        if hasattr(os, "pwrite"):
            n = os.pwrite(fd, view, offset)
        else:  # pragma: no cover - Windows: each process has its own descriptor
            os.lseek(fd, offset, os.SEEK_SET)
            n = os.write(fd, view)
        view = view[n:]
        offset += n


def _copy_at(src: int, dst: int, offset: int, size: int, chunk: int = 1 << 22) -> None:
    """Copy the first `size` bytes of file `src` into file `dst` at `offset`."""
    done = 0
    while done < size:
        os.lseek(src, done, os.SEEK_SET)
        data = os.read(src, min(chunk, size - done))
        if not data:
            raise OSError("the temporary file of faces ended early")
        _write_at(dst, data, offset + done)
        done += len(data)


def _plane_keys(verts: np.ndarray) -> np.ndarray:
    """The (y, z) coordinates' bits of float32 vertices as one ``(V,)`` uint64 key each."""
    bits = np.ascontiguousarray(verts[:, 1:]).view(np.uint32).astype(np.uint64)
    return (bits[:, 0] << np.uint64(32)) | bits[:, 1]


# ----------------------------------------------------------------------------- stitching


class _Stitch:
    """Global vertex numbers, places in the file and the edge check across the planes
    two slabs share. Feed the slabs in order of x (:meth:`add` or :meth:`skip`, then
    :meth:`measured` for each added one), then :meth:`finish`.
    """

    def __init__(self, ply: bool):
        self.ply = ply
        self.nverts = 0
        self.triangles = 0
        self.area = 0.0
        self.volume = 0.0
        self.solid = False
        self.watertight = True
        self.winding_consistent = True
        # the previous slab's vertices on its last plane (sorted keys, global numbers)
        # and the directed edges lying in that plane (keys of their ends)
        self._keys = np.zeros(0, np.uint64)
        self._numbers = np.zeros(0, np.int64)
        self._edges = np.zeros((0, 2), np.uint64)
        # surface pieces numbered across slabs: the previous slab's last-plane vertices' pieces,
        # the pairs of pieces that share a vertex on a plane, and each piece's volume
        self._pieces = 0
        self._last_pieces = np.zeros(0, np.int64)
        self._joins: list[np.ndarray] = []
        self._piece_volumes: list[np.ndarray] = []

    def add(self, m: _Meshed) -> _Place:
        """Number a slab's vertices, check the plane it shares with the previous one; where it goes."""
        self.solid = True
        matched_local = matched_numbers = np.zeros(0, np.int64)
        if len(m.first_keys) and len(self._keys):
            at = np.minimum(np.searchsorted(self._keys, m.first_keys), len(self._keys) - 1)
            hit = self._keys[at] == m.first_keys
            matched_local = m.first_local[hit]  # ascending, as first_local is
            matched_numbers = self._numbers[at[hit]]
            if m.first_pieces is not None and len(self._last_pieces):
                self._joins.append(np.stack([self._last_pieces[at[hit]], self._pieces + m.first_pieces[hit]], 1))
        count = m.vertices - len(matched_local)
        if self.nverts + count > _KEY_BASE - 1:
            raise ScaffoldError(f"the mesh has more than {_KEY_BASE - 1} vertices, more than PLY can number; "
                                "use a larger --voxel")
        place = _Place(self.triangles, self.nverts, matched_local, matched_numbers)
        self.triangles += m.triangles
        if not self.ply and self.triangles >= 2 ** 32:
            raise ScaffoldError(f"more than {2 ** 32 - 1} triangles do not fit in an STL file; write .ply")
        # the shared plane's edges: the previous slab's uses and this one's
        self._check(np.concatenate([self._edges, m.first_edges]))
        self.watertight &= m.watertight
        self.winding_consistent &= m.winding_consistent
        # new vertices are numbered in local order after the matched ones are taken out
        # (none of them lies on the last plane)
        self._numbers = self.nverts + m.last_local - np.searchsorted(matched_local, m.last_local)
        self._keys = m.last_keys
        self._edges = m.last_edges
        self._last_pieces = (self._pieces + m.last_pieces if m.last_pieces is not None
                             else np.zeros(0, np.int64))
        self._pieces += m.pieces
        self.nverts += count
        return place

    def measured(self, area: float, volume: float, pieces=None) -> None:
        """Add a slab's sums (in slab order, so that the totals do not depend on the workers),
        and its pieces' volumes."""
        self.area += area
        self.volume += volume
        if pieces is not None:
            self._piece_volumes.append(np.asarray(pieces, np.float64))

    def bodies(self) -> int:
        """Closed pieces of surface of positive volume, joined across the slabs (as
        :func:`~implicit_scaffold.mesh.marching.mesh_summary` counts them on a whole mesh); a void
        sealed in the solid is a piece of negative volume and does not count."""
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components

        n = self._pieces
        if n == 0:
            return 0
        joins = np.concatenate(self._joins) if self._joins else np.zeros((0, 2), np.int64)
        graph = coo_matrix((np.ones(len(joins)), (joins[:, 0], joins[:, 1])), shape=(n, n))
        _, label = connected_components(graph, directed=False)
        volumes = np.concatenate(self._piece_volumes) if self._piece_volumes else np.zeros(n)
        return int(np.count_nonzero(np.bincount(label, weights=volumes[:n], minlength=label.max() + 1) > 0))

    def skip(self) -> None:
        """A slab without surface: whatever the previous slab left on its last plane stays open."""
        self._check(self._edges)
        self._edges = np.zeros((0, 2), np.uint64)
        self._keys = np.zeros(0, np.uint64)
        self._numbers = np.zeros(0, np.int64)
        self._last_pieces = np.zeros(0, np.int64)

    def finish(self) -> None:
        """Check the edges left on the last slab's last plane (none on a closed surface)."""
        self.skip()

    def _check(self, edges: np.ndarray) -> None:
        """Fold in the directed edges given (rows of end keys): each undirected edge used
        twice, once each way."""
        if not len(edges):
            return
        src, dst = edges[:, 0], edges[:, 1]
        lo = np.minimum(src, dst)
        hi = np.maximum(src, dst)
        backward = src > dst
        order = np.lexsort((backward, hi, lo))
        lo, hi, backward = lo[order], hi[order], backward[order]
        start = np.flatnonzero(np.concatenate([[True], (lo[1:] != lo[:-1]) | (hi[1:] != hi[:-1])]))
        count = np.diff(start, append=len(lo))
        self.watertight &= bool(np.all(count == 2))
        pair = start[count == 2]
        self.winding_consistent &= bool(np.all(backward[pair] != backward[pair + 1]))


# ----------------------------------------------------------------------------- the slab task


@dataclass(frozen=True)
class _SlabJob:
    """What every slab's meshing needs: the field source (or, for a worker process, how to
    open its own: :func:`_worker_source`), the level and the output."""

    source: object
    level: float
    target: _Target


def _worker_source(source):
    """How a worker process gets `source`, or None when it cannot."""
    if isinstance(source, FieldFile):
        return ("file", source.path, source.grid)  # its own reader: a shared one shares the offset
    if type(source) is ArraySlabs and start_method() == "fork":
        return source  # inherited
    return None


def _mesh_task(job: _SlabJob, slab):
    """Mesh one slab, ask the parent where its records go (its :class:`_Meshed`, or None for
    no surface, answered with a :class:`_Place`), write them there; its sums
    (:func:`_write_slab`) or None. A generator: see :mod:`~implicit_scaffold.run.executor`'s ``answer``."""
    source = job.source
    if isinstance(source, tuple):
        source = FieldFile.open_readonly(source[1], source[2])
    if job.target.out is None:
        # a worker process, which meshes slab after slab: its freed arrays stay for the next
        keep_freed_memory()
    try:
        held = _mesh_slab(source, slab.x0, slab.x1, job.level)
        place = yield None if held is None else held[2]
        if held is None:
            return None
        verts, faces_, _, labels = held
        del held
        target = job.target
        if target.out is not None:
            return _write_slab(verts, faces_, slab.x0, source.grid, place, target, labels)
        # a worker process: its own descriptors, opened by path
        out = os.open(target.out_path, os.O_WRONLY)
        faces = os.open(target.faces_path, os.O_WRONLY) if target.faces_path else None
        try:
            return _write_slab(verts, faces_, slab.x0, source.grid, place,
                               _Target(target.out_path, target.faces_path, out, faces, target.ply), labels)
        finally:
            os.close(out)
            if faces is not None:
                os.close(faces)
    finally:
        if source is not job.source:
            source.close()
