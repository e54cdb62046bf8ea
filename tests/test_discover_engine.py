"""Discovery engine on per-run summaries generated from the valve model.

These exercise the statistics (selection, false alarms, held-out error) on
exactly known effects; tests/test_discover_sim.py runs the whole loop on
simulator data.
"""
import functools

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from seanv_analysis import ValveModel, load_rig
from seanv_analysis.discover import chrono_split, discover_flow_steps
from seanv_analysis.errors import FitError
from seanv_analysis.models import ValveSide, side_pressures
from seanv_analysis.models import effects as fx

MODEL = ValveModel.from_rig(load_rig())


def synth_summary(seed=0, effect=None, *, rel_noise=0.03, abs_noise=20.0):
    """Flow-step summary over a paper-like grid; ``effect`` = (name, side, value)."""
    rng = np.random.default_rng(seed)
    rows, i = [], 0
    name, eff_side, value = effect if effect else (None, None, None)
    for side in ("supply", "drain"):
        cams = np.arange(-7.5, 10.1, 2.5) if side == "supply" else np.arange(-40, -21, 2.5)
        for load in (0.3, 0.35, 0.4, 0.45):
            for cam in cams:
                for r in range(3):
                    ph = 4 * load + (0.6 if side == "supply" else -0.6) + rng.normal(0, 0.02)
                    approach = 1 if (side == "supply") == (r % 2 == 0) else -1
                    base = MODEL.side(side)
                    z0, c, n, theta = base.z0_mm, base.c_flow, 0.5, cam
                    if name == "drift" and eff_side == side:
                        c = c * fx.drift_multiplier(i, step=value, every=3)
                    if name == "threshold_shift" and eff_side == side:
                        z0 = z0 + fx.threshold_shift_mm(i, rate_mm_per_run=value)
                    if name == "backlash":
                        theta = fx.backlash_cam_deg(cam, approach, width_deg=value)
                    if name == "pressure_law" and eff_side == side:
                        n = value
                    vs = ValveSide(side, z0, c, base.geometry, n)
                    p1, dp = side_pressures(side, 3.3, ph, 0.0)
                    q = float(vs.flow(theta, p1, dp))
                    if name == "saturation" and eff_side == side:
                        q = float(fx.saturate_flow(np.array([q]), value)[0])
                    q = q * (1 + rng.normal(0, rel_noise)) + rng.normal(0, abs_noise)
                    rows.append(dict(run_id=f"r{i}", kind="flow_step", side=side, run_index=i,
                                     load_mpag=load, cam_deg=cam, cam_measured_deg=cam,
                                     cam_approach=approach, q_mm3_s=q, dp_mpa=dp, p1_mpa=p1,
                                     excluded="" if abs(q) > 50 else "leakage"))
                    i += 1
    return pd.DataFrame(rows)


CASES = [("drift", "drain", 0.04), ("drift", "supply", -0.03),
         ("threshold_shift", "supply", 6e-4), ("threshold_shift", "drain", -3e-4),
         ("backlash", "both", 2.0), ("pressure_law", "drain", 0.8),
         ("saturation", "supply", 6000.0)]


@functools.lru_cache(maxsize=None)
def discovered(seed: int, effect: tuple | None):
    """discover_flow_steps on ``synth_summary(seed, effect)``, once per test
    process: several tests read the same case (do not modify the result)."""
    return discover_flow_steps(synth_summary(seed, effect), model=MODEL)


@pytest.mark.parametrize("effect", CASES, ids=lambda e: f"{e[0]}-{e[1]}")
def test_names_injected_effect_and_cuts_heldout_error(effect):
    """One seed per case here; the rates over seeds and strengths are
    benchmarks/bench_discover.py's (make bench)."""
    d = discovered(0, effect)
    named = [(e.name, e.side) for e in d.effects]
    assert d.verdict == "effect_found" and named[0] == effect[:2], d.report()
    assert d.rmse_after_mm3_s <= 0.7 * d.rmse_before_mm3_s


