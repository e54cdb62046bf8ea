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
