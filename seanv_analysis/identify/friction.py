"""Actuator friction from the force balance of the flow steps' steady motion.

While the piston moves at a steady speed v = Q / A the head pressure holds
the load and the seal friction (inertia is nil):

    p_head A - p_load A_load = F_c sign(v) + b v           [N]

(A: water-actuator piston area, A_load: pneumatic load piston area, both
from the rig file; p_head from the run's steady window: p1 - dp on the
supply side, p1 on the drain side). The head pressure is measured at the
valve end of the line (as on the paper's rig and in the simulator), so the
line's laminar resistance R adds R A^2 v to the measured force: R comes
from the line's published length and bore (rig ``tube``, ``fluid``) and is
taken off the slope before it is called seal friction. Supply runs extend (v > 0), drain runs
retract (v < 0), so F_c is the jump between them and b the slope:
a robust linear fit (``soft_l1``) with 95 % intervals from its Jacobian.

A rig whose seals lose force with speed over the steps' speeds (a Stribeck
law, F = sign(v) [F_c + (F_s - F_c) exp(-(v/v_s)^2)] + b v, the simulator's
own) biases F_c + b v: the slow steps carry part of the breakaway force. With
the breakaway force F_s read from the position runs, the Stribeck velocity
v_s is fitted with F_c and b (:func:`fit_stribeck`) and kept only when the
training steps tell it (F-test, p < 0.01), it lowers the held-out steps'
error, and it lies inside the speeds the steps span (0.1 x the slowest to
the fastest: outside that the term is a constant or nil there); otherwise
the rig file's v_s is kept and said so. Measured on a rig with v_s = 4 mm/s
(steady speeds 3-33 mm/s): F_c 92.8 [91.1, 94.5] N -> 84.7 N for a true 85,
b 0.82 -> 1.21 N s/mm for 1.2, force RMSE 3.7 -> 1.3 N.

The breakaway force is read where the piston starts to move after it was
held (:func:`breakaway_events`): while it is held no flow passes the line,
so p_head A - p_load A_load is the force on it, and it moves when that force
reaches the breakaway force. Without such events the rig file's
breakaway/Coulomb ratio is kept (and said so). The moving mass is not
identified: at the accelerations of these runs its force is far below the
friction (the report gives the ratio).
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np
from scipy import stats
from scipy.optimize import least_squares

from ..sim.plant import tube_constants
from .result import Constant

__all__ = ["friction_constants", "fit_friction", "fit_stribeck", "breakaway_events"]

#: a hold: the position stays within this many encoder steps for at least _HOLD_S
_HOLD_STEPS = 2
_HOLD_S = 0.15
#: the force at breakaway: median over this window before the first move [s]
_FORCE_WINDOW_S = 0.01
#: the force's rate of rise before a start: a line over this window [s]
_RATE_WINDOW_S = 0.02


def fit_friction(v_mm_s, f_net_n) -> dict[str, Any]:
    """(F_c [N], b [N s/mm]) of F = F_c sign(v) + b v, robust, with 95 % intervals."""
    v, f = np.asarray(v_mm_s, float), np.asarray(f_net_n, float)
    s = np.sign(v)
    A = np.column_stack([s, v])
    x0, *_ = np.linalg.lstsq(A, f, rcond=None)
    r0 = f - A @ x0
    scale = max(1.4826 * float(np.median(np.abs(r0 - np.median(r0)))), 1e-3)

    def fun(x):
        return (A @ x - f) / scale

    sol = least_squares(fun, x0, loss="soft_l1", f_scale=2.0)
    dof = max(v.size - 2, 1)
    s2 = float(np.sum(sol.fun ** 2)) / dof
    half = _half_widths_95(sol.jac, s2)
    return {"coulomb_n": float(sol.x[0]), "viscous_n_s_per_mm": float(sol.x[1]),
            "coulomb_ci95": (float(sol.x[0] - half[0]), float(sol.x[0] + half[0])),
            "viscous_ci95": (float(sol.x[1] - half[1]), float(sol.x[1] + half[1])),
            "rmse_n": float(np.sqrt(np.mean((A @ sol.x - f) ** 2)))}


def _half_widths_95(jac: np.ndarray, s2: float) -> np.ndarray:
    """Half-widths of the 95 % intervals of a least-squares fit's parameters
    from its Jacobian ``jac`` (residuals in their own units) and residual
    variance ``s2``; NaN when J^T J is singular."""
    try:
        return 1.96 * np.sqrt(np.maximum(np.diag(np.linalg.inv(jac.T @ jac) * s2), 0.0))
    except np.linalg.LinAlgError:
        return np.full(jac.shape[1], math.nan)


def _exp(x: float) -> float:
    """exp(x) of a log-parameter or its interval's end: inf beyond the float
    range (a v_s the data do not constrain has a Jacobian column near 0, so
    a half-width of 1e3 and more in log v_s)."""
    return math.exp(x) if not x >= 709.0 else math.inf


def fit_stribeck(v_mm_s, f_net_n, static_n: float, start: tuple[float, float, float]
                 ) -> dict[str, Any]:
    """(F_c [N], b [N s/mm], v_s [mm/s]) of F = sign(v) [F_c + (F_s - F_c)
    exp(-(v/v_s)^2)] + b v with the breakaway force F_s = ``static_n`` [N]
    held; robust (``soft_l1``), v_s as its log; 95 % intervals from the
    Jacobian. ``start``: (F_c, b, v_s)."""
    v, f = np.asarray(v_mm_s, float), np.asarray(f_net_n, float)
    s = np.sign(v)

    def model(x):
        fc, b, vs = x[0], x[1], math.exp(x[2])
        return s * (fc + (static_n - fc) * np.exp(-(v / vs) ** 2)) + b * v

    r0 = f - model(np.array([start[0], start[1], math.log(start[2])]))
    scale = max(1.4826 * float(np.median(np.abs(r0 - np.median(r0)))), 1e-3)
    sol = least_squares(lambda x: (model(x) - f) / scale,
                        [start[0], start[1], math.log(max(start[2], 1e-3))],
                        loss="soft_l1", f_scale=2.0)
    res = model(sol.x) - f
    s2 = float(np.sum(res ** 2)) / max(v.size - 3, 1)
    jac = sol.jac * scale
    half = _half_widths_95(jac, s2)
    vs = _exp(sol.x[2])
    return {"coulomb_n": float(sol.x[0]), "viscous_n_s_per_mm": float(sol.x[1]),
            "stribeck_velocity_mm_s": vs,
            "coulomb_ci95": (float(sol.x[0] - half[0]), float(sol.x[0] + half[0])),
            "viscous_ci95": (float(sol.x[1] - half[1]), float(sol.x[1] + half[1])),
            "stribeck_ci95": (vs * _exp(-half[2]), vs * _exp(half[2])),
            "rss_n2": float(np.sum(res ** 2)), "rmse_n": float(np.sqrt(np.mean(res ** 2))),
            "predict": lambda vv: (np.sign(vv) * (sol.x[0] + (static_n - sol.x[0])
                                                  * np.exp(-(np.asarray(vv) / vs) ** 2))
                                   + sol.x[1] * np.asarray(vv))}


def _stribeck_choice(v, f, pick, static_n: float, linear: dict, start_vs: float,
                     static_ci95: tuple[float, float] = (math.nan, math.nan)
                     ) -> tuple[dict | None, str]:
    """The Stribeck fit on the training rows (``~pick``) when the data tell
    v_s (module docstring: F-test p < 0.01 against F_c + b v, lower held-out
    RMSE, v_s inside 0.1 x the slowest .. the fastest speed), else None; and
    a one-line reason either way. The slow steps fix the Stribeck term
    (F_s - F_c) exp(-(v/v_s)^2), in which F_s and v_s trade off: the
    intervals also span the refits with F_s at the ends of ``static_ci95``
    (on our simulator the breakaway read 169 N for 160 and v_s 0.88
    [0.855, 0.906] mm/s for 1.0 without this)."""
    vt, ft = v[~pick], f[~pick]
    speeds = np.abs(vt)
    if vt.size < 8 or not static_n > linear["coulomb_n"]:
        return None, "too few steps, or no breakaway force above the Coulomb friction"
    best = None
    for vs0 in (start_vs, 0.3 * float(np.median(speeds)), float(np.median(speeds))):
        try:
            fit = fit_stribeck(vt, ft, static_n, (linear["coulomb_n"],
                                                   linear["viscous_n_s_per_mm"], vs0))
        except (ValueError, FloatingPointError, np.linalg.LinAlgError):
            continue
        if not math.isfinite(fit["rss_n2"]):
            continue
        if best is None or fit["rss_n2"] < best["rss_n2"]:
            best = fit
    if best is None:
        return None, "the Stribeck fit did not converge"
    rss0 = float(np.sum((linear["coulomb_n"] * np.sign(vt) + linear["viscous_n_s_per_mm"] * vt
                         - ft) ** 2))
    dof = vt.size - 3
    p = float(stats.f.sf((rss0 - best["rss_n2"]) / max(best["rss_n2"] / dof, 1e-12), 1, dof))
    held0 = _force_rmse(v[pick], f[pick], linear["coulomb_n"], linear["viscous_n_s_per_mm"])
    held1 = (float(np.sqrt(np.mean((best["predict"](v[pick]) - f[pick]) ** 2)))
             if pick.any() else math.nan)
    vs, lo_v, hi_v = best["stribeck_velocity_mm_s"], 0.1 * float(speeds.min()), float(speeds.max())
    what = (f"v_s {vs:.3g} mm/s: training p {p:.2g}, held-out force RMSE {held0:.3g} -> "
            f"{held1:.3g} N")
    if p < 0.01 and held1 < held0 and lo_v <= vs <= hi_v and all(
            math.isfinite(x) for x in best["stribeck_ci95"]):
        best["vs_bounded"] = True
        for end in static_ci95:
            if not math.isfinite(end):
                continue
            if end <= best["coulomb_n"]:
                # F_s may be as low as F_c: the Stribeck term may vanish (v_s
                # unbounded), and the law tends to F_c + b v
                best["vs_bounded"] = False
                alt = {**linear, "stribeck_velocity_mm_s": vs}
            else:
                try:
                    alt = fit_stribeck(vt, ft, end, (best["coulomb_n"],
                                                     best["viscous_n_s_per_mm"], vs))
                except (ValueError, FloatingPointError, np.linalg.LinAlgError):
                    alt = {}
                if not all(math.isfinite(alt.get(k, math.nan)) for k in
                           ("coulomb_n", "viscous_n_s_per_mm", "stribeck_velocity_mm_s")):
                    best["vs_bounded"] = False      # the edge cannot be fitted: not bounded
                    continue
            for key, ci in (("coulomb_n", "coulomb_ci95"), ("viscous_n_s_per_mm", "viscous_ci95"),
                            ("stribeck_velocity_mm_s", "stribeck_ci95")):
                # the refit's own interval where it has one: the union over
                # F_s's interval, not only the refits' values (F_c + b v's
                # interval covered our simulator's F_c where its value and the
                # Stribeck fits' intervals, 0.01 N wide, missed by 0.002 N)
                lo_a, hi_a = alt.get(ci, (math.nan, math.nan))
                if not (math.isfinite(lo_a) and math.isfinite(hi_a)):
                    lo_a = hi_a = alt[key]
                best[ci] = (min(best[ci][0], lo_a), max(best[ci][1], hi_a))
        return best, what
    return None, what + f" (kept when p < 0.01, the held-out RMSE drops and {lo_v:.2g} <= v_s <= {hi_v:.2g} mm/s)"


def breakaway_events(run, rig, *, window_s: float = _FORCE_WINDOW_S,
                     with_rate: bool = False) -> list:
    """|p_head A - p_load A_load| [N] at each start from a hold (the position
    held within 2 encoder steps for >= 0.15 s, then leaving by > 3 steps),
    the median over the ``window_s`` before the start (0: the samples at the
    last held instant). With ``with_rate``: (force [N], its rate of rise
    [N/s] over the :data:`_RATE_WINDOW_S` before the start (a line through
    |force|), the held position [mm]) per start."""
    starts = _hold_starts(run, rig)
    return [] if starts is None else _events(*starts, window_s=window_s, with_rate=with_rate)


def _hold_starts(run, rig) -> tuple[np.ndarray, np.ndarray, list] | None:
    """(t [s], force [N], [(index of the last held sample, held position
    [mm])]) of the run's starts from a hold (:func:`breakaway_events`);
    None without a position, the pressures, an encoder step or 100 samples."""
    from ..errors import DataError
    from ..signals.align import align_run

    try:
        d = align_run(run)
    except DataError:
        return None
    if not {"position_mm", "p_head_mpag", "p_load_mpag"} <= set(d.columns):
        return None
    t = d["t_s"].to_numpy(float)
    x = d["position_mm"].to_numpy(float)
    f = (d["p_head_mpag"].to_numpy(float) * rig.piston_area_mm2
         - d["p_load_mpag"].to_numpy(float) * rig.load_area_mm2)
    steps = np.diff(np.unique(np.round(x[np.isfinite(x)], 6)))
    res = float(np.min(steps[steps > 0])) if np.any(steps > 0) else 0.0
    if res <= 0 or t.size < 100:
        return None
    starts = []
    i, n = 0, t.size
    t_arr, (t, x) = t, (t.tolist(), x.tolist())    # the sample loop on floats: ~3x faster
    while i < n - 1:
        # grow a hold from i while the position stays within the band
        j = i
        lo = hi = x[i]
        while j + 1 < n and max(hi, x[j + 1]) - min(lo, x[j + 1]) <= _HOLD_STEPS * res + 1e-12:
            j += 1
            lo, hi = min(lo, x[j]), max(hi, x[j])
        if t[j] - t[i] >= _HOLD_S:
            ref = 0.5 * (lo + hi)
            k = j + 1
            while k < n and abs(x[k] - ref) <= 3 * res and t[k] - t[j] < 0.05:
                k += 1
            if k < n and abs(x[k] - ref) > 3 * res:
                starts.append((j, ref))
        i = j + 1
    return t_arr, f, starts


def _events(t: np.ndarray, f: np.ndarray, starts: list, *, window_s: float,
            with_rate: bool) -> list:
    """:func:`breakaway_events`' values at the ``starts`` of :func:`_hold_starts`."""
    out = []
    for j, ref in starts:
        w = (t >= t[j] - window_s - 1e-9) & (t <= t[j])
        fw = f[w]
        fw = fw[np.isfinite(fw)]
        if fw.size and not with_rate:
            out.append(float(abs(np.median(fw))))
        elif fw.size:
            wr = (t >= t[j] - _RATE_WINDOW_S - 1e-9) & (t <= t[j]) & np.isfinite(f)
            rate = float(np.polyfit(t[wr], np.abs(f[wr]), 1)[0]) if wr.sum() > 3 else 0.0
            out.append((float(abs(np.median(fw))), rate, float(ref)))
    return out


