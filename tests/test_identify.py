"""``identify`` on a rig that is not ours (tests/foreign_rig.py, ``own_rig``).

The foreign rig owns every constant the paper does not publish: needle
centres, servo (dead time, lag, rate limit, quantisation), a lumped line
unlike the simulator's tube, stick-slip friction, and it runs at 3.0 MPaG.
The analysis is given only the package's default rig file.
"""
from __future__ import annotations

import json
from dataclasses import replace
from functools import partial

import numpy as np
import pytest
from click.testing import CliRunner
from foreign_rig import ForeignTruth, flowstep_plan, own_rig, write_flowsteps, write_position
from json_schemas import check_schema, keys_without_unit

from seanv_analysis import ValveModel, load_rig
from seanv_analysis.cli import cli
from seanv_analysis.identify.result import suffix_of_unit

PLAN = flowstep_plan(supply_cams=(-5.0, 0.0, 5.0, 10.0), drain_cams=(-40.0, -32.5, -25.0, -20.0),
                     loads=(0.15, 0.3, 0.45), repeats=2)


@pytest.fixture(scope="module")
def foreign_own(tmp_path_factory):
    root = tmp_path_factory.mktemp("own")
    truth = own_rig()
    write_flowsteps(root / "flow", plan=PLAN, seed=11, truth=truth)
    write_position(root / "position", seed=11, truth=truth, n_runs=2, duration_s=40.0)
    res = CliRunner().invoke(cli, ["identify", str(root / "flow"), str(root / "position"),
                                   "--out", str(root / "out"), "--json", "--n-boot", "20"])
    assert res.exit_code == 0, res.output
    assert "Traceback" not in res.output
    doc = json.loads(res.stdout)
    check_schema("identify", doc)  # data_schema/json/identify.schema.json
    assert keys_without_unit(doc) == []
    return root, truth, doc


def _const(doc, key):
    return next(c for c in doc["constants"] if c["key"] == key)


def _geometry(truth: ForeignTruth, side: str, rig):
    base = ValveModel.from_rig(rig).side(side)
    return replace(base, z0_mm=getattr(truth, f"{side}_z0_mm"), c_flow=getattr(truth, f"{side}_c"),
                   geometry=truth.geometry(side))


def test_threshold_over_the_tested_pressures(foreign_own):
    """The identified (y_c, z0) give the foreign threshold within 0.15 deg
    over the pressures of the runs, where the rig file's geometry is off."""
    root, truth, doc = foreign_own
    rig_id = load_rig(root / "out" / "rig-identified.toml")
    ident = ValveModel.from_rig(rig_id)
    default = ValveModel.from_rig(load_rig())
    for side in ("supply", "drain"):
        assert _const(doc, f"valve.{side}.needle_y_c_mm")["identified"]
        true = _geometry(truth, side, load_rig())
        ps = 2.97
        ph = np.linspace(0.15, 0.45, 7) * 4.0 + (0.3 if side == "supply" else -0.2)
        p1, dp = (np.full(ph.shape, ps), ps - ph) if side == "supply" else (ph, ph)
        err = np.abs(ident.side(side).threshold_deg(p1, dp) - true.threshold_deg(p1, dp))
        assert err.max() < 0.15, (side, err)
        off = np.abs(default.side(side).threshold_deg(p1, dp) - true.threshold_deg(p1, dp))
        assert off.max() > 0.5
        c = _const(doc, f"valve.{side}.c_flow")
        assert c["value_mm3_s_deg2_sqrtMPa"] == pytest.approx(getattr(truth, f"{side}_c"), rel=0.03)


def test_servo_dead_time_plus_lag_and_rate(foreign_own):
    _, truth, doc = foreign_own
    dead = _const(doc, "servo.dead_time_s")["value_s"]
    tau = _const(doc, "servo.time_constant_s")["value_s"]
    assert dead + tau == pytest.approx(truth.servo_dead_s + truth.servo_tau_s, rel=0.15)
    assert tau == pytest.approx(truth.servo_tau_s, rel=0.15)
    rate = _const(doc, "servo.max_rate_deg_s")
    assert rate["identified"] and rate["value_deg_s"] == pytest.approx(truth.servo_rate_deg_s, rel=0.15)
    lo, hi = _const(doc, "servo.dead_time_s")["ci95_s"]
    assert lo <= truth.servo_dead_s <= hi


