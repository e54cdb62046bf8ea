"""Simulator speed: real-time factor of ``paper-position``, the real compile
cost, and the simulator's integrator against ``scipy.integrate.odeint`` and
``solve_ivp`` at EQUAL error (each method's error-vs-time curve), in one run.

1. Real-time factor (RTF). ``simulate_position_control`` on the paper's
   position profile with the flow-model controller (95 s simulated, the
   whole call: kernel + DataFrames), best of ``RTF_REPEATS`` after a warm-up
   call; RTF = simulated s / wall s. Also the whole
   ``simulate_scenario('paper-position')`` (two 95 s runs, CSV files written).

2. Compile cost, really compiled (:func:`_cold_compile`): a child process
   whose cache folder (``SEANV_NUMBA_CACHE``: the ahead-of-time module and
   numba's cache, :mod:`seanv_analysis.sim.compiled`) is a fresh, empty
   temporary folder: the first call builds the ahead-of-time module
   (``aot_build``; what ``make`` pays once at install), a second fresh
   process loads it (``aot_load``); the same with ``SEANV_AOT=0`` (numba's
   JIT compiles from nothing, then loads its cache). Each child checks it
   built what it says (the folder was empty, the module / numba's cache
   files are there afterwards).

3. Equal error (issue 35). The kernel's stiction (Karnopp velocity reset)
   and servo quantisation are not an ODE, so the comparison runs on
   ``tests/sim_rhs.py`` (the ODE twin): f(t, y) of the same plant (same packed
   parameters, the same compiled plant physics
   :func:`seanv_analysis.sim.rosenbrock.plant_f` the kernel steps; friction
   ``(Fc + (Fs-Fc) exp(-(v/vs)^2)) tanh(v/eps_v) + b v``, ``eps_v = EPS_V``;
   continuous servo angle; sealing thresholds at the current pressures).
   Case: open-loop supply flow step, cam -15 -> +5 deg commanded at 0.5 s
   (through dead time, lag and rate limit), load 0.4 MPaG, piston from
   5 mm, 3 s (no controller in the loop).

   - reference: LSODA at rtol 1e-11 (atol 1e-13 x state scale), checked
     against Radau; their difference is the floor below which an error is
     not resolved;
   - ``kernel_ros2``: ``sim_rhs.fixed_step``, the SIMULATOR'S OWN integrator
     (the ROS2 step of :mod:`seanv_analysis.sim.rosenbrock` the kernel
     calls) on the same compiled physics, its step swept 1 ms / k
     (``STEP_DIVISORS``; 1 ms is the simulator's);
   - ``odeint`` (LSODA without ``solve_ivp``'s Python layer), without and
     with a compiled finite-difference Jacobian (``sim_rhs.jacobian``), and
     ``solve_ivp`` with LSODA, BDF and Radau: rtol swept in half decades
     (``CURVE_RTOLS``, atol = rtol x state scale), each restarted at the
     servo-target switch;
   - error: max |x - x_ref| [mm] and max |v A - (v A)_ref| [mm^3/s] on the
     1 kHz grid; time: best wall time of repeats within a budget;
   - each curve goes to ``results/sim_error_vs_time.json`` and ``.png``; the
     ratio at equal error is read on each method's Pareto front at the
     errors the kernel makes at each of its steps (log-log interpolation
     between the two settings that bracket it, and the cheapest setting at
     least as accurate), per metric. The headline ratios (``lsoda_ratio``,
     ``odeint_ratio``, ``odeint_jacobian_ratio``) are the smaller of the x
     and the flow ratio at the simulator's 1 ms step.

   Sensitivity rows (the earlier, weaker definition, kept for the variants):
   LSODA's loosest third-decade rtol whose x AND flow errors are both <=
   ours, with ``EPS_V_ALT`` (tighter friction regularisation), with servo
   quantisation, and with LSODA restarted every 10 ms (what a 100 Hz
   controller forces on a solver). For information: the kernel itself on
   the same flow step (its own physics) against the ODE reference, and the
   per-call cost of the compiled valve functions the kernel and the RHS share.

Other processes on the machine disturb the 1 ms - 5 s timings; the 1-minute
load average is recorded before and after.
Targets: ``rtf_position_control >= 1000``, ``lsoda_ratio >= 20``,
``odeint_jacobian_ratio >= 20`` (at equal error).
Results: ``benchmarks/results/sim.json``, ``sim_error_vs_time.json``,
``sim_error_vs_time.png``. Usage: ``python -m benchmarks sim``.
"""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from . import tests_module

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "sim.json"
REPEATS = 7
RTF_REPEATS = 5
RTF_TARGET = 1000.0
RATIO_TARGET = 20.0
EPS_V = 1e-2          # friction regularisation velocity [mm/s]
EPS_V_ALT = 1e-3
CASE = {"cam_deg": 5.0, "load_mpag": 0.4, "x0_mm": 5.0, "t_cmd_s": 0.5, "duration_s": 3.0}
RTOLS = [10.0 ** (-k / 3) for k in range(9, 28)]   # third decades, 1e-3 .. 1e-9