def _breakaway(runs, rig, coulomb: float) -> dict[str, Any] | None:
    """Breakaway force from the starts after a hold: the force is still
    rising when the start is detected, so the breakaway lies between its
    median over the 10 ms before the start and its value at the last held
    instant. The estimate is the median of the two's midpoint per event; the
    95 % interval spans both estimators' bootstrap intervals (the method's
    systematic part: on 8 foreign-rig seeds one of the two alone missed
    the truth in 1 and 2 seeds, their span in none), and reaches down by
    the valve-side pressure's lead (:func:`_line_lead_n`)."""
    win, end, lead = [], [], []
    for r in runs:
        starts = _hold_starts(r, rig)       # one scan of the run for both estimators
        if starts is None:
            continue
        a = _events(*starts, window_s=_FORCE_WINDOW_S, with_rate=False)
        b = _events(*starts, window_s=0.0, with_rate=True)
        if len(a) == len(b):
            win += a
            end += [e[0] for e in b]
            lead += [_line_lead_n(rig, rate, x) for _, rate, x in b]
    win, end, lead = np.asarray(win), np.asarray(end), np.asarray(lead)
    keep = (win >= 0.5 * coulomb) & (end >= 0.5 * coulomb)
    win, end, lead = win[keep], end[keep], lead[keep]
    if win.size < 3:
        return None
    mid = 0.5 * (win + end)
    rng = np.random.default_rng(0)
    picks = rng.integers(0, win.size, (400, win.size))
    lo, hi = math.inf, -math.inf
    for f in (win, end):
        boot = np.median(f[picks], axis=1)
        lo, hi = min(lo, float(np.percentile(boot, 2.5))), max(hi, float(np.percentile(boot, 97.5)))
    down = float(np.median(lead))
    return {"static_n": float(np.median(mid)), "ci95": (lo - down, hi), "n_events": int(win.size),
            "lead_n": down}


