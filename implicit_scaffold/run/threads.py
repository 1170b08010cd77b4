"""Compiled loops on every core, without numba's parallel compiler.

numba's ``parallel=True`` costs 1.5 to 8 s of compilation per kernel and signature (its
parfor passes), against well under a second for the same loop compiled serially: on a
fresh machine the 19 parallel kernels of this package took most of a minute to compile
before the first scaffold was measured. The kernels are therefore serial, compiled with
``nogil=True``, and take the range ``[lo, hi)`` of outer rows they work on;
:func:`over_rows` splits the rows into consecutive pieces and runs the pieces on a thread
pool, so both cores still share the work.

Every row is written by one piece alone, and a kernel that sums writes one partial per row
(summed afterwards in row order), so the result is the same bytes whatever the number of
threads.
"""
from __future__ import annotations

import contextlib
import os
import threading
from collections import deque
from concurrent.futures import ThreadPoolExecutor

_POOL: ThreadPoolExecutor | None = None
_POOL_SIZE = 0
_LOCK = threading.Lock()


def _forget_pool() -> None:
    # a forked child has none of its parent's threads: it starts a pool of its own
    global _POOL, _POOL_SIZE
    _POOL, _POOL_SIZE = None, 0


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)


def _pool(size: int) -> ThreadPoolExecutor:
    """One pool for the process, kept between calls (a multigrid cycle makes thousands of
    small calls, and starting threads for each cost a millisecond)."""
    global _POOL, _POOL_SIZE
    with _LOCK:
        if _POOL is None or _POOL_SIZE < size:
            if _POOL is not None:
                _POOL.shutdown(wait=False)
            _POOL, _POOL_SIZE = ThreadPoolExecutor(size, thread_name_prefix="implicit_scaffold"), size
        return _POOL


#: a thread count set by :func:`limited`, else None
_LIMIT: int | None = None


def count() -> int:
    """The number of threads for compiled loops: :func:`limited`'s, else ``NUMBA_NUM_THREADS``
    when it is set, else the CPUs this process may run on.

    numba's own ``get_num_threads`` is not asked: it starts numba's threading layer, TBB's
    workers where TBB is installed (the Intel OpenCL runtime brings it), whose fork handler
    then prints "Unable to join threads to shut down before fork()" on standard output each
    time the mesh workers are forked; no kernel here uses that layer.
    """
    if _LIMIT is not None:
        return _LIMIT
    import numba

    return max(1, int(numba.config.NUMBA_NUM_THREADS))


@contextlib.contextmanager
def limited(n: int):
    """Compiled loops on at most `n` threads within the block (``n >= 1``)."""
    global _LIMIT
    old = _LIMIT
    _LIMIT = max(1, int(n))
    try:
        yield
    finally:
        _LIMIT = old


def over_rows(kernel, n: int, *args, pieces: int | None = None) -> None:
    """Call ``kernel(*args, lo, hi)`` over consecutive pieces ``[lo, hi)`` of ``range(n)``,
    concurrently.

    Parameters
    ----------
    kernel : callable
        A compiled kernel that releases the interpreter (``nogil=True``) and writes only the
        rows it is given.
    n : int
        The number of rows.
    *args
        The kernel's leading arguments.
    pieces : int, optional
        How many pieces (default four per thread, so that uneven rows even out).
    """
    n = int(n)
    if n <= 0:
        return
    threads = count()
    k = max(1, min(n, pieces if pieces is not None else 4 * threads))
    if threads == 1 or k == 1:
        kernel(*args, 0, n)
        return
    bounds = [n * p // k for p in range(k + 1)]
    left = iter(range(k))
    lock = threading.Lock()

    def work():
        while True:
            with lock:
                p = next(left, None)
            if p is None:
                return
            kernel(*args, bounds[p], bounds[p + 1])

    # the calling thread works too, beside threads - 1 of the pool's: pieces go to whoever is free
    helpers = min(threads, k) - 1
    pool = _pool(helpers)
    jobs = [pool.submit(work) for _ in range(helpers)]
    try:
        work()
    finally:
        for job in jobs:
            job.result()


def by_rows(kernel):
    """``kernel`` over the rows of its first argument's first axis, concurrently: a callable
    ``f(*args)`` that runs ``over_rows(kernel, args[0].shape[0], *args)``."""
    def run(*args):
        over_rows(kernel, args[0].shape[0], *args)

    run.__name__ = run.__qualname__ = kernel.__name__.removeprefix("_").removesuffix("_rows")
    return run


def submit(fn, *args):
    """``fn(*args)`` on the thread pool, as a future (called at once, in this thread, when
    there is one thread)."""
    from concurrent.futures import Future

    if count() == 1:
        done: Future = Future()
        try:
            done.set_result(fn(*args))
        except BaseException as exc:  # noqa: BLE001 - handed to the caller through the future
            done.set_exception(exc)
        return done
    return _pool(count()).submit(fn, *args)


def imap(fn, items, *, ahead: int | None = None):
    """``fn(item)`` for each of `items` on the thread pool, yielded in the items' order.

    For work that frees the interpreter (an image encoder, file writes). At most `ahead`
    items (default twice the threads) are in flight, so the memory they hold stays bounded.
    """
    threads = count()
    if threads == 1:
        yield from map(fn, items)
        return
    pool = _pool(threads)
    ahead = max(1, int(ahead or 2 * threads))
    waiting: deque = deque()
    for item in items:
        waiting.append(pool.submit(fn, item))
        if len(waiting) >= ahead:
            yield waiting.popleft().result()
    while waiting:
        yield waiting.popleft().result()