@pytest.mark.parametrize("seed", [0, 8])
def test_servo_intervals_hold_the_truth(tmp_path, seed):
    """Seed 0: the Jacobian with the dead-time column (a finite difference of
    a step function) was singular and the time constant and rate had no
    interval; seed 8: least_squares stopped in a local minimum of the dead
    time (0.035 s, 8 % above the profile's minimum) with an interval that
    missed the truth. The refitted profile finds the minimum and holds all
    three truths."""
    from seanv_analysis.identify import split_runs
    from seanv_analysis.identify.servo import fit_servo, servo_data
    from seanv_analysis.io.reader import find_runs, read_run

    rig = load_rig()
    truth = own_rig()
    write_position(tmp_path / "pos", seed=seed, truth=truth, n_runs=2, duration_s=60.0)
    runs = [read_run(p, rig=rig) for p in find_runs(tmp_path / "pos")]
    train, _ = split_runs(runs)
    sv = rig["servo"]
    fit = fit_servo([d for d in map(servo_data, train) if d is not None],
                    start=(sv["dead_time_s"], sv["time_constant_s"], sv["max_rate_deg_s"]),
                    resolution_deg=sv["resolution_deg"])
    assert fit.rate_identified
    # the dead time's interval also spans the stamps' phase: a command may
    # have been sent up to one servo-log sample before its stamp
    # (seed 0: synchronous 50 Hz logs, 0.02 s; seed 8: asynchronous, 0)
    lead = max(d.stamp_lead_s for d in map(servo_data, train) if d is not None)
    assert lead == pytest.approx({0: 0.02, 8: 0.0}[seed])
    for value, (lo, hi), true, extra in (
            (fit.dead_time_s, fit.dead_ci95, truth.servo_dead_s, lead),
            (fit.time_constant_s, fit.tau_ci95, truth.servo_tau_s, 0.0),
            (fit.max_rate_deg_s, fit.rate_ci95, truth.servo_rate_deg_s, 0.0)):
        assert lo <= true <= hi, (seed, value, lo, hi, true)
        assert lo <= value <= hi and hi - lo < 0.5 * true + extra


def test_friction(foreign_own):
    """Coulomb and breakaway within 20 %; the slope the force balance sees is
    the seal's viscous term plus the line's resistance (one sensor at the
    valve cannot split them), and that sum is what the twin gets. The slow
    steps that stick-slip (their mean force lies above F_c + b v) are left
    out, so the Coulomb interval holds the truth (with them: +0.6..+1.8 %
    biased, outside in 1 of 8 bench seeds)."""
    _, truth, doc = foreign_own
    coulomb = _const(doc, "actuator.coulomb_friction_n")
    assert coulomb["value_n"] == pytest.approx(truth.coulomb_n, rel=0.2)
    assert coulomb["ci95_n"][0] <= truth.coulomb_n <= coulomb["ci95_n"][1], coulomb
    assert any("did not move at a steady speed" in n for n in doc["notes"]), doc["notes"]
    static = _const(doc, "actuator.static_friction_n")
    assert "starts after a hold" in static["constrained_by"]
    assert static["value_n"] == pytest.approx(truth.static_n, rel=0.2)
    rig = load_rig()
    from seanv_analysis.sim import tube_constants

    line_pkg = tube_constants(rig)["R"] * rig.piston_area_mm2 ** 2
    line_true = truth.line_resistance_mpa_s_per_mm3 * rig.piston_area_mm2 ** 2
    seen = _const(doc, "actuator.viscous_friction_n_s_per_mm")["value_n_s_per_mm"] + line_pkg
    assert seen == pytest.approx(truth.viscous_n_s_per_mm + line_true, rel=0.2)


