"""Typed specs: checked when built, the same run as the flat keywords, refused when given twice."""
import dataclasses
import hashlib
import json

import numpy as np
import pytest

import implicit_scaffold
from implicit_scaffold import GridSpec, LatticeSpec, Outputs, ScaffoldError, generate

# keys whose values are the machine's, not the build's: they differ between two runs of the same options
RUN_KEYS = ("timings_s", "peak_memory_mb", "peak_memory_after_stage_mb")


def _build_keys(report: dict) -> dict:
    return {k: v for k, v in report.items() if k not in RUN_KEYS}


def test_specs_build_the_same_bytes_and_report_as_flat_keywords(tmp_path):
    # one non-default option in every spec (and the patient's skin beside them), so that a spec
    # field the run dropped or read from the wrong place would change the bytes or the report
    lattice = dict(seeds=60, porosity=0.7, sf=0.7, sv=0.65, blend=0.05, seed=3, fill_sealed_voids=False)
    # a budget above the default (4G) yet not one that what earlier tests left in this worker can exceed:
    # with "2G" a worker holding 1.9 GiB refused the 42^3 run (CI, ba45d8a)
    grid = dict(voxel=0.1, max_memory="8G")
    flat = generate(**lattice, **grid, output=tmp_path / "flat.npy", morphometry=False, size=4.0, skin=0.2)
    typed = generate(lattice=LatticeSpec(**lattice), grid=GridSpec(**grid),
                     outputs=Outputs(tmp_path / "typed.npy", morphometry=False), size=4.0, skin=0.2)
    assert typed.params == flat.params
    assert typed.field.tobytes() == flat.field.tobytes()
    digest = [hashlib.sha256((tmp_path / f"{n}.npy").read_bytes()).hexdigest() for n in ("flat", "typed")]
    assert digest[0] == digest[1]
    reports = [json.loads((tmp_path / f"{n}.json").read_text()) for n in ("flat", "typed")]
    assert _build_keys(reports[0]) == _build_keys(reports[1])
    assert reports[0]["sf"] == 0.7 and reports[0]["rng_seed"] == 3 and "morphometry" not in reports[0]


def test_the_command_line_builds_the_specs_generate_takes(tmp_path):
    from implicit_scaffold.cli import main

    assert main(["generate", "--seeds", "40", "--size", "3", "--voxel", "0.1", "--porosity", "0.5",
                 "--sf", "0.6", "--blend", "0", "-o", str(tmp_path / "cli.npy"), "-q"]) == 0
    generate(lattice=LatticeSpec(seeds=40, porosity=0.5, sf=0.6, blend=0), grid=GridSpec(voxel=0.1),
             outputs=Outputs(tmp_path / "api.npy"), size=3.0)
    assert (tmp_path / "cli.npy").read_bytes() == (tmp_path / "api.npy").read_bytes()


@pytest.mark.parametrize("specs, flat", [
    ({"lattice": LatticeSpec()}, {"sf": 0.75}),         # even at the spec's default: one of the two would be ignored
    ({"grid": GridSpec(voxel=0.1)}, {"voxel": 0.1}),
    ({"outputs": Outputs(mesh=False)}, {"output": "s.npy"}),
])
def test_an_option_given_both_ways_is_refused(specs, flat):
    with pytest.raises(ScaffoldError) as exc:
        generate(**specs, **flat)
    name = next(iter(flat))
    assert name in str(exc.value) and "one place" in str(exc.value) and "\n" not in str(exc.value)


