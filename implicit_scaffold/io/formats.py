"""Every file format the tool reads and writes, by extension, in one place.

The writers and readers dispatch on these tuples; the CLI's help and the error messages
list them from here, so a format added here is added everywhere.
"""
from __future__ import annotations

from pathlib import Path

#: triangle meshes :func:`~implicit_scaffold.mesh.writers.write_mesh` writes
MESH_WRITERS = (".stl", ".ply", ".obj", ".3mf")
#: of those, the ones written straight from the slabs (:mod:`~implicit_scaffold.mesh.stream`); the others
#: are formatted from a streamed PLY
MESH_STREAMED = (".stl", ".ply")
#: the scaffold's field (float32 signed distance, mm) or its binary solid
#: (:func:`~implicit_scaffold.io.export.write_volume`; TIFF is always the solid)
FIELD_WRITERS = (".npy", ".vti", ".nii.gz", ".nii", ".nrrd", ".mha", ".tif", ".tiff", ".zarr")
#: triangle meshes read as a patient or a scaffold to analyse
MESH_READERS = (".stl", ".obj", ".ply", ".off", ".3mf")
#: volumes (CT, a segmentation, a binary scaffold) read with their spacing and origin;
#: a folder holding a DICOM series reads too
VOLUME_READERS = (".nii", ".nii.gz", ".nrrd", ".nhdr", ".mha", ".mhd")
#: binary image stacks (a scaffold to analyse; no CT: a stack has no calibrated geometry)
IMAGE_STACKS = (".tif", ".tiff")


def suffix(path) -> str:
    """`path`'s extension, lower case, ``.nii.gz`` as a whole ('' for none)."""
    name = Path(path).name.lower()
    if name.endswith(".nii.gz"):
        return ".nii.gz"
    return Path(name).suffix


def report_path(path) -> Path:
    """The JSON report beside an output: ``scaffold.stl`` -> ``scaffold.json``, ``f.nii.gz`` -> ``f.json``, a stack's
    folder ``layers`` -> ``layers.json``; where ``analyze``, ``check`` and ``mechanics`` look for a run's report."""
    path = Path(path)
    return path.with_name(path.name[: len(path.name) - len(suffix(path))] + ".json")


def match(path, formats) -> str | None:
    """The entry of `formats` that `path`'s name ends with (lower case), or None."""
    ext = suffix(path)
    return ext if ext in formats else None
