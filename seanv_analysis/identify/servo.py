"""Servo dead time, time constant and rate limit from the servo logs.

The servo log holds the command sent (``cam_cmd_deg``) and the measured cam
angle (``cam_deg``). The simulator's servo (:func:`seanv_analysis.sim.servo.
servo_response`: dead time, then a rate-limited first-order lag, solved
exactly) is run on the logged command and fitted to the logged angle by
simulation error (``scipy.optimize.least_squares``, bounded, residuals in
units of the servo's resolution):

- a start for the dead time from a 5 ms grid (with the rig file's lag and
  rate), then dead time, time constant and rate limit together (time
  constant and rate as logs; the dead time's finite-difference step is 2 ms
  since the cost is a step function below the integration step);
- 95 % intervals (the residual variance scaled by the residuals'
  integrated autocorrelation time: they are correlated in time): the dead
  time's where the cost (the others held) rises by
  the chi-square(1) quantile, widened by the command-timing uncertainty
  (half a servo-log sample, below); the others from the Jacobian with the
  dead time held, widened to their refits with the dead time at its
  interval's ends. The rate limit
  is identified only when the data drive the servo into it; otherwise it
  keeps the rig file's value.

Command timing: when the controller log shares the servo log's instants,
each command is taken as sent at its logged instant; when the servo log
samples the command on its own clock, a change is taken at the middle of
the sample interval before it was logged (unbiased for a clock unrelated to
the controller's). A log stamp records the command in force at that
instant, so a command may have been sent up to one sample before it: with
the synchronous rule that phase is one for the whole rig (the logs cannot
tell it from a longer dead time), so the dead time's interval reaches one
servo-log sample above the delay from the logged commands (the value
reported, and what the twin replays). Measured on a rig whose logs stamp a
command after it was sent: delay 0.0355 s from the stamps, 0.045 s true.

Runs are split in time order: fit on the training ones, the headline error
on the held-out ones.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
from scipy import stats
from scipy.optimize import least_squares

from ..sim.servo import servo_response
from .noise import integrated_autocorrelation
from .result import Constant

__all__ = ["ServoData", "servo_data", "command_schedule", "fit_servo", "servo_constants"]

#: dead-time profile grid [s]: coarse, then fine around the best node
_DEAD_MAX_S = 0.5
_COARSE_S = 0.005
_FINE_S = 0.001


@dataclass(frozen=True)
class ServoData:
    """One run's servo log, ready for the fit: command instants (timing
    corrected) and values [s, deg], feedback instants and angles [s, deg]."""

    run_id: str
    t_cmd: np.ndarray
    cmd: np.ndarray
    t_fb: np.ndarray
    fb: np.ndarray
    timing: str
    #: half-width [s] of the command-instant error (half a servo-log sample)
    timing_u_s: float = 0.0
    #: how long before its log stamp a command may have been sent, one phase
    #: for the whole rig [s] (one servo-log sample, synchronous rule; 0 else)
    stamp_lead_s: float = 0.0


def command_schedule(run) -> tuple[np.ndarray, np.ndarray, str, float, float] | None:
    """The cam command as the servo received it: (instants of its changes
    [s], values [deg], timing rule, half-width of the instants' error [s],
    how long before its stamp a command may have been sent, one phase for
    the rig [s]),
    from the servo log's ``cam_cmd_deg`` (see the module's "Command timing");
    None without a servo log of at least 20 commands."""
    sv = run.tables.get("servo")
    if sv is None or "cam_cmd_deg" not in sv or len(sv) < 20:
        return None
    t = sv["t_s"].to_numpy(float)
    cmd = sv["cam_cmd_deg"].to_numpy(float)
    ok = np.isfinite(cmd) & np.isfinite(t)
    t, cmd = t[ok], cmd[ok]
    if t.size < 20:
        return None
    dt = float(np.median(np.diff(t)))
    shift, timing, lead = dt / 2.0, "asynchronous: change taken mid-interval before its log instant", 0.0
    ctrl = run.tables.get("controller")
    if ctrl is not None and len(ctrl) > 10:
        tc = ctrl["t_s"].to_numpy(float)
        j = np.clip(np.searchsorted(tc, t), 1, tc.size - 1)
        near = np.minimum(np.abs(tc[j] - t), np.abs(tc[j - 1] - t))
        if float(np.median(near)) < 0.1 * dt:
            shift, timing, lead = 0.0, "synchronous with the controller log", dt
    # a command sample only matters where the command changes
    change = np.concatenate(([True], np.diff(cmd) != 0.0))
    t_cmd = t[change].copy()
    t_cmd[1:] -= shift
    # either way the instant a command was sent is known to half a servo
    # sample only (a controller log may itself be stamped late)
    return t_cmd, cmd[change], timing, dt / 2.0, lead


def servo_data(run) -> ServoData | None:
    """:class:`ServoData` of a run, or None when its servo log has no usable
    feedback (empty ``cam_deg``) or the command never moves."""
    sv = run.tables.get("servo")
    if sv is None or "cam_deg" not in sv or len(sv) < 20:
        return None
    sched = command_schedule(run)
    if sched is None:
        return None
    t_cmd, cmd, timing, half, lead = sched
    t = sv["t_s"].to_numpy(float)
    fb = sv["cam_deg"].to_numpy(float)
    ok = np.isfinite(sv["cam_cmd_deg"].to_numpy(float)) & np.isfinite(t)
    t, fb = t[ok], fb[ok]
    good = np.isfinite(fb)
    if good.sum() < 20 or np.ptp(cmd) < 0.5:
        return None
    return ServoData(run.run_id, t_cmd, cmd, t[good], fb[good], timing, half, lead)


def _residual(data: Sequence[ServoData], dead, tau, rate, scale):
    out = []
    for d in data:
        y = servo_response(d.t_cmd, d.cmd, d.t_fb, dead_time_s=dead, time_constant_s=tau,
                           max_rate_deg_s=rate, theta0_deg=float(d.fb[0]))
        out.append((y - d.fb) / scale)
    return np.concatenate(out)


def _fit_all(data, x0, scale, fit_rate: bool, rate_fixed: float):
    """(dead, tau[, rate]) least squares; tau and rate as logs. The cost is a
    step function of the dead time below the integration step, so its
    finite-difference step is 2 ms."""
    def unpack(p):
        return p[0], math.exp(p[1]), (math.exp(p[2]) if fit_rate else rate_fixed)

    def fun(p):
        return _residual(data, *unpack(p), scale)

    p0 = [x0[0], math.log(x0[1])] + ([math.log(x0[2])] if fit_rate else [])
    lo = [0.0, math.log(1e-3)] + ([math.log(5.0)] if fit_rate else [])
    hi = [_DEAD_MAX_S, math.log(2.0)] + ([math.log(1e4)] if fit_rate else [])
    p0 = np.clip(p0, np.add(lo, 1e-9), np.subtract(hi, 1e-9))
    sol = least_squares(fun, p0, bounds=(lo, hi), diff_step=2e-3, max_nfev=80)
    return unpack(sol.x), sol


def _fit_dead_fixed(data, dead, x0, scale, fit_rate: bool, rate_fixed: float):
    """(dead, tau, rate) with the dead time held at ``dead``."""
    def unpack(p):
        return dead, math.exp(p[0]), (math.exp(p[1]) if fit_rate else rate_fixed)

    def fun(p):
        return _residual(data, *unpack(p), scale)

    p0 = [math.log(x0[0])] + ([math.log(x0[1])] if fit_rate else [])
    lo = [math.log(1e-3)] + ([math.log(5.0)] if fit_rate else [])
    hi = [math.log(2.0)] + ([math.log(1e4)] if fit_rate else [])
    p0 = np.clip(p0, np.add(lo, 1e-9), np.subtract(hi, 1e-9))
    sol = least_squares(fun, p0, bounds=(lo, hi), diff_step=2e-3, max_nfev=40)
    return unpack(sol.x), sol


def _dead_profile(data, dead, x0, scale, fit_rate: bool, rate_fixed: float, *,
                  step: float = 0.002, half: float = 0.024, grow: int = 3):
    """Profile of the cost over the dead time, the time constant and rate
    refitted at each node (warm-started outward from ``dead``).

    Returns (nodes [s], 2 x cost, tau [s], rate [deg/s]) sorted by node; the
    grid grows by ``half`` on a side whose edge is still near the minimum
    (within 2x its cost), at most ``grow`` times.
    """
    done: dict[float, tuple[float, float, float]] = {}

    def walk(ds, warm):
        for d in ds:
            d = round(float(d), 6)
            if d in done or not 0.0 <= d <= _DEAD_MAX_S:
                continue
            (_, t_e, r_e), sol = _fit_dead_fixed(data, d, warm, scale, fit_rate, rate_fixed)
            done[d] = (2.0 * float(sol.cost), t_e, r_e)
            warm = (t_e, r_e)

    lo, hi = dead - half, dead + half
    walk(np.arange(dead, hi + 1e-12, step), x0)
    walk(np.arange(dead, lo - 1e-12, -step), x0)
    for _ in range(grow):
        keys = sorted(done)
        best = min(v[0] for v in done.values())
        grew = False
        if done[keys[0]][0] < 2.0 * best and keys[0] > 0.0:
            walk(np.arange(keys[0], keys[0] - half - 1e-12, -step), done[keys[0]][1:])
            grew = True
        if done[keys[-1]][0] < 2.0 * best and keys[-1] < _DEAD_MAX_S:
            walk(np.arange(keys[-1], keys[-1] + half + 1e-12, step), done[keys[-1]][1:])
            grew = True
        if not grew:
            break
    keys = sorted(done)
    vals = np.array([done[k] for k in keys])
    return np.array(keys), vals[:, 0], vals[:, 1], vals[:, 2]


@dataclass
class ServoFit:
    dead_time_s: float
    dead_ci95: tuple[float, float]
    time_constant_s: float
    tau_ci95: tuple[float, float]
    max_rate_deg_s: float
    rate_ci95: tuple[float, float]
    rate_identified: bool
    rate_note: str
    rmse_deg: float
    n_runs: int
    n_samples: int
    timing: list[str]


def fit_servo(data: Sequence[ServoData], *, start: tuple[float, float, float],
              resolution_deg: float) -> ServoFit:
    """Fit (dead time, time constant, rate limit) to the runs' servo logs.

    ``start``: the rig file's (dead [s], tau [s], rate [deg/s]).
    ``resolution_deg``: the servo's step (residual scale and quantisation noise).
    """
    scale = max(resolution_deg, 1e-3)
    n = sum(d.fb.size for d in data)
    tau0, rate0 = max(start[1], 0.005), max(start[2], 1.0)
    # start: the dead time on a coarse grid with the rig file's lag and rate
    coarse = np.arange(0.0, _DEAD_MAX_S + 1e-12, _COARSE_S)
    costs = [float(np.sum(_residual(data, d, tau0, rate0, scale) ** 2)) for d in coarse]
    dead0 = float(coarse[int(np.argmin(costs))])
    best = None
    for d_start in (dead0, max(dead0 - 2 * _COARSE_S, 0.0), dead0 + 2 * _COARSE_S):
        x, sol = _fit_all(data, (d_start, tau0, rate0), scale, True, rate0)
        if best is None or sol.cost < best[1].cost:
            best = (x, sol)
    (dead, tau, rate), sol = best
    reached = _fraction_rate_limited(data, dead, tau, rate)
    rate_note = ""
    rate_identified = reached >= 0.01
    if not rate_identified:
        held, sol_held = _fit_all(data, (dead, tau, start[2]), scale, False, start[2])
        stat = _rate_statistic(data, sol, sol_held, n)
        if stat > stats.chi2.ppf(1.0 - _RATE_ALPHA, 1):
            # rarely reached, yet the rig file's rate contradicts the logs:
            # the moves that reach it are the large ones, where a slower
            # servo lags for tenths of a second (field logs: the rig file's
            # 240 deg/s, 4.6 x the cost of the free fit's 301 for 300)
            rate_identified = True
            rate_note = (f"the servo reaches its rate limit in {100 * reached:.1f} % of the "
                         f"samples, and the rig file's {start[2]:g} deg/s fits them worse "
                         f"(likelihood ratio {stat:.0f})")
        else:
            rate_note = (f"the servo reaches its rate limit in {100 * reached:.1f} % of the samples "
                         "(< 1 %): the data do not constrain it")
            (dead, tau, rate), sol = held, sol_held
    npar = 3 if rate_identified else 2
    rate_fixed = rate if rate_identified else start[2]
    # dead time: profile with the time constant and rate refitted at each
    # node (they trade off against it: a profile with them held was too
    # narrow), which also moves the fit out of the local minima the step-
    # function cost leaves to least_squares (8 % lower cost on a foreign seed)
    nodes, prof, taus, rates = _dead_profile(data, dead, (tau, rate), scale, rate_identified,
                                             rate_fixed)
    k = int(np.argmin(prof))
    if prof[k] < 2.0 * sol.cost:
        dead, tau, rate = float(nodes[k]), float(taus[k]), float(rates[k])
    # the final fit with the dead time held: its Jacobian has no dead-time column
    (_, tau, rate), sol = _fit_dead_fixed(data, dead, (tau, rate), scale, rate_identified,
                                          rate_fixed)
    # residuals are correlated in time (quantised feedback, timing): scale
    # the variance by the integrated autocorrelation time of each run's part
    tau_int = _tau_int(data, sol.fun)
    s2 = 2.0 * sol.cost / max(n - npar, 1) * tau_int
    lim = min(float(prof.min()), 2.0 * sol.cost) + stats.chi2.ppf(0.95, 1) * s2
    inside = prof <= lim
    step = float(nodes[1] - nodes[0]) if nodes.size > 1 else _FINE_S
    dead_ci = ((float(nodes[inside].min()) - step / 2, float(nodes[inside].max()) + step / 2)
               if inside.any() else (math.nan, math.nan))
    dead_ci = (max(dead_ci[0], 0.0), dead_ci[1])
    # the logs give each run's command instants to one unknown phase,
    # uniform over +-half a servo sample; their mean over n runs adds
    # 1.96 x (2 u) / sqrt(12 n) (at most u) in quadrature
    u = [d.timing_u_s for d in data if d.timing_u_s > 0]
    if u:
        extra = min(max(u), 1.96 * 2 * float(np.mean(u)) / math.sqrt(12 * len(u)))
        lo_h, hi_h = float(dead) - dead_ci[0], dead_ci[1] - float(dead)
        dead_ci = (float(dead) - math.hypot(lo_h, extra), float(dead) + math.hypot(hi_h, extra))
    # time constant and rate: Jacobian with the dead time held (a finite
    # difference of the step-function cost in the dead time made J^T J
    # singular in 3 of 8 foreign-rig seeds); the dead time's own uncertainty
    # moves them: their intervals span the profile's refits over the dead
    # time's interval and at its (timing-widened) ends
    cov = _cov(sol.jac, s2)
    tau_ci = _log_ci(tau, cov, 0)
    rate_ci = _log_ci(rate, cov, 1) if rate_identified else (math.nan, math.nan)
    ends = []
    for d_end in dead_ci:
        if math.isfinite(d_end):
            (_, t_e, r_e), _ = _fit_dead_fixed(data, d_end, (tau, rate), scale, rate_identified,
                                               rate_fixed)
            ends.append((t_e, r_e))
    along = list(zip(taus[inside], rates[inside])) + ends
    for t_e, r_e in along:
        tau_ci = (min(tau_ci[0], t_e), max(tau_ci[1], t_e))
        if rate_identified:
            rate_ci = (min(rate_ci[0], r_e), max(rate_ci[1], r_e))
    # a command sent before its stamp, one phase for the rig (synchronous
    # logs): the delay from the stamps is the dead time's lower reading; the
    # time constant and rate do not move with it (every instant shifts alike)
    lead = max((d.stamp_lead_s for d in data), default=0.0)
    if lead > 0.0 and math.isfinite(dead_ci[1]):
        dead_ci = (dead_ci[0], max(dead_ci[1], float(dead) + lead))
    rmse = float(np.sqrt(2.0 * sol.cost / n)) * scale
    return ServoFit(float(dead), dead_ci, tau, tau_ci, rate, rate_ci, rate_identified, rate_note,
                    rmse, len(data), n, sorted({d.timing for d in data}))


#: false-alarm rate of taking the rate limit from the logs where it is rarely
#: reached (:func:`_rate_statistic` against chi-square(1))
_RATE_ALPHA = 1e-3


def _rate_statistic(data, sol_free, sol_held, n: int) -> float:
    """Likelihood ratio of the free rate limit against the rig file's: the
    drop of the sum of squares over the free fit's residual variance, scaled
    by the residuals' integrated autocorrelation time (0 when the free fit
    is not better)."""
    drop = 2.0 * (sol_held.cost - sol_free.cost)
    if not drop > 0:
        return 0.0
    s2 = 2.0 * sol_free.cost / max(n - 3, 1) * _tau_int(data, sol_free.fun)
    return drop / s2 if s2 > 0 else 0.0


def _tau_int(data, r) -> float:
    """Sample-weighted integrated autocorrelation time of the per-run residuals."""
    out, k = 0.0, 0
    for d in data:
        part = r[k:k + d.fb.size]
        k += d.fb.size
        out += integrated_autocorrelation(part) * part.size
    return out / max(k, 1)


def _fraction_rate_limited(data, dead, tau, rate) -> float:
    hit = tot = 0
    for d in data:
        y = servo_response(d.t_cmd, d.cmd, d.t_fb, dead_time_s=dead, time_constant_s=tau,
                           max_rate_deg_s=rate, theta0_deg=float(d.fb[0]))
        target = d.cmd[np.clip(np.searchsorted(d.t_cmd, d.t_fb - dead, side="right") - 1, 0, None)]
        hit += int(np.sum(np.abs(target - y) > rate * tau * 1.05))
        tot += y.size
    return hit / max(tot, 1)


def _cov(jac, s2) -> np.ndarray | None:
    try:
        jtj = jac.T @ jac
        if not np.all(np.isfinite(jtj)) or np.linalg.cond(jtj) > 1e12:
            return None
        return np.linalg.inv(jtj) * s2
    except np.linalg.LinAlgError:
        return None


def _log_ci(value, cov, i) -> tuple[float, float]:
    """95 % interval of a parameter fitted as its log."""
    if cov is None or i >= cov.shape[0] or not np.isfinite(cov[i, i]):
        return (math.nan, math.nan)
    half = 1.96 * math.sqrt(max(cov[i, i], 0.0))
    return (value * math.exp(-half), value * math.exp(half))


def heldout_rmse(data: Sequence[ServoData], dead, tau, rate) -> float:
    """RMSE [deg] of the servo model's angle against the logged one."""
    if not data:
        return math.nan
    r = _residual(data, dead, tau, rate, 1.0)
    return float(np.sqrt(np.mean(r ** 2)))


