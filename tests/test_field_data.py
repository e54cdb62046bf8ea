"""Logs of a rig nobody here wrote (../shared/field-data), with their truth:
the static discovery (flow steps) on the clean set and on the set with an
undeclared supply drift, the servo and friction from their logs, and the
twin's line on the set whose position runs carry an undeclared play. Their
constants are read from the truth files, never written into the package.
The rest of the closed loop (the dynamic effects, every command end to end
on all three sets, the confusion matrix) runs in benchmarks/bench_field.py,
which the note of issue 31 quotes.
"""
from __future__ import annotations

import pytest
from field_data import field_truth

from seanv_analysis import ValveModel, load_rig
from seanv_analysis.discover import discover_flow_steps
from seanv_analysis.stages import run_stages

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def summaries(field_root):
    """Each field set's ingest summary, read once for the module."""
    cache = {}

    def get(name):
        if name not in cache:
            cache[name] = run_stages(field_root / name, ["ingest"]).result("ingest").summary
        return cache[name]
    return get


def _static(summaries, name):
    return discover_flow_steps(summaries(name), model=ValveModel.from_rig(load_rig()))


def test_field_clean_flow_steps_say_none(field_root, summaries):
    """Nothing undeclared: no effect, and the needle centres the rig file does
    not know (its y_c is -20 / +20 mm) are found near the rig's own."""
    truth = field_truth(field_root, "field-clean")
    d = _static(summaries, "field-clean")
    assert d.verdict == "none" and d.effects == [], d.report()
    assert d.geometry is not None
    for side in ("supply", "drain"):
        # an effective centre: x_c stays the rig file's, whose effect on the
        # threshold over the tested pressures y_c takes up
        assert d.geometry[side]["needle_y_c_mm"] == pytest.approx(truth[side]["y_c_mm"], abs=2.0)
    assert d.rmse_after_mm3_s < 0.2 * d.rmse_before_mm3_s     # the geometry, not an effect


def test_field_drift_is_named_and_cuts_the_heldout_error(field_root, summaries):
    """An undeclared drift of the supply side's C (a step every third supply
    sweep): named on the supply side, nothing else, held-out error down >= 30 %."""
    truth = field_truth(field_root, "field-drift-backlash")
    assert truth["flow_effect"] == "drift_supply"
    d = _static(summaries, "field-drift-backlash")
    assert [(e.name, e.side) for e in d.effects] == [("drift", "supply")], d.report()
    assert d.effects[0].params["step"] > 0        # C falls with use
    assert d.rmse_after_mm3_s <= 0.7 * d.rmse_before_mm3_s


@pytest.mark.parametrize("name", ["field-clean", "field-slow-servo"])
def test_field_servo_intervals_hold_the_truth(field_root, name):
    """The servo from its logs (synchronous 100 Hz stamps): the delay from
    the stamps is 0.0355 s on field-clean for a true 0.045 s dead time (the
    rig stamps a command after sending it); the interval spans the stamps'
    phase, one servo-log sample, and holds the truth; the time constant too."""
    from seanv_analysis.identify.servo import fit_servo, servo_data
    from seanv_analysis.io.reader import find_runs, read_run

    truth = field_truth(field_root, name)["plant"]
    rig = load_rig()
    sv = rig["servo"]
    runs = [read_run(p, rig=rig) for p in find_runs(field_root / name)]
    data = [d for d in map(servo_data, runs) if d is not None and d.t_fb.size > 1000]
    assert data and all(d.stamp_lead_s == pytest.approx(0.01) for d in data)
    fit = fit_servo(data[:1], start=(sv["dead_time_s"], sv["time_constant_s"],
                                     sv["max_rate_deg_s"]), resolution_deg=sv["resolution_deg"])
    lo, hi = fit.dead_ci95
    assert lo <= truth["servo_dead_time_s"] <= hi, fit
    assert hi - lo < 0.5 * truth["servo_dead_time_s"] + 0.01
    lo, hi = fit.tau_ci95
    assert lo <= truth["servo_time_constant_s"] <= hi, fit
    # the rate limit: reached in 0.1-0.2 % of the samples only, but on
    # field-clean the rig file's 240 deg/s fits the logs far worse than the
    # free fit (likelihood ratio ~100): taken from the logs, its interval
    # holds the truth; on field-slow-servo the free fit is no better
    # (truth 250): the rig file's rate is kept, said not identified
    assert fit.rate_identified == (name == "field-clean"), fit.rate_note
    if fit.rate_identified:
        lo, hi = fit.rate_ci95
        assert lo <= truth["servo_rate_limit_deg_s"] <= hi, fit


