"""The controller's law read from its logs (``identify.controller``).

Constructed logs: a position record of known shape (a decaying or a
sustained oscillation about each reference), and the commands the
simulator's own controller law (:mod:`seanv_analysis.sim.control`) gives on
it, with known gain, band, release, hold angle and cam limits; identify must
read them back. The field-data test (marked slow) runs ``identify`` and
``validate`` on ``field-slow-servo``, whose controller releases its hold as
soon as |e| leaves the band.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import write_synthetic_run
from json_schemas import check_schema, keys_without_unit

from seanv_analysis import ValveModel, load_rig
from seanv_analysis.analysis.validate import build_controller
from seanv_analysis.identify.controller import controller_constants, controller_law
from seanv_analysis.identify.result import nest_constants
from seanv_analysis.io import read_run
from seanv_analysis.sim.control import CamController, FlowModelController

#: references [mm] and their start [s]; each holds 10 s
REFS = np.array([0.0, 10.0, 4.0, 12.0, 6.0, 14.0])
T_REF = 10.0 * np.arange(REFS.size)


def _position(t: np.ndarray, *, sustained: bool) -> np.ndarray:
    """Position [mm]: each reference approached as a decaying oscillation
    (overshooting well past any band), or a sustained one of +-2 mm about it;
    every segment with its own period, so the band is crossed at many
    different speeds."""
    k = np.clip(np.searchsorted(T_REF, t, side="right") - 1, 0, REFS.size - 1)
    tau = t - T_REF[k]
    prev = np.r_[0.5, REFS[:-1]][k]          # starts 0.5 mm off the first reference
    period = 3.0 + 0.37 * k
    if sustained:
        amp = np.where(k == 0, 0.0, 2.0)
        return REFS[k] + (prev - REFS[k]) * np.exp(-tau / 0.3) + amp * np.sin(
            2 * np.pi * tau / period)
    return REFS[k] + (prev - REFS[k]) * np.exp(-tau / 2.5) * np.cos(2 * np.pi * tau / period)


def _constructed_run(root: Path, controller, *, sustained: bool, run_id: str,
                     declared: dict | None = None, seed: int = 0) -> Path:
    """A position-control run whose commands are ``controller``'s on a position
    record of known shape (1 kHz encoder and pressure, 100 Hz controller and
    servo on the same instants)."""
    rng = np.random.default_rng(seed)
    t_enc = np.arange(60_000) / 1000.0
    x = np.round(_position(t_enc, sustained=sustained), 3)
    ps = 3.3 + rng.normal(0.0, 0.003, t_enc.size)
    ph = 1.6 + 0.2 * np.sin(2 * np.pi * t_enc / 7.0) + rng.normal(0.0, 0.003, t_enc.size)
    t_c = t_enc[::10]
    state = controller.initial_state()
    cmd, q = np.empty(t_c.size), np.empty(t_c.size)
    x_ref = REFS[np.searchsorted(T_REF, t_c, side="right") - 1]
    for i, j in enumerate(range(0, t_enc.size, 10)):
        out, state = controller.step(state, x_ref[i], x[j], ps[j], ph[j], 0.0)
        cmd[i], q[i] = out.cam_cmd_deg, out.q_ref_mm3_s
    tables = {
        "encoder": pd.DataFrame({"t_s": t_enc, "position_mm": x}),
        "pressure": pd.DataFrame({"t_s": t_enc, "p_supply_mpag": ps, "p_head_mpag": ph,
                                  "p_load_mpag": np.full(t_enc.size, 0.35)}),
        "servo": pd.DataFrame({"t_s": t_c, "cam_cmd_deg": cmd, "cam_deg": cmd}),
        "controller": pd.DataFrame({"t_s": t_c, "x_ref_mm": x_ref, "q_ref_mm3_s": q})}
    doc = declared or controller.run_json()
    return write_synthetic_run(root, "position_control", run_id=run_id, tables=tables,
                               controller=doc, load_mpag=0.35)


def _cam(**kw) -> CamController:
    base = dict(kp_deg_per_mm=12.0, neutral_deg=-14.0, convergence_band_mm=0.6,
                release_band_mm=None, cam_min_deg=-35.0, cam_max_deg=8.0)
    return CamController(**{**base, **kw})


def _law(tmp_path, controller, *, sustained: bool, rig=None, **kw):
    rig = rig or load_rig()
    path = _constructed_run(tmp_path, controller, sustained=sustained, run_id="pos", **kw)
    run = read_run(path, rig=rig)
    return controller_law(run, ValveModel.from_rig(rig), rig), run


def test_latching_cam_controller(tmp_path):
    """A hold that lasts until the next reference: gain, neutral, band, the
    latch, hold angle and both cam limits read back."""
    law, _ = _law(tmp_path, _cam(), sustained=False)
    assert law.kind == "cam" and law.offset_s == 0.0
    assert law.kp == pytest.approx(12.0, rel=1e-3) and law.kp_ci95[0] <= 12.0 <= law.kp_ci95[1]
    assert law.neutral_deg == pytest.approx(-14.0, abs=0.01)
    assert law.hold is True and law.hold_deg == pytest.approx(-14.0, abs=1e-9)
    lo, hi = law.band_interval_mm
    assert lo <= 0.6 <= hi and hi - lo < 0.1 and law.band_mm == pytest.approx(0.6, abs=0.05)
    assert law.release == "latch" and law.release_mm == math.inf
    assert law.max_held_error_mm > 1.0
    assert (law.cam_min_deg, law.cam_max_deg) == (-35.0, 8.0)


def test_cam_controller_releasing_at_the_band(tmp_path):
    """A hold that ends as soon as |e| leaves the band (the field rig's):
    release 'band', the release band equal to the band."""
    law, _ = _law(tmp_path, _cam(release_band_mm=0.6), sustained=True)
    assert law.hold is True and law.release == "band" and law.n_releases >= 20
    assert law.release_mm == law.band_mm == pytest.approx(0.6, abs=0.05)


def test_cam_controller_releasing_at_a_wider_band(tmp_path):
    """Released at |e| > 1.2 mm, held in between: release 'threshold', its
    interval holds 1.2 and excludes the band."""
    law, _ = _law(tmp_path, _cam(release_band_mm=1.2), sustained=True)
    lo, hi = law.release_interval_mm
    assert law.release == "threshold" and lo <= 1.2 <= hi and lo > 0.7, law
    assert law.release_mm == pytest.approx(1.2, abs=0.05)


def test_cam_controller_without_hold(tmp_path):
    """A P law down to e = 0 (band 0: never held): no hold, band 0."""
    law, _ = _law(tmp_path, _cam(convergence_band_mm=0.0), sustained=True)
    assert law.hold is False and law.band_mm == 0.0 and law.release == "none"
    assert law.kp == pytest.approx(12.0, rel=1e-3)


def test_flow_model_controller(tmp_path, rig):
    """eq. (6) with the rig's valve: Kp from Q_ref, no threshold offset, the
    hold's angle below the supply threshold, band and latch."""
    ctrl = FlowModelController(ValveModel.from_rig(rig), kp_mm3_s_per_mm=300.0,
                               hold_below_threshold_deg=2.5, convergence_band_mm=0.4,
                               release_band_mm=None)
    law, _ = _law(tmp_path, ctrl, sustained=False)
    assert law.kind == "flow_model"
    assert law.kp == pytest.approx(300.0, rel=1e-6)
    assert abs(law.threshold_offset_deg["supply"]) < 1e-3
    assert law.opening_gain["supply"] == pytest.approx(1.0, abs=1e-3)
    assert law.hold_below_deg == pytest.approx(2.5, abs=0.05)
    lo, hi = law.band_interval_mm
    assert lo <= 0.4 <= hi and law.release == "latch"


def test_flow_model_controller_with_another_valve(tmp_path, rig):
    """A controller whose eq. (6) model is not the given valve (z0 moved):
    its threshold offset is found, and the hold is counted from its own
    threshold."""
    valve = ValveModel.from_rig(rig)
    own = valve.with_side("supply", z0_mm=valve.supply.z0_mm + 0.01)
    ctrl = FlowModelController(own, kp_mm3_s_per_mm=480.0, hold_below_threshold_deg=3.0,
                               convergence_band_mm=0.5, release_band_mm=None)
    path = _constructed_run(tmp_path, ctrl, sustained=False, run_id="pos")
    law = controller_law(read_run(path, rig=rig), valve, rig)
    shift = float(np.median(own.supply.threshold_deg(3.3, 1.7) - valve.supply.threshold_deg(3.3, 1.7)))
    assert abs(shift) > 0.5
    assert law.threshold_offset_deg["supply"] == pytest.approx(shift, abs=0.1)
    assert law.hold_below_deg == pytest.approx(3.0, abs=0.1)


def test_constants_the_twin_reads(tmp_path, rig):
    """controller_constants gives the rig keys; the twin's controller built
    from them is the logged one; a logged gain that is not run.json's is said
    and taken (``kp_from_logs``)."""
    path = _constructed_run(tmp_path, _cam(release_band_mm=0.6), sustained=True, run_id="pos",
                            declared={"kp": 15.0, "flow_model": False, "rate_hz": 100.0})
    run = read_run(path, rig=rig)
    consts, fits, notes = controller_constants([run], ValveModel.from_rig(rig), rig)
    by = {c.key: c for c in consts}
    assert by["controller.kp_cam_deg_per_mm"].value == pytest.approx(12.0, rel=1e-3)
    assert by["controller.kp_from_logs"].value is True
    assert any("run.json says 15" in n for n in notes)
    assert by["controller.release_band_mm"].value == by["controller.convergence_band_mm"].value
    assert by["servo.neutral_deg"].value == pytest.approx(-14.0)
    assert by["valve.cam_min_deg"].value == -35.0 and by["valve.cam_max_deg"].value == 8.0
    assert fits["train_default"] > 1.0 and fits["train"] < 0.05   # replayed command [deg]
    twin = rig.with_overrides(nest_constants(consts))
    ctrl = build_controller(run, ValveModel.from_rig(twin), twin)
    assert ctrl.kp_deg_per_mm == pytest.approx(12.0, rel=1e-3)
    assert ctrl.release_band_mm == ctrl.convergence_band_mm
    assert (ctrl.neutral_deg, ctrl.cam_min_deg, ctrl.cam_max_deg) == (-14.0, -35.0, 8.0)


# --------------------------------------------------------------- field data

@pytest.mark.slow
def test_field_slow_servo_limit_cycle(field_root, tmp_path):
    """field-slow-servo: its controller releases the hold as soon as |e|
    leaves the band, so the run without the flow model hunts for the whole
    run. identify reads that from the logs; validate on the identified twin
    reproduces the limit cycle (amplitude and period within 20 %) and flags
    neither run. Measured: band 0.5025 [0.5, 0.505] mm, release at the band
    (188 releases); amplitude 2.26 / 2.56 mm, period 0.77 / 0.82 s; position
    fit 81.8 % (77.3 % with the latching twin, flagged); ~25 s."""
    from click.testing import CliRunner

    from seanv_analysis.cli import cli

    data = field_root / "field-slow-servo"
    res = CliRunner().invoke(cli, ["identify", str(data), "--out", str(tmp_path / "id"), "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    check_schema("identify", doc)
    assert keys_without_unit(doc) == []
    by = {c["key"]: c for c in doc["constants"]}
    band, release = by["controller.convergence_band_mm"], by["controller.release_band_mm"]
    assert band["identified"] and band["ci95_mm"][0] <= 0.5 <= band["ci95_mm"][1]
    assert release["identified"] and release["value_mm"] == band["value_mm"]
    assert by["controller.kp_cam_deg_per_mm"]["value_deg_per_mm"] == pytest.approx(15.0, rel=0.01)
    assert by["servo.neutral_deg"]["value_deg"] == pytest.approx(-15.0, abs=0.01)
    res = CliRunner().invoke(cli, ["validate", str(data), "--rig",
                                   str(tmp_path / "id" / "rig-identified.toml"), "--json",
                                   "--no-figures", "--out", str(tmp_path / "val")])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    check_schema("validate", doc)
    assert doc["flagged"] == []
    row = next(r for r in doc["runs"] if r["controller"] == "cam")
    assert row["limit_cycle"] == "agrees"
    for stat in ("amplitude", "period"):
        unit = "mm" if stat == "amplitude" else "s"
        m, s = row[f"limit_cycle_{stat}_measured_{unit}"], row[f"limit_cycle_{stat}_simulated_{unit}"]
        assert s == pytest.approx(m, rel=0.2), (stat, m, s)
    assert row["limit_cycle_duration_measured_s"] > 60.0
