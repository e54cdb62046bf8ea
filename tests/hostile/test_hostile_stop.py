"""Issue 34, point 4 (long loops): the time step is bounded by the rig
schema (1e-5..1e-2 s, tests/hostile/test_hostile_rig_file.py), and a long
simulation stops on Ctrl-C and SIGTERM: a compiled kernel reads its stop
slot (``PP.STOP``) every few hundred samples; a long call from the main
thread runs on a helper thread so the signal is handled at once; the CLI's
handlers stop every running kernel (threads too) and refuse new ones."""
from __future__ import annotations

import _thread
import os
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from seanv_analysis.config import load_rig
from seanv_analysis.sim import compiled, simulate_flow_step, simulate_position_control
from seanv_analysis.sim.control import FlowModelController

FINE = load_rig(overrides={"sim": {"time_step_s": 1e-5}})   # 100 plant steps per sample


def _long_run():
    """A position-control run of 300 s at 10 us: about 30 M plant steps (10-20 s)."""
    ref = (np.array([0.0, 100.0, 200.0]), np.array([20.0, 60.0, 30.0]))
    return simulate_position_control(FINE, controller=FlowModelController.from_rig(FINE),
                                     x_ref=ref, load=0.3, duration_s=300.0, x0_mm=20.0)


@pytest.fixture(scope="module", autouse=True)
def warm():
    """The kernel built or loaded before any clock starts."""
    simulate_flow_step(load_rig(), side="supply", cam_deg=0.0, load_mpag=0.3, hold_max_s=0.1)


def _kernel_threads():
    return [t for t in threading.enumerate() if t.name == "seanv-kernel"]


def test_ctrl_c_stops_a_long_simulation_of_the_main_thread():
    timer = threading.Timer(0.5, _thread.interrupt_main)
    t0 = time.monotonic()
    timer.start()
    with pytest.raises(KeyboardInterrupt):
        _long_run()
    assert time.monotonic() - t0 < 3.0
    deadline = time.monotonic() + 2.0
    while _kernel_threads() and time.monotonic() < deadline:   # its kernel saw the stop slot
        time.sleep(0.05)
    assert not _kernel_threads()


def test_stop_all_stops_simulations_on_other_threads(monkeypatch):
    monkeypatch.setattr(compiled, "_STOPPED", False)
    with ThreadPoolExecutor(1) as pool:
        future = pool.submit(_long_run)
        time.sleep(0.5)
        t0 = time.monotonic()
        compiled.stop_all()
        with pytest.raises(compiled.SimulationStopped):
            future.result(timeout=5)
        assert time.monotonic() - t0 < 2.0
    with pytest.raises(compiled.SimulationStopped, match="this process is stopping"):
        simulate_flow_step(load_rig(), side="supply", cam_deg=0.0, load_mpag=0.3, hold_max_s=0.1)
    monkeypatch.setattr(compiled, "_STOPPED", False)


def test_a_short_main_thread_call_runs_in_place(monkeypatch):
    started = []
    real = threading.Thread.start
    monkeypatch.setattr(threading.Thread, "start",
                        lambda self: (started.append(self.name), real(self))[1])
    simulate_flow_step(load_rig(), side="supply", cam_deg=0.0, load_mpag=0.3, hold_max_s=0.1)
    assert "seanv-kernel" not in started


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")
def test_the_command_exits_130_at_once_on_ctrl_c(tmp_path):
    """The probe: a long simulation ignored SIGINT and SIGTERM."""
    (tmp_path / "rig.toml").write_text("[sim]\ntime_step_s = 1e-5\n")
    exe = os.path.join(os.path.dirname(sys.executable), "seanv-analyze")
    proc = subprocess.Popen([exe, "simulate", "paper-position", "--out", str(tmp_path / "d"),
                             "--rig", str(tmp_path / "rig.toml"), "-q"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(4.0)   # started, simulating (14 s in all)
    t0 = time.monotonic()
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 130, (out, err)
    assert time.monotonic() - t0 < 3.0
    assert "Traceback" not in err and err.strip().startswith("interrupted (Ctrl-C)")