def _best_pair(fa, fb, repeats: int = REPEATS) -> tuple[float, float]:
    """Best wall times of two calls timed alternately (so both see the same
    machine load)."""
    ta, tb = np.inf, np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fa()
        ta = min(ta, time.perf_counter() - t0)
        t0 = time.perf_counter()
        fb()
        tb = min(tb, time.perf_counter() - t0)
    return ta, tb


def _best(fn, repeats: int = REPEATS) -> tuple[float, object]:
    best, out = np.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


# 1. real-time factor ------------------------------------------------------------

_COLD = r"""
import json, os, sys, time
from pathlib import Path
t0 = time.perf_counter()
from seanv_analysis import load_rig
from seanv_analysis.sim import compiled
from seanv_analysis.sim.control import FlowModelController
from seanv_analysis.sim import simulate_position_control
from seanv_analysis.sim.scenarios import paper_position_profile
t1 = time.perf_counter()
base = Path(os.environ["SEANV_NUMBA_CACHE"])
before = sorted(str(p.relative_to(base)) for p in base.rglob("*") if p.is_file())
rig = load_rig(); ref, load, _ = paper_position_profile()
ctrl = FlowModelController.from_rig(rig)
simulate_position_control(rig, controller=ctrl, x_ref=ref, load=load, duration_s=0.1)
t2 = time.perf_counter()
simulate_position_control(rig, controller=ctrl, x_ref=ref, load=load, duration_s=0.1)
t3 = time.perf_counter()
after = [p for p in base.rglob("*") if p.is_file()]
print(json.dumps({"import_s": t1 - t0, "first_call_s": t2 - t1, "second_call_s": t3 - t2,
                  "aot_status": compiled.aot_status(),
                  "aot_module_existed_before": str(compiled.aot_module_path().relative_to(base))
                  in before,
                  "aot_module_loaded": compiled.aot_status() is None
                  and compiled.aot_module_path().is_file(),
                  "numba_files_before": sum(p.endswith((".nbi", ".nbc")) for p in before),
                  "numba_files_after": sum(p.suffix in (".nbi", ".nbc") for p in after),
                  "numba_imported": "numba" in sys.modules}))
"""


def _child(cache: Path, aot: bool) -> dict:
    """The first simulation of a fresh process whose cache folder is ``cache``
    (``SEANV_NUMBA_CACHE``: the ahead-of-time module and numba's cache)."""
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "NUMBA_DISABLE_JIT")}
    env.update(SEANV_NUMBA_CACHE=str(cache), SEANV_AOT="1" if aot else "0")
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-c", _COLD], env=env, capture_output=True,
                       text=True, cwd=HERE.parent, timeout=900)
    wall = time.perf_counter() - t0
    if r.returncode != 0:
        return {"error": r.stderr[-500:]}
    d = json.loads(r.stdout.strip().splitlines()[-1])
    d = {k: (round(v, 3) if isinstance(v, float) else v) for k, v in d.items()}
    d["process_wall_s"] = round(wall, 3)
    return d


