"""One naming rule for every number the package gives (issue 33, point 4):
a number's key (JSON) or column (``to_frame()``) ends in its unit
(``seanv_analysis.units``), and one quantity has one name everywhere: C is
``C_mm3_s_deg2_sqrtMPa``, z0 ``z0_mm``, a delay estimate ``lag_s`` and the
delay compensated ``shift_s``, an error ``rmse_<what>_<unit>``. The whole
pipeline's result.json is held to it in tests/test_golden.py."""
from __future__ import annotations

import json
import math
import re

import pytest
from json_schemas import check_schema, columns_without_unit, keys_without_unit

from seanv_analysis.jsonable import json_num

#: spellings that name a quantity another way than its one name (or its unit
#: beside it instead of at its end), with the name to use
OTHER_NAMES = {
    r"^c_flow$|^c_lo$|^c_hi$|^C$": "C_mm3_s_deg2_sqrtMPa, C_ci95_lo_mm3_s_deg2_sqrtMPa",
    r"^z0_lo_mm$|^z0_hi_mm$": "z0_ci95_lo_mm, z0_ci95_hi_mm",
    r"^lag_applied_s$|^lag_source$": "shift_s, shift_source (lag_s is an estimate)",
    r"_MPa$|_N$": "_mpa, _n (one spelling of a unit)",
    r"^(value|ci95|default)$": "value_<unit>, ci95_<unit>, default_<unit>",
    r"^alpha(_se|_model)?$": "alpha_mm3_s_deg2",
    r"^RMSE|^Rmse|_RMSE": "rmse_<what>_<unit>",
}


def other_names(doc, path: str = "") -> list[str]:
    """Paths of keys (or columns) spelled as :data:`OTHER_NAMES` forbids."""
    out = []
    if isinstance(doc, dict):
        for k, v in doc.items():
            if k in ("pipeline", "inputs"):
                continue
            for pattern, use in OTHER_NAMES.items():
                if re.search(pattern, str(k)):
                    out.append(f"{path}/{k} (use {use})")
            out += other_names(v, f"{path}/{k}")
    elif isinstance(doc, list):
        for v in doc:
            out += other_names(v, f"{path}[]")
    return out


@pytest.fixture(scope="module")
def ctx(tmp_path_factory):
    from conftest import write_synthetic_dataset

    from seanv_analysis.stages import run_stages

    data = write_synthetic_dataset(tmp_path_factory.mktemp("names") / "d", n_flow=8,
                                   n_position=2, duration_s=1.0)
    return run_stages(data, ["ingest", "flowfit", "tracking", "validate"],
                      options={"flowfit": {"n_boot": 0}, "ingest": {"derive": True}})


@pytest.mark.parametrize("name", ["ingest", "flowfit", "tracking", "validate"])
def test_every_frame_and_json_names_units_once(ctx, name):
    result = ctx.result(name)
    frames = {"to_frame()": result.to_frame()}
    for attr in ("per_run", "per_load"):
        if isinstance(getattr(result, attr, None), type(frames["to_frame()"])):
            frames[attr] = getattr(result, attr)
    for where, frame in frames.items():
        assert columns_without_unit(frame) == [], (name, where)
        assert other_names({str(c): None for c in frame.columns}) == [], (name, where)
    doc = json.loads(result.to_json())
    assert keys_without_unit(doc) == [] and other_names(doc) == [], name


def test_flowfit_frame_and_json_say_c_and_z0_alike(ctx):
    fit = ctx.result("flowfit")
    frame, doc = fit.to_frame(), fit.to_json_dict()
    for side in frame.index:
        assert frame.loc[side, "C_mm3_s_deg2_sqrtMPa"] == doc[side]["C_mm3_s_deg2_sqrtMPa"]
        assert frame.loc[side, "z0_mm"] == doc[side]["z0_mm"]
        assert [json_num(frame.loc[side, "C_ci95_lo_mm3_s_deg2_sqrtMPa"]),
                json_num(frame.loc[side, "C_ci95_hi_mm3_s_deg2_sqrtMPa"])] == \
            doc[side]["C_ci95_mm3_s_deg2_sqrtMPa"]


def test_tracking_says_the_estimate_lag_and_the_compensation_shift(ctx, tmp_path):
    """``lag_s`` was the given shift at the top and each run's estimate in
    ``runs[]``: one key, two meanings. Now a lag is always an estimate."""
    from seanv_analysis.stages import run_stages

    tr = run_stages(ctx.data, ["ingest", "tracking"],
                    options={"tracking": {"shift_s": 0.2}}).result("tracking")
    doc = tr.to_json_dict()
    assert doc["shift_s"] == 0.2 and doc["shift_source"] == "given"
    assert doc["lag_s"] == tr.lag.lag_s != 0.2                 # the pooled estimate
    assert [r["lag_s"] for r in doc["runs"]] == [r.lag.lag_s for r in tr.runs]
    assert set(tr.per_run["shift_s"]) == {0.2}
    check_schema("tracking", doc)


def test_identify_constants_end_in_their_unit():
    """identify's value/ci95/default beside a 'unit' key are now
    value_<unit>, ci95_<unit>, default_<unit>; score keys use the one
    spelling of a unit (heldout_mpa, train_n: not heldout_MPa, train_N)."""
    from seanv_analysis.config import load_rig
    from seanv_analysis.identify.result import Constant, Identification

    consts = [Constant("supply.pressure_mpag", "supply pressure", 3.3, 3.3, "MPaG", True, "logs",
                       (3.29, 3.31)),
              Constant("actuator.viscous_friction_n_s_per_mm", "viscous", 2.0, 2.0, "N s/mm",
                       True, "force balance"),
              Constant("valve.supply.c_flow", "supply C", 17.4, 17.435,
                       "mm^3/(s deg^2 MPa^0.5)", True, "flowfit"),
              Constant("tube.inertance_factor", "inertance factor", 0.1, 1.0, "", True, "line")]
    fits = {"load": {"metric": "load pressure RMSE [MPa]", "train": 0.01, "heldout": 0.02},
            "friction": {"metric": "force RMSE [N]", "train": 5.0, "train_default": 6.0}}
    ident = Identification(consts, load_rig(), fits=fits)
    doc = ident.to_json_dict()
    assert [sorted(k for k in c if k.split("_")[0] in ("value", "ci95", "default"))
            for c in doc["constants"]] == [
        ["ci95_mpag", "default_mpag", "value_mpag"],
        ["ci95_n_s_per_mm", "default_n_s_per_mm", "value_n_s_per_mm"],
        ["ci95_mm3_s_deg2_sqrtMPa", "default_mm3_s_deg2_sqrtMPa", "value_mm3_s_deg2_sqrtMPa"],
        ["ci95_ratio", "default_ratio", "value_ratio"]]
    assert doc["fits"]["load"] == {"metric": "load pressure RMSE [MPa]", "train_mpa": 0.01,
                                   "heldout_mpa": 0.02}
    assert set(doc["fits"]["friction"]) == {"metric", "train_n", "train_default_n"}
    assert keys_without_unit(doc) == [] and other_names(doc) == []
    check_schema("identify", {**doc, "identified_keys": [], "not_separable": [], "notes": []})
    assert columns_without_unit(ident.to_frame()) == []      # a long table: its unit column
    assert math.isnan(ident.to_frame().loc[1, "ci95_lo"])


def test_a_number_beside_a_unit_key_is_refused():
    assert keys_without_unit({"x": {"value": 1.0, "unit": "mm"}}) == ["/x/value"]
    assert other_names({"tracking": {"lag_source": "given"}})
