"""The mesh writers (stage 8): STL, PLY, OBJ and 3MF, byte-identical for identical input.

:func:`write_mesh` writes a mesh in memory in the format its extension names (the registry is
:mod:`~implicit_scaffold.io.formats`), through :func:`~implicit_scaffold.io.files.atomic_path` (never a half-written file);
:func:`write_mesh_from_ply` converts the binary PLY that a slab-by-slab run streams
(:mod:`~implicit_scaffold.mesh.stream`) into any of them, block by block. :func:`stl_chunk` builds binary STL
records with the compiled per-triangle kernel that also gives the mesh's measures
(:func:`~implicit_scaffold.mesh.marching.face_measures`), so a streamed STL and a written one hold the same bytes.
Units are mm.
"""
from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from ..errors import ScaffoldError
from ..io.files import PiecewiseDeflate, atomic_path, check_format
from ..io.formats import MESH_WRITERS as MESH_FORMATS
from .marching import _NO_MEASURES, _NO_NUMBERS, FACE_CHUNK, compiled_kernels
from ..run.threads import imap

__all__ = ["FLOAT32_FORMATS", "MESH_FORMATS", "STL_HEADER", "float32_collapse_warning", "ply_header", "stl_buffer", "stl_chunk", "write_mesh", "write_mesh_from_ply"]

STL_HEADER = b"binary STL written by implicit_scaffold; units: mm".ljust(80, b" ")
_ZIP_DATE = (1980, 1, 1, 0, 0, 0)


def stl_buffer(n: int) -> np.ndarray:
    """Room for `n` binary STL records, as ``(25 n,)`` uint16 (zeros: the attribute bytes stay 0)."""
    return np.zeros(25 * n, np.uint16)




def stl_chunk(verts, faces, f0: int, f1: int, buf, *, grid=None, x0: int = 0, ref=None,
               area=_NO_MEASURES, vol=_NO_MEASURES) -> np.ndarray:
    """The binary STL records of faces ``[f0, f1)``, as a view of `buf` (from :func:`stl_buffer`).

    `verts` ``(V, 3)`` are float64 mm, or, with `grid`, float32 index coordinates with x
    counted from plane `x0` (turned into mm as :func:`index_to_mm` does). Each record
    is a unit normal from the winding (float64, cast to float32; zero for a collapsed
    triangle), the three corners (float32) and a zero attribute. With `ref` ``(3,)`` mm,
    `area` and `vol` (``(F,)`` float64) get entries ``[f0, f1)`` of :func:`face_measures`.
    """
    if grid is not None:
        origin = np.asarray(grid.origin, np.float64)
        h = float(grid.spacing)
    else:
        origin = np.zeros(3)
        h = 1.0
    ref = np.zeros(3) if ref is None else np.asarray(ref, np.float64)
    compiled_kernels()["triangles"](verts, faces, f0, f1, grid is not None, float(x0), h, origin, ref, buf, area, vol)
    return buf[:25 * (f1 - f0)]


#: formats whose coordinates are float32 (binary STL); PLY writes float64, OBJ and 3MF 9 digits
FLOAT32_FORMATS = (".stl",)


def float32_collapse_warning(path, grid, vertices=None) -> str | None:
    """A one-line warning when a float32 format cannot hold the mesh's vertices apart, or None
    (:func:`float32_merges`' warning)."""
    return float32_merges(path, grid, vertices)[1]