def _cold_compile() -> dict:
    """The compile a fresh install pays, really compiled: each case in a
    fresh, empty, temporary cache folder (``SEANV_NUMBA_CACHE``), checked
    to have built what it says (the folder was empty; the ahead-of-time
    module is there and loaded; numba's cache files appeared):

    - ``aot_build``: the default, the first call builds the ahead-of-time
      module (``numba.pycc``) and loads it; what ``make`` pays once at install;
    - ``aot_load``: a second fresh process on the same folder: the module loads;
    - ``jit_compile``: ``SEANV_AOT=0``, numba's JIT compiles from nothing;
    - ``jit_cache_load``: a second fresh process on that folder: numba's cache loads.
    """
    out = {}
    for aot in (True, False):
        with tempfile.TemporaryDirectory(prefix="bench-sim-cache-") as tmp:
            cache = Path(tmp) / "cache"
            first = _child(cache, aot)
            second = _child(cache, aot)
        if aot:
            first["compiled"] = (first.get("aot_module_loaded") is True
                                 and first.get("aot_module_existed_before") is False)
            out.update(aot_build=first, aot_load=second)
        else:
            first["compiled"] = (first.get("numba_files_before") == 0
                                 and (first.get("numba_files_after") or 0) > 0)
            out.update(jit_compile=first, jit_cache_load=second)
    return out


def _rtf() -> dict:
    from seanv_analysis import load_rig
    from seanv_analysis.sim import simulate_position_control, simulate_scenario
    from seanv_analysis.sim.control import FlowModelController
    from seanv_analysis.sim.scenarios import paper_position_profile

    rig = load_rig()
    ref, load, duration = paper_position_profile()
    ctrl = FlowModelController.from_rig(rig)

    def once():
        return simulate_position_control(rig, controller=ctrl, x_ref=ref, load=load,
                                         duration_s=duration)

    t0 = time.perf_counter()
    once()                                  # warm-up: numba cache load (or compile)
    first = time.perf_counter() - t0
    wall, _ = _best(once, RTF_REPEATS)
    with tempfile.TemporaryDirectory(prefix="bench-sim-") as tmp:
        simulate_scenario("paper-position", Path(tmp) / "warm")
        times = []
        for k in range(2):
            t0 = time.perf_counter()
            out = simulate_scenario("paper-position", Path(tmp) / f"run{k}")
            times.append(time.perf_counter() - t0)
        mb = sum(f.stat().st_size for f in out.rglob("*") if f.is_file()) / 2**20
    scen = min(times)
    return {"simulated_s": duration, "wall_s": round(wall, 4),
            "rtf_position_control": round(duration / wall, 1),
            "first_call_in_process_s": round(first, 3),
            "scenario_simulated_s": 2 * duration, "scenario_wall_s": round(scen, 4),
            "scenario_written_mb": round(mb, 1),
            "rtf_scenario_with_io": round(2 * duration / scen, 1)}


# 3b. sensitivity rows: LSODA not worse in both errors -----------------------------

