"""Killing `seanv-analyze run` (issue 16, point 3): no worker outlives it,
SIGINT/SIGTERM cancel queued work at once (exit 130/143), a resumed run
gives the numbers of an uninterrupted one."""
from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
from pandas.testing import assert_frame_equal

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")

EXE = Path(sys.executable).with_name("seanv-analyze")
N_RUNS = 40


@pytest.fixture(scope="module")
def big(tmp_path_factory):
    from conftest import write_synthetic_dataset

    return write_synthetic_dataset(tmp_path_factory.mktemp("sig") / "data", n_flow=N_RUNS,
                                   duration_s=3.0)


def _children(pid: int) -> list[int]:
    out = []
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                stat = Path(f"/proc/{d}/stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                out.append(int(d))
    return out


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


#: `seanv-analyze` with the exit race of concurrent.futures made certain:
#: its exit hook (``_python_exit``, run by ``threading._shutdown``) checks
#: that a pool's wake-up pipe is open, then writes to it without the pool's
#: lock, while the pool's manager thread may be closing that pipe. A thread
#: switch between the two now and then under load (1 CI run in 7) gave a
#: traceback ending "Bad file descriptor" after the one-line message; the
#: 0.3 s sleep here between check and write makes it happen every time
#: unless the command has stopped the pool (manager thread ended, pipe
#: closed) before it exits. CPython 3.11's code, with the sleep added.
_RACY_EXIT = """
import sys, time
import concurrent.futures.process as cfp

def wakeup(self):
    if not self._closed:
        if cfp._global_shutdown:
            time.sleep(0.3)
        self._writer.send_bytes(b"")

cfp._ThreadWakeup.wakeup = wakeup
from seanv_analysis.cli import main
main(sys.argv[1:])
"""


def _start_and_wait_for_workers(data: Path, out: Path, *, racy_exit: bool = False,
                                extra: tuple[str, ...] = ()):
    """Start `run` with 2 workers; return (process, worker pids) once both
    workers run and a few results are cached (mid-run). ``racy_exit``: the
    command runs under :data:`_RACY_EXIT`; ``extra``: more options."""
    exe = [sys.executable, "-c", _RACY_EXIT] if racy_exit else [str(EXE)]
    cmd = exe + ["run", "flowfit", str(data), "--out", str(out), "--workers", "2", "-q", *extra]
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True)
    entries = out / ".cache" / "runs"
    deadline = time.monotonic() + 90
    while time.monotonic() < deadline:
        kids = _children(proc.pid)
        if len(kids) >= 2 and entries.is_dir() and len(list(entries.glob("*.json"))) >= 3:
            return proc, kids
        if proc.poll() is not None:
            break
        time.sleep(0.02)
    proc.kill()
    pytest.fail("the run did not reach its workers in time: " + (proc.stderr.read() or ""))


@pytest.mark.parametrize("sig,code", [(signal.SIGKILL, -9), (signal.SIGTERM, 143),
                                      (signal.SIGINT, 130)])
def test_no_worker_outlives_the_command(big, tmp_path, sig, code):
    out = tmp_path / "out"
    proc, kids = _start_and_wait_for_workers(big, out, racy_exit=sig != signal.SIGKILL)
    t0 = time.monotonic()
    proc.send_signal(sig)
    rc = proc.wait(timeout=20)
    took = time.monotonic() - t0
    err = proc.stderr.read()
    assert rc == code, err
    assert "Traceback" not in err
    if sig != signal.SIGKILL:
        assert took < 5, f"{took:.1f} s: queued runs were waited for"
        assert len(err.strip().splitlines()) == 1, err
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline and any(_alive(k) for k in kids):
        time.sleep(0.05)
    assert not [k for k in kids if _alive(k)], "a worker outlived its parent by 5 s"
    done = len(list((out / ".cache" / "runs").glob("*.json")))
    assert done < N_RUNS, "the run finished before it was killed"


def test_resumed_run_gives_the_uninterrupted_numbers(big, tmp_path):
    """The numbers (summary, flow fit) of a resumed run and an uninterrupted
    one; no figures (nothing here compares them: test_outputs does)."""
    out = tmp_path / "out"
    proc, _ = _start_and_wait_for_workers(big, out, extra=("--no-figures",))
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=20)
    leftover = tmp_path / "leftover"
    shutil.copytree(out, leftover)          # what the killed run left
    for folder in (out, tmp_path / "clean"):
        res = subprocess.run([str(EXE), "run", "flowfit", str(big), "--out", str(folder),
                              "--workers", "2", "-q", "--no-figures"], capture_output=True, text=True,
                             timeout=300)
        assert res.returncode == 0, res.stderr
    a = pd.read_parquet(out / "summary.parquet").drop(columns=["path"], errors="ignore")
    b = pd.read_parquet(tmp_path / "clean" / "summary.parquet").drop(columns=["path"],
                                                                       errors="ignore")
    assert_frame_equal(a, b)
    assert (out / "flowfit" / "flowfit.json").read_text() == \
        (tmp_path / "clean" / "flowfit" / "flowfit.json").read_text()


_HOLD_GIL = """
import os, re
from seanv_analysis.batch.executor import make_executor

def hold_gil(_):
    print(os.getpid(), flush=True)
    re.match(r"(a+)+$", "a" * 60 + "b")   # exponential, in C, never lets the GIL go

with make_executor(workers=2) as ex:
    ex.map(hold_gil, [0], quiet=True)
"""


def test_a_worker_holding_the_gil_dies_with_its_parent():
    """The watchdog thread cannot run while a C call holds the GIL: the
    kernel (PR_SET_PDEATHSIG) ends such a worker when its parent is killed."""
    proc = subprocess.Popen([sys.executable, "-c", _HOLD_GIL], stdout=subprocess.PIPE, text=True)
    busy = int(proc.stdout.readline())
    kids = set(_children(proc.pid)) | {busy}
    try:
        time.sleep(0.7)                       # the watchdog has had its turn
        proc.kill()
        proc.wait(timeout=10)
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and any(_alive(k) for k in kids):
            time.sleep(0.05)
        assert not [k for k in kids if _alive(k)], "a busy worker outlived its parent by 5 s"
    finally:
        for k in kids:
            if _alive(k):
                os.kill(k, signal.SIGKILL)


def test_dask_queued_work_is_cancelled_on_interrupt():
    """Best effort on a cluster: Ctrl-C during a Dask map cancels its queued tasks."""
    distributed = pytest.importorskip("dask.distributed")
    from seanv_analysis.batch.executor import make_executor

    def interrupt(res):
        raise KeyboardInterrupt

    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster, \
            distributed.Client(cluster) as client:
        with pytest.raises(KeyboardInterrupt):
            make_executor(client=client).map(time.sleep, [0.01] + [0.5] * 20, quiet=True,
                                             on_result=interrupt)
        deadline = time.monotonic() + 2
        while time.monotonic() < deadline and client.run_on_scheduler(
                lambda dask_scheduler: len(dask_scheduler.tasks)):
            time.sleep(0.05)
        assert client.run_on_scheduler(lambda dask_scheduler: len(dask_scheduler.tasks)) == 0
