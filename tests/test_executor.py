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


def test_imports_beside_start_after_the_workers_are_forked():
    """``import_beside``: the pool's workers are forked before the thread
    starts (a fork while a thread holds an import lock can leave a child
    waiting on it forever), the modules are imported once the wait returns,
    and the workers did not inherit them; the thread has ended when the
    executor closes; a second call, the serial back end and an empty list do
    nothing. In a fresh interpreter: a module no test has imported."""
    from fresh_process import last_literal

    code = """
import sys, threading
from seanv_analysis.batch.executor import make_executor, _nothing

def has(module):
    return module in sys.modules

mod = "xml.dom.minidom"
with make_executor(workers=2) as ex:
    wait = ex.import_beside([mod])
    forked = len(ex._pool._processes)
    again = ex.import_beside(["xml.sax"]) is _nothing
    wait()
    here = mod in sys.modules
    there = [r.value for r in ex.map(has, [mod] * 2, quiet=True)]
    empty = ex.import_beside([]) is _nothing
threads = [t.name for t in threading.enumerate() if t.name == "seanv-import-beside"]
with make_executor(workers=1) as ex:
    serial = ex.import_beside(["xml.sax"]) is _nothing and "xml.sax" not in sys.modules
print((forked, again, here, there, empty, threads, serial))
"""
    forked, again, here, there, empty, threads, serial = last_literal(code)
    assert forked == 2 and again and here and empty and serial
    assert there == [False, False]
    assert threads == []


def test_an_interrupted_executor_does_not_wait_for_its_imports(tmp_path, monkeypatch):
    """Ctrl-C while the thread of ``import_beside`` imports: the executor
    closes (``wait=False``, as on an interrupt) without waiting for it, and
    a command's run mapper (:class:`seanv_analysis.cli._common._WarmAfter`)
    neither waits for the imports nor warms the workers after a batch that
    raised; after one that ended it does both, once, the imports first."""
    import time

    from seanv_analysis.cli._common import _WarmAfter

    (tmp_path / "seanv_slow_import_probe.py").write_text("import time\ntime.sleep(5.0)\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    t0 = time.monotonic()
    ex = make_executor(workers=2)
    ex.import_beside(["seanv_slow_import_probe"])
    ex.close(wait=False)
    assert time.monotonic() - t0 < 2.5

    calls = []

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    mapper = _WarmAfter(interrupted, lambda: calls.append("warm"), lambda: calls.append("imported"))
    with pytest.raises(KeyboardInterrupt):
        mapper("ingest")
    assert calls == []
    mapper.mapper = lambda *args, **kwargs: "read"
    assert mapper("ingest") == "read" and mapper("again") == "read"
    assert calls == ["imported", "warm"]
