"""Simulator: the paper's headlines, leakage/friction, effects, determinism."""
from __future__ import annotations

import hashlib

import numpy as np
import pytest

from seanv_analysis import load_rig
from seanv_analysis.errors import ConfigError
from seanv_analysis.models import ValveModel
from seanv_analysis.signals.align import align_run
from seanv_analysis.signals.derive import derive_samples, summarize_run
from seanv_analysis.sim import (
    Plant,
    simulate_flow_step,
    simulate_position_control,
    simulate_scenario,
    tube_constants,
)
from seanv_analysis.sim.control import CamController, FlowModelController
from seanv_analysis.sim.scenarios import paper_position_profile


@pytest.fixture(scope="module")
def rig():
    return load_rig()


def _position_run(rig, *, model: bool, effects=(), seed=0):
    ref, load, duration = paper_position_profile()
    ctrl = FlowModelController.from_rig(rig) if model else CamController.from_rig(rig)
    run, trace = simulate_position_control(rig, controller=ctrl, x_ref=ref, load=load,
                                           duration_s=duration, seed=seed, effects=effects)
    return run, trace


def _xcorr_lag(t, target, actual, max_lag_s=0.6):
    """Independent lag estimate: argmax of the normalised cross-correlation [s]."""
    dt = t[1] - t[0]
    a = np.nan_to_num(target)
    lags = np.arange(int(max_lag_s / dt))
    c = [np.corrcoef(a[:a.size - k], actual[k:])[0, 1] for k in lags]
    return lags[int(np.argmax(c))] * dt


@pytest.fixture(scope="module")
def with_model(rig):
    return _position_run(rig, model=True)


@pytest.fixture(scope="module")
def without_model(rig):
    return _position_run(rig, model=False)


def test_tube_constants_match_hagen_poiseuille(rig):
    c = tube_constants(rig)
    # 128 mu L / (pi d^4) with mu = 1e-3 Pa s, L = 20 m, d = 2.5 mm, in MPa s/mm^3
    assert c["R"] == pytest.approx(128 * 1e-9 * 20000 / (np.pi * 2.5 ** 4), rel=1e-12)
    assert c["I"] == pytest.approx(998e-12 * 20000 / (np.pi / 4 * 2.5 ** 2), rel=1e-12)


def test_paper_position_delay_convergence_rmse(with_model):
    run, _ = with_model
    d, a = derive_samples(run), align_run(run)
    t, q = d["t_s"].to_numpy(), d["q_mm3_s"].to_numpy()
    q_ref, x, x_ref = a["q_ref_mm3_s"].to_numpy(), d["position_mm"].to_numpy(), a["x_ref_mm"].to_numpy()
    lag = _xcorr_lag(t, q_ref, q)
    assert 0.20 <= lag <= 0.30
    # converged within +-0.5 mm just before every reference change and at the end
    for t_end in [5.0 + 15.0 * k - 0.05 for k in range(1, 7)] + [t[-1]]:
        i = np.searchsorted(t, t_end) - 1
        assert abs(x[i] - x_ref[i]) <= 0.5, t_end
    shifted = np.interp(t + lag, t, q)
    m = (q_ref >= -2.5e3) & (q_ref <= 8e3) & (t + lag <= t[-1])
    rmse = float(np.sqrt(np.mean((shifted[m] - q_ref[m]) ** 2)))
    assert 300.0 <= rmse <= 800.0


def test_overshoot_larger_without_flow_model(with_model, without_model):
    def overshoot(run):
        d = derive_samples(run)
        t, x = d["t_s"].to_numpy(), d["position_mm"].to_numpy()
        m = (t > 5.0) & (t < 20.0)                       # 0 -> 30 mm step
        return float(x[m].max() - 30.0)
    assert overshoot(without_model[0]) > overshoot(with_model[0]) + 0.5


def test_leakage_when_sealed_within_50(rig):
    for side, cam in (("supply", -13.0), ("drain", -18.0)):
        run, trace = simulate_flow_step(rig, side=side, cam_deg=cam, load_mpag=0.4)
        # the needle is sealed at these angles: the true flow stays tiny
        assert np.max(np.abs(trace["q_true_mm3_s"])) <= 50.0
        assert abs(summarize_run(run)["q_mm3_s"]) <= 50.0


def test_low_load_drain_is_friction_dominated(rig):
    for cam in (-40.0, -35.0, -30.0, -25.0):
        for load in (0.1, 0.2):
            run, _ = simulate_flow_step(rig, side="drain", cam_deg=cam, load_mpag=load)
            assert abs(summarize_run(run)["q_mm3_s"]) <= 500.0
    # at a higher load the same opening gives far more flow
    run, _ = simulate_flow_step(rig, side="drain", cam_deg=-40.0, load_mpag=0.4)
    assert abs(summarize_run(run)["q_mm3_s"]) > 2000.0


