"""The README's examples run as they stand."""
import re
from pathlib import Path

import numpy as np
import trimesh

README = Path(__file__).resolve().parents[1] / "README.md"


def _block(title: str, nth: int = 0) -> str:
    """The `nth` Python block after the heading or sentence `title`."""
    text = README.read_text()
    section = text[text.index(title):]
    return re.findall(r"```python\n(.*?)```", section, re.S)[nth]


def test_the_composed_stages_example_builds_a_closed_ball_scaffold(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    exec(compile(_block("### Compose the stages yourself"), "README.md", "exec"), {})
    watertight, porosity = capsys.readouterr().out.split()
    assert watertight == "True" and abs(float(porosity) - 0.7) < 1e-3
    mesh = trimesh.load(tmp_path / "ball.stl")
    # an independent check of the file: closed, and its solid inside the ball (4/3 π 2.8³)
    assert mesh.is_watertight
    assert 0 < mesh.volume < 4 / 3 * np.pi * 2.8 ** 3
    assert np.all(np.linalg.norm(mesh.vertices - 3.0, axis=1) < 2.8 + 0.05)


def test_the_field_nodes_example_gives_the_composed_stages_field(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    names = {}
    exec(compile(_block("### Compose the stages yourself"), "README.md", "exec"), names)
    exec(compile(_block("### Compose the stages yourself", 1), "README.md", "exec"), names)
    # the oracle: the stage functions called by hand in the block before
    assert names["field"].tobytes() == names["s"].tobytes()
    assert names["level"] == names["solve_level"](names["lattice"], names["ball"] < 0, porosity=0.7)


def test_the_specs_example_builds_what_the_flat_keywords_build(tmp_path):
    # in a fresh interpreter, as a user runs it: its --max-memory 2G counts the process's own memory,
    # which in a test worker holds what the tests before it left (a worker at 2.11 GiB refused it)
    import subprocess
    import sys

    # the oracle: the same options as flat keywords, as the README says, give the same file
    flat = ("from implicit_scaffold import generate\n"
            "flat = generate(pore_size=0.8, porosity=0.7, sf=0.6, seed=2, voxel=0.08, max_memory='2G',\n"
            "                output='flat.stl', morphometry=False, size=4.0)\n"
            "print(flat.report['seeds'])\n")
    out = subprocess.run([sys.executable, "-c", _block("### From Python: typed specs") + "\n" + flat], cwd=tmp_path,
                         capture_output=True, text=True, check=True).stdout
    seeds, porosity, watertight, flat_seeds = out.split()[-4:]
    assert watertight == "True" and abs(float(porosity) - 0.7) < 0.003
    assert (tmp_path / "cube.stl").read_bytes() == (tmp_path / "flat.stl").read_bytes()
    assert int(seeds) == int(flat_seeds)
    mesh = trimesh.load(tmp_path / "cube.stl")
    assert mesh.is_watertight and abs(1 - mesh.volume / 4.0 ** 3 - 0.7) < 0.003
