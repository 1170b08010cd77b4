"""Volume exports: the scaffold's field, or its binary solid, for ParaView, 3D Slicer and ImageJ/BoneJ.

Every writer keeps the grid's geometry (voxel-centre origin and spacing, mm), writes
atomically (a hidden temporary file renamed into place) and gives the same bytes for
the same field.

| extension | what | for |
|---|---|---|
| ``.npy`` | float32 signed distance (origin and spacing in the JSON report) | NumPy |
| ``.vti`` | VTK XML image, point data ``sdf`` (float32) or ``solid`` (uint8 0/1) | ParaView, PyVista |
| ``.nii.gz``, ``.nii`` | NIfTI, float32 distance or uint8 solid | 3D Slicer, ITK-SNAP |
| ``.nrrd``, ``.mha`` | NRRD / MetaImage (compressed) | 3D Slicer, ITK |
| ``.tif``, ``.tiff`` | multi-page TIFF, one page per z, uint8 solid 255 / void 0 | ImageJ / BoneJ |
| ``.zarr`` | Zarr array ``sdf`` or ``solid`` with the geometry in its attributes | Dask, napari (extra ``zarr``) |

Every format is written as a stream, z block by z block (x fastest, as these formats
store a volume; Zarr x block by x block, a row of whole chunks at a time), from an array
or from a field on disk read plane range by plane range (a tiled run's
:class:`~implicit_scaffold.run.tiles.FieldFile`): the whole grid is one source among others,
and a field of any size is written in bounded memory. The headers
are the ones SimpleITK writes for the same image (taken from it on a 2x2x2 image of the
same geometry, its sizes set); the data follows raw (``.nii``, ``.vti`` appended raw),
gzip-compressed (``.nii.gz``, ``.nrrd``) or zlib-compressed (``.mha``), and TIFF pages
go one z at a time.
"""
from __future__ import annotations

import contextlib
import itertools
import os
import shutil
import struct
from pathlib import Path

import numpy as np

from ..errors import ScaffoldError
from .files import PiecewiseDeflate
from ..run.grid import Grid

#: extensions :func:`write_volume` writes (``.nii.gz`` is matched as a whole)
from .formats import FIELD_WRITERS as VOLUME_FORMATS, match  # noqa: E402

_ITK_IO = {".nii.gz": "NiftiImageIO", ".nii": "NiftiImageIO", ".nrrd": "NrrdImageIO",
           ".mha": "MetaImageIO", ".tif": "TIFFImageIO", ".tiff": "TIFFImageIO"}


def volume_format(path) -> str | None:
    """The :data:`VOLUME_FORMATS` entry that `path` ends with (lower case), or None."""
    return match(path, VOLUME_FORMATS)


def write_volume(field, grid: Grid, path, *, binary: bool = False, max_bytes: int | None = None) -> Path:
    """Write `field` (or its solid, ``field < 0``) in the format the extension names.

    Parameters
    ----------
    field : (nx, ny, nz) float ndarray, mm, or a field on disk (``.grid``, ``.read(x0, x1)``)
        Signed distance on `grid`, negative in the solid.
    grid : Grid
    path : str or os.PathLike
        Ends in one of :data:`VOLUME_FORMATS`.
    binary : bool
        Write the solid as uint8 (1 solid, 0 void; 255 / 0 in TIFF) instead of the
        float32 distance. TIFF is always binary.
    max_bytes : int, optional
        Memory the writer may hold (:func:`z_blocks`; Zarr: its chunks' x thickness).

    Returns
    -------
    pathlib.Path

    Raises
    ------
    ScaffoldError
        An unknown extension, a field that does not match its grid, a folder that
        cannot be written, or ``.zarr`` without the ``zarr`` extra installed.
    """
    from .files import atomic_path, write_field

    final = Path(path)
    ext = volume_format(final)
    if ext is None:
        raise ScaffoldError(f"cannot write {final.name}: use one of {', '.join(VOLUME_FORMATS)}")
    shape = tuple(field.grid.shape) if hasattr(field, "read") else tuple(field.shape)
    if shape != tuple(grid.shape):
        raise ScaffoldError(f"the field's shape {shape} does not match its grid {grid.shape}")
    if ext == ".npy":
        if binary:
            raise ScaffoldError("a .npy output holds the signed distance; use .nii.gz, .tif or .vti for the solid")
        return write_field(field, final)
    if ext in (".tif", ".tiff"):
        binary = True
    if ext == ".zarr":
        return _write_zarr(field, grid, final, "solid" if binary else "sdf", np.dtype(np.uint8 if binary else "<f4"),
                           max_bytes=max_bytes)
    dtype = np.dtype(np.uint8 if binary else "<f4")
    # TIFF pages hold 255 for the solid (ImageJ's binary), the other formats 1
    solid = 255 if ext in (".tif", ".tiff") else 1
    blocks = z_blocks(field, grid, dtype, solid=solid, max_bytes=max_bytes)
    with atomic_path(final) as tmp:
        if ext == ".vti":
            _stream_vti(blocks, grid, tmp, "solid" if binary else "sdf", dtype)
        elif ext in (".tif", ".tiff"):
            _stream_tiff(blocks, grid, tmp)
        else:
            _stream_itk(blocks, grid, tmp, ext, dtype)
    return final


