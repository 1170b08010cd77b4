"""Progress on stderr: one line per stage, a bar for the tiled stages (quiet when asked or not a terminal)."""
from __future__ import annotations

import sys
import time
from contextlib import contextmanager


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
        try:
            yield
        finally:
            if timer is not None:
                timer.cancel()
        self.timings[name] = self.timings.get(name, 0.0) + time.perf_counter() - t0
        from .run.memory import peak_memory

        self.high_water[name] = peak_memory()
        check_interrupted()

    def note(self, text: str) -> None:
        """One line of what a stage found (e.g. how many seeds it drew), under the stage's line."""
        if self.enabled:
            print(f"    {text}", file=sys.stderr, flush=True)

    def solver(self, every: float = 5.0):
        """A callback ``(name, iteration, residual)`` for an iterative solve: a note at most every
        `every` seconds (None when not enabled)."""
        if not self.enabled:
            return None
        last = [time.perf_counter()]

        def tell(name, it, res):
            now = time.perf_counter()
            if now - last[0] >= every:
                last[0] = now
                self.note(f"{name}: CG iteration {it}, residual {res:.1e}")

        return tell

    def bar(self, label: str):
        """A callback ``(done, total)`` for tiled work; draws a bar with an ETA on a terminal."""
        if not self._bar_enabled:
            return None
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