def test_steady_flow_matches_valve_model(rig):
    """The plant's valve is eq. (5): the settled flow matches the model at the
    measured pressures within 1 % (leakage and noise aside)."""
    model = ValveModel.from_rig(rig)
    for side, cam in (("supply", 0.0), ("supply", 5.0), ("drain", -35.0)):
        run, _ = simulate_flow_step(rig, side=side, cam_deg=cam, load_mpag=0.4)
        row = summarize_run(run)
        pred = float(model.side(side).flow(cam, row["p1_mpa"], row["dp_mpa"]))
        assert row["q_mm3_s"] == pytest.approx(pred, rel=0.01)


def _flow(rig, side, cam, load=0.4, **kw):
    run, _ = simulate_flow_step(rig, side=side, cam_deg=cam, load_mpag=load, **kw)
    return summarize_run(run)


def _c_ratio(rig, side, cam, row):
    """Measured flow over the clean model's flow at the measured pressures."""
    return row["q_mm3_s"] / float(ValveModel.from_rig(rig).side(side).flow(cam, row["p1_mpa"], row["dp_mpa"]))


def test_effect_drift_lowers_drain_flow_stepwise(rig):
    eff = ["drift:side=drain,step=0.1,every=3"]
    r = [_c_ratio(rig, "drain", -35.0, _flow(rig, "drain", -35.0, effects=eff, run_index=i))
         for i in (0, 2, 3, 6)]
    np.testing.assert_allclose(r, [1.0, 1.0, 0.9, 0.81], rtol=0.01)
    # the supply side is untouched
    assert _c_ratio(rig, "supply", 0.0, _flow(rig, "supply", 0.0, effects=eff, run_index=9)) == \
        pytest.approx(1.0, rel=0.01)


def test_effect_threshold_shift_moves_supply_threshold(rig):
    base = _flow(rig, "supply", -5.0)["q_mm3_s"]
    shifted = _flow(rig, "supply", -5.0, effects=["threshold_shift:side=supply,rate_mm_per_run=1e-4"],
                    run_index=100)["q_mm3_s"]
    assert shifted < 0.8 * base        # z0 up by 0.01 mm: threshold later, less flow


def test_effect_backlash_depends_on_approach(rig):
    eff = ["backlash:width_deg=2"]
    up = _flow(rig, "supply", 0.0, effects=eff, approach=+1)["q_mm3_s"]
    down = _flow(rig, "supply", 0.0, effects=eff, approach=-1)["q_mm3_s"]
    clean_up = _flow(rig, "supply", 0.0, approach=+1)["q_mm3_s"]
    clean_down = _flow(rig, "supply", 0.0, approach=-1)["q_mm3_s"]
    assert clean_down == pytest.approx(clean_up, rel=0.02)
    assert down > 1.1 * up


def test_effect_pressure_law_changes_dp_dependence(rig):
    eff = ["pressure_law:side=drain,exponent=0.8"]
    for load in (0.3, 0.5):
        row = _flow(rig, "drain", -35.0, load=load, effects=eff)
        model = ValveModel.from_rig(rig).drain
        c_eff = row["q_mm3_s"] / model.flow(-35.0, row["p1_mpa"], row["dp_mpa"]) * row["dp_mpa"] ** 0.5
        # Q / (C o^2) = dp^0.8
        assert c_eff == pytest.approx(row["dp_mpa"] ** 0.8, rel=0.02)


def test_effect_saturation_caps_flow(rig):
    row = _flow(rig, "supply", 10.0, load=0.2, effects=["saturation:side=supply,q_max_mm3_s=3000"])
    assert 2500.0 < row["q_mm3_s"] <= 3000.0


def test_effect_sensor_gain_scales_reading(rig):
    run, trace = simulate_flow_step(rig, side="supply", cam_deg=0.0, load_mpag=0.4,
                                    effects=["sensor_gain:sensor=encoder,gain=1.1"])
    x = run.tables["encoder"]["position_mm"].to_numpy()
    np.testing.assert_allclose(x, 1.1 * trace["x_true_mm"], atol=0.001)


def test_effect_delay_adds_lag(rig, with_model):
    delayed, _ = _position_run(rig, model=True, effects=["delay:delay_s=0.1"])
    lags = []
    for run in (with_model[0], delayed):
        d, a = derive_samples(run), align_run(run)
        lags.append(_xcorr_lag(d["t_s"].to_numpy(), a["q_ref_mm3_s"].to_numpy(), d["q_mm3_s"].to_numpy()))
    assert lags[1] - lags[0] == pytest.approx(0.1, abs=0.02)


