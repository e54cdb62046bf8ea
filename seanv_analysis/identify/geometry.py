"""Needle geometry: how the sealing threshold moves with the pressures.

Eq. (3) gives the threshold's spring displacement z_c = z0 - F_w / k, with
F_w = pi/4 (d_n^2 p1 - d_o^2 dp) (eq. 1); eq. (4) turns it into a cam angle
through the needle-head centre (x_c, y_c), which Table II does not publish.
Near the thresholds the cam angle moves by dz_c / (dz/dtheta) per unit
height, and dz/dtheta = tan(phi) (-x_c sin theta - y_c cos theta) + O(r
tan(phi) sin(phi)): at theta = -10..-25 deg, y_c sets it ~4-6 times more
strongly than x_c, while x_c's effect on the height itself is a constant
offset that z0 absorbs. So the one-parameter form fitted here is y_c with
x_c kept at the rig file's value: with z0 it reproduces the threshold over
the tested pressures whatever the true (x_c, y_c) (the acceptance is on the
threshold angle, not on the centre itself).

Per side, Q = C (theta - theta_d(p1, dp; z0, y_c))^2 dp^0.5 (eq. 5) is
fitted to the flow steps flowfit used, (z0, C, y_c) together, with the same
per-run noise scale and robust loss as flowfit's joint fit. y_c is
identified only when the runs span different fluid forces (>= 2 load levels
whose thresholds differ by more than the threshold's own scatter) and its
95 % interval is finite and narrower than +-50 % of the value; otherwise the
rig file's value stays.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy.optimize import least_squares

from ..fit.flowfit import C_KEY
from ..models import ValveSide, fluid_force_n
from .result import Constant

__all__ = ["GeometryFit", "fit_geometry", "geometry_constants", "threshold_span"]


@dataclass
class GeometryFit:
    """(z0, C, y_c) of one side with 95 % intervals (Jacobian, scaled by the
    residual variance); ``identified`` False with ``note`` when y_c cannot be told."""

    side: str
    z0_mm: float
    c_flow: float
    y_c_mm: float
    y_c_ci95: tuple[float, float]
    identified: bool
    note: str
    rmse_mm3_s: float
    rmse_default_mm3_s: float
    n_runs: int
    n_loads: int
    force_span_n: float


def _with(side: ValveSide, z0, c, y_c) -> ValveSide:
    geom = replace(side.geometry, needle_y_c_mm=float(y_c))
    return replace(side, z0_mm=float(z0), c_flow=float(c), geometry=geom)


def _valid(side: ValveSide, y_c) -> bool:
    """Eq. (4) with this y_c is monotonic over the model's cam range (it can
    be inverted: a geometry the valve model can use)."""
    try:
        z, _ = _with(side, side.z0_mm, side.c_flow, y_c).geometry.height_table
    except ValueError:
        return False
    return z.size > 0


def _predict(side: ValveSide, x, theta, p1, dp):
    try:
        return _with(side, *x).flow(theta, p1, dp)
    except ValueError:          # eq. (4) not monotonic for this y_c
        return np.full(theta.shape, np.nan)


def _fit(side, theta, p1, dp, q, sigma, x0, lo, hi, f_scale, free_y: bool):
    y_fixed = x0[2]

    def full(p):
        return p if free_y else [p[0], p[1], y_fixed]

    def resid(p):
        r = (q - _predict(side, full(p), theta, p1, dp)) / sigma
        return np.where(np.isfinite(r), r, 1e3)

    n = 3 if free_y else 2
    starts = [x0[2], x0[2] * 0.75, x0[2] * 1.3] if free_y else [x0[2]]
    best = None
    for y_start in starts:     # a few starts: the threshold is piecewise in the parameters
        p0 = np.clip([x0[0], x0[1], y_start][:n], np.add(lo[:n], 1e-9), np.subtract(hi[:n], 1e-9))
        sol = least_squares(resid, p0, bounds=(lo[:n], hi[:n]), loss="soft_l1", f_scale=f_scale,
                            x_scale=[0.01, max(abs(x0[1]), 1e-3), 1.0][:n], diff_step=1e-5)
        if best is None or sol.cost < best.cost:
            best = sol
    return np.asarray(full(best.x), float), best


def fit_geometry(side: ValveSide, theta_deg, p1_mpa, dp_mpa, q_mm3_s, sigma_mm3_s, load_level,
                 *, z0_start_mm: float, c_start: float, heldout=None) -> GeometryFit:
    """Fit (z0, C, y_c) of one side to its flow steps (eq. 3-5); see the module notes.

    ``heldout``: optional (theta, p1, dp, q) of runs kept out of the fit; the
    RMSEs reported are then on them, for this fit and for (z0, C) fitted with
    the rig file's y_c (``rmse_default_mm3_s``).
    """
    theta, p1, dp, q, sigma = (np.asarray(a, float) for a in
                               (theta_deg, p1_mpa, dp_mpa, q_mm3_s, sigma_mm3_s))
    y0 = float(side.geometry.needle_y_c_mm)
    sgn = math.copysign(1.0, y0) if y0 != 0 else -1.0
    levels = np.unique(np.asarray(load_level, float)[np.isfinite(np.asarray(load_level, float))])
    force = fluid_force_n(p1, dp, side.geometry)
    span = float(np.ptp(force)) if force.size else 0.0
    x0 = [z0_start_mm, c_start, y0]
    r0 = (q - _predict(side, x0, theta, p1, dp)) / sigma
    f_scale = max(1.4826 * float(np.nanmedian(np.abs(r0))), 1e-6)
    lo = [z0_start_mm - 1.0, min(0.0, 20 * c_start), -80.0 if sgn < 0 else 4.0]
    hi = [z0_start_mm + 1.0, max(0.0, 20 * c_start), -4.0 if sgn < 0 else 80.0]
    x_def, _ = _fit(side, theta, p1, dp, q, sigma, x0, lo, hi, f_scale, free_y=False)
    x, best = _fit(side, theta, p1, dp, q, sigma, x_def, lo, hi, f_scale, free_y=True)
    ci = (math.nan, math.nan)
    try:
        dof = max(q.size - 3, 1)
        s2 = float(np.sum(best.fun ** 2)) / dof
        cov = np.linalg.inv(best.jac.T @ best.jac) * s2
        if np.isfinite(cov[2, 2]) and cov[2, 2] >= 0:
            half = 1.96 * math.sqrt(cov[2, 2])
            ci = (float(x[2] - half), float(x[2] + half))
    except np.linalg.LinAlgError:
        pass
    if heldout is not None:
        th, hp1, hdp, hq = (np.asarray(a, float) for a in heldout)
    else:
        th, hp1, hdp, hq = theta, p1, dp, q

    def rmse(xx):
        r = hq - _predict(side, xx, th, hp1, hdp)
        return float(np.sqrt(np.nanmean(r ** 2))) if np.isfinite(r).any() else math.nan

    note, ok = "", True
    if not _valid(side, x[2]):
        # the fit ended where eq. (4) cannot be inverted (every residual at
        # its sentinel, a flat cost): no centre of a valve
        ok, note = False, (f"the fit ended at y_c = {x[2]:.1f} mm, where eq. (4) is not "
                           "monotonic over the cam range")
    elif levels.size < 2:
        ok, note = False, (f"{levels.size} load level(s): the threshold's dependence on the "
                           "pressures needs >= 2")
    elif not all(math.isfinite(v) for v in ci) or (ci[1] - ci[0]) / 2 > 0.5 * abs(x[2]):
        ok, note = False, (f"the fluid force spans {span:.1f} N only; y_c's 95 % interval "
                           f"{_fmt_ci(ci)} mm is too wide")
    elif abs(x[2] - lo[2]) < 1e-6 or abs(x[2] - hi[2]) < 1e-6:
        ok, note = False, f"y_c ran into its bound ({x[2]:.1f} mm)"
    return GeometryFit(side.side, float(x[0]), float(x[1]), float(x[2]), ci, ok, note,
                       rmse(x), rmse(x_def), int(q.size), int(levels.size), span)


def _fmt_ci(ci) -> str:
    return "[" + ", ".join("n/a" if not math.isfinite(v) else f"{v:.3g}" for v in ci) + "]"


def threshold_span(side: ValveSide, p1_mpa, dp_mpa) -> np.ndarray:
    """Sealing threshold [deg] (eq. 3+4) at each (p1, dp)."""
    return np.asarray(side.threshold_deg(np.asarray(p1_mpa, float), np.asarray(dp_mpa, float)))


def geometry_constants(per_run, model, rig) -> tuple[list[Constant], dict[str, Any], list[str]]:
    """Needle centre y_c per side from flowfit's per-run table (runs used);
    constants, fit summary and notes."""
    consts, fits, notes = [], {}, []
    for name in ("supply", "drain"):
        key = f"valve.{name}.needle_y_c_mm"
        default = float(rig["valve"][name]["needle_y_c_mm"])
        rows = per_run[(per_run["side"] == name) & per_run["used"].astype(bool)]
        if len(rows) < 8:
            why = f"{len(rows)} usable flow step(s) on this side (need >= 8)"
            consts.append(Constant(key, f"{name} needle centre y_c", default, default, "mm", False,
                                   "flow steps", note=why))
            continue
        side = model.side(name)
        rows = rows.sort_values("run_index")
        # held out: every third run in time order (all loads and angles stay in
        # both parts: the constants are static, the split tests prediction)
        pick = (np.arange(len(rows)) % 3 == 2) if len(rows) >= 12 else np.zeros(len(rows), bool)
        train, held = rows[~pick], rows[pick]
        n_held = int(pick.sum())
        cols = ["theta_deg", "p1_mpa", "dp_mpa", "q_mm3_s"]
        g = fit_geometry(side, train["theta_deg"], train["p1_mpa"], train["dp_mpa"],
                         train["q_mm3_s"], train["sigma_mm3_s"].fillna(1.0).clip(lower=1e-3),
                         train["load_level_mpag"], z0_start_mm=side.z0_mm, c_start=side.c_flow,
                         heldout=[held[c] for c in cols] if n_held else None)
        by = (f"threshold vs fluid force over {g.n_loads} load levels ({g.n_runs} flow steps, "
              f"F_w span {g.force_span_n:.1f} N)")
        consts.append(Constant(key, f"{name} needle centre y_c", g.y_c_mm if g.identified else
                               default, default, "mm", g.identified, by,
                               g.y_c_ci95 if g.identified else (math.nan, math.nan), note=g.note))
        thr_default = threshold_span(side, rows["p1_mpa"], rows["dp_mpa"])
        thr_new = threshold_span(_with(side, g.z0_mm, g.c_flow, g.y_c_mm), rows["p1_mpa"],
                                 rows["dp_mpa"]) if _valid(side, g.y_c_mm) else thr_default
        part = "heldout" if n_held else "train"
        fits[name] = {"metric": "flow-step RMSE [mm^3/s], y_c of the rig file vs identified "
                                "(z0, C refitted for each)",
                      f"{part}_default": g.rmse_default_mm3_s, part: g.rmse_mm3_s, "n_train_runs": len(train), "n_heldout_runs": n_held,
                      "z0_mm": g.z0_mm, C_KEY: g.c_flow,
                      "threshold_range_deg": [float(np.min(thr_new)), float(np.max(thr_new))],
                      "threshold_range_default_deg": [float(np.min(thr_default)),
                                                      float(np.max(thr_default))]}
        if not g.identified:
            notes.append(f"geometry ({name}): {g.note}; y_c stays {default:g} mm")
    return consts, fits, notes