def _ode_compare(plant, *, eps_v: float, quantise: bool, radau_check: bool,
                 restart_every_s: float | None = None, full_scan: bool = True) -> dict:
    """Reference, our fixed step, the LSODA rtol scan, the matched timing.
    ``full_scan=False`` stops the scan at the first matched rtol (variants)."""
    R = tests_module("sim_rhs")

    case = R.open_loop_step(plant, eps_v_mm_s=eps_v, quantise=quantise, **CASE)
    area = case.pp[R.PP.AREA]

    def err(ys, ref):
        ix, iv = case.lay["x"], case.lay["v"]
        return (float(np.abs(ys[:, ix] - ref[:, ix]).max()),
                float(np.abs(ys[:, iv] - ref[:, iv]).max() * area))

    scale = R.atol_scale(case.lay)
    t0 = time.perf_counter()
    ref, nfev_ref, ok = R.solve_ivp_grid(case, method="LSODA", rtol=1e-10, atol=1e-12 * scale)
    out = {"reference": {"method": "LSODA", "rtol": 1e-10, "atol": "1e-12 x scale",
                         "success": ok, "nfev": nfev_ref,
                         "wall_s": round(time.perf_counter() - t0, 3)}}
    if radau_check:
        t0 = time.perf_counter()
        rad, nfev, ok = R.solve_ivp_grid(case, method="Radau", rtol=1e-10, atol=1e-12 * scale)
        ex, eq = err(rad, ref)
        out["reference"]["radau_check"] = {"success": ok, "nfev": nfev,
                                           "wall_s": round(time.perf_counter() - t0, 3),
                                           "max_dx_mm": ex, "max_dq_mm3_s": eq}
    ys = case.run_fixed_step()               # compile / cache load
    t_ours, _ = _best(case.run_fixed_step)
    ours_x, ours_q = err(ys, ref)
    scan = []
    for rtol in RTOLS:
        t0 = time.perf_counter()
        y, nfev, ok = R.solve_ivp_grid(case, method="LSODA", rtol=rtol,
                                       restart_every_s=restart_every_s)
        wall = time.perf_counter() - t0
        ex, eq = err(y, ref)
        scan.append({"rtol": float(f"{rtol:.3g}"), "success": ok, "nfev": nfev,
                     "wall_s": round(wall, 4), "err_x_mm": ex, "err_q_mm3_s": eq,
                     "not_worse": bool(ok and ex <= ours_x and eq <= ours_q),
                     "rtol_exact": rtol})
        if scan[-1]["not_worse"] and not full_scan:
            break
    matched = next((s for s in scan if s["not_worse"]), None)
    matched = dict(matched) if matched else None
    # for information: the loosest rtol from which every tighter one scanned also matches
    # (not the headline: LSODA's cheaper isolated matching points count in its favour)
    robust = None
    if full_scan:
        for row in reversed(scan):
            if not row["not_worse"]:
                break
            robust = row["rtol"]
    for row in scan:
        row.pop("rtol_exact")
    res = {"eps_v_mm_s": eps_v, "servo_quantisation": quantise,
           "lsoda_restart_every_s": restart_every_s,
           "steps": int(round(case.duration / case.pp[R.PP.DT])),
           "travel_mm": round(float(ref[-1, case.lay["x"]] - ref[0, case.lay["x"]]), 2),
           "ours_s": round(t_ours, 5), "our_error_mm": ours_x, "our_error_q_mm3_s": ours_q,
           **out, "lsoda_scan": scan}
    if full_scan:
        res["lsoda_rtol_all_tighter_match"] = robust
    if matched is None:
        res.update(lsoda_rtol_matched=None, lsoda_s=None, lsoda_ratio=None)
        return res
    # matched pair timed alternately, best of REPEATS each
    t_ours, t_l = _best_pair(
        case.run_fixed_step,
        lambda: R.solve_ivp_grid(case, method="LSODA", rtol=matched["rtol_exact"],
                                 restart_every_s=restart_every_s))
    res["ours_s"] = round(t_ours, 5)
    # why the ratio is what it is: calls x cost per call on each side
    res["ours_ns_per_step"] = round(t_ours / res["steps"] * 1e9, 1)
    res["lsoda_us_per_rhs_call"] = round(t_l / matched["nfev"] * 1e6, 2)
    res.update(lsoda_rtol_matched=matched["rtol"], lsoda_nfev=matched["nfev"],
               lsoda_error_mm=matched["err_x_mm"], lsoda_error_q_mm3_s=matched["err_q_mm3_s"],
               lsoda_s=round(t_l, 5), lsoda_ratio=round(t_l / t_ours, 2))
    return res


def _kernel_on_case(plant) -> dict:
    """The kernel itself on the same flow step (its own physics), for information."""
    R = tests_module("sim_rhs")
    from seanv_analysis.sim import simulate_flow_step

    kw = dict(side="supply", cam_deg=CASE["cam_deg"], load_mpag=CASE["load_mpag"], plant=plant,
              pre_s=CASE["t_cmd_s"], hold_max_s=CASE["duration_s"] - CASE["t_cmd_s"], post_s=0.0)
    simulate_flow_step(plant.rig, **kw)
    wall, (_, trace) = _best(lambda: simulate_flow_step(plant.rig, **kw))
    case = R.open_loop_step(plant, eps_v_mm_s=EPS_V, quantise=False, **CASE)
    ref, _, _ = R.solve_ivp_grid(case, method="LSODA", rtol=1e-10,
                                 atol=1e-12 * R.atol_scale(case.lay))
    dx = np.abs(trace["x_true_mm"] - ref[:, case.lay["x"]])
    dq = np.abs(trace["q_true_mm3_s"] - ref[:, case.lay["v"]] * case.pp[R.PP.AREA])
    return {"wall_s_whole_call": round(wall, 5),
            "max_dx_vs_ode_reference_mm": float(dx.max()),
            "rms_dq_vs_ode_reference_mm3_s": float(np.sqrt(np.mean(dq ** 2))),
            "note": "same ROS2 step and step size as the ODE twin, different physics (Karnopp "
                    "stiction instead of tanh friction, servo quantisation), so the deviation "
                    "is model difference, not integration error"}


