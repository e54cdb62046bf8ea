"""Tests of seanv_analysis.signals.filters: the paper's exclusion filters."""
from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from seanv_analysis.config import load_rig
from seanv_analysis.errors import ConfigError, DataError
from seanv_analysis.signals.filters import EXCLUSION_REASONS, apply_filters, exclusion_counts

RIG = load_rig()
TH = RIG.analysis


def row(**kw):
    base = {"run_id": "r", "kind": "flow_step", "side": "supply", "q_mm3_s": 2000.0,
            "dp_mpa": 1.7, "p1_mpa": 3.3, "cam_deg": -8.0, "load_mpag": 0.35}
    base.update(kw)
    return base


def judge(**kw):
    out = apply_filters(pd.DataFrame([row(**kw)]), RIG)
    return out["excluded"].iloc[0], out["excluded_detail"].iloc[0]


def test_kept_run():
    assert judge() == ("", "")
    assert judge(side="drain", q_mm3_s=-2000.0, cam_deg=-30.0, dp_mpa=1.6, p1_mpa=1.6) == ("", "")


@pytest.mark.parametrize("q", [TH["leakage_flow_mm3_s"], -TH["leakage_flow_mm3_s"], 0.0, 12.5])
def test_leakage_boundary_inclusive(q):
    reason, detail = judge(q_mm3_s=q)
    assert reason == "leakage"
    assert detail == f"leakage: |Q| = {abs(q):.1f} mm^3/s <= 50 mm^3/s"


@pytest.mark.parametrize("q", [np.nextafter(50.0, 100.0), 50.01, -50.01])
def test_just_above_leakage_is_kept(q):
    assert judge(q_mm3_s=q)[0] == ""


@pytest.mark.parametrize("load, q, expected", [
    (0.2, -500.0, "friction"),           # both boundaries, inclusive
    (0.2, -499.0, "friction"),
    (0.0, -300.0, "friction"),
    (np.nextafter(0.2, 1.0), -300.0, ""),  # load just above 0.2 MPaG
    (0.21, -300.0, ""),
    (0.2, -500.01, ""),                  # flow just above 500
    (0.2, -40.0, "leakage"),             # leakage takes precedence
])
def test_friction_boundaries(load, q, expected):
    reason, detail = judge(side="drain", cam_deg=-30.0, q_mm3_s=q, load_mpag=load)
    assert reason == expected
    if expected == "friction":
        assert detail == (f"friction: drain, load {load:g} MPaG <= 0.2 MPaG and "
                          f"|Q| = {abs(q):.1f} mm^3/s <= 500 mm^3/s")
    if expected == "leakage":
        assert detail.endswith("(also: friction)")


def test_friction_only_on_drain_side():
    assert judge(side="supply", q_mm3_s=300.0, load_mpag=0.1)[0] == ""


@pytest.mark.parametrize("cam, expected", [(-40.0, ""), (10.0, ""), (-40.5, "cam_range"),
                                           (10.01, "cam_range"), (25.0, "cam_range")])
def test_cam_range_inclusive(cam, expected):
    reason, detail = judge(cam_deg=cam)
    assert reason == expected
    if expected:
        assert detail == f"cam_range: cam {cam:g} deg outside [-40, 10] deg"


@pytest.mark.parametrize("col", ["q_mm3_s", "dp_mpa", "p1_mpa", "cam_deg"])
def test_invalid_non_finite(col):
    for bad in (math.nan, math.inf):
        reason, detail = judge(**{col: bad})
        assert reason == "invalid"
        assert detail.startswith(f"invalid: {col} = {bad}") and "expected finite" in detail


def test_invalid_drain_load_and_side():
    assert judge(side="drain", q_mm3_s=-2000.0, load_mpag=math.nan)[0] == "invalid"
    assert judge(load_mpag=math.nan)[0] == ""  # supply: load not needed
    reason, detail = judge(side="both")
    assert reason == "invalid" and "side 'both'" in detail


