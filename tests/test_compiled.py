"""The simulator's ahead-of-time compiled kernel (sim/compiled.py).

What must hold: it gives what numba's JIT gives, bit for bit (flow steps with
effects and closed-form terms, position control with either controller, a
cam replay, the servo alone); it takes any float array (strided, other
dtypes) as the JIT does; importing the simulator does not import numba; when
it cannot be built or is turned off, the JIT serves and says why.
"""
from __future__ import annotations

import shutil
import subprocess
import sys

import numpy as np
import pytest

from seanv_analysis import load_rig
from seanv_analysis.sim import (
    compiled,
    simulate_cam_replay,
    simulate_flow_step,
    simulate_position_control,
)
from seanv_analysis.sim._pp import PP, PP_SIZE
from seanv_analysis.sim.control import CamController, FlowModelController
from seanv_analysis.sim.servo import servo_response

RIG = load_rig()
HAVE_CC = any(shutil.which(c) for c in ("cc", "gcc", "clang"))


@pytest.fixture(scope="module")
def aot():
    """The AOT functions (built on first use, about 20 s once per machine)."""
    if not HAVE_CC:
        pytest.skip("no C compiler: the simulator runs on numba's JIT here")
    fn = compiled.simulate_kernel()
    assert compiled.aot_status() is None, compiled.aot_status()
    return fn


def _record(monkeypatch, aot_fn):
    """Run the simulator through the AOT kernel, keeping each call's inputs
    (copied before the call: the kernel writes into the packed terms)."""
    calls = []

    def rec(*args):
        calls.append(tuple(a.copy() if isinstance(a, np.ndarray) else a for a in args))
        return aot_fn(*args)

    monkeypatch.setitem(compiled._loaded, "simulate_kernel", rec)
    return calls


def _same(a, b):
    return all(np.array_equal(x, y, equal_nan=True) for x, y in zip(a, b))


def test_aot_kernel_equals_the_jit_bit_for_bit(aot, monkeypatch):
    from seanv_analysis.sim.kernel import simulate_kernel as jit_kernel

    calls = _record(monkeypatch, aot)
    simulate_flow_step(RIG, side="supply", cam_deg=2.0, load_mpag=0.4, hold_max_s=0.6,
                       effects=["backlash", "delay", "term:side=supply,mode=mul,"
                                "expr=-0.2*tanh(dp/0.5) + 0.01*approach"])
    simulate_flow_step(RIG, side="drain", cam_deg=-35.0, load_mpag=0.2, hold_max_s=0.6,
                       approach=-1, effects=["drift:side=drain", "saturation"])
    ref = (np.array([0.0, 1.0, 2.5]), np.array([20.0, 60.0, 40.0]))
    simulate_position_control(RIG, controller=FlowModelController.from_rig(RIG), x_ref=ref,
                              load=0.3, duration_s=4.0, x0_mm=20.0)
    simulate_position_control(RIG, controller=CamController.from_rig(RIG), x_ref=ref,
                              load=(np.array([0.0, 2.0]), np.array([0.3, 0.5])),
                              duration_s=4.0, x0_mm=20.0)
    simulate_cam_replay(RIG, cam_cmd=(np.array([0.0, 0.5, 1.5]), np.array([-15.0, 3.0, -30.0])),
                        load=0.3, duration_s=2.5, x0_mm=30.0)
    assert len(calls) == 5
    for args in calls:
        got = aot(*args)
        want = jit_kernel(*args)
        assert _same(got, want)
        assert np.isfinite(got[0]).all()