def float32_merges(path, grid, vertices=None, *, on_grid_edges: bool = False) -> tuple[int | None, str | None]:
    """The vertices a float32 format merges (None when not counted: not a float32 format, or a streamed mesh)
    and a one-line warning when it cannot hold them apart, or None.

    Marching cubes keeps a vertex at least ``_NUDGE / (_NUDGE + _CLAMP)`` of a voxel from a grid
    point (:mod:`~implicit_scaffold.mesh.marching`), so two vertices differ by at least that;
    float32 coordinates far from the origin are coarser (their step is 2^-23 of the coordinate:
    0.001 mm at 10,000 mm), and vertices closer than that step merge in the file: triangles
    collapse, edges join more than two triangles and the file is not watertight, though the mesh
    measured (float64) is.

    Parameters
    ----------
    path : str or Path
        The output; only a float32 format (:data:`FLOAT32_FORMATS`) is checked.
    grid : Grid
        The run's grid (its far corner bounds the coordinates), mm.
    vertices : (V, 3) float ndarray, mm, optional
        The mesh as written (float64): given, the vertices that merge in float32 are counted
        (exact); without it (a streamed mesh) the grid's farthest coordinate is compared with
        the smallest gap marching cubes leaves (a bound: it says "can").
    on_grid_edges : bool
        `vertices` are marching cubes' own (not simplified): where the bound says none can merge, none is
        counted (two sorts of every vertex, some 3.4 s for the default cube's 2.6 M, on every run).
    """
    from .marching import _CLAMP, _NUDGE

    if Path(path).suffix.lower() not in FLOAT32_FORMATS:
        return None, None
    corners = np.abs(np.stack([np.asarray(grid.origin, np.float64),
                               np.asarray(grid.origin, np.float64) + np.asarray(grid.shape) * grid.spacing]))
    far = float(corners.max())
    step = float(np.spacing(np.float32(far)))
    gap = _NUDGE / (_NUDGE + _CLAMP) * float(grid.spacing)
    way_out = (f"write .3mf or .ply (their coordinates keep the precision), or move the patient near the origin "
               f"(a float32 step is {step:.2g} mm at {far:.6g} mm from it)")
    if vertices is not None and not (on_grid_edges and step < gap):
        v = np.asarray(vertices, np.float64)
        merged = len(np.unique(v, axis=0)) - len(np.unique(v.astype(np.float32), axis=0))
        if merged == 0:
            return 0, None
        return merged, (f"{Path(path).name}: {merged:,} vertices merge in the STL's float32 coordinates, so some "
                        "triangles collapse and the file is not watertight (the report's watertight is the file's; "
                        "the mesh in float64 was closed); " + way_out)
    if step < gap:
        return (0 if vertices is not None else None), None
    return None, (f"{Path(path).name}: the STL's float32 coordinates are coarser than the smallest gap between the "
                  f"mesh's vertices ({gap:.2g} mm at --voxel {grid.spacing:g}), so vertices can merge, triangles "
                  "collapse and the file not be watertight though the report (measured in float64) says so; "
                  + way_out)


def write_mesh(mesh, path) -> Path:
    """Write a triangle mesh, atomically and deterministically, in the format its extension names.

    ``.stl`` binary STL (float32, fixed header text), ``.ply`` binary little-endian
    PLY (float64 vertices), ``.obj`` Wavefront OBJ, ``.3mf`` 3D Manufacturing Format
    (a zip whose entries carry a fixed 1980-01-01 date; no UUIDs). The same mesh gives
    the same bytes every time. Text formats write coordinates with 9 significant
    digits. Units are mm.

    Parameters
    ----------
    mesh : trimesh.Trimesh
    path : str or os.PathLike

    Returns
    -------
    pathlib.Path

    Raises
    ------
    ScaffoldError
        Unknown extension (the message names the allowed ones), or the folder cannot
        be written to.
    """
    final = Path(path)
    ext = check_format(final, MESH_FORMATS)
    vertices = np.asarray(mesh.vertices, dtype=np.float64).reshape(-1, 3)
    faces = np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3)
    writer = {".stl": _write_stl, ".ply": _write_ply, ".obj": _write_obj, ".3mf": _write_3mf}[ext]
    with atomic_path(final) as tmp, open(tmp, "wb") as fh:
        writer(vertices, faces, fh)
    return final


def _write_stl(vertices, faces, fh) -> None:
    if len(faces) >= 2 ** 32:
        raise ScaffoldError(f"{len(faces)} triangles do not fit in an STL file; write .ply or .3mf")
    fh.write(STL_HEADER)
    fh.write(np.array([len(faces)], dtype="<u4").tobytes())
    _write_stl_records(vertices, faces, fh)


