"""implicit_scaffold: porous, patient-shaped Voronoi bone scaffolds as implicit fields.

The pipeline (see DESIGN.md): seeds -> Voronoi cells -> scaled skeleton (pores,
channels, rims, rails) -> lattice field (OpenCL) -> intersection with the patient
-> mesh -> metrics. ``generate(**options)`` runs it end to end; every stage is a
module of its own. Units are millimetres.
"""
__version__ = "0.1.0"

from .errors import ScaffoldError  # noqa: E402


def generate(**options):
    """Build a scaffold end to end; see :func:`implicit_scaffold.pipeline.generate`."""
    from .pipeline import generate as _generate

    return _generate(**options)


__all__ = ["generate", "ScaffoldError", "__version__"]
