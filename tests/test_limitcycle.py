"""Sustained oscillations (``analysis.limitcycle``) and how ``validate``
judges a run that hunts: by the limit cycle's statistics, not its phase."""
from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
from conftest import write_synthetic_run

from seanv_analysis import ValveModel
from seanv_analysis.analysis.limitcycle import LimitCycle, compare_limit_cycles, limit_cycle
from seanv_analysis.analysis.validate import validate_run
from seanv_analysis.io import read_run

T = np.arange(0.0, 30.0, 0.001)
REF_T, REF = np.array([0.0, 10.0, 20.0]), np.array([0.0, 4.0, 1.0])


def _ref(t):
    return REF[np.searchsorted(REF_T, t, side="right") - 1]


def _hunting(t, *, amp=2.0, period=0.8, phase=0.0, offset=0.0):
    """Each reference reached in 0.3 s, then a sustained oscillation about it."""
    k = np.searchsorted(REF_T, t, side="right") - 1
    tau = t - REF_T[k]
    prev = np.r_[0.0, REF[:-1]][k]
    return (REF[k] + (prev - REF[k]) * np.exp(-tau / 0.1) + offset
            + amp * np.sin(2 * np.pi * tau / period + phase) * (1 - np.exp(-tau / 0.3)))


def test_statistics_of_a_sustained_oscillation():
    x = _hunting(T, amp=2.0, period=0.8, offset=-0.3)
    lc = limit_cycle(T, x, REF_T, REF, band_mm=0.5)
    assert lc.present and len(lc.windows_s) == 3
    assert lc.amplitude_mm == pytest.approx(2.0, rel=0.01)
    assert lc.period_s == pytest.approx(0.8, rel=0.01)
    assert lc.mean_error_mm == pytest.approx(0.3, abs=0.05)   # e = x_ref - x
    assert lc.duration_s == pytest.approx(26.0, abs=1.5) and lc.n_cycles > 30


@pytest.mark.parametrize("shape", ["decaying", "one overshoot", "dies out", "noise"])
def test_no_limit_cycle(shape):
    """A decaying oscillation, a step's overshoot, hunting that stops before
    the reference changes, or sensor noise is not a limit cycle."""
    k = np.searchsorted(REF_T, T, side="right") - 1
    tau = T - REF_T[k]
    prev = np.r_[0.0, REF[:-1]][k]
    rng = np.random.default_rng(0)
    x = {"decaying": REF[k] + (prev - REF[k]) * np.exp(-tau / 0.8) * np.cos(2 * np.pi * tau / 0.8),
         "one overshoot": REF[k] + (prev - REF[k]) * np.exp(-tau / 0.2) * np.cos(2 * np.pi * tau / 2.0),
         "dies out": _hunting(T) * (tau < 4.0) + REF[k] * (tau >= 4.0),
         "noise": _ref(T) + 0.2 * (tau > 0.5) + rng.normal(0.0, 0.01, T.size)}[shape]
    assert not limit_cycle(T, x, REF_T, REF, band_mm=0.5).present


def test_compare():
    m = LimitCycle(True, 2.0, 0.8, 0.1)
    assert compare_limit_cycles(m, LimitCycle(True, 2.3, 0.9, -0.2)) == "agrees"
    assert compare_limit_cycles(m, LimitCycle(True, 2.5, 0.8, 0.1)) == "differs"
    assert compare_limit_cycles(m, LimitCycle(True, 2.0, 0.6, 0.1)) == "differs"
    assert compare_limit_cycles(m, LimitCycle(True, 2.0, 0.8, 0.6)) == "differs"   # mean error
    assert compare_limit_cycles(m, LimitCycle(False)) == "measured only"
    assert compare_limit_cycles(LimitCycle(False), m) == "simulated only"
    assert compare_limit_cycles(LimitCycle(False), LimitCycle(False)) == "none"


def _run(root, run_id, x_fn):
    t_enc = np.arange(0.0, 30.0, 0.001)
    t_c = t_enc[::10]
    x = np.round(x_fn(t_enc), 3)
    e_c = _ref(t_c) - x[::10]
    cmd = np.clip(-15.0 + 15.0 * e_c, -40.0, 10.0)
    tables = {"encoder": pd.DataFrame({"t_s": t_enc, "position_mm": x}),
              "pressure": pd.DataFrame({"t_s": t_enc, "p_supply_mpag": 3.3, "p_head_mpag": 1.6,
                                        "p_load_mpag": 0.35}),
              "servo": pd.DataFrame({"t_s": t_c, "cam_cmd_deg": cmd, "cam_deg": cmd}),
              "controller": pd.DataFrame({"t_s": t_c, "x_ref_mm": _ref(t_c),
                                          "q_ref_mm3_s": np.nan})}
    return write_synthetic_run(root, "position_control", run_id=run_id, tables=tables,
                               controller={"kp": 15.0, "flow_model": False, "rate_hz": 100.0},
                               load_mpag=0.35)


@pytest.mark.parametrize("twin, status, flagged", [
    (dict(amp=2.2, period=0.85, phase=3.0), "agrees", False),     # low fit, same limit cycle
    (dict(amp=3.0, period=0.85, phase=3.0), "differs", True),
    (dict(amp=0.0), "measured only", True)])
def test_validate_judges_a_hunting_run_by_its_limit_cycle(tmp_path, rig, twin, status, flagged):
    """The twin's record stands in for the simulation: a limit cycle in
    another phase fits badly (< 80 %) yet agrees and is not flagged; another
    amplitude, or no oscillation, is flagged."""
    measured = read_run(_run(tmp_path, "rig", _hunting), rig=rig)
    sim = read_run(_run(tmp_path, "twin", lambda t: _hunting(t, **twin)), rig=rig)
    rv = validate_run(measured, ValveModel.from_rig(rig), rig=rig,
                      simulate=lambda *a, **k: sim)
    row = rv.row
    assert row["fit_position_pct"] < 80.0
    assert row["limit_cycle"] == status and row["flagged"] is flagged
    assert row["limit_cycle_amplitude_measured_mm"] == pytest.approx(2.0, rel=0.02)
    assert row["limit_cycle_period_measured_s"] == pytest.approx(0.8, rel=0.02)
    if status == "measured only":
        assert math.isnan(row["limit_cycle_amplitude_simulated_mm"])
        assert row["limit_cycle_duration_simulated_s"] == 0.0