def _write_stl_records(vertices, faces, fh) -> None:
    """The 50-byte triangle records of binary STL (normal from the winding, float32)."""
    vertices = np.asarray(vertices, np.float64)
    buf = stl_buffer(min(len(faces), FACE_CHUNK))
    for f0 in range(0, len(faces), FACE_CHUNK):
        fh.write(stl_chunk(vertices, faces, f0, min(f0 + FACE_CHUNK, len(faces)), buf))


def ply_header(nverts: int, nfaces: int, size: int = 0) -> bytes:
    """The binary PLY header; its comment is padded with spaces to `size` bytes when shorter."""
    def text(comment):
        return ("ply\nformat binary_little_endian 1.0\n"
                f"{comment}\n"
                f"element vertex {nverts}\n"
                "property double x\nproperty double y\nproperty double z\n"
                f"element face {nfaces}\n"
                "property list uchar int vertex_indices\nend_header\n").encode("ascii")

    comment = "comment written by implicit_scaffold; units: mm"
    header = text(comment)
    return text(comment + " " * (size - len(header))) if size > len(header) else header


def _write_ply(vertices, faces, fh) -> None:
    fh.write(ply_header(len(vertices), len(faces)))
    fh.write(np.ascontiguousarray(vertices, dtype="<f8").tobytes())
    _write_ply_faces(faces, fh)


def _write_ply_faces(faces, fh) -> None:
    """The face records of binary PLY: a count byte (3) and three int32 vertex indices."""
    buf = np.empty(13 * min(len(faces), FACE_CHUNK), np.uint8)
    for f0 in range(0, len(faces), FACE_CHUNK):
        f1 = min(f0 + FACE_CHUNK, len(faces))
        compiled_kernels()["ply_faces"](faces, _NO_NUMBERS, f0, f1, buf)
        fh.write(buf[:13 * (f1 - f0)])


def _formatted(fmt: str, rows: np.ndarray, chunk: int = 1 << 16):
    """Rows formatted with the %-format `fmt` (one row each), as ASCII byte chunks.

    `fmt` holds three fields, all ``%.9g`` (float rows) or all ``%d`` (integer rows), and
    plain text between them. A compiled loop writes the text, the same bytes as Python's
    ``fmt % row`` (2.6 M rows of vertices: 0.53 s against 1.75 s, in chunks on the thread pool); a ``%.9g`` value
    whose rounding the loop cannot decide (within 2e-6 of a half in its ninth digit, or
    beyond the magnitudes it handles) is formatted by Python.
    """
    floats = "%.9g" in fmt
    field = "%.9g" if floats else "%d"
    text = fmt.split(field)
    if len(text) != 4 or any("%" in t for t in text):
        raise ValueError(f"a row format of three {field} fields, got {fmt!r}")
    pieces = [np.frombuffer(t.encode("ascii"), np.uint8) for t in text]
    literal = np.concatenate(pieces)
    bounds = np.cumsum([0] + [len(t) for t in pieces]).astype(np.int64)
    rows = np.ascontiguousarray(rows, dtype=np.float64 if floats else np.int64).reshape(-1, 3)
    kernel = _text_kernels()[0 if floats else 1]
    n = len(rows)

    def piece(r0: int) -> bytes:
        # a %.9g field takes at most 16 characters, a %d one 20
        r1 = min(r0 + chunk, n)
        out = np.empty((r1 - r0) * (len(literal) + 3 * 20), np.uint8)
        parts = []
        while r0 < r1:
            end, stop = kernel(rows, r0, r1, literal, bounds, out)
            parts.append(out[:end].tobytes())
            if stop < r1:
                parts.append((fmt % tuple(rows[stop].tolist())).encode("ascii"))
            r0 = stop + 1 if stop < r1 else r1
        return b"".join(parts)

    yield from imap(piece, range(0, n, chunk))


_TEXT_KERNELS = None


