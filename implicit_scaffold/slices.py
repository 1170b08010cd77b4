"""Printer slices: the layer images a DLP or SLA printer takes, straight from the field.

No mesh is needed: each layer is the scaffold's signed distance sampled (trilinearly)
at the centres of the printer's pixels, at the height of the layer's middle. A pixel's
grey level is the share of it that is solid, ``clip(0.5 - s / pixel, 0, 1)``, which is
exact for a straight edge crossing the pixel and gives anti-aliased edges; 255 is solid.

The stack is written layer by layer (one layer of the field is read at a time), into a
hidden temporary folder that is renamed onto the output folder at the end, so an
interrupted run leaves no half stack under the final name.
"""
from __future__ import annotations

import io
import os
import secrets
import shutil
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from .errors import ScaffoldError, positive_mm
from .grid import Grid

#: name of layer ``k`` in the stack folder
LAYER_NAME = "layer_{:05d}.png"
#: the stack's geometry, beside the layers
STACK_JSON = "stack.json"


@dataclass(frozen=True)
class SliceStack:
    """Geometry of a stack of layer images (units mm).

    Attributes
    ----------
    pixel_mm : float
        Pixel pitch in x and y.
    layer_mm : float
        Layer height.
    width, height : int
        Pixels per layer along x (columns) and y (rows). Row 0 is the largest y,
        so an image shows the layer as seen from above (+z), +x right, +y up.
    layers : int
    origin_mm : (3,) tuple of float
        Corner ``(x_min, y_min, z_min)`` of the stack: pixel column 0 starts at
        ``x_min``, the bottom row ends at ``y_min``, layer 0 starts at ``z_min``.
    files : str
        Pattern of the layer file names.
    solid_share : tuple of float
        Share of each layer's pixels that are solid (at least half: grey >= 128).
    grey_mean : tuple of float
        Mean grey level of each layer / 255.
    """

    pixel_mm: float
    layer_mm: float
    width: int
    height: int
    layers: int
    origin_mm: tuple
    files: str
    solid_share: tuple
    grey_mean: tuple

    @property
    def solid_volume_mm3(self) -> float:
        """Volume of the solid pixels of all layers, mm³."""
        return float(sum(self.solid_share)) * self.width * self.height * self.pixel_mm ** 2 * self.layer_mm

    def to_dict(self) -> dict:
        d = asdict(self)
        d["units"] = "mm"
        d["solid_volume_mm3"] = self.solid_volume_mm3
        d["rows"] = "row 0 is the largest y (image seen from +z)"
        d["grey"] = "255 solid, 0 void; edges anti-aliased by the share of the pixel that is solid"
        return d




def stack_geometry(grid: Grid, pixel: float, layer: float) -> tuple[np.ndarray, tuple[int, int, int]]:
    """Corner and size (width, height, layers) of the stack that covers `grid`'s voxels.

    Parameters
    ----------
    grid : Grid
    pixel, layer : float, mm

    Returns
    -------
    origin : (3,) float64 ndarray, mm
    shape : (width, height, layers) tuple of int
    """
    pixel = positive_mm("pixel", pixel, example="0.05")
    layer = positive_mm("layer", layer, example="0.05")
    size = grid.hi - grid.lo
    counts = np.maximum(np.ceil(size / np.array([pixel, pixel, layer]) - 1e-9), 1).astype(np.int64)
    return grid.lo.astype(np.float64), (int(counts[0]), int(counts[1]), int(counts[2]))


def layer_coverage(field: np.ndarray, grid: Grid, z: float, pixel: float, origin, width: int,
                   height: int) -> np.ndarray:
    """Solid share of each pixel of the layer at height `z`.

    Parameters
    ----------
    field : (nx, ny, nz) float ndarray, mm
        Signed distance on `grid`, negative in the solid.
    grid : Grid
    z : float, mm
        Height at which the layer is sampled (its middle).
    pixel : float, mm
    origin : (3,) array_like of float, mm
        Corner of the stack (see :class:`SliceStack`).
    width, height : int

    Returns
    -------
    (height, width) float32 ndarray
        In [0, 1]; row 0 is the largest y.
    """
    from scipy import ndimage

    # the two voxel planes around z: only they are read, so a layer costs one slab
    kz = (z - grid.origin[2]) / grid.spacing
    k0 = int(np.clip(np.floor(kz), 0, grid.shape[2] - 1))
    k1 = min(k0 + 1, grid.shape[2] - 1)
    w = float(np.clip(kz - k0, 0.0, 1.0)) if k1 > k0 else 0.0
    plane = (1.0 - w) * np.asarray(field[:, :, k0], np.float64) + w * np.asarray(field[:, :, k1], np.float64)
    xs = origin[0] + (np.arange(width) + 0.5) * pixel
    ys = origin[1] + (np.arange(height)[::-1] + 0.5) * pixel
    ix = (xs - grid.origin[0]) / grid.spacing
    iy = (ys - grid.origin[1]) / grid.spacing
    coords = np.stack(np.meshgrid(iy, ix, indexing="ij")[::-1])  # (2, height, width): x index, y index
    # beyond the grid the scaffold is absent: the grid's outer layer is outside already
    s = ndimage.map_coordinates(plane, coords.reshape(2, -1), order=1, mode="nearest").reshape(height, width)
    return np.clip(0.5 - s / pixel, 0.0, 1.0).astype(np.float32)