def test_aot_servo_equals_the_jit_and_takes_any_float_array(aot):
    from seanv_analysis.sim.kernel import servo_track as jit_track

    t = np.arange(0.0, 2.0, 0.01)
    cmd = np.where(t < 0.5, -15.0, 5.0) + np.sin(7 * t)
    pp = np.zeros(PP_SIZE)
    pp[PP.SERVO_TAU], pp[PP.SERVO_RATE] = 0.03, 400.0  # [s], [deg/s]
    args = (t, cmd, 0.0, 5e-4, 4000, 0.02, pp, -15.0)
    got = compiled.servo_track()(*args)
    assert np.array_equal(got, jit_track(*args))
    # strided and float32 arrays: converted, not refused or misread
    t2 = np.repeat(t, 2)[::2]
    assert not t2.flags.c_contiguous
    assert np.array_equal(compiled.servo_track()(t2, *args[1:]), got)
    c32 = cmd.astype(np.float32)
    assert np.array_equal(compiled.servo_track()(t, c32, *args[2:]),
                          jit_track(t, c32.astype(np.float64), *args[2:]))
    y = servo_response(t, cmd, t[::3], dead_time_s=0.02, time_constant_s=0.03,
                       max_rate_deg_s=400.0)
    assert y.shape == t[::3].shape and np.isfinite(y).all()


