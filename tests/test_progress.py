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


def test_the_pace_of_a_geometric_residual_is_the_closed_form_count():
    from implicit_scaffold.progress import cg_pace

    # r_k = 2^-k at 0.1 s an iteration: 2^-k <= 1e-9 first at k = ceil(9 log2(10)) = 30
    history = [(k, 0.5 ** k, 0.1 * k) for k in range(1, 21)]
    more, seconds = cg_pace(history, 1e-9)
    assert more == 30 - 20 and abs(seconds - 1.0) < 1e-9
    # the later half sets the pace: a fast start (r / 100 an iteration) then r / 2 an iteration
    fast_start = [(k, 100.0 ** -k, 0.1 * k) for k in range(1, 4)]
    slow = [(k, 1e-6 * 0.5 ** (k - 3), 0.1 * k) for k in range(4, 24)]
    assert cg_pace(fast_start + slow, 1e-6 * 0.5 ** 30)[0] == 30 - 20
    assert cg_pace(history[:7], 1e-9) is None  # too few iterations to tell
    assert cg_pace(history, 0.5 ** 20) is None  # met
    assert cg_pace([(k, 1.0 + k, k) for k in range(1, 21)], 1e-6) is None  # not falling
    # a plateau (r / 1.01 an iteration): 1e-6 some 1,390 iterations on, beyond 4 times the 20 run
    assert cg_pace([(k, 1.01 ** -k, 0.1 * k) for k in range(1, 21)], 1e-6) is None
    assert cg_pace([(k, 1.01 ** -k, 0.1 * k) for k in range(1, 21)], 1.01 ** -100)[0] == 80


def test_a_solver_note_gives_the_pace_of_its_own_solve_only(capsys):
    progress = Progress(True)
    tell = progress.solver(every=0.0, goal=0.5 ** 30)
    for k in range(1, 21):
        tell("compression", k, 0.5 ** k)
    lines = capsys.readouterr().err.splitlines()
    assert lines[-1].startswith("    compression: CG iteration 20, residual 9.5e-07 (to 9.31323e-10 at this pace: ~10 ")
    assert "at this pace" not in lines[6] and "at this pace" in lines[7]  # from its 8th iteration
    # the next solve, and the next part of one (its residual starts again), start their pace afresh
    for name in ("homogenization", "homogenization"):
        for k in range(1, 8):
            tell(name, 20 + k, 0.5 ** k)
        assert "at this pace" not in capsys.readouterr().err
    tell("homogenization", 28, 0.5 ** 8)  # the part's 8th iteration: r / 2 an iteration, 2^-30 in 22 more
    assert "at this pace: ~22 more" in capsys.readouterr().err
    assert Progress(False).solver(goal=1e-6) is None


def test_a_solver_note_with_an_energy_accuracy_gives_the_sooner_pace(capsys):
    # the residual falls by 1.1 an iteration, the energy estimate (none for its first 4 iterations, as the
    # CG's) by 2: 2^-k <= 1e-6 first at k = ceil(6 log2(10)) = 20, 8 after the 12th iteration, where the
    # residual's 1e-6 is some 130 more (beyond its horizon: 4 times the 12 run)
    progress = Progress(True)
    tell = progress.solver(every=0.0, goal=1e-6, accuracy=1e-6)
    for k in range(1, 13):
        tell("homogenization", k, 1.1 ** -k, float("inf") if k < 5 else 0.5 ** k)
    last = capsys.readouterr().err.splitlines()[-1]
    assert last.startswith("    homogenization: CG iteration 12, residual 3.2e-01, energy error 2.4e-04 "
                           "(to energy error 1e-06 at this pace: ~8 more iterations")
    # an estimate above 1 (a piece's own ratio) is none: 6 estimates, too few for a pace, and the residual's
    # (0.9 an iteration, 1e-3 some 58 more) lies beyond its horizon
    tell = progress.solver(every=0.0, goal=1e-3, accuracy=1e-6)
    for k in range(1, 9):
        tell("compression", k, 0.9 ** k, 1e297 if k < 3 else 0.5 ** k)
    last = capsys.readouterr().err.splitlines()[-1]
    assert last == "    compression: CG iteration 8, residual 4.3e-01, energy error 3.9e-03"
    tell = progress.solver(every=0.0, goal=1e-3, accuracy=1e-6)
    for k in range(1, 9):
        tell("compression", k, 0.5 ** k, 0.5 ** k)
    last = capsys.readouterr().err.splitlines()[-1]
    assert "energy error 3.9e-03 (to 0.001 at this pace: ~2 more iterations, ~1 s)" in last  # the residual's, sooner
    tell("compression", 9, 0.5 ** 9, 0.5 ** 9)  # 2^-9 to 1e-3: one more halving
    assert "~1 more iteration, " in capsys.readouterr().err
    # no accuracy asked (a tolerance given): the residual's note, as before
    tell = progress.solver(every=0.0, goal=1e-6)
    tell("compression", 1, 0.5, 0.1)
    assert "energy" not in capsys.readouterr().err


