"""Simulator speed: real-time factor of ``paper-position`` and the fixed-step
integrator against ``scipy.integrate.solve_ivp`` (LSODA) on the same
right-hand side at matched accuracy, in one run.

1. Real-time factor (RTF). ``simulate_position_control`` on the paper's
   position profile with the flow-model controller (95 s simulated, the
   whole call: kernel + DataFrames), best of ``REPEATS`` after a warm-up
   call; RTF = simulated s / wall s. Also the whole
   ``simulate_scenario('paper-position')`` (two 95 s runs, CSV files written),
   and the compile cost: the first call in this process (numba's on-disk
   cache loaded) and a cold compile in a child process with an empty
   ``NUMBA_CACHE_DIR``.

2. Ratio against LSODA. The kernel's stiction (Karnopp velocity reset) and
   servo quantisation are not an ODE, so the comparison runs on
   ``tests/sim_rhs.py`` (the ODE twin): f(t, y) of the same plant (same packed
   parameters, the same compiled plant physics
   :func:`seanv_analysis.sim.rosenbrock.plant_f` the kernel steps; friction
   ``(Fc + (Fs-Fc) exp(-(v/vs)^2)) tanh(v/eps_v) + b v``, ``eps_v = EPS_V``;
   continuous servo angle; sealing thresholds at the current pressures).
   Case: open-loop supply flow step, cam -15 -> +5 deg commanded at 0.5 s
   (through dead time, lag and rate limit), load 0.4 MPaG, piston from
   5 mm, 3 s (no controller in the loop).

   - reference: LSODA at rtol 1e-10 (atol 1e-12 x state scale), checked
     against Radau at the same tolerances;
   - ours: ``sim_rhs.fixed_step``, the SIMULATOR'S OWN
     integrator: the ROS2 (2nd-order Rosenbrock-W) step of
     :mod:`seanv_analysis.sim.rosenbrock` that the kernel calls, at the
     kernel's step ``sim.time_step_s`` (1 ms, 3000 steps), on the same
     compiled plant physics LSODA calls (thresholds per step, moved linearly
     for stage 2, as in the kernel), 1 kHz output. What differs from the
     kernel is only the model's non-ODE parts (Karnopp, quantisation), see
     ``kernel_on_ode_case``;
   - error: max |x - x_ref| [mm] and max |v A - (v A)_ref| [mm^3/s] on the
     1 kHz grid;
   - LSODA (no Jacobian given: finite differences inside LSODA) scanned
     over rtol 1e-3..1e-9 in third decades (``RTOLS``, atol = rtol x state
     scale); LSODA's error is not monotone in rtol, and the matched rtol is
     the LOOSEST whose errors are both <= ours (the cheapest matching
     setting, in LSODA's favour); timings are the best of ``REPEATS``, ours
     and LSODA timed alternately (LSODA with its 1 kHz ``t_eval``,
     restarted at the servo-target switch, a time discontinuity). Other
     processes on the machine disturb these 1-50 ms timings; the 1-minute
     load average is recorded.

   Sensitivity rows: ``EPS_V_ALT`` (tighter friction regularisation),
   with servo quantisation (the discontinuous staircase the kernel has), and
   LSODA restarted every 10 ms (what the 100 Hz controller of a closed-loop
   run forces on a solver: the servo target may change at every tick; the
   fixed-step loop pays nothing for it). The headline ``lsoda_ratio`` is the
   plain open-loop case (one restart, continuous servo, ``EPS_V``).
   For information: the kernel itself on the same flow step (its own
   physics: Karnopp, quantisation), its wall time and its deviation from
   the ODE reference, and the per-call cost of the compiled valve functions
   the kernel and the RHS share.

3. Ratio against ``scipy.integrate.odeint`` (issue 18): the same LSODA
   without ``solve_ivp``'s per-call Python layer, without and with a
   compiled finite-difference Jacobian (``sim_rhs.jacobian``), each at its
   loosest rtol matching our errors, timed alternately with ours.

Targets: ``rtf_position_control >= 1000``, ``lsoda_ratio >= 20``,
``odeint_jacobian_ratio >= 20``.
Results: ``benchmarks/results/sim.json``. Usage: ``python -m benchmarks sim``.
"""
from __future__ import annotations

