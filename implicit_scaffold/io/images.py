"""The one reader of images: a volume file, a folder holding a DICOM series, or a folder of
TIFF slices, as a SimpleITK image with its spacing and origin (mm).

The patient (:mod:`~implicit_scaffold.fields.patient_volume`), the CT of a graded run (:mod:`~implicit_scaffold.geometry.grade`) and the
scaffold analysed by ``analyze`` (:mod:`~implicit_scaffold.measure.morphometry`) all read through :func:`read_image`,
so each format is read, and each failure worded, one way.
"""
from __future__ import annotations

import gzip
import math
import warnings
import zlib
from pathlib import Path

from ..errors import ScaffoldError, ScaffoldWarning
from .formats import IMAGE_STACKS, VOLUME_READERS, suffix

#: what a folder may hold: a DICOM series (a CT) or TIFF slices (a binary scaffold)
FOLDER_KINDS = ("dicom", "tiff")
#: bytes decompressed per step when a compressed volume's stream is checked: its memory, whatever the volume's size
GZIP_CHUNK = 1 << 22
#: a DICOM series' slices may stray from one even step along their normal (and from that normal) by this
#: share of the step, or by :data:`SLICE_TOLERANCE_MM` where that is more: positions are written to
#: about 1e-4 mm, and 1 % of a 2 mm step is a fiftieth of a voxel
SLICE_TOLERANCE = 0.01
#: see :data:`SLICE_TOLERANCE`, mm
SLICE_TOLERANCE_MM = 0.01


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

    Where ITK would read a file wrong without a word, it is refused or warned about here: compressed data cut
    short or corrupt (:func:`check_compressed`), a tilted, duplicated or unevenly spaced DICOM series
    (:func:`check_series`), a NRRD's ``space units`` (:func:`nrrd_units`, to mm), a NIfTI's sform that
    disagrees with where ITK places it (:func:`warn_sform`).
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
                # a series without its UID has an empty ID: name it by its first file
                which = series[best] or f"the one of {Path(files[best][0]).name}"
                warnings.warn(f"folder {path} holds {len(series)} DICOM series; using {which} "
                              f"({len(files[best])} slices; the others have "
                              f"{', '.join(str(len(f)) for i, f in enumerate(files) if i != best)}): give a folder of "
                              "one series to choose another", ScaffoldWarning, stacklevel=3)
            reader.SetFileNames(files[best])
            reader.MetaDataDictionaryArrayUpdateOn()   # each slice's position, for check_series
            image = reader.Execute()
            return check_series(path, reader, files[best], image)
        check_compressed(path)
        image = sitk.ReadImage(str(path))
        if suffix(path) in (".nrrd", ".nhdr"):
            nrrd_units(path, image)
        if suffix(path) in (".nii", ".nii.gz"):
            warn_sform(path, image)
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


#: length units as image headers name them (ImageJ's ``unit=``, NRRD's ``space units``), in mm
LENGTH_UNITS = {"mm": 1.0, "millimeter": 1.0, "millimetre": 1.0, "millimeters": 1.0, "millimetres": 1.0,
                "cm": 10.0, "centimeter": 10.0, "centimetre": 10.0, "centimeters": 10.0, "centimetres": 10.0,
                "m": 1000.0, "meter": 1000.0, "metre": 1000.0, "meters": 1000.0, "metres": 1000.0,
                "micron": 1e-3, "microns": 1e-3, "um": 1e-3, "micrometer": 1e-3, "micrometre": 1e-3,
                "micrometers": 1e-3, "micrometres": 1e-3, "\u00b5m": 1e-3, "\\u00b5m": 1e-3, "nm": 1e-6}


def _header(path, sep: str) -> tuple[dict, int]:
    """The text header of the NRRD (`sep` ``":"``) or MetaImage (``"="``) file at `path`: its fields (keys lower
    case, values stripped) and the byte at which the data attached to it start (a NRRD's blank line, the line
    after a MetaImage's ``ElementDataFile``); an offset of -1 where the header does not end in its first 64 KiB."""
    with open(path, "rb") as fh:
        raw = fh.read(65536)
    fields, offset = {}, 0
    for line in raw.split(b"\n"):
        offset += len(line) + 1
        text = line.decode("latin-1").rstrip("\r")
        if sep == ":" and not text.strip():
            return fields, offset
        key, found, value = text.partition(sep)
        if found:
            fields.setdefault(key.strip().lower(), value.strip())
        if sep == "=" and key.strip().lower() == "elementdatafile":
            return fields, offset
    return fields, -1


