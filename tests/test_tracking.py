"""Flow tracking (analysis.tracking): delay, shift, RMSE; figures."""
from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
from numpy.testing import assert_allclose

from seanv_analysis.analysis.tracking import run_flows, tracking_runs
from seanv_analysis.config import load_rig
from seanv_analysis.errors import ConfigError, DataError
from seanv_analysis.io import read_dataset, read_run, write_run
from seanv_analysis.signals.align import align_run
from seanv_analysis.signals.derive import derive_samples
from seanv_analysis.stages import run_stages

AREA = math.pi / 4 * 16.0 ** 2


def write_delayed_run(root, run_id, *, delay_s=0.237, seed=0, duration_s=30.0,
                      flow_model=True, q_ref_empty=False, started_at="2026-03-02T10:00:00Z"):
    """A position_control run whose actual flow is the target flow delayed by
    ``delay_s`` (target: 100 Hz random steps, some zero holds); the position
    is the flow's integral / A at 1 kHz. Load alternates 0.3 / 0.45 MPaG."""
    rng = np.random.default_rng(seed)
    t_c = np.round(np.arange(0.0, duration_s, 0.01), 9)
    q_c = np.zeros(t_c.size)
    i = 0
    while i < t_c.size:
        n = int(rng.integers(40, 200))
        q_c[i:i + n] = 0.0 if rng.random() < 0.25 else rng.uniform(-4000, 9500)
        i += n
    t = np.round(np.arange(0.0, duration_s + 1e-9, 0.001), 9)
    k = np.clip(np.searchsorted(t_c, t - delay_s, side="right") - 1, 0, None)
    q_act = np.where(t - delay_s >= 0, q_c[k], 0.0)
    x = 30.0 + np.concatenate(([0.0], np.cumsum(q_act[:-1]) * 0.001)) / AREA
    load = np.where((t % 10.0) < 5.0, 0.3, 0.45)
    ps = 3.3 + 0.005 * rng.standard_normal(t.size)
    tables = {
        "encoder": pd.DataFrame({"t_s": t, "position_mm": x}),
        "pressure": pd.DataFrame({"t_s": t, "p_supply_mpag": ps, "p_head_mpag": 4 * load,
                                  "p_load_mpag": load}),
        "servo": pd.DataFrame({"t_s": t_c, "cam_cmd_deg": -15 + q_c / 600,
                               "cam_deg": -15 + q_c / 600}),
        "controller": pd.DataFrame({"t_s": t_c, "x_ref_mm": np.where(t_c < duration_s / 2, 40., 20.),
                                    "q_ref_mm3_s": np.nan if q_ref_empty else q_c}),
    }
    meta = {"run_id": run_id, "kind": "position_control", "started_at": started_at,
            "load_mpag": None, "controller": {"kp": 480 if flow_model else 15,
                                              "flow_model": flow_model, "rate_hz": 100}}
    return write_run(root / run_id, meta, tables)


@pytest.fixture(scope="module")
def delayed_dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("delayed")
    for j in range(2):
        write_delayed_run(root, f"pos{j}", seed=j, started_at=f"2026-03-02T10:0{j}:00Z")
    return root


@pytest.fixture(scope="module")
def delayed_runs(delayed_dataset):
    return read_dataset(delayed_dataset).runs


def test_estimates_known_delay(delayed_runs):
    tr = tracking_runs(delayed_runs)
    assert tr.shift_source == "estimated" and tr.shift_s == tr.lag_s
    assert abs(tr.lag_s - 0.237) < 0.005
    lo, hi = tr.lag_ci95_s
    assert lo <= tr.lag_s <= hi
    for r in tr.runs:
        assert abs(r.lag_s - 0.237) < 0.01
    # after compensation the actual flow follows the target closely
    assert tr.rmse_mm3_s < 0.2 * np.nanstd(np.concatenate([r.data.q_ref_mm3_s for r in tr.runs]))


def _independent_rmse(runs, shift_s, lo, hi):
    """Paper's procedure written out with numpy: Q(t + shift) - Q_ref(t)."""
    res = []
    for run in runs:
        d = derive_samples(run)
        t = d["t_s"].to_numpy()
        q = d["q_mm3_s"].to_numpy()
        q_ref = d["q_ref_mm3_s"].to_numpy()
        inside_t = t + shift_s <= t[-1]
        q_shift = np.interp(t[inside_t] + shift_s, t, q)
        target = q_ref[inside_t]
        m = (target >= lo) & (target <= hi)
        res.append(q_shift[m] - target[m])
    r = np.concatenate(res)
    return float(np.sqrt(np.mean(r ** 2))), float(np.mean(r)), r.size