def _digest(folder):
    h = hashlib.sha256()
    for f in sorted(p for p in folder.rglob("*") if p.is_file()):
        h.update(f.relative_to(folder).as_posix().encode())
        h.update(f.read_bytes())
    return h.hexdigest()


def test_seed_reproduces_dataset_bit_for_bit(tmp_path):
    a = simulate_scenario("paper-position-model", tmp_path / "a", seed=3)
    b = simulate_scenario("paper-position-model", tmp_path / "b", seed=3)
    c = simulate_scenario("paper-position-model", tmp_path / "c", seed=4)
    assert _digest(a) == _digest(b)
    assert _digest(a) != _digest(c)


def test_truth_only_when_asked_and_effects_hidden(tmp_path):
    eff = "drift:side=drain,step=0.05,every=3"
    a = simulate_scenario("paper-position-model", tmp_path / "a", effects=[eff])
    assert not (a / "_truth.json").exists()
    text = " ".join(p.read_text() for p in a.rglob("run.json"))
    assert "drift" not in text
    b = simulate_scenario("paper-position-model", tmp_path / "b", effects=[eff], write_truth=True)
    assert "drift" in (b / "_truth.json").read_text()


def test_bad_scenario_and_effect(tmp_path):
    with pytest.raises(ConfigError, match="scenario"):
        simulate_scenario("nope", tmp_path / "x")
    with pytest.raises(ConfigError, match="drift: step"):
        Plant.from_rig(load_rig(), effects=["drift:step=abc"])
    simulate_scenario("paper-position-model", tmp_path / "y")
    with pytest.raises(ConfigError, match="already holds runs"):
        simulate_scenario("paper-position-model", tmp_path / "y")


def test_simulate_cli(tmp_path):
    from click.testing import CliRunner

    from seanv_analysis.cli import cli

    res = CliRunner().invoke(cli, ["simulate", "paper-position-model", "--out", str(tmp_path / "d"),
                                   "--effect", "delay:delay_s=0.1", "--write-truth", "--quiet"])
    assert res.exit_code == 0, res.output
    assert "wrote 1 runs" in res.output
    assert (tmp_path / "d" / "_truth.json").exists()
    res = CliRunner().invoke(cli, ["simulate", "paper-position-model", "--out", str(tmp_path / "e"),
                                   "--effect", "delay:bogus=1"])
    assert res.exit_code == 2
    assert "unknown parameter 'bogus'" in res.output


def test_list_effects_says_whole_sentences():
    """Issue 33, point 6: --list-effects cut the descriptions at their
    docstring's first line break ("the needle lags width/2 behind")."""
    import inspect

    from click.testing import CliRunner

    from seanv_analysis.cli import cli
    from seanv_analysis.cli.simulate_cmd import effect_summary
    from seanv_analysis.models.effects import EFFECTS

    res = CliRunner().invoke(cli, ["simulate", "--list-effects"])
    assert res.exit_code == 0
    text = " ".join(res.output.split())
    for name, cls in EFFECTS.items():
        summary = effect_summary(cls)
        first = inspect.cleandoc(cls.__doc__).split("\n\n")[0]
        assert summary == " ".join(first.split()) and summary.rstrip().endswith((".", ")")), name
        assert f"{name}: {summary}" in text, name
    assert "the needle lags width/2 behind the servo in the direction it last moved." in text


@pytest.mark.parametrize("effect", ["drfit:side=drain", "drift:side=drian"])
def test_a_bad_effect_leaves_no_out_folder(tmp_path, effect):
    """Issue 33, point 6: a typo'd --effect left an empty --out folder."""
    from click.testing import CliRunner

    from seanv_analysis.cli import cli

    res = CliRunner().invoke(cli, ["simulate", "paper-position-model", "--out",
                                   str(tmp_path / "new"), "--effect", effect])
    assert res.exit_code == 2 and res.stderr.startswith("error: ")
    assert not (tmp_path / "new").exists()


#: a rig whose supply needle centre makes eq. (4) non-monotonic (no threshold inverse)
BAD_GEOMETRY = "[valve.supply]\nneedle_x_c_mm = 0.0\nneedle_y_c_mm = 0.0\n"