def test_a_wait_is_given_in_the_unit_a_person_would_name():
    from implicit_scaffold.progress import format_duration

    assert [format_duration(s) for s in (0.2, 40, 89, 200, 5399, 7200)] == ["1 s", "40 s", "89 s", "3 min", "90 min",
                                                                            "2.0 h"]


def test_a_bar_off_a_terminal_notes_its_count_and_the_time_left(capsys):
    # a log or a pipe gets no bar: a line now and then, with what is done and the time left at its pace
    progress = Progress(True)
    update = progress.bar("mesh", every=0.0)
    for done in (1, 2, 4):
        time.sleep(0.05)
        update(done, 4)
    lines = capsys.readouterr().err.splitlines()
    assert [line.split(",")[0] for line in lines] == ["    mesh: 1 of 4 (25 %)", "    mesh: 2 of 4 (50 %)"]
    assert all(line.endswith(" left") for line in lines)
    assert Progress(False).bar("mesh") is None


def test_a_long_stage_off_a_terminal_says_it_is_still_running_until_it_ends(capsys, monkeypatch):
    import implicit_scaffold.progress as progress_module

    monkeypatch.setattr(progress_module, "HEARTBEAT_S", 0.1)
    with Progress(True).stage("cells"):
        time.sleep(0.35)
    lines = capsys.readouterr().err.splitlines()
    assert lines[0] == "  cells ..." and 2 <= len(lines) - 1 <= 4
    assert all(line.startswith("    cells: still running, ") for line in lines[1:])
    time.sleep(0.3)  # the stage is over: no more lines
    assert capsys.readouterr().err == ""
    with Progress(False).stage("cells"):
        time.sleep(0.25)
    assert capsys.readouterr().err == ""


def test_elapsed_times_thirty_seconds_apart_read_apart():
    # the heartbeat's "still running, 2 min" named both 90 s and 120 s
    from implicit_scaffold.progress import format_elapsed

    assert [format_elapsed(t) for t in (0.2, 40, 60, 90, 120, 150, 3599.6, 3900)] == \
        ["1 s", "40 s", "1 min", "1 min 30 s", "2 min", "2 min 30 s", "1 h 00 min", "1 h 05 min"]


def test_a_solver_note_names_the_part_and_the_parts_after_it(capsys):
    # a block of load cases (or a piece) names itself; its pace is its own, and the note says what follows it
    progress = Progress(True)
    tell = progress.solver(every=0.0, goal=0.5 ** 30)
    for k in range(1, 21):
        tell("homogenization", k, 0.5 ** k, None, part=(("block", 1, 3),))
    line = capsys.readouterr().err.splitlines()[-1]
    assert line.startswith("    homogenization, block 1 of 3: CG iteration 20, residual 9.5e-07 (to 9.31323e-10 at "
                           "this pace: ~10 more iterations")
    assert line.endswith("; then 2 more blocks)")
    # the next block starts its pace afresh (its residual starts again), and the last has none after it
    for k in range(1, 4):
        tell("homogenization", 20 + k, 0.5 ** k, None, part=(("piece", 2, 2), ("block", 3, 3)))
    lines = capsys.readouterr().err.splitlines()
    assert lines[-1] == "    homogenization, piece 2 of 2, block 3 of 3: CG iteration 23, residual 1.2e-01"
    tell("compression", 1, 0.5, None, part=(("piece", 1, 2),))
    assert capsys.readouterr().err.splitlines()[-1].endswith("residual 5.0e-01 (then 1 more piece)")