def test_coulomb_interval_holds_the_linear_law_when_the_stribeck_term_may_vanish():
    """A Stribeck law whose breakaway force's interval reaches the Coulomb
    force (the term may vanish): F_c's interval is the union over that
    interval, so it holds F_c + b v's own interval, not only its value (on
    our simulator the Stribeck fits' intervals, 0.01 N wide, and the linear
    value missed the true 155 N by 0.002 N in 4 of 20 seeds). Synthetic
    force balance: F_c 155 N, b 2 N s/mm, F_s 160 N, v_s 1 mm/s, speeds
    2..30 mm/s both ways, noise 0.03 N."""
    from seanv_analysis.identify.friction import _stribeck_choice, fit_friction

    rng = np.random.default_rng(4)
    v = np.concatenate([np.linspace(2.0, 30.0, 60), -np.linspace(2.0, 30.0, 60)])
    f = (np.sign(v) * (155.0 + 5.0 * np.exp(-(v / 1.0) ** 2)) + 2.0 * v
         + rng.normal(0.0, 0.03, v.size))
    pick = np.arange(v.size) % 3 == 2
    linear = fit_friction(v[~pick], f[~pick])
    best, why = _stribeck_choice(v, f, pick, 160.0, linear, 1.0, (150.0, 170.0))
    assert best is not None and not best["vs_bounded"], why
    lo, hi = best["coulomb_ci95"]
    assert lo <= linear["coulomb_ci95"][0] and linear["coulomb_ci95"][1] <= hi
    assert lo <= 155.0 <= hi and hi - lo < 0.2
    blo, bhi = best["viscous_ci95"]
    assert blo <= linear["viscous_ci95"][0] and linear["viscous_ci95"][1] <= bhi


def test_a_stribeck_velocity_the_data_do_not_bound_gets_an_open_interval(monkeypatch):
    """A v_s far below every measured speed has a Jacobian column near 0: its
    log interval's half-width ran past exp's range and ``identify`` ended
    in OverflowError (benchmarks/bench_identify.py, foreign rig seed 4:
    v_s 0.80 mm/s, speeds 3-46 mm/s). Its interval is now (0, inf), and
    the Stribeck choice, which needs v_s bounded, falls back to F_c + b v."""
    from seanv_analysis.identify import friction

    rng = np.random.default_rng(0)
    v = np.concatenate([np.linspace(3.0, 46.0, 40), -np.linspace(3.0, 46.0, 40)])
    f = np.sign(v) * 40.0 + 1.576 * v + rng.normal(0.0, 0.5, v.size)
    wide = friction._half_widths_95      # the Stribeck fit's log v_s: 1e4 wider

    def wider(jac, s2):
        return wide(jac, s2) + (np.array([0.0, 0.0, 1e4]) if jac.shape[1] == 3 else 0.0)

    monkeypatch.setattr(friction, "_half_widths_95", wider)
    fit = friction.fit_stribeck(v, f, 54.6, (40.0, 1.576, 1.0))
    assert fit["stribeck_ci95"] == (0.0, np.inf)
    pick = np.arange(v.size) % 3 == 2
    linear = friction.fit_friction(v[~pick], f[~pick])
    best, why = friction._stribeck_choice(v, f, pick, 54.6, linear, 1.0, (50.0, 60.0))
    assert best is None and why


def test_supply_pressure_and_unidentified_mass(foreign_own):
    """The foreign supply (3.0 MPaG at no flow, 2e-5 MPa per mm^3/s drawn):
    both from the supply flow steps' steady pressure vs flow, both inside
    their intervals; the rig file says a stiff 3.3 MPaG supply. The line
    goes through the steps whose motion was steady: with the stick-slipping
    cam -5 deg steps in it (their mean speed is less than the valve's flow),
    p_0 was 2.9992 [2.9987, 2.9997] MPaG, the truth outside."""
    from foreign_rig import SUPPLY_DROOP_MPA_S_PER_MM3

    _, truth, doc = foreign_own
    p0 = _const(doc, "supply.pressure_mpag")
    assert p0["value_mpag"] == pytest.approx(truth.supply_mpag, abs=0.005)
    lo, hi = p0["ci95_mpag"]
    assert lo <= truth.supply_mpag <= hi and hi - lo < 0.002, p0
    droop = _const(doc, "supply.droop_mpa_s_per_mm3")
    assert droop["identified"] and droop["default_mpa_s_per_mm3"] == 0.0
    assert droop["value_mpa_s_per_mm3"] == pytest.approx(SUPPLY_DROOP_MPA_S_PER_MM3, rel=0.03)
    lo, hi = droop["ci95_mpa_s_per_mm3"]
    assert lo <= SUPPLY_DROOP_MPA_S_PER_MM3 <= hi and hi - lo < 0.1 * SUPPLY_DROOP_MPA_S_PER_MM3
    mass = _const(doc, "actuator.moving_mass_kg")
    assert not mass["identified"] and mass["note"]