def test_bad_rig_geometry_is_a_config_error(tmp_path):
    """The models raise ValueError for a bad geometry; the simulator, where a
    rig value of the user meets them, raises ConfigError with the same text,
    and the command line prints it on one line with exit code 2."""
    from click.testing import CliRunner

    from seanv_analysis.cli import cli

    rig = load_rig(overrides={"valve": {"supply": {"needle_x_c_mm": 0.0, "needle_y_c_mm": 0.0}}})
    with pytest.raises(ValueError, match="not monotonic"):
        ValveModel.from_rig(rig).supply.threshold_deg(3.3, 1.6)
    with pytest.raises(ConfigError, match="eq. \\(4\\) is not monotonic"):
        simulate_flow_step(rig, side="supply", cam_deg=0.0, load_mpag=0.3, hold_max_s=0.1)
    with pytest.raises(ConfigError, match="not monotonic"):
        FlowModelController.from_rig(rig)
    (tmp_path / "rig.toml").write_text(BAD_GEOMETRY)
    res = CliRunner().invoke(cli, ["simulate", "paper-position-model", "--out", str(tmp_path / "d"),
                                   "--rig", str(tmp_path / "rig.toml"), "--quiet"])
    assert res.exit_code == 2
    assert res.output.count("\n") == 1 and "not monotonic" in res.output


@pytest.mark.parametrize("over, match, schema", [
    ({"tube": {"inertance_factor": 0.0}}, "tube.inertance_factor: expected > 0",
     r"tube\.inertance_factor = 0\.0 is not positive"),
    ({"supply": {"droop_mpa_s_per_mm3": -1e-5}}, "supply.droop_mpa_s_per_mm3: expected >= 0",
     r"supply\.droop_mpa_s_per_mm3 = -1e-05 is outside the plausible range"),
])
def test_line_and_supply_keys_out_of_range_are_config_errors(over, match, schema):
    """A line without inertance (a division by zero in the tube's flow
    equation) or a supply that rises with flow is refused, naming the key:
    by the rig schema when the rig is loaded, and by the plant for a rig
    changed in code."""
    with pytest.raises(ConfigError, match=schema):
        load_rig(overrides=over)
    rig = load_rig().with_overrides(over)
    with pytest.raises(ConfigError, match=match):
        simulate_flow_step(rig, side="supply", cam_deg=0.0, load_mpag=0.3, hold_max_s=0.1)


def test_supply_droops_with_the_flow_drawn():
    """supply.droop_mpa_s_per_mm3: the logged supply pressure of a supply
    flow step falls by the droop x the actuator's flow; 0 leaves it at the
    rig's pressure (up to the ripple and the sensor noise)."""
    k = 2.0e-5
    for droop in (0.0, k):
        rig = load_rig(overrides={"supply": {"droop_mpa_s_per_mm3": droop}})
        run, trace = simulate_flow_step(rig, side="supply", cam_deg=5.0, load_mpag=0.3,
                                        hold_max_s=0.8)
        p = run.tables["pressure"]
        t, ps = p["t_s"].to_numpy(float), p["p_supply_mpag"].to_numpy(float)
        q = np.interp(t, np.arange(len(trace["q_true_mm3_s"])) * 1e-3, trace["q_true_mm3_s"])
        moving = q > 0.5 * q.max()
        expected = float(rig["supply"]["pressure_mpag"]) - droop * q[moving]
        assert np.mean(ps[moving] - expected) == pytest.approx(0.0, abs=0.004)
        assert q.max() > 1000.0


@pytest.mark.parametrize("kind", ["cam", "flow_model"])
def test_controller_replay_is_its_step_law_tick_by_tick(rig, kind):
    """``Controller.replay`` (one compiled loop over logged ticks) gives what
    ``step`` gives tick by tick, holds, releases and clipping included; a
    tick without a position is skipped (NaN), its state carried over, and a
    missing pressure counts as 0 MPaG."""
    ctrl = (CamController.from_rig(rig) if kind == "cam"
            else FlowModelController.from_rig(rig))
    rng = np.random.default_rng(1)
    n = 600
    x_ref = np.repeat([0.0, 30.0, 15.0, 33.0], n // 4)
    x = x_ref - np.concatenate([np.linspace(8.0, -0.3, n // 4)] * 4) + rng.normal(0, 0.05, n)
    x[17] = np.nan
    ps = 3.3 + rng.normal(0, 0.01, n)
    ph = 1.0 + rng.normal(0, 0.01, n)
    ph[40] = np.nan
    pt = np.zeros(n)
    got = ctrl.replay(x_ref, x, ps, ph, pt)
    state, want = ctrl.initial_state(), np.full(n, np.nan)
    for i in range(n):
        if not np.isfinite(x[i]):
            continue
        out, state = ctrl.step(state, x_ref[i], x[i], ps[i],
                               ph[i] if np.isfinite(ph[i]) else 0.0, pt[i])
        want[i] = out.cam_cmd_deg
    np.testing.assert_array_equal(got, want)
    assert np.isnan(got[17]) and np.isfinite(got).sum() == n - 1
    assert np.ptp(got[np.isfinite(got)]) > 5.0     # the law moved, not a constant
