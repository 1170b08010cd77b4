"""threads.over_rows: every row once, in pieces on several threads, errors passed on."""
import threading

import numpy as np
import pytest

from implicit_scaffold.run.threads import over_rows


def _count(hits, seen, lo, hi):
    seen.add(threading.get_ident())
    hits[lo:hi] += 1


@pytest.mark.parametrize("n, pieces", [(1, None), (7, None), (100, None), (100, 3), (5, 50)])
def test_every_row_is_visited_once(n, pieces):
    hits = np.zeros(n, int)
    over_rows(_count, n, hits, set(), pieces=pieces)
    assert np.array_equal(hits, np.ones(n, int))


def test_no_rows_calls_nothing():
    calls = []
    over_rows(lambda lo, hi: calls.append((lo, hi)), 0)
    assert calls == []


def test_pieces_run_on_more_than_one_thread():
    import numba

    if numba.get_num_threads() < 2:
        pytest.skip("one thread on this machine")
    barrier = threading.Barrier(2, timeout=10)
    seen = set()

    def piece(lo, hi):
        seen.add(threading.get_ident())
        barrier.wait()  # two pieces must run at once, or this times out

    over_rows(piece, 2, pieces=2)
    assert len(seen) == 2


def test_one_thread_takes_the_rows_at_once():
    from implicit_scaffold.run.threads import limited

    calls = []
    with limited(1):
        over_rows(lambda lo, hi: calls.append((lo, hi)), 10)
    assert calls == [(0, 10)]


def test_an_error_in_a_piece_is_raised():
    def piece(lo, hi):
        if lo > 0:
            raise ValueError("bad row")

    with pytest.raises(ValueError, match="bad row"):
        over_rows(piece, 8, pieces=4)


def test_by_rows_covers_the_first_arguments_rows():
    from implicit_scaffold.run.threads import by_rows

    def _mark_rows(hits, lo, hi):
        hits[lo:hi] += 1

    hits = np.zeros((13, 4), int)
    by_rows(_mark_rows)(hits)
    assert np.array_equal(hits, np.ones((13, 4), int))


def _kernel_builders():
    """Every function of the package that builds compiled kernels (no arguments, 'kernel' or
    'compiled' in its name), called, with the numba dispatchers it made."""
    import importlib
    import inspect
    import pkgutil

    import numba

    import implicit_scaffold

    made = []
    real = numba.njit

    def spy(*args, **kw):
        out = real(*args, **kw)
        if args and callable(args[0]):  # @nb.njit without arguments
            made.append(out)
            return out

        def decorate(fn):
            d = out(fn)
            made.append(d)
            return d
        return decorate

    names = [m.name for m in pkgutil.walk_packages(implicit_scaffold.__path__, "implicit_scaffold.")
             if not m.ispkg and not m.name.endswith("__main__")]
    builders = []
    for name in names:
        mod = importlib.import_module(name)
        for fname, obj in list(vars(mod).items()):
            fn = getattr(obj, "__wrapped__", obj)  # a builder behind an lru_cache that another test filled
            if (inspect.isfunction(fn) and fn.__module__ == mod.__name__ and fn.__code__.co_argcount == 0
                    and not fn.__code__.co_kwonlyargcount
                    and ("kernel" in fname.lower() or "compiled" in fname.lower())):
                builders.append((mod, fname, fn))
    for mod, fname, fn in builders:
        cached = {k: v for k, v in vars(mod).items() if k.isupper() and k.startswith("_") and "KERNEL" in k}
        for k in cached:
            setattr(mod, k, None)  # built again under the spy
        numba.njit = spy
        try:
            fn()
        finally:
            numba.njit = real
            for k, v in cached.items():
                setattr(mod, k, v)
    return builders, made


def test_no_compiled_kernel_keeps_a_dispatcher_in_its_closure():
    # numba keys its disk cache on the pickled cells of a closure, and a dispatcher pickles
    # differently in every process: a kernel calling a helper held in a cell compiles afresh
    # in every run (0.3 s for the quantile's bracket pass) and its cache grows by one entry
    from numba.core.registry import CPUDispatcher

    builders, made = _kernel_builders()
    # the spy saw the package's kernels, those that call helpers among them
    assert len(builders) >= 8 and len(made) >= 30
    assert {"bracket", "edge_check", "float_rows", "nearest_rows", "flood_faces"} <= {d.py_func.__name__ for d in made}
    held = [d.py_func.__qualname__ for d in made
            if getattr(d, "py_func", None) is not None and d.py_func.__closure__
            and any(isinstance(c.cell_contents, CPUDispatcher) for c in d.py_func.__closure__)]
    assert held == []


def test_a_kernel_calling_a_helper_loads_from_the_cache_in_a_new_process(tmp_path):
    # the behaviour itself: the quantile's bracket pass (which calls the key helper), run in two
    # fresh processes on an empty cache folder, compiles in the first and only loads in the second
    import os
    import subprocess
    import sys

    code = ("import numpy as np\nfrom implicit_scaffold.run.tiles import order_pair_sampled\n"
            "v = np.random.default_rng(0).random(50000).astype(np.float32)\n"
            "print(order_pair_sampled(v, v > 0.1, 2000, int((v > 0.1).sum())))\n")
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path), "NUMBA_DEBUG_CACHE": "1"}
    runs = [subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
            for _ in range(2)]
    for r in runs:
        assert r.returncode == 0, r.stderr[-2000:]
    assert runs[0].stdout.count("data saved") >= 2  # bracket and its key helper compiled
    assert runs[1].stdout.count("data saved") == 0 and runs[1].stdout.count("data loaded") >= 1
    assert runs[0].stdout.splitlines()[-1] == runs[1].stdout.splitlines()[-1]
