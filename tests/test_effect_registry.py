"""The effects registry is the one place to extend (models/effects.py).

A toy effect, defined here only and registered for one test at a time,
must be tried by discover, named in its verdict and described in its
report without any other module knowing it. And the registry, discover's
candidates and the simulator's plant must agree on the built-in effects.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from html import escape as html_escape
from pathlib import Path
from types import SimpleNamespace
from typing import ClassVar

import numpy as np
import pandas as pd
import pytest

from seanv_analysis import ValveModel, load_rig
from seanv_analysis.discover import FlowData, discover_flow_steps, predict_static
from seanv_analysis.discover.candidates import candidate_specs
from seanv_analysis.discover.static import EffectSpec
from seanv_analysis.errors import ConfigError
from seanv_analysis.models import effects as fx
from seanv_analysis.models import side_pressures
from seanv_analysis.report import render_report
from seanv_analysis.stages import report_sections

RIG = load_rig()
MODEL = ValveModel.from_rig(RIG)
TOY_AMPLITUDE = 0.08   # C swings by +-8 % ...
TOY_PERIOD = 8         # ... over 8 runs


@pytest.fixture
def toy(monkeypatch):
    """A toy effect, registered in a copy of the registry for this test only.

    This is the whole recipe for a new effect: one class with its parameters,
    sentence and static form.
    """
    monkeypatch.setattr(fx, "EFFECTS", dict(fx.EFFECTS))

    @dataclass(frozen=True)
    class Ripple(fx.Effect):
        """C of both sides swings with use (a warm-up cycle of the rig):
        C (1 + amplitude sin(2 pi i / period_runs))."""

        name: ClassVar[str] = "ripple"
        PARAMS: ClassVar[dict[str, str]] = {
            "amplitude": "relative swing of C [-]",
            "period_runs": "runs per cycle [runs]"}
        SENTENCE: ClassVar[str] = ("C swings by {amplitude:.1%} with use, one cycle every "
                                   "{period_runs} runs")
        STATIC: ClassVar[fx.StaticForm] = fx.StaticForm(
            ("amplitude",), (0.0,), (-0.5,), (0.5,), {"period_runs": TOY_PERIOD}, ("run_index",))

        amplitude: float = 0.05
        period_runs: int = TOY_PERIOD

        def __post_init__(self):
            self._check(abs(self.amplitude) < 1.0, "amplitude", "|amplitude| < 1")

        @classmethod
        def apply_static(cls, terms, data, rows, p):
            phase = 2.0 * np.pi * data.run_index[rows] / p["period_runs"]
            terms.c_multiplier[rows] *= 1.0 + p["amplitude"] * np.sin(phase)

    return Ripple


def flow_step_summary(seed: int = 0, effects: dict | None = None, *, rel_noise: float = 0.03,
                      abs_noise_mm3_s: float = 20.0) -> pd.DataFrame:
    """Per-run flow-step summary over a paper-like grid (both sides, 4 loads,
    alternating approach): the static prediction of the rig's valve with
    ``effects`` ({label: (EffectSpec, values)}) applied, plus seeded noise."""
    rng = np.random.default_rng(seed)
    rows, i = [], 0
    for side in ("supply", "drain"):
        cams = np.arange(-7.5, 10.1, 2.5) if side == "supply" else np.arange(-40, -21, 2.5)
        for load in (0.3, 0.35, 0.4, 0.45):
            for cam in cams:
                for rep in range(3):
                    p_head = 4 * load + (0.6 if side == "supply" else -0.6) + rng.normal(0, 0.02)
                    p1, dp = side_pressures(side, 3.3, p_head, 0.0)
                    rows.append(dict(run_id=f"r{i}", kind="flow_step", side=side, run_index=i,
                                     load_mpag=load, cam_deg=cam, cam_measured_deg=cam,
                                     cam_approach=1 if (side == "supply") == (rep % 2 == 0) else -1,
                                     q_mm3_s=0.0, dp_mpa=float(dp), p1_mpa=float(p1), excluded=""))
                    i += 1
    df = pd.DataFrame(rows)
    q = predict_static(MODEL, FlowData.from_summary(df), effects)
    q = q * (1 + rng.normal(0, rel_noise, q.size)) + rng.normal(0, abs_noise_mm3_s, q.size)
    df["q_mm3_s"] = q
    df["excluded"] = np.where(np.abs(q) > 50, "", "leakage")
    return df


def _with(effect: type[fx.Effect], side: str, **values) -> dict:
    spec = EffectSpec.from_form(effect.name, side, effect.STATIC)
    return {spec.label: (spec, np.array([values[p] for p in spec.params]))}


def test_toy_effect_is_a_candidate(toy):
    data = FlowData.from_summary(flow_step_summary(0))
    labels = [s.label for s in candidate_specs(data, None)]
    assert "ripple[both]" in labels
    assert toy in fx.static_effects()


def test_discover_names_the_toy_effect_and_reports_it(toy):
    df = flow_step_summary(1, _with(toy, "both", amplitude=TOY_AMPLITUDE, period_runs=TOY_PERIOD))
    d = discover_flow_steps(df, model=MODEL)
    assert d.verdict == "effect_found"
    first = d.effects[0]
    assert (first.name, first.side) == ("ripple", "both")
    assert first.params["amplitude"] == pytest.approx(TOY_AMPLITUDE, abs=0.02)
    assert first.params["period_runs"] == TOY_PERIOD
    assert d.rmse_after_mm3_s <= 0.7 * d.rmse_before_mm3_s
    report = d.report()
    assert "misses ripple (both)" in report
    assert first.sentence() in report
    assert "with use, one cycle every 8 runs" in report
    # what discover found rebuilds the effect (what validate would simulate)
    _, specs = d.augmented_model_and_effects()
    assert specs[0].startswith("ripple:amplitude=")
    # and the HTML report names it with its sentence (no report code knows "ripple")
    html = render_report(_record(d), report_sections())
    assert "ripple" in html and html_escape(first.sentence(), quote=True) in html


def _record(discovery) -> SimpleNamespace:
    """A pipeline record holding only a discovery (the report reads it duck-typed)."""
    pipeline = SimpleNamespace(name="toy", description="", source=None,
                               to_dict=lambda: {"name": "toy"})
    return SimpleNamespace(
        pipeline=pipeline, data=[Path("data")], executor="serial", command=["toy"], rig=None,
        runs_found=0, runs_read=0, summary=pd.DataFrame(), excluded={}, failed=[], flowfit=None,
        tracking=None, validation=None, validation_augmented=None, discovery=discovery,
        figures={}, stage_errors={}, stage_notes={}, warnings=[], input_hashes={},
        manifest_path=None, timings_s={}, computed={}, cached={})


def test_toy_effect_is_gone_after_its_test():
    assert "ripple" not in fx.EFFECTS
    data = FlowData.from_summary(flow_step_summary(0))
    assert all(s.name != "ripple" for s in candidate_specs(data, None))


def test_defining_an_effect_registers_it(monkeypatch):
    monkeypatch.setattr(fx, "EFFECTS", dict(fx.EFFECTS))

    @dataclass(frozen=True)
    class Quiet(fx.Effect):
        """Does nothing (registration only)."""

        name: ClassVar[str] = "quiet"

    assert fx.EFFECTS["quiet"] is Quiet
    assert fx.parse_effect("quiet") == Quiet()
    assert Quiet not in fx.static_effects() and Quiet not in fx.dynamic_effects()
    with pytest.raises(ValueError, match="registered twice"):
        @dataclass(frozen=True)
        class Drift(fx.Effect):
            """Another drift."""

            name: ClassVar[str] = "drift"


# The registry, discover and the simulator agree ------------------------------------

def test_every_named_static_effect_is_a_discover_candidate():
    data = FlowData.from_summary(flow_step_summary(0))
    specs = candidate_specs(data, None)
    got = {(s.name, s.side) for s in specs}
    want = set()
    for cls in fx.vocabulary_effects():
        want |= {(cls.name, side) for side in (("supply", "drain") if cls.sided() else ("both",))}
    assert got == want
    # and nothing else: the candidates are the registry's, in its order
    order = list(fx.EFFECTS)
    sided = [s for s in specs if s.side != "both"]
    assert [s.name for s in sided if s.side == "supply"] == [
        c.name for c in fx.vocabulary_effects() if c.sided()]
    both = [s.name for s in specs if s.side == "both"]
    assert both == sorted(both, key=order.index)


#: discover's candidates on a two-sided data set before the generic ``term``
#: effect was registered
CANDIDATES = ["drift[supply]", "threshold_shift[supply]", "pressure_law[supply]",
              "saturation[supply]", "drift[drain]", "threshold_shift[drain]",
              "pressure_law[drain]", "saturation[drain]", "backlash[both]", "sensor_gain[both]"]


def test_the_generic_term_is_not_a_discover_candidate():
    """``term`` has a static form (a given formula can be predicted) but is
    no named effect: discover never tries it, and its candidate list is the
    one it had before ``term`` existed."""
    term = fx.EFFECTS["term"]
    assert term in fx.static_effects() and term in fx.dynamic_effects()
    assert term not in fx.vocabulary_effects() and not term.VOCABULARY
    data = FlowData.from_summary(flow_step_summary(0))
    assert [s.label for s in candidate_specs(data, None)] == CANDIDATES


def test_every_effect_has_a_form_a_sentence_and_a_spec():
    for name, cls in fx.EFFECTS.items():
        assert cls.name == name
        assert cls.STATIC is not None or cls.has_dynamic_form(), name
        effect = cls()
        assert fx.parse_effect(effect.spec()) == effect
        params = {k: v for k, v in effect.params().items() if k != "side"}
        side = getattr(effect, "side", "both")
        assert cls.sentence(side, params)   # the report's text for it
        assert set(cls.PARAMS) == {f.name for f in dataclasses.fields(cls)}


def test_static_forms_are_consistent():
    data = FlowData.from_summary(flow_step_summary(0))
    for cls in fx.static_effects():
        form = cls.STATIC
        assert len(form.params) == len(form.x0) == len(form.lower) == len(form.upper)
        assert all(lo <= x <= hi for x, lo, hi in zip(form.x0, form.lower, form.upper)), cls.name
        assert set(form.params) | set(form.fixed) <= set(cls.PARAMS), cls.name
        assert all(hasattr(data, v) for v in form.needs), cls.name
        # the start values leave eq. (5) unchanged where the effect is neutral
        spec = EffectSpec.from_form(cls.name, "supply" if cls.sided() else "both", form)
        if not spec.needs_search:
            predict_static(MODEL, data, {spec.label: (spec, np.array(spec.x0))})


def _same_valve(a: tuple, b: tuple) -> bool:
    return all(np.array_equal(x, y) for x, y in zip(a, b))


def test_simulator_puts_in_every_dynamic_effect():
    from seanv_analysis.sim.plant import Plant

    base = Plant.from_rig(RIG)
    neutral = base.packed_params(neutral_deg=-15.0, x_stop_mm=(0.0, 40.0))
    for cls in fx.dynamic_effects():
        plant = Plant.from_rig(RIG, effects=[cls.name])
        changed = not np.array_equal(plant.packed_params(neutral_deg=-15.0, x_stop_mm=(0.0, 40.0)),
                                     neutral)
        changed |= not all(_same_valve(plant.valve_at(i), base.valve_at(i)) for i in range(12))
        changed |= not np.array_equal(plant.term_at(3), base.term_at(3))
        assert changed, f"{cls.name}: the plant ignores it"
    for cls in fx.EFFECTS.values():
        if not cls.has_dynamic_form():
            plant = Plant.from_rig(RIG, effects=[cls.name])
            assert _same_valve(plant.valve_at(5), base.valve_at(5))
            assert np.array_equal(plant.term_at(5), base.term_at(5))


def test_plant_terms_fold_effects_in_order():
    from seanv_analysis.sim.plant import Plant

    plant = Plant.from_rig(RIG, effects=["drift:side=drain,step=0.1,every=2",
                                         "threshold_shift:side=drain,rate_mm_per_run=1e-4",
                                         "pressure_law:side=supply,exponent=0.6",
                                         "backlash:width_deg=1.5", "delay:delay_s=0.2",
                                         "sensor_gain:sensor=encoder,gain=1.1",
                                         "sensor_gain:sensor=p_head,gain=0.9"])
    drain = plant.valve_terms("drain", 4)
    assert drain.c_multiplier == pytest.approx(0.9 ** 2)
    assert drain.z0_offset_mm == pytest.approx(4e-4)
    assert drain.dp_exponent is None
    assert plant.valve_terms("supply", 4) == fx.ValveTerms(dp_exponent=0.6)
    extra = plant.plant_terms()
    assert dict(extra.items()) == {"BACKLASH": 1.5, "DELAY": 0.2, "GAIN_X": 1.1, "GAIN_PS": 1.0,
                                   "GAIN_PH": 0.9, "GAIN_PL": 1.0}


# Errors: ValueError in models, ConfigError at the simulator's boundary -------------

@pytest.mark.parametrize("spec,match", [
    ("nope", "unknown effect 'nope'"),
    ("drift:step=abc", "drift: step: expected a number"),
    ("drift:every=1.5", "drift: every: expected an integer"),
    ("drift:side=left", "drift: side: expected 'supply' or 'drain'"),
    ("delay:bogus=1", "unknown parameter 'bogus'"),
    ("sensor_gain:sensor=thermo", "sensor_gain: sensor: expected one of"),
    ("saturation:q_max_mm3_s=-1", "saturation: q_max_mm3_s: expected a positive flow"),
    ("term:side=left", "term: side: expected 'supply' or 'drain'"),
    ("term:mode=pow", "term: mode: expected one of mul, add, threshold"),
    ("term:expr=__import__('os')", "term: expr .*unknown function '__import__'"),
    ("term:expr=dp**p1", "term: expr .*exponent of \\*\\* must be a constant"),
    ("term:expr=", "term: expected param=value, got 'expr='"),
    ("term:expr='dp", "term: expr: the quote ' is not closed"),
    ("term:expr='dp' x", "term: expr: expected ',' after the quoted value"),
    ("term:side=drain,bogus=1,expr=dp", "term: unknown parameter 'bogus'"),
])
def test_bad_spec_is_a_value_error_in_models_and_a_config_error_in_sim(spec, match):
    from seanv_analysis.sim.plant import Plant

    with pytest.raises(ValueError, match=match):
        fx.parse_effect(spec)
    with pytest.raises(ConfigError, match=match):
        Plant.from_rig(RIG, effects=[spec])


def test_term_spec_takes_commas_in_its_expression():
    """``expr`` runs to the end of the spec (commas included), or is quoted;
    it is kept in canonical form, and the spec round-trips."""
    e = fx.parse_effect("term:side=drain,mode=add,expr=-20*clip(dp, 0, max(p1, 1))")
    assert (e.side, e.mode, e.expr) == ("drain", "add", "-20*clip(dp, 0, max(p1, 1))")
    assert fx.parse_effect(e.spec()) == e
    assert e.spec() == "term:side=drain,mode=add,expr=-20*clip(dp, 0, max(p1, 1))"
    q = fx.parse_effect("term:expr=\"min(dp , 1)\" , mode=threshold,side=drain")
    assert (q.side, q.mode, q.expr) == ("drain", "threshold", "min(dp, 1)")
    assert fx.parse_effect({"name": "term", "expr": "0.1 * q"}).expr == "0.1*q"
    assert fx.parse_effect("term:side=supply,expr=0.02 * dp ** 1.5") == \
        fx.Term(side="supply", expr="0.02*dp**(3/2)")
    assert e.program.variables == ("dp", "p1")
    assert "Q -> Q + -20*clip(dp, 0, max(p1, 1)) [mm^3/s]" in e.sentence("drain", e.params())
    assert "theta_d -> theta_d + min(dp, 1) [deg]" in q.sentence("drain", q.params())
    with pytest.raises(ValueError, match="term given twice for drain"):
        fx.parse_effects([e, "term:side=drain,mode=mul,expr=0.1"])


def _term(side: str, mode: str, expr: str) -> dict:
    spec = EffectSpec.from_form("term", side, fx.Term.STATIC)
    spec = dataclasses.replace(spec, fixed={"mode": mode, "expr": expr})
    return {spec.label: (spec, np.array([]))}


def test_term_static_form_predicts_the_formula():
    """The static form (discover's predict_static) applies the three modes
    to eq. (5) on the term's side only."""
    data = FlowData.from_summary(flow_step_summary(0))
    base = predict_static(MODEL, data)
    sup = data.side == "supply"
    p1, dp = side_pressures("supply", data.p_supply_mpag, data.p_head_mpag, data.p_tank_mpag)
    q = predict_static(MODEL, data, _term("supply", "mul", "-0.2*tanh(dp/0.5)"))
    np.testing.assert_allclose(q[sup], base[sup] * (1 - 0.2 * np.tanh(dp[sup] / 0.5)), rtol=1e-12)
    np.testing.assert_array_equal(q[~sup], base[~sup])
    q = predict_static(MODEL, data, _term("supply", "add", "30*dp**1.5 + 0*q"))
    np.testing.assert_allclose(q[sup], base[sup] + 30 * dp[sup] ** 1.5, rtol=1e-12)
    # threshold + s approach on the drain side: the opening theta_d - theta
    # grows by s approach, the same as the cam angle moved by -s approach
    dr = ~sup
    q = predict_static(MODEL, data, _term("drain", "threshold", "0.4*approach"))
    moved = FlowData(**{**{f: getattr(data, f) for f in data.__dataclass_fields__},
                        "theta_deg": data.theta_deg - 0.4 * data.approach})
    np.testing.assert_allclose(q[dr], predict_static(MODEL, moved)[dr], rtol=1e-12)
    np.testing.assert_array_equal(q[sup], base[sup])
    # dtheta is the opening past the threshold in use; load and run reach it
    q = predict_static(MODEL, data, _term("drain", "mul", "0.01*run + 0.5*(load - 0.4)"))
    np.testing.assert_allclose(q[dr], base[dr] * (1 + 0.01 * data.run_index[dr]
                                                  + 0.5 * (data.load_mpag[dr] - 0.4)), rtol=1e-12)
    opening = data.theta_deg[sup] - MODEL.supply.threshold_deg(p1[sup], dp[sup])
    q = predict_static(MODEL, data, _term("supply", "mul", "0.01*dtheta"))
    np.testing.assert_allclose(q[sup], base[sup] * (1 + 0.01 * opening), rtol=1e-12)


def test_one_effect_of_a_name_per_side_or_sensor():
    with pytest.raises(ValueError, match="drift given twice for drain"):
        fx.parse_effects(["drift:side=drain", "drift:side=drain,step=0.1"])
    with pytest.raises(ValueError, match="sensor_gain given twice for p_head_mpag"):
        fx.parse_effects(["sensor_gain:sensor=pressure", "sensor_gain:sensor=p_head"])
    assert len(fx.parse_effects(["drift:side=drain", "drift:side=supply"])) == 2
