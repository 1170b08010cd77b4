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
from .run.memory import avoid_cold_huge_pages as _avoid_cold_huge_pages  # noqa: E402

# before any large array: on a machine whose host takes free memory back, NumPy's huge pages are faulted in
# from the host, ten times the cost of small pages (run.memory.avoid_cold_huge_pages)
_avoid_cold_huge_pages()

#: public name -> the module that defines it; loaded on first use, so that importing the
#: package stays cheap (no OpenCL, no mesh libraries until a stage runs)
_PUBLIC = {
    # the run end to end, its specs and its result
    "generate": "pipeline", "Result": "pipeline",
    "LatticeSpec": "specs", "GridSpec": "specs", "Outputs": "specs", "MechanicsSpec": "specs",
    # stage 1: patients
    "Box": "fields.patient", "Cylinder": "fields.patient", "Sphere": "fields.patient",
    "load_patient": "io.patient_io",
    # stages 2-4: seeds, cells, skeleton
    "uniform_seeds": "geometry.seeds", "voronoi_cells": "geometry.cells", "Cells": "geometry.cells",
    "scaled_skeleton": "geometry.skeleton", "Skeleton": "geometry.skeleton",
    "closed_form_porosity": "geometry.skeleton",
    # stage 5: the lattice's field on a grid
    "Grid": "run.grid", "lattice_sdf": "fields.lattice", "blend_field": "fields.field",
    # stage 6: the cut, at the level that meets a porosity
    "solve_level": "fields.field", "scaffold_field": "fields.field",
    # the same stages as field nodes, evaluated plane range by plane range (slab by slab)
    "FieldNode": "fields.nodes", "PaperLattice": "fields.nodes", "Struts": "fields.nodes", "Blend": "fields.nodes",
    "Patient": "fields.nodes", "SDF": "fields.nodes", "Cut": "fields.nodes", "evaluate": "fields.nodes",
    # stage 7: the mesh
    "mesh_field": "mesh.marching", "mesh_summary": "mesh.marching", "write_mesh": "mesh.writers",
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