@pytest.mark.parametrize("make, words", [
    (lambda: LatticeSpec(sf=1.5), "--sf must lie strictly between 0 and 1"),
    (lambda: LatticeSpec(style="gyroid"), "use paper or struts"),
    (lambda: LatticeSpec(seeds=1), "at least 2 seeds"),
    (lambda: LatticeSpec(porosity=80), "did you mean 0.8"),
    (lambda: LatticeSpec(style="struts", porosity=None), "--style struts solves the strut radius"),
    (lambda: LatticeSpec(weighted=True), "--weighted weights the cells"),
    (lambda: LatticeSpec(remove_fragments="no"), "remove_fragments must be True or False"),
    (lambda: GridSpec(voxel=-0.1), "--voxel must be a positive number of mm"),
    (lambda: GridSpec(max_memory="lots"), "--max-memory must be a size such as 4G"),
    (lambda: GridSpec(max_memory=0), "--max-memory must be a positive size"),
    (lambda: GridSpec(tiled=0), "tiled must be True, False, None or the voxels of a slab"),
    (lambda: GridSpec(workers=0), "--workers must be a whole number of processes"),
    (lambda: GridSpec(workers=2, scheduler="tcp://x:8786"), "give one"),
    (lambda: Outputs("s.xyz"), "cannot write s.xyz"),
    (lambda: Outputs("s.stl", mesh=False), "a mesh output needs the mesh stage"),
    (lambda: Outputs(repair=True), "add --printer NAME"),
    (lambda: Outputs(tolerance=-1), "--tolerance must be a distance >= 0"),
    (lambda: Outputs(slices={"pixel": 0.05}), "slices must be a dict such as"),
    (lambda: dataclasses.replace(LatticeSpec(), sv=0), "--sv must lie strictly between 0 and 1"),
])
def test_a_bad_value_is_refused_when_the_spec_is_built_in_one_line(make, words):
    with pytest.raises(ScaffoldError) as exc:
        make()
    assert words in str(exc.value) and "\n" not in str(exc.value)


def test_a_spec_holds_its_values_normalised():
    spec = LatticeSpec(porosity="none", sf="0.5", grade="0:0.3,2:0.8", style="PAPER")
    assert spec.porosity is None and spec.sf == 0.5 and spec.style == "paper"
    assert spec.grade.depths == (0.0, 2.0) and spec.grade.sizes == (0.3, 0.8)
    # normalised values are valid input: replace() checks them again and keeps them
    assert dataclasses.replace(spec) == spec
    assert GridSpec(max_memory="1.5G").max_memory == int(1.5 * 2**30)
    assert Outputs(printer="dlp-resin").printer.min_strut_mm == 0.4
    with pytest.raises(dataclasses.FrozenInstanceError):
        spec.sf = 0.9


def test_the_specs_defaults_are_the_runs():
    from implicit_scaffold.pipeline import Params, validate

    # Params is what the stages read: built from default specs it is the defaults of every option
    assert validate() == Params()
    assert generate.__kwdefaults__["lattice"] is None
    assert (Params().sf, Params().porosity, Params().pore_size, Params().tolerance) == (
        LatticeSpec().sf, LatticeSpec().porosity, LatticeSpec().pore_size, Outputs().tolerance)


def test_the_public_names_come_from_their_stage_modules():
    import importlib

    for name, module in implicit_scaffold._PUBLIC.items():
        assert getattr(implicit_scaffold, name) is getattr(
            importlib.import_module(f"implicit_scaffold.{module}"), name), name
    assert set(implicit_scaffold._PUBLIC) <= set(implicit_scaffold.__all__)
    with pytest.raises(AttributeError):
        implicit_scaffold.no_such_name
    # every stage function a script composes documents its parameters (numpydoc)
    for name in ("uniform_seeds", "voronoi_cells", "scaled_skeleton", "lattice_sdf", "blend_field", "solve_level",
                 "scaffold_field", "mesh_field", "generate", "LatticeSpec", "GridSpec", "Outputs", "Blend", "Cut",
                 "PaperLattice", "Struts", "evaluate"):
        doc = getattr(implicit_scaffold, name).__doc__
        assert "Parameters\n" in doc and "----------" in doc, name


def test_grid_spec_voxel_is_the_grids(tmp_path):
    r = generate(lattice=LatticeSpec(seeds=20, porosity=None), grid=GridSpec(voxel=0.125), size=2.0,
                 outputs=Outputs(mesh=False, morphometry=False))
    assert r.grid.spacing == 0.125 and r.report["voxel_mm"] == 0.125
    assert np.isclose(r.report["porosity_voxel"], 1 - np.count_nonzero(r.field < 0) / np.count_nonzero(r.patient_sdf < 0))


def test_every_spec_field_is_a_flat_keyword_of_generate():
    import inspect

    from implicit_scaffold.specs import FLAT_KEYWORDS

    # a spec field generate does not take as a keyword (or one it takes but no spec has)
    # would make the two ways of calling it differ
    unset = {name for name, p in inspect.signature(generate).parameters.items()
             if repr(p.default) == "<the spec's default>"}
    assert unset == FLAT_KEYWORDS
    assert len(FLAT_KEYWORDS) == sum(len(dataclasses.fields(c)) for c in (LatticeSpec, GridSpec, Outputs))
