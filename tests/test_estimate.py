"""One estimate type (issue 32): every result's estimated numbers are
:class:`seanv_analysis.estimate.Estimate` objects in ``result.params``
(FlowFit, Identification, Discovery), in units of the one unit table; the
frame (``params.to_frame()``, the result's ``to_frame()``) and the JSON are
made from the same objects, so they agree on names and values; an
identified value lies in its 95 % interval; the type round-trips to JSON."""
from __future__ import annotations

import json
import math

import pytest
from json_schemas import check_schema, columns_without_unit, keys_without_unit

from seanv_analysis.estimate import SOURCES, Estimate, Estimates
from seanv_analysis.jsonable import dumps, json_num
from seanv_analysis.units import DIMENSIONLESS_SUFFIXES, UNIT_SUFFIXES, key_suffix

#: every unit an estimate may have: the table's and the dimensionless ones
TABLE_UNITS = set(UNIT_SUFFIXES.values()) | set(DIMENSIONLESS_SUFFIXES)


def check_params(params: Estimates) -> None:
    """Each estimate: its name is its key in ``params``, its unit is from
    the unit table, its source known, its value inside its 95 % interval
    where identified, its record round-trips through JSON text; the long
    frame holds the same names and numbers."""
    assert isinstance(params, Estimates) and params
    for name, e in params.items():
        assert isinstance(e, Estimate) and e.name == name
        assert e.unit in TABLE_UNITS, (name, e.unit)
        assert e.source in SOURCES
        if e.identified:
            assert e.inside(), (name, e.value, e.ci95)
        back = Estimate.from_json_dict(json.loads(dumps(e.to_json_dict())))
        assert back.to_json_dict() == json.loads(dumps(e.to_json_dict()))
        assert keys_without_unit(e.to_json_dict()) == []
    frame = params.to_frame()
    assert list(frame["name"]) == list(params)
    for row, e in zip(frame.itertuples(), params.values()):
        assert [json_num(row.value), json_num(row.ci95_lo), json_num(row.ci95_hi)] == \
            [json_num(e.value), *map(json_num, e.ci95)]
        assert row.unit == e.unit
    doc = Estimates.from_json_dict(json.loads(dumps(params.to_json_dict())))
    assert doc.to_json_dict() == json.loads(dumps(params.to_json_dict()))


# the type ---------------------------------------------------------------------

def test_estimate_record_round_trips_and_names_its_unit():
    e = Estimate("supply.C", 17.44, "mm^3/(s deg^2 MPa^0.5)", (17.35, 17.53), 0.045,
                 method="joint fit of eq. (5)", constrained_by="24 flow steps", default=17.435)
    d = e.to_json_dict()
    assert d == {"name": "supply.C", "value_mm3_s_deg2_sqrtMPa": 17.44,
                 "ci95_mm3_s_deg2_sqrtMPa": [17.35, 17.53], "stderr_mm3_s_deg2_sqrtMPa": 0.045,
                 "default_mm3_s_deg2_sqrtMPa": 17.435, "bounds_mm3_s_deg2_sqrtMPa": [None, None],
                 "unit": "mm^3/(s deg^2 MPa^0.5)",
                 "source": "identified", "method": "joint fit of eq. (5)",
                 "constrained_by": "24 flow steps", "note": ""}
    assert Estimate.from_json_dict(json.loads(json.dumps(d))) == e
    assert (e.key, e.ci95_key) == ("C_mm3_s_deg2_sqrtMPa", "C_ci95_mm3_s_deg2_sqrtMPa")
    assert e.wide_items() == {"C_mm3_s_deg2_sqrtMPa": 17.44, "C_ci95_lo_mm3_s_deg2_sqrtMPa": 17.35,
                              "C_ci95_hi_mm3_s_deg2_sqrtMPa": 17.53}
    assert "95 % [17.35, 17.53]" in repr(e) and "stderr 0.045" in repr(e)
    # unknown numbers are null in JSON and NaN back; a count stays an int
    n = Estimate("drain.drift.every", 7, "runs", method="grid search")
    d = json.loads(dumps(n.to_json_dict()))
    assert d["value_runs"] == 7 and d["ci95_runs"] == [None, None] and d["stderr_runs"] is None
    back = Estimate.from_json_dict(d)
    assert back.value == 7 and all(math.isnan(v) for v in back.ci95) and not back.has_interval
    assert back.inside() and "no 95 % interval" in repr(back)
    assert Estimate("x.step", 0.1, "-").key == "step_ratio"