import json
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

_COLD = r"""
import json, time
t0 = time.perf_counter()
from seanv_analysis import load_rig
from seanv_analysis.sim.control import FlowModelController
from seanv_analysis.sim import simulate_position_control
from seanv_analysis.sim.scenarios import paper_position_profile
t1 = time.perf_counter()
rig = load_rig(); ref, load, _ = paper_position_profile()
ctrl = FlowModelController.from_rig(rig)
simulate_position_control(rig, controller=ctrl, x_ref=ref, load=load, duration_s=0.1)
t2 = time.perf_counter()
simulate_position_control(rig, controller=ctrl, x_ref=ref, load=load, duration_s=0.1)
t3 = time.perf_counter()
print(json.dumps({"import_s": t1 - t0, "first_call_s": t2 - t1, "second_call_s": t3 - t2}))
"""


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

def _cold_compile() -> dict:
    """First call in a child process with an empty numba cache (full compile)."""
    with tempfile.TemporaryDirectory(prefix="bench-sim-numba-") as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        r = subprocess.run([sys.executable, "-c", _COLD], env=env, capture_output=True,
                           text=True, cwd=HERE.parent, timeout=300)
    if r.returncode != 0:
        return {"error": r.stderr[-500:]}
    d = json.loads(r.stdout.strip().splitlines()[-1])
    return {k: round(v, 3) for k, v in d.items()}


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


# 2. fixed step vs LSODA -----------------------------------------------------------

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
    if full_scan and restart_every_s is None:
        res["odeint"] = {name: _odeint_matched(R, case, err, ref, ours_x, ours_q, jac)
                         for name, jac in (("no_jacobian", False), ("compiled_jacobian", True))}
    return res


def _odeint_matched(R, case, err, ref, ours_x, ours_q, with_jacobian: bool) -> dict:
    """``scipy.integrate.odeint`` (the same LSODA without ``solve_ivp``'s
    Python layer), without or with the compiled finite-difference Jacobian
    (tests/sim_rhs.jacobian), at its loosest rtol matching our errors; timed
    alternately with our fixed step, best of ``REPEATS``."""
    R.odeint_grid(case, rtol=1e-4, with_jacobian=with_jacobian)  # compile / cache load
    for rtol in RTOLS:
        y, nfev, ok = R.odeint_grid(case, rtol=rtol, with_jacobian=with_jacobian)
        ex, eq = err(y, ref)
        if ok and ex <= ours_x and eq <= ours_q:
            break
    else:
        return {"rtol_matched": None}
    t_ours, t_o = _best_pair(case.run_fixed_step,
                             lambda: R.odeint_grid(case, rtol=rtol, with_jacobian=with_jacobian))
    return {"rtol_matched": float(f"{rtol:.3g}"), "nfev": nfev, "error_mm": ex,
            "error_q_mm3_s": eq, "odeint_s": round(t_o, 5), "ours_s": round(t_ours, 5),
            "ratio": round(t_o / t_ours, 2)}


def _kernel_on_case(plant, ref_case_result) -> dict:
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
            "lsoda_matched_s_over_kernel_s": (round(ref_case_result["lsoda_s"] / wall, 2)
                                              if ref_case_result.get("lsoda_s") else None),
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


