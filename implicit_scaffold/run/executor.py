"""Where the slabs run: in this process, in local worker processes, or on a dask.distributed cluster.

Every slab pass (the lattice's, the mesh's) hands its slabs to an executor through one
interface::

    with contextlib.closing(executor.map(fn, slabs, shared)) as results:
        for result in results:   # in the order of `slabs` (or as they finish: ordered=False)
            ...

``fn(shared, item)`` runs once per item, wherever the executor runs it; `shared` (the
lattice's primitives, a field source) goes once to each worker. At most ``window`` items
are in flight or waiting to be taken, so what the caller holds stays bounded whatever the
number of items. Closing the iterator early (an error, Ctrl-C) stops the workers.

A pass whose slabs must agree on something only the parent can decide in slab order (the
mesh: where each slab's records go in the file depends on the slabs before it) gives an
``answer`` callable: `fn` is then a generator function that does its work, yields one
question, receives the parent's answer and returns its result. The parent answers the
questions in item order, each as soon as the item's turn comes, while later items keep
working (:func:`~implicit_scaffold.mesh.stream.write_mesh_slabs`).

The three executors give the same results for the same items: the work is the same
function on the same inputs, whichever process runs it.

Worker processes (:class:`Processes`)
-------------------------------------
- started with ``fork`` where the system has it (nothing to pickle, no re-import; the
  workers share the parent's loaded code), else ``spawn`` (then `fn` must be a module-level
  function and `shared` must pickle);
- Ctrl-C reaches the whole process group: the workers ignore it and the parent, which gets
  it, stops them (kills them) on its way out, so a ``with`` block around an atomic output
  leaves no partial file; SIGTERM ends the parent the same way once the CLI turns it into
  an exception;
- on Linux each worker is killed by the kernel when its parent dies (``PR_SET_PDEATHSIG``),
  so none is left working for nobody;
- a worker's exception comes back to the parent and is raised there in item order: a
  :class:`~implicit_scaffold.errors.ScaffoldError`, OSError or MemoryError as itself,
  anything else as a RuntimeError carrying the worker's traceback; a worker killed outright
  (the system out of memory) is one line naming the likely cause.
"""
from __future__ import annotations

import collections
import contextlib
import gc
import itertools
import os
import pickle
import signal
import threading
import traceback
import types
from typing import Callable, Iterable, Iterator

import numpy as np

from ..errors import ScaffoldError

__all__ = ["DaskCluster", "InProcess", "Processes", "check_workers", "executor_for", "free_cpus", "start_method"]


