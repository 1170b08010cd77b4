"""Read a patient's bone geometry from a file: a surface mesh or a CT/segmentation volume.

``load_patient`` is what ``implicit-scaffold generate --patient FILE`` calls. Meshes
(STL ascii or binary, OBJ, PLY, OFF, 3MF) become a
:class:`~implicit_scaffold.fields.patient_mesh.MeshPatient`; volumes (NIfTI, NRRD, MHA/MHD or
a folder holding a DICOM series) are read by :mod:`implicit_scaffold.fields.patient_volume`.
A clip box or two osteotomy planes then keep the part of the bone a surgeon keeps
(:class:`~implicit_scaffold.fields.patient.CutPatient`).
"""
from __future__ import annotations

import math
import struct
import time
import warnings
import zipfile
from pathlib import Path

import numpy as np

from ..errors import ScaffoldError, ScaffoldWarning

from .formats import MESH_READERS as MESH_EXTENSIONS, VOLUME_READERS as VOLUME_EXTENSIONS  # noqa: E402
#: mm per unit of a mesh file (``in``: the inch, exactly 25.4 mm)
UNITS = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "um": 1e-3, "in": 25.4}
#: a bone (or a defect in one) spans between these sizes in mm; outside them the file's
#: unit is probably not mm (a femur 0.45 long is in metres, a vertebra 90,000 wide in µm)
PLAUSIBLE_MM = (2.0, 2000.0)
#: what trimesh raises on content it cannot parse (it has no error type of its own)
_PARSE_ERRORS = (ValueError, LookupError, TypeError, AttributeError, OSError, EOFError, SyntaxError,
                 struct.error, zipfile.BadZipFile)


def _kind(path: Path) -> str | None:
    name = path.name.lower()
    if path.is_dir():
        return "volume"
    if name.endswith(VOLUME_EXTENSIONS):
        return "volume"
    if name.endswith(MESH_EXTENSIONS):
        return "mesh"
    return None


def load_patient(path, *, label=None, threshold=None, units=None, clip=None, cut_planes=None, spacing=None):
    """The patient in `path`, optionally cut to what a surgeon keeps.

    Parameters
    ----------
    path : str or Path
        A mesh (``.stl .obj .ply .off .3mf``), a volume (``.nii .nii.gz .nrrd .mha .mhd``)
        or a folder holding a DICOM series.
    label : int, optional
        Volume only: keep this segmentation label.
    threshold : float, optional
        Volume only: keep intensities at or above it (HU).
    units : {'mm', 'cm', 'm', 'um', 'in'}, optional
        Mesh only: the file's length unit (default: the unit the file declares, a 3MF's
        ``<model unit=...>``, else mm; a warning names a likelier one). Given, it overrides
        a declared unit, with a warning.
    spacing : float or (3,) floats, mm, optional
        Volume only: the voxel spacing of a file whose header states none (required then).
    clip : (6,) sequence of float, mm, optional
        ``(xmin, ymin, zmin, xmax, ymax, zmax)``: keep the bone inside this box.
    cut_planes : (12,) sequence of float, mm, optional
        Two osteotomy planes (point and normal each): keep the segment between them.

    Returns
    -------
    patient
        ``lo``, ``hi`` (3,) mm bounds, ``volume`` mm³, ``sdf_grid(grid)``, ``describe()``
        and ``load_seconds`` (time spent here).

    Raises
    ------
    ScaffoldError
        Unusable input, with one line saying what and how to fix it.
    """
    from ..fields.patient import CutPatient, cut_halfspaces

    t0 = time.perf_counter()
    path = Path(path)
    if not path.exists():
        raise ScaffoldError(f"--patient {path}: no such file or folder")
    kind = _kind(path)
    if kind is None:
        raise ScaffoldError(f"--patient {path.name} is neither a mesh ({' '.join(MESH_EXTENSIONS)}) nor a volume "
                            f"({' '.join(VOLUME_EXTENSIONS)} or a DICOM folder); convert it to one of those")
    if units is not None and units not in UNITS:
        raise ScaffoldError(f"--units takes one of {', '.join(UNITS)}, got {units!r}")
    halfspaces = cut_halfspaces(clip, cut_planes)
    if kind == "mesh":
        if label is not None or threshold is not None:
            raise ScaffoldError(f"--label and --threshold select bone in a volume; {path.name} is a surface mesh, "
                                "drop them")
        if spacing is not None:
            raise ScaffoldError(f"--spacing gives a volume's voxel size; {path.name} is a surface mesh, drop it "
                                "(--units sets a mesh's length unit)")
        patient = load_mesh(path, units=units)
    else:
        if units is not None and units != "mm":
            raise ScaffoldError(f"--units applies to a mesh; the volume {path.name} carries its own spacing, "
                                "drop --units")
        from ..fields.patient_volume import load_volume

        patient = load_volume(path, label=label, threshold=threshold, spacing=spacing)
    if len(halfspaces):
        what = " and ".join(f"{flag} {_numbers(v)}" for flag, v in (("--clip", clip), ("--cut-planes", cut_planes))
                            if v is not None)
        patient = CutPatient(patient, halfspaces, what=what)
    _set(patient, "load_seconds", time.perf_counter() - t0)
    # how to load it again (analyze --region reads it from the run's report)
    _set(patient, "load_options", {"file": str(path.resolve()), "label": label, "threshold": threshold,
                                   "units": units, "spacing": None if spacing is None else [float(v) for v in np.broadcast_to(spacing, (3,))], "clip": None if clip is None else [float(v) for v in clip],
                                   "cut_planes": None if cut_planes is None else [float(v) for v in cut_planes]})
    return patient


