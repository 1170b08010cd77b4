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
"""
from __future__ import annotations

import contextlib
import os
import shutil
from pathlib import Path

import numpy as np

from .errors import ScaffoldError
from .grid import Grid

#: extensions :func:`write_volume` writes (``.nii.gz`` is matched as a whole)
VOLUME_FORMATS = (".npy", ".vti", ".nii.gz", ".nii", ".nrrd", ".mha", ".tif", ".tiff", ".zarr")

_ITK_IO = {".nii.gz": "NiftiImageIO", ".nii": "NiftiImageIO", ".nrrd": "NrrdImageIO",
           ".mha": "MetaImageIO", ".tif": "TIFFImageIO", ".tiff": "TIFFImageIO"}


def volume_format(path) -> str | None:
    """The :data:`VOLUME_FORMATS` entry that `path` ends with (lower case), or None."""
    name = Path(path).name.lower()
    for ext in sorted(VOLUME_FORMATS, key=len, reverse=True):
        if name.endswith(ext):
            return ext
    return None


def write_volume(field: np.ndarray, grid: Grid, path, *, binary: bool = False) -> Path:
    """Write `field` (or its solid, ``field < 0``) in the format the extension names.

    Parameters
    ----------
    field : (nx, ny, nz) float ndarray, mm
        Signed distance on `grid`, negative in the solid.
    grid : Grid
    path : str or os.PathLike
        Ends in one of :data:`VOLUME_FORMATS`.
    binary : bool
        Write the solid as uint8 (1 solid, 0 void; 255 / 0 in TIFF) instead of the
        float32 distance. TIFF is always binary.

    Returns
    -------
    pathlib.Path

    Raises
    ------
    ScaffoldError
        An unknown extension, a field that does not match its grid, a folder that
        cannot be written, or ``.zarr`` without the ``zarr`` extra installed.
    """
    from .mesh import atomic_path, write_field

    final = Path(path)
    ext = volume_format(final)
    if ext is None:
        raise ScaffoldError(f"cannot write {final.name}: use one of {', '.join(VOLUME_FORMATS)}")
    if tuple(field.shape) != tuple(grid.shape):
        raise ScaffoldError(f"the field's shape {field.shape} does not match its grid {grid.shape}")
    if ext == ".npy":
        if binary:
            raise ScaffoldError("a .npy output holds the signed distance; use .nii.gz, .tif or .vti for the solid")
        return write_field(field, final)
    if ext in (".tif", ".tiff"):
        binary = True
    values = (np.asarray(field) < 0).astype(np.uint8) if binary else np.asarray(field, np.float32)
    if ext == ".zarr":
        return _write_zarr(values, grid, final, "solid" if binary else "sdf")
    with atomic_path(final) as tmp:
        if ext == ".vti":
            _write_vti(values, grid, tmp, "solid" if binary else "sdf")
        else:
            # ITK (the NIfTI library above all) reads the format from the whole name and
            # rewrites names with extra dots: write under a plain name with the full
            # extension, then move it onto the temporary file that atomic_path renames
            full = tmp.with_name(tmp.name.replace(".", "-").lstrip("-").join([".", ext]))
            try:
                _write_itk(values * np.uint8(255) if ext in (".tif", ".tiff") else values, grid, full, ext)
                os.replace(full, tmp)
            finally:
                with contextlib.suppress(FileNotFoundError):
                    os.remove(full)
    return final


def _write_vti(values: np.ndarray, grid: Grid, tmp: Path, name: str) -> None:
    import pyvista as pv

    image = pv.ImageData(dimensions=values.shape, spacing=(grid.spacing,) * 3, origin=grid.origin)
    # VTK orders points x fastest: Fortran order of an (nx, ny, nz) array
    image.point_data[name] = values.ravel(order="F")
    image.save(str(tmp), binary=True)


def _write_itk(values: np.ndarray, grid: Grid, tmp: Path, ext: str) -> None:
    import SimpleITK as sitk

    # ITK arrays are (z, y, x)
    image = sitk.GetImageFromArray(np.ascontiguousarray(values.transpose(2, 1, 0)))
    image.SetSpacing((grid.spacing,) * 3)
    image.SetOrigin(tuple(float(v) for v in grid.origin))
    sitk.WriteImage(image, str(tmp), useCompression=ext in (".nii.gz", ".nrrd", ".mha"), imageIO=_ITK_IO[ext])


def _write_zarr(values: np.ndarray, grid: Grid, final: Path, name: str) -> Path:
    try:
        import zarr
    except ImportError:
        raise ScaffoldError("writing .zarr needs the zarr extra: pip install -e \".[zarr]\"") from None
    import secrets

    from .mesh import check_writable

    check_writable(final)
    if final.exists():
        raise ScaffoldError(f"{final} already exists; give a new name with -o or remove it")
    tmp = final.parent / f".{final.name}.tmp-{secrets.token_hex(4)}"
    try:
        root = zarr.open_group(str(tmp), mode="w")
        arr = root.create_array(name, shape=values.shape, dtype=values.dtype,
                                chunks=tuple(min(128, n) for n in values.shape))
        arr[...] = values
        root.attrs.update({"origin_mm": list(grid.origin), "spacing_mm": grid.spacing, "units": "mm",
                           "axes": "x, y, z (voxel centres)"})
        tmp.rename(final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return final
