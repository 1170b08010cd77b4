"""Progress on stderr: one line per stage, a bar for the tiled stages (quiet when asked or not a terminal)."""
from __future__ import annotations

import sys
import time
from contextlib import contextmanager


#: seconds between a long stage's "still running" lines off a terminal (:meth:`Progress.stage`)
HEARTBEAT_S = 30.0

#: set by the command line's SIGINT/SIGTERM handler: a KeyboardInterrupt raised while the
#: interpreter runs a finalizer (``__del__``) is swallowed, so every stage boundary raises it again
INTERRUPTED = False


def check_interrupted() -> None:
    """Raise KeyboardInterrupt if the run was asked to stop (see :data:`INTERRUPTED`)."""
    if INTERRUPTED:
        raise KeyboardInterrupt


class Progress:
    """Reports stages as they run and keeps their wall-clock times.

    Parameters
    ----------
    enabled : bool
        Print to stderr; the times are kept either way.
    """

    def __init__(self, enabled: bool = False):
        self.enabled = enabled
        self.timings: dict[str, float] = {}
        #: the process's peak resident bytes as each stage ended (its high-water mark, which
        #: only grows): the stage where it jumps is the one that needed the memory
        self.high_water: dict[str, int] = {}
        self._bar_enabled = enabled and sys.stderr.isatty()

    @contextmanager
    def stage(self, name: str, detail: str = "", *, after: float | None = None):
        """A stage of the run: its line on stderr as it starts, or, with `after` (seconds), only once it
        has run that long (a quick run's error then stays the one line on stderr)."""
        line = f"  {name}{' (' + detail + ')' if detail else ''} ..."
        timer = None
        if self.enabled and after is None:
            print(line, file=sys.stderr, flush=True)
        elif self.enabled:
            import threading

            timer = threading.Timer(after, lambda: print(line, file=sys.stderr, flush=True))
            timer.daemon = True
            timer.start()
        check_interrupted()
        t0 = time.perf_counter()
        beat = self._heartbeat(name, t0) if self.enabled and not self._bar_enabled else None
        try:
            yield
        finally:
            if timer is not None:
                timer.cancel()
            if beat is not None:
                beat.set()
        self.timings[name] = self.timings.get(name, 0.0) + time.perf_counter() - t0
        from .run.memory import peak_memory

        self.high_water[name] = peak_memory()
        check_interrupted()

    def _heartbeat(self, name: str, t0: float):
        """Off a terminal (a log, a pipe), a line every :data:`HEARTBEAT_S` seconds while stage `name` runs, so
        that a long stage with no count of its own (cells for 382,000 seeds: 145 s) is seen to be alive; the
        returned event stops it."""
        import threading

        stop = threading.Event()

        def beat():
            while not stop.wait(HEARTBEAT_S):
                print(f"    {name}: still running, {format_elapsed(time.perf_counter() - t0)}", file=sys.stderr,
                      flush=True)

        threading.Thread(target=beat, daemon=True, name=f"heartbeat {name}").start()
        return stop

    def note(self, text: str) -> None:
        """One line of what a stage found (e.g. how many seeds it drew), under the stage's line."""
        if self.enabled:
            print(f"    {text}", file=sys.stderr, flush=True)

    def solver(self, every: float = 5.0, goal: float | None = None, accuracy: float | None = None):
        """A callback ``(name, iteration, residual[, energy error])`` for an iterative solve: a note at most
        every `every` seconds (None when not enabled). With `goal`, the relative residual the solve stops at
        (at the latest), the note adds how many more iterations and seconds the residual's recent pace
        takes to reach it (:func:`cg_pace`). With `accuracy`, the energy accuracy that stops the solve
        where it comes first (the mechanics' default stop), the note gives the solve's estimated relative
        energy error (the callback's fourth argument, None or inf where there is none yet) and the pace is
        the sooner of the two: the energy's on its own estimates, or the residual's (the default cube's
        ``generate --mechanics``: at the homogenization's iteration 37 the residual's pace said 88 more, and
        the energy's stop came at 44)."""
        if not self.enabled:
            return None
        import math

        last = [time.perf_counter()]
        history: list = []

        def tell(name, it, res, energy=None, part=()):
            now = time.perf_counter()
            part = tuple(part)
            # a new solve, or the next part of one (a block of load cases, a piece) whose residual
            # starts again from its own right-hand side: the pace of the one before says nothing
            if history and (history[-1][0] != (name, part) or res > 10 * history[-1][2]):
                history.clear()
            # an estimate above 1 says nothing (a piece that keeps almost none of its energy: its own ratio)
            known = energy is not None and math.isfinite(energy) and energy < 1
            history.append(((name, part), it, res, now, energy if known else None))
            if now - last[0] >= every:
                last[0] = now
                # the part named (block 1 of 3): its pace is its own, and the parts after it follow
                label = name + "".join(f", {what} {k} of {n}" for what, k, n in part)
                text = f"{label}: CG iteration {it}, residual {res:.1e}"
                if known and accuracy is not None:
                    text += f", energy error {energy:.1e}"
                paces = []
                if goal is not None:
                    paces.append((cg_pace([h[1:4] for h in history], goal), f"{goal:g}"))
                if accuracy is not None:
                    paces.append((cg_pace([(h[1], h[4], h[3]) for h in history if h[4] is not None], accuracy),
                                  f"energy error {accuracy:g}"))
                paces = [p for p in paces if p[0] is not None]
                after = ""
                if part and part[-1][2] > part[-1][1]:
                    what, k, n = part[-1]
                    after = f"then {n - k} more {what}{'' if n - k == 1 else 's'}"
                if paces:
                    (more, seconds), what = min(paces, key=lambda p: p[0][0])
                    text += (f" (to {what} at this pace: ~{more} more iteration{'' if more == 1 else 's'}, "
                             f"~{format_duration(seconds)}" + (f"; {after})" if after else ")"))
                elif after:
                    text += f" ({after})"
                self.note(text)

        tell.takes_energy = True
        tell.takes_part = True
        return tell

    def bar(self, label: str, every: float = 10.0):
        """A callback ``(done, total)`` for tiled work; draws a bar with an ETA on a terminal, and
        elsewhere (a log, a pipe) a note at most every `every` seconds with the count and the time
        left at the pace so far (None when not enabled)."""
        if not self.enabled:
            return None
        if not self._bar_enabled:
            t0 = time.perf_counter()
            last = [t0]

            def note(done: int, total: int):
                now = time.perf_counter()
                if now - last[0] >= every and 0 < done < total:
                    last[0] = now
                    left = (now - t0) * (total - done) / done
                    self.note(f"{label}: {done} of {total} ({100 * done / total:.0f} %), "
                              f"~{format_duration(left)} left")

            return note
        from tqdm import tqdm

        state = {}

        def update(done: int, total: int):
            if "bar" not in state:
                state["bar"] = tqdm(total=total, desc=f"  {label}", unit="tile", leave=False,
                                    file=sys.stderr)
            state["bar"].update(done - state["bar"].n)
            if done >= total:
                state["bar"].close()

        return update