def test_shift_025_is_the_papers_procedure_exactly(delayed_runs):
    tr = tracking_runs(delayed_runs, shift_s=0.25)
    rmse, bias, n = _independent_rmse(delayed_runs, 0.25, -2.5e3, 8e3)
    assert tr.shift_s == 0.25 and tr.shift_source == "given"
    assert tr.lag_s == tr.lag.lag_s and tr.lag_ci95_s == tr.lag.ci95_s   # the estimate, still
    assert tr.n_samples == n
    assert_allclose(tr.rmse_mm3_s, rmse, rtol=1e-9)
    assert_allclose(tr.bias_mm3_s, bias, rtol=1e-9)
    doc = tr.to_json_dict()
    assert list(doc) == ["shift_s", "shift_source", "lag_s", "lag_ci95_s", "rmse_mm3_s",
                         "bias_mm3_s", "range_mm3_s", "n_samples", "pooled", "pooled_runs",
                         "runs"]
    assert doc["range_mm3_s"] == [-2500.0, 8000.0] and doc["shift_s"] == 0.25
    assert [set(r) for r in doc["runs"]] == [{"run_id", "target_source", "pooled", "lag_s",
                                              "rmse_mm3_s"}] * 2


def test_range_is_inclusive_and_per_side(delayed_runs):
    tr = tracking_runs(delayed_runs, shift_s=0.237, q_range=(0.0, 9500.0))
    rmse, _, n = _independent_rmse(delayed_runs, 0.237, 0.0, 9500.0)
    assert_allclose(tr.rmse_mm3_s, rmse, rtol=1e-9)
    assert math.isnan(tr.rmse_drain_mm3_s)  # no target < 0 inside [0, 9500]
    assert_allclose(tr.rmse_supply_mm3_s, tr.rmse_mm3_s, rtol=1e-12)
    assert set(tr.rmse_by_load_mm3_s) == {0.3, 0.45}


def test_per_run_rmse_matches_independent(delayed_runs):
    tr = tracking_runs(delayed_runs, shift_s=0.25)
    for run, r in zip(delayed_runs, tr.runs):
        rmse, bias, n = _independent_rmse([run], 0.25, -2.5e3, 8e3)
        assert_allclose(r.rmse_mm3_s, rmse, rtol=1e-9)
        assert r.n_samples == n


def test_target_from_kp_error_and_model(tmp_path):
    from seanv_analysis.models import ValveModel

    run = read_run(write_delayed_run(tmp_path, "kp", q_ref_empty=True, duration_s=6.0))
    df, source = run_flows(run)
    assert source == "kp_error"
    ctrl = run.tables["controller"]
    enc = run.tables["encoder"]
    x_c = np.interp(ctrl.t_s, enc.t_s, enc.position_mm)
    expected = 480 * (ctrl.x_ref_mm.to_numpy() - x_c)
    at = np.searchsorted(df.t_s.to_numpy(), ctrl.t_s.to_numpy()[5])
    assert_allclose(df.q_ref_mm3_s.iloc[at], expected[5], rtol=1e-12)

    nomodel = read_run(write_delayed_run(tmp_path, "cam", q_ref_empty=True, flow_model=False,
                                         duration_s=6.0))
    with pytest.warns(UserWarning, match="skipped run cam"):
        tr = tracking_runs([run, nomodel])
    assert "cam" in tr.skipped and [r.run_id for r in tr.runs] == ["kp"]
    model = ValveModel.from_rig(load_rig())
    df, source = run_flows(nomodel, model=model)
    assert source == "model"
    a = align_run(nomodel)
    assert_allclose(df.q_ref_mm3_s, model.net_flow(a.cam_cmd_deg, a.p_supply_mpag,
                                                   a.p_head_mpag, a.p_tank_mpag))


def test_headline_pools_the_runs_with_a_commanded_target(tmp_path):
    """Issue 33, point 2: the paper's RMSE is over runs with a commanded
    Q_ref. A run whose target is only implied by a valve model gets its own
    numbers but is not pooled, so the headline is the same with a model
    (the pipeline) as without one (``tracking`` alone, which skips that run);
    with no commanded run at all, every run is pooled and it says so."""
    from seanv_analysis.analysis.tracking import POOLED_ALL, POOLED_COMMANDED
    from seanv_analysis.models import ValveModel

    commanded = read_run(write_delayed_run(tmp_path, "kp", q_ref_empty=True, duration_s=6.0))
    implied = read_run(write_delayed_run(tmp_path, "cam", q_ref_empty=True, flow_model=False,
                                         duration_s=6.0, seed=3))
    model = ValveModel.from_rig(load_rig())
    both = tracking_runs([commanded, implied], model=model)
    with pytest.warns(UserWarning, match="skipped run cam"):
        alone = tracking_runs([commanded, implied])
    assert [r.target_source for r in both.runs] == ["kp_error", "model"]
    assert both.pooled == POOLED_COMMANDED and both.pooled_runs == ["kp"]
    assert both.rmse_mm3_s == alone.rmse_mm3_s == both.runs[0].rmse_mm3_s
    assert both.shift_s == alone.shift_s and both.n_samples == both.runs[0].n_samples
    assert both.runs[1].n_samples > 0 and math.isfinite(both.runs[1].rmse_mm3_s)
    doc = both.to_json_dict()
    assert [(r["run_id"], r["pooled"]) for r in doc["runs"]] == [("kp", True), ("cam", False)]
    assert "runs with a commanded Q_ref (kp)" in both.report()
    only = tracking_runs([implied], model=model, shift_s=0.25)
    assert only.pooled == POOLED_ALL and only.pooled_runs == ["cam"]
    assert only.rmse_mm3_s == only.runs[0].rmse_mm3_s


