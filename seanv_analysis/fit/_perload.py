"""Per-load quadratic fits and the paper's two-step identification (Sec. II-D.2).

(a) per side and load level: Q = alpha (theta - theta_d)^2 on the open side;
(b) z0 so that the eq. (3)+(4) thresholds match the per-load theta_d;
(c) C from alpha = C dp^n (n = 0.5: eq. 5).

Units: deg, MPa, mm^3/s, mm; alpha in mm^3/(s deg^2).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import least_squares

from ..models import ValveSide, signed_power

__all__ = ["LoadFit", "group_loads", "fit_load", "NoiseModel", "fit_noise_model",
           "two_step", "side_flow"]

#: sqrt(2/pi): E|r| / sigma for Gaussian noise
_ABS_MEAN = math.sqrt(2.0 / math.pi)


def side_flow(side: ValveSide, z0_mm: float, c_flow: float, theta_deg, p1_mpa, dp_mpa):
    """Eq. (5) for one side with trial parameters: Q = C opening^2 dp^n [mm^3/s]
    (threshold from eq. 3+4 via :meth:`ValveSide.threshold_deg`)."""
    return replace(side, z0_mm=float(z0_mm), c_flow=float(c_flow)).flow(theta_deg, p1_mpa, dp_mpa)


def group_loads(load_mpag: np.ndarray, *, tol_mpag: float = 0.02) -> np.ndarray:
    """Load-level label of each run: loads closer than ``tol_mpag`` [MPa] to the
    previous sorted load share a level; the label is the level's median load [MPaG]."""
    load = np.asarray(load_mpag, dtype=float)
    out = np.full(load.shape, np.nan)
    ok = np.flatnonzero(np.isfinite(load))
    if not ok.size:
        return out
    order = ok[np.argsort(load[ok], kind="stable")]
    breaks = np.flatnonzero(np.diff(load[order]) > tol_mpag) + 1
    for grp in np.split(order, breaks):
        out[grp] = round(float(np.median(load[grp])), 4)
    return out


@dataclass(frozen=True)
class NoiseModel:
    """Run-to-run flow noise: sigma(Q) = floor + rel |Q| [mm^3/s], fitted to
    the per-load residuals (robustly)."""

    floor_mm3_s: float
    rel: float

    def sigma(self, q_mm3_s) -> np.ndarray:
        return self.floor_mm3_s + self.rel * np.abs(np.asarray(q_mm3_s, dtype=float))


def fit_noise_model(residual_mm3_s, q_model_mm3_s) -> NoiseModel:
    """sigma = a + b |Q| from |r| ~ sqrt(2/pi) sigma (soft_l1 regression, a > 0, b >= 0).

    With fewer than 6 residuals: a constant sigma = 1.4826 MAD.
    """
    r = np.asarray(residual_mm3_s, dtype=float)
    q = np.abs(np.asarray(q_model_mm3_s, dtype=float))
    ok = np.isfinite(r) & np.isfinite(q)
    r, q = np.abs(r[ok]), q[ok]
    mad = 1.4826 * float(np.median(r)) if r.size else 1.0
    floor_min = max(1e-3, 1e-3 * mad)
    if r.size < 6:
        return NoiseModel(max(mad, floor_min), 0.0)
    scale = max(mad, floor_min)

    def fun(p):
        return (_ABS_MEAN * (p[0] + p[1] * q) - r) / scale

    res = least_squares(fun, [max(mad, floor_min), 0.01], bounds=([floor_min, 0.0], [np.inf, 1.0]),
                        loss="soft_l1", f_scale=1.0)
    return NoiseModel(float(res.x[0]), float(res.x[1]))


@dataclass
class LoadFit:
    """Quadratic fit at one load level: Q = alpha (theta - theta_d)^2 (open side).

    Attributes
    ----------
    theta_d_deg, theta_d_se_deg : threshold angle and its standard error [deg]
    alpha, alpha_se : flow sensitivity [mm^3/(s deg^2)] (negative on the drain side)
    rmse_mm3_s : RMSE of the fit [mm^3/s]
    success, message : whether the fit could be made, and why not
    """

    theta_d_deg: float = math.nan
    theta_d_se_deg: float = math.nan
    alpha: float = math.nan
    alpha_se: float = math.nan
    rmse_mm3_s: float = math.nan
    success: bool = False
    message: str = ""

    def predict(self, theta_deg, *, opens_upward: bool) -> np.ndarray:
        """alpha max(+-(theta - theta_d), 0)^2 [mm^3/s]."""
        return _quadratic(theta_deg, self.theta_d_deg, self.alpha, opens_upward)


def _quadratic(theta_deg, theta_d_deg, alpha, opens_upward: bool) -> np.ndarray:
    d = np.asarray(theta_deg, dtype=float) - theta_d_deg
    return alpha * np.maximum(d if opens_upward else -d, 0.0) ** 2


