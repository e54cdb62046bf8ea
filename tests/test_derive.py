"""Tests of seanv_analysis.signals.derive: velocity, derived samples, per-run flow.

Synthetic flow-step runs are built here with a known true flow: the
actuator velocity follows a chosen profile (ringing step response,
stick-slip, constant, end stop) from a motion start after the cam step, the
position is its integral (20x oversampled), then sampled at 1 kHz, with
Gaussian noise and 0.001 mm encoder quantisation.
"""
from __future__ import annotations

import math
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from numpy.testing import assert_allclose

from seanv_analysis.config import load_rig
from seanv_analysis.errors import ConfigError, DataError
from seanv_analysis.io.run import SUMMARY_COLUMNS, Run, RunMeta
from seanv_analysis.signals.align import align_run
from seanv_analysis.signals.derive import (
    FLOW_METHODS,
    DerivativeInfo,
    FlowEstimate,
    derive_samples,
    estimate_flow,
    step_window,
    summarize_run,
    velocity_mm_s,
)

RIG = load_rig()
AREA = RIG.piston_area_mm2
WINDOW_S = RIG.analysis["derivative_window_s"]
ORDER = RIG.analysis["derivative_polyorder"]
Q_RES_MM = RIG["sensors"]["encoder_resolution_mm"]


# --------------------------------------------------------------------------
# synthetic data
# --------------------------------------------------------------------------

def quantise(x_mm, rng, noise_mm=0.001):
    """Encoder reading: noise, then 0.001 mm quantisation."""
    return np.round((x_mm + rng.normal(0.0, noise_mm, np.size(x_mm))) / Q_RES_MM) * Q_RES_MM


def ringing(v_ss, zeta, fn_hz):
    """Underdamped second-order step response of velocity [mm/s], final value v_ss."""
    wn = 2 * math.pi * fn_hz
    wd = wn * math.sqrt(1 - zeta ** 2)

    def profile(s):
        s = np.maximum(s, 0.0)
        return v_ss * (1 - np.exp(-zeta * wn * s) * (np.cos(wd * s)
                                                      + zeta / math.sqrt(1 - zeta ** 2)
                                                      * np.sin(wd * s)))
    return profile


def stick_slip(v_mean, t_stick, t_slip):
    """Stuck for t_stick, then a half-sine slip of t_slip; mean velocity v_mean [mm/s]."""
    period = t_stick + t_slip
    v_pk = math.pi / 2 * v_mean * period / t_slip

    def profile(s):
        phase = np.mod(np.maximum(s, 0.0), period)
        return np.where((s > 0) & (phase >= t_stick),
                        v_pk * np.sin(math.pi * (phase - t_stick) / t_slip), 0.0)
    return profile


def constant(v):
    return lambda s: np.where(s > 0, v, 0.0)


def make_run(profile, *, side="supply", cam_deg=-8.0, cam_start=-15.0, duration_s=2.0,
             x0=10.0, t_step=0.2, delay_s=0.08, p_head_ss=1.6, p_head_gain=0.0,
             load_mpag=0.4, meta_load=True, seed=0, feedback=True, servo=None,
             p_tank=False):
    """A flow-step Run with velocity ``profile(t - t_step - delay_s)`` [mm/s].

    Travel is clipped to [0, stroke] (end stops); at a stop the head pressure
    goes to supply (supply side) or tank (drain side). Otherwise p_head =
    p_head_ss + p_head_gain (v - v_final): dp during steady motion is
    3.3 - p_head_ss (supply) or p_head_ss (drain).
    """
    rng = np.random.default_rng(seed)
    stroke = RIG["actuator"]["stroke_mm"]
    rate, sub = 1000.0, 20
    tf = np.arange(int(round(duration_s * rate * sub)) + 1) / (rate * sub)
    vf = profile(tf - t_step - delay_s)
    xf = x0 + np.concatenate(([0.0], np.cumsum(0.5 * (vf[1:] + vf[:-1]) * np.diff(tf))))
    xc = np.clip(xf, 0.0, stroke)
    t, x, v, stopped = tf[::sub], xc[::sub], vf[::sub], (xc != xf)[::sub]
    v_final = float(profile(np.array([1e3]))[0])
    noise = rng.normal(0.0, 0.005, (2, t.size))
    ph = p_head_ss + p_head_gain * (v - v_final) + noise[1]
    ph = np.where(stopped, 3.3 if side == "supply" else 0.0, ph)
    pressure = pd.DataFrame({"t_s": t, "p_supply_mpag": 3.3 + noise[0], "p_head_mpag": ph,
                             "p_load_mpag": load_mpag + rng.normal(0, 0.002, t.size)})
    if p_tank:
        pressure["p_tank_mpag"] = 0.05
    ts = 0.002 + np.arange(int(duration_s * 100)) / 100.0
    if servo is None:
        cmd = np.where(ts < t_step, cam_start, cam_deg)
        fb = np.where(ts < t_step, cam_start,
                      cam_deg + (cam_start - cam_deg) * np.exp(-(ts - t_step) / 0.06))
        fb = fb + rng.normal(0.0, 0.02, ts.size) if feedback else np.full(ts.size, np.nan)
        servo = pd.DataFrame({"t_s": ts, "cam_cmd_deg": cmd, "cam_deg": fb})
    tables = {"encoder": pd.DataFrame({"t_s": t, "position_mm": quantise(x, rng)}),
              "pressure": pressure, "servo": servo}
    meta = RunMeta(run_id=f"{side}-cam{cam_deg}", kind="flow_step",
                   started_at=datetime(2026, 3, 2, 10, 14, 5, tzinfo=timezone.utc),
                   path=Path("/nonexistent/run"), load_mpag=load_mpag if meta_load else None,
                   side=side, cam_deg=cam_deg)
    return Run(meta=meta, tables=tables, rig=RIG)


