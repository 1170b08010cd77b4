"""The one reader of images: a volume file, a folder holding a DICOM series, or a folder of
TIFF slices, as a SimpleITK image with its spacing and origin (mm).

The patient (:mod:`~implicit_scaffold.fields.patient_volume`), the CT of a graded run (:mod:`~implicit_scaffold.geometry.grade`) and the
scaffold analysed by ``analyze`` (:mod:`~implicit_scaffold.measure.morphometry`) all read through :func:`read_image`,
so each format is read, and each failure worded, one way.
"""
from __future__ import annotations

import math
import warnings
from pathlib import Path

from ..errors import ScaffoldError
from .formats import IMAGE_STACKS, VOLUME_READERS, suffix

#: what a folder may hold: a DICOM series (a CT) or TIFF slices (a binary scaffold)
FOLDER_KINDS = ("dicom", "tiff")


def _name(path: Path) -> str:
    return path.name or str(path)


def folder_kind(path) -> str:
    """What a folder holds, as :func:`read_image`'s `folder` names it: ``"tiff"`` when it holds .tif
    slices, else ``"dicom"`` (also the answer for a file, which needs none)."""
    path = Path(path)
    if path.is_dir() and any(suffix(f) in IMAGE_STACKS for f in path.iterdir()):
        return "tiff"
    return "dicom"


def read_image(path, *, folder: str = "dicom", what: str = "a volume"):
    """The image at `path`, as SimpleITK reads it; a :class:`ScaffoldError` in one line otherwise.

    Parameters
    ----------
    path : str or Path
        A volume file (:data:`~implicit_scaffold.io.formats.VOLUME_READERS`, or a TIFF stack file), or a folder.
    folder : {"dicom", "tiff"}
        What a folder holds: a DICOM series (the one with the most slices when there are
        several, with a warning), or TIFF slices in name order.
    what : str
        How the error messages name what was expected.
    """
    import SimpleITK as sitk

    path = Path(path)
    if folder not in FOLDER_KINDS:
        raise ValueError(f"folder must be one of {FOLDER_KINDS}, got {folder!r}")
    if not path.exists():
        raise ScaffoldError(f"volume {path} does not exist; check the path")
    # ITK prints its warnings (e.g. "No Series were found") on stderr: they become our errors
    shown = sitk.ProcessObject.GetGlobalWarningDisplay()
    sitk.ProcessObject.SetGlobalWarningDisplay(False)
    try:
        if path.is_dir() and folder == "tiff":
            files = sorted(str(f) for f in path.iterdir() if suffix(f) in IMAGE_STACKS)
            if not files:
                raise ScaffoldError(f"folder {path} holds no .tif slices; give a folder of TIFF slices or a "
                                    "volume file")
            return sitk.ReadImage(files)
        if path.is_dir():
            reader = sitk.ImageSeriesReader()
            series = reader.GetGDCMSeriesIDs(str(path))
            if not series:
                raise ScaffoldError(f"folder {path} holds no DICOM series; give a folder of .dcm slices "
                                    f"or a volume file ({', '.join(VOLUME_READERS)})")
            files = [reader.GetGDCMSeriesFileNames(str(path), s) for s in series]
            best = max(range(len(series)), key=lambda i: len(files[i]))
            if len(series) > 1:
                warnings.warn(f"folder {path} holds {len(series)} DICOM series; using {series[best]} "
                              f"({len(files[best])} slices)", stacklevel=3)
            reader.SetFileNames(files[best])
            return reader.Execute()
        image = sitk.ReadImage(str(path))
        stated = imagej_spacing(path) if suffix(path) in IMAGE_STACKS else None
        if stated is not None:
            image.SetSpacing(stated)  # ITK reads 1 mm: its TIFF reader knows no ImageJ voxel size
        return image
    except RuntimeError as exc:
        text = str(exc)
        if "spacing" in text.lower():
            raise ScaffoldError(f"{_name(path)} has a zero or non-finite voxel spacing in its header; "
                                "spacings must be positive finite mm (fix the header)") from None
        # ITK's messages carry a source path and an object address before the reason
        reason = text.split("ERROR:")[-1]
        reason = " ".join(reason.split("): ", 1)[-1].split())[:160]
        raise ScaffoldError(f"cannot read {_name(path)} as {what}: {reason}") from None
    finally:
        sitk.ProcessObject.SetGlobalWarningDisplay(shown)


