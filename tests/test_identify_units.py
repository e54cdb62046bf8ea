"""The parts of ``identify`` on signals with known truth (no simulator data set).

Each truth here is chosen unlike data_schema/rig/default.toml, so a fit that
returned the rig file's value would fail.
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from seanv_analysis import ValveModel, load_rig
from seanv_analysis.identify.friction import fit_friction
from seanv_analysis.identify.geometry import fit_geometry
from seanv_analysis.identify.servo import ServoData, fit_servo
from seanv_analysis.sim.servo import servo_response

RIG = load_rig()


def test_servo_response_is_the_rate_limited_lag():
    """A 30 deg step, rate 200 deg/s, tau 0.05 s, dead 0.04 s: a ramp at the
    rate limit until the error is rate x tau = 10 deg, then exponential."""
    t = np.arange(0.0, 0.6, 0.001)
    y = servo_response([0.0, 0.1], [0.0, 30.0], t, dead_time_s=0.04, time_constant_s=0.05,
                       max_rate_deg_s=200.0)
    assert np.all(y[t < 0.14 - 1e-9] == 0.0)
    t_switch = 0.14 + 20.0 / 200.0                     # ramp of 20 deg
    on_ramp = (t > 0.145) & (t < t_switch - 0.005)
    assert np.allclose(y[on_ramp], 200.0 * (t[on_ramp] - 0.14), atol=0.11)
    tail = t > t_switch + 0.005
    expect = 30.0 - 10.0 * np.exp(-(t[tail] - t_switch) / 0.05)
    assert np.allclose(y[tail], expect, atol=0.11)


def _servo_log(seed, dead, tau, rate, *, n_steps=12):
    """Logged command (100 Hz, random steps and ramps) and quantised feedback."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 1.5 * n_steps, 0.01)
    cmd = np.zeros_like(t)
    for k in range(n_steps):
        m = t >= 1.5 * k
        cmd[m] = rng.uniform(-40, 10)
    fb = servo_response(t, cmd, t, dead_time_s=dead, time_constant_s=tau, max_rate_deg_s=rate,
                        theta0_deg=cmd[0])
    step = 360 / 4096
    fb = np.round(fb / step) * step + step * rng.choice([-1, 0, 0, 0, 1], t.size)
    return ServoData("s", t, cmd, t, fb, "synchronous with the controller log")


def test_fit_servo_recovers_dead_time_lag_and_rate():
    truth = (0.05, 0.03, 180.0)
    data = [_servo_log(s, *truth) for s in range(2)]
    f = fit_servo(data, start=(0.03, 0.07, 240.0), resolution_deg=0.0879)
    assert f.dead_time_s == pytest.approx(truth[0], abs=0.002)
    assert f.time_constant_s == pytest.approx(truth[1], rel=0.1)
    assert f.rate_identified and f.max_rate_deg_s == pytest.approx(truth[2], rel=0.05)
    assert f.dead_ci95[0] <= truth[0] <= f.dead_ci95[1]