def _stream_ends(path, offset: int, wbits: int) -> bool:
    """Whether the zlib (`wbits` 15) or gzip (31) stream from byte `offset` of `path` reaches its end marker, its
    check sum verified, decompressed :data:`GZIP_CHUNK` bytes at a time (its memory, whatever the volume's size);
    zlib.error where it is corrupt."""
    stream = zlib.decompressobj(wbits)
    with open(path, "rb") as fh:
        fh.seek(offset)
        while not stream.eof:
            data = stream.unconsumed_tail or fh.read(GZIP_CHUNK)
            if not data:
                return False
            stream.decompress(data, GZIP_CHUNK)
    return True


def check_compressed(path) -> None:
    """A one-line :class:`ScaffoldError` when the compressed data of the volume file at `path` are cut short or corrupt.

    ITK's NIfTI reader fills what a truncated ``.nii.gz`` (an interrupted download) lacks with zeros, without a
    word, so the bone loses its slices; its NRRD and MetaImage readers refuse such data, but in messages that
    name no cause ("No such file or directory") or lose it in teem's trace. Checked: a file that is a gzip
    stream (``.nii.gz``), a NRRD's gzip data (attached, or its ``data file``), a MetaImage's zlib data
    (``CompressedData = True``, attached or its ``ElementDataFile``).
    """
    path = Path(path)
    with open(path, "rb") as fh:
        gzipped = fh.read(2) == b"\x1f\x8b"
    where, offset, wbits = path, 0, 31
    if not gzipped and suffix(path) in (".nrrd", ".nhdr"):
        fields, offset = _header(path, ":")
        if fields.get("encoding", "").lower() not in ("gzip", "gz"):
            return
        data = fields.get("data file", fields.get("datafile"))
        if data is not None:
            where, offset = path.parent / data, 0
    elif not gzipped and suffix(path) in (".mha", ".mhd"):
        fields, offset = _header(path, "=")
        if fields.get("compresseddata", "").lower() != "true":
            return
        data = fields.get("elementdatafile", "LOCAL")
        if data.upper() != "LOCAL":
            where, offset = path.parent / data, 0
        wbits = 15
    elif not gzipped:
        return
    if offset < 0 or not where.is_file():
        return      # no data where this looks: ITK's reader says what is wrong
    which = f"{_name(path)}" + ("" if where == path else f" (its data file {where.name})")
    try:
        whole = _stream_ends(where, offset, wbits)
    except zlib.error as exc:
        raise ScaffoldError(f"{which} is corrupt: its compressed data fail their check ({exc}); download or copy "
                            "it again") from None
    if not whole:
        raise ScaffoldError(f"{which} is cut short: its compressed data stop before their end marker (an interrupted "
                            "download or copy); download or copy it again")


