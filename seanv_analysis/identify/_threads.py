"""Threads for the twin's independent replays (identify and discover).

The simulator's kernel runs without the GIL (numba's JIT and the
ahead-of-time module alike), about two thirds of a replay, so replays of
different candidate values run side by side on threads. Each is computed
alone and the results come back in the items' order: the same numbers as
the plain loop.
"""
from __future__ import annotations

import os
import threading
from concurrent.futures import FIRST_EXCEPTION, ThreadPoolExecutor, wait
from typing import Callable, Sequence

__all__ = ["Stopped", "threads", "map_on_threads"]


class Stopped(Exception):
    """A twin search's thread gives up: the caller was interrupted or failed."""


def threads() -> int:
    """Threads for the twin's independent replays: the processors this
    process may use, at most 4 (the kernel runs without the GIL; the rest of
    a replay, about a third, holds it)."""
    try:
        n = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        n = os.cpu_count() or 1
    return max(1, min(n, 4))


def map_on_threads(fn: Callable, items: Sequence, stop: threading.Event) -> list:
    """``[fn(x) for x in items]``, the items on threads, the results in
    order (the same numbers as the loop: each is computed alone). On an
    error or Ctrl-C in the caller, ``stop`` is set, so the threads' next
    replay raises :class:`Stopped` and the call returns within one replay."""
    items = list(items)
    n = min(len(items), threads())
    if n < 2:
        return [fn(x) for x in items]
    pool = ThreadPoolExecutor(max_workers=n, thread_name_prefix="seanv-twin")
    futures = [pool.submit(fn, x) for x in items]
    try:
        wait(futures, return_when=FIRST_EXCEPTION)
        failed = [f.exception() for f in futures if f.done() and not f.cancelled()
                  and f.exception() is not None and not isinstance(f.exception(), Stopped)]
        if failed:
            raise failed[0]
        return [f.result() for f in futures]
    except BaseException:
        stop.set()
        raise
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