def test_aot_controller_replay_equals_the_jit_and_loads_no_numba(aot):
    """Both controllers replayed over logged ticks (a NaN position, a NaN
    head pressure): the ahead-of-time function gives the JIT's commands bit
    for bit, and a process that replays imports no numba (its first JIT
    call took 1.4-1.7 s there, for a 2 ms replay)."""
    from seanv_analysis.sim.control_law import controller_replay as jit_replay

    rng = np.random.default_rng(0)
    n = 2000
    x_ref = np.repeat([0.0, 30.0, 15.0, 30.0], n // 4)
    x = np.cumsum(rng.normal(0, 0.3, n)) + 10.0
    ps, ph, pt = np.full(n, 3.3), 2.0 + rng.normal(0, 0.1, n), np.zeros(n)
    x[100], ph[200] = np.nan, np.nan
    for c in (FlowModelController.from_rig(RIG), CamController.from_rig(RIG)):
        kind, cp, tables = c.jit_spec()
        want = jit_replay(kind, cp, *tables, c.initial_state().packed(), x_ref, x, ps, ph, pt)
        got = c.replay(x_ref, x, ps, ph, pt)
        assert np.array_equal(got, want, equal_nan=True) and np.isnan(got).sum() == 1
    code = ("import sys, numpy as np; from seanv_analysis import load_rig; "
            "from seanv_analysis.sim.control import FlowModelController; "
            "c = FlowModelController.from_rig(load_rig()); "
            "c.replay(np.full(9, 30.0), np.zeros(9), np.full(9, 3.3), np.full(9, 2.0), np.zeros(9)); "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('numba', 'llvmlite')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.strip()
    assert out == "[]"


def test_servo_response_reads_its_grid_as_np_interp_does():
    """servo_response's interpolation on the servo's uniform step grid is
    np.interp on that grid: inside, before its first and after its last
    point (held), at a grid point, and NaN where the time is NaN."""
    from seanv_analysis.sim.servo import _on_uniform_grid

    rng = np.random.default_rng(2)
    y = np.cumsum(rng.normal(0, 1, 2001))
    t_first, step = 0.3, 5e-4
    grid = t_first + step * np.arange(y.size)
    t = np.concatenate([rng.uniform(grid[0] - 0.1, grid[-1] + 0.1, 500), grid[[0, 7, -1]],
                        [np.nan]])
    got = _on_uniform_grid(y, t_first, step, t)
    want = np.interp(t, grid, y)
    assert np.isnan(got[-1]) and np.isnan(want[-1])
    np.testing.assert_allclose(got[:-1], want[:-1], rtol=0, atol=1e-9)
    before, after = t[:-1] < grid[0], t[:-1] > grid[-1]
    assert before.any() and after.any()
    assert (got[:-1][before] == y[0]).all() and (got[:-1][after] == y[-1]).all()


def test_importing_the_simulator_does_not_import_numba():
    code = ("import sys; import seanv_analysis.sim, seanv_analysis.sim.scenarios, "
            "seanv_analysis.sim.servo, seanv_analysis.sim.control; "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('numba', 'llvmlite')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.strip()
    assert out == "[]"


def _fresh(monkeypatch, tmp_path):
    monkeypatch.setenv("SEANV_NUMBA_CACHE", str(tmp_path))
    monkeypatch.setattr(compiled, "_loaded", {})
    monkeypatch.setattr(compiled, "_status", None)
    monkeypatch.setattr(compiled, "_module", None)


def test_turned_off_runs_the_jit(monkeypatch, tmp_path):
    from seanv_analysis.sim import kernel

    _fresh(monkeypatch, tmp_path)
    monkeypatch.setenv("SEANV_AOT", "0")
    assert compiled.simulate_kernel().__wrapped__ is kernel.simulate_kernel
    assert "turned off" in compiled.aot_status()
    assert not compiled.aot_module_path().exists()


def test_a_failed_build_is_not_retried_and_the_jit_serves(monkeypatch, tmp_path):
    from seanv_analysis.sim import kernel

    _fresh(monkeypatch, tmp_path)
    monkeypatch.delenv("SEANV_AOT", raising=False)
    path = compiled.aot_module_path()
    assert path.is_relative_to(tmp_path)
    path.parent.mkdir(parents=True)
    (path.parent / "build-failed.txt").write_text("CompileError: no Python.h\n")
    assert compiled.servo_track().__wrapped__ is kernel.servo_track
    status = compiled.aot_status()
    assert "no Python.h" in status and "delete that file to try again" in status
    assert not path.exists()


def test_the_key_follows_the_compiled_sources(monkeypatch):
    before = compiled._key()
    from seanv_analysis.sim import _sources

    monkeypatch.setattr(_sources, "COMPILED_SOURCES", _sources.COMPILED_SOURCES[:-1])
    assert compiled._key() != before
    monkeypatch.setattr(compiled, "SIGNATURES", {"servo_track": "f8(f8)"})
    assert compiled._key() != before


def test_main_builds_or_reports_and_leaves_the_log_level(aot, capsys):
    import logging

    level = logging.getLogger("seanv_analysis.sim.compiled").level
    assert compiled.main() == 0
    assert capsys.readouterr().out.strip() == \
        f"simulator compiled ahead of time: {compiled.aot_module_path()}"
    assert logging.getLogger("seanv_analysis.sim.compiled").level == level


def test_threads_first_calls_load_the_module_once(aot, monkeypatch):
    import threading

    monkeypatch.setattr(compiled, "_loaded", {})
    monkeypatch.setattr(compiled, "_module", None)
    loads = []
    real = compiled._load

    def counted(path):
        loads.append(path)
        return real(path)

    monkeypatch.setattr(compiled, "_load", counted)
    got = []
    threads = [threading.Thread(target=lambda: got.append(compiled.simulate_kernel()))
               for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(got) == 4 and len({id(f) for f in got}) == 1
    compiled.servo_track()
    assert len(loads) == 1


def test_every_source_of_the_compiled_code_keys_the_caches():
    """The caches are keyed by ``COMPILED_SOURCES``: each module of ``sim`` that
    the kernel reaches through its imports, and each file with an ``njit``,
    must be in it (else an edit there would reuse stale machine code)."""
    import ast
    from pathlib import Path

    from seanv_analysis.sim._sources import COMPILED_SOURCES

    pkg = Path(compiled.__file__).resolve().parents[1]
    bookkeeping = {"sim/numba_cache.py", "sim/_sources.py", "sim/compiled.py"}
    reached, todo = set(), ["sim/kernel.py"]
    while todo:
        rel = todo.pop()
        if rel in reached:
            continue
        reached.add(rel)
        for node in ast.walk(ast.parse((pkg / rel).read_text())):
            if isinstance(node, ast.ImportFrom) and node.level == 1:    # from .x import / from . import x
                names = [node.module] if node.module else [a.name for a in node.names]
                todo += [f"sim/{n}.py" for n in names if (pkg / "sim" / f"{n}.py").is_file()]
    assert reached - bookkeeping <= set(COMPILED_SOURCES), reached - bookkeeping - set(COMPILED_SOURCES)
    with_njit = {p.relative_to(pkg).as_posix() for p in pkg.rglob("*.py")
                 if "njit" in p.read_text() and p.parent.name in ("sim", "models")}
    assert with_njit - bookkeeping <= set(COMPILED_SOURCES), with_njit - set(COMPILED_SOURCES)
    assert all((pkg / rel).is_file() for rel in COMPILED_SOURCES)
