"""Discover beyond its vocabulary (issue 19): where the named effects (if any)
leave a structured residual, the term search (``seanv_analysis.discover.terms``) proposes
the missing correction of eq. (5) in closed form.

Data: the foreign rig's flow steps (``tests/foreign_rig.py``, 27-81 runs, loads
0.1/0.3/0.5 MPaG) with one of its out-of-vocabulary effects. What must hold,
against the known truth: the proposal has the injected functional form (or
one equal to it over the data's runs) with the true coefficient inside its
interval where the form is exact, it lowers the held-out error, the verdict
stays 'unexplained' (never a known effect); clean data get no proposal; the
JSON follows its schema and names units; the report has its paragraph; the
augmented model carries the term for the closed-loop check.
"""
from __future__ import annotations

import json

import numpy as np
import pytest
from foreign_rig import ForeignTruth, flowstep_plan, write_flowsteps
from json_schemas import check_schema, keys_without_unit
from test_foreign_rig import run_cli

from seanv_analysis.api import load_dataset
from seanv_analysis.discover import discover_flow_steps, predict_static
from seanv_analysis.discover.terms import term_spec
from seanv_analysis.models import ValveModel
from seanv_analysis.models.effects import Term, parse_effects

# the rig's protocol (81 runs), and the smaller plans of the cases whose
# checks hold on them (writing the data and reading them back is most of
# this module's time). Measured at the fixtures' seeds: the leak's term holds
# at 1 sweep per load (27 runs), the choke's at 2 (54; at 1 no term is
# proposed), the approach's with 3 drain angles (63; at 2 sweeps no term),
# the load-dependent C's with 3 supply angles (72; at 2 sweeps no term). The
# clean case keeps PLAN, as benchmarks/bench_discover.py's clean seeds do:
# no proposal on the most data.
_PLAN_R = {"supply_cams": (-5.0, 0.0, 5.0, 10.0), "drain_cams": (-40.0, -32.5, -25.0, -20.0, -15.0),
           "loads": (0.1, 0.3, 0.5), "repeats": 3}
PLAN = flowstep_plan(**_PLAN_R)
PLAN_LEAK = flowstep_plan(**{**_PLAN_R, "repeats": 1})
PLAN_CHOKE = flowstep_plan(**{**_PLAN_R, "repeats": 2})
PLAN_APPROACH = flowstep_plan(**{**_PLAN_R, "drain_cams": (-40.0, -25.0, -15.0)})
PLAN_LOAD_C = flowstep_plan(**{**_PLAN_R, "supply_cams": (-5.0, 5.0, 10.0)})
CHOKE = {"side": "supply", "dp_c_mpa": 1.5, "n": 4.0}
LEAK = {"side": "supply", "k_mm3_s": 60.0, "m": 2.0}
SHIFT = {"side": "supply", "shift_deg": 0.6}
LOAD_C = {"side": "drain", "k_per_mpa": 1.0, "load_ref_mpag": 0.3}
CASES = {"choke": (1, ForeignTruth(dp_choke=CHOKE), PLAN_CHOKE),
         "leak": (0, ForeignTruth(pressure_leak=LEAK), PLAN_LEAK),
         "load_c": (0, ForeignTruth(load_c=LOAD_C), PLAN_LOAD_C),
         "approach": (1, ForeignTruth(approach_threshold=SHIFT, approach_overshoot_deg=1.5),
                      PLAN_APPROACH),
         "clean0": (0, ForeignTruth(), PLAN)}   # clean seeds 0-5: benchmarks/bench_discover.py


@pytest.fixture(scope="module")
def folders(tmp_path_factory):
    """{case: data folder} of the foreign rig's flow steps."""
    out = {}
    for name, (seed, truth, plan) in CASES.items():
        out[name] = tmp_path_factory.mktemp(name)
        write_flowsteps(out[name], plan=plan, seed=seed, truth=truth)
    return out


@pytest.fixture(scope="module")
def found(folders):
    """{case: Discovery} on the foreign rig's flow steps."""
    out = {}
    for name, folder in folders.items():
        ds = load_dataset(folder)
        out[name] = discover_flow_steps(ds.summary, model=ValveModel.from_rig(ds.rig), seed=0)
    return out