def test_estimate_refuses_a_unit_outside_the_table_and_an_unknown_source():
    with pytest.raises(ValueError, match="UNIT_SUFFIXES"):
        Estimate("a.b", 1.0, "furlong")
    with pytest.raises(ValueError, match="source: expected one of identified"):
        Estimate("a.b", 1.0, "mm", source="guessed")
    with pytest.raises(ValueError, match="no 'unit'"):
        Estimate.from_json_dict({"name": "a", "value_mm": 1.0})
    with pytest.raises(ValueError, match="given twice"):
        Estimates.of([Estimate("a", 1.0, "mm"), Estimate("a", 2.0, "mm")])
    assert key_suffix("") == key_suffix("-") == "_ratio"


def test_value_outside_its_interval_is_seen():
    assert not Estimate("a.b", 2.0, "mm", (0.0, 1.0)).inside()
    assert Estimate("a.b", 1.0, "mm", (0.0, math.inf)).inside()   # one-sided: not known


def test_a_value_on_a_bound_of_its_fit_is_seen():
    e = Estimate("drain.drift.step", 0.5, "-", (0.45, 0.55), bounds=(-0.5, 0.5))
    assert e.at_bound() and "at a bound of the fit" in repr(e)
    assert e.to_json_dict()["bounds_ratio"] == [-0.5, 0.5]
    assert Estimate.from_json_dict(e.to_json_dict()) == e
    free = Estimate("x.g", 0.0, "mm^3/(s MPa)", bounds=(0.0, math.inf))
    assert free.at_bound() and free.to_json_dict()["bounds_mm3_s_per_mpa"] == [0.0, None]
    assert not Estimate("x.g", 3.0, "mm^3/(s MPa)", bounds=(0.0, math.inf)).at_bound()
    assert Estimates.of([e]).to_frame()["at_bound"].tolist() == [True]


# FlowFit ------------------------------------------------------------------------

@pytest.fixture(scope="module")
def flow_fit():
    from synthetic_flow import synthetic_flow_summary

    from seanv_analysis.config import load_rig
    from seanv_analysis.fit import fit_flow
    from seanv_analysis.models import ValveModel

    rig = load_rig()
    return fit_flow(synthetic_flow_summary(ValveModel.from_rig(rig), rig, seed=2), rig, n_boot=30)


def test_flowfit_params_frame_and_json_agree(flow_fit):
    from seanv_analysis.fit import Parameter
    from seanv_analysis.fit.flowfit import C_KEY

    p = flow_fit.params
    check_params(p)
    assert list(p) == ["supply.z0", "supply.C", "drain.z0", "drain.C", "leakage.g"]
    assert Parameter is Estimate
    doc, frame = flow_fit.to_json_dict(), flow_fit.to_frame()
    g = p["leakage.g"]   # the seat leakage: in the details (to_dict), not the --json contract
    assert flow_fit.to_dict()["seat_leakage"] == {**g.to_json_dict(), "fitted": g.identified,
                                                  "n_runs": flow_fit.leakage.n_runs,
                                                  "n_conditions": flow_fit.leakage.n_conditions,
                                                  "message": flow_fit.leakage.message}
    assert keys_without_unit(flow_fit.to_dict()["seat_leakage"]) == []
    for name, e in ((n, e) for n, e in p.items() if n != "leakage.g"):
        side = name.split(".")[0]
        # the JSON and the wide frame name the estimate by its key, with the same numbers
        assert doc[side][e.key] == json_num(e.value) == json_num(frame.loc[side, e.key])
        assert doc[side][e.ci95_key] == [json_num(v) for v in e.ci95]
        lo, hi = (k for k in e.wide_items() if k != e.key)
        assert [frame.loc[side, lo], frame.loc[side, hi]] == list(e.ci95)
        assert e.identified and e.has_interval and math.isfinite(e.stderr)
        assert "fit of eq. (5)" in e.method and "flow steps" in e.constrained_by
    check_schema("flowfit", doc)
    # flowfit_details.json: both procedures under the estimates' keys
    details = json.loads(dumps(flow_fit.to_dict()))
    for side, f in flow_fit.sides.items():
        for procedure in ("joint", "two_step"):
            block = details["sides"][side][procedure]
            for e in f.procedure_estimates(procedure).values():
                assert block[e.key] == json_num(e.value)
                assert block[e.stderr_key] == json_num(e.stderr)
            assert not {"c_flow", "c_se", "z0_se_mm"} & set(block)
        assert details["sides"][side][f.procedure][C_KEY] == doc[side][C_KEY]


