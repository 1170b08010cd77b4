"""The run's progress lines (implicit_scaffold/progress.py)."""
from __future__ import annotations

import time

from implicit_scaffold.progress import Progress


def test_a_stage_with_after_prints_its_line_only_once_it_has_run_that_long(capsys):
    progress = Progress(True)
    with progress.stage("quick", "done at once", after=0.5):
        pass
    time.sleep(0.7)  # past `after`: a timer left running would print now
    assert capsys.readouterr().err == ""
    with progress.stage("slow", "a while", after=0.05):
        time.sleep(0.5)
    assert capsys.readouterr().err == "  slow (a while) ...\n"
    assert set(progress.timings) == {"quick", "slow"} and progress.timings["slow"] >= 0.5


def test_a_stage_prints_its_line_at_once_by_default_and_nothing_when_quiet(capsys):
    with Progress(True).stage("reading", "x.nrrd"):
        assert capsys.readouterr().err == "  reading (x.nrrd) ...\n"
    with Progress(False).stage("reading", after=0.0):
        time.sleep(0.2)
    assert capsys.readouterr().err == ""
