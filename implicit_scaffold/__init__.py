"""implicit_scaffold: porous, patient-shaped Voronoi bone scaffolds as implicit fields.

The pipeline (see DESIGN.md): seeds -> Voronoi cells -> scaled skeleton (pores,
channels, rims, rails) -> lattice field (OpenCL) -> intersection with the patient
-> mesh -> metrics. ``generate(...)`` runs it end to end; every stage is a
module of its own. Units are millimetres.
"""
__version__ = "0.1.0"

from .errors import ScaffoldError  # noqa: E402


def __getattr__(name):
    # generate (its keyword signature and docstring are pipeline.generate's) loads the
    # pipeline's modules on first use, not when the package is imported
    if name == "generate":
        from .pipeline import generate

        return generate
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["generate", "ScaffoldError", "__version__"]
