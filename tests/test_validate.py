"""Closed-loop validation (analysis.validate) and its CLI."""
from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest
from numpy.testing import assert_allclose
from test_tracking import write_delayed_run

from seanv_analysis.analysis.validate import (
    Validation,
    build_controller,
    fit_percent,
    load_steps,
    reference_steps,
    step_metrics,
    validate_runs,
)
from seanv_analysis.config import load_rig
from seanv_analysis.errors import ConfigError, DataError
from seanv_analysis.io import Run, read_run
from seanv_analysis.models import ValveModel
from seanv_analysis.sim.control import CamController, FlowModelController

# --- pure helpers ------------------------------------------------------------

def test_fit_percent_exact_cases():
    y = np.array([0.0, 1.0, 2.0, 3.0])
    assert fit_percent(y, y) == 100.0
    assert fit_percent(y, np.full(4, y.mean())) == 0.0
    s = y + np.array([0.1, -0.2, 0.0, 0.3])
    expected = 100 * (1 - np.sqrt(0.14) / np.sqrt(5.0))
    assert_allclose(fit_percent(y, s), expected, rtol=1e-12)
    assert math.isnan(fit_percent(np.ones(3), np.ones(3)))


def test_step_metrics_first_order_response():
    t = np.arange(0.0, 10.0, 0.001)
    tau = 0.5
    x = np.where(t < 5, 10 + 20 * (1 - np.exp(-t / tau)),
                 30 - 10 * (1 - np.exp(-(t - 5) / tau)))
    x = x + np.where(t < 5, 0.8 * np.exp(-((t - 2) / 0.3) ** 2), 0.0)  # an overshoot bump
    m = step_metrics(t, x, [0.0, 5.0], [30.0, 20.0], x0_mm=10.0, band_mm=0.5)
    assert list(m.converged) == [True, True]
    # second step: |e| = 10 exp(-t/tau) <= 0.5 from tau ln 20
    assert_allclose(m.settling_time_s.iloc[1], tau * np.log(20), atol=2e-3)
    assert m.overshoot_mm.iloc[1] == 0.0
    assert 0.0 < m.overshoot_mm.iloc[0] < 0.8
    assert list(m.step_mm) == [20.0, -10.0]


# --- sequences and controllers from a run -----------------------------------

@pytest.fixture(scope="module")
def measured(tmp_path_factory):
    root = tmp_path_factory.mktemp("validate")
    return [read_run(write_delayed_run(root, "fm", duration_s=12.0, seed=1)),
            read_run(write_delayed_run(root, "cam", duration_s=12.0, seed=2, flow_model=False))]


def test_sequences_and_controller_from_run(measured, rig):
    t, v = reference_steps(measured[0])
    assert_allclose(t, [0.0, 6.0]) and assert_allclose(v, [40.0, 20.0])
    t, v = load_steps(measured[0])
    assert_allclose(t, [0.0, 5.0, 10.0], atol=0.06)
    assert_allclose(v, [0.3, 0.45, 0.3])
    model = ValveModel.from_rig(rig)
    c = build_controller(measured[0], model)
    assert isinstance(c, FlowModelController) and c.kp_mm3_s_per_mm == 480 and c.model is model
    c = build_controller(measured[1], model)
    assert isinstance(c, CamController) and c.kp_deg_per_mm == 15


# --- plumbing with a stand-in simulator --------------------------------------

def _fake_simulator(measured, *, offset_mm=0.0, delay_s=0.0):
    """Returns the measured run itself (optionally delayed / offset): checks the
    arguments validate passes on."""
    by_id = {r.run_id: r for r in measured}

    def simulate(rig, *, controller, x_ref, load, duration_s, seed, valve, effects, x0_mm,
                 run_id, started_at):
        run = by_id[run_id.removesuffix("-sim")]
        assert duration_s == pytest.approx(run.tables["encoder"].t_s.iloc[-1])
        assert x0_mm == run.tables["encoder"].position_mm.iloc[0]
        assert_allclose(x_ref[1], reference_steps(run)[1])
        enc = run.tables["encoder"].copy()
        t = enc.t_s.to_numpy()
        enc["position_mm"] = np.interp(t - delay_s, t, enc.position_mm) + offset_mm
        tables = dict(run.tables, encoder=enc)
        return Run(meta=replace(run.meta, run_id=run_id), tables=tables, rig=run.rig), {}

    return simulate