def _relative_correction(d):
    """(fit runs of the term's side, log of the flow with the proposed term
    over the flow without it, both with the valve refitted with the term)."""
    t = d.proposed_term
    data = d.fit_data.subset(d.fit_data.side == t.side)
    spec = term_spec(t.side, t.mode, t.features)
    with_term = predict_static(t.model, data, {spec.label: (spec, np.asarray(t.coefficients))})
    without = predict_static(t.model, data)
    return data, np.log(with_term / without), without


def test_choke_is_proposed_as_a_term_of_the_supply_side_that_matches_the_truth(found):
    d = found["choke"]
    t = d.proposed_term
    assert d.verdict == "unexplained" and not d.effects and t is not None
    assert t.side == "supply" and t.p_value < 0.01
    assert t.heldout_drop >= 0.3, (t.rmse_before_mm3_s, t.rmse_after_mm3_s)
    # its shape over the fit runs is the true factor (1 + (dp/dp_c)^n)^(-1/n),
    # up to a constant (C carries it): log-ratios centred
    data, got, q = _relative_correction(d)
    dp = data.p_supply_mpag - data.p_head_mpag
    want = -np.log1p((dp / CHOKE["dp_c_mpa"]) ** CHOKE["n"]) / CHOKE["n"]
    open_ = q > 100.0
    got, want = got[open_] - got[open_].mean(), want[open_] - want[open_].mean()
    assert np.corrcoef(got, want)[0, 1] > 0.95
    assert np.sqrt(np.mean((got - want) ** 2) / np.mean(want ** 2)) < 0.2


def test_pressure_leak_is_proposed_as_k_dp_squared(found):
    t = found["leak"].proposed_term
    assert t is not None and (t.side, t.mode) == ("supply", "add")
    assert t.features[0] == "dp**2"
    lo, hi = t.coefficients_ci95[0]
    assert lo < LEAK["k_mm3_s"] < hi and abs(t.coefficients[0] - LEAK["k_mm3_s"]) < 3.0
    # an added flow per MPa^2: the units module's derived unit and key suffix
    (a1,) = t.estimates.values()
    assert (a1.unit, a1.suffix) == ("mm^3/(s MPa^2)", "_mm3_per_s_mpa2")
    # the leak feeds the head in the drain runs too (the supply needle
    # sealed, dp = p_supply - p_head): an 'add' term acts there as well, so
    # the held-out error falls to the noise
    assert t.heldout_drop >= 0.6, (t.rmse_before_mm3_s, t.rmse_after_mm3_s)
    assert t.rmse_after_mm3_s < found["clean0"].rmse_after_mm3_s * 1.5


def test_approach_dependent_threshold_is_proposed_as_a_shift_by_direction(found):
    """theta_d + 0.6 a (a = +1 up, -1 down): the threshold of a run that came
    down lies 1.2 deg below that of one that came up. A quarter of the runs'
    logs start at the angle (a unknown, 0 in the summary; they came up), so
    the search states it as a shift of the runs that came down against all
    others, min(approach, 0), or as shift x approach."""
    t = found["approach"].proposed_term
    assert t is not None and (t.side, t.mode) == ("supply", "threshold")
    assert t.features in (("approach",), ("min(approach, 0)",)), t.features
    per_unit = 2.0 if t.features == ("approach",) else 1.0   # up minus down, per coefficient
    lo, hi = (per_unit * x for x in t.coefficients_ci95[0])
    assert lo < 2.0 * SHIFT["shift_deg"] < hi
    assert [e.unit for e in t.estimates.values()] == ["deg"]   # a threshold shift per direction
    assert t.heldout_drop >= 0.6


def test_load_dependent_c_gets_a_term_beyond_the_pressure_law_it_resembles(found):
    """In drain runs the head pressure, hence dp, follows the load, so a C
    that grows with the load looks like a pressure law to the vocabulary:
    that is named first, and what it leaves is a proposed term of the drain
    side that cuts the held-out error by more than two thirds again."""
    d = found["load_c"]
    t = d.proposed_term
    assert [(e.name, e.side) for e in d.effects] == [("pressure_law", "drain")]
    assert d.verdict == "effect_found"
    assert t is not None and t.side == "drain" and t.p_value < 0.01
    assert t.heldout_drop >= 0.7, (t.rmse_before_mm3_s, t.rmse_after_mm3_s)
    assert t.rmse_after_mm3_s < 0.05 * d.rmse_before_mm3_s      # the base model's
    assert "Beyond the named effects, the flow-step residual holds a proposed term" in d.report()