def check_series(path, reader, files, image):
    """`image`, a DICOM series as ITK read it, placed where its slices' tags put them: refused where ITK would
    misplace it, warned about where it stretches it, in one line each; a gantry-tilted series resampled.

    ITK places slice k of `image` at the first slice's position plus k times one step (the mean) along the
    slice normal (ImageOrientationPatient's row x column): a gantry-tilted (sheared) series, whose slices
    step along the table while their normal leans, is then misplaced by millimetres (each slice is shifted
    in its plane back to where its tags put it, :func:`_untilt`, with a warning), two slices at one
    position (a copied file) halve the step, and a missing or irregular slice stretches the slices around
    it. The slices' positions (ImagePositionPatient), as `reader` read them from `files` in ITK's order,
    say so, within :data:`SLICE_TOLERANCE` of the step or :data:`SLICE_TOLERANCE_MM`.
    """
    import numpy as np

    def tag(i, key):
        try:
            return [float(v) for v in reader.GetMetaData(i, key).split("\\")]
        except (RuntimeError, ValueError):
            return []

    name, files = _name(Path(path)), [Path(f).name for f in files]
    pos = [tag(i, "0020|0032") for i in range(len(files))]
    ori = [tag(i, "0020|0037") for i in range(len(files))]
    if len(files) < 2 or any(len(p) != 3 for p in pos) or any(len(o) != 6 for o in ori):
        return image  # no positions to check ITK's geometry against
    pos, ori = np.asarray(pos), np.asarray(ori)
    if np.abs(ori - ori[0]).max() > 1e-4:
        raise ScaffoldError(f"the slices of {name} differ in orientation (ImageOrientationPatient); give a folder "
                            "holding one series of parallel slices")
    normal = np.cross(ori[0, :3], ori[0, 3:])
    normal /= np.linalg.norm(normal)
    along = (pos - pos[0]) @ normal
    across = np.linalg.norm(pos - pos[0] - along[:, None] * normal, axis=1)
    # GDCM sorts a series by position, but leaves a copied slice's file after the others: sort to pair it
    order = np.argsort(along, kind="stable")
    step = np.diff(along[order])
    typical = float(np.median(step))
    tol = max(SLICE_TOLERANCE_MM, SLICE_TOLERANCE * typical)
    same = np.nonzero(step <= tol)[0]
    if same.size:
        a, b = order[same[0]], order[same[0] + 1]
        where = " ".join(f"{v:.6g}" for v in pos[a])
        raise ScaffoldError(f"{same.size} slice(s) of {name} lie at the position of another: {files[a]} and "
                            f"{files[b]} at ({where}) mm; remove the duplicate files")
    if np.abs(step - typical).max() > tol:
        k = int(np.argmax(np.abs(step - typical)))
        a, b = order[k], order[k + 1]
        placed = np.arange(len(files)) * image.GetSpacing()[2]
        off = float(np.abs(np.abs(along) - placed).max())
        warnings.warn(f"the slices of {name} are not evenly spaced: {files[a]} and {files[b]} are {step[k]:.4g} mm "
                      f"apart, the others {typical:.4g} mm (a missing or extra slice); read with one step of "
                      f"{image.GetSpacing()[2]:.4g} mm, slices lie up to {off:.3g} mm from their place; give the whole "
                      "series, or resample it onto even slices", ScaffoldWarning, stacklevel=4)
    if across.max() > tol:
        k = int(np.argmax(across))
        tilt = math.degrees(math.atan2(across[k], abs(along[k])))
        image = _untilt(image, pos, ori[0], along)
        warnings.warn(f"the slices of {name} are not stacked along their normal (a gantry-tilted or sheared series, "
                      f"{tilt:.3g} degrees): each slice is shifted in its plane to where its tags put it, up to "
                      f"{across.max():.3g} mm, onto an orthogonal grid (linear interpolation, as dcm2niix corrects a "
                      "tilt)", ScaffoldWarning, stacklevel=4)
    return image


def _untilt(image, pos, orientation, along):
    """A sheared DICOM series, as ITK stacked it (`image`: slice k at the first slice's position plus k steps
    along the normal), with each slice moved in its plane to where its ImagePositionPatient `pos` (mm, slice k's
    in row k: ITK's order, its files') puts it: bilinear in the slice, the image's lowest value where a slice has
    no data, the step along the normal the slices' mean (`along`, their positions along it). Rows along
    `orientation`'s first three cosines, columns along its last three."""
    import numpy as np
    import SimpleITK as sitk
    from scipy import ndimage

    row, col = np.asarray(orientation[:3], float), np.asarray(orientation[3:], float)
    spacing = image.GetSpacing()
    # (slice, column index j, row index i): ITK's copy, each slice replaced in it (it reads only its own)
    array = sitk.GetArrayFromImage(image)
    fill = float(array.min())
    for k in range(array.shape[0]):
        # slice k's offset in its plane from the normal through the first: where its pixel (i, j) lies, the
        # grid's pixel (i + di, j + dj) is
        off = pos[k] - pos[0]
        di, dj = off @ row / spacing[0], off @ col / spacing[1]
        moved = ndimage.shift(array[k].astype(np.float64), (dj, di), order=1, mode="constant", cval=fill)
        array[k] = np.rint(moved) if array.dtype.kind in "iu" else moved
    fixed = sitk.GetImageFromArray(array)
    fixed.SetOrigin(tuple(float(v) for v in pos[0]))
    fixed.SetDirection(image.GetDirection())
    step = float((along.max() - along.min()) / (len(along) - 1))
    fixed.SetSpacing((spacing[0], spacing[1], step))
    for key in image.GetMetaDataKeys():
        fixed.SetMetaData(key, image.GetMetaData(key))
    return fixed