def free_cpus() -> int:
    """CPUs this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def start_method() -> str:
    """``fork`` where there is one (no re-import of the caller's script, nothing to pickle), else ``spawn``."""
    import multiprocessing

    return "fork" if "fork" in multiprocessing.get_all_start_methods() else "spawn"


def _call(fn: Callable, shared, item, answer: Callable | None):
    """`fn`'s result for `item`; with `answer`, `fn` is a generator that asks one question."""
    out = fn(shared, item)
    if answer is None:
        return out
    return _finish(out, answer(_ask(out)))


def _ask(task: types.GeneratorType):
    """A conversing task's question."""
    if not isinstance(task, types.GeneratorType):
        raise TypeError("with answer=, fn must be a generator function that yields one question")
    return next(task)


def _finish(task: types.GeneratorType, reply):
    """A conversing task's result, once it has its answer."""
    try:
        task.send(reply)
    except StopIteration as stop:
        return stop.value
    task.close()
    raise TypeError("a task given answer= yielded more than one question")


class InProcess:
    """The items one after the other in this process (one slab held in memory, or a small run)."""

    workers = 1

    def map(self, fn: Callable, items: Iterable, shared=None, *, ordered: bool = True,
            answer: Callable | None = None) -> Iterator:
        """``fn(shared, item)`` for each item, in order (`ordered` changes nothing here).

        With `answer`, each item's question is answered before the next item starts.
        """
        for item in items:
            yield _call(fn, shared, item, answer)

    def close(self) -> None:
        pass


class Processes:
    """Local worker processes, one item in each at a time (module notes).

    Parameters
    ----------
    workers : int
        Processes, at least 1; a map over fewer items starts fewer.
    name : str
        The processes' name (as ``ps`` and the error messages show it).
    window : int, optional
        Items in flight or waiting to be taken, at most; by default twice the workers.
    method : {"fork", "spawn"}, optional
        How the workers start; by default :func:`start_method`. Work that runs OpenCL kernels
        needs ``spawn``: a runtime's own threads do not survive a fork, so a forked child that
        launches a kernel on its parent's context may hang (Intel's CPU runtime happened to
        cope; nothing promises it, nor PoCL).
    """

    def __init__(self, workers: int, *, name: str = "implicit_scaffold-worker", window: int | None = None,
                 method: str | None = None):
        self.workers = check_workers(workers)
        self.name = name
        self.window = max(self.workers, int(window or 2 * self.workers))
        self.method = method or start_method()

    def map(self, fn: Callable, items: Iterable, shared=None, *, ordered: bool = True,
            answer: Callable | None = None) -> Iterator:
        """``fn(shared, item)`` for each item in the workers; results in item order, or as they
        finish with `ordered` False. Errors are raised in item order. Close the iterator to stop
        early: the workers are then killed."""
        items = list(items)
        if not items:
            return
        pool = _Pool(min(self.workers, len(items)), fn, shared, self.name, self.method)
        ok = False
        try:
            yield from pool.run(items, ordered, answer, self.window)
            ok = True
        finally:
            pool.close(kill=not ok)

    def close(self) -> None:
        pass  # each map starts and stops its own workers


class DaskCluster:
    """The items on a dask.distributed cluster.

    Parameters
    ----------
    scheduler : str or distributed.Client
        A scheduler's address (``tcp://host:8786``), or a client already connected.
    """

    def __init__(self, scheduler):
        try:
            from distributed import Client
        except ImportError:
            raise ScaffoldError("--scheduler needs dask.distributed: pip install 'implicit_scaffold[cluster]'") \
                from None
        if isinstance(scheduler, Client):
            self.client, self._own = scheduler, False
        else:
            try:
                self.client, self._own = Client(str(scheduler), timeout="10s"), True
            except (OSError, TimeoutError) as exc:
                raise ScaffoldError(f"cannot reach the Dask scheduler at {scheduler}: {exc}; "
                                    "check the address (tcp://host:8786) and that the scheduler runs") from None
        self.workers = max(1, len(self.client.scheduler_info().get("workers", {})))

    def map(self, fn: Callable, items: Iterable, shared=None, *, ordered: bool = True,
            answer: Callable | None = None) -> Iterator:
        """``fn(shared, item)`` for each item on the cluster, a few per worker in flight (enough
        to keep them busy, few enough to bound what waits on the client). `answer` is not
        supported: a cluster's workers cannot wait on this process."""
        from distributed import as_completed

        if answer is not None:
            raise TypeError("a Dask cluster runs independent items only: answer= needs InProcess or Processes")
        shared = self.client.scatter(shared, broadcast=True)
        items = iter(items)

        def submit(item):
            return self.client.submit(fn, shared, item, pure=False)

        first = [submit(item) for item in itertools.islice(items, 2 * self.workers)]
        # in item order: the oldest future first; else whichever finishes first
        queue = collections.deque(first) if ordered else as_completed(first)
        take = queue.popleft if ordered else queue.__next__
        add = queue.append if ordered else queue.add
        end = object()
        while True:
            try:
                future = take()
            except (IndexError, StopIteration):
                return
            result = future.result()
            future.release()
            nxt = next(items, end)
            if nxt is not end:
                add(submit(nxt))
            yield result

    def close(self) -> None:
        if self._own:
            self.client.close()


def check_workers(workers, scheduler=None) -> int:
    """`workers` as a count of local processes, checked before any work.

    Raises
    ------
    ScaffoldError
        Not a whole number of 1 or more, or above 1 beside a `scheduler` (the cluster has
        its own workers).
    """
    if isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) or workers < 1:
        raise ScaffoldError(f"--workers must be a whole number of processes, 1 or more; got {workers!r}")
    if scheduler is not None and workers > 1:
        raise ScaffoldError("--workers runs the slabs in local processes, --scheduler on a cluster: give one")
    return int(workers)