def test_clean_data_get_no_proposal(found):
    """One clean seed here; the rate over seeds 0-5 (seed 2, checked here
    before, among them) is benchmarks/bench_discover.py's
    ``terms_clean_foreign``."""
    assert found["clean0"].proposed_term is None and found["clean0"].verdict == "none"


def test_json_schema_report_and_augmented_model(found):
    d = found["choke"]
    doc = d.to_json_dict()
    check_schema("discover", doc)
    assert keys_without_unit(doc) == []
    pt = doc["proposed_term"]
    assert pt["spec"].startswith("term:side=supply,mode=")
    assert pt["heldout_rmse_after_mm3_s"] < pt["heldout_rmse_before_mm3_s"]
    assert [c["feature"] for c in pt["coefficients"]] == list(d.proposed_term.features)
    # the coefficients are estimates: JSON records, rows of to_frame() and
    # Discovery.params, one name and one number each
    est = d.proposed_term.estimates
    assert [c["name"] for c in pt["coefficients"]] == list(est) and set(est) <= set(d.params)
    rows = d.to_frame().set_index("name").loc[list(est)]
    for c, e in zip(pt["coefficients"], est.values()):
        assert c[f"value{e.suffix}"] == e.value == rows.loc[e.name, "value"]
        assert c["unit"] == e.unit == rows.loc[e.name, "unit"]
        assert rows.loc[e.name, "effect"] == "term"
    text = d.report()
    assert "No named effect explains the flow-step residual; a proposed term (not a known " \
           "effect): " \
           f"{d.proposed_term.spec} lowers the held-out error from" in text
    model, specs = d.augmented_model_and_effects()
    (term,) = parse_effects(specs)
    assert isinstance(term, Term) and term.expr == d.proposed_term.expr
    assert model is d.proposed_term.model
    assert d.augmented_model_dict()["proposed_term"] == d.proposed_term.spec
    assert "proposed_term" not in found["clean0"].to_json_dict()


def test_the_figure_shows_the_residual_with_the_term(found, tmp_path):
    from seanv_analysis.plots.residuals import plot_discovery_residuals

    paths = plot_discovery_residuals(found["approach"], out_dir=tmp_path, formats=("png",))
    assert paths and paths[0].stat().st_size > 0
    ax = found["approach"].plot(variable="cam_approach")
    assert any("proposed term" in t.get_text() for t in ax.get_legend().get_texts())


def test_the_discover_command_writes_the_proposal(folders, found, tmp_path):
    doc = run_cli("discover", folders["choke"], "--out", tmp_path / "out", "--json", "-q",
                  "--no-figures")  # the figure: test_the_figure_shows_the_residual_with_the_term
    check_schema("discover", doc)
    assert doc["verdict"] == "unexplained"
    assert doc["proposed_term"]["spec"] == found["choke"].proposed_term.spec
    text = (tmp_path / "out" / "discover.txt").read_text()
    assert "a proposed term (not a known effect): term:side=supply" in text
    model = json.loads((tmp_path / "out" / "model_augmented.json").read_text())
    assert model["proposed_term"] == doc["proposed_term"]["spec"]


def test_the_parametric_term_is_the_term_effect_with_its_expression(found):
    """The refit's form (features + coefficients as parameters) predicts what
    the ``term`` effect with the written expression predicts; every library
    feature is a valid expression of the grammar."""
    from seanv_analysis.discover.static import EffectSpec
    from seanv_analysis.discover.terms import library, side_variables
    from seanv_analysis.models.expr import compile_expr

    d = found["leak"]
    t = d.proposed_term
    spec = term_spec(t.side, t.mode, t.features)
    got = predict_static(t.model, d.fit_data, {spec.label: (spec, np.asarray(t.coefficients))})
    fixed = EffectSpec("term", t.side, (), (), (), (), {"mode": t.mode, "expr": t.expr})
    want = predict_static(t.model, d.fit_data, {"t": (fixed, np.array([]))})
    assert np.allclose(got, want, rtol=1e-3, atol=0.5)       # 4 significant digits in the text
    assert Term.linear_expr([60.0, -1.5], ["dp**2", "load"]) == "60*dp**2 + -1.5*load"
    feats = library(side_variables(d.model, d.fit_data, "supply"))
    assert 30 < len(feats) < 100 and "dp**2" in feats
    assert all(compile_expr(f).text == f for f in feats)