def _text_kernels():
    """The compiled row formatters (numba, cached on disk): ``(float rows, integer rows)``,
    each ``kernel(rows, r0, r1, literal, bounds, out) -> (bytes written, row stopped at)``."""
    # helpers called by other kernels are module globals, not closure cells (see tiles._key_kernels)
    global _TEXT_KERNELS, _put_int, _put_text, _put_g9
    if _TEXT_KERNELS is not None:
        return _TEXT_KERNELS
    import math

    import numba as nb

    pow10 = np.array([10.0 ** k for k in range(23)])  # exact in float64

    @nb.njit(cache=True, nogil=True, boundscheck=False)
    def _put_int(v, out, pos):  # pragma: no cover - compiled
        if v < 0:
            out[pos] = 45
            pos += 1
            v = -v
        n = 1
        t = v // 10
        while t:
            n += 1
            t //= 10
        for i in range(n - 1, -1, -1):
            out[pos + i] = 48 + v % 10
            v //= 10
        return pos + n

    @nb.njit(cache=True, nogil=True, boundscheck=False)
    def _put_g9(x, out, pos, pow10, digits):  # pragma: no cover - compiled
        # Python's '%.9g' % x, or -1 when the ninth digit's rounding is not certain. m is
        # x scaled to nine integer digits by one exact power of ten: one rounding, so within
        # 1.2e-7 of the true value, and the round to nearest is certain unless m lies
        # within 2e-6 of a half
        if not math.isfinite(x):
            return -1
        if x == 0.0:
            if math.copysign(1.0, x) < 0:
                out[pos] = 45
                pos += 1
            out[pos] = 48
            return pos + 1
        if x < 0:
            out[pos] = 45
            pos += 1
            x = -x
        e = int(math.floor(math.log10(x)))
        m = 0.0
        for _ in range(4):
            k = 8 - e
            if k > 22 or k < -22:
                return -1
            m = x * pow10[k] if k >= 0 else x / pow10[-k]
            if m >= 999999999.5:
                e += 1
            elif m < 99999999.5:
                e -= 1
            else:
                break
        else:
            return -1
        frac = m - math.floor(m)
        if abs(frac - 0.5) < 2e-6:
            return -1
        r = int(math.floor(m + 0.5))
        for i in range(8, -1, -1):
            digits[i] = r % 10
            r //= 10
        last = 8  # the last digit kept: trailing zeros go
        while last > 0 and digits[last] == 0:
            last -= 1
        if -4 <= e < 9:
            if e >= 0:
                for i in range(e + 1):
                    out[pos] = 48 + digits[i]
                    pos += 1
                if last > e:
                    out[pos] = 46
                    pos += 1
                    for i in range(e + 1, last + 1):
                        out[pos] = 48 + digits[i]
                        pos += 1
            else:
                out[pos] = 48
                out[pos + 1] = 46
                pos += 2
                for _ in range(-e - 1):
                    out[pos] = 48
                    pos += 1
                for i in range(last + 1):
                    out[pos] = 48 + digits[i]
                    pos += 1
            return pos
        out[pos] = 48 + digits[0]
        pos += 1
        if last > 0:
            out[pos] = 46
            pos += 1
            for i in range(1, last + 1):
                out[pos] = 48 + digits[i]
                pos += 1
        out[pos] = 101
        out[pos + 1] = 45 if e < 0 else 43
        pos += 2
        a = -e if e < 0 else e
        if a < 10:
            out[pos] = 48
            pos += 1
        return _put_int(a, out, pos)

    @nb.njit(cache=True, nogil=True, boundscheck=False)
    def _put_text(literal, bounds, j, out, pos):  # pragma: no cover - compiled
        for i in range(bounds[j], bounds[j + 1]):
            out[pos] = literal[i]
            pos += 1
        return pos

    @nb.njit(cache=True, nogil=True, boundscheck=False)
    def float_rows(rows, r0, r1, literal, bounds, out):  # pragma: no cover - compiled
        pos = 0
        digits = np.empty(9, np.int64)
        for r in range(r0, r1):
            start = pos
            pos = _put_text(literal, bounds, 0, out, pos)
            for c in range(3):
                pos = _put_g9(rows[r, c], out, pos, pow10, digits)
                if pos < 0:
                    return start, r
                pos = _put_text(literal, bounds, c + 1, out, pos)
        return pos, r1

    @nb.njit(cache=True, nogil=True, boundscheck=False)
    def int_rows(rows, r0, r1, literal, bounds, out):  # pragma: no cover - compiled
        pos = 0
        for r in range(r0, r1):
            pos = _put_text(literal, bounds, 0, out, pos)
            for c in range(3):
                pos = _put_int(rows[r, c], out, pos)
                pos = _put_text(literal, bounds, c + 1, out, pos)
        return pos, r1

    _TEXT_KERNELS = (float_rows, int_rows)
    return _TEXT_KERNELS