def servo_constants(train: Sequence[ServoData], held: Sequence[ServoData], rig
                    ) -> tuple[list[Constant], dict[str, Any], list[str]]:
    """The servo's constants, their training/held-out fit, and notes."""
    sv = rig["servo"]
    default = (float(sv["dead_time_s"]), float(sv["time_constant_s"]), float(sv["max_rate_deg_s"]))
    keys = [("servo.dead_time_s", "servo dead time", "s"),
            ("servo.time_constant_s", "servo time constant", "s"),
            ("servo.max_rate_deg_s", "servo rate limit", "deg/s")]
    if not train:
        why = "no run has servo feedback (cam_deg) and a moving command"
        return ([Constant(k, name, d, d, u, False, "servo logs", note=why)
                 for (k, name, u), d in zip(keys, default)], {}, [f"servo: {why}"])
    f = fit_servo(train, start=default, resolution_deg=float(sv["resolution_deg"]))
    by = f"servo logs of {f.n_runs} training run(s) ({f.n_samples} feedback samples)"
    consts = [
        Constant(keys[0][0], keys[0][1], f.dead_time_s, default[0], "s", True, by, f.dead_ci95,
                 note="profile interval"),
        Constant(keys[1][0], keys[1][1], f.time_constant_s, default[1], "s", True, by, f.tau_ci95),
        Constant(keys[2][0], keys[2][1], f.max_rate_deg_s if f.rate_identified else default[2],
                 default[2], "deg/s", f.rate_identified, by, f.rate_ci95, note=f.rate_note),
    ]
    fits = {"metric": "servo angle RMSE [deg]",
            "train_default": heldout_rmse(train, *default), "train": f.rmse_deg,
            "heldout_default": heldout_rmse(held, *default),
            "heldout": heldout_rmse(held, f.dead_time_s, f.time_constant_s, f.max_rate_deg_s),
            "n_train_runs": len(train), "n_heldout_runs": len(held),
            "command_timing": f.timing}
    return consts, fits, []