def test_fit_servo_leaves_the_rate_when_it_is_never_reached():
    """Small steps only: the rate limit is never hit, so it is not identified."""
    rng = np.random.default_rng(1)
    t = np.arange(0.0, 20.0, 0.01)
    cmd = np.repeat(rng.uniform(-12, -10, 20), t.size // 20)
    fb = servo_response(t, cmd, t, dead_time_s=0.02, time_constant_s=0.05, max_rate_deg_s=300.0)
    f = fit_servo([ServoData("s", t, cmd, t, fb, "")], start=(0.03, 0.07, 240.0),
                  resolution_deg=0.0879)
    assert not f.rate_identified and "rate limit" in f.rate_note
    assert f.time_constant_s == pytest.approx(0.05, rel=0.05)


def test_fit_friction_recovers_coulomb_and_viscous():
    rng = np.random.default_rng(0)
    v = np.concatenate([rng.uniform(2, 40, 30), -rng.uniform(2, 30, 30)])
    f = 42.0 * np.sign(v) + 0.7 * v + rng.normal(0, 1.5, v.size)
    fr = fit_friction(v, f)
    assert fr["coulomb_n"] == pytest.approx(42.0, rel=0.03)
    assert fr["viscous_n_s_per_mm"] == pytest.approx(0.7, rel=0.1)
    lo, hi = fr["coulomb_ci95"]
    assert lo <= 42.0 <= hi


def _flow_steps(side_true, loads, seed=0, rel_noise=0.02):
    """Per-run (theta, p1, dp, q, load) of flow steps of one side."""
    rng = np.random.default_rng(seed)
    rows = []
    cams = np.arange(-6.0, 10.1, 2.0) if side_true.side == "supply" else np.arange(-40.0, -19.0, 2.5)
    for load in loads:
        for cam in cams:
            for _ in range(2):
                ph = 4.0 * load + (0.4 if side_true.side == "supply" else -0.4) + rng.normal(0, 0.02)
                p1, dp = (3.0, 3.0 - ph) if side_true.side == "supply" else (ph, ph)
                q = float(side_true.flow(cam, p1, dp))
                if abs(q) < 60:
                    continue
                rows.append((cam, p1, dp, q * (1 + rng.normal(0, rel_noise)), load))
    return np.array(rows).T


@pytest.mark.parametrize("side,x_c,y_c", [("supply", -4.0, -24.0), ("drain", -12.0, 17.0)])
def test_geometry_reproduces_a_foreign_threshold(side, x_c, y_c):
    """A needle centre unlike the rig file's (x_c and y_c both differ): the
    fitted one-parameter form gives the threshold within 0.15 deg over the
    tested pressures, where the rig file's geometry is > 0.3 deg off."""
    base = ValveModel.from_rig(RIG).side(side)
    geom = replace(base.geometry, needle_x_c_mm=x_c, needle_y_c_mm=y_c)
    true = replace(base, z0_mm=base.z0_mm + 0.03, c_flow=base.c_flow * 0.85, geometry=geom)
    theta, p1, dp, q, load = _flow_steps(true, (0.1, 0.25, 0.4, 0.55))
    sigma = 0.02 * np.abs(q) + 5.0
    g = fit_geometry(base, theta, p1, dp, q, sigma, load, z0_start_mm=base.z0_mm,
                     c_start=base.c_flow)
    assert g.identified, g.note
    fitted = replace(base, z0_mm=g.z0_mm, c_flow=g.c_flow,
                     geometry=replace(base.geometry, needle_y_c_mm=g.y_c_mm))
    err = np.abs(fitted.threshold_deg(p1, dp) - true.threshold_deg(p1, dp))
    assert err.max() < 0.15
    assert g.c_flow == pytest.approx(true.c_flow, rel=0.03)
    # better than the rig file's geometry with its own best z0 and C
    assert g.rmse_mm3_s < g.rmse_default_mm3_s


def test_geometry_fit_jacobian_is_the_derivative_of_its_residual():
    """The geometry fit's Jacobian (eq. 5's analytic z0 and C columns per
    side, a forward difference in y_c, -dp_leak / sigma for g, the prior's
    row) against central differences of the fit's residual, both sides
    with y_c free and the leakage fitted."""
    from seanv_analysis.fit import SideRuns
    from seanv_analysis.identify import geometry

    model = ValveModel.from_rig(RIG)
    runs = {}
    for name, load in (("supply", (0.1, 0.3, 0.5)), ("drain", (0.2, 0.4))):
        side = model.side(name)
        theta, p1, dp, q, lv = _flow_steps(side, load)
        runs[name] = SideRuns(side, theta, p1, dp, q, 0.02 * np.abs(q) + 5.0,
                              np.linspace(-1.0, 2.0, q.size), load_level=lv)
    layout = geometry._Layout(list(runs), ("supply", "drain"), True)
    y_fixed = {n: float(r.side.geometry.needle_y_c_mm) for n, r in runs.items()}
    x = np.array([v for n, r in runs.items()
                  for v in (r.side.z0_mm + 0.01, r.side.c_flow * 1.05, y_fixed[n] * 1.02)] + [2.0])
    hi = np.full(x.size, np.inf)
    g_fixed, sd = 3.0, 1.5

    def resid(p):
        g = layout.leak(p, g_fixed)
        return np.concatenate([geometry._side_resid(runs[n], layout.side_x(p, n, y_fixed[n]), g)
                               for n in layout.names] + [[(g - g_fixed) / sd]])

    got = geometry._jacobian(runs, layout, x, y_fixed, g_fixed, hi, True, sd)
    h = 1e-7 * np.maximum(np.abs(x), 1.0)     # within one node of eq. (4)'s table
    numeric = np.column_stack([(resid(x + e * hj) - resid(x - e * hj)) / (2 * hj)
                               for e, hj in zip(np.eye(x.size), h)])
    assert got.shape == numeric.shape == (sum(r.q_mm3_s.size for r in runs.values()) + 1, 7)
    scale = np.abs(numeric).max(axis=0)
    assert np.all(scale > 0)
    # z0, C, g: exact (1e-8); y_c: a forward difference (its truncation, ~1e-4)
    err = np.abs(got - numeric).max(axis=0) / scale
    assert np.all(err[[0, 1, 3, 4, 6]] < 1e-7) and np.all(err[[2, 5]] < 1e-3), err


def test_geometry_not_identified_from_one_load():
    base = ValveModel.from_rig(RIG).side("supply")
    theta, p1, dp, q, load = _flow_steps(base, (0.3,))
    g = fit_geometry(base, theta, p1, dp, q, 0.02 * np.abs(q) + 5.0, load,
                     z0_start_mm=base.z0_mm, c_start=base.c_flow)
    assert not g.identified and "load level" in g.note
    assert math.isfinite(g.z0_mm)


def test_geometry_fit_ending_where_eq4_cannot_be_inverted(monkeypatch):
    """A fit that stops where eq. (4) is not monotonic (every residual at its
    sentinel, a flat cost: another rig's data gave a traceback here) keeps
    the rig file's centre and says why; the fit summary still forms."""
    import pandas as pd

    from seanv_analysis.identify import geometry

    base = ValveModel.from_rig(RIG).side("supply")
    bad_y = -4.5     # the rig's x_c with this y_c: eq. (4) turns over inside the cam range
    assert not geometry._valid(base, bad_y)
    theta, p1, dp, q, load = _flow_steps(base, (0.1, 0.3, 0.5))

    def stuck(runs, x0, lo, hi, f_scale, layout, y_fixed, g_fixed, g_prior_sd=None, **_):
        n = sum(r.q_mm3_s.size for r in runs.values())
        sol = type("Sol", (), {"fun": np.ones(n), "jac": np.ones((n, x0.size)), "cost": 1.0})()
        x = np.array(x0, float)
        for name, free in zip(layout.names, layout.free):
            if free:
                x[layout.slices[name].stop - 1] = bad_y
        return x, sol, lambda p: np.ones(n)

    monkeypatch.setattr(geometry, "_fit", stuck)
    g = fit_geometry(base, theta, p1, dp, q, 0.02 * np.abs(q) + 5.0, load,
                     z0_start_mm=base.z0_mm, c_start=base.c_flow)
    assert not g.identified and "not monotonic" in g.note
    model = ValveModel.from_rig(RIG)
    per_run = pd.DataFrame({"side": "supply", "used": True, "run_index": np.arange(q.size),
                            "theta_deg": theta, "p1_mpa": p1, "dp_mpa": dp, "q_mm3_s": q,
                            "sigma_mm3_s": 0.02 * np.abs(q) + 5.0, "load_level_mpag": load})
    consts, fits, notes = geometry.geometry_constants(per_run, model, RIG)
    yc = [c for c in consts if c.key == "valve.supply.needle_y_c_mm"][0]
    assert not yc.identified and yc.value == yc.default
    assert any("not monotonic" in n for n in notes)


def test_lag_fit_on_saturated_flow_gives_no_interval_rather_than_overflow():
    """The actuator's flow pinned at a limit while the valve's steps: the lag's
    time constant cannot be told. No overflow, no (0, 1e97) interval: none."""
    from seanv_analysis.identify.flowpath import FlowPathData, fit_lag

    t = np.arange(0.0, 10.0, 0.002)
    rng = np.random.default_rng(0)
    q_valve = np.where(t > 1.0, 8000.0, 0.0)
    q = np.clip(np.interp(t - 0.2, t, q_valve), 0.0, 3000.0) + rng.normal(0, 20, t.size)
    fit = fit_lag([FlowPathData("r", t, q_valve, q, np.zeros_like(t))])
    lo, hi = fit["tau_ci95"]
    assert math.isnan(lo) and math.isnan(hi)
    assert math.isfinite(fit["tau_s"]) and math.isfinite(fit["rmse_mm3_s"])


@pytest.mark.parametrize("droop, taken", [(2e-5, True), (1.2e-8, False)])
def test_supply_droop_taken_only_where_material(droop, taken):
    """The supply line p1 = p_0 - k Q through steady supply flow steps: a
    droop of 2e-5 MPa s/mm^3 (0.14 MPa at 7000 mm^3/s) is taken, with p_0
    and k inside their intervals; 1.2e-8 (84 Pa at 7000 mm^3/s, what our
    stiff simulated supply showed at t = -3.3 where the pump ripple's phase
    moved the line's p_0 by 4e-5 MPa) is significant on 400 quiet steps but
    below a transducer's 0.1 %: not taken, p_0 is the steps' median. The
    steps that stick-slip (not steady) sit 3 kPa low and are left out."""
    import pandas as pd

    from seanv_analysis.identify.engine import _supply_pressure

    rng = np.random.default_rng(3)
    n, p0 = 400, 3.1
    q = rng.uniform(100.0, 7000.0, n)
    steady = q > 600.0
    p1 = p0 - droop * q + rng.normal(0.0, 2e-6, n) - np.where(steady, 0.0, 3e-3)
    summary = pd.DataFrame({"kind": "flow_step", "side": "supply", "q_mm3_s": q, "p1_mpa": p1,
                            "motion_steady": steady})
    got = {c.key: c for c in _supply_pressure(summary, [], RIG)}
    p = got["supply.pressure_mpag"]
    assert ("supply.droop_mpa_s_per_mm3" in got) is taken
    if taken:
        k = got["supply.droop_mpa_s_per_mm3"]
        assert k.ci95[0] <= droop <= k.ci95[1] and p.ci95[0] <= p0 <= p.ci95[1], (k, p)
    else:
        assert p.value == pytest.approx(float(np.median(p1)))
