"""The paper's experiments on the 10 mm cube, reproduced (paper §3, Figs. 10, 11, 13, 14, 17, 19).

:func:`run_sweep` writes, for each experiment, a CSV of the measured values and a
PNG plot of them. Porosity is measured on the voxels of what
:func:`implicit_scaffold.generate` builds with ``porosity=None`` (the lattice as Sf
and Sv make it), both with sharp creases (blend 0, whose porosity has the closed
form ``P0``) and with the default blend (our stand-in for the paper's Catmull-Clark
smoothing). The cell metrics (pore size, interconnection, channel size, trabecular
thickness) need only the cells, so they are measured on the Voronoi cells of the
seeds that ``generate`` would draw for each target pore size.
"""
from __future__ import annotations

import csv
import io
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from .errors import ScaffoldError

#: the paper's specimen: a 10 mm cube, mm
BOX_LO = (0.0, 0.0, 0.0)
BOX_HI = (10.0, 10.0, 10.0)
#: the paper's Fig. 9 porosities (%) at 500 seeds, Sf = Sv = key
PAPER_FIG9_POROSITY = {0.25: 17.4, 0.5: 47.8, 0.75: 79.6}
#: the paper's seed counts at P = 80 % for the ends of the target pore sizes, mm -> seeds
PAPER_SEEDS = {5.0: 12, 0.5: 12223}
#: mean faces of a Poisson-Voronoi cell, 2 + 48 π² / 35
POISSON_VORONOI_FACES = 2.0 + 48.0 * math.pi ** 2 / 35.0
#: seeds within this many mean spacings of a wall are left out of the interior-cell statistics
INTERIOR_MARGIN_SPACINGS = 3.0
#: fewer interior cells than this give no interior mean (too noisy to read)
INTERIOR_MIN_CELLS = 100


@dataclass(frozen=True)
class SweepSettings:
    """How fine a sweep is.

    Attributes
    ----------
    voxel : float, mm
        Voxel size of every porosity run.
    fig10_scales : tuple of (float, float)
        The pairs (Sf, Sv) of Fig. 10.
    fig10_seeds : int
        Seeds of the Fig. 10 runs (the paper's 500).
    fig11_seeds : tuple of int
        Seed counts of Fig. 11 (Sf = Sv = 0.75).
    blends : tuple
        Blend widths of the porosity runs: 0 (sharp) and/or None (the default blend).
    targets : tuple of float, mm
        Target pore sizes of Figs. 13, 14, 17 and 19 (P = 80 %, Sf = Sv = 0.75).
    """

    voxel: float
    fig10_scales: tuple
    fig10_seeds: int
    fig11_seeds: tuple
    blends: tuple
    targets: tuple


FULL = SweepSettings(
    voxel=0.05,
    fig10_scales=tuple((sf, sv) for sf in (0.25, 0.5, 0.75) for sv in (0.1, 0.25, 0.4, 0.5, 0.6, 0.75, 0.9)),
    fig10_seeds=500,
    fig11_seeds=tuple(range(100, 1001, 50)),
    blends=(0.0, None),
    targets=(5.0, 4.5, 4.0, 3.5, 3.0, 2.5, 2.0, 1.5, 1.0, 0.75, 0.6, 0.5),
)
QUICK = SweepSettings(
    voxel=0.1,
    fig10_scales=((0.25, 0.25), (0.5, 0.5), (0.75, 0.75)),
    fig10_seeds=500,
    fig11_seeds=(100, 1000),
    blends=(0.0, None),
    targets=(5.0, 2.0, 1.0, 0.5),
)
#: the target porosity and scale factors of Figs. 13-19
TARGET_POROSITY = 0.8
TARGET_SCALE = 0.75


def _fmt(v) -> str:
    if v is None:
        return ""
    if isinstance(v, (bool, np.bool_)):
        return "1" if v else "0"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return f"{float(v):.6g}" if math.isfinite(v) else ""
    return str(v)


def _write_csv(path: Path, rows: list[dict]) -> None:
    from .io.files import atomic_path

    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    columns = list(rows[0])
    writer.writerow(columns)
    for row in rows:
        writer.writerow([_fmt(row[c]) for c in columns])
    with atomic_path(path) as tmp:
        Path(tmp).write_text(buf.getvalue(), encoding="utf-8")