def _numbers(values) -> str:
    return " ".join(f"{float(v):g}" for v in values)


def _set(obj, name, value):
    try:
        setattr(obj, name, value)
    except (AttributeError, TypeError):  # frozen dataclasses
        object.__setattr__(obj, name, value)


def _declared_unit(mesh, path: Path) -> tuple[str | None, float]:
    """The length unit a mesh file declares (trimesh's ``units``: a 3MF's ``<model unit=...>``) and
    its mm per unit; ``(None, 1.0)`` when the file declares none (STL, OBJ, PLY, OFF)."""
    import trimesh

    declared = getattr(mesh, "units", None)
    if not declared:
        return None, 1.0
    try:
        return str(declared), float(trimesh.units.unit_conversion(str(declared), "millimeters"))
    except (ValueError, KeyError):
        raise ScaffoldError(f"{path.name} declares the unit {declared!r}, which is not a length unit known to "
                            "trimesh; export it again in mm") from None


def load_mesh(path, *, units=None):
    """A :class:`~implicit_scaffold.fields.patient_mesh.MeshPatient` from a mesh file, in mm.

    Parameters
    ----------
    path : str or Path
    units : {'mm', 'cm', 'm', 'um', 'in'}, optional
        The file's unit. When not given, a unit the file declares (a 3MF's ``<model unit=...>``,
        as trimesh reads it) is converted to mm, with a warning saying so; with neither, a size
        that suggests metres or micrometres is warned about, naming the ``--units`` that fixes it.
    """
    import trimesh

    from ..fields.patient_mesh import MAX_ODD_SHARE, mesh_patient_from_trimesh

    path = Path(path)
    ext = path.suffix.lower()
    try:
        with warnings.catch_warnings():
            # trimesh warns on odd-but-readable files; what matters is checked below
            warnings.simplefilter("ignore")
            mesh = trimesh.load(str(path), file_type=ext.lstrip("."), force="mesh", process=False)
    except _PARSE_ERRORS as exc:
        raise ScaffoldError(f"cannot read {path.name} as a {ext.lstrip('.').upper()} mesh ({type(exc).__name__}: "
                            f"{str(exc).splitlines()[0] if str(exc) else 'no detail'}); "
                            "check the file or export it again") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ScaffoldError(f"{path.name} holds no triangles (empty, or not a valid {ext.lstrip('.').upper()} file); "
                            "export the bone surface again")
    v = np.asarray(mesh.vertices, np.float64)
    used = np.unique(np.asarray(mesh.faces))
    if used.max() >= len(v) or used.min() < 0:
        raise ScaffoldError(f"{path.name} has faces that refer to missing vertices; export the mesh again")
    if not np.all(np.isfinite(v[used])):
        bad = int(np.count_nonzero(~np.all(np.isfinite(v[used]), axis=1)))
        raise ScaffoldError(f"{path.name} has {bad} vertices with NaN or infinite coordinates; "
                            "repair or export the mesh again")
    size = float(np.max(v[used].max(axis=0) - v[used].min(axis=0)))
    if size == 0:
        raise ScaffoldError(f"{path.name} has all its vertices at one point; it encloses no bone")
    declared, declared_scale = _declared_unit(mesh, path)
    if units is not None:
        scale = UNITS[units]
        if declared is not None and not math.isclose(scale, declared_scale, rel_tol=1e-9):
            warnings.warn(f"{path.name} declares its unit as {declared} ({declared_scale:g} mm); --units {units} "
                          f"overrides it ({scale:g} mm per unit); drop --units to use the file's",
                          ScaffoldWarning, stacklevel=2)
    elif declared is not None and declared_scale != 1.0:
        scale = declared_scale
        # the file says so, but the user should hear that the numbers were scaled
        warnings.warn(f"{path.name} declares its unit as {declared}: read as {declared_scale:g} mm per unit "
                      f"({size * scale:.4g} mm across); pass --units mm (or another) to override",
                      ScaffoldWarning, stacklevel=2)
        if not PLAUSIBLE_MM[0] <= size * scale <= PLAUSIBLE_MM[1]:
            warnings.warn(f"{path.name} is {size * scale:.4g} mm across in its declared unit {declared}, which is "
                          "not a bone's size; if its coordinates are in another unit, pass it with --units",
                          ScaffoldWarning, stacklevel=2)
    else:
        scale = 1.0
    if units is None and declared_scale == 1.0 and not PLAUSIBLE_MM[0] <= size <= PLAUSIBLE_MM[1]:
        guess = "m" if size < PLAUSIBLE_MM[0] else "um"
        unit_name = {"m": "metres", "um": "micrometres"}[guess]
        warnings.warn(f"{path.name} is {size:.4g} units across, which suggests {unit_name}, not mm; "
                      f"pass --units {guess} (or --units mm to keep it as is)", ScaffoldWarning, stacklevel=2)
    patient = mesh_patient_from_trimesh(mesh, name=path.name, scale=scale)
    if len(patient.faces) == 0 or len(patient.solid_faces) == 0:
        raise ScaffoldError(f"{path.name} has only degenerate triangles; it encloses no bone")
    if not patient.closed:
        # not closed: the sign comes from a vote, which needs most lines to cross it an even number of times
        share = patient.odd_share()
        if share > MAX_ODD_SHARE:
            raise ScaffoldError(f"{path.name} is too open to tell inside from outside ({share:.0%} of the lines "
                                "through it cross it an odd number of times); close its holes "
                                "(e.g. MeshLab's Close Holes) and try again")
        if patient.volume <= 0:
            raise ScaffoldError(f"{path.name} encloses no volume; is it a closed bone surface?")
        warnings.warn(f"{path.name} is not a closed surface (holes, or triangles wound both ways): inside and outside "
                      f"come from a vote of the grid lines through it ({share:.1%} of them cross it an odd number of "
                      "times) and its volume is integrated along them, not exact; close its holes (e.g. MeshLab's "
                      "Close Holes) for the bone's exact shape", ScaffoldWarning, stacklevel=2)
    return patient
