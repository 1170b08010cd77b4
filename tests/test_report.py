"""The HTML report: self-contained, shows the measured values of the run it reports."""
import base64
import re

import numpy as np
import pytest

import implicit_scaffold
from implicit_scaffold.io import report


@pytest.fixture(scope="module")
def small_run():
    return implicit_scaffold.generate(seeds=40, size=4.0, voxel=0.1, porosity=0.75)


def test_page_is_self_contained(tmp_path, small_run):
    r = small_run
    imgs = {"section": report.section_image(r.field, r.grid),
            "pores": report.histogram(implicit_scaffold.measure.metrics.pore_sizes(r.cells, 0.75), title="pores",
                                      xlabel="mm", marks={"target": 0.6})}
    path = tmp_path / "r.html"
    report.write_html(path, r.report, imgs)
    page = path.read_text()
    # no network: every src is an embedded data URI, no link to any host
    assert not re.search(r"(src|href)\s*=\s*['\"]?(https?:|//)", page)
    blobs = re.findall(r"data:image/png;base64,([A-Za-z0-9+/=]+)", page)
    assert len(blobs) == 2
    assert all(base64.b64decode(b)[:8] == b"\x89PNG\r\n\x1a\n" for b in blobs)
    # the measured porosity shown is the run's own, to four significant digits
    assert f"{r.report['porosity_voxel']:.4g}" in page
    assert list(tmp_path.iterdir()) == [path]


def test_section_shows_the_solid(small_run):
    r = small_run
    png = report.section_image(r.field, r.grid, axis=2)
    import matplotlib.image as mpimg
    import io

    img = mpimg.imread(io.BytesIO(png))
    # the section holds both solid (dark) and void (light) pixels
    grey = img[..., :3].mean(axis=-1)
    assert (grey < 0.2).mean() > 0.02 and (grey > 0.8).mean() > 0.2


def test_render_mesh_draws_something(small_run):
    png = report.render_mesh(small_run.mesh, size=(300, 240))
    import io

    import matplotlib.image as mpimg

    img = mpimg.imread(io.BytesIO(png))
    assert img.shape[:2] == (240, 300)
    # not a blank page: a good share of pixels differ from the white background
    assert (np.abs(img[..., :3] - 1.0).sum(axis=-1) > 0.1).mean() > 0.05


def test_run_page_shows_the_sphere_histograms_and_measures(tmp_path, small_run):
    r = small_run
    path = tmp_path / "run.html"
    report.write_run_report(r, path)
    page = path.read_text()
    for caption in ("pore size, polyhedron-sphere method", "strut thickness (maximal spheres)",
                    "pore diameter (maximal spheres)"):
        assert f"<figcaption>{caption}</figcaption>" in page
    # the measured values shown are the run's own
    rep = r.report
    assert f"{rep['connectivity_density_per_mm3']:.4g}" in page
    assert f"mean {rep['strut_thickness_mm']['mean']:.4g}" in page
    assert f"mean {rep['pore_diameter_mm']['mean']:.4g}" in page
    assert f"{rep['bs_bv_per_mm']:.4g}" in page
    assert not re.search(r"(src|href)\s*=\s*['\"]?(https?:|//)", page)


def test_histogram_from_counts_shows_shares():
    import io

    import matplotlib.image as mpimg

    png = report.histogram_from_counts([0, 0.1, 0.2, 0.3], [10, 30, 0], title="t", xlabel="mm",
                                       marks={"target": 0.15})
    img = mpimg.imread(io.BytesIO(png))
    assert img.shape[0] > 100 and (img[..., :3].mean(axis=-1) < 0.9).mean() > 0.01


def test_targets_table_of_an_analysed_file_has_no_cell_rows():
    rep = {"porosity_voxel": 0.7, "strut_thickness_mm": {"mean": 0.2, "sd": 0.05, "max": 0.4},
           "connectivity_density_per_mm3": 12.5, "bs_bv_per_mm": 9.0}
    rows = report.targets_table(rep)
    names = [q for q, _, _ in rows]
    assert "interconnection (faces per cell)" not in names
    assert ("connectivity density (mm⁻³)", "—", "12.5") in rows
    assert any(q.startswith("strut thickness") and "mean 0.2" in m for q, _, m in rows)