def test_errors(delayed_runs, tmp_path):
    with pytest.raises(ConfigError, match="q_range"):
        tracking_runs(delayed_runs, q_range=(1.0, -1.0))
    with pytest.raises(ConfigError, match="shift_s"):
        tracking_runs(delayed_runs, shift_s=float("nan"))
    with pytest.raises(DataError, match="no usable position_control run"):
        tracking_runs([])


def test_write_and_figures(delayed_runs, delayed_dataset, tmp_path):
    from seanv_analysis.plots.fig6 import plot_fig6
    from seanv_analysis.plots.fig7 import plot_fig7

    ctx = run_stages(delayed_dataset, ["ingest", "tracking"], options={"tracking": {"shift_s": 0.25}})
    tr, errors = ctx.result("tracking"), ctx.result("ingest").failed
    assert not errors
    from seanv_analysis.stages import tracking as tracking_stage

    paths = tracking_stage.write(tr, tmp_path / "out")
    names = {p.name for p in paths}
    assert {"tracking.json", "tracking_runs.parquet", "tracking_pos0.parquet"} <= names
    back = pd.read_parquet(tmp_path / "out" / "tracking_pos0.parquet")
    assert {"t_s", "q_ref_mm3_s", "q_mm3_s", "q_shifted_mm3_s", "in_range"} <= set(back.columns)
    figs = plot_fig7(tr, tmp_path / "figs", per_run=False) \
        + plot_fig6(delayed_runs[0], tmp_path / "figs")
    assert all(p.stat().st_size > 1000 for p in figs)
    assert {p.suffix for p in figs} == {".png", ".svg"}
    assert "RMSE" in tr.report()


# --- against the simulator -----------------------------------------------------

def _paper_run(effects=(), seed=0):
    sim = pytest.importorskip("seanv_analysis.sim")
    from seanv_analysis.models import ValveModel
    from seanv_analysis.sim.control import FlowModelController
    from seanv_analysis.sim.scenarios import paper_position_profile

    rig = load_rig()
    ref, load, duration = paper_position_profile()
    out = sim.simulate_position_control(
        rig, controller=FlowModelController.from_rig(rig, ValveModel.from_rig(rig)),
        x_ref=ref, load=load, duration_s=duration, seed=seed, effects=effects,
        run_id=f"paper-{len(effects)}")
    return out[0] if isinstance(out, tuple) else out


@pytest.fixture(scope="module")
def paper_lags():
    base = tracking_runs([_paper_run()])
    delayed = tracking_runs([_paper_run(("delay:delay_s=0.1",))])
    return base, delayed


def test_recovers_simulator_delay(paper_lags):
    base, delayed = paper_lags
    # the paper's ~0.25 s (servo ~0.1 s + tube and actuator dynamics)
    assert abs(base.lag_s - 0.25) < 0.05, base.report()
    # an extra 0.1 s dead time in the plant is recovered within 0.02 s
    assert abs((delayed.lag_s - base.lag_s) - 0.1) < 0.02, (base.lag_s, delayed.lag_s)
    lo, hi = base.lag_ci95_s
    assert lo <= base.lag_s <= hi


def test_compensation_lowers_rmse_on_simulator(paper_lags):
    base, _ = paper_lags
    run = base.runs[0].run
    unshifted = tracking_runs([run], shift_s=0.0)
    assert base.rmse_mm3_s < unshifted.rmse_mm3_s
    assert set(base.rmse_by_load_mm3_s) == {0.35, 0.45}


def test_load_levels_merge_transitions():
    from seanv_analysis.analysis.tracking import load_levels_mpag

    t = np.arange(0.0, 10.0, 0.001)
    p = np.where(t < 5, 0.35, 0.45)
    ramp = (t >= 5) & (t < 5.2)  # pressure passes 0.40 on the way
    p[ramp] = 0.35 + 0.1 * (t[ramp] - 5) / 0.2
    lv = load_levels_mpag(t, p)
    assert set(np.unique(lv)) == {0.35, 0.45}
    assert abs(t[np.argmax(lv == 0.45)] - 5.1) < 0.06


def test_after_change_marks_the_delay_window(delayed_runs):
    tr = tracking_runs(delayed_runs, shift_s=0.25)
    d = tr.runs[0].data
    t = d.t_s.to_numpy()
    marked = d.after_change.to_numpy()
    # x_ref changes at 15 s, load at 5, 10, 20, 25 s
    for tc in (5.0, 10.0, 15.0, 20.0, 25.0):
        assert marked[(t > tc + 0.06) & (t < tc + 0.2)].all()
        assert not marked[(t > tc + 0.3) & (t < tc + 1.0)].any()