def test_backlash_width_and_exponent_recovered():
    d = discovered(0, ("backlash", "both", 2.0))
    lo, hi = d.effects[0].params_ci95["width_deg"]
    assert abs(d.effects[0].params["width_deg"] - 2.0) < 0.3 and lo < 2.0 < hi
    d = discovered(0, ("pressure_law", "drain", 0.8))
    assert abs(d.effects[0].params["exponent"] - 0.8) < 0.1


def test_clean_data_says_none():
    """One clean seed here; the rate over seeds 100-119 (101 and 102,
    checked here before, among them) is benchmarks/bench_discover.py's
    ``engine_clean`` (make bench, which fails below its floor)."""
    assert discover_flow_steps(synth_summary(100), model=MODEL).verdict == "none"


def test_heldout_runs_are_never_fitted():
    df = synth_summary(3, ("drift", "drain", 0.04))
    d = discover_flow_steps(df, model=MODEL)
    fit_runs = set(d.fit_data.run_index.tolist())
    held_runs = set(d.heldout_data.run_index.tolist())
    assert fit_runs.isdisjoint(held_runs)
    # corrupting the held-out flows must not change what was selected or fitted
    df2 = df.copy()
    df2.loc[df2.run_index.isin(held_runs), "q_mm3_s"] *= 3.0
    d2 = discover_flow_steps(df2, model=MODEL)
    assert [e.to_json_dict() for e in d2.effects] == [e.to_json_dict() for e in d.effects]


def test_json_contract():
    d = discovered(1, ("drift", "drain", 0.04))
    j = d.to_json_dict()
    assert set(j) >= {"verdict", "effects", "heldout", "trend_variable"}
    assert set(j["heldout"]) == {"n_runs", "rmse_before_mm3_s", "rmse_after_mm3_s"}
    e = j["effects"][0]
    assert set(e) == {"name", "side", "params", "estimates", "p_value"}
    assert {r["name"]: r["unit"] for r in e["estimates"]} == {
        "drain.drift.step": "-", "drain.drift.every": "runs", "drain.drift.offset": "runs"}
    assert repr(d).startswith("<Discovery effect_found: drift (drain); held-out RMSE ")
    frame = d.to_frame()
    assert list(frame.effect) == ["drift"] * 3 and list(frame.name) == list(d.params)
    assert frame.ci95_lo[0] <= frame.value[0] <= frame.ci95_hi[0] and frame.unit[0] == "-"
    assert "<table" in d._repr_html_()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots()
    assert d.plot(ax=ax, variable="dp_mpa") is ax and "Delta p" in ax.get_xlabel()
    plt.close(fig)
    assert e["name"] == "drift" and e["side"] == "drain" and 0 < e["p_value"] <= 0.05


def test_chrono_split_per_side():
    idx = np.arange(20)
    side = np.array(["supply"] * 10 + ["drain"] * 10)
    fit, held = chrono_split(idx, fraction=0.3, groups=side)
    assert held.tolist() == [False] * 7 + [True] * 3 + [False] * 7 + [True] * 3


def test_too_few_runs():
    with pytest.raises(FitError, match="usable flow_step runs"):
        discover_flow_steps(synth_summary(0).head(5), model=MODEL)