def test_field_friction_is_a_stribeck_law(field_root, summaries):
    """That rig's seals lose force with speed over the steps' speeds (a
    Stribeck velocity of its own): F_c + b v alone gave 92.8 [91.1, 94.5] N
    for a true 85 N; with v_s fitted (the breakaway read from the position
    runs) the Coulomb force, the Stribeck velocity and the breakaway hold
    their truths, and the held-out force error halves."""
    from seanv_analysis.identify.friction import friction_constants
    from seanv_analysis.io.reader import find_runs, read_run

    truth = field_truth(field_root, "field-clean")["plant"]
    rig = load_rig()
    pos = [r for r in (read_run(p, rig=rig) for p in find_runs(field_root / "field-clean"))
           if r.kind == "position_control"]
    consts, fits, _ = friction_constants(summaries("field-clean"), rig, pos)
    got = {c.key: c for c in consts if c.key}
    for key, true in (("actuator.coulomb_friction_n", truth["coulomb_friction_n"]),
                      ("actuator.stribeck_velocity_mm_s", truth["stribeck_velocity_mm_s"]),
                      ("actuator.static_friction_n", truth["static_friction_n"])):
        c = got[key]
        assert c.identified and c.ci95[0] <= true <= c.ci95[1], (key, c)
    assert got["actuator.coulomb_friction_n"].value == pytest.approx(
        truth["coulomb_friction_n"], rel=0.03)
    assert fits["heldout"] < 3.0          # N; 4.2 with F_c + b v, 2.1 measured


def test_field_line_keeps_the_tube_despite_the_play(field_root, summaries):
    """field-drift-backlash's position runs carry a 1.5 deg play between
    servo and cam that the twin has not. With the rig file's servo rate
    (240 deg/s for the rig's 300), fitted on the training run alone, the
    line's inertance went to the end of its range (0.03 x the tube's water
    column) for 3 % less SSE and took the play in; only the held-out
    replay's veto kept the tube. With the rate the servo logs give (297),
    the tube is the best line on the training run outright, by 24 % of
    the flow SSE over the next factor, and the rig file's tube is kept."""
    from seanv_analysis.identify import identify_rig
    from seanv_analysis.io.reader import find_runs, read_run

    rig = load_rig()
    name = "field-drift-backlash"
    pos = [r for r in (read_run(p, rig=rig) for p in find_runs(field_root / name))
           if r.kind == "position_control"]
    ident = identify_rig(summaries(name), rig, position_runs=pos, n_boot=0)
    truth = field_truth(field_root, name)["plant"]
    rate = next(c for c in ident.constants if c.key == "servo.max_rate_deg_s")
    assert rate.identified and rate.value == pytest.approx(truth["servo_rate_limit_deg_s"],
                                                           rel=0.05), rate
    line = next(c for c in ident.constants if c.key == "tube.inertance_factor")
    assert line.value == rig["tube"]["inertance_factor"], line
    assert "no other inertance fits significantly better" in line.note, line.note
    # the play is not in the twin: B (250 for 300) is called an effective value,
    # the held-out run replaying better at its interval's upper end
    bulk = next(c for c in ident.constants if c.key == "tube.effective_bulk_modulus_mpa")
    assert not bulk.ci95[0] <= truth["line_bulk_modulus_mpa"] <= bulk.ci95[1], bulk
    assert "upper end" in bulk.note and "effective value" in bulk.note, bulk.note
    assert ident.fits["flow_path"]["bulk_modulus_heldout"]["beyond_interval"] is True


def test_field_clean_needle_centres_hold_the_truth(field_root, summaries):
    """identify's valve on field-clean (x_c, y_c, z0 of that rig all differ
    from the rig file's): x_c is said to be not told by the flow steps, and
    y_c's, z0's and C's intervals, which carry the rig file's range of x_c,
    hold the truth on both sides (before: y_c and z0 outside on the supply
    side, -30.9 [-31.7, -30.0] mm for -32 and -0.169 [-0.171, -0.167] mm for
    -0.14)."""
    from seanv_analysis.identify import identify_rig

    truth = field_truth(field_root, "field-clean")
    ident = identify_rig(summaries("field-clean"), load_rig(), parts=("geometry",), n_boot=60)
    got = {c.key: c for c in ident.constants}
    for side in ("supply", "drain"):
        x_c = got[f"valve.{side}.needle_x_c_mm"]
        assert not x_c.identified and f"valve.{side}.z0_mm" in x_c.confounded_with, x_c
        for key, true in (("needle_y_c_mm", truth[side]["y_c_mm"]), ("z0_mm", truth[side]["z0_mm"]),
                          ("c_flow", truth[side]["C"])):
            c = got[f"valve.{side}.{key}"]
            lo, hi = sorted(c.ci95)
            assert c.identified and lo <= true <= hi, (side, key, c.value, c.ci95)
