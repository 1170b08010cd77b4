"""Marching cubes slab by slab, streamed to binary STL or PLY in bounded memory (stage 7, large grids).

:func:`write_mesh_slabs` meshes the solid ``field < level`` of a field source (an
:class:`~implicit_scaffold.tiles.ArraySlabs` or a :class:`~implicit_scaffold.tiles.FieldFile`)
one slab of cube layers along x at a time and appends each slab's triangles to the
file, so no more than one slab's field and triangles are held at once.

How slabs join without cracks
-----------------------------
Slab ``[x0, x1)`` meshes the cube layers between planes ``x0`` and ``x1``; the next
slab starts at plane ``x1``, so two slabs share that plane, and their vertices on it
must be the same bits. They are, because every value of the prepared copy (see
:mod:`implicit_scaffold.mesh`) is the whole grid's value:

- clamping and nudging act voxel by voxel; only the grid's outer layer is forced
  outside (planes ``0`` and ``nx - 1`` only in the slabs that hold them);
- a round of face-tie breaking changes a voxel of plane ``i`` from the values of
  planes ``i`` and ``i + 1`` only, with a factor hashed from the voxel's index in the
  whole grid; after the ``_TIE_ROUNDS`` rounds at most, plane ``i`` depends on planes
  ``i .. i + _TIE_ROUNDS``. A slab therefore reads and breaks ties on
  ``1 + _TIE_ROUNDS`` planes beyond ``x1`` (fewer at the grid's end) and none before ``x0``;
- a vertex on a grid plane has an exact integer x index, to which the slab's offset is
  added in float64 before scaling by the spacing and adding the origin.

The cubes on either side of the shared plane then decide every face in it the same
way, so the surface closes across it. The checks are exact and bounded too: vertices
on the shared plane are matched (by their coordinate bits) with the previous slab's
and take its global numbers, and the edges lying in the shared plane are carried over
to the next slab's edge check, so every edge is checked once with all its uses.
"""
from __future__ import annotations

import contextlib
import shutil
import tempfile

import numpy as np

from .errors import ScaffoldError
from .mesh import (_TIE_ROUNDS, _break_face_ties, _check_level, _check_meshable, _edge_keys,
                   _face_measures, _folder_of, _force_outside, _index_to_mm, _nothing_to_mesh,
                   _ply_header, _prepare_planes, _STL_HEADER, _surface, _write_ply_faces,
                   _write_stl_records, atomic_path, check_writable)
from .tiles import plan_slabs

__all__ = ["STREAM_FORMATS", "write_mesh_slabs"]

#: Mesh file formats :func:`write_mesh_slabs` writes, by extension.
STREAM_FORMATS = (".stl", ".ply")

#: Planes a slab reads beyond its last cube layer: that layer's far plane, and the
#: planes tie breaking looks ahead (module notes).
_AHEAD = 1 + _TIE_ROUNDS
#: Global vertex numbers are PLY's int32, and an edge key packs two of them in an int64.
_KEY_BASE = 2 ** 31
#: Bytes kept for the PLY header, written last: room for counts of 20 digits.
_PLY_HEADER_SIZE = len(_ply_header(10 ** 19, 10 ** 19))