#: bytes a volume writer holds at once by default (a z block and the planes it is cut from)
STREAM_BYTES = 256 * 2**20


def z_blocks(field, grid: Grid, dtype, *, solid: int = 1, max_bytes: int | None = None):
    """The volume in z blocks, each ``(dz, ny, nx)`` C order (x fastest), as the formats store it.

    Parameters
    ----------
    field : (nx, ny, nz) float ndarray, mm, or a field on disk (``.read(x0, x1)``)
    grid : Grid
    dtype : numpy dtype
        float32 for the distance; uint8 for the solid (``field < 0`` as `solid`, else 0).
    solid : int
        The value of a solid voxel in a uint8 volume.
    max_bytes : int, optional
        Memory the blocks and the planes read to make them may hold
        (:data:`STREAM_BYTES` by default). A field on disk is read once per block.

    Yields
    ------
    (dz, ny, nx) ndarray of `dtype`
    """
    nx, ny, nz = (int(n) for n in grid.shape)
    dtype = np.dtype(dtype)
    budget = int(max_bytes or STREAM_BYTES)
    # half for the block, half for the planes of x read to fill it
    dz = int(min(nz, max(1, budget // 2 // (dtype.itemsize * nx * ny))))
    step = int(min(nx, max(1, budget // 2 // (4 * ny * nz))))
    read = field.read if hasattr(field, "read") else None
    for z0 in range(0, nz, dz):
        z1 = min(z0 + dz, nz)
        block = np.empty((z1 - z0, ny, nx), dtype)
        for x0 in range(0, nx, step):
            x1 = min(x0 + step, nx)
            planes = read(x0, x1)[:, :, z0:z1] if read is not None else field[x0:x1, :, z0:z1]
            part = block[:, :, x0:x1]
            if dtype == np.uint8:
                np.copyto(part, (planes < 0).transpose(2, 1, 0))
                part *= np.uint8(solid)
            else:
                np.copyto(part, planes.transpose(2, 1, 0), casting="same_kind")
            del planes
        yield block


def _itk_header(grid: Grid, ext: str, dtype) -> bytes:
    """The header SimpleITK writes for an image of `grid`'s geometry and `dtype`, up to its data.

    Taken from SimpleITK itself on a 2x2x2 image of the same spacing and origin, its
    sizes then set to the grid's: the rest of these headers does not depend on the size
    or the values (checked in the tests against SimpleITK's whole files).
    NRRD: the text up to the blank line; MetaImage: the text up to ``ElementDataFile = LOCAL``
    with ``CompressedDataSize = {size}`` left to fill; NIfTI: the 352 bytes before the data.
    """
    import struct
    import tempfile

    import SimpleITK as sitk

    image = sitk.GetImageFromArray(np.zeros((2, 2, 2), dtype))
    image.SetSpacing((grid.spacing,) * 3)
    image.SetOrigin(tuple(float(v) for v in grid.origin))
    with tempfile.TemporaryDirectory() as folder:
        path = os.path.join(folder, "header" + ext)
        sitk.WriteImage(image, path, useCompression=ext != ".nii", imageIO=_ITK_IO[ext])
        with open(path, "rb") as fh:
            data = fh.read()
    nx, ny, nz = (int(n) for n in grid.shape)
    if ext == ".nii.gz":
        import gzip

        data, ext = gzip.decompress(data), ".nii"
    if ext == ".nii":
        if max(nx, ny, nz) > 32767:
            raise ScaffoldError(f"NIfTI-1 holds at most 32767 voxels along an axis, the grid has "
                                f"{nx}x{ny}x{nz}; write .nrrd or .mha")
        header = bytearray(data[:352])
        struct.pack_into("<3h", header, 42, nx, ny, nz)  # dim[1..3]
        return bytes(header)
    text = data.decode("latin-1")
    if ext == ".nrrd":
        head = text[:text.index("\n\n") + 2]
        return head.replace("sizes: 2 2 2\n", f"sizes: {nx} {ny} {nz}\n").encode("latin-1")
    head = text[:text.index("ElementDataFile = LOCAL\n") + len("ElementDataFile = LOCAL\n")]
    head = head.replace("DimSize = 2 2 2\n", f"DimSize = {nx} {ny} {nz}\n")
    size = head[head.index("CompressedDataSize = "):].split("\n", 1)[0]
    return head.replace(size + "\n", "CompressedDataSize = {size}\n").encode("latin-1")


#: zlib's level for the compressed volumes (SimpleITK's), deflated in pieces on every core
VOLUME_DEFLATE_LEVEL = 6
#: the 10 bytes zlib's gzip writer (SimpleITK's) starts a file with: no name, time 0, Unix
_GZIP_HEADER = b"\x1f\x8b\x08\x00\x00\x00\x00\x00\x00\x03"


def _stream_itk(blocks, grid: Grid, tmp: Path, ext: str, dtype) -> None:
    """NIfTI, NRRD or MetaImage: SimpleITK's header, then the blocks raw or compressed."""
    import zlib

    header = _itk_header(grid, ext, dtype)
    with open(tmp, "wb") as fh:
        if ext == ".nii":
            fh.write(header)
            for block in blocks:
                fh.write(memoryview(block.reshape(-1).view(np.uint8)))
        elif ext == ".mha":
            # the header gives the compressed size: the zlib stream goes to a side file first
            side = tmp.with_name(tmp.name + ".data")
            try:
                with open(side, "w+b") as data:
                    # a zlib stream: its two header bytes (level 6's), the deflate, Adler-32
                    data.write(b"\x78\x9c")
                    pack = PiecewiseDeflate(VOLUME_DEFLATE_LEVEL)
                    check = 1
                    for block in blocks:
                        chunk = memoryview(block.reshape(-1).view(np.uint8))
                        check = zlib.adler32(chunk, check)
                        data.write(pack.compress(chunk))
                    data.write(pack.flush())
                    data.write(struct.pack(">I", check))
                    size = data.tell()
                    fh.write(header.replace(b"{size}", str(size).encode()))
                    data.seek(0)
                    shutil.copyfileobj(data, fh, 1 << 22)
            finally:
                with contextlib.suppress(FileNotFoundError):
                    os.remove(side)
        else:
            # .nii.gz compresses the header with the data; .nrrd's header stays text
            pack = PiecewiseDeflate(VOLUME_DEFLATE_LEVEL)
            crc, length = 0, 0
            if ext == ".nrrd":
                fh.write(header)
            fh.write(_GZIP_HEADER)
            chunks = ([memoryview(header)] if ext == ".nii.gz" else [])
            for chunk in itertools.chain(chunks, (memoryview(b.reshape(-1).view(np.uint8)) for b in blocks)):
                crc = zlib.crc32(chunk, crc)
                length += chunk.nbytes
                fh.write(pack.compress(chunk))
            fh.write(pack.flush())
            fh.write(struct.pack("<II", crc, length & 0xFFFFFFFF))


def _stream_tiff(blocks, grid: Grid, tmp: Path) -> None:
    """A multi-page TIFF, one uint8 page per z (ImageJ's layout, with its spacing in mm)."""
    import tifffile

    nx, ny, nz = (int(n) for n in grid.shape)

    def pages():
        for block in blocks:
            yield from block

    tifffile.imwrite(tmp, pages(), shape=(nz, ny, nx), dtype=np.uint8, imagej=True,
                     resolution=(1 / grid.spacing, 1 / grid.spacing),
                     metadata={"spacing": grid.spacing, "unit": "mm", "axes": "ZYX"})


def _stream_vti(blocks, grid: Grid, tmp: Path, name: str, dtype) -> None:
    """A VTK XML image with its one point array appended raw (UInt64 byte count, then the data)."""
    nx, ny, nz = (int(n) for n in grid.shape)
    kind = "UInt8" if np.dtype(dtype) == np.uint8 else "Float32"
    extent = f"0 {nx - 1} 0 {ny - 1} 0 {nz - 1}"
    origin = " ".join(repr(float(v)) for v in grid.origin)
    h = repr(float(grid.spacing))
    head = (f'<?xml version="1.0"?>\n'
            f'<VTKFile type="ImageData" version="1.0" byte_order="LittleEndian" header_type="UInt64">\n'
            f'  <ImageData WholeExtent="{extent}" Origin="{origin}" Spacing="{h} {h} {h}" '
            f'Direction="1 0 0 0 1 0 0 0 1">\n'
            f'    <Piece Extent="{extent}">\n'
            f'      <PointData Scalars="{name}">\n'
            f'        <DataArray type="{kind}" Name="{name}" format="appended" offset="0"/>\n'
            f'      </PointData>\n'
            f'      <CellData>\n      </CellData>\n'
            f'    </Piece>\n'
            f'  </ImageData>\n'
            f'  <AppendedData encoding="raw">\n   _')
    with open(tmp, "wb") as fh:
        fh.write(head.encode("ascii"))
        fh.write(struct.pack("<Q", nx * ny * nz * np.dtype(dtype).itemsize))
        for block in blocks:
            fh.write(memoryview(block.reshape(-1).view(np.uint8)))
        fh.write(b"\n  </AppendedData>\n</VTKFile>\n")


#: a Zarr chunk's side at most (voxels)
ZARR_CHUNK = 128


def _write_zarr(field, grid: Grid, final: Path, name: str, dtype, *, max_bytes: int | None = None) -> Path:
    """Zarr, a row of chunks along x at a time: chunks of up to :data:`ZARR_CHUNK` voxels a
    side, thinner in x when a row of them would pass `max_bytes` (:data:`STREAM_BYTES`)."""
    try:
        import zarr
    except ImportError:
        raise ScaffoldError("writing .zarr needs the zarr extra: pip install -e \".[zarr]\"") from None
    import secrets

    from .files import check_writable

    check_writable(final)
    if final.exists():
        raise ScaffoldError(f"{final} already exists; give a new name with -o or remove it")
    tmp = final.parent / f".{final.name}.tmp-{secrets.token_hex(4)}"
    try:
        nx, ny, nz = (int(n) for n in grid.shape)
        # the row of chunks, the planes read for it and their solid mask
        per_plane = ny * nz * (4 + 2 * dtype.itemsize)
        cx = int(max(1, min(ZARR_CHUNK, nx, int(max_bytes or STREAM_BYTES) // per_plane)))
        root = zarr.open_group(str(tmp), mode="w")
        arr = root.create_array(name, shape=(nx, ny, nz), dtype=dtype,
                                chunks=(cx, min(ZARR_CHUNK, ny), min(ZARR_CHUNK, nz)))
        read = field.read if hasattr(field, "read") else (lambda a, b: field[a:b])
        for x0 in range(0, nx, cx):
            planes = read(x0, min(x0 + cx, nx))
            arr[x0:x0 + len(planes)] = (planes < 0).astype(dtype) if dtype == np.uint8 \
                else np.asarray(planes, dtype)
            del planes
        root.attrs.update({"origin_mm": list(grid.origin), "spacing_mm": grid.spacing, "units": "mm",
                           "axes": "x, y, z (voxel centres)"})
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    from .files import place

    place(tmp, final)
    return final