def _write_png(path: Path, fig) -> None:
    from .io.files import atomic_path
    from .io.report import _png

    data = _png(fig)
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(data)


def _out_dir(out_dir) -> Path:
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ScaffoldError(f"cannot write the sweep to {out}: it is a file; give a folder with -o")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ScaffoldError(f"cannot create the folder {out}: {exc.strerror or exc}; choose another -o") from None
    return out


def _blend_name(blend) -> str:
    return "sharp" if blend == 0 else "blend"


def _porosity_run(sf: float, sv: float, seeds: int, blend, settings: SweepSettings, seed: int) -> dict:
    """Voxel porosity of the 10 mm cube's lattice as Sf and Sv make it (no target porosity)."""
    from . import generate

    r = generate(seeds=seeds, sf=sf, sv=sv, porosity=None, blend=blend, voxel=settings.voxel, seed=seed,
                 mesh=False, morphometry=False).report
    return {"porosity_voxel_pct": 100.0 * r["porosity_voxel"], "blend_mm": r["blend_mm"]}


def _cell_run(target: float, seed: int) -> dict:
    """The paper's cell metrics of the seeds ``generate`` draws for a target pore size at P = 80 %."""
    from .geometry.cells import voronoi_cells
    from .measure.metrics import cell_metrics, pore_sizes
    from .geometry.seeds import seed_count, uniform_seeds

    lo, hi = np.asarray(BOX_LO), np.asarray(BOX_HI)
    volume = float(np.prod(hi - lo))
    n = seed_count(volume, TARGET_POROSITY, target)
    # the same generator and draw as generate(pore_size=target, seed=seed)
    cells = voronoi_cells(uniform_seeds(lo, hi, n, np.random.default_rng(seed)), lo, hi)
    m = cell_metrics(cells, TARGET_SCALE, TARGET_SCALE)
    d = pore_sizes(cells, TARGET_SCALE)
    ps = m["pore_size_mm"]
    margin = INTERIOR_MARGIN_SPACINGS * (volume / n) ** (1 / 3)
    interior = cells.interior_cells(margin)
    faces_interior = cells.faces_per_cell(walls=True)[interior]
    enough = faces_interior.size >= INTERIOR_MIN_CELLS
    return {
        "target_mm": target,
        "seeds": n,
        "pore_mean_mm": ps["mean"],
        "pore_sd_mm": ps["sd"],
        "pore_min_mm": ps["min"],
        "pore_max_mm": ps["max"],
        "pore_share_below_target": float(np.mean(d < target)),
        "pore_share_150_600um": ps["share_150_600um"],
        "pore_volume_sum_mm3": m["pore_volume_mm3_sum"],
        "interconnection_faces_with_walls_mean": m["interconnection_faces_with_walls_mean"],
        "interconnection_faces_mean": m["interconnection_faces_mean"],
        "interior_cells": int(np.count_nonzero(interior)),
        "interconnection_interior_mean": float(faces_interior.mean()) if enough else None,
        "channel_area_mm2_mean": m["channel_area_mm2_mean"],
        "window_area_mm2_mean": m["window_area_mm2_mean"],
        "trabecular_thickness_mm_mean": m["trabecular_thickness_mm_mean"],
        "trabecular_thickness_mm_sd": m["trabecular_thickness_mm_sd"],
    }


# ---------------------------------------------------------------- plots


def _fig10_plot(rows: list[dict], settings: SweepSettings):
    from .io.report import _figure
    from .geometry.skeleton import closed_form_porosity

    fig, ax = _figure(6.4, 4.4)
    colours = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd"]
    sv_dense = np.linspace(0.0, 1.0, 101)

    for i, sf in enumerate(sorted({sf for sf, _ in settings.fig10_scales})):
        c = colours[i % len(colours)]
        ax.plot(sv_dense, [100 * closed_form_porosity(sf, s) for s in sv_dense], color=c, lw=1, ls=":")
        for blend, marker, ls in ((0.0, "o", "-"), (None, "s", "--")):
            pts = [r for r in rows if r["sf"] == sf and r["blend"] == _blend_name(blend)]
            if pts:
                ax.plot([r["sv"] for r in pts], [r["porosity_voxel_pct"] for r in pts], marker=marker, ls=ls,
                        color=c, ms=4, label=f"Sf = {sf:g}, {_blend_name(blend)}")
    ax.plot(list(PAPER_FIG9_POROSITY), list(PAPER_FIG9_POROSITY.values()), "k*", ms=10,
            label="paper, Sf = Sv (Fig. 9)")
    ax.set_xlabel("Sv")
    ax.set_ylabel("porosity (%)")
    ax.set_title(f"Fig. 10: porosity against Sf and Sv ({settings.fig10_seeds} seeds; dotted: P0)")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 100)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper left")
    return fig