def test_precedence_cam_range_invalid_leakage_friction():
    assert EXCLUSION_REASONS == ("cam_range", "invalid", "leakage", "friction")
    reason, detail = judge(cam_deg=-45.0, q_mm3_s=math.nan)
    assert reason == "cam_range" and detail.endswith("(also: invalid)")
    reason, detail = judge(side="drain", cam_deg=-45.0, q_mm3_s=-30.0, load_mpag=0.1)
    assert reason == "cam_range" and detail.endswith("(also: leakage, friction)")
    reason, _ = judge(side="drain", q_mm3_s=-30.0, dp_mpa=math.nan, load_mpag=0.1)
    assert reason == "invalid"


def test_thresholds_come_from_rig():
    rig = RIG.with_overrides({"analysis": {"leakage_flow_mm3_s": 100.0,
                                           "friction_load_max_mpag": 0.3,
                                           "friction_flow_mm3_s": 800.0,
                                           "cam_range_deg": [-20.0, 0.0]}})
    s = pd.DataFrame([row(q_mm3_s=80.0), row(side="drain", q_mm3_s=-700.0, load_mpag=0.3),
                      row(cam_deg=-25.0), row()])
    assert apply_filters(s, rig)["excluded"].tolist() == ["leakage", "friction", "cam_range", ""]
    assert apply_filters(s, RIG)["excluded"].tolist() == ["", "", "", ""]


def test_other_kinds_not_judged_and_input_unchanged():
    s = pd.DataFrame([row(kind="position_control", side="", q_mm3_s=math.nan,
                          cam_deg=math.nan), row(q_mm3_s=10.0)])
    before = s.copy()
    out = apply_filters(s, RIG)
    assert out["excluded"].tolist() == ["", "leakage"]
    assert out["excluded_detail"].iloc[0] == ""
    pd.testing.assert_frame_equal(s, before)
    assert list(out.columns[:len(s.columns)]) == list(s.columns)


def test_exclusion_counts():
    s = pd.DataFrame([row(q_mm3_s=10.0), row(q_mm3_s=-20.0), row(cam_deg=20.0),
                      row(side="drain", q_mm3_s=-200.0, load_mpag=0.1), row(dp_mpa=math.nan),
                      row()])
    counts = exclusion_counts(apply_filters(s, RIG))
    assert counts == {"leakage": 2, "friction": 1, "cam_range": 1, "invalid": 1}
    empty = exclusion_counts(apply_filters(pd.DataFrame([row()]), RIG))
    assert empty == {"leakage": 0, "friction": 0, "cam_range": 0, "invalid": 0}


def test_errors():
    with pytest.raises(DataError, match="no 'excluded' column"):
        exclusion_counts(pd.DataFrame([row()]))
    with pytest.raises(DataError, match="unknown exclusion reason"):
        exclusion_counts(pd.DataFrame({"excluded": ["", "dust"]}))
    with pytest.raises(DataError, match="no column.*dp_mpa"):
        apply_filters(pd.DataFrame([row()]).drop(columns="dp_mpa"), RIG)
    bad = RIG.with_overrides({"analysis": {"cam_range_deg": [10.0, -40.0]}})
    with pytest.raises(ConfigError, match="min > max"):
        apply_filters(pd.DataFrame([row()]), bad)


def test_filters_on_summaries_of_runs(tmp_path, make_dataset):
    from seanv_analysis.io.reader import read_dataset
    from seanv_analysis.signals.derive import summarize_run
    root = make_dataset(tmp_path, n_flow=3, duration_s=0.6)
    rows = [summarize_run(r) for r in read_dataset(root).runs]
    out = apply_filters(pd.DataFrame(rows), RIG)
    assert out["excluded"].tolist() == ["", "", ""]
    assert exclusion_counts(out) == {"leakage": 0, "friction": 0, "cam_range": 0, "invalid": 0}