def executor_for(*, workers: int = 1, scheduler=None, method: str | None = None) -> InProcess | Processes | DaskCluster:
    """This process (1 worker, no scheduler), `workers` local processes (started by `method`, see
    :class:`Processes`), or a Dask cluster.

    Raises
    ------
    ScaffoldError
        As :func:`check_workers`; a scheduler that cannot be reached.
    """
    workers = check_workers(workers, scheduler)
    if scheduler is not None:
        return DaskCluster(scheduler)
    return InProcess() if workers == 1 else Processes(workers, method=method)


# ----------------------------------------------------------------------------- worker processes


def _worker(conn, fn: Callable, shared) -> None:  # pragma: no cover - runs in a worker
    """A worker process: run the items sent, one at a time, and send back what came of each."""
    # Ctrl-C reaches the whole process group; the parent stops the workers
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _die_with_parent()
    try:
        while True:
            task = conn.recv()
            if task is None:
                return
            index, item, asks = task
            try:
                out = fn(shared, item)
                if asks:
                    conn.send(("ask", index, _ask(out)))
                    reply = conn.recv()
                    if reply is None:
                        return  # the parent is stopping
                    out = _finish(out, reply[1])
                conn.send(("done", index, out))
                del out
            except Exception as exc:  # noqa: BLE001 - handed to the parent, which raises it in item order
                conn.send(("error", index, _portable(exc)))
    except (EOFError, BrokenPipeError):
        return  # the parent is gone


def _die_with_parent() -> None:  # pragma: no cover - runs in a worker
    """Where Linux allows, have the kernel kill this worker when its parent dies (killed,
    say), so that no worker is left working for nobody."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL))  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return


def _portable(exc: BaseException) -> BaseException:
    """`exc` if it pickles and says enough, else a RuntimeError carrying its traceback."""
    if isinstance(exc, (ScaffoldError, OSError, MemoryError)):
        try:
            pickle.dumps(exc)
            return exc
        except Exception:  # noqa: BLE001 - any pickling failure: fall back to the text
            pass
    return RuntimeError("a worker process failed:\n" + "".join(traceback.format_exception(exc)))


@contextlib.contextmanager
def _sigint_ignored():
    """Ignore Ctrl-C while workers start, so that they inherit that and leave it to the parent."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)


@contextlib.contextmanager
def _main_not_rerun(method: str):
    """While a ``spawn`` worker starts, hide the caller's main module from multiprocessing.

    A spawned child runs the parent's main script again (as ``__mp_main__``) before it
    unpickles its target, so a user's script that calls :func:`~implicit_scaffold.generate`
    without an ``if __name__ == "__main__":`` guard would start the run again in every worker
    (where multiprocessing refuses it, and the parent would wait on workers that never
    answer). The workers' functions and data are this package's, which the child imports by
    name, so the main script is not needed there.
    """
    import sys

    main = sys.modules.get("__main__")
    if method != "spawn" or main is None:
        yield
        return
    sys.modules["__main__"] = types.ModuleType("__main__")
    try:
        yield
    finally:
        sys.modules["__main__"] = main