def test_closed_loop_on_heldout_runs(foreign_own):
    """The identified twin (its line found lumped: ``tube.inertance_factor``)
    re-runs the held-out position-control run closer to the measurement than
    the rig file's twin. Whole runs: position fit >= 88 %; their flow fit
    is not a criterion (a hold's end, decided by hundredths of a millimetre
    under stick-slip, is carried into every later step, see
    docs/identify.md: 0.3 N less Coulomb friction moved it from ~60 to 55 %,
    the rig file's twin's 61 %), only a floor. Each segment re-run from the logged state (the
    issue's acceptance): position fit >= 90 %, flow fit >= 75 %, where the
    rig file's twin stays below 70 %."""
    _, _, doc = foreign_own
    cl = doc["fits"]["closed_loop"]
    assert cl["heldout_pct"] >= 88.0
    assert cl["heldout_pct"] > cl["heldout_default_pct"]
    assert cl["heldout_flow_pct"] >= 50.0
    seg = doc["fits"]["closed_loop_segments"]        # measured: 96 / 84 %, rig file 79 / 63 %
    assert seg["heldout_pct"] >= 90.0 and seg["train_pct"] >= 90.0
    assert seg["heldout_flow_pct"] >= 75.0 and seg["train_flow_pct"] >= 75.0
    assert seg["heldout_default_pct"] < seg["heldout_pct"] - 10.0
    assert seg["heldout_default_flow_pct"] < 70.0


def test_validate_both_controllers_on_the_identified_twin(foreign_own, tmp_path):
    """``validate --rig rig-identified.toml`` on clean runs of the foreign
    rig with each controller (eq. 6 with the flow model; the paper's cam law
    without it, runs identify never saw): nothing flagged, position fit
    >= 90 % per segment and >= 85 % whole, flow fit >= 75 % per segment;
    the rig file's twin does worse on each. Measured: per segment 96 / 85 %
    (flow model), 95 / 80 % (cam); whole runs 90 / 92 %; rig file's twin
    81-84 / 46-56 %, its cam run flagged."""
    root, truth, _ = foreign_own
    write_position(tmp_path / "pos", seed=23, truth=truth, n_runs=2, duration_s=40.0,
                   controllers=("flow_model", "cam"))
    rows = {}
    for name, rig_args in (("identified", ["--rig", str(root / "out" / "rig-identified.toml")]),
                           ("default", [])):
        res = CliRunner().invoke(cli, ["validate", str(tmp_path / "pos"), "--json", "--no-figures",
                                       "--out", str(tmp_path / name), *rig_args])
        assert res.exit_code == 0, res.output
        doc = json.loads(res.stdout)
        check_schema("validate", doc)
        rows[name] = {r["controller"]: r for r in doc["runs"]}
        if name == "identified":
            assert doc["flagged"] == []
    for ctrl in ("flow_model", "cam"):
        r, d = rows["identified"][ctrl], rows["default"][ctrl]
        assert r["fit_position_segments_pct"] >= 90.0 and r["fit_position_pct"] >= 85.0, r
        assert r["fit_flow_segments_pct"] >= 75.0, r
        assert r["fit_flow_segments_pct"] > d["fit_flow_segments_pct"] + 5.0
        assert r["fit_position_segments_pct"] > d["fit_position_segments_pct"]


def test_line_found_lumped(foreign_own):
    """The foreign line is a lumped compliance behind a resistance (no
    water-column inertance): identify takes a small inertance factor, the
    rig file's tube (factor 1) outside its interval."""
    _, _, doc = foreign_own
    c = _const(doc, "tube.inertance_factor")
    assert c["identified"] and c["default_ratio"] == 1.0
    assert c["value_ratio"] <= 0.1 and c["ci95_ratio"][1] < 1.0, c


def test_line_time_constant_holds_the_foreign_lag(foreign_own):
    """The twin's line time constant, its compliance counting the head
    chamber at the runs' piston positions, matches the foreign lumped line's
    C_l (R_l + b/A^2) within 5 %, inside its interval (tube alone: 7-9 %
    low, outside)."""
    _, truth, doc = foreign_own
    tau = next(c for c in doc["constants"] if c["name"].startswith("line time constant"))
    lag = truth.flow_lag_s("position_control")
    assert tau["value_s"] == pytest.approx(lag, rel=0.05)
    assert tau["ci95_s"][0] <= lag <= tau["ci95_s"][1], (tau, lag)
    assert "head chamber" in tau["constrained_by"]


