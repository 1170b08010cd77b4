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

from .files import atomic_path


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

    from vtkmodules.vtkCommonCore import vtkObject

    faces = np.hstack([np.full((len(mesh.faces), 1), 3), mesh.faces]).astype(np.int64).ravel()
    surf = pv.PolyData(np.asarray(mesh.vertices, np.float64), faces)
    # off screen, VTK still tries the X display first and prints its failure on the
    # user's terminal: a picture needs no display, so that message is noise
    shown = vtkObject.GetGlobalWarningDisplay()
    vtkObject.GlobalWarningDisplayOff()
    try:
        plotter = pv.Plotter(off_screen=True, window_size=list(size))
    finally:
        vtkObject.SetGlobalWarningDisplay(shown)
    plotter.set_background("white")
    if cut:
        centre = surf.center
        # the half nearest the iso camera goes, showing the inside face-on
        surf = surf.clip(normal=(1, 1, 1), origin=centre, invert=True)
    # sharp edges (flat-faced meshes from other tools) keep their crease instead of a smeared normal
    plotter.add_mesh(surf, color="#e6d8bd", smooth_shading=True, split_sharp_edges=True, specular=0.25)
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


def certificate_section(section: np.ndarray, grid, axis: int, index: int, printer: str) -> bytes:
    """A section map of the print certificate: each problem in its colour over solid and void."""
    from matplotlib.colors import ListedColormap

    from ..measure.printability import SECTION_LABELS

    colours = ["#f4f4f4", "#8a8a8a", "#d62728", "#1f77b4", "#e377c2", "#ff7f0e"]
    fig, ax = _figure(5.2, 4.4)
    axes = [a for a in range(3) if a != axis]
    lo, hi = grid.lo, grid.hi
    ax.imshow(section.T, origin="lower", cmap=ListedColormap(colours), vmin=0, vmax=len(colours) - 1,
              interpolation="nearest", extent=(lo[axes[0]], hi[axes[0]], lo[axes[1]], hi[axes[1]]))
    names = "xyz"
    present = sorted(set(np.unique(section).tolist()))
    from matplotlib.patches import Patch

    ax.legend(handles=[Patch(color=colours[k], label=SECTION_LABELS[k]) for k in present], fontsize=7,
              loc="upper right", framealpha=0.9)
    ax.set_title(f"{printer}: section {names[axis]} = {grid.origin[axis] + index * grid.spacing:.2f} mm")
    ax.set_xlabel(f"{names[axes[0]]} (mm)")
    ax.set_ylabel(f"{names[axes[1]]} (mm)")
    return _png(fig)


def certificate_rows(cert: dict) -> list[tuple[str, str, str]]:
    """The certificate's checks for the page: what was measured, the profile's limit, the verdict."""
    p, v = cert["printer"], cert["verdict"]

    def share(x):
        return "n/a" if x is None else f"{100 * x:.1f} %"

    return [
        ("thinnest solid (min, 1st percentile; share below the minimum)",
         f"{cert['thinnest_mm']['min']:.3f}, {cert['thinnest_mm']['p1']:.3f} mm; "
         f"{share(cert['below_min_strut_share'])}", f"≥ {p['min_strut_mm']:g} mm: {v['thinnest']}"),
        ("narrowest throat to 90 % of the pore volume", f"{cert['throat_mm']:.3f} mm",
         f"≥ {p['min_throat_mm']:g} mm: {v['throat']}"),
        ("void the drain reaches", share(cert["void_reached_by_drain_share"]),
         f"{p['drain_mm']:g} mm drain: {v['drain']}"),
        ("void 100 µm cells reach", share(cert["void_reached_by_100um_share"]), v["cell_infiltration"]),
        ("sealed voids", f"{cert['sealed_voids']['count']} ({cert['sealed_voids']['volume_mm3']:.4g} mm³)",
         v["sealed_voids"]),
        ("floating solid", f"{cert['floating_solid']['count']} ({cert['floating_solid']['volume_mm3']:.4g} mm³)",
         v["floating_solid"]),
        (f"overhangs flatter than {p['overhang_deg']:g}° along {cert['build_axis']} (best axis "
         f"{cert['best_build_axis']})", share(cert["overhang_share"]), v["overhang"]),
        (f"as built (+{p['deviation_mm']:g} mm): porosity, throat",
         f"{cert['as_built']['porosity']:.4f}, {cert['as_built']['throat_mm']:.3f} mm", v["as_built"]),
    ]


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