def _valve_cost_ns(plant) -> dict:
    """ns per call of the compiled valve functions (shared by kernel and RHS)."""
    from numba import njit

    from seanv_analysis.sim import jit as J

    @njit(cache=False)
    def thr(n, p, z, th):
        s = 0.0
        for i in range(n):
            s += J.threshold_deg(p, z, th, 3.3, 1.0 + i * 1e-7)
        return s

    @njit(cache=False)
    def flw(n, p):
        s = 0.0
        for i in range(n):
            q, g = J.side_flow_at(p, -10.0, 5.0, 1.0 + i * 1e-7, 0.01)
            s += q + g
        return s

    sup, sz, st = plant.valve_at(0)[:3]
    thr(10, sup, sz, st)
    flw(10, sup)
    n = 200_000
    t1, _ = _best(lambda: thr(n, sup, sz, st))
    t2, _ = _best(lambda: flw(n, sup))
    return {"threshold_deg_ns": round(t1 / n * 1e9, 1), "side_flow_at_ns": round(t2 / n * 1e9, 1)}


# 3. error vs time, each method swept, at equal error -------------------------------

#: the kernel's ROS2 step swept: dt = 1 ms / k (k = 1: the simulator's own step)
STEP_DIVISORS = (1, 2, 4, 8, 16, 32)
#: the general solvers' rtol swept in half decades, 1e-2 .. 1e-9 (atol = rtol x scale)
CURVE_RTOLS = [10.0 ** (-k / 2) for k in range(4, 19)]
#: a setting slower than this [s] is the last one of its method (tighter ones are slower)
CURVE_MAX_CALL_S = 3.0


def _time_call(fn, budget_s: float = 1.5, max_repeats: int = 11):
    """Best wall time of ``fn`` over repeats that fit ``budget_s`` (>= 1), and its output."""
    t0 = time.perf_counter()
    out = fn()
    best = time.perf_counter() - t0
    spent, k = best, 1
    while k < max_repeats and spent + best <= budget_s:
        t0 = time.perf_counter()
        out = fn()
        dt = time.perf_counter() - t0
        best, spent, k = min(best, dt), spent + dt, k + 1
    return best, out


def _reference(R, case) -> tuple[np.ndarray, dict]:
    """The tight reference: LSODA at rtol 1e-11 (atol 1e-13 x scale), checked
    against Radau (an implicit Runge-Kutta method, another family) at rtol
    1e-9; their difference bounds the reference's own error (``floor``;
    against Radau at 1e-10: 2e-9 mm, 1e-6 mm^3/s, three or more decades below
    the kernel's errors)."""
    scale = R.atol_scale(case.lay)
    ix, iv, area = case.lay["x"], case.lay["v"], case.pp[R.PP.AREA]
    t0 = time.perf_counter()
    ref, nfev, ok = R.solve_ivp_grid(case, method="LSODA", rtol=1e-11, atol=1e-13 * scale)
    wall = time.perf_counter() - t0
    t0 = time.perf_counter()
    chk, nfev2, ok2 = R.solve_ivp_grid(case, method="Radau", rtol=1e-9, atol=1e-11 * scale)
    wall2 = time.perf_counter() - t0
    floor_x = float(np.abs(chk[:, ix] - ref[:, ix]).max())
    floor_q = float(np.abs(chk[:, iv] - ref[:, iv]).max() * area)
    return ref, {"method": "LSODA (solve_ivp)", "rtol": 1e-11, "atol": "1e-13 x scale",
                 "success": ok, "nfev": nfev, "wall_s": round(wall, 2),
                 "check": {"method": "Radau (solve_ivp)", "rtol": 1e-9, "atol": "1e-11 x scale",
                           "success": ok2, "nfev": nfev2, "wall_s": round(wall2, 2)},
                 "floor_x_mm": floor_x, "floor_q_mm3_s": floor_q}