def load_stepped_summary(seed, *, c_per_mpa=0.0, drift_step=0.0):
    """A protocol that steps the load up with time (as the paper's and most
    rigs' do): per load, three sweeps of both sides. ``c_per_mpa``: C grows
    with the load, C (1 + k (load - 0.3)) (an effect outside the vocabulary
    that is a trend in run order too); ``drift_step``: a real drain drift
    every 3 runs."""
    rng = np.random.default_rng(seed)
    rows, i = [], 0
    for load in (0.1, 0.2, 0.3, 0.4, 0.5):
        for _ in range(3):
            for side in ("drain", "supply"):
                cams = np.arange(-7.5, 10.1, 2.5) if side == "supply" else np.arange(-40, -21, 2.5)
                for cam in cams:
                    base = MODEL.side(side)
                    c = base.c_flow * (1 + c_per_mpa * (load - 0.3))
                    if side == "drain" and drift_step:
                        c *= fx.drift_multiplier(i, step=drift_step, every=3)
                    ph = 4 * load + (0.6 if side == "supply" else -0.6) + rng.normal(0, 0.02)
                    p1, dp = side_pressures(side, 3.3, ph, 0.0)
                    q = float(ValveSide(side, base.z0_mm, c, base.geometry, 0.5).flow(cam, p1, dp))
                    q = q * (1 + rng.normal(0, 0.03)) + rng.normal(0, 20.0)
                    rows.append(dict(run_id=f"r{i}", kind="flow_step", side=side, run_index=i,
                                     load_mpag=load, cam_deg=cam, cam_measured_deg=cam,
                                     cam_approach=1 if side == "supply" else -1, q_mm3_s=q,
                                     dp_mpa=dp, p1_mpa=p1,
                                     excluded="" if abs(q) > 50 else "leakage"))
                    i += 1
    return pd.DataFrame(rows)


def test_load_dependence_is_not_passed_off_as_wear():
    """C that grows with the load, loads stepped up with time: the residual
    trends with run order, but within a load run order explains nothing.
    The run-order candidates are tested by permuting the order within each
    load; scattering the residuals (as before) named a drift in 2 of 4 seeds.
    One seed here; the rate over 8 seeds (seed 1, checked here before, among
    them) is benchmarks/bench_discover.py's ``engine_load_dependence``."""
    seed = 0
    d = discover_flow_steps(load_stepped_summary(seed, c_per_mpa=0.4), model=MODEL, seed=seed)
    named = {e.name for e in d.effects}
    assert not named & {"drift", "threshold_shift"}, (seed, d.report())


def test_drift_still_named_when_loads_step_with_time():
    """One seed here; the rate over 8 seeds (seed 1, checked here before,
    among them) is benchmarks/bench_discover.py's ``engine_drift_with_loads``."""
    d = discover_flow_steps(load_stepped_summary(0, drift_step=0.02), model=MODEL, seed=0)
    assert ("drift", "drain") in {(e.name, e.side) for e in d.effects}, d.report()
    assert d.rmse_after_mm3_s <= 0.7 * d.rmse_before_mm3_s


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(-5, 5), st.floats(-1e3, 1e3, allow_nan=False)),
                min_size=8, max_size=60))
def test_spearman_is_scipys(pairs):
    """discover's Spearman test (no scipy.stats import at start) gives
    scipy.stats.spearmanr's rho and p, ties included; the F and chi-square
    survival functions are scipy.stats' too."""
    from scipy import stats

    from seanv_analysis.discover.diagnostics import ljung_box, spearman
    from seanv_analysis.discover.engine import _f_test

    x, y = (np.array(v, float) for v in zip(*pairs))
    if np.ptp(x) == 0 or np.ptp(y) == 0:
        return
    rho, p = spearman(x, y)
    want = stats.spearmanr(x, y)
    assert rho == pytest.approx(want.statistic, abs=1e-12)
    assert p == pytest.approx(want.pvalue, rel=1e-9, abs=1e-300)
    q, p_lb = ljung_box(y)
    h = min(10, max(y.size // 4, 1))
    assert p_lb == pytest.approx(stats.chi2.sf(q, h), rel=1e-9, abs=1e-300)
    f, p_f = _f_test(10.0 + abs(y[0]), 2, 10.0, 3, x.size + 3)
    assert p_f == pytest.approx(stats.f.sf(f, 1, x.size), rel=1e-9)


def test_side_masks_are_made_once_and_cannot_be_changed():
    from seanv_analysis.discover.static import FlowData

    data = FlowData.from_summary(synth_summary(0))
    m = data.on_side("drain")
    assert m is data.on_side("drain") and np.array_equal(m, data.side == "drain")
    with pytest.raises(ValueError):
        m[0] = not m[0]
    assert np.array_equal(data.subset(m).on_side("drain"), np.ones(int(m.sum()), bool))