class _Pool:
    """Worker processes for one map; stopped (killed if need be) by :meth:`close`."""

    def __init__(self, n: int, fn: Callable, shared, name: str, method: str):
        import multiprocessing

        ctx = multiprocessing.get_context(method)
        self.procs = []
        self.conns = []
        # what the parent's objects hold is not copied into the workers by their collector
        gc.freeze()
        try:
            for _ in range(n):
                mine, theirs = ctx.Pipe()
                proc = ctx.Process(target=_worker, args=(theirs, fn, shared), daemon=True, name=name)
                with _sigint_ignored(), _main_not_rerun(method):
                    proc.start()
                theirs.close()
                self.procs.append(proc)
                self.conns.append(mine)
        except BaseException:
            self.close(kill=True)
            raise
        finally:
            gc.unfreeze()

    def close(self, *, kill: bool) -> None:
        """Stop the workers: ask them to finish (or kill them, after an error or Ctrl-C), and wait."""
        for conn in self.conns:
            if not kill:
                with contextlib.suppress(OSError):
                    conn.send(None)
        for proc in self.procs:
            if kill and proc.is_alive():
                proc.kill()
            proc.join(timeout=None if kill else 60)
            if proc.is_alive():  # pragma: no cover - a worker that would not finish
                proc.kill()
                proc.join()
        for conn in self.conns:
            conn.close()
        self.procs = []
        self.conns = []

    def _stopped(self, w: int) -> ScaffoldError:
        """The one-line error for worker `w`, gone without a word."""
        code = self.procs[w].exitcode
        self.procs[w].join(timeout=5)
        code = self.procs[w].exitcode if code is None else code
        why = f"killed by signal {-code}" if code is not None and code < 0 else f"exit code {code}"
        return ScaffoldError(f"a worker process stopped ({why}; the system may have run out of memory): "
                             "lower --max-memory or use a larger --voxel")

    def _receive(self, w: int):
        try:
            return self.conns[w].recv()
        except (EOFError, OSError):
            raise self._stopped(w) from None

    def _send(self, w: int, message) -> None:
        try:
            self.conns[w].send(message)
        except (BrokenPipeError, ConnectionResetError):
            raise self._stopped(w) from None

    def run(self, items: list, ordered: bool, answer: Callable | None, window: int) -> Iterator:
        """Run `items` in the workers; answer their questions in item order; yield the results."""
        from multiprocessing.connection import wait

        total = len(items)
        idle = list(range(len(self.procs)))
        busy: dict[int, int] = {}       # worker -> item
        holder: dict[int, int] = {}     # item -> worker, while it waits for its answer
        asked: dict[int, object] = {}   # item -> its question, waiting for its turn
        results: dict[int, object] = {}
        errors: dict[int, BaseException] = {}
        sent = answered = yielded = 0
        while yielded < total:
            # bounded: no more than `window` items between sent and taken by the caller
            while idle and sent < total and sent - yielded < window:
                w = idle.pop()
                self._send(w, (sent, items[sent], answer is not None))
                busy[w] = sent
                if answer is not None:
                    holder[sent] = w
                sent += 1
            for conn in wait([self.conns[w] for w in busy]):
                w = self.conns.index(conn)
                kind, index, payload = self._receive(w)
                if kind == "ask":
                    asked[index] = payload  # the worker waits for its answer
                    continue
                (results if kind == "done" else errors)[index] = payload
                del busy[w]
                idle.append(w)
            # the questions in item order, each as soon as its turn comes (an item that
            # failed before asking stops them: its error is raised below, in its turn)
            while answer is not None and answered in asked:
                self._send(holder.pop(answered), ("answer", answer(asked.pop(answered))))
                answered += 1
            if ordered:
                while yielded in results or yielded in errors:
                    if yielded in errors:
                        raise errors[yielded]
                    yielded += 1
                    yield results.pop(yielded - 1)
            else:
                if errors:
                    raise errors[min(errors)]
                for index in sorted(results):
                    yielded += 1
                    yield results.pop(index)