def histogram_from_counts(edges, counts, *, title: str, xlabel: str, marks: dict | None = None) -> bytes:
    """A histogram already counted (bin edges and counts), as PNG bytes, with labelled marks.

    The counts are shown as shares of all voxels (%), so that volumes of any size compare.
    """
    fig, ax = _figure()
    edges = np.asarray(edges, float)
    counts = np.asarray(counts, float)
    share = 100.0 * counts / max(counts.sum(), 1.0)
    ax.bar(edges[:-1], share, width=np.diff(edges), align="edge", color="#b9a27a", edgecolor="white")
    ax.set_ylim(0, max(share.max(), 1e-9) * 1.12)
    for label, x in (marks or {}).items():
        if x is not None:
            ax.axvline(x, color="#c0392b", lw=1.5, ls="--")
            ax.text(x, ax.get_ylim()[1] * 0.97, f" {label}", color="#c0392b", va="top", fontsize=8)
    ax.set_title(title)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("share of the voxels (%)")
    return _png(fig)


def grade_profile_plot(profile: dict, *, xlabel: str, title: str) -> bytes:
    """Porosity and mean pore size per bin beside their targets (a graded run), as PNG bytes.

    Parameters
    ----------
    profile : dict
        One of ``report["grade"]["profiles"]`` (:func:`~implicit_scaffold.geometry.grade.profiles`).
    xlabel, title : str
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    edges = np.asarray(profile["edges_mm"], float)
    mid = (edges[:-1] + edges[1:]) / 2

    def arr(key):
        return np.array([np.nan if v is None else v for v in profile[key]], float)

    fig, (top, bottom) = plt.subplots(2, 1, figsize=(5.4, 5.4), sharex=True)
    top.plot(mid, 100 * arr("porosity_target"), color="#c0392b", ls="--", label="target")
    top.plot(mid, 100 * arr("porosity"), "o-", color="#2c6ea3", ms=3, label="measured (voxels)")
    shown = 100 * np.concatenate([arr("porosity_target"), arr("porosity")])
    shown = shown[np.isfinite(shown)]
    if shown.size:
        # at least +-5 points: a profile met to a hundredth of a point must look flat, not noisy
        top.set_ylim(min(shown.min(), shown.mean() - 5) - 1, max(shown.max(), shown.mean() + 5) + 1)
    top.set_ylabel("porosity (%)")
    top.legend(fontsize=8)
    top.set_title(title)
    bottom.plot(mid, arr("pore_size_target_mm"), color="#c0392b", ls="--", label="target Dp")
    bottom.plot(mid, arr("pore_size_expected_mm"), color="#e67e22", ls=":",
                label="expected polyhedron-sphere")
    bottom.plot(mid, arr("pore_size_mm"), "o-", color="#2c6ea3", ms=3, label="measured polyhedron-sphere")
    bottom.set_ylabel("pore size (mm)")
    bottom.set_xlabel(xlabel)
    bottom.legend(fontsize=8)
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
    ps = report.get("pore_size_mm")
    if not isinstance(ps, dict):  # an analysed file has no cells: only the voxel measures
        return rows[:1] + [r for r in _measured_rows(report)]
    return rows + _cell_rows(report, ps) + _measured_rows(report)


def _cell_rows(report: dict, ps: dict) -> list[tuple[str, str, str]]:
    rows = []
    target = "graded: see the profiles" if report.get("grade") else _fmt(report.get("pore_size_target_mm"))
    rows.append(("pore size, polyhedron-sphere (mm)", target,
                 f"mean {_fmt(ps.get('mean'))}, sd {_fmt(ps.get('sd'))}, max {_fmt(ps.get('max'))}"))
    rows.append(("pores in 150-600 µm", "—", _fmt(ps.get("share_150_600um"))))
    rows.append(("interconnection (faces per cell)", "—", _fmt(report.get("interconnection_faces_mean"))))
    rows.append(("channel / window area (mm²)", "—",
                 f"{_fmt(report.get('channel_area_mm2_mean'))} / {_fmt(report.get('window_area_mm2_mean'))}"))
    rows.append(("trabecular thickness, paper (mm)", "—", _fmt(report.get("trabecular_thickness_mm_mean"))))
    return rows


def _measured_rows(report: dict) -> list[tuple[str, str, str]]:
    rows = []
    for key, label, target in (("strut_thickness_mm", "strut thickness, max spheres (mm)", None),
                               ("pore_diameter_mm", "pore diameter, max spheres (mm)",
                                report.get("pore_size_target_mm"))):
        st = report.get(key)
        if isinstance(st, dict):
            rows.append((label, _fmt(target), f"mean {_fmt(st.get('mean'))}, sd {_fmt(st.get('sd'))}, "
                                              f"max {_fmt(st.get('max'))}"))
    for key, label in (("connectivity_density_per_mm3", "connectivity density (mm⁻³)"),
                       ("euler_characteristic", "Euler characteristic"),
                       ("interconnected_porosity", "interconnected share of the void"),
                       ("fragments", "solid fragments left"), ("fragments_removed", "fragments removed"),
                       ("surface_area_mm2", "surface area (mm²)"), ("bs_bv_per_mm", "BS/BV (mm⁻¹)"),
                       ("triangles", "triangles"), ("bodies", "bodies"), ("watertight", "watertight")):
        if key in report:
            rows.append((label, "—", _fmt(report[key])))
    return rows


#: how the voxel measures are taken, under the table (a reviewer's first question)
_HOW = ("How measured: porosity from voxel counts within the patient (or the region analysed) and from "
        "the mesh volume. "
        "Strut thickness and pore diameter by maximal inscribed spheres (Hildebrand &amp; Rüegsegger, as "
        "BoneJ): at each voxel the diameter of the largest sphere inside the solid (or the void) that holds "
        "it; mean and sd are over voxels. Connectivity density (1 − χ) / V from the Euler characteristic χ "
        "of the 26-connected solid (whole object, no edge correction). Interconnected share: void joined to "
        "the outside of the patient (6-connected). Fragments: solid pieces not joined to the largest by a "
        "face. Surface area and BS/BV from the triangle mesh.")


def write_html(path, report: dict, images: dict[str, bytes], *, title: str = "Scaffold report",
               measures: bool = True) -> None:
    """Write the page atomically; `images` maps captions to PNG bytes. Without `measures` (a page of the
    mechanics alone) no table of porosity, pore size and struts: none was measured."""
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>",
             "<style>body{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}"
             "table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:4px 10px;text-align:left}"
             "figure{display:inline-block;margin:8px;vertical-align:top}figcaption{font-size:90%;color:#555}"
             "</style></head><body>", f"<h1>{html.escape(title)}</h1>"]
    params = ", ".join(f"{k} {_fmt(report[k])}" for k in ("style", "seeds", "sf", "sv", "voxel_mm", "blend_mm",
                                                      "rng_seed", "kind", "region", "resampled")
                       if report.get(k) is not None)
    parts.append(f"<p>{html.escape(params)}. implicit_scaffold {html.escape(str(report.get('version', '')))}; "
                 "every measured value is computed from what was built.</p>")
    if measures:
        parts.append("<h2>Targets and measurements</h2><table><tr><th>quantity</th><th>target</th>"
                     "<th>measured</th></tr>")
        for q, t, m in targets_table(report):
            parts.append(f"<tr><td>{html.escape(q)}</td><td>{t}</td><td>{m}</td></tr>")
        parts.append("</table>")
        parts.append(f"<p style='font-size:90%;color:#555;max-width:60em'>{_HOW}</p>")
    cert = report.get("print_check")
    if isinstance(cert, dict):
        p = cert["printer"]
        parts.append(f"<h2>Print certificate: {html.escape(p['name'])} — {cert['verdict']['overall'].upper()}</h2>"
                     f"<p>{html.escape(p['process'])}. Sources: {html.escape(p['source'])}.</p>"
                     "<table><tr><th>check</th><th>measured</th><th>limit: verdict</th></tr>")
        for q, m, t in certificate_rows(cert):
            parts.append(f"<tr><td>{html.escape(q)}</td><td>{html.escape(m)}</td><td>{html.escape(t)}</td></tr>")
        parts.append("</table>")
    if isinstance(report.get("mechanics"), dict):
        parts.append(mechanics_html(report["mechanics"]))
    parts.append("<h2>Pictures</h2>")
    for caption, png in images.items():
        b64 = base64.b64encode(png).decode("ascii")
        parts.append(f"<figure><img src='data:image/png;base64,{b64}' style='max-width:520px'>"
                     f"<figcaption>{html.escape(caption)}</figcaption></figure>")
    parts.append("</body></html>\n")
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write("\n".join(parts))


def write_run_report(result, path, *, extra_images: dict[str, bytes] | None = None) -> None:
    """The page for a :func:`~implicit_scaffold.generate` result: pictures, histograms, table
    (and `extra_images`, e.g. the mechanics' strain section)."""
    from ..measure.metrics import pore_sizes

    r = result.report
    images: dict[str, bytes] = {}
    # a run in slabs is pictured by its sections: its mesh would be read back whole to be rendered
    if getattr(result, "tiled", None) is None and result.mesh is not None:
        images["the scaffold"] = render_mesh(result.mesh)
        images["cut-away: the trabecular inside"] = render_mesh(result.mesh, cut=True)
    if result.field is not None:
        # a tiled run's field is a map of its file on disk: an x section is one contiguous plane of
        # it, where a z section would page in the whole file
        axis = 0 if isinstance(result.field, np.memmap) else 2
        images["section through the middle (solid dark)"] = section_image(result.field, result.grid, axis=axis)
    images["pore size, polyhedron-sphere method"] = histogram(
        pore_sizes(result.cells, result.params.sv), title="pore size (polyhedron-sphere)", xlabel="diameter (mm)",
        marks={"target": r.get("pore_size_target_mm"), "150 µm": 0.15, "600 µm": 0.6})
    images.update(_sphere_histograms(r, strut_mark=("paper's trabecular thickness",
                                                    r.get("trabecular_thickness_mm_mean"))))
    cert = r.get("print_check")
    for (axis, index), section in getattr(cert, "sections", {}).items():
        images[f"print certificate: where the problems lie ({'xyz'[axis]} section)"] = certificate_section(
            section, result.grid, axis, index, cert["printer"]["name"])
    grade = r.get("grade")
    if isinstance(grade, dict) and grade.get("profiles"):
        prof = grade["profiles"]
        images["graded: porosity and pore size against depth"] = grade_profile_plot(
            prof["depth"], xlabel="depth below the patient surface (mm)", title=grade.get("field", "graded"))
        images[f"graded: porosity and pore size along {prof['axis_name']}"] = grade_profile_plot(
            prof["axis"], xlabel=f"{prof['axis_name']} (mm)", title=grade.get("field", "graded"))
    images.update(extra_images or {})
    write_html(path, r, images, title=f"Scaffold report: {r.get('patient', 'patient')}")


def _sphere_histograms(r: dict, strut_mark=(None, None)) -> dict[str, bytes]:
    """Histograms of the maximal-sphere strut thickness and pore diameter in a report."""
    images = {}
    for key, label, xlabel, marks in (
            ("strut_thickness_mm", "strut thickness (maximal spheres)", "thickness (mm)",
             {strut_mark[0]: strut_mark[1]} if strut_mark[0] else {}),
            ("pore_diameter_mm", "pore diameter (maximal spheres)", "diameter (mm)",
             {"target": r.get("pore_size_target_mm"), "150 µm": 0.15, "600 µm": 0.6})):
        st = r.get(key)
        if isinstance(st, dict) and st.get("histogram") and st["histogram"]["counts"]:
            hist = st["histogram"]
            top = hist["edges_mm"][-1]
            shown = {k: v for k, v in marks.items() if v is not None and v <= 1.3 * top}
            images[label] = histogram_from_counts(hist["edges_mm"], hist["counts"], title=label,
                                                  xlabel=xlabel, marks=shown)
    return images


def write_analysis_report(analysis, path) -> None:
    """The page for :func:`~implicit_scaffold.measure.morphometry.analyze_file`: picture, section, histograms, table."""
    from ..measure.morphometry import surface_mesh

    r = analysis.report
    mesh = analysis.mesh if analysis.mesh is not None else surface_mesh(analysis.solid, analysis.grid)
    images: dict[str, bytes] = {}
    if mesh is not None and len(mesh.faces):
        images["the solid"] = render_mesh(mesh)
        images["cut-away: the inside"] = render_mesh(mesh, cut=True)
    field = np.where(analysis.solid, np.float32(-1), np.float32(1))
    images["section through the middle (solid dark)"] = section_image(field, analysis.grid)
    images.update(_sphere_histograms(r))
    write_html(path, r, images, title=f"Morphometry of {r.get('source', 'a scaffold')}")


# ----------------------------------------------------------------------------- mechanics (issue 14)


def strain_section_image(compression, h: float) -> bytes:
    """The compression's von Mises strain on the section through the middle, across the load axis."""
    vm = compression.von_mises_strain
    axis = 0 if compression.axis != 0 else 1  # a section that contains the load axis
    index = vm.shape[axis] // 2
    sl = np.take(vm, index, axis=axis)
    axes = [a for a in range(3) if a != axis]
    fig, ax = _figure(4.8, 4.2)
    shown = np.ma.masked_where(sl <= 0, sl / compression.strain)
    im = ax.imshow(shown.T, origin="lower", cmap="inferno", interpolation="nearest",
                   extent=(0, sl.shape[0] * h, 0, sl.shape[1] * h))
    fig.colorbar(im, ax=ax, label="von Mises strain / applied strain")
    names = "xyz"
    ax.set_title(f"compression along {names[compression.axis]}: section {names[axis]} = {(index + 0.5) * h:.2f} mm")
    ax.set_xlabel(f"{names[axes[0]]} (mm)")
    ax.set_ylabel(f"{names[axes[1]]} (mm)")
    return _png(fig)


def solver_text(sol: dict) -> str:
    """The mechanics solve in a few words: each solve's CG iterations (its slowest piece's, where it has
    several) and the stop it met (its residual, or its estimated energy error, the other figure beside it;
    or that it met neither), and the time."""
    solves = sol["solves"]

    def one(name: str) -> str:
        s = solves[name]
        err = "" if s["energy_error"] is None else f"energy error {s['energy_error']:.1e} (estimated)"
        residual = f"residual {s['residual']:.1e}"
        if s["stopped_by"] == "residual":
            stop = f"{residual} <= {sol['tolerance']:g}" + (f", {err}" if err else "")
        elif s["stopped_by"] == "energy":
            stop = f"{err} <= {sol['accuracy']:g}, {residual}"
        else:
            stop = f"NOT converged: {residual}" + (f", {err}" if err else "")
        # pieces that share no node are solved one after another, each to its own stop: the figure is
        # the slowest's, where the progress lines counted them all on
        pieces = (sol.get("pieces") or {}).get(name, 1)
        of = f" (the slowest of {pieces} pieces)" if pieces > 1 else ""
        return f"{name} {s['iterations']} CG iterations{of}, {stop}"

    return f"{one('compression')}; {one('homogenization')}; {sol['seconds']:.1f} s"  # in the order they run


def mechanics_html(mech: dict) -> str:
    """The page's mechanics section: moduli beside bone's bands, the verdict, the solver."""
    E, G = mech["youngs_modulus_gpa"], mech["shear_modulus_gpa"]
    comp = mech["compression"]
    rows = [(f"Young's modulus {a} (GPa)", _fmt(E[a])) for a in "xyz"]
    rows += [(f"shear modulus {k} (GPa)", _fmt(v)) for k, v in G.items()]
    rows += [(f"Poisson's ratio {k}", _fmt(v)) for k, v in (mech.get("poisson_ratio") or {}).items()]
    rows.append((f"compression along {comp['axis']}, apparent modulus (GPa)", _fmt(comp["apparent_modulus_gpa"])))
    for name, band in mech["bone_bands_gpa"].items():
        rows.append((f"{name} bone (GPa)", f"{_fmt(band['low'])}–{_fmt(band['high'])}"))
    rows.append(("anisotropy index", _fmt(mech["anisotropy_index"])))
    rows.append(("solid fraction", _fmt(mech["solid_fraction"])))
    sol = mech["solver"]
    rows.append(("solver", solver_text(sol)))
    mat = mech["material"]
    out = ["<h2>Mechanics</h2>",
           f"<p><b>{html.escape(mech['stress_shielding'])}</b></p>",
           f"<p>{html.escape(mat['name'])}: E {_fmt(mat['E_gpa'])} GPa, ν {_fmt(mat['nu'])} "
           f"({html.escape(mat.get('source', ''))}). Boundary conditions: {html.escape(mech['boundary_conditions'])}."
           "</p><table><tr><th>quantity</th><th>value</th></tr>"]
    out += [f"<tr><td>{html.escape(q)}</td><td>{html.escape(v)}</td></tr>" for q, v in rows]
    out.append("</table>")
    sources = "; ".join(f"{k}: {b['source']}" for k, b in mech["bone_bands_gpa"].items())
    out.append(f"<p style='font-size:90%;color:#555'>Bone bands: {html.escape(sources)}.</p>")
    out += [f"<p style='font-size:90%'>note: {html.escape(n)}</p>" for n in mech.get("notes", [])]
    return "\n".join(out)


def write_mechanics_report(report: dict, compression, h: float, path) -> None:
    """The page for ``implicit-scaffold mechanics``: the mechanics section and the strain section."""
    mech = {k: v for k, v in report.items() if k not in ("version", "source", "kind")}
    page = {"version": report.get("version"), "kind": report.get("kind"), "voxel_mm": h, "mechanics": mech}
    images = {"compression: von Mises strain, middle section": strain_section_image(compression, h)}
    write_html(path, page, images, title=f"Mechanics of {report.get('source', 'a scaffold')}", measures=False)
