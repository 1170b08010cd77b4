"""implicit_scaffold: porous, patient-shaped Voronoi bone scaffolds as implicit fields.

The pipeline (see DESIGN.md): seeds -> Voronoi cells -> scaled skeleton (pores,
channels, rims, rails) -> lattice field (OpenCL) -> intersection with the patient
-> mesh -> metrics. Units are millimetres.

``generate(lattice=LatticeSpec(...), grid=GridSpec(...), outputs=Outputs(...), patient=...)``
runs it end to end. Every stage is also a public function over NumPy arrays, importable
from here, so that a script can compose its own scaffold::

    seeds = uniform_seeds(lo, hi, n, rng)           # stage 2, mm
    cells = voronoi_cells(seeds, lo, hi)            # stage 3
    skeleton = scaled_skeleton(cells, sf, sv)       # stage 4
    lattice = lattice_sdf(skeleton, grid, cutoff=1.0)  # stage 5, then blend_field
    s = scaffold_field(lattice, my_sdf, level=solve_level(lattice, my_sdf < 0, 0.7))  # stage 6
    mesh = mesh_field(s, grid)                      # stage 7
"""
__version__ = "0.1.0"

from .errors import ScaffoldError  # noqa: E402

#: public name -> the module that defines it; loaded on first use, so that importing the
#: package stays cheap (no OpenCL, no mesh libraries until a stage runs)
_PUBLIC = {
    # the run end to end, its specs and its result
    "generate": "pipeline", "Result": "pipeline",
    "LatticeSpec": "specs", "GridSpec": "specs", "Outputs": "specs", "MechanicsSpec": "specs",
    # stage 1: patients
    "Box": "patient", "Cylinder": "patient", "Sphere": "patient", "load_patient": "patient_io",
    # stages 2-4: seeds, cells, skeleton
    "uniform_seeds": "seeds", "voronoi_cells": "cells", "Cells": "cells",
    "scaled_skeleton": "skeleton", "Skeleton": "skeleton", "closed_form_porosity": "skeleton",
    # stage 5: the lattice's field on a grid
    "Grid": "grid", "lattice_sdf": "lattice", "blend_field": "field",
    # stage 6: the cut, at the level that meets a porosity
    "solve_level": "field", "scaffold_field": "field",
    # the same stages as field nodes, evaluated plane range by plane range (slab by slab)
    "FieldNode": "nodes", "PaperLattice": "nodes", "Struts": "nodes", "Blend": "nodes", "Patient": "nodes",
    "SDF": "nodes", "Cut": "nodes", "evaluate": "nodes",
    # stage 7: the mesh
    "mesh_field": "mesh", "mesh_summary": "mesh", "write_mesh": "mesh_writers",
}


def __getattr__(name):
    module = _PUBLIC.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__():
    return sorted(set(globals()) | set(_PUBLIC))


__all__ = ["ScaffoldError", "__version__", *_PUBLIC]