def test_flowfit_without_leakage_has_no_leakage_estimate(flow_fit):
    import dataclasses

    from seanv_analysis.fit import LeakageFit

    none = dataclasses.replace(flow_fit, settings={**flow_fit.settings, "leakage": "none"},
                               leakage=LeakageFit(0.0, message="not modelled (leakage='none')"))
    assert "leakage.g" not in none.params
    assert none.to_dict()["seat_leakage"]["source"] == "not_estimated"


# Identification -------------------------------------------------------------------

def test_identification_params_frame_and_json_agree():
    from seanv_analysis.config import load_rig
    from seanv_analysis.identify.result import Constant, Identification

    consts = [Constant("supply.pressure_mpag", "supply pressure", 3.3001, 3.3, "MPaG", True,
                       "logs", (3.29, 3.31)),
              Constant("valve.supply.needle_y_c_mm", "supply needle centre y_c", -20.0, -20.0,
                       "mm", False, "threshold vs fluid force", note="too wide"),
              Constant(None, "flow-path dead time", 0.012, math.nan, "s", True, "steps",
                       (0.010, 0.014)),
              Constant("controller.release_band_mm", "release band", math.inf, 3.0, "mm", True,
                       "holds", (2.75, math.inf)),
              Constant("tube.inertance_factor", "inertance factor", 1.0, 1.0, "", True, "line",
                       (0.8, 1.2))]
    ident = Identification(consts, load_rig())
    p = ident.params
    check_params(p)
    assert list(p) == ["supply.pressure_mpag", "valve.supply.needle_y_c_mm",
                       "flow-path dead time", "controller.release_band_mm",
                       "tube.inertance_factor"]
    assert [e.source for e in p.values()] == ["identified", "rig_file", "identified",
                                              "identified", "identified"]
    doc, frame = ident.to_json_dict(), ident.to_frame()
    for c, e, (_, row) in zip(doc["constants"], p.values(), frame.iterrows()):
        u = e.suffix
        rec = json.loads(dumps(e.to_json_dict()))
        assert c["name"] == (c["key"] or c["label"]) == e.name == row["name"]
        assert c["label"] == row["label"]
        for k in ("value", "ci95", "default"):
            assert c[f"{k}{u}"] == rec[f"{k}{u}"]
        assert [json_num(row["value"]), json_num(row["ci95_lo"]), json_num(row["ci95_hi"])] == \
            [rec[f"value{u}"], *rec[f"ci95{u}"]]
        assert c["unit"] == e.unit == row["unit"] and c["identified"] == row["identified"]
        # how each was obtained: identified, or kept from the rig file
        for k in ("source", "method", "constrained_by", "note"):
            assert c[k] == rec[k] == row[k]
    assert [c["source"] for c in doc["constants"]][:2] == ["identified", "rig_file"]
    assert list(frame.columns[:2]) == ["key", "name"] and "identified" in frame
    check_schema("identify", {**doc, "identified_keys": [], "not_separable": [], "notes": []})


# Discovery --------------------------------------------------------------------------

@pytest.fixture(scope="module")
def discovery():
    from test_discover_engine import MODEL, synth_summary

    from seanv_analysis.discover import discover_flow_steps

    return discover_flow_steps(synth_summary(1, ("drift", "drain", 0.04)), model=MODEL)