def write_mesh_slabs(source, path, *, level: float = 0.0, max_voxels: int, progress=None) -> dict:
    """Mesh the solid ``field < level`` of `source` slab by slab into a binary STL or PLY file.

    The file is what :func:`~implicit_scaffold.mesh.write_mesh` writes for the whole
    grid's :func:`~implicit_scaffold.mesh.mesh_field` of the same float32 values (same
    header text, same records; a PLY header's comment is padded with spaces to a fixed
    size): the same triangles, with vertices off the shared planes up to a float32
    rounding of their x index; with one slab, the same bytes for STL and the same
    vertices and faces for PLY. Memory: one slab of field (`max_voxels` float32) and
    its triangles. Unlike :func:`~implicit_scaffold.mesh.mesh_field`, an open surface
    (a bug) does not raise: the summary says so.

    Parameters
    ----------
    source : ArraySlabs or FieldFile
        A field source: ``.grid`` (a :class:`~implicit_scaffold.grid.Grid`) and
        ``.read(x0, x1)`` giving planes ``[x0, x1)`` as ``(x1 - x0, ny, nz)`` float32, mm.
    path : str or os.PathLike
        ``.stl`` (binary) or ``.ply`` (binary little-endian); written through a hidden
        temporary file renamed at the end, so an error or Ctrl-C leaves nothing.
    level : float, mm
        Iso-level: the solid is ``field < level``.
    max_voxels : int
        Voxels of field one slab may read, its look-ahead planes included: at least
        19 planes (one cube layer, its far plane and 17 planes of look-ahead, planned
        as a two-sided halo of 9 by :func:`~implicit_scaffold.tiles.plan_slabs`).
    progress : callable, optional
        ``progress(done, total)`` after each slab, counted in slabs.

    Returns
    -------
    dict
        ``triangles`` (int), ``vertices`` (int, those on the planes shared by two slabs
        counted once), ``volume_mm3`` (float, signed enclosed volume by the divergence
        theorem), ``surface_area_mm2`` (float), ``watertight`` and ``winding_consistent``
        (bool: every edge used by exactly two triangles / in opposite directions, checked
        across the slabs), ``slabs`` (int).

    Raises
    ------
    ScaffoldError
        Unknown extension or a folder that cannot be written (before any work); a grid
        too small to mesh, a bad level, `max_voxels` below one slab, a field holding
        NaN, or no solid away from the grid's outer layer; more triangles than STL can
        count or vertices than PLY can number.
    """
    final = check_writable(path, formats=STREAM_FORMATS)
    grid = source.grid
    nx, ny, nz = (int(n) for n in grid.shape)
    _check_meshable((nx, ny, nz))
    level = _check_level(level)
    # slabs of cube layers (nx - 1 of them), each reading _AHEAD planes past its last
    # layer and none before: a two-sided halo of half that keeps it within max_voxels
    slabs = plan_slabs((nx - 1, ny, nz), max_voxels=max_voxels, halo=(_AHEAD + 1) // 2)
    seams = _Seams()
    centre = (grid.lo + grid.hi) / 2  # one reference point for every slab's volume
    volume = area = 0.0
    triangles = 0
    solid = False
    ply = final.suffix.lower() == ".ply"
    with atomic_path(final) as tmp, open(tmp, "wb") as fh, contextlib.ExitStack() as stack:
        # PLY's faces wait in an unnamed file beside the output (gone however the run ends)
        faces_fh = stack.enter_context(tempfile.TemporaryFile(dir=_folder_of(final))) if ply else None
        # STL: the count is patched at the end; PLY: the header is written last, over
        # the room kept for it, and the faces follow the vertices
        fh.write(b"\0" * _PLY_HEADER_SIZE if ply else _STL_HEADER + b"\0" * 4)
        for done, slab in enumerate(slabs, start=1):
            surface = _slab_surface(source, slab.x0, slab.x1, level)
            if surface is not None:
                solid = True
                verts, faces = surface
                numbers, new = seams.add(verts, faces, slab.x1 - slab.x0)
                vertices = _index_to_mm(verts, grid, slab.x0)
                del verts
                a, v = _face_measures(vertices, faces, ref=centre)
                area += float(a.sum())
                volume += float(v.sum())
                del a, v
                triangles += len(faces)
                if ply:
                    fh.write(np.ascontiguousarray(vertices[new], dtype="<f8").tobytes())
                    _write_ply_faces(numbers[faces], faces_fh)
                else:
                    if triangles >= 2 ** 32:
                        raise ScaffoldError(f"more than {2 ** 32 - 1} triangles do not fit in an STL file; "
                                            "write .ply")
                    _write_stl_records(vertices, faces, fh)
                del vertices, faces, numbers, new
            else:
                seams.skip()
            if progress is not None:
                progress(done, len(slabs))
        seams.finish()
        if not solid:
            raise _nothing_to_mesh(level)
        if ply:
            faces_fh.seek(0)
            shutil.copyfileobj(faces_fh, fh, 1 << 22)
            fh.seek(0)
            fh.write(_ply_header(seams.nverts, triangles, size=_PLY_HEADER_SIZE))
        else:
            fh.seek(len(_STL_HEADER))
            fh.write(np.array([triangles], dtype="<u4").tobytes())
    return {
        "triangles": int(triangles),
        "vertices": int(seams.nverts),
        "volume_mm3": float(volume),
        "surface_area_mm2": float(area),
        "watertight": seams.watertight,
        "winding_consistent": seams.winding_consistent,
        "slabs": len(slabs),
    }


def _slab_surface(source, x0: int, x1: int, level: float):
    """Marching cubes of the cube layers ``[x0, x1)``: ``(verts, faces)`` or None (no solid).

    ``verts`` ``(V, 3)`` float32, voxel index coordinates with x counted from plane
    `x0`; ``faces`` ``(F, 3)`` int64, wound outward.
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
    _prepare_planes(work, work, level, float(grid.spacing), x0)
    _force_outside(work, first_x=x0 == 0, last_x=end == nx)
    _break_face_ties(work, offset=x0 * ny * nz)
    cubes = work[:x1 - x0 + 1]
    if not cubes.min() < 0:
        return None
    return _surface(cubes)


class _Seams:
    """Global vertex numbers and the edge check across the planes two slabs share.

    Feed the slabs in order of x (:meth:`add` or :meth:`skip`), then :meth:`finish`.
    """

    def __init__(self):
        self.nverts = 0
        self.watertight = True
        self.winding_consistent = True
        # the previous slab's vertices on its last plane: sorted (y, z) bit keys, numbers
        self._keys = np.zeros(0, np.uint64)
        self._numbers = np.zeros(0, np.int64)
        # directed edges lying in that plane, as _edge_keys over global numbers
        self._edges = np.zeros(0, np.int64)

    def add(self, verts: np.ndarray, faces: np.ndarray, last: int):
        """Number a slab's vertices and check its edges.

        `verts` are index coordinates from the slab's first plane, `last` the index of
        its last plane. Returns the global numbers ``(V,)`` int64 and which of them are
        new ``(V,)`` bool (the others were numbered by the previous slab).
        """
        keys = _plane_keys(verts)
        numbers = np.full(len(verts), -1, np.int64)
        first = np.flatnonzero(verts[:, 0] == 0)
        if len(first) and len(self._keys):
            at = np.minimum(np.searchsorted(self._keys, keys[first]), len(self._keys) - 1)
            hit = self._keys[at] == keys[first]
            numbers[first[hit]] = self._numbers[at[hit]]
        new = numbers < 0
        count = int(np.count_nonzero(new))
        if self.nverts + count > _KEY_BASE - 1:
            raise ScaffoldError(f"the mesh has more than {_KEY_BASE - 1} vertices, more than PLY can number; "
                                "use a larger --voxel")
        numbers[new] = np.arange(self.nverts, self.nverts + count)
        self.nverts += count

        on_last = verts[:, 0] == np.float32(last)
        corner = on_last[faces]
        # edge e runs from corner j to corner j + 1 of its face (as _edge_keys numbers them)
        seam = (corner & np.roll(corner, -1, axis=1)).reshape(-1)
        del corner
        edges = _edge_keys(numbers[faces], _KEY_BASE)
        self._check(np.concatenate([edges[~seam], self._edges]))
        self._edges = edges[seam]
        order = np.argsort(keys[on_last], kind="stable")
        self._keys = keys[on_last][order]
        self._numbers = numbers[on_last][order]
        return numbers, new

    def skip(self) -> None:
        """A slab without surface: whatever the previous slab left on its last plane stays open."""
        self._check(self._edges)
        self._edges = np.zeros(0, np.int64)
        self._keys = np.zeros(0, np.uint64)
        self._numbers = np.zeros(0, np.int64)

    def finish(self) -> None:
        """Check the edges left on the last slab's last plane (none on a closed surface)."""
        self.skip()

    def _check(self, keys: np.ndarray) -> None:
        """Fold in the edges given: each undirected edge used twice, once each way."""
        if not len(keys):
            return
        keys = np.sort(keys)
        undirected = keys >> 1
        start = np.flatnonzero(np.concatenate([[True], undirected[1:] != undirected[:-1]]))
        count = np.diff(start, append=len(keys))
        self.watertight &= bool(np.all(count == 2))
        pair = start[count == 2]
        # a pair's keys are 2u and 2u + 1 when its edges run opposite ways
        self.winding_consistent &= bool(np.all(keys[pair] != keys[pair + 1]))


def _plane_keys(verts: np.ndarray) -> np.ndarray:
    """The (y, z) coordinates' bits of float32 vertices as one ``(V,)`` uint64 key each."""
    bits = np.ascontiguousarray(verts[:, 1:]).view(np.uint32).astype(np.uint64)
    return (bits[:, 0] << np.uint64(32)) | bits[:, 1]
