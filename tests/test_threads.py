"""threads.over_rows: every row once, in pieces on several threads, errors passed on."""
import threading

import numpy as np
import pytest

from implicit_scaffold.threads import over_rows


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
    from implicit_scaffold.threads import limited

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
    from implicit_scaffold.threads import by_rows

    def _mark_rows(hits, lo, hi):
        hits[lo:hi] += 1

    hits = np.zeros((13, 4), int)
    by_rows(_mark_rows)(hits)
    assert np.array_equal(hits, np.ones((13, 4), int))
