"""The foreign rig's effects outside discover's vocabulary
(``tests/foreign_rig.py``: ``dp_choke``, ``load_c``, ``pressure_leak``,
``approach_threshold``).

What must hold: off by default (the rig's files do not change: the seeded
byte-for-byte tests of ``test_foreign_rig_v2.py`` still pass); on, the
steady flows the package derives from the written runs show each effect's
formula, run by run against the same runs without it (same seed, same
protocol), on its side only; position-control runs take them too; bad
options are refused.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from foreign_rig import ForeignTruth, _Needle, flowstep_plan, write_flowsteps, write_position

from seanv_analysis.io import read_dataset
from seanv_analysis.signals.derive import summarize_run

#: 3 supply + 2 drain angles x 3 loads x 2 repeats = 30 short flow steps;
#: -5 deg seals the supply needle on this rig
PLAN = flowstep_plan(supply_cams=(-5.0, 5.0, 10.0), drain_cams=(-40.0, -30.0),
                     loads=(0.1, 0.3, 0.5), repeats=2)
SEED = 4


def _rows(folder, truth: ForeignTruth) -> list[dict]:
    write_flowsteps(folder, plan=PLAN, seed=SEED, truth=truth)
    return [summarize_run(run) for run in sorted(read_dataset(folder).runs,
                                                    key=lambda r: r.meta.run_id)]


def _q5(truth: ForeignTruth, row, shift_deg: float = 0.0) -> float:
    """This rig's plain eq. (5) at the run's measured angle and pressures
    (the threshold moved by ``shift_deg``) [mm^3/s]."""
    side = row["side"]
    needle = _Needle(side, getattr(truth, f"{side}_z0_mm"), getattr(truth, f"{side}_c"),
                     truth.geometry(side))
    theta = row["cam_measured_deg"] if math.isfinite(row["cam_measured_deg"]) else row["cam_deg"]
    return float(needle.flow(theta - shift_deg, row["p1_mpa"], row["dp_mpa"]))


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    return _rows(tmp_path_factory.mktemp("clean"), ForeignTruth())


def _pairs(tmp_path, clean, truth):
    """(row with the effect, the same run without it) for every run."""
    rows = _rows(tmp_path / "effect", truth)
    assert [r["run_id"] for r in rows] == [r["run_id"] for r in clean]
    return list(zip(rows, clean))


def _c_ratio(truth, row, clean_row, shift_deg=0.0):
    """Measured flow over eq. (5) at its own pressures, relative to the same
    ratio of the run without the effect (cancels what the analysis'
    derivation does to every run alike)."""
    return (row["q_mm3_s"] / _q5(truth, row, shift_deg)) / (
        clean_row["q_mm3_s"] / _q5(truth, clean_row))


def test_defaults_are_off():
    tr = ForeignTruth()
    assert (tr.dp_choke, tr.load_c, tr.pressure_leak, tr.approach_threshold) == (None,) * 4
    assert tr.approach_overshoot_deg == 0.0


def test_dp_choke_limits_the_flow_above_dp_c(tmp_path, clean):
    choke = {"side": "supply", "dp_c_mpa": 1.5, "n": 4.0}
    tr = ForeignTruth(dp_choke=choke)
    ratios, dps = [], []
    for row, ref in _pairs(tmp_path, clean, tr):
        if row["side"] == "drain":
            assert row["q_mm3_s"] == pytest.approx(ref["q_mm3_s"], rel=0.005)
            continue
        if _q5(tr, row) < 500.0:           # sealed
            continue
        want = (1.0 + (row["dp_mpa"] / 1.5) ** 4.0) ** -0.25
        assert _c_ratio(tr, row, ref) == pytest.approx(want, rel=0.015), row["run_id"]
        ratios.append(_c_ratio(tr, row, ref))
        dps.append(row["dp_mpa"])
    # ~1 at the lowest dp, ~0.6 at the highest: the flow ratio falls with dp
    order = np.argsort(dps)
    assert ratios[order[0]] > 0.95 and ratios[order[-1]] < 0.65
    assert np.all(np.diff(np.asarray(ratios)[order]) < 0.02)


def test_load_dependent_c(tmp_path, clean):
    tr = ForeignTruth(load_c={"side": "drain", "k_per_mpa": 1.0, "load_ref_mpag": 0.3})
    seen = set()
    for row, ref in _pairs(tmp_path, clean, tr):
        if row["side"] == "supply":
            assert row["q_mm3_s"] == pytest.approx(ref["q_mm3_s"], rel=0.005)
            continue
        load = round(ref["load_mpag"], 1) if math.isfinite(ref["load_mpag"]) else None
        if load is None:
            continue
        assert _c_ratio(tr, row, ref) == pytest.approx(1.0 + (load - 0.3), rel=0.015)
        seen.add(load)
    assert seen == {0.1, 0.3, 0.5}


def test_pressure_leak_grows_with_dp_open_or_sealed(tmp_path, clean):
    k, m = 60.0, 2.0
    tr = ForeignTruth(pressure_leak={"side": "supply", "k_mm3_s": k, "m": m})
    sealed = 0
    for row, ref in _pairs(tmp_path, clean, tr):
        if row["side"] == "drain":
            continue   # (the supply needle leaks during drain runs too)
        # what the leak adds: the flow beyond the run without it, less what
        # eq. (5) changes with the slightly different pressures
        extra = row["q_mm3_s"] - ref["q_mm3_s"] - (_q5(tr, row) - _q5(tr, ref))
        assert extra == pytest.approx(k * row["dp_mpa"] ** m, rel=0.05, abs=10.0), row["run_id"]
        sealed += _q5(tr, row) == 0.0
    assert sealed >= 3


def test_threshold_depends_on_the_approach_direction(tmp_path, clean):
    s = 0.6
    tr = ForeignTruth(approach_threshold={"side": "supply", "shift_deg": s},
                      approach_overshoot_deg=3.0)
    by_dir = {}
    for row, ref in _pairs(tmp_path, clean, tr):
        if row["side"] == "drain":
            # the overshoot shows in the log: the drain cam comes back up
            assert row["cam_approach"] in (0.0, -1.0 if row["run_id"][-1] == "1" else 1.0)
            assert row["q_mm3_s"] == pytest.approx(ref["q_mm3_s"], rel=0.01)
            continue
        if _q5(tr, row) < 500.0:
            continue
        a = row["cam_approach"]
        truth_a = a if a != 0.0 else 1.0     # a log that starts at the angle: it came up
        assert _c_ratio(tr, row, ref, shift_deg=s * truth_a) == pytest.approx(1.0, rel=0.015)
        by_dir.setdefault((row["cam_deg"], ref["load_mpag"], truth_a), row["q_mm3_s"])
    # same angle and load, arriving from above opens more than from below
    both = [(k[:2], v) for k, v in by_dir.items() if (k[0], k[1], -k[2]) in by_dir and k[2] < 0]
    assert both
    for (cam, load), q_down in both:
        assert q_down > 1.05 * by_dir[(cam, load, 1.0)]


def test_position_runs_take_the_effects(tmp_path):
    effects = dict(dp_choke={"side": "supply", "dp_c_mpa": 1.5, "n": 4.0},
                   load_c={"side": "drain", "k_per_mpa": 1.0, "load_ref_mpag": 0.3},
                   pressure_leak={"side": "drain", "k_mm3_s": 30.0, "m": 1.5},
                   approach_threshold={"side": "supply", "shift_deg": 0.5})
    for name, tr in (("clean", ForeignTruth()), ("fx", ForeignTruth(**effects))):
        write_position(tmp_path / name, seed=2, truth=tr, n_runs=1, duration_s=8.0,
                       empty_qref_run=False, trace=True)
    import pandas as pd

    a = pd.read_parquet(next((tmp_path / "clean").rglob("_trace.parquet")))
    b = pd.read_parquet(next((tmp_path / "fx").rglob("_trace.parquet")))
    assert np.all(np.isfinite(b["q_mm3_s"])) and not np.allclose(a["x_mm"], b["x_mm"])
    # the loop still tracks its references
    assert abs(b["x_mm"].iloc[-1] - a["x_mm"].iloc[-1]) < 2.0


@pytest.mark.parametrize("kw, match", [
    ({"dp_choke": {"side": "both", "dp_c_mpa": 1.0, "n": 2.0}}, "dp_choke: expected"),
    ({"dp_choke": {"side": "supply", "dp_c_mpa": 0.0, "n": 2.0}}, "dp_choke: dp_c_mpa"),
    ({"load_c": {"side": "drain", "k": 1.0}}, "load_c: expected"),
    ({"pressure_leak": {"side": "drain", "k_mm3_s": 1.0, "m": -1.0}}, "pressure_leak: m"),
    ({"approach_threshold": 0.5}, "approach_threshold: expected"),
    ({"approach_overshoot_deg": -1.0}, "approach_overshoot_deg"),
])
def test_bad_effect_options_are_refused(kw, match):
    with pytest.raises(ValueError, match=match):
        ForeignTruth(**kw)