# --------------------------------------------------------------------------
# velocity_mm_s
# --------------------------------------------------------------------------

@pytest.mark.parametrize("rate_hz, expected", [(1000.0, 51), (500.0, 25), (2000.0, 103),
                                               (100.0, 5), (50.0, 5)])
def test_window_samples_odd_from_rate(rate_hz, expected):
    t = np.arange(400) / rate_hz
    v, info = velocity_mm_s(t, 2.0 * t, window_s=WINDOW_S, polyorder=ORDER)
    assert isinstance(info, DerivativeInfo)
    assert info.window_samples == expected and expected % 2 == 1
    assert info.window_samples >= ORDER + 2
    assert_allclose(info.window_s, expected / rate_hz)
    assert_allclose(info.edge_s, (expected // 2) / rate_hz)
    assert_allclose(info.valid_start_s, t[expected // 2])
    assert_allclose(info.valid_end_s, t[-1 - expected // 2])
    assert not info.resampled
    assert_allclose(v, 2.0, rtol=1e-9)  # linear motion is exact, edges included
    assert "51 samples" in velocity_mm_s(np.arange(200) / 1e3, np.zeros(200), window_s=WINDOW_S,
                                         polyorder=ORDER)[1].report()


@pytest.mark.parametrize("v_true", [1.0, 10.0, -25.0, 50.0])
def test_constant_velocity_within_1pct_after_edge(v_true):
    rng = np.random.default_rng(1)
    t = np.arange(3000) / 1000.0
    x = quantise(20.0 + v_true * t, rng)
    v, info = velocity_mm_s(t, x, window_s=WINDOW_S, polyorder=ORDER)
    inner = (t >= info.valid_start_s) & (t <= info.valid_end_s)
    # noise floor of a centred LS slope: sigma_x / (dt sqrt(sum k^2)), ~0.01 mm/s here
    k = np.arange(info.window_samples) - info.window_samples // 2
    sigma_v = math.hypot(0.001, Q_RES_MM / math.sqrt(12)) / (info.dt_s * math.sqrt(np.sum(k ** 2)))
    assert np.max(np.abs(v[inner] - v_true)) <= max(0.01 * abs(v_true), 5 * sigma_v)
    if abs(v_true) >= 5.0:  # >= 1000 mm^3/s: every sample within 1 %
        assert np.max(np.abs(v[inner] - v_true)) <= 0.01 * abs(v_true)
    assert abs(np.mean(v[inner]) - v_true) <= 0.01 * abs(v_true)
    # edges: off-centre fit, noisier but unbiased for linear motion
    assert abs(np.mean(v[~inner]) - v_true) <= 0.01 * abs(v_true)


def test_sine_within_1pct_of_amplitude_after_edge():
    rng = np.random.default_rng(2)
    t = np.arange(4000) / 1000.0
    amp_mm, f_hz = 5.0, 1.0
    x = quantise(30.0 + amp_mm * np.sin(2 * np.pi * f_hz * t), rng)
    v_exact = 2 * np.pi * f_hz * amp_mm * np.cos(2 * np.pi * f_hz * t)
    v, info = velocity_mm_s(t, x, window_s=WINDOW_S, polyorder=ORDER)
    inner = (t >= info.valid_start_s) & (t <= info.valid_end_s)
    v_amp = 2 * np.pi * f_hz * amp_mm
    err = np.abs(v - v_exact) / v_amp
    assert err[inner].max() <= 0.01
    # where |v| is large the relative error itself is within 1 %
    big = inner & (np.abs(v_exact) > 0.5 * v_amp)
    assert np.max(np.abs(v[big] / v_exact[big] - 1)) <= 0.01
    # edges (25 ms each end): off-centre quadratic fit, larger but bounded error
    assert err[~inner].max() <= 0.05


def test_matches_independent_local_polyfit():
    rng = np.random.default_rng(3)
    t = np.arange(500) / 1000.0
    x = np.cumsum(rng.normal(0, 0.01, t.size))
    v, info = velocity_mm_s(t, x, window_s=WINDOW_S, polyorder=ORDER)
    n, h = info.window_samples, info.window_samples // 2
    for i in (h, 100, 250, t.size - 1 - h):
        c = np.polyfit(t[i - h:i + h + 1] - t[i], x[i - h:i + h + 1], ORDER)
        assert_allclose(v[i], c[-2], rtol=1e-7, atol=1e-9)
    # edge samples: derivative of the polynomial fitted to the first/last window
    for i in (0, 7, h - 1):
        c = np.polyfit(t[:n] - t[i], x[:n], ORDER)
        assert_allclose(v[i], c[-2], rtol=1e-7, atol=1e-9)
    for i in (t.size - 1, t.size - h):
        c = np.polyfit(t[-n:] - t[i], x[-n:], ORDER)
        assert_allclose(v[i], c[-2], rtol=1e-7, atol=1e-9)


def test_jittered_timestamps_are_resampled():
    rng = np.random.default_rng(4)
    t = np.arange(3000) / 1000.0 + rng.uniform(-3e-4, 3e-4, 3000)
    amp_mm, f_hz = 5.0, 1.0
    x = quantise(30.0 + amp_mm * np.sin(2 * np.pi * f_hz * t), rng)
    v, info = velocity_mm_s(t, x, window_s=WINDOW_S, polyorder=ORDER)
    assert info.resampled and info.jitter > 0.1
    assert info.window_samples == 51
    v_exact = 2 * np.pi * f_hz * amp_mm * np.cos(2 * np.pi * f_hz * t)
    inner = (t >= info.valid_start_s) & (t <= info.valid_end_s)
    assert np.max(np.abs(v - v_exact)[inner]) <= 0.01 * 2 * np.pi * f_hz * amp_mm


def test_dropped_samples_are_resampled():
    rng = np.random.default_rng(5)
    t = np.delete(np.arange(2000) / 1000.0, np.arange(900, 910))
    x = quantise(5.0 + 12.0 * t, rng)
    v, info = velocity_mm_s(t, x, window_s=WINDOW_S, polyorder=ORDER)
    assert info.resampled
    assert_allclose(info.dt_s, 1e-3)
    inner = (t >= info.valid_start_s) & (t <= info.valid_end_s)
    assert np.max(np.abs(v[inner] - 12.0)) <= 0.12


def test_small_jitter_is_uniform():
    t = np.arange(1000) / 1000.0 + np.random.default_rng(6).uniform(-1e-6, 1e-6, 1000)
    assert not velocity_mm_s(t, t, window_s=WINDOW_S, polyorder=ORDER)[1].resampled


@pytest.mark.parametrize("t, x, kwargs, match", [
    (np.arange(30) / 1e3, np.zeros(30), {}, "fewer than the 51-sample derivative window"),
    (np.array([0.0, 0.001, 0.001, 0.003]), np.zeros(4), {}, "strictly increasing"),
    (np.arange(100) / 1e3, np.r_[np.zeros(99), np.nan], {}, "position_mm.*index 99"),
    (np.arange(100) / 1e3, np.zeros(99), {}, "expected equal lengths"),
    (np.arange(100) / 1e3, np.zeros(100), {"window_s": 0.0}, "window_s: expected a positive"),
    (np.arange(100) / 1e3, np.zeros(100), {"polyorder": 0}, "polyorder: expected an integer"),
])
def test_velocity_errors(t, x, kwargs, match):
    opts = {"window_s": WINDOW_S, "polyorder": ORDER, **kwargs}
    err = ConfigError if ("window_s" in kwargs or "polyorder" in kwargs) else DataError
    with pytest.raises(err, match=match):
        velocity_mm_s(t, x, **opts)


# --------------------------------------------------------------------------
# derive_samples
# --------------------------------------------------------------------------

def test_derive_samples_columns_and_values():
    run = make_run(constant(2000.0 / AREA))
    d = derive_samples(run)
    for col in ("velocity_mm_s", "q_mm3_s", "dp_supply_mpa", "dp_drain_mpa", "position_mm",
                "cam_cmd_deg"):
        assert col in d
    assert_allclose(d["q_mm3_s"], d["velocity_mm_s"] * AREA)
    assert_allclose(d["dp_supply_mpa"], d["p_supply_mpag"] - d["p_head_mpag"])
    assert_allclose(d["dp_drain_mpa"], d["p_head_mpag"] - RIG["supply"]["tank_pressure_mpag"])
    assert d.attrs["velocity"]["window_samples"] == 51
    enc = run.tables["encoder"]
    v_enc, _ = velocity_mm_s(enc["t_s"], enc["position_mm"], window_s=WINDOW_S, polyorder=ORDER)
    assert_allclose(d["velocity_mm_s"], np.interp(d["t_s"], enc["t_s"], v_enc))
    late = d["t_s"] > 0.6
    assert_allclose(d.loc[late, "q_mm3_s"].mean(), 2000.0, rtol=0.01)


def test_derive_samples_tank_column_and_aligned_argument():
    run = make_run(constant(5.0), p_tank=True)
    aligned = align_run(run).iloc[100:900].reset_index(drop=True)
    d = derive_samples(run, aligned=aligned)
    assert len(d) == 800 and d["t_s"].iloc[0] == aligned["t_s"].iloc[0]
    assert_allclose(d["dp_drain_mpa"], d["p_head_mpag"] - 0.05)
    d2 = derive_samples(run, window_s=0.101, polyorder=3)
    assert d2.attrs["velocity"]["window_samples"] == 101
    assert d2.attrs["velocity"]["polyorder"] == 3


def test_derive_samples_missing_column():
    run = make_run(constant(5.0))
    with pytest.raises(DataError, match="p_head_mpag"):
        derive_samples(run, aligned=align_run(run).drop(columns="p_head_mpag"))


# --------------------------------------------------------------------------
# per-run flow: steady vs peak on cases with a known true flow
# --------------------------------------------------------------------------

# name: (run kwargs, true flow [mm^3/s], true dp [MPa], steady rtol, peak |bias| at least)
CASES = {
    "ringing": (dict(profile=ringing(3000.0 / AREA, 0.3, 6.0), p_head_gain=0.05),
                3000.0, 1.7, 0.01, 0.25),
    "stick_slip_drain": (dict(profile=stick_slip(-300.0 / AREA, 0.15, 0.05), side="drain",
                              cam_deg=-30.0, duration_s=3.0, x0=60.0), -300.0, 1.6, 0.02, 2.0),
    "end_stop_supply": (dict(profile=ringing(8000.0 / AREA, 0.5, 6.0), duration_s=3.0),
                        8000.0, 1.7, 0.01, 0.1),
    "end_stop_drain": (dict(profile=ringing(-6000.0 / AREA, 0.5, 6.0), side="drain",
                            cam_deg=-30.0, duration_s=3.0, x0=60.0), -6000.0, 1.6, 0.01, 0.1),
}


@pytest.mark.parametrize("name", list(CASES))
def test_steady_unbiased_peak_biased(name):
    kwargs, q_true, dp_true, rtol, peak_bias = CASES[name]
    run = make_run(**kwargs)
    d = derive_samples(run)
    steady = estimate_flow(run, method="steady", derived=d)
    peak = estimate_flow(run, method="peak", derived=d)
    assert isinstance(steady, FlowEstimate) and steady.success and steady.moving
    assert_allclose(steady.q_mm3_s, q_true, rtol=rtol)
    assert_allclose(steady.dp_mpa, dp_true, atol=0.01)
    # the paper's peak picks the overshoot / slip burst: |Q| too large
    assert peak.q_mm3_s / q_true - 1 >= peak_bias
    assert steady.report().startswith("steady: Q =")


def test_end_stop_window_excludes_stall():
    run = make_run(ringing(8000.0 / AREA, 0.5, 6.0), duration_s=3.0)
    est = estimate_flow(run)
    enc = run.tables["encoder"]
    t_impact = enc["t_s"][enc["position_mm"] >= 75.0 - 2 * Q_RES_MM].iloc[0]
    # the velocity at the window's end comes from samples before the impact only
    assert est.t_end_s + WINDOW_S / 2 <= t_impact + 1e-3
    assert est.t_end_s > t_impact - 0.1
    assert "stall" in est.message and est.steady
    assert_allclose(est.p1_mpa, 3.3, atol=0.005)


def test_stick_slip_uses_whole_cycles():
    run = make_run(stick_slip(-300.0 / AREA, 0.15, 0.05), side="drain", cam_deg=-30.0,
                   duration_s=3.0, x0=60.0)
    est = estimate_flow(run)
    assert not est.steady and "stick-slip" in est.message
    # median velocity would say 0: the actuator is stuck 75 % of the time
    d = derive_samples(run)
    w = (d["t_s"] >= est.t_start_s) & (d["t_s"] <= est.t_end_s)
    assert abs(np.median(d.loc[w, "velocity_mm_s"])) < 0.1 * abs(est.velocity_mm_s)


def test_ringing_pressure_at_peak_is_biased_too():
    run = make_run(ringing(3000.0 / AREA, 0.3, 6.0), p_head_gain=0.05)
    peak = estimate_flow(run, method="peak")
    assert peak.dp_mpa < 1.7 - 0.1  # head pressure high during the overshoot


@pytest.mark.parametrize("q_leak", [0.0, 20.0, -30.0])
def test_not_moving_gives_mean_leakage(q_leak):
    run = make_run(constant(q_leak / AREA), seed=7)
    est = estimate_flow(run)
    assert not est.moving and "did not move" in est.message
    assert abs(est.q_mm3_s - q_leak) <= 3.0
    assert_allclose(est.dp_mpa, 1.7, atol=0.005)


def test_constant_motion_both_methods_agree():
    run = make_run(constant(2000.0 / AREA))
    row = summarize_run(run)
    assert_allclose(row["q_steady_mm3_s"], 2000.0, rtol=0.005)
    assert_allclose(row["q_peak_mm3_s"], 2000.0, rtol=0.01)


def test_unsettled_motion_is_flagged():
    def slow(s):
        return np.where(s > 0, 3000.0 / AREA * (1 - np.exp(-np.maximum(s, 0) / 0.5)), 0.0)
    est = estimate_flow(make_run(slow))
    assert not est.steady and "did not settle" in est.message


def test_estimate_flow_errors():
    run = make_run(constant(5.0))
    with pytest.raises(ConfigError, match="method: expected one of steady, peak"):
        estimate_flow(run, method="mean")
    pc = Run(meta=RunMeta("p", "position_control", run.meta.started_at, run.meta.path),
             tables=run.tables, rig=RIG)
    with pytest.raises(DataError, match="expected a flow_step run"):
        estimate_flow(pc)


# --------------------------------------------------------------------------
# step window and summary row
# --------------------------------------------------------------------------

@pytest.mark.parametrize("cam_start, cam_deg, approach", [(-15.0, -8.0, 1.0),
                                                          (-15.0, -30.0, -1.0),
                                                          (-8.0, -8.0, 0.0)])
def test_step_window_approach_and_measured(cam_start, cam_deg, approach):
    run = make_run(constant(5.0), cam_start=cam_start, cam_deg=cam_deg)
    step = step_window(run)
    assert step.cam_approach == approach
    assert_allclose(step.cam_measured_deg, cam_deg, atol=0.02)
    assert step.settled_from_feedback
    if approach:
        assert_allclose(step.t_start_s, 0.202)
        assert 0.3 < step.t_settled_s < 0.5  # servo time constant 0.06 s, 7 deg or more
    assert step.t_end_s == pytest.approx(2.0)


def test_step_window_command_overshoot_gives_last_approach():
    ts = 0.002 + np.arange(200) / 100.0
    cmd = np.where(ts < 0.2, -15.0, np.where(ts < 0.3, 0.0, -8.0))
    servo = pd.DataFrame({"t_s": ts, "cam_cmd_deg": cmd, "cam_deg": cmd})
    step = step_window(make_run(constant(5.0), servo=servo))
    assert step.cam_approach == -1.0 and step.t_start_s == pytest.approx(0.302)


def test_step_window_without_feedback_uses_servo_model():
    run = make_run(constant(5.0), feedback=False)
    step = step_window(run)
    srv = RIG["servo"]
    expected = 0.202 + srv["dead_time_s"] + 7.0 / srv["max_rate_deg_s"] + 5 * srv["time_constant_s"]
    assert not step.settled_from_feedback and math.isnan(step.cam_measured_deg)
    assert_allclose(step.t_settled_s, expected)
    assert_allclose(estimate_flow(run).q_mm3_s, 5.0 * AREA, rtol=0.01)


def test_step_window_no_matching_command():
    run = make_run(constant(5.0))
    run.tables["servo"]["cam_cmd_deg"] = -15.0
    with pytest.raises(DataError, match="no command within 0.0879 deg of run.json cam_deg -8.0"):
        step_window(run)


def test_summarize_run_row():
    run = make_run(ringing(3000.0 / AREA, 0.3, 6.0))
    row = summarize_run(run)
    assert set(row) == set(SUMMARY_COLUMNS) - {"run_index", "excluded", "excluded_detail"}
    assert row["flow_method"] == "steady" and row["q_mm3_s"] == row["q_steady_mm3_s"]
    assert row["side"] == "supply" and row["cam_deg"] == -8.0 and row["cam_approach"] == 1.0
    assert row["load_mpag"] == 0.4
    assert_allclose(row["p1_mpa"], 3.3, atol=0.005)
    assert row["started_at"] == pd.Timestamp("2026-03-02T10:14:05Z")
    peak = summarize_run(run, method="peak")
    assert peak["flow_method"] == "peak" and peak["q_mm3_s"] == peak["q_peak_mm3_s"]
    assert peak["q_peak_mm3_s"] == row["q_peak_mm3_s"]
    with pytest.raises(ConfigError, match="method"):
        summarize_run(run, method="max")
    assert set(FLOW_METHODS) == {"steady", "peak"}


def test_summarize_run_load_from_pressure_when_null():
    run = make_run(constant(5.0), load_mpag=0.25, meta_load=False)
    assert_allclose(summarize_run(run)["load_mpag"], 0.25, atol=0.001)


def test_summarize_position_control_has_nan_flows(tmp_path, make_run):
    from seanv_analysis.io.reader import read_run
    run = read_run(make_run(tmp_path, "position_control", meta={"load_mpag": None}))
    row = summarize_run(run)
    assert row["kind"] == "position_control" and row["side"] == "" and row["flow_method"] == ""
    for col in ("q_mm3_s", "q_peak_mm3_s", "q_steady_mm3_s", "dp_mpa", "p1_mpa", "cam_deg"):
        assert math.isnan(row[col])
    assert_allclose(row["load_mpag"], 0.35, atol=0.002)


@pytest.mark.parametrize("side, cam", [("supply", -8.0), ("drain", -30.0)])
def test_summarize_run_from_reader(tmp_path, make_run, side, cam):
    from seanv_analysis.io.reader import read_run
    run = read_run(make_run(tmp_path, side=side, cam_deg=cam, seed=3))
    samples = derive_samples(run)
    row = summarize_run(run, derived=samples)
    q = 2000.0 if side == "supply" else -2000.0
    assert_allclose(row["q_steady_mm3_s"], q, rtol=0.01)
    assert row["cam_approach"] == (1.0 if side == "supply" else -1.0)
    assert_allclose(row["cam_measured_deg"], cam, atol=0.05)


def test_derivative_beside_alignment_gives_the_same_frame(monkeypatch):
    """Long records compute the derivative on a helper thread while the
    streams are aligned: the frame is identical to the serial one."""
    import seanv_analysis.signals.derive as derive_mod

    run = make_run(constant(2000.0 / AREA))
    monkeypatch.setattr(derive_mod, "_OVERLAP_MIN_SAMPLES", 10**9)
    serial = derive_samples(run)
    monkeypatch.setattr(derive_mod, "_OVERLAP_MIN_SAMPLES", 0)
    beside = derive_samples(run)
    pd.testing.assert_frame_equal(beside, serial, check_exact=True)
    assert beside.attrs == serial.attrs


def test_derivative_beside_alignment_keeps_the_alignment_error_first(monkeypatch):
    import seanv_analysis.signals.derive as derive_mod

    run = make_run(constant(5.0))
    late = run.tables["pressure"].assign(t_s=run.tables["pressure"]["t_s"] + 100.0)
    bad = type(run)(meta=run.meta, tables={**run.tables, "pressure": late}, rig=run.rig,
                    files=run.files, file_sha256=run.file_sha256)
    monkeypatch.setattr(derive_mod, "_OVERLAP_MIN_SAMPLES", 0)
    with pytest.raises(DataError, match="do not overlap"):
        derive_samples(bad)