def fit_load(theta_deg, q_mm3_s, *, opens_upward: bool, sigma_mm3_s=None) -> LoadFit:
    """Fit Q = alpha max(+-(theta - theta_d), 0)^2 to one load level.

    Start from a line through sqrt|Q| vs theta, then a soft_l1 least-squares
    fit of Q itself (residuals divided by ``sigma_mm3_s`` when given).
    Needs 3 runs at >= 2 distinct cam angles.
    """
    theta = np.asarray(theta_deg, dtype=float)
    q = np.asarray(q_mm3_s, dtype=float)
    if theta.size < 3 or np.unique(theta).size < 2:
        return LoadFit(message=f"{theta.size} run(s) at {np.unique(theta).size} cam angle(s); "
                               "need 3 runs at >= 2 angles")
    sig = np.ones_like(q) if sigma_mm3_s is None else np.asarray(sigma_mm3_s, dtype=float)
    slope, icpt = np.polyfit(theta, np.sqrt(np.abs(q)), 1)
    if slope == 0 or (slope > 0) != opens_upward:
        theta_d0 = float(np.min(theta) - 1.0) if opens_upward else float(np.max(theta) + 1.0)
        span = max(abs(float(np.ptp(theta))), 1.0)
        alpha0 = float(np.median(q)) / span ** 2
    else:
        theta_d0 = float(-icpt / slope)
        alpha0 = float(np.sign(np.median(q)) * slope ** 2)
    # the threshold must stay below (supply) / above (drain) the most open run
    if opens_upward:
        theta_d0 = min(theta_d0, float(np.max(theta)) - 0.5)
    else:
        theta_d0 = max(theta_d0, float(np.min(theta)) + 0.5)
    def fun(p):
        return (q - _quadratic(theta, p[0], p[1], opens_upward)) / sig

    r0 = fun([theta_d0, alpha0])
    f_scale = max(1.4826 * float(np.median(np.abs(r0 - np.median(r0)))), 1e-6)
    if sigma_mm3_s is not None:
        f_scale = 1.0
    res = least_squares(fun, [theta_d0, alpha0], loss="soft_l1", f_scale=f_scale,
                        x_scale=[1.0, max(abs(alpha0), 1e-3)])
    theta_d, alpha = (float(v) for v in res.x)
    resid = q - _quadratic(theta, theta_d, alpha, opens_upward)
    rmse = float(np.sqrt(np.mean(resid ** 2)))
    se = _stderr(res.jac, (resid / sig), n_par=2)
    return LoadFit(theta_d, se[0], alpha, se[1], rmse, bool(res.success),
                   "" if res.success else res.message)


def _stderr(jac, resid_norm, *, n_par: int) -> np.ndarray:
    """Asymptotic standard errors from J (residual-scaled); NaN when singular."""
    m = resid_norm.size
    if m <= n_par:
        return np.full(n_par, np.nan)
    jtj = jac.T @ jac
    try:
        if not np.all(np.isfinite(jtj)) or np.linalg.cond(jtj) > 1e12:
            return np.full(n_par, np.nan)
        cov = np.linalg.inv(jtj)
    except np.linalg.LinAlgError:
        return np.full(n_par, np.nan)
    s2 = float(np.sum(resid_norm ** 2)) / (m - n_par)
    return np.sqrt(np.maximum(np.diag(cov) * s2, 0.0))


def two_step(side: ValveSide, theta_d_deg, theta_d_se_deg, alpha, alpha_se, p1_mpa, dp_mpa,
             p1_threshold_mpa=None, dp_threshold_mpa=None) -> dict:
    """The paper's procedure from per-load results: z0 from the thresholds
    (eq. 3+4, at ``p1/dp_threshold_mpa``, default ``p1/dp_mpa``), then C from
    alpha = C dp^n (weighted least squares through 0; ``dp_mpa`` is the dp
    alpha refers to).

    Returns ``{'z0_mm', 'z0_se_mm', 'c_flow', 'c_se', 'n_loads', 'success', 'message'}``.
    """
    th = np.asarray(theta_d_deg, dtype=float)
    p1_thr = np.asarray(p1_mpa if p1_threshold_mpa is None else p1_threshold_mpa, float)
    dp_thr = np.asarray(dp_mpa if dp_threshold_mpa is None else dp_threshold_mpa, float)
    ok = (np.isfinite(th) & np.isfinite(alpha) & np.isfinite(p1_mpa) & np.isfinite(dp_mpa)
          & np.isfinite(p1_thr) & np.isfinite(dp_thr))
    out = {"z0_mm": math.nan, "z0_se_mm": math.nan, "c_flow": math.nan, "c_se": math.nan,
           "n_loads": int(ok.sum()), "success": False, "message": ""}
    if ok.sum() < 1:
        out["message"] = "no load level with a quadratic fit"
        return out
    th, dp = th[ok], np.asarray(dp_mpa, float)[ok]
    p1_thr, dp_thr = p1_thr[ok], dp_thr[ok]
    a = np.asarray(alpha, float)[ok]
    w_th = _weights(np.asarray(theta_d_se_deg, float)[ok])
    w_a = _weights(np.asarray(alpha_se, float)[ok])

    def fun(z):
        return (side.threshold_deg(p1_thr, dp_thr, z0_mm=z[0]) - th) * np.sqrt(w_th)

    res = least_squares(fun, [side.z0_mm], x_scale=[0.01])
    out["z0_mm"] = float(res.x[0])
    out["z0_se_mm"] = float(_stderr(res.jac, res.fun, n_par=1)[0]) if th.size > 1 else math.nan
    g = signed_power(dp, side.dp_exponent)
    den = float(np.sum(w_a * g * g))
    out["c_flow"] = float(np.sum(w_a * a * g) / den)
    if a.size > 1:
        r = a - out["c_flow"] * g
        out["c_se"] = float(np.sqrt(np.sum(w_a * r * r) / (a.size - 1) / den))
    out["success"] = bool(res.success)
    out["message"] = "" if res.success else res.message
    return out


def _weights(se: np.ndarray) -> np.ndarray:
    """1/se^2, normalised; equal weights where any se is missing or zero."""
    if not np.all(np.isfinite(se) & (se > 0)):
        return np.ones_like(se)
    w = 1.0 / se ** 2
    return w / w.mean()
