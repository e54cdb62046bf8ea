"""The batch executor stopped by an interrupt (in-process; the whole
command under signals is tested in test_batch_signals.py)."""
from __future__ import annotations

import sys
import threading

import pytest

from seanv_analysis.batch.executor import make_executor

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"),
                                reason="the forked pool and its kill path")


def test_interrupted_pool_leaves_nothing_for_the_exit_hook():
    """Ctrl-C during a process-pool map: when the executor's ``with`` block
    has unwound, the workers are dead, the pool's manager thread has ended
    and its wake-up pipe is closed, so concurrent.futures' exit hook has no
    open pipe to write to while another thread closes it (the race behind a
    traceback after the "interrupted" line, test_batch_signals.py)."""
    import concurrent.futures.process as cfp

    before = set(threading.enumerate())
    workers, wakeup = [], []
    with pytest.raises(KeyboardInterrupt):
        with make_executor(workers=2) as ex:
            pool = ex._process_pool()

            def interrupt(res):                  # Ctrl-C as the first result arrives
                workers.extend(pool._processes.values())
                wakeup.append(pool._executor_manager_thread_wakeup)
                raise KeyboardInterrupt

            ex.map(abs, [-1] + [-2] * 20, quiet=True, on_result=interrupt)
    assert ex._pool is None
    assert len(workers) == 2
    assert not [p for p in workers if p.is_alive()]
    left = [t for t in threading.enumerate() if t not in before]
    assert not [t for t in left if isinstance(t, cfp._ExecutorManagerThread)], left
    assert wakeup[0]._closed


@pytest.mark.parametrize("n, workers", [(1, 2), (31, 2), (32, 2), (200, 2), (982, 2), (982, 7), (5, 1)])
def test_chunks_cover_every_item_once_in_order(n, workers):
    """A process pool's tasks: every item once, in order; fewer than 16 items
    per worker one a task; long lists in chunks of at most CHUNK_MAX, at
    least 8 per worker."""
    from seanv_analysis.batch.executor import CHUNK_MAX, _chunks

    chunks = _chunks(n, workers)
    assert [i for c in chunks for i in c] == list(range(n))
    sizes = {len(c) for c in chunks[:-1]} or {len(chunks[0])}
    assert len(sizes) == 1 and max(sizes) <= CHUNK_MAX
    if n < 16 * workers:
        assert max(sizes) == 1
    else:
        assert len(chunks) >= 8 * workers


def test_pool_results_in_input_order_with_errors_in_place():
    """Chunked tasks hand back each item's own outcome at its own place:
    a failing item fails alone."""
    items = list(range(-40, 40))
    with make_executor(workers=2) as ex:
        res = ex.map(_inverse, items, quiet=True)
    assert [r.item for r in res] == items
    assert [r.ok for r in res] == [i != 0 for i in items]
    assert all(r.value == 1.0 / i for r, i in zip(res, items) if i != 0)
    assert "division by zero" in res[40].error


def _inverse(x: int) -> float:
    return 1.0 / x