def _line_lead_n(rig, rate_n_s: float, x_mm: float) -> float:
    """How far the force read at the valve leads the piston's [N] while it
    rises at ``rate_n_s`` [N/s] with the piston held at ``x_mm``: the head
    pressure is logged at the valve end of the line, which fills the tube
    and the head chamber through its resistance, so the piston's pressure
    lags by about R (C_tube / 2 + C_chamber) (the rig file's tube and bulk
    modulus: identify fits B later, from the twin that needs this friction).
    On our simulator (20 m, 150 MPa: 8 ms) the force read at the true start
    was 158-190 N for 160, +6-16 ms x its rate of rise (300-2500 N/s); a
    ringing line (its water column) makes the lead vary from start to
    start, so it widens the interval (downwards) rather than correcting
    the estimate."""
    tc = tube_constants(rig)
    bulk = float(rig["tube"]["effective_bulk_modulus_mpa"])
    chamber = (float(rig["actuator"]["dead_volume_mm3"])
               + rig.piston_area_mm2 * max(float(x_mm), 0.0)) / bulk
    tau = tc["R"] * (0.5 * tc["C"] + chamber)
    return max(float(rate_n_s), 0.0) * tau


def _steady_rows(df):
    """The rows whose piston moved at a steady speed (summary column
    ``motion_steady``), and how many were left out. Stick-slip and
    unsettled motion (slow steps on a rig with stiction) carry a mean force
    between the Coulomb and the breakaway force, which would bias F_c
    upwards; when fewer than 3 steady rows remain in a direction (or the
    column is absent) every row is kept."""
    if "motion_steady" not in df:
        return df, 0
    ok = df["motion_steady"].fillna(False).astype(bool).to_numpy()
    v = df["q_mm3_s"].to_numpy(float)
    if np.sum(ok & (v > 0)) < 3 or np.sum(ok & (v < 0)) < 3:
        return df, 0
    return df[ok], int(np.sum(~ok & (v != 0)))