def _fig11_plot(rows: list[dict]):
    from .io.report import _figure

    fig, ax = _figure(6.0, 4.0)
    for name, marker in (("sharp", "o"), ("blend", "s")):
        pts = [r for r in rows if r["blend"] == name]
        if pts:
            ax.plot([r["seeds"] for r in pts], [r["porosity_voxel_pct"] for r in pts], marker=marker, ms=4,
                    label=f"measured, {name}")
    ax.axhline(rows[0]["porosity_closed_form_pct"], color="k", ls=":", lw=1, label="closed form P0")
    ax.axhline(PAPER_FIG9_POROSITY[0.75], color="#c0392b", ls="--", lw=1, label="paper, 500 seeds (Fig. 9)")
    ax.set_xlabel("number of seeds")
    ax.set_ylabel("porosity (%)")
    ax.set_ylim(70, 95)
    ax.set_title("Fig. 11: porosity against seed count (Sf = Sv = 0.75)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return fig


def _fig13_plot(rows: list[dict]):
    from .io.report import _figure

    fig, ax = _figure(6.0, 4.0)
    dense = np.linspace(0.5, 5.0, 200)
    volume = float(np.prod(np.subtract(BOX_HI, BOX_LO)))
    ax.plot(dense, volume * TARGET_POROSITY / (np.pi * dense ** 3 / 6), color="#888", lw=1,
            label="n = V P / (π Dp³ / 6)")
    ax.plot([r["target_mm"] for r in rows], [r["seeds"] for r in rows], "o", label="seeds used")
    for d, n in PAPER_SEEDS.items():
        ax.plot([d], [n], "k*", ms=10)
        ax.annotate(f"paper: {n:,}", (d, n), textcoords="offset points", fontsize=8, va="center",
                    xytext=(-10, 6) if d > 1 else (10, -2), ha="right" if d > 1 else "left")
    ax.set_yscale("log")
    ax.set_xlabel("target pore size Dp (mm)")
    ax.set_ylabel("number of seeds")
    ax.set_title("Fig. 13: seeds against target pore size (P = 80 %)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    return fig


def _fig14_plot(rows: list[dict]):
    from .io.report import _figure

    fig, ax = _figure(6.0, 4.4)
    t = np.array([r["target_mm"] for r in rows])
    mean = np.array([r["pore_mean_mm"] for r in rows])
    sd = np.array([r["pore_sd_mm"] for r in rows])
    ax.axhspan(0.15, 0.6, color="#2ca02c", alpha=0.12, label="150-600 µm")
    ax.plot([0, 5.2], [0, 5.2], color="k", ls=":", lw=1, label="measured = target")
    ax.errorbar(t, mean, yerr=sd, fmt="o", ms=4, capsize=3, label="mean ± sd")
    ax.plot(t, [r["pore_max_mm"] for r in rows], "v", color="#c0392b", ms=5, label="max")
    ax.plot(t, [r["pore_min_mm"] for r in rows], "^", color="#7f8c8d", ms=5, label="min")
    ax.set_xlabel("target pore size Dp (mm)")
    ax.set_ylabel("pore size, polyhedron-sphere (mm)")
    ax.set_title("Fig. 14: measured pore size against target (Sf = Sv = 0.75)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    return fig


def _fig17_plot(rows: list[dict]):
    from .io.report import _figure

    fig, ax = _figure(6.4, 4.4)
    t = [r["target_mm"] for r in rows]
    ax.plot(t, [r["interconnection_faces_with_walls_mean"] for r in rows], "o-", color="#1f77b4",
            label="faces per cell (walls incl.)")
    ax.plot(t, [r["interconnection_faces_mean"] for r in rows], "s--", color="#9467bd",
            label="neighbours per cell")
    inner = [(r["target_mm"], r["interconnection_interior_mean"]) for r in rows
             if r["interconnection_interior_mean"] is not None]
    if inner:
        ax.plot(*zip(*inner), "d:", color="#2ca02c", label="faces, cells far from walls")
    ax.axhline(POISSON_VORONOI_FACES, color="k", ls=":", lw=1, label="Poisson-Voronoi 15.54")
    ax.set_xlabel("target pore size Dp (mm)")
    ax.set_ylabel("mean pore interconnection (faces)")
    ax.grid(alpha=0.3)
    ax2 = ax.twinx()
    ax2.plot(t, [r["channel_area_mm2_mean"] for r in rows], "^-", color="#c0392b", label="channel (face) area")
    ax2.plot(t, [r["window_area_mm2_mean"] for r in rows], "v--", color="#e67e22", label="window area Sf² A")
    ax2.set_yscale("log")
    ax2.set_ylabel("mean channel size (mm²)")
    lines = ax.get_legend_handles_labels()
    lines2 = ax2.get_legend_handles_labels()
    ax.legend(lines[0] + lines2[0], lines[1] + lines2[1], fontsize=7, loc="upper left",
              bbox_to_anchor=(1.18, 1.0))
    ax.set_title("Fig. 17: interconnection and channel size against target")
    return fig


def _fig19_plot(rows: list[dict]):
    from .io.report import _figure

    fig, ax = _figure(6.0, 4.0)
    t = [r["target_mm"] for r in rows]
    ax.errorbar(t, [r["trabecular_thickness_mm_mean"] for r in rows],
                yerr=[r["trabecular_thickness_mm_sd"] for r in rows], fmt="o-", ms=4, capsize=3,
                label="mean ± sd")
    ax.set_xlabel("target pore size Dp (mm)")
    ax.set_ylabel("trabecular thickness (mm)")
    ax.set_title("Fig. 19: trabecular thickness against target (Sf = Sv = 0.75)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return fig


# ---------------------------------------------------------------- the sweep


def run_sweep(out_dir, *, quick: bool = False, seed: int = 0,
              progress: Callable[[int, int], None] | None = None,
              settings: SweepSettings | None = None) -> dict:
    """Reproduce the paper's experiments on the 10 mm cube; write a CSV and a PNG for each.

    Parameters
    ----------
    out_dir : str or Path
        Folder for the files (created if missing). Files written, each atomically:
        ``fig10_porosity_scale.{csv,png}``, ``fig11_porosity_seeds``, ``fig13_seeds_target``,
        ``fig14_pore_size``, ``fig17_interconnection``, ``fig19_trabecular_thickness``.
    quick : bool
        A coarse version (0.1 mm voxels; Fig. 10 on the diagonal Sf = Sv only, Fig. 11 at
        100 and 1000 seeds, four target pore sizes; about 20 s on 2 cores) instead of the
        full one (0.05 mm voxels, 21 pairs (Sf, Sv), every seed count of Fig. 11, twelve
        target pore sizes; about 3 minutes on 2 cores).
    seed : int
        RNG seed of every run: the same seed gives the same bytes.
    progress : callable(done, total), optional
        Called after each run (porosity run or cell tessellation).
    settings : SweepSettings, optional
        Overrides `quick` (tests use a smaller sweep).

    Returns
    -------
    dict
        ``out_dir`` (str), ``quick`` (bool), ``seed`` (int), ``settings`` (dict),
        ``seconds`` (float, wall clock; never written to the files), ``files`` (list of str,
        every path written) and ``figures``: for each of ``fig10``, ``fig11``, ``fig13``,
        ``fig14``, ``fig17``, ``fig19`` a dict with ``csv`` and ``png`` (str paths) and ``rows``
        (list of dicts, the CSV's rows).
    """
    t_start = time.perf_counter()
    try:
        seed = int(seed)
    except (TypeError, ValueError):
        raise ScaffoldError(f"--seed must be a whole number, got {seed!r}") from None
    if seed < 0:
        raise ScaffoldError(f"--seed must be >= 0, got {seed}")
    s = settings if settings is not None else (QUICK if quick else FULL)
    out = _out_dir(out_dir)
    from .geometry.skeleton import closed_form_porosity

    blends = list(s.blends)
    total = (len(s.fig10_scales) + len(s.fig11_seeds)) * len(blends) + len(s.targets)
    done = 0

    def step():
        nonlocal done
        done += 1
        if progress is not None:
            progress(done, total)

    fig10 = []
    for sf, sv in s.fig10_scales:
        p0 = 100.0 * closed_form_porosity(sf, sv)
        paper = PAPER_FIG9_POROSITY.get(sf) if sf == sv else None
        for blend in blends:
            run = _porosity_run(sf, sv, s.fig10_seeds, blend, s, seed)
            fig10.append({"sf": sf, "sv": sv, "seeds": s.fig10_seeds, "blend": _blend_name(blend),
                          "blend_mm": run["blend_mm"], "voxel_mm": s.voxel,
                          "porosity_voxel_pct": run["porosity_voxel_pct"], "porosity_closed_form_pct": p0,
                          "paper_pct": paper})
            step()

    fig11 = []
    p0 = 100.0 * closed_form_porosity(TARGET_SCALE, TARGET_SCALE)
    for n in s.fig11_seeds:
        for blend in blends:
            run = _porosity_run(TARGET_SCALE, TARGET_SCALE, n, blend, s, seed)
            fig11.append({"seeds": n, "sf": TARGET_SCALE, "sv": TARGET_SCALE, "blend": _blend_name(blend),
                          "blend_mm": run["blend_mm"], "voxel_mm": s.voxel,
                          "porosity_voxel_pct": run["porosity_voxel_pct"], "porosity_closed_form_pct": p0})
            step()

    volume = float(np.prod(np.subtract(BOX_HI, BOX_LO)))
    cell_rows = []
    for target in s.targets:
        cell_rows.append(_cell_run(target, seed))
        step()
    fig13 = [{"target_mm": r["target_mm"], "seeds": r["seeds"],
              "seeds_exact": volume * TARGET_POROSITY / (math.pi * r["target_mm"] ** 3 / 6),
              "paper_seeds": PAPER_SEEDS.get(r["target_mm"])} for r in cell_rows]
    pore_keys = ("target_mm", "seeds", "pore_mean_mm", "pore_sd_mm", "pore_min_mm", "pore_max_mm",
                 "pore_share_below_target", "pore_share_150_600um", "pore_volume_sum_mm3")
    link_keys = ("target_mm", "seeds", "interconnection_faces_with_walls_mean", "interconnection_faces_mean",
                 "interior_cells", "interconnection_interior_mean", "channel_area_mm2_mean",
                 "window_area_mm2_mean")
    thick_keys = ("target_mm", "seeds", "trabecular_thickness_mm_mean", "trabecular_thickness_mm_sd")
    fig14 = [{k: r[k] for k in pore_keys} for r in cell_rows]
    fig17 = [{k: r[k] for k in link_keys} for r in cell_rows]
    fig19 = [{k: r[k] for k in thick_keys} for r in cell_rows]

    experiments = {
        "fig10": ("fig10_porosity_scale", fig10, lambda rows: _fig10_plot(rows, s)),
        "fig11": ("fig11_porosity_seeds", fig11, _fig11_plot),
        "fig13": ("fig13_seeds_target", fig13, _fig13_plot),
        "fig14": ("fig14_pore_size", fig14, _fig14_plot),
        "fig17": ("fig17_interconnection", fig17, _fig17_plot),
        "fig19": ("fig19_trabecular_thickness", fig19, _fig19_plot),
    }
    figures, files = {}, []
    for key, (stem, rows, plot) in experiments.items():
        if not rows:
            continue
        csv_path, png_path = out / f"{stem}.csv", out / f"{stem}.png"
        _write_csv(csv_path, rows)
        _write_png(png_path, plot(rows))
        files += [str(csv_path), str(png_path)]
        figures[key] = {"csv": str(csv_path), "png": str(png_path), "rows": rows}
    return {"out_dir": str(out), "quick": bool(quick), "seed": seed,
            "settings": {k: (list(v) if isinstance(v, tuple) else v) for k, v in s.__dict__.items()},
            "seconds": time.perf_counter() - t_start, "files": files, "figures": figures}
