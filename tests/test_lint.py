"""The code holds to the project's ruff rules (pyproject.toml, [tool.ruff]): pyflakes and pycodestyle."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_ruff_finds_nothing_under_the_projects_rules():
    pytest.importorskip("ruff", reason="ruff is in the test extras: pip install -e '.[test]'")
    run = subprocess.run([sys.executable, "-m", "ruff", "check", "implicit_scaffold", "tests", "benchmarks"],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-1000:]