def test_identical_plant_fits_perfectly(measured, tmp_path):
    v = validate_runs(measured, simulate=_fake_simulator(measured))
    assert isinstance(v, Validation) and v.flagged == []
    assert_allclose(v.table.fit_position_pct, 100.0)
    assert list(v.table.controller) == ["flow_model", "cam"]
    doc = json.loads(json.dumps(v.to_json_dict()))
    assert doc["flagged"] == [] and len(doc["runs"]) == 2
    assert set(doc["by_controller"]) == {"flow_model", "cam"}
    assert doc["by_controller"]["cam"]["n_runs"] == 1
    assert "kp_mm3_s_per_mm" in doc["runs"][0] and "kp_deg_per_mm" not in doc["runs"][0]
    # notebook display: one line, a table in Jupyter, a frame indexed by run
    assert repr(v).startswith("<Validation position fit: ") and "100.0 %" in repr(v)
    assert "\n" not in repr(v) and "<table" in v._repr_html_()
    assert list(v.to_frame().index) == list(v.table.run_id)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots()
    assert v.plot(ax=ax, quantity="flow") is ax and len(ax.lines) == 2 * len(v.runs)
    plt.close(fig)
    from seanv_analysis.stages import validate as validate_stage

    paths = validate_stage.write(validate_stage.ValidateResult(v), tmp_path / "out")
    assert (tmp_path / "out" / "validate.json").exists() and len(paths) == 6
    assert set(v.steps().source) == {"measured", "simulated"}
    from seanv_analysis.plots.validate import plot_overlay
    figs = plot_overlay(v, tmp_path / "out")
    assert {p.name for p in figs} >= {"validate_fm.png", "validate_fit.svg"}


def test_disagreeing_plant_is_flagged(measured):
    v = validate_runs(measured, simulate=_fake_simulator(measured, delay_s=1.5), threshold_pct=95)
    assert v.flagged == ["fm", "cam"]
    assert (v.table.fit_position_pct < 95).all()
    assert "FLAGGED" in v.report()


def test_errors(measured):
    with pytest.raises(ConfigError, match="threshold_pct"):
        validate_runs(measured, threshold_pct=float("nan"))
    with pytest.raises(DataError, match="no position_control run"):
        validate_runs([])


# --- against the simulator ----------------------------------------------------

XREF = (np.array([0.0, 3.0, 7.0, 11.0]), np.array([40.0, 20.0, 45.0, 30.0]))
LOAD = (np.array([0.0, 5.0, 9.0]), np.array([0.30, 0.45, 0.30]))


def _simulated(rig, *, controller, effects=(), seed=0, run_id="sim"):
    sim = pytest.importorskip("seanv_analysis.sim")
    out = sim.simulate_position_control(rig, controller=controller, x_ref=XREF, load=LOAD,
                                        duration_s=14.0, seed=seed, effects=effects, x0_mm=30.0,
                                        run_id=run_id)
    return out[0] if isinstance(out, tuple) else out


@pytest.fixture(scope="module")
def sim_runs():
    rig = load_rig()
    model = ValveModel.from_rig(rig)
    clean = [_simulated(rig, controller=FlowModelController.from_rig(rig, model), run_id="fm"),
             _simulated(rig, controller=CamController.from_rig(rig), run_id="cam", seed=1)]
    drifted = [_simulated(rig, controller=FlowModelController.from_rig(rig, model),
                          effects=("delay:delay_s=0.3",), run_id="fm-delay")]
    return rig, model, clean, drifted


def test_same_plant_fits_above_90(sim_runs):
    rig, model, clean, _ = sim_runs
    v = validate_runs(clean, model, seed=7)
    assert (v.table.fit_position_pct > 90).all(), v.report()
    assert v.flagged == []


def test_injected_effect_drops_fit_and_flags(sim_runs):
    rig, model, clean, drifted = sim_runs
    base = validate_runs(clean[:1], model, seed=7)
    v = validate_runs(drifted, model, seed=7, threshold_pct=base.table.fit_position_pct[0] - 1)
    assert v.table.fit_position_pct[0] < base.table.fit_position_pct[0]
    assert v.flagged == ["fm-delay"], v.report()


def test_controller_model_choice(measured):
    v = validate_runs(measured[:1], simulate=_fake_simulator(measured), controller_model="plant")
    assert v.to_json_dict()["controller_model"] == "plant"
    with pytest.raises(ConfigError, match="controller_model"):
        validate_runs(measured[:1], simulate=_fake_simulator(measured), controller_model="x")


def test_pooled_rmse_is_the_rmse_of_all_samples():
    """Runs' RMSEs are pooled over their samples (the package's one pooling:
    validate's per-controller numbers, identify's and discover's closed-loop
    numbers), not averaged: two runs of 100 and 300 samples pool to the RMSE
    of their 400 residuals; a run without an RMSE is left out."""
    import numpy as np

    from seanv_analysis.analysis.validate import pooled_rmse

    rng = np.random.default_rng(0)
    a, b = rng.normal(0, 1.0, 100), rng.normal(0, 5.0, 300)
    rms = lambda r: float(np.sqrt(np.mean(r ** 2)))  # noqa: E731
    got = pooled_rmse([rms(a), rms(b), float("nan")], [a.size, b.size, 50])
    assert got == pytest.approx(rms(np.concatenate([a, b])), rel=1e-12)
    assert got != pytest.approx((rms(a) + rms(b)) / 2, rel=1e-3)
