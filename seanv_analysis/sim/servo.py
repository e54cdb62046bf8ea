"""The simulator's servo alone, driven by a logged command (for identification).

The servo of the plant (:mod:`.kernel`) acts on the command of ``dead_time``
earlier and follows it with a rate-limited first-order lag, solved exactly
over each step by :func:`.rosenbrock.servo_step`. :func:`servo_response`
runs that same compiled step on a recorded command (held between its
samples; :func:`.kernel.servo_track`, through :mod:`.compiled`), so
identifying the servo from a log fits the simulator's own equations, not a
copy of them.

Units: s, deg, deg/s.
"""
from __future__ import annotations

import numpy as np

from . import compiled
from ._pp import _SERVO_RATE, _SERVO_TAU, PP_SIZE

__all__ = ["servo_response"]


def servo_response(t_cmd_s, cmd_deg, t_out_s, *, dead_time_s: float, time_constant_s: float,
                   max_rate_deg_s: float, theta0_deg: float | None = None,
                   step_s: float = 5e-4) -> np.ndarray:
    """Servo angle [deg] at ``t_out_s`` for the command ``cmd_deg`` logged at
    ``t_cmd_s`` (held between samples; before the first sample: its value).

    The servo acts on the command of ``dead_time_s`` earlier and follows it
    with d(theta)/dt = clip((target - theta) / tau, -rate, rate), integrated
    exactly on a ``step_s`` grid (the simulator's step) and interpolated
    linearly at ``t_out_s`` (held at the grid's ends). ``theta0_deg``: angle
    at the first instant (default: the first command).
    """
    t_cmd = np.ascontiguousarray(t_cmd_s, dtype=float)
    cmd = np.ascontiguousarray(cmd_deg, dtype=float)
    t_out = np.asarray(t_out_s, dtype=float)
    if t_cmd.size == 0 or t_out.size == 0:
        return np.full(t_out.shape, np.nan)
    t0 = float(min(t_cmd[0], t_out[0]))
    n = int(np.ceil((float(t_out[-1]) - t0) / step_s)) + 2
    pp = np.zeros(PP_SIZE)
    pp[_SERVO_TAU] = max(float(time_constant_s), 1e-6)
    pp[_SERVO_RATE] = max(float(max_rate_deg_s), 1e-6)
    theta0 = float(cmd[0]) if theta0_deg is None else float(theta0_deg)
    y = compiled.servo_track()(t_cmd, cmd, t0, float(step_s), n, float(dead_time_s), pp, theta0)
    return _on_uniform_grid(y, t0 + step_s, step_s, t_out)


def _on_uniform_grid(y: np.ndarray, t_first: float, step: float, t) -> np.ndarray:
    """``y`` (at least 2 samples, at ``t_first + k step``) linearly
    interpolated at ``t``, held at its ends (``np.interp`` without building
    the grid: the servo's has 2000 points a second of log); NaN where ``t``
    is."""
    t = np.asarray(t, dtype=float)
    pos = np.clip((t - t_first) / step, 0.0, y.size - 1.0)
    finite = np.isfinite(pos)
    pos[~finite] = 0.0
    i = np.minimum(pos.astype(np.int64), y.size - 2)
    y0 = y[i]
    out = y0 + (pos - i) * (y[i + 1] - y0)
    out[~finite] = np.nan
    return out