def _write_obj(vertices, faces, fh) -> None:
    _write_obj_blocks([vertices], [faces], fh)


def _write_obj_blocks(vertex_blocks, face_blocks, fh) -> None:
    """OBJ from blocks of vertex rows and of face rows (0-based), in order: the bytes do not depend on the blocks."""
    fh.write(b"# written by implicit_scaffold; units: mm\n")
    for block in vertex_blocks:
        for text in _formatted("v %.9g %.9g %.9g\n", block):
            fh.write(text)
    for block in face_blocks:
        for text in _formatted("f %d %d %d\n", block + 1):
            fh.write(text)


_CONTENT_TYPES = (
    '<?xml version="1.0" encoding="UTF-8"?>\n'
    '<Types xmlns="http://schemas.openxmlformats.org/package/2006/content-types">'
    '<Default Extension="rels" ContentType="application/vnd.openxmlformats-package.relationships+xml"/>'
    '<Default Extension="model" ContentType="application/vnd.ms-package.3dmanufacturing-3dmodel+xml"/>'
    "</Types>\n").encode("utf-8")
_RELS = (
    '<?xml version="1.0" encoding="UTF-8"?>\n'
    '<Relationships xmlns="http://schemas.openxmlformats.org/package/2006/relationships">'
    '<Relationship Target="/3D/3dmodel.model" Id="rel0" '
    'Type="http://schemas.microsoft.com/3dmanufacturing/2013/01/3dmodel"/>'
    "</Relationships>\n").encode("utf-8")


def _zip_entry(name: str) -> zipfile.ZipInfo:
    info = zipfile.ZipInfo(name, date_time=_ZIP_DATE)
    info.compress_type = zipfile.ZIP_DEFLATED
    info.create_system = 3  # the same bytes on every platform
    info.external_attr = 0o644 << 16
    return info


#: deflate level of a 3MF's model: zlib's 4 deflates the XML about three times as fast as
#: its default 6, for a file about 5 % larger (the default cube: 61.4 MB against 58.2 MB)
DEFLATE_LEVEL = 4


def _write_3mf(vertices, faces, fh) -> None:
    _write_3mf_blocks(len(vertices), len(faces), [vertices], [faces], fh)


def _write_3mf_blocks(nverts: int, nfaces: int, vertex_blocks, face_blocks, fh) -> None:
    """3MF from blocks of vertex rows and of face rows, in order: the model XML is deflated as it
    is formatted, a block at a time, so no more than a block is held; the bytes do not depend
    on the blocks (zlib is fed one stream, never flushed in between)."""
    head = ('<?xml version="1.0" encoding="UTF-8"?>\n'
            '<model unit="millimeter" xml:lang="en-US" '
            'xmlns="http://schemas.microsoft.com/3dmanufacturing/core/2015/02">\n'
            '<resources>\n<object id="1" type="model">\n<mesh>\n<vertices>\n').encode("utf-8")
    middle = b"</vertices>\n<triangles>\n"
    tail = (b"</triangles>\n</mesh>\n</object>\n</resources>\n"
            b'<build>\n<item objectid="1"/>\n</build>\n</model>\n')
    large = 64 * nverts + 48 * nfaces > 2 ** 31
    with zipfile.ZipFile(fh, mode="w") as z:
        z.writestr(_zip_entry("[Content_Types].xml"), _CONTENT_TYPES)
        z.writestr(_zip_entry("_rels/.rels"), _RELS)
        with z.open(_zip_entry("3D/3dmodel.model"), mode="w", force_zip64=large) as f:
            # zipfile's own deflate runs on one thread; the writer's compressor is the one
            # attribute it calls (compress, then flush), in every Python since 3.6
            if hasattr(f, "_compressor"):
                f._compressor = PiecewiseDeflate(DEFLATE_LEVEL)
            f.write(head)
            for block in vertex_blocks:
                for text in _formatted('<vertex x="%.9g" y="%.9g" z="%.9g"/>\n', block):
                    f.write(text)
            f.write(middle)
            for block in face_blocks:
                for text in _formatted('<triangle v1="%d" v2="%d" v3="%d"/>\n', block):
                    f.write(text)
            f.write(tail)