def _curve_methods(R, case_for_dt) -> dict:
    """name -> (settings, run(setting) -> (states, rhs calls, success), setting's label)."""
    case = case_for_dt(None)

    def ours(k):
        c = case_for_dt(case.pp[R.PP.DT] / k)
        c.run_fixed_step()                       # numba: compiled once, not per step size
        return lambda: (c.run_fixed_step(), 2 * k * (c.t_grid.size - 1), True)

    def ivp(method):
        return lambda rtol: (lambda: R.solve_ivp_grid(case, method=method, rtol=rtol))

    def ode(jac):
        return lambda rtol: (lambda: R.odeint_grid(case, rtol=rtol, with_jacobian=jac))

    return {
        "kernel_ros2": (STEP_DIVISORS, ours, "dt_s"),
        "odeint": (CURVE_RTOLS, ode(False), "rtol"),
        "odeint_compiled_jacobian": (CURVE_RTOLS, ode(True), "rtol"),
        "solve_ivp_LSODA": (CURVE_RTOLS, ivp("LSODA"), "rtol"),
        "solve_ivp_BDF": (CURVE_RTOLS, ivp("BDF"), "rtol"),
        "solve_ivp_Radau": (CURVE_RTOLS, ivp("Radau"), "rtol"),
    }


def _curves(R, case_for_dt, ref, floor: dict, methods=None) -> dict:
    """Each method's (wall time, max x error, max flow error) over its sweep."""
    case = case_for_dt(None)
    ix, iv, area = case.lay["x"], case.lay["v"], case.pp[R.PP.AREA]
    R.odeint_grid(case, rtol=1e-4, with_jacobian=True)   # compile / cache load of the Jacobian
    out = {}
    for name, (settings, make, label) in _curve_methods(R, case_for_dt).items():
        if methods is not None and name not in methods:
            continue
        rows = []
        for s in settings:
            fn = make(s)
            wall, (ys, nfev, ok) = _time_call(fn)
            ex = float(np.abs(ys[:, ix] - ref[:, ix]).max())
            eq = float(np.abs(ys[:, iv] - ref[:, iv]).max() * area)
            rows.append({label: (case.pp[R.PP.DT] / s if name == "kernel_ros2"
                                 else float(f"{s:.3g}")),
                         "success": ok, "nfev": nfev, "wall_s": wall,
                         "err_x_mm": ex, "err_q_mm3_s": eq,
                         # an error within 10x the reference's own is not resolved
                         "resolved": bool(ex > 10 * floor["floor_x_mm"]
                                          and eq > 10 * floor["floor_q_mm3_s"])})
            if wall > CURVE_MAX_CALL_S:
                break
        out[name] = rows
    return out


def _time_at_error(rows: list[dict], key: str, target: float) -> dict:
    """The time a method needs for an error of ``target`` (metric ``key``),
    on its Pareto front (the cheapest setting at least that accurate, and
    the log-log interpolation between the two front settings bracketing the
    target). None where its sweep never got that accurate."""
    pts = sorted((r[key], r["wall_s"]) for r in rows if r["success"])
    front, best = [], np.inf             # error ascending; keep the ones cheaper than all better
    for e, t in pts:
        if t < best:
            front.append((e, t))
            best = t
    # front: error ascending, time descending
    ok = [(e, t) for e, t in front if e <= target]
    if not ok:
        return {"cheapest_not_worse_s": None, "interpolated_s": None}
    e_lo, t_lo = ok[-1]                  # the loosest front point still <= target
    above = [(e, t) for e, t in front if e > target]
    interp = t_lo
    if above and e_lo > 0:
        e_hi, t_hi = above[0]
        w = (math.log(target) - math.log(e_lo)) / (math.log(e_hi) - math.log(e_lo))
        interp = math.exp(math.log(t_lo) + w * (math.log(t_hi) - math.log(t_lo)))
    return {"cheapest_not_worse_s": t_lo, "interpolated_s": interp}


def _equal_error(curves: dict) -> dict:
    """At each error the kernel's ROS2 reaches (one per step size), each
    method's time for the same error (per metric, and for both at once),
    over the kernel's time: the honest ratio."""
    out = {}
    for row in curves["kernel_ros2"]:
        at = {"dt_s": row["dt_s"], "kernel_s": row["wall_s"], "err_x_mm": row["err_x_mm"],
              "err_q_mm3_s": row["err_q_mm3_s"], "resolved": row["resolved"], "ratios": {}}
        for name, rows in curves.items():
            if name == "kernel_ros2":
                continue
            r = {}
            for metric in ("err_x_mm", "err_q_mm3_s"):
                t = _time_at_error(rows, metric, row[metric])
                r[metric] = {k: (None if v is None else round(v / row["wall_s"], 2))
                             for k, v in t.items()}
            both = [x for x in rows if x["success"] and x["err_x_mm"] <= row["err_x_mm"]
                    and x["err_q_mm3_s"] <= row["err_q_mm3_s"]]
            r["both_not_worse"] = (round(min(x["wall_s"] for x in both) / row["wall_s"], 2)
                                   if both else None)
            at["ratios"][name] = r
        out[f"dt_{row['dt_s'] * 1e3:g}ms"] = at
    return out