def test_rig_file_round_trip(foreign_own):
    """rig-identified.toml holds only identified keys and loads as a rig file."""
    root, _, doc = foreign_own
    text = (root / "out" / "rig-identified.toml").read_text()
    rig = load_rig(root / "out" / "rig-identified.toml")
    for c in doc["constants"]:
        if c["key"] and c["identified"]:
            section, *rest = c["key"].split(".")
            v = rig[section]
            for k in rest:
                v = v[k]
            assert v == pytest.approx(c[f"value{suffix_of_unit(c['unit'])}"], rel=1e-5)
        elif c["key"]:
            assert c["key"].split(".")[-1] + " =" not in text


def test_discover_does_not_blame_the_unknown_geometry(foreign_own):
    """Clean foreign flow steps, default rig file (wrong needle centres):
    discover fits the centre as part of its base model and names no effect."""
    root, _, _ = foreign_own
    res = CliRunner().invoke(cli, ["discover", str(root / "flow"), "--out", str(root / "disc"),
                                   "--json", "--no-figures"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    assert doc["verdict"] == "none", doc
    assert set(doc["base_geometry"]) == {"supply", "drain"}
    check_schema("discover", doc)  # data_schema/json/discover.schema.json
    assert keys_without_unit(doc) == []
    h = doc["heldout"]
    assert h["rmse_after_mm3_s"] < 0.5 * h["rmse_before_mm3_s"]   # the geometry's share


def test_discover_reports_both_readings_of_the_needle_centre(foreign_own):
    """identify fits the needle centre before and without any effect;
    discover fits it again with the effects it names. After an identify
    stage, discover's geometry carries both readings with their intervals
    (issue 31: report both where the data cannot tell them apart), and its
    text names both; two intervals apart are said to be apart."""
    from seanv_analysis.discover.result import _geometry_sentence
    from seanv_analysis.stages import run_stages

    root, _, _ = foreign_own
    ctx = run_stages(root / "flow", ["ingest", "identify", "discover"],
                     options={"identify": {"n_boot": 0, "parts": ["geometry"]}})
    ident = {c.key: c for c in ctx.result("identify").constants if c.key}
    geometry = ctx.result("discover").discovery.geometry
    assert set(geometry) == {"supply", "drain"}
    for side, g in geometry.items():
        c = ident[f"valve.{side}.needle_y_c_mm"]
        assert g["identified_mm"] == c.value and g["identified_ci95_mm"] == list(c.ci95)
        lo, hi = g["ci95_mm"]
        assert lo < g["needle_y_c_mm"] < hi
    text = ctx.result("discover").discovery.report()
    assert "identify " in text and "do not overlap" not in text
    apart = _geometry_sentence({"supply": {"needle_y_c_mm": -31.3, "ci95_mm": [-33.0, -29.6],
                                           "rig_file_mm": -20.0, "identified_mm": -22.5,
                                           "identified_ci95_mm": [-25.2, -19.8]}}, True)
    assert "On the supply side the two readings' intervals do not overlap" in apart


def test_flow_steps_only_says_what_it_cannot_tell(foreign_own, tmp_path):
    """Without position-control runs the servo, breakaway and line keep the
    rig file's values, each saying why; the geometry is still identified."""
    root, _, _ = foreign_own
    res = CliRunner().invoke(cli, ["identify", str(root / "flow"), "--out", str(tmp_path / "o"),
                                   "--json", "--n-boot", "0", "--part", "geometry",
                                   "--part", "friction"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    assert _const(doc, "valve.supply.needle_y_c_mm")["identified"]
    static = _const(doc, "actuator.static_friction_n")
    assert "x the rig file's breakaway/Coulomb ratio" in static["constrained_by"]
    assert not _const(doc, "actuator.moving_mass_kg")["identified"]
    assert not any(c["key"] and c["key"].startswith("servo.") for c in doc["constants"])


def test_bad_data_is_one_line(tmp_path):
    """As every command: a data set whose runs are all bad lists them (exit 1);
    a single bad run folder is one line (exit 2)."""
    (tmp_path / "d" / "r1").mkdir(parents=True)
    (tmp_path / "d" / "r1" / "run.json").write_text("{broken")
    res = CliRunner().invoke(cli, ["identify", str(tmp_path / "d"), "--out", str(tmp_path / "o")])
    assert res.exit_code == 1
    assert "Traceback" not in res.output and "r1/run.json: not valid JSON" in res.output
    res = CliRunner().invoke(cli, ["identify", str(tmp_path / "d" / "r1"),
                                   "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and len(res.output.strip().splitlines()) == 1


def test_load_regulator_interval_holds_the_spread_between_changes():
    """Load changes that differ by more than their noise (here each change
    its own time constant, 0.14..0.16 s around 0.15, noise 0.2 kPa): the
    95 % interval of the one pooled tau is at least Student's t over the
    changes' own fits (n - 1 = 5 degrees of freedom) and holds their
    centre, where the residuals alone gave an interval far narrower (on
    our simulator 17 of 20 seeds held the truth with it, 38 of 40 now)."""
    from scipy import stats

    from seanv_analysis.identify.load import fit_regulator

    rng = np.random.default_rng(7)
    t = np.arange(-0.4, 1.5, 0.002)
    taus = np.array([0.140, 0.158, 0.146, 0.160, 0.152, 0.144])
    changes = []
    for k, tau in enumerate(taus):
        a, b = (0.35, 0.45) if k % 2 == 0 else (0.45, 0.35)
        p = a + (b - a) * (1.0 - np.exp(-np.clip(t, 0.0, None) / tau))
        changes.append((t + 15.0 * k, p + rng.normal(0.0, 2e-4, t.size), a, b, 15.0 * k))
    pooled = fit_regulator(changes)
    lo, hi = pooled["ci95"]
    narrow = fit_regulator(changes, between=False)["ci95"]
    logs = np.log(taus)
    half = stats.t.ppf(0.975, taus.size - 1) * np.std(logs, ddof=1) / np.sqrt(taus.size)
    assert np.log(hi / lo) / 2 >= 0.9 * half
    assert lo <= float(np.exp(logs.mean())) <= hi
    assert narrow[1] - narrow[0] < 0.5 * (hi - lo)


def test_identify_parts_as_tasks_on_worker_processes_give_the_same_numbers(foreign_own):
    """identify's independent fits (the servo's; the geometry part's refit
    and its y_c interval-edge fits) run as tasks on an executor's worker
    processes beside the main one (issue 35: parallel data-set stages):
    every constant, interval and fit is the same as when all run here."""
    from seanv_analysis.batch import make_executor
    from seanv_analysis.identify import identify_rig
    from seanv_analysis.jsonable import dumps
    from seanv_analysis.stages import run_stages
    from seanv_analysis.stages.identify import position_runs

    root, _, _ = foreign_own
    ctx = run_stages([root / "flow", root / "position"], ["ingest"])
    ds, pos = ctx.result("ingest"), position_runs(ctx)
    kw = dict(position_runs=pos, parts=("geometry", "servo"), n_boot=20)
    here = identify_rig(ds.summary, ctx.rig, **kw)
    calls = []
    with make_executor(workers=2) as ex:
        def mapper(func, items, **k):
            calls.append((k["kwargs"]["task"].__name__, len(items)))
            return ex.tasks(func, items, quiet=True, **k)
        tasks = identify_rig(ds.summary, ctx.rig, map_tasks=mapper, **kw)
    # the servo's fit, and the refit with both sides' y_c interval edges
    assert sorted(calls) == [("_flow_fit_task", 5), ("_servo_task", 1)]
    assert dumps(tasks.to_json_dict()) == dumps(here.to_json_dict())
    assert {c.key for c in tasks.identified()} >= {"valve.supply.needle_y_c_mm",
                                                    "servo.dead_time_s"}


def _warning_task(x, *, k):
    import warnings

    if x < 0:
        raise ValueError(f"negative {x}")
    warnings.warn(f"task {x}", RuntimeWarning, stacklevel=2)
    return x * k


def test_a_task_on_a_worker_gives_its_warnings_here_and_its_error_as_here():
    """identify's tasks on worker processes: each task's warnings are given
    again in this process (a command and the batch record them with the
    rest), and a task that failed there is run here, raising its own error."""
    import warnings

    from seanv_analysis.batch import make_executor
    from seanv_analysis.identify.engine import _on_tasks

    with make_executor(workers=2) as ex:
        mapper = partial(ex.tasks, quiet=True)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            assert _on_tasks(mapper, _warning_task, [1, 2], {"k": 3}, "test") == [3, 6]
        assert sorted(str(w.message) for w in caught) == ["task 1", "task 2"]
        assert {w.category for w in caught} == {RuntimeWarning}
        with pytest.raises(ValueError, match="negative -1"):
            _on_tasks(mapper, _warning_task, [1, -1], {"k": 3}, "test")