def nrrd_units(path, image) -> None:
    """Scale `image`'s spacing and origin to mm from the ``space units`` the NRRD header at `path` states.

    ITK reads a NRRD's ``space directions`` and ``space origin`` as mm whatever its ``space units``
    (a micro-CT exporter's ``"microns"`` gave 51.3 mm voxels for 51.3 µm ones), as it does not for NIfTI,
    whose ``xyzt_units`` it honours. A unit :data:`LENGTH_UNITS` does not know, or several, are refused
    in one line; empty units (NRRD's "unknown") stay mm.
    """
    import re

    stated = _header(path, ":")[0].get("space units")
    units = [u.strip().lower() for u in re.findall(r'"([^"]*)"', stated)] if stated else []
    units = [u for u in units if u]
    if not units:
        return
    scales = {LENGTH_UNITS.get(u) for u in units}
    if None in scales or len(scales) > 1:
        raise ScaffoldError(f"{_name(Path(path))} states space units {stated}, not one length unit "
                            "known here (mm, um or microns, cm, m); rewrite its header in one of them")
    scale = scales.pop()
    image.SetSpacing(tuple(v * scale for v in image.GetSpacing()))
    image.SetOrigin(tuple(v * scale for v in image.GetOrigin()))


def warn_sform(path, image) -> None:
    """Warn (:class:`ScaffoldWarning`) where the NIfTI at `path` states an sform (code > 0) that puts its
    voxels more than a voxel from where ITK put them in `image`.

    ITK may place a NIfTI by its qform where nibabel, FSL and TotalSegmentator use the sform: when the two
    disagree, the scaffold sits where ITK puts the bone, not where those tools show it. The sform is read
    from the header's bytes (NIfTI-1: ``sform_code`` at byte 254, ``srow_x/y/z`` at 280), RAS, and
    compared at the image's eight corners with ITK's (LPS) geometry.
    """
    import itertools
    import struct

    import numpy as np

    opener = gzip.open if suffix(path) == ".nii.gz" else open
    with opener(path, "rb") as fh:
        head = fh.read(348)
    ends = [e for e in "<>" if len(head) == 348 and struct.unpack(e + "i", head[:4])[0] == 348]
    if not ends or image.GetDimension() != 3:
        return      # NIfTI-2, or not a volume (refused later)
    qcode, scode = struct.unpack(ends[0] + "2h", head[252:256])
    if scode <= 0:
        return
    srow = np.asarray(struct.unpack(ends[0] + "12f", head[280:328]), float).reshape(3, 4)
    corners = np.asarray(list(itertools.product(*[(0, n - 1) for n in image.GetSize()])), float)
    sform = corners @ srow[:, :3].T + srow[:, 3]
    itk = np.asarray([image.TransformContinuousIndexToPhysicalPoint(c) for c in corners.tolist()]) * [-1, -1, 1]
    off = float(np.linalg.norm(sform - itk, axis=1).max())
    if off > max(image.GetSpacing()):
        warnings.warn(f"{_name(Path(path))}'s sform (code {scode}) puts the volume up to {off:.3g} mm from where ITK "
                      f"reads it (its qform, code {qcode}); nibabel and FSL use the sform, so the scaffold may not "
                      "overlay the scan there: make the two agree (e.g. fslorient -copysform2qform)",
                      ScaffoldWarning, stacklevel=4)


def imagej_spacing(path) -> tuple | None:
    """The voxel size (x, y, z) in mm an ImageJ TIFF states: its resolution tags (pixels per unit) in x and
    y, ``spacing=`` in its description in z, ``unit=`` a length :data:`LENGTH_UNITS` knows (as ImageJ, BoneJ and
    this package's own ``.tif`` output write them); None for any other TIFF (its resolution is for printing)."""
    import tifffile

    try:
        with tifffile.TiffFile(str(path)) as tif:
            meta = tif.imagej_metadata or {}
            tags = tif.pages[0].tags
            res = [tags[name].value for name in ("XResolution", "YResolution")]
    except (OSError, KeyError, ValueError, IndexError, tifffile.TiffFileError):
        return None
    scale = LENGTH_UNITS.get(str(meta.get("unit", "")).strip().lower())
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