#: :func:`cg_pace` gives no count beyond this many times the iterations run so far: on the data folder's CT
#: (``mechanics totalseg_example_ct_dicom --threshold 200``, 83 pieces solved one after another), a piece on a
#: plateau at its 120th iteration was promised 7,609 more, and its solve ended within 91
PACE_HORIZON = 4


def cg_pace(history, goal: float):
    """(iterations, seconds) an iterative solve's residual takes to fall to `goal` at its recent pace, or
    None (too few iterations yet, the residual not falling, or the goal met).

    The pace is the residual's mean fall per iteration (a geometric rate) and the seconds an iteration
    took, over the later half of `history` ((iteration, residual, seconds since any fixed time) per
    iteration, in order, of one solve): CG's residual falls unevenly (plateaus, then steps), its early
    iterations faster than its later ones, so the first half would promise too soon an end. A count
    beyond :data:`PACE_HORIZON` times the iterations so far is not given (None).
    """
    import math

    if len(history) < 8:
        return None
    it1, r1, t1 = history[-1]
    it0, r0, t0 = history[len(history) // 2]
    if not (0 < r1 < r0) or it1 <= it0 or r1 <= goal:
        return None
    rate = math.log(r1 / r0) / (it1 - it0)  # < 0
    more = math.ceil(math.log(goal / r1) / rate)
    if more > PACE_HORIZON * (it1 - history[0][0] + 1):
        return None  # a plateau's pace: a CG that stalls this long mostly finds its next step later
    return more, more * (t1 - t0) / (it1 - it0)


def format_elapsed(seconds: float) -> str:
    """``"40 s"``, ``"1 min 30 s"``, ``"1 h 05 min"``: a time spent, to the second (under an hour), so that lines
    30 s apart never read the same (:func:`format_duration`'s "2 min" named both 90 s and 120 s)."""
    total = int(round(seconds))
    if total < 60:
        return f"{max(1, total)} s"
    if total < 3600:
        m, s = divmod(total, 60)
        return f"{m} min" if s == 0 else f"{m} min {s:02d} s"
    h, m = divmod(total // 60, 60)
    return f"{h} h {m:02d} min"


def format_duration(seconds: float) -> str:
    """``"40 s"``, ``"3 min"`` or ``"1.5 h"``: a time to wait, as a person says it."""
    if seconds < 90:
        return f"{max(1, round(seconds))} s"
    if seconds < 5400:
        return f"{round(seconds / 60)} min"
    return f"{seconds / 3600:.1f} h"
