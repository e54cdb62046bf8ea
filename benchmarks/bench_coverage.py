"""Coverage of the 95 % intervals: how often each identified constant's
interval holds the truth, over seeds, on three kinds of data with known truth.

1. ``sim``: the project's own simulator, clean (``paper-flowsteps`` +
   ``paper-position``, one seed each); the truth is the rig file the
   simulator ran with (``data_schema/rig/default.toml``). ``identify`` (every
   part, 100 bootstrap resamples as the command's default) and ``flowfit``
   alone (200 resamples); beside the intervals, Fig. 4(b)'s check (each
   load's theta_d within 2 standard errors of the fitted eq. 3+4 line) and
   whether ``discover`` calls the needle geometry unlike the rig file's.
2. ``foreign``: ``tests/foreign_rig.py``'s ``own_rig`` (every unpublished
   constant its own: needle centres, servo, a lumped line, stick-slip
   friction, 3.0 MPaG with a droop), the benchmark plan of ``bench_identify``
   (240 flow steps, 2 position-control runs of 60 s).
3. ``field``: the three field data sets (``tests/field_data.py``), once each;
   the truth of ``_truth/<set>.json``.

Constants whose truth the model cannot be compared with (the needle-head
height z0 where the rig's x_c differs from the rig file's: z0 absorbs it; the
line's bulk modulus of a rig whose line is not the rig file's tube; the seal's
viscous term alone, which one pressure sensor at the valve cannot split from
the line's resistance) are listed with the reason and not counted.
Coverage below 90 % is reported with the reason found (``REASONS``), or "no
reason known".

Writes ``benchmarks/results/bench_coverage.json`` and ``bench_coverage.md``
(the table). Seeds: ``SEANV_COVERAGE_SEEDS`` (default 20),
``SEANV_COVERAGE_FOREIGN_SEEDS`` (default 4), ``SEANV_COVERAGE_SOURCES``
(default ``sim,foreign,field``), ``SEANV_COVERAGE_WORKERS`` (default: the
processors), or from the command line::

    python -m benchmarks.bench_coverage --seeds 3 --foreign-seeds 1 --sources sim,field

Measured on the shared 2-core machine, 2 workers (load 5-6): one ``sim``
seed 69 s of wall time (median of 20: simulation 9 s, ingest 4 s, identify
46 s, flowfit 6 s, discover 2 s), a ``foreign`` seed 67-78 s, a field set
36-66 s; 20 + 4 + 3 runs: 15 min.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

HERE = Path(__file__).resolve().parent
TESTS = HERE.parent / "tests"

#: coverage asked for, per constant
TARGET = 0.90

#: (source, key or derived name) -> why its truth is not compared
_XC = ("the flow steps cannot tell x_c (to first order a z0 offset): identify keeps the rig "
       "file's and says so; z0's, C's and y_c's intervals carry its range "
       "(valve.needle_x_c_uncertainty_mm)")
NOT_COMPARABLE = {
    **{(src, f"valve.{side}.needle_x_c_mm"): _XC for src in ("foreign", "field")
       for side in ("supply", "drain")},
    **{(src, "actuator.viscous_friction_n_s_per_mm"): "not separable from the line's "
       "resistance: the sum is compared" for src in ("foreign", "field")},
    ("foreign", "tube.effective_bulk_modulus_mpa"): "the foreign line is one lumped compliance, "
                                                    "not the tube: its time constant is compared",
    ("foreign", "tube.inertance_factor"): "the foreign line is lumped (no truth factor)",
    ("field", "tube.inertance_factor"): "the field rig's line is its own model (no truth factor)",
}

#: (source, key or derived name) -> why coverage stays below the target
#: (what was measured; see docs/identify.md)
REASONS = {
    ("sim", "load.regulator_time_constant_s"): (
        "3 of 20 intervals (+-1.1 %) missed by 1.2-1.9 %: at a true 95 %, 3 or more misses "
        "in 20 have a 7.5 % chance; no systematic cause found"),
    ("sim", "actuator.coulomb_friction_n"): (
        "154.99 N for 155 in every seed, intervals +-0.01 N: 4 of 20 missed by 0.001-0.002 N; "
        "a 0.005 % bias whose source in the simulator's friction is not found (docs/identify.md)"),
    ("foreign", "supply.droop_mpa_s_per_mm3"): (
        "one miss in 4 seeds (seed 2: 2.0081e-5 [2.0022e-5, 2.0141e-5] for 2e-5: the value 0.4 % off, the interval 0.1 % short); "
        "at a true 95 % one or more misses in 4 have an 18.5 % chance"),
    ("field", "actuator.coulomb_friction_n"): (
        "field-clean and field-drift-backlash hold it (the Stribeck law fitted, 85.8 and 86.2 N "
        "for 85); field-slow-servo has no flow steps, so no force balance: not identified"),
    ("field", "friction + line slope b + R A^2"): (
        "the Stribeck law's slope: the steady speeds' force is F_c + (F_s - F_c) exp(-v/v_s) "
        "+ b v, whose tangent a straight line fitted alone would give"),
    ("field", "tube.effective_bulk_modulus_mpa"): (
        "field-clean: 317 [304, 318] MPa for 300 (with the servo's rate from the logs; 313 "
        "[308, 339] with the rig file's): on the identified twin the training run's replay "
        "is best at B ~310, the held-out run's at >= 330 (a scan over B): the field rig's "
        "line is not the twin's R-I-C ladder, and one effective B is a compromise of the "
        "runs; field-drift-backlash (250 [248, 271]): its position runs carry an undeclared "
        "1.5 deg backlash the twin has not (with the play, discover's joint search puts B at "
        "275-305; with the position runs' supply C, 16.0 for the flow steps' 15.10 averaged "
        "over the drift, identify's B is 253: the play moves it, not the drift); "
        "field-slow-servo has no flow steps, so the twin's valve is the rig file's, unlike "
        "this rig's (352 MPa): B takes the twin's misfit. identify says so on the two sets "
        "with a held-out run: the held-out run replays better at the interval's upper end "
        "(B's note: an effective value)"),
    ("field", "valve.supply.c_flow"): (
        "field-drift-backlash: its supply C falls 4 % every third sweep (an undeclared "
        "effect): one C cannot hold it (discover's job)"),
    ("field", "valve.supply.needle_y_c_mm"): (
        "field-drift-backlash: the undeclared supply drift bends the threshold's movement "
        "with the load, which y_c reads (identify -22.5 mm for -32; discover, which chooses "
        "the centre with the drift, -31.3 [-40.9, -21.8])"),
}


def _foreign():
    sys.path.insert(0, str(TESTS))
    import foreign_rig

    return foreign_rig


def _get(rig, key: str) -> float:
    v = rig
    for part in key.split("."):
        v = v[part]
    return float(v)


def _rows(res, truth: dict, source: str, run: str) -> list[dict]:
    """One row per constant of an identification with a truth (by rig key,
    or by name for derived ones)."""
    out = []
    for c in res.constants:
        ident = c.key or c.name
        if ident not in truth:
            continue
        lo, hi = (float(v) for v in c.ci95)
        out.append({"source": source, "run": run, "key": ident, "value": float(c.value),
                    "lo": lo, "hi": hi, "truth": float(truth[ident]),
                    "identified": bool(c.identified)})
    return out


def _sim_truth(rig) -> dict:
    from seanv_analysis.sim import tube_constants

    keys = ["supply.pressure_mpag", "valve.supply.needle_y_c_mm", "valve.drain.needle_y_c_mm",
            "valve.supply.z0_mm", "valve.supply.c_flow", "valve.drain.z0_mm",
            "valve.drain.c_flow", "valve.plant.leakage_conductance_mm3_s_per_mpa",
            "servo.dead_time_s", "servo.time_constant_s", "servo.max_rate_deg_s",
            "actuator.coulomb_friction_n", "actuator.viscous_friction_n_s_per_mm",
            "actuator.static_friction_n", "load.regulator_time_constant_s",
            "tube.effective_bulk_modulus_mpa", "tube.inertance_factor",
            "controller.convergence_band_mm"]
    truth = {k: _get(rig, k) for k in keys}
    truth["friction + line slope b + R A^2"] = (
        _get(rig, "actuator.viscous_friction_n_s_per_mm")
        + tube_constants(rig)["R"] * rig.piston_area_mm2 ** 2)
    return truth


def _sim(seed: int) -> dict:
    """Our simulator, clean, one seed: identify, flowfit, Fig. 4(b), discover."""
    import numpy as np

    from seanv_analysis import load_rig
    from seanv_analysis.discover import discover_flow_steps
    from seanv_analysis.fit import fit_flow
    from seanv_analysis.identify import identify_rig
    from seanv_analysis.sim.scenarios import simulate_scenario
    from seanv_analysis.stages import run_stages
    from seanv_analysis.stages.dataset import position_runs

    rig = load_rig()
    times = {}
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        simulate_scenario("paper-flowsteps", Path(tmp) / "flow", seed=seed)
        simulate_scenario("paper-position", Path(tmp) / "position", seed=seed)
        t1 = time.perf_counter()
        ctx = run_stages([Path(tmp) / "flow", Path(tmp) / "position"], ["ingest"])
        summary, pos = ctx.result("ingest").summary, position_runs(ctx)
        t2 = time.perf_counter()
        res = identify_rig(summary, ctx.rig, position_runs=pos)
        t3 = time.perf_counter()
    fit = fit_flow(summary, ctx.rig, n_boot=200, seed=0)
    t4 = time.perf_counter()
    disc = discover_flow_steps(summary, model=fit.model, seed=0)
    t5 = time.perf_counter()
    times = {"simulate_s": t1 - t0, "ingest_s": t2 - t1, "identify_s": t3 - t2,
             "flowfit_s": t4 - t3, "discover_s": t5 - t4}
    truth = _sim_truth(rig)
    rows = _rows(res, truth, "sim", f"seed {seed}")
    for side, sf in fit.sides.items():
        for name, v, ci, key in (("z0_mm", sf.z0_mm, sf.z0_ci95, f"valve.{side}.z0_mm"),
                                 ("c_flow", sf.c_flow, sf.c_ci95, f"valve.{side}.c_flow")):
            rows.append({"source": "sim", "run": f"seed {seed}", "key": f"flowfit {side}.{name}",
                         "value": float(v), "lo": float(ci[0]), "hi": float(ci[1]),
                         "truth": truth[key], "identified": bool(sf.success)})
    lk = fit.leakage
    rows.append({"source": "sim", "run": f"seed {seed}", "key": "flowfit seat leakage",
                 "value": lk.conductance_mm3_s_per_mpa, "lo": lk.ci95[0], "hi": lk.ci95[1],
                 "truth": truth["valve.plant.leakage_conductance_mm3_s_per_mpa"],
                 "identified": bool(lk.fitted)})
    pl = fit.per_load[fit.per_load["success"].astype(bool)]
    off = (pl["theta_d_deg"] - pl["theta_d_model_deg"]).to_numpy(float)
    z = off / pl["theta_d_se_deg"].to_numpy(float)
    fig4b = {"loads": int(len(pl)), "within_2se": int(np.sum(np.abs(z) <= 2.0)),
             "offset_deg": {f"{s} {lv:g}": round(float(o), 4) for s, lv, o in
                            zip(pl["side"], pl["load_level_mpag"], off)},
             "z": [round(float(v), 2) for v in z]}
    return {"rows": rows, "fig4b": fig4b, "discover_geometry": disc.geometry,
            "discover_verdict": disc.verdict, "times": times}


def _foreign_truth(truth) -> dict:
    fr = _foreign()
    from seanv_analysis import load_rig

    area = load_rig().piston_area_mm2
    return {"supply.pressure_mpag": truth.supply_mpag,
            "supply.droop_mpa_s_per_mm3": fr.SUPPLY_DROOP_MPA_S_PER_MM3,
            "valve.supply.needle_y_c_mm": truth.supply_y_c_mm,
            "valve.drain.needle_y_c_mm": truth.drain_y_c_mm,
            "valve.supply.needle_x_c_mm": truth.supply_x_c_mm,
            "valve.drain.needle_x_c_mm": truth.drain_x_c_mm,
            "valve.supply.c_flow": truth.supply_c, "valve.drain.c_flow": truth.drain_c,
            "valve.supply.z0_mm": truth.supply_z0_mm, "valve.drain.z0_mm": truth.drain_z0_mm,
            "valve.plant.leakage_conductance_mm3_s_per_mpa": fr.LEAK_MM3_S_PER_MPA,
            "servo.dead_time_s": truth.servo_dead_s, "servo.time_constant_s": truth.servo_tau_s,
            "servo.max_rate_deg_s": truth.servo_rate_deg_s,
            "actuator.coulomb_friction_n": truth.coulomb_n,
            "actuator.static_friction_n": truth.static_n,
            "actuator.viscous_friction_n_s_per_mm": truth.viscous_n_s_per_mm,
            "friction + line slope b + R A^2": (truth.viscous_n_s_per_mm
                                                + truth.line_resistance_mpa_s_per_mm3 * area ** 2),
            # the foreign rig's load regulator (tests/foreign_rig.py: tau 0.1 s)
            "load.regulator_time_constant_s": 0.1,
            "line time constant C (R + b/A^2)": truth.flow_lag_s("position_control"),
            "tube.effective_bulk_modulus_mpa": math.nan, "tube.inertance_factor": math.nan}


def _foreign_run(seed: int) -> dict:
    fr = _foreign()
    from seanv_analysis.identify import identify_rig
    from seanv_analysis.stages import run_stages
    from seanv_analysis.stages.dataset import position_runs

    truth = fr.own_rig()
    plan = fr.flowstep_plan(supply_cams=(-5.0, -2.5, 0.0, 2.5, 5.0, 7.5, 10.0),
                            drain_cams=(-40.0, -37.5, -35.0, -32.5, -30.0, -27.5, -25.0, -22.5,
                                        -20.0),
                            loads=(0.1, 0.2, 0.3, 0.4, 0.5), repeats=3)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        t0 = time.perf_counter()
        fr.write_flowsteps(root / "flow", plan=plan, seed=seed, truth=truth)
        fr.write_position(root / "position", seed=seed, truth=truth, n_runs=2, duration_s=60.0)
        ctx = run_stages([root / "flow", root / "position"], ["ingest"])
        t1 = time.perf_counter()
        res = identify_rig(ctx.result("ingest").summary, ctx.rig, position_runs=position_runs(ctx))
        t2 = time.perf_counter()
    return {"rows": _rows(res, _foreign_truth(truth), "foreign", f"seed {seed}"),
            "times": {"data_s": t1 - t0, "identify_s": t2 - t1}}


def _field_truth(doc: dict) -> dict:
    from seanv_analysis import load_rig

    p, area = doc["plant"], load_rig().piston_area_mm2
    out = {"supply.pressure_mpag": p["supply_mpag"],
           "servo.dead_time_s": p["servo_dead_time_s"],
           "servo.time_constant_s": p["servo_time_constant_s"],
           "servo.max_rate_deg_s": p["servo_rate_limit_deg_s"],
           "actuator.coulomb_friction_n": p["coulomb_friction_n"],
           "actuator.static_friction_n": p["static_friction_n"],
           "actuator.viscous_friction_n_s_per_mm": p["viscous_friction_n_s_per_mm"],
           "friction + line slope b + R A^2": (p["viscous_friction_n_s_per_mm"]
                                               + p["line_resistance_mpa_s_mm3"] * area ** 2),
           "load.regulator_time_constant_s": p["load_regulator_time_constant_s"],
           "tube.effective_bulk_modulus_mpa": p["line_bulk_modulus_mpa"],
           "tube.inertance_factor": math.nan,
           "valve.plant.leakage_conductance_mm3_s_per_mpa": p["sealed_needle_leak_mm3_s_mpa"]}
    for side in ("supply", "drain"):
        out[f"valve.{side}.c_flow"] = doc[side]["C"]
        out[f"valve.{side}.z0_mm"] = doc[side]["z0_mm"]
        out[f"valve.{side}.needle_y_c_mm"] = doc[side]["y_c_mm"]
        out[f"valve.{side}.needle_x_c_mm"] = doc[side]["x_c_mm"]
    return out


def _field_run(args) -> dict:
    name, root = args
    sys.path.insert(0, str(TESTS))
    from field_data import field_truth

    from seanv_analysis.identify import identify_rig
    from seanv_analysis.stages import run_stages
    from seanv_analysis.stages.dataset import position_runs

    t0 = time.perf_counter()
    ctx = run_stages(Path(root) / name, ["ingest"])
    t1 = time.perf_counter()
    res = identify_rig(ctx.result("ingest").summary, ctx.rig, position_runs=position_runs(ctx))
    t2 = time.perf_counter()
    return {"rows": _rows(res, _field_truth(field_truth(root, name)), "field", name),
            "times": {"ingest_s": t1 - t0, "identify_s": t2 - t1}}


def _task(args):
    kind, arg = args
    t0 = time.perf_counter()
    out = {"sim": _sim, "foreign": _foreign_run, "field": _field_run}[kind](arg)
    out["wall_s"] = time.perf_counter() - t0
    out["task"] = f"{kind} {arg if kind != 'field' else arg[0]}"
    return out


def coverage_table(rows: list[dict]) -> list[dict]:
    """Per (source, constant): runs with a finite interval, runs whose
    interval holds the truth, the rate, and why when below the target or
    not compared."""
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in rows:
        groups.setdefault((r["source"], r["key"]), []).append(r)
    table = []
    for (source, key), rs in sorted(groups.items()):
        why_not = NOT_COMPARABLE.get((source, key))
        finite = [r for r in rs if r["identified"] and math.isfinite(r["lo"])
                  and math.isfinite(r["hi"]) and math.isfinite(r["truth"])]
        hit = [r for r in finite if r["lo"] <= r["truth"] <= r["hi"]]
        rate = len(hit) / len(finite) if finite else math.nan
        row = {"source": source, "constant": key, "runs": len(rs), "with_interval": len(finite),
               "covered": len(hit), "rate": rate,
               "truth": rs[0]["truth"],
               "values": [round(r["value"], 6) for r in rs],
               "misses": [(r["run"], round(r["value"], 6), [round(r["lo"], 6), round(r["hi"], 6)])
                          for r in finite if r not in hit]}
        if why_not:
            row["status"], row["note"] = "not compared", why_not
        elif not finite:
            row["status"], row["note"] = "no interval", "not identified in any run"
        elif rate >= TARGET:
            row["status"], row["note"] = "ok", ""
        else:
            row["status"] = "below target"
            row["note"] = REASONS.get((source, key), "no reason known")
        table.append(row)
    return table


def _markdown(table: list[dict]) -> str:
    lines = ["| source | constant | truth | covered / with interval | rate | status |",
             "|---|---|---|---|---|---|"]
    for r in table:
        rate = "n/a" if not math.isfinite(r["rate"]) else f"{100 * r['rate']:.0f} %"
        truth = "n/a" if not math.isfinite(r["truth"]) else f"{r['truth']:.4g}"
        status = r["status"] + (f": {r['note']}" if r["note"] else "")
        lines.append(f"| {r['source']} | {r['constant']} | {truth} | {r['covered']} / "
                     f"{r['with_interval']} | {rate} | {status} |")
    return "\n".join(lines) + "\n"


def main(seeds: int | None = None, foreign_seeds: int | None = None,
         sources: tuple[str, ...] | None = None, workers: int | None = None) -> dict:
    seeds = int(os.environ.get("SEANV_COVERAGE_SEEDS", 20)) if seeds is None else seeds
    foreign_seeds = (int(os.environ.get("SEANV_COVERAGE_FOREIGN_SEEDS", 4))
                     if foreign_seeds is None else foreign_seeds)
    sources = tuple(os.environ.get("SEANV_COVERAGE_SOURCES", "sim,foreign,field").split(",")
                    if sources is None else sources)
    workers = int(os.environ.get("SEANV_COVERAGE_WORKERS", os.cpu_count() or 1)
                  if workers is None else workers)
    tasks = []
    if "sim" in sources:
        tasks += [("sim", s) for s in range(seeds)]
    if "foreign" in sources:
        tasks += [("foreign", s) for s in range(foreign_seeds)]
    field_tmp = None
    if "field" in sources:
        sys.path.insert(0, str(TESTS))
        from field_data import FIELD_SETS, unpack_field_data

        field_tmp = tempfile.TemporaryDirectory()
        root = unpack_field_data(Path(field_tmp.name))
        if root is not None:
            tasks += [("field", (name, str(root))) for name in FIELD_SETS]
    t0 = time.perf_counter()
    try:
        with ProcessPoolExecutor(max_workers=max(1, workers)) as pool:
            done = list(pool.map(_task, tasks))
    finally:
        if field_tmp is not None:
            field_tmp.cleanup()
    rows = [r for d in done for r in d["rows"]]
    table = coverage_table(rows)
    sims = [d for d in done if d["task"].startswith("sim")]
    out = {"seeds": {"sim": seeds if "sim" in sources else 0,
                     "foreign": foreign_seeds if "foreign" in sources else 0,
                     "field": sum(d["task"].startswith("field") for d in done)},
           "target": TARGET, "wall_s": time.perf_counter() - t0, "workers": workers,
           "task_wall_s": {d["task"]: round(d["wall_s"], 1) for d in done},
           "task_times_s": {d["task"]: {k: round(v, 1) for k, v in d["times"].items()}
                            for d in done},
           "below_target": [{k: r[k] for k in ("source", "constant", "rate", "note")}
                            for r in table if r["status"] == "below target"],
           "table": table}
    if sims:
        out["fig4b_within_2se"] = {d["task"]: f"{d['fig4b']['within_2se']}/{d['fig4b']['loads']}"
                                   for d in sims}
        out["fig4b_offsets_deg"] = {d["task"]: d["fig4b"]["offset_deg"] for d in sims}
        out["discover_geometry"] = {d["task"]: d["discover_geometry"] for d in sims}
        out["discover_verdict"] = {d["task"]: d["discover_verdict"] for d in sims}
    results = HERE / "results"
    results.mkdir(exist_ok=True)
    (results / "bench_coverage.json").write_text(json.dumps(out, indent=2, default=str) + "\n")
    (results / "bench_coverage.md").write_text(_markdown(table))
    return out


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=None, help="seeds of our simulator (20)")
    ap.add_argument("--foreign-seeds", type=int, default=None, help="foreign-rig seeds (4)")
    ap.add_argument("--sources", default=None, help="sim,foreign,field (all)")
    ap.add_argument("--workers", type=int, default=None, help="processes (the processors)")
    a = ap.parse_args()
    res = main(a.seeds, a.foreign_seeds, tuple(a.sources.split(",")) if a.sources else None,
               a.workers)
    print(_markdown(res["table"]))
    print(json.dumps({k: v for k, v in res.items() if k != "table"}, indent=2, default=str))