#: One record of a binary PLY face list as this package writes it: a count byte (3), three int32.
_PLY_FACE = np.dtype([("n", "u1"), ("v", "<i4", (3,))])


def _ply_layout(path) -> tuple[int, int, int]:
    """``(header bytes, vertices, faces)`` of a binary PLY written by this package (float64
    x y z, uchar/int face lists); a ScaffoldError for any other layout."""
    with open(path, "rb") as fh:
        head = fh.read(4096)
    end = head.find(b"end_header\n")
    if not head.startswith(b"ply\n") or end < 0:
        raise ScaffoldError(f"{path} is not a binary PLY written by implicit_scaffold")
    nverts = nfaces = None
    lines = head[:end].decode("ascii", "replace").splitlines()
    for line in lines:
        words = line.split()
        if words[:2] == ["element", "vertex"]:
            nverts = int(words[2])
        elif words[:2] == ["element", "face"]:
            nfaces = int(words[2])
    expected = ["format binary_little_endian 1.0", "property double x", "property double y", "property double z",
                "property list uchar int vertex_indices"]
    if nverts is None or nfaces is None or not all(e in lines for e in expected):
        raise ScaffoldError(f"{path} is not a binary PLY written by implicit_scaffold")
    return end + len(b"end_header\n"), nverts, nfaces


def write_mesh_from_ply(ply, path, *, block: int = FACE_CHUNK) -> Path:
    """Rewrite a binary PLY (as :func:`write_mesh` or :func:`~implicit_scaffold.mesh.stream.write_mesh_slabs`
    write it) as the mesh format `path` names, a block of rows at a time.

    The file is what :func:`write_mesh` writes for the PLY's vertices and faces, byte for
    byte, while only one block of ``block`` rows is held (the PLY is memory-mapped), so a
    mesh larger than the memory can be written as ``.3mf`` or ``.obj``.

    Parameters
    ----------
    ply : str or os.PathLike
    path : str or os.PathLike
        ``.stl``, ``.ply``, ``.obj`` or ``.3mf``; written atomically.
    block : int
        Rows formatted at a time.

    Returns
    -------
    pathlib.Path
    """
    final = Path(path)
    ext = check_format(final, MESH_FORMATS)
    start, nverts, nfaces = _ply_layout(ply)
    vertices = np.memmap(ply, dtype="<f8", mode="r", offset=start, shape=(nverts, 3)) if nverts else \
        np.zeros((0, 3))
    records = np.memmap(ply, dtype=_PLY_FACE, mode="r", offset=start + 24 * nverts, shape=(nfaces,)) if nfaces \
        else np.zeros(0, _PLY_FACE)

    def vertex_blocks():
        for r0 in range(0, nverts, block):
            yield np.asarray(vertices[r0:r0 + block], dtype=np.float64)

    def face_blocks():
        for r0 in range(0, nfaces, block):
            part = records[r0:r0 + block]
            if not np.all(part["n"] == 3):
                raise ScaffoldError(f"{ply} holds faces that are not triangles")
            yield np.asarray(part["v"], dtype=np.int64)

    with atomic_path(final) as tmp, open(tmp, "wb") as fh:
        if ext == ".3mf":
            _write_3mf_blocks(nverts, nfaces, vertex_blocks(), face_blocks(), fh)
        elif ext == ".obj":
            _write_obj_blocks(vertex_blocks(), face_blocks(), fh)
        else:  # STL and PLY index the vertices from anywhere: whole arrays (the memory map)
            v = np.asarray(vertices, dtype=np.float64)
            f = np.asarray(records["v"], dtype=np.int64)
            {".stl": _write_stl, ".ply": _write_ply}[ext](v, f, fh)
    vertices = records = None  # the memory maps closed (the block readers read them no more)
    return final
