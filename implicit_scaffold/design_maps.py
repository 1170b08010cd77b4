"""The design maps (issue 16): minimum strut and apparent modulus against style, Sf, Sv and porosity.

Measured once on forward builds by ``benchmarks/design_maps.py`` and shipped as
``design_maps.json`` beside this module; :func:`~implicit_scaffold.design.design` reads them for its first guess
(which style, which Sv), so fewer forward builds are spent finding the bracket. The search then
corrects on the builds it measures itself, so the maps need only be close.

Both measures are scale-free and kept so: the minimum strut as a share of the pore size (a
geometrically similar scaffold has the same share), the modulus as a share of the solid's
(linear elasticity: the apparent modulus is proportional to the solid's Young's modulus at a
given Poisson's ratio, here Ti-6Al-4V's 0.342). Each entry is one build of one random seed.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: the file shipped beside this module
MAPS_FILE = Path(__file__).with_name("design_maps.json")
#: the grid of the maps: (style, Sf) pairs, Sv and porosity values. The struts style does not
#: read Sf (capsules on the Voronoi edges), so it is mapped at one Sf
STYLES = (("paper", 0.5), ("paper", 0.75), ("struts", 0.75))
SV_VALUES = (0.3, 0.4, 0.5, 0.6, 0.75, 0.9)
PAPER_SV_VALUES = (0.5, 0.75, 0.9)
POROSITY_VALUES = (0.5, 0.6, 0.7, 0.8, 0.9)
#: the builds' pore size (mm), solid and random seed
PORE_SIZE = 0.5
MATERIAL = "ti64"
SEED = 0
#: each build's cube holds this many cells (of its own Sv) a side, at a sixteenth of the pore
#: size a voxel, at most :data:`MAX_VOXELS_SIDE` voxels a side
CELLS = 4
MAX_VOXELS_SIDE = 96
#: significant digits kept in the file (the entries' seed-to-seed spread is far larger)
DIGITS = 5


def grid_points() -> list[tuple[str, float, float, float]]:
    """Every ``(style, sf, sv, porosity)`` of the maps, in the file's order."""
    out = []
    for style, sf in STYLES:
        for sv in (SV_VALUES if style == "struts" else PAPER_SV_VALUES):
            for p in POROSITY_VALUES:
                out.append((style, sf, sv, p))
    return out


def cube(sv: float) -> dict:
    """The cube an entry is built on (``size``, ``voxel``, ``margin``, mm), as :func:`~implicit_scaffold.design.forward` takes it."""
    size = CELLS * PORE_SIZE / sv
    voxel = max(PORE_SIZE / 16.0, size / MAX_VOXELS_SIDE)
    return {"size": size, "voxel": voxel, "margin": 0.5 * PORE_SIZE}


def measure_entry(style: str, sf: float, sv: float, porosity: float) -> dict:
    """One entry of the maps, built and measured (:func:`~implicit_scaffold.design.forward`): the minimum strut over the
    pore size and the apparent modulus over the solid's, rounded to :data:`DIGITS` digits."""
    from .design import Targets, forward
    from .measure.mechanics import material

    m = forward({"style": style, "sf": sf, "sv": sv},
                Targets(porosity=porosity, pore_size=PORE_SIZE, material=MATERIAL), cube(sv), SEED, stiffness=True)
    return {"style": style, "sf": sf, "sv": sv, "porosity": porosity,
            "min_strut_rel": _round(m["min_strut"] / PORE_SIZE),
            "modulus_rel": _round(m["stiffness"] / material(MATERIAL).E_gpa)}


def _round(x: float) -> float:
    return float(f"{x:.{DIGITS}g}")


def header() -> dict:
    """What the file says about how it was made."""
    return {"made_by": "benchmarks/design_maps.py", "pore_size_mm": PORE_SIZE, "material": MATERIAL, "seed": SEED,
            "cells_a_side": CELLS, "max_voxels_side": MAX_VOXELS_SIDE,
            "min_strut_rel": "1st percentile local thickness (design.min_strut_p1) / pore size",
            "modulus_rel": "apparent modulus (design.apparent_modulus: platens along z, every other voxel) / the "
                           "solid's Young's modulus"}


@dataclass(frozen=True)
class DesignMaps:
    """The maps read back, with interpolation in porosity and in log Sv, linear on the logs of the
    values (the modulus falls as a power of the solid fraction: a straight line between 0.7 and 0.8
    would overestimate it in between).

    Attributes
    ----------
    entries : list of dict
        As :func:`measure_entry` returns them.
    """

    entries: tuple

    def _table(self, style: str, sf: float, key: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        rows = [e for e in self.entries if e["style"] == style and math.isclose(e["sf"], sf)]
        if not rows:
            raise KeyError(f"no map for style {style!r}, Sf {sf:g}")
        svs = np.array(sorted({e["sv"] for e in rows}))
        ps = np.array(sorted({e["porosity"] for e in rows}))
        t = np.full((len(svs), len(ps)), np.nan)
        for e in rows:
            t[np.searchsorted(svs, e["sv"]), np.searchsorted(ps, e["porosity"])] = e[key]
        return svs, ps, t

    def value(self, key: str, style: str, sf: float, sv: float, porosity: float) -> float:
        """`key` (``min_strut_rel`` or ``modulus_rel``) at (`sv`, `porosity`), interpolated (clamped at the edges)."""
        svs, ps, t = self._table(style, sf, key)
        at_p = self._at_porosity(ps, t, porosity)
        return float(np.exp(np.interp(math.log(sv), np.log(svs), at_p)))

    @staticmethod
    def _at_porosity(ps: np.ndarray, t: np.ndarray, porosity: float) -> np.ndarray:
        """The log of each Sv row of `t` at `porosity` (linear in porosity on the logs)."""
        logs = np.log(np.maximum(t, 1e-12))
        return np.array([np.interp(porosity, ps, row) for row in logs])

    def sv_for(self, key: str, style: str, sf: float, porosity: float, goal: float) -> float | None:
        """The Sv of the maps' grid range at which `key` is `goal` at `porosity`, interpolated on the logs;
        None when `goal` lies beyond what the mapped Sv values give."""
        svs, ps, t = self._table(style, sf, key)
        at_p = self._at_porosity(ps, t, porosity)
        order = np.argsort(at_p)
        g = math.log(goal)
        if not at_p[order[0]] <= g <= at_p[order[-1]]:
            return None
        return float(np.exp(np.interp(g, at_p[order], np.log(svs)[order])))


def load_maps(path=None) -> DesignMaps:
    """The maps in `path` (default: the shipped :data:`MAPS_FILE`)."""
    data = json.loads(Path(path or MAPS_FILE).read_text())
    return DesignMaps(tuple(data["entries"]))
