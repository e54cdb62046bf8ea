"""The twin search's threads (identify/_threads.py ``map_on_threads``): results in the
order of the items whatever order the threads finish in; an error in one
item stops the others at their next replay and is raised in the caller;
one processor: a plain loop. (That the closed-loop check names the same
effect with the same numbers is tests/test_identify.py and test_golden.py;
the line's fit, tests/test_identify.py too.)"""
from __future__ import annotations

import threading
import time

import pytest

from seanv_analysis.identify import _threads as T


@pytest.fixture
def two_threads(monkeypatch):
    monkeypatch.setattr(T, "threads", lambda: 2)


def test_results_in_item_order(two_threads):
    stop = threading.Event()

    def slow_first(x):
        time.sleep(0.05 if x == 0 else 0.0)
        return x * x

    assert T.map_on_threads(slow_first, range(6), stop) == [0, 1, 4, 9, 16, 25]
    assert not stop.is_set()


def test_an_error_stops_the_other_threads(two_threads):
    stop = threading.Event()
    ran = []

    def item(x):
        if x == 1:
            raise ValueError("bad twin")
        for _ in range(200):            # a long search: a replay every 10 ms
            if stop.is_set():
                raise T.Stopped
            time.sleep(0.01)
        ran.append(x)
        return x

    t0 = time.perf_counter()
    with pytest.raises(ValueError, match="bad twin"):
        T.map_on_threads(item, [0, 1, 2, 3], stop)
    assert stop.is_set() and ran == []
    assert time.perf_counter() - t0 < 1.0      # not the 2 s the searches would take


def test_one_processor_is_a_plain_loop(monkeypatch):
    monkeypatch.setattr(T, "threads", lambda: 1)
    names = []

    def item(x):
        names.append(threading.current_thread().name)
        return x

    assert T.map_on_threads(item, [1, 2, 3], threading.Event()) == [1, 2, 3]
    assert set(names) == {threading.current_thread().name}
