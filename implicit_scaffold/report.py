"""The visual report: one self-contained HTML page (pictures embedded, no network).

It shows what was built: a rendered picture of the scaffold, a cut-away section,
histograms of pore size and strut thickness, and a table of targets against
measured values. It only reads a run's report dict, mesh and field.
"""
from __future__ import annotations

import base64
import html
import io
import os

import numpy as np

from .mesh import atomic_path


def _png(fig) -> bytes:
    buf = io.BytesIO()
    # no timestamp or software tag: the same figure gives the same bytes
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight", metadata={"Software": None})
    import matplotlib.pyplot as plt

    plt.close(fig)
    return buf.getvalue()


def _figure(width=5.0, height=3.4):
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt.subplots(figsize=(width, height))


def render_mesh(mesh, *, size=(900, 700), cut: bool = False) -> bytes:
    """A shaded picture of `mesh` (pyvista, off screen) as PNG bytes; `cut` clips away the front half."""
    os.environ.setdefault("PYVISTA_OFF_SCREEN", "true")
    import pyvista as pv

    faces = np.hstack([np.full((len(mesh.faces), 1), 3), mesh.faces]).astype(np.int64).ravel()
    surf = pv.PolyData(np.asarray(mesh.vertices, np.float64), faces)
    plotter = pv.Plotter(off_screen=True, window_size=list(size))
    plotter.set_background("white")
    if cut:
        centre = surf.center
        # the half nearest the iso camera goes, showing the inside face-on
        surf = surf.clip(normal=(1, 1, 1), origin=centre, invert=True)
    plotter.add_mesh(surf, color="#e6d8bd", smooth_shading=True, specular=0.25)
    plotter.camera_position = "iso"
    plotter.camera.zoom(1.15)
    img = plotter.screenshot(return_img=True)
    plotter.close()
    import matplotlib.image as mpimg

    buf = io.BytesIO()
    mpimg.imsave(buf, img, format="png")
    return buf.getvalue()


def section_image(field: np.ndarray, grid, *, axis: int = 2, index: int | None = None) -> bytes:
    """A section through the scaffold field: solid dark, void light, as PNG bytes."""
    index = field.shape[axis] // 2 if index is None else index
    sl = np.take(field, index, axis=axis)
    fig, ax = _figure(4.6, 4.2)
    axes = [a for a in range(3) if a != axis]
    lo = grid.lo
    hi = grid.hi
    ax.imshow((sl < 0).T, origin="lower", cmap="Greys", interpolation="nearest",
              extent=(lo[axes[0]], hi[axes[0]], lo[axes[1]], hi[axes[1]]))
    names = "xyz"
    coord = grid.origin[axis] + index * grid.spacing
    ax.set_title(f"section {names[axis]} = {coord:.2f} mm (solid dark)")
    ax.set_xlabel(f"{names[axes[0]]} (mm)")
    ax.set_ylabel(f"{names[axes[1]]} (mm)")
    return _png(fig)


def histogram(values, *, title: str, xlabel: str, marks: dict | None = None, bins=30) -> bytes:
    """A histogram as PNG bytes, with labelled vertical marks (e.g. the target)."""
    fig, ax = _figure()
    v = np.asarray(values, float)
    ax.hist(v[np.isfinite(v)], bins=bins, color="#8aa9c9", edgecolor="white")
    for label, x in (marks or {}).items():
        if x is not None:
            ax.axvline(x, color="#c0392b", lw=1.5, ls="--")
            ax.text(x, ax.get_ylim()[1] * 0.95, f" {label}", color="#c0392b", va="top", fontsize=8)
    ax.set_title(title)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("count")
    return _png(fig)


def histogram_from_counts(edges, counts, *, title: str, xlabel: str) -> bytes:
    """A histogram already counted (bin edges and counts), as PNG bytes."""
    fig, ax = _figure()
    edges = np.asarray(edges, float)
    ax.bar(edges[:-1], counts, width=np.diff(edges), align="edge", color="#b9a27a", edgecolor="white")
    ax.set_title(title)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("voxels")
    return _png(fig)


def _fmt(v) -> str:
    if v is None:
        return "—"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return f"{v:.4g}"
    return html.escape(str(v))