def _curve_png(curves: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(8.0, 3.4), dpi=100)
    for ax, key, label in ((axes[0], "err_x_mm", "max |x - x_ref| [mm]"),
                           (axes[1], "err_q_mm3_s", "max |Q - Q_ref| [mm$^3$/s]")):
        for name, rows in curves.items():
            rr = [r for r in rows if r["success"]]
            ax.loglog([r["wall_s"] for r in rr], [r[key] for r in rr],
                      "o-" if name == "kernel_ros2" else ".-", lw=2 if name == "kernel_ros2"
                      else 1, ms=4, label=name.replace("_", " "))
        ax.set_xlabel("wall time per solve [s]")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
    axes[1].legend(fontsize=6, loc="best")
    fig.suptitle("open-loop flow step (3 s): error vs time, each method's step / rtol swept",
                 fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _ode_case(dt_s: float | None):
    """The benchmark's open-loop flow step on the plant with the integration
    step ``dt_s`` (None: the rig file's, 1 ms)."""
    from seanv_analysis import load_rig
    from seanv_analysis.sim import Plant

    R = tests_module("sim_rhs")
    rig = load_rig(overrides={"sim": {"time_step_s": dt_s}}) if dt_s else load_rig()
    return R.open_loop_step(Plant.from_rig(rig), eps_v_mm_s=EPS_V, quantise=False, **CASE)


def _equal_error_section() -> dict:
    """Part 4: the reference, every method's error-vs-time curve (JSON and
    PNG in ``benchmarks/results/``), and the ratios at equal error."""
    R = tests_module("sim_rhs")
    ref, ref_info = _reference(R, _ode_case(None))
    curves = _curves(R, _ode_case, ref, ref_info)
    at = _equal_error(curves)
    png = RESULTS.with_name("sim_error_vs_time.png")
    RESULTS.parent.mkdir(exist_ok=True)
    _curve_png(curves, png)
    doc = {"case": CASE, "eps_v_mm_s": EPS_V, "reference": ref_info, "curves": curves,
           "at_kernel_errors": at, "load_average_1min": round(os.getloadavg()[0], 2)}
    RESULTS.with_name("sim_error_vs_time.json").write_text(json.dumps(doc, indent=2) + "\n")
    default = at["dt_1ms"]
    headline = {name: {"x": r["err_x_mm"]["interpolated_s"], "q": r["err_q_mm3_s"]["interpolated_s"],
                       "x_cheapest_not_worse": r["err_x_mm"]["cheapest_not_worse_s"],
                       "q_cheapest_not_worse": r["err_q_mm3_s"]["cheapest_not_worse_s"],
                       "both_not_worse": r["both_not_worse"]}
                for name, r in default["ratios"].items()}
    return {"reference": ref_info, "kernel_1ms": {k: default[k] for k in
                                                  ("kernel_s", "err_x_mm", "err_q_mm3_s")},
            "ratio_at_kernel_1ms_error": headline,
            "json": str(RESULTS.with_name("sim_error_vs_time.json").relative_to(HERE.parent)),
            "png": str(png.relative_to(HERE.parent))}


def main() -> dict:
    """Measure and write ``benchmarks/results/sim.json`` (and the error-vs-time
    curves, ``sim_error_vs_time.json`` / ``.png``); return the results."""
    from seanv_analysis import load_rig
    from seanv_analysis.sim import Plant

    t_start = time.perf_counter()
    load_before = round(os.getloadavg()[0], 2)
    cold = _cold_compile()
    rtf = _rtf()
    plant = Plant.from_rig(load_rig())
    equal = _equal_error_section()
    alt_eps = _ode_compare(plant, eps_v=EPS_V_ALT, quantise=False, radau_check=False,
                           full_scan=False)
    quant = _ode_compare(plant, eps_v=EPS_V, quantise=True, radau_check=False, full_scan=False)
    restarted = _ode_compare(plant, eps_v=EPS_V, quantise=False, radau_check=False,
                             restart_every_s=0.01, full_scan=False)
    kernel = _kernel_on_case(plant)
    eq = equal["ratio_at_kernel_1ms_error"]

    def lower(name):       # the honest claim: the smaller of the two metrics' ratios
        r = eq.get(name) or {}
        vals = [v for v in (r.get("x"), r.get("q")) if v is not None]
        return min(vals) if vals else None

    out = {
        "rtf_position_control": rtf["rtf_position_control"],
        "rtf_scenario_with_io": rtf["rtf_scenario_with_io"],
        # a real compile, in a fresh empty cache folder (a fresh install's cost)
        "aot_build_s": cold.get("aot_build", {}).get("first_call_s"),
        "aot_build_compiled": cold.get("aot_build", {}).get("compiled"),
        "jit_compile_s": cold.get("jit_compile", {}).get("first_call_s"),
        "jit_compile_compiled": cold.get("jit_compile", {}).get("compiled"),
        "aot_load_fresh_process_s": cold.get("aot_load", {}).get("first_call_s"),
        "first_call_in_process_s": rtf["first_call_in_process_s"],
        # equal error (issue 35): time each method needs for the error the kernel's
        # ROS2 step (1 ms) makes, over the kernel's time; per metric, the smaller of
        # the two is the headline
        "lsoda_ratio": lower("solve_ivp_LSODA"),
        "odeint_ratio": lower("odeint"),
        "odeint_jacobian_ratio": lower("odeint_compiled_jacobian"),
        "equal_error_ratios_at_1ms": eq,
        "our_error_mm": equal["kernel_1ms"]["err_x_mm"],
        "our_error_q_mm3_s": equal["kernel_1ms"]["err_q_mm3_s"],
        "ours_s": equal["kernel_1ms"]["kernel_s"],
        "targets": {"rtf_position_control": RTF_TARGET, "lsoda_ratio": RATIO_TARGET,
                    "odeint_jacobian_ratio": RATIO_TARGET},
        "rtf_detail": rtf,
        "cold_compile": cold,
        "equal_error": equal,
        # sensitivity rows, the earlier definition: LSODA's loosest third-decade rtol
        # whose x AND flow errors are both <= ours (not equal error: the binding
        # metric makes the other one far smaller)
        "not_worse_in_both_eps_1e-3": alt_eps,
        "not_worse_in_both_servo_quantised": quant,
        "not_worse_in_both_lsoda_restarted_100hz": restarted,
        "kernel_on_ode_case": kernel,
        "valve_function_cost": _valve_cost_ns(plant),
        "cpu_count": os.cpu_count(),
        "load_average_1min_before": load_before,
        "load_average_1min": round(os.getloadavg()[0], 2),
    }
    out["meets_targets"] = {
        "rtf_position_control": bool(out["rtf_position_control"] >= RTF_TARGET),
        "lsoda_ratio": bool((out["lsoda_ratio"] or 0.0) >= RATIO_TARGET),
        "odeint_jacobian_ratio": bool((out["odeint_jacobian_ratio"] or 0.0) >= RATIO_TARGET),
    }
    out["notes"] = (
        "Equal error: the open-loop flow step, continuous servo, friction tanh-regularised "
        f"(eps_v {EPS_V} mm/s) in every method; 'kernel_ros2' = sim_rhs.fixed_step = the "
        "simulator's own integrator (sim.rosenbrock ROS2 step, the one the kernel calls) on "
        "the same compiled plant physics the solvers call, its step swept 1 ms / k; each "
        "solver's rtol swept in half decades (atol = rtol x state scale). Errors: max over "
        "the 1 kHz grid against the tight reference. A method's time at an error is read "
        "on its Pareto front (log-log interpolation between the two settings bracketing "
        "it; 'cheapest_not_worse' is the scanned setting at least as accurate). The x and "
        "flow ratios differ because each method's x/flow error balance differs; the "
        "headline (lsoda_ratio, odeint_ratio, odeint_jacobian_ratio) is the smaller. "
        "solve_ivp's RK45 is left out: explicit on the stiff line, 48 s at rtol 1e-3. "
        "Our max errors occur at the piston's breakaway (~0.77 s): a shift of the "
        "breakaway time from the 2nd-order error of the pressure build-up before it.")
    out["bench_wall_s"] = round(time.perf_counter() - t_start, 1)
    RESULTS.parent.mkdir(exist_ok=True)
    RESULTS.write_text(json.dumps(out, indent=2) + "\n")
    return out


if __name__ == "__main__":
    print(json.dumps(main(), indent=2))