#: ImageJ's length units (its ``unit=`` and the TIFF's resolution), in mm
IMAGEJ_UNITS = {"mm": 1.0, "millimeter": 1.0, "millimetre": 1.0, "cm": 10.0, "micron": 1e-3, "um": 1e-3,
                "\u00b5m": 1e-3, "\\u00b5m": 1e-3, "nm": 1e-6}


def imagej_spacing(path) -> tuple | None:
    """The voxel size (x, y, z) in mm an ImageJ TIFF states: its resolution tags (pixels per unit) in x and
    y, ``spacing=`` in its description in z, ``unit=`` a length :data:`IMAGEJ_UNITS` knows (as ImageJ, BoneJ and
    this package's own ``.tif`` output write them); None for any other TIFF (its resolution is for printing)."""
    import tifffile

    try:
        with tifffile.TiffFile(str(path)) as tif:
            meta = tif.imagej_metadata or {}
            tags = tif.pages[0].tags
            res = [tags[name].value for name in ("XResolution", "YResolution")]
    except (OSError, KeyError, ValueError, IndexError, tifffile.TiffFileError):
        return None
    scale = IMAGEJ_UNITS.get(str(meta.get("unit", "")).strip().lower())
    if scale is None or "spacing" not in meta:
        return None
    try:
        x, y = (float(den) / float(num) * scale for num, den in res)
        z = float(meta["spacing"]) * scale
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    out = (x, y, z)
    return out if all(math.isfinite(v) and v > 0 for v in out) else None


def header_states_spacing(path, *, folder: str = "dicom") -> bool:
    """Whether the volume at `path` states its voxel spacing (ITK reads 1 mm when it does not).

    NIfTI always carries one (``pixdim``); a NRRD states it by ``space directions`` or
    ``spacings``, a MetaImage by ``ElementSpacing`` or ``ElementSize``. A TIFF file states one when
    ImageJ's description gives its unit and z spacing (:func:`imagej_spacing`); other TIFF resolution
    tags are for printing, not for voxels, so such a TIFF (file or folder) states none; a DICOM
    series always does (its slices' pixel spacing and positions). `folder` says what a folder
    holds, as in :func:`read_image`.
    """
    path = Path(path)
    kind = suffix(path)
    if kind in (".nii", ".nii.gz"):
        return True
    if kind in IMAGE_STACKS:
        return not path.is_dir() and imagej_spacing(path) is not None
    if path.is_dir():
        return folder == "dicom"
    with open(path, "rb") as fh:
        head = fh.read(65536).decode("latin-1", "replace").lower()
    if kind in (".nrrd", ".nhdr"):
        head = head.split("\n\n")[0]
        return "space directions:" in head or "spacings:" in head
    return "elementspacing" in head or "elementsize" in head


def warn_spacing_override(path, image, spacing, *, folder: str = "dicom") -> None:
    """Warn (:class:`~implicit_scaffold.errors.ScaffoldWarning`) where ``--spacing`` (`spacing`) replaces another
    voxel spacing that the header of the volume at `path` (read as `image`) states: the option is for a file that
    states none, and a wrong one scales every length and modulus of the run without a word."""
    import warnings

    import numpy as np

    from ..errors import ScaffoldWarning

    if spacing is None or not header_states_spacing(path, folder=folder):
        return
    given = np.asarray(spacing_triple(spacing))
    stated = np.asarray(image.GetSpacing(), float)
    if not np.allclose(given, stated, rtol=1e-6, atol=0):
        def mm(v):
            return f"{v[0]:.4g}" if np.all(v == v[0]) else " ".join(f"{x:.4g}" for x in v)

        warnings.warn(f"--spacing {mm(given)} mm replaces the {mm(stated)} mm voxels that {Path(path).name} "
                      "states; leave --spacing out to use the file's own", ScaffoldWarning, stacklevel=3)


def spacing_triple(spacing) -> tuple[float, float, float]:
    """`spacing` (one or three mm) as three positive finite floats; a :class:`ScaffoldError` otherwise."""
    import numpy as np

    try:
        step = np.broadcast_to(np.asarray(spacing, float), (3,))
    except (TypeError, ValueError):
        step = np.full(3, np.nan)
    if not np.all(np.isfinite(step) & (step > 0)):
        raise ScaffoldError(f"--spacing takes one or three positive lengths in mm, got {spacing!r}")
    return tuple(float(v) for v in step)