def _png_bytes(grey: np.ndarray) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    # Pillow writes no time or software chunk: the same layer gives the same bytes
    Image.fromarray(grey, mode="L").save(buf, format="PNG", optimize=False, compress_level=6)
    return buf.getvalue()


def _prepare_folder(out_dir: Path) -> Path:
    out_dir = Path(os.path.abspath(os.fspath(out_dir)))
    parent = out_dir.parent
    if not parent.is_dir():
        raise ScaffoldError(f"cannot write to {parent}: folder does not exist; pick an existing folder with -o")
    if out_dir.exists() and (not out_dir.is_dir() or any(out_dir.iterdir())):
        raise ScaffoldError(f"{out_dir} already exists and is not an empty folder; "
                            "give a new folder name with -o or remove it")
    try:
        tmp = parent / f".{out_dir.name}.tmp-{secrets.token_hex(4)}"
        tmp.mkdir()
    except OSError as exc:
        raise ScaffoldError(f"cannot write to {parent}: {exc.strerror or exc}; "
                            "pick a folder you can write to with -o") from None
    return tmp


def check_stack_output(out_dir, *, pixel: float | None = None, layer: float | None = None) -> None:
    """Raise a :class:`ScaffoldError` now, before a long build, if the stack could not be written.

    Parameters
    ----------
    out_dir : str or os.PathLike
    pixel, layer : float, mm, optional
    """
    for name, value in (("pixel", pixel), ("layer", layer)):
        if value is not None:
            positive_mm(name, value, example="0.05")
    _prepare_folder(Path(out_dir)).rmdir()


def write_slices(field: np.ndarray, grid: Grid, out_dir, *, pixel: float | None = None,
                 layer: float | None = None,
                 progress: Callable[[int, int], None] | None = None) -> SliceStack:
    """Write the scaffold's layers as 8-bit PNG images and their geometry as ``stack.json``.

    Parameters
    ----------
    field : (nx, ny, nz) float ndarray, mm
        The scaffold's signed distance on `grid`, negative in the solid.
    grid : Grid
    out_dir : str or os.PathLike
        A folder to create (or an empty one); it appears only when the stack is complete.
    pixel : float, mm, optional
        The printer's pixel pitch; the voxel size by default.
    layer : float, mm, optional
        The layer height; the voxel size by default.
    progress : callable(done, total), optional

    Returns
    -------
    SliceStack

    Raises
    ------
    ScaffoldError
        A non-positive pixel or layer, or an output folder that cannot be written.
    """
    from .mesh import write_json

    pixel = grid.spacing if pixel is None else positive_mm("pixel", pixel, example="0.05")
    layer = grid.spacing if layer is None else positive_mm("layer", layer, example="0.05")
    if field.shape != grid.shape:
        raise ScaffoldError(f"the field's shape {field.shape} does not match its grid {grid.shape}")
    origin, (width, height, layers) = stack_geometry(grid, pixel, layer)
    final = Path(out_dir)
    tmp = _prepare_folder(final)
    shares, greys = [], []
    try:
        for k in range(layers):
            z = origin[2] + (k + 0.5) * layer
            cover = layer_coverage(field, grid, z, pixel, origin, width, height)
            grey = np.rint(cover * 255).astype(np.uint8)
            shares.append(float(np.count_nonzero(grey >= 128) / grey.size))
            greys.append(float(grey.mean(dtype=np.float64) / 255))
            (tmp / LAYER_NAME.format(k)).write_bytes(_png_bytes(grey))
            if progress is not None:
                progress(k + 1, layers)
        stack = SliceStack(pixel_mm=float(pixel), layer_mm=float(layer), width=width, height=height,
                           layers=layers, origin_mm=tuple(float(v) for v in origin), files=LAYER_NAME,
                           solid_share=tuple(shares), grey_mean=tuple(greys))
        write_json(stack.to_dict(), tmp / STACK_JSON)
        if final.is_dir():
            final.rmdir()  # empty, checked above
        os.replace(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return stack