def main() -> dict:
    """Measure and write ``benchmarks/results/sim.json``; return the results."""
    from seanv_analysis import load_rig
    from seanv_analysis.sim import Plant

    t_start = time.perf_counter()
    cold = _cold_compile()
    rtf = _rtf()
    plant = Plant.from_rig(load_rig())
    main_case = _ode_compare(plant, eps_v=EPS_V, quantise=False, radau_check=True)
    alt_eps = _ode_compare(plant, eps_v=EPS_V_ALT, quantise=False, radau_check=False,
                           full_scan=False)
    quant = _ode_compare(plant, eps_v=EPS_V, quantise=True, radau_check=False, full_scan=False)
    restarted = _ode_compare(plant, eps_v=EPS_V, quantise=False, radau_check=False,
                             restart_every_s=0.01, full_scan=False)
    kernel = _kernel_on_case(plant, main_case)
    out = {
        "rtf_position_control": rtf["rtf_position_control"],
        "rtf_scenario_with_io": rtf["rtf_scenario_with_io"],
        "jit_compile_s": cold.get("first_call_s"),
        "jit_cache_load_s": rtf["first_call_in_process_s"],
        "lsoda_ratio": main_case["lsoda_ratio"],
        # the stricter baselines: odeint (no solve_ivp layer), without and
        # with a compiled Jacobian, at matched accuracy
        "odeint_ratio": (main_case.get("odeint") or {}).get("no_jacobian", {}).get("ratio"),
        "odeint_jacobian_ratio": (main_case.get("odeint") or {}).get(
            "compiled_jacobian", {}).get("ratio"),
        "our_error_mm": main_case["our_error_mm"],
        "our_error_q_mm3_s": main_case["our_error_q_mm3_s"],
        "lsoda_rtol_matched": main_case["lsoda_rtol_matched"],
        "lsoda_error_mm": main_case.get("lsoda_error_mm"),
        "ours_s": main_case["ours_s"],
        "lsoda_s": main_case["lsoda_s"],
        "targets": {"rtf_position_control": RTF_TARGET, "lsoda_ratio": RATIO_TARGET,
                    "odeint_jacobian_ratio": RATIO_TARGET},
        "rtf_detail": rtf,
        "cold_compile_child": cold,
        "ode_case": {"case": CASE, **main_case},
        "ode_case_eps_1e-3": alt_eps,
        "ode_case_servo_quantised": quant,
        "ode_case_lsoda_restarted_100hz": restarted,
        "kernel_on_ode_case": kernel,
        "valve_function_cost": _valve_cost_ns(plant),
        "cpu_count": os.cpu_count(),
        "load_average_1min": round(os.getloadavg()[0], 2),
    }
    out["meets_targets"] = {
        "rtf_position_control": bool(out["rtf_position_control"] >= RTF_TARGET),
        "lsoda_ratio": bool((out["lsoda_ratio"] or 0.0) >= RATIO_TARGET),
        "odeint_jacobian_ratio": bool((out["odeint_jacobian_ratio"] or 0.0) >= RATIO_TARGET),
    }
    out["notes"] = (
        "lsoda_ratio: open-loop flow step, continuous servo, friction tanh-regularised "
        f"(eps_v {EPS_V} mm/s) in BOTH integrators; ours = sim_rhs.fixed_step = the simulator's "
        "own integrator (sim.rosenbrock ROS2 step, the one the kernel calls, at the kernel's "
        "1 ms step, 2 RHS evaluations + one tridiagonal factorisation + 2 solves per step) on "
        "the same compiled plant physics LSODA calls; the kernel adds only non-ODE parts "
        "(Karnopp stiction, servo quantisation, end stops). LSODA's matched rtol is the "
        "loosest of a third-decade scan whose errors are both <= ours (its error is not "
        "monotone in rtol). Our max errors occur at the piston's breakaway (~0.77 s), but "
        "they are mostly a shift of the breakaway time from the 2nd-order error of the "
        "pressure build-up before it (0.5-0.77 s): re-integrating only the knee-crossing "
        "steps in 2-64 sub-steps left them at ~1e-3 mm / 50-80 mm^3/s, halving the step "
        "everywhere gives 6e-4 mm / 17 mm^3/s at twice the cost.")
    out["bench_wall_s"] = round(time.perf_counter() - t_start, 1)
    RESULTS.parent.mkdir(exist_ok=True)
    RESULTS.write_text(json.dumps(out, indent=2) + "\n")
    return out


if __name__ == "__main__":
    print(json.dumps(main(), indent=2))