def _force_rmse(v, f, coulomb, viscous) -> float:
    if not np.size(v):
        return math.nan
    return float(np.sqrt(np.mean((coulomb * np.sign(v) + viscous * v - f) ** 2)))


def friction_constants(summary, rig, runs=()) -> tuple[list[Constant], dict[str, Any], list[str]]:
    """Coulomb and viscous friction from the flow-step rows of the data-set
    summary that passed the filters, and the breakaway force from the starts
    after a hold in ``runs`` (position-control runs)."""
    act = rig["actuator"]
    d_c, d_b = float(act["coulomb_friction_n"]), float(act["viscous_friction_n_s_per_mm"])
    d_s = float(act["static_friction_n"])
    keys = (("actuator.coulomb_friction_n", "Coulomb friction", d_c, "N"),
            ("actuator.viscous_friction_n_s_per_mm", "viscous friction", d_b, "N s/mm"),
            ("actuator.static_friction_n", "breakaway friction", d_s, "N"))
    df = summary[(summary["kind"] == "flow_step") & (summary["excluded"].fillna("") == "")]
    df = df[np.isfinite(df["q_mm3_s"]) & np.isfinite(df["p1_mpa"]) & np.isfinite(df["dp_mpa"])
            & np.isfinite(df["load_mpag"].astype(float))].sort_values("run_index")
    df, unsteady = _steady_rows(df)
    area, load_area = float(rig.piston_area_mm2), float(rig.load_area_mm2)
    sup = (df["side"] == "supply").to_numpy()
    p1, dp = df["p1_mpa"].to_numpy(float), df["dp_mpa"].to_numpy(float)
    p_head = np.where(sup, p1 - dp, p1)
    f_net = p_head * area - df["load_mpag"].to_numpy(float) * load_area
    v = df["q_mm3_s"].to_numpy(float) / area
    line_r = float(tube_constants(rig)["R"]) * area ** 2      # N s/mm of the line's resistance
    f_net = f_net - line_r * v
    n_up, n_down = int(np.sum(v > 0)), int(np.sum(v < 0))
    if n_up < 3 or n_down < 3:
        why = (f"steady motion in both directions is needed ({n_up} extending, {n_down} "
               "retracting flow steps)")
        return ([Constant(k, n, d, d, u, False, "flow-step force balance", note=why)
                 for k, n, d, u in keys], {}, [f"friction: {why}"])
    pick = np.arange(v.size) % 3 == 2
    fr = fit_friction(v[~pick], f_net[~pick])
    by = (f"force balance of {int((~pick).sum())} training flow steps (speeds "
          f"{np.min(v):.2g}..{np.max(v):.2g} mm/s)")
    coulomb, viscous = fr["coulomb_n"], fr["viscous_n_s_per_mm"]
    notes = [f"friction: the line's laminar resistance ({line_r:.3g} N s/mm at the piston) is "
             "taken off the measured force before fitting"]
    if unsteady:
        notes.append(f"friction: {unsteady} flow step(s) whose piston did not move at a steady "
                     "speed (stick-slip, or still settling) are left out: their mean force is "
                     "not F_c + b v")
    d_v = float(act["stribeck_velocity_mm_s"])
    brk = _breakaway(runs, rig, coulomb if coulomb > 0 else d_c)
    strib, strib_why = (None, "no breakaway force read from position-control runs")
    if brk is not None:
        strib, strib_why = _stribeck_choice(v, f_net, pick, brk["static_n"], fr, d_v,
                                            tuple(brk["ci95"]))
    if strib is not None:
        fr = {**fr, **{k: strib[k] for k in ("coulomb_n", "viscous_n_s_per_mm", "coulomb_ci95",
                                              "viscous_ci95", "rmse_n")}}
        coulomb, viscous = fr["coulomb_n"], fr["viscous_n_s_per_mm"]
        notes.append(f"friction: a Stribeck law fitted with the breakaway force "
                     f"{brk['static_n']:.4g} N held ({strib_why}): F_c + b v alone is biased "
                     "by the slow steps")
    ok_c = coulomb > 0 and math.isfinite(fr["coulomb_ci95"][0])
    ok_b = math.isfinite(fr["viscous_ci95"][0]) and np.ptp(np.abs(v)) > 0.5
    if viscous < 0:
        ok_b, why_b = False, f"fitted slope {viscous:.3g} N s/mm is negative"
    else:
        why_b = "" if ok_b else "the speeds do not spread enough"
    ratio = d_s / d_c if d_c > 0 else 1.0
    lo_b, hi_b = fr["viscous_ci95"]
    split = (f"not separable from the line's resistance (the head pressure is logged at the "
             f"valve): the force balance gives their sum b + R A^2 = {viscous + line_r:.3g} "
             f"[{lo_b + line_r:.3g}, {hi_b + line_r:.3g}] N s/mm; the line's part is fixed at "
             f"the rig file's tube ({line_r:.3g} N s/mm), the rest is called viscous")
    consts = [
        Constant(keys[0][0], keys[0][1], coulomb if ok_c else d_c, d_c, "N", ok_c, by,
                 fr["coulomb_ci95"] if ok_c else (math.nan, math.nan),
                 note="" if ok_c else f"fitted {coulomb:.3g} N is not a friction force"),
        Constant(keys[1][0], keys[1][1], viscous if ok_b else d_b, d_b, "N s/mm", ok_b, by,
                 fr["viscous_ci95"] if ok_b else (math.nan, math.nan),
                 note=split if ok_b else why_b,
                 confounded_with=("tube.length_m", "tube.inner_diameter_mm") if ok_b else ()),
    ]
    if ok_b:
        # the number the data do fix: the slope of the force balance
        consts.append(Constant(None, "friction + line slope b + R A^2", viscous + line_r,
                               d_b + line_r, "N s/mm", True, by,
                               (lo_b + line_r, hi_b + line_r),
                               note="what steady motion measures; identifiable as a sum only"))
    if strib is not None and strib["vs_bounded"]:
        consts.append(Constant("actuator.stribeck_velocity_mm_s", "Stribeck velocity",
                               strib["stribeck_velocity_mm_s"], d_v, "mm/s", True,
                               by + " and the breakaway force", strib["stribeck_ci95"],
                               note=strib_why))
    else:
        if strib is not None:
            strib_why = (f"{strib_why}, but the breakaway force's interval reaches the Coulomb "
                         "force: F_s - F_c and v_s trade off and v_s has no upper bound (F_c "
                         "and b from the Stribeck fit, their intervals reaching F_c + b v's)")
        consts.append(Constant("actuator.stribeck_velocity_mm_s", "Stribeck velocity", d_v, d_v,
                               "mm/s", False, "flow-step force balance",
                               note=f"the rig file's is kept: {strib_why}"))
    if brk is not None and brk["static_n"] >= (coulomb if ok_c else 0.0):
        consts.append(Constant(keys[2][0], keys[2][1], brk["static_n"], d_s, "N", True,
                               f"force at {brk['n_events']} starts after a hold (position-control "
                               "runs)", brk["ci95"],
                               note=(f"read at the valve, which leads the piston while the force "
                                     f"rises: the interval reaches {brk['lead_n']:.2g} N lower "
                                     "(the line's R (C_tube/2 + C_chamber) x the median rate of "
                                     "rise)") if brk["lead_n"] > 0 else ""))
    elif ok_c:
        lo, hi = fr["coulomb_ci95"]
        consts.append(Constant(keys[2][0], keys[2][1], coulomb * ratio, d_s, "N", True,
                               "Coulomb friction x the rig file's breakaway/Coulomb ratio "
                               f"{ratio:.3g}", (lo * ratio, hi * ratio),
                               note="steady motion does not show the breakaway force"))
    else:
        consts.append(Constant(*keys[2][:2], d_s, d_s, "N", False, "flow-step force balance",
                               note="needs the Coulomb friction"))
    fits = {"metric": "force-balance RMSE [N]",
            "train_default": _force_rmse(v[~pick], f_net[~pick], d_c, d_b),
            "train": fr["rmse_n"],
            "heldout_default": _force_rmse(v[pick], f_net[pick], d_c, d_b),
            "heldout": (float(np.sqrt(np.mean((strib["predict"](v[pick]) - f_net[pick]) ** 2)))
                        if strib is not None and pick.any()
                        else _force_rmse(v[pick], f_net[pick], consts[0].value, consts[1].value)),
            "n_train_runs": int((~pick).sum()), "n_heldout_runs": int(pick.sum())}
    return consts, fits, notes