def targets_table(report: dict) -> list[tuple[str, str, str]]:
    """Rows (quantity, target, measured) for the page."""
    rows = [("porosity", _fmt(report.get("porosity_target")),
             f"{_fmt(report.get('porosity_voxel'))} (voxels), {_fmt(report.get('porosity_mesh'))} (mesh)")]
    ps = report.get("pore_size_mm") or {}
    rows.append(("pore size, polyhedron-sphere (mm)", _fmt(report.get("pore_size_target_mm")),
                 f"mean {_fmt(ps.get('mean'))}, sd {_fmt(ps.get('sd'))}, max {_fmt(ps.get('max'))}"))
    rows.append(("pores in 150-600 µm", "—", _fmt(ps.get("share_150_600um"))))
    rows.append(("interconnection (faces per cell)", "—", _fmt(report.get("interconnection_faces_mean"))))
    rows.append(("channel / window area (mm²)", "—",
                 f"{_fmt(report.get('channel_area_mm2_mean'))} / {_fmt(report.get('window_area_mm2_mean'))}"))
    rows.append(("trabecular thickness, paper (mm)", "—", _fmt(report.get("trabecular_thickness_mm_mean"))))
    for key, label in (("strut_thickness_mm", "strut thickness, max spheres (mm)"),
                       ("pore_diameter_mm", "pore diameter, max spheres (mm)")):
        st = report.get(key)
        if isinstance(st, dict):
            rows.append((label, "—", f"mean {_fmt(st.get('mean'))}, sd {_fmt(st.get('sd'))}, "
                                      f"max {_fmt(st.get('max'))}"))
    for key, label in (("connectivity_density_per_mm3", "connectivity density (mm⁻³)"),
                       ("interconnected_porosity", "interconnected share of the void"),
                       ("fragments", "solid fragments"), ("fragments_removed", "fragments removed"),
                       ("surface_area_mm2", "surface area (mm²)"), ("bs_bv_per_mm", "BS/BV (mm⁻¹)"),
                       ("triangles", "triangles"), ("bodies", "bodies"), ("watertight", "watertight")):
        if key in report:
            rows.append((label, "—", _fmt(report[key])))
    return rows


def write_html(path, report: dict, images: dict[str, bytes], *, title: str = "Scaffold report") -> None:
    """Write the page atomically; `images` maps captions to PNG bytes."""
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>",
             "<style>body{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}"
             "table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:4px 10px;text-align:left}"
             "figure{display:inline-block;margin:8px;vertical-align:top}figcaption{font-size:90%;color:#555}"
             "</style></head><body>", f"<h1>{html.escape(title)}</h1>"]
    params = ", ".join(f"{k} {report[k]}" for k in ("style", "seeds", "sf", "sv", "voxel_mm", "blend_mm",
                                                      "rng_seed") if k in report)
    parts.append(f"<p>{html.escape(params)}. implicit_scaffold {html.escape(str(report.get('version', '')))}; "
                 "every measured value is computed from what was built.</p>")
    parts.append("<h2>Targets and measurements</h2><table><tr><th>quantity</th><th>target</th>"
                 "<th>measured</th></tr>")
    for q, t, m in targets_table(report):
        parts.append(f"<tr><td>{html.escape(q)}</td><td>{t}</td><td>{m}</td></tr>")
    parts.append("</table><h2>Pictures</h2>")
    for caption, png in images.items():
        b64 = base64.b64encode(png).decode("ascii")
        parts.append(f"<figure><img src='data:image/png;base64,{b64}' style='max-width:520px'>"
                     f"<figcaption>{html.escape(caption)}</figcaption></figure>")
    parts.append("</body></html>\n")
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write("\n".join(parts))


def write_run_report(result, path) -> None:
    """The page for a :func:`~implicit_scaffold.generate` result: pictures, histograms, table."""
    from .metrics import pore_sizes

    r = result.report
    images: dict[str, bytes] = {}
    if result.mesh is not None:
        images["the scaffold"] = render_mesh(result.mesh)
        images["cut-away: the trabecular inside"] = render_mesh(result.mesh, cut=True)
    images["section through the middle (solid dark)"] = section_image(result.field, result.grid)
    images["pore size, polyhedron-sphere method"] = histogram(
        pore_sizes(result.cells, result.params.sv), title="pore size (polyhedron-sphere)", xlabel="diameter (mm)",
        marks={"target": r.get("pore_size_target_mm"), "150 µm": 0.15, "600 µm": 0.6})
    for key, label in (("strut_thickness_mm", "strut thickness (maximal spheres)"),
                       ("pore_diameter_mm", "pore diameter (maximal spheres)")):
        st = r.get(key)
        if isinstance(st, dict) and st.get("histogram"):
            hist = st["histogram"]
            images[label] = histogram_from_counts(hist["edges_mm"], hist["counts"], title=label,
                                                  xlabel="mm")
    write_html(path, r, images, title=f"Scaffold report: {r.get('patient', 'patient')}")