def test_discovery_params_frame_and_json_agree(discovery):
    p = discovery.params
    check_params(p)
    assert list(p) == ["drain.drift.step", "drain.drift.every", "drain.drift.offset"]
    step, every = p["drain.drift.step"], p["drain.drift.every"]
    assert step.unit == "-" and step.has_interval and "Wald" in step.method
    assert step.bounds == (-0.5, 0.5) and not step.at_bound()      # drift's static form
    assert step.stderr == pytest.approx((step.ci95[1] - step.ci95[0]) / 3.92)
    assert every.unit == "runs" and isinstance(every.value, int) and "grid search" in every.method
    doc = discovery.to_json_dict()
    (eff,) = doc["effects"]
    # the effect's spec and its estimate records hold the same numbers
    assert eff["estimates"] == [json.loads(dumps(e.to_json_dict())) for e in p.values()]
    for e in p.values():
        assert eff["params"][e.quantity] == json_num(e.value)
    assert keys_without_unit(doc) == []
    check_schema("discover", doc)
    frame = discovery.to_frame()     # the estimates' table, with the effect and its p value
    assert list(frame["name"]) == [r["name"] for r in eff["estimates"]]
    assert frame.loc[0, "ci95_lo"] == eff["estimates"][0]["ci95_ratio"][0]
    assert list(frame["effect"]) == ["drift"] * 3 and set(frame["p_value"]) == {eff["p_value"]}
    assert columns_without_unit(frame) == []


def test_dynamic_candidate_json_comes_from_its_estimate():
    from seanv_analysis.discover.assemble import CLOSED_LOOP_EVIDENCE
    from seanv_analysis.discover.result import Discovery, EffectFinding
    from seanv_analysis.identify.dynamic import DynamicFinding
    from seanv_analysis.models import ValveModel

    f = DynamicFinding("delay", "delay_s", 0.1, (0.08, 0.12), 1e-6, 0.3, named=True)
    e = f.estimate
    assert (e.name, e.unit, e.ci95) == ("delay.delay_s", "s", (0.08, 0.12)) and e.inside()
    d = f.to_json_dict()
    assert (d["value_s"], d["ci95_s"]) == (0.1, [0.08, 0.12])
    model = ValveModel.from_rig(__import__("seanv_analysis").load_rig())
    disc = Discovery("effect_found", [EffectFinding("delay", "both", {"delay_s": 0.1},
                                                    {"delay_s": (0.08, 0.12)}, 1e-6,
                                                    evidence=CLOSED_LOOP_EVIDENCE)],
                     1, 100.0, 80.0, None, model, model)
    check_params(disc.params)
    assert "twin" in disc.params["both.delay.delay_s"].method


# Tracking -------------------------------------------------------------------------

@pytest.fixture(scope="module")
def tracking(tmp_path_factory):
    from conftest import write_synthetic_dataset

    from seanv_analysis.stages import run_stages

    data = write_synthetic_dataset(tmp_path_factory.mktemp("est") / "d", n_flow=2, n_position=2,
                                   duration_s=2.0)
    return run_stages(data, ["ingest", "tracking"]).result("tracking")


def test_tracking_lag_estimates_frame_and_json_agree(tracking):
    p = tracking.params
    check_params(p)
    assert list(p) == ["lag", *(f"{r.run_id}.lag" for r in tracking.runs)]
    doc, per_run = tracking.to_json_dict(), tracking.per_run
    lag = p["lag"]
    assert (lag.key, lag.ci95_key) == ("lag_s", "lag_ci95_s")
    assert doc["lag_s"] == json_num(lag.value) == json_num(tracking.lag_s)
    assert doc["lag_ci95_s"] is None or doc["lag_ci95_s"] == [json_num(v) for v in lag.ci95]
    for r, row, (_, frow) in zip(doc["runs"], tracking.runs, per_run.iterrows()):
        e = p[f"{row.run_id}.lag"]
        assert r["lag_s"] == json_num(e.value) == json_num(frow["lag_s"])
        assert [json_num(frow["lag_ci95_lo_s"]), json_num(frow["lag_ci95_hi_s"])] == \
            [json_num(v) for v in e.ci95]
    check_schema("tracking", doc)
