"""Per-load quadratic fits and the paper's two-step identification (Sec. II-D.2).

(a) per side and load level: Q = alpha (theta - theta_d)^2 on the open side;
(b) z0 so that the eq. (3)+(4) thresholds match the per-load theta_d;
(c) C from alpha = C dp^n (n = 0.5: eq. 5);

and the lack-of-fit test of a fitted side (:func:`lack_of_fit_test`).

Units: deg, MPa, mm^3/s, mm; alpha in mm^3/(s deg^2).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..models import ValveSide, signed_power

__all__ = ["LoadFit", "group_loads", "fit_load", "NoiseModel", "fit_noise_model",
           "two_step", "side_flow", "LackOfFit", "lack_of_fit_test", "LOF_P_MAX", "LOF_RATIO_MIN",
           "LOF_SYSTEMATIC_MIN"]

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

    from scipy.optimize import least_squares  # lazy: reading a fit needs no scipy
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


def _quadratic_residual_jac(theta_deg, theta_d_deg, alpha, opens_upward: bool, sigma
                            ) -> np.ndarray:
    """(runs, 2) Jacobian of r = (q - alpha o^2) / sigma, o = max(s (theta -
    theta_d), 0) (s = +1 opening upward, else -1): [d r / d theta_d, d r / d
    alpha] = [2 s alpha o / sigma, -o^2 / sigma]."""
    s = 1.0 if opens_upward else -1.0
    o = np.maximum(s * (theta_deg - theta_d_deg), 0.0)
    return np.column_stack([2.0 * s * alpha * o / sigma, -(o * o) / sigma])


def fit_load(theta_deg, q_mm3_s, *, opens_upward: bool, sigma_mm3_s=None,
             theta_shift_deg=None) -> LoadFit:
    """Fit Q = alpha max(+-(theta - theta_d - s), 0)^2 to one load level.

    ``theta_shift_deg`` s [deg] (default 0): each run's threshold offset from
    the one fitted (e.g. its threshold at its own pressures less the one at
    the load's median pressures, eq. 3+4), so theta_d is the threshold at a
    common reference. Start from a line through sqrt|Q| vs theta - s, then a
    soft_l1 least-squares fit of Q itself (residuals divided by
    ``sigma_mm3_s`` when given; analytic Jacobian). Needs 3 runs at >= 2
    distinct cam angles (of ``theta_deg`` itself: the shifts do not make
    repeats distinct).
    """
    theta_raw = np.asarray(theta_deg, dtype=float)
    q = np.asarray(q_mm3_s, dtype=float)
    if theta_raw.size < 3 or np.unique(theta_raw).size < 2:
        return LoadFit(message=f"{theta_raw.size} run(s) at {np.unique(theta_raw).size} cam "
                               "angle(s); need 3 runs at >= 2 angles")
    theta = theta_raw if theta_shift_deg is None else \
        theta_raw - np.asarray(theta_shift_deg, dtype=float)
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

    def jac(p):
        return _quadratic_residual_jac(theta, p[0], p[1], opens_upward, sig)

    r0 = fun([theta_d0, alpha0])
    f_scale = max(1.4826 * float(np.median(np.abs(r0 - np.median(r0)))), 1e-6)
    if sigma_mm3_s is not None:
        f_scale = 1.0
    from scipy.optimize import least_squares  # lazy: reading a fit needs no scipy
    res = least_squares(fun, [theta_d0, alpha0], jac=jac, loss="soft_l1", f_scale=f_scale,
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

    from scipy.optimize import least_squares  # lazy: reading a fit needs no scipy
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


#: Lack of fit is flagged when it is significant (p < LOF_P_MAX), large next
#: to the repeats' scatter (ratio > LOF_RATIO_MIN) *and* material next to the
#: flow (systematic misfit > LOF_SYSTEMATIC_MIN of the weighted RMS flow): on
#: very clean data (the simulator's repeats agree to ~1 mm^3/s) a systematic
#: term of 0.1 % of the flow is significant and many times the repeats'
#: scatter, yet immaterial. 1 % is twice the flow-scale calibration
#: uncertainty (0.5 %, 95 %).
LOF_P_MAX = 0.01
LOF_RATIO_MIN = 1.5
LOF_SYSTEMATIC_MIN = 0.01


@dataclass(frozen=True)
class LackOfFit:
    """Classical lack-of-fit F test of a fitted model against the repeats.

    Attributes
    ----------
    flagged : True when p < :data:`LOF_P_MAX`, ratio > :data:`LOF_RATIO_MIN`
        and systematic > :data:`LOF_SYSTEMATIC_MIN` (when known); None when
        the test cannot be made (``reason`` says why)
    ratio : sqrt(F): scatter of the conditions' mean residuals (scaled to
        one run) / scatter of the repeats about their condition's mean [-];
        ~1 when the model describes the runs
    p_value : P(F(df_lof, df_pe) >= F)
    f_stat : F = (SS_lof / df_lof) / (SS_pe / df_pe)
    systematic : systematic misfit (the lack of fit less the noise expected in
        it) as a fraction of the flow, both RMS with the same weights [-]; NaN
        without ``flow_mm3_s``
    df_lof, df_pe : degrees of freedom (conditions - parameters; runs - conditions)
    n_conditions, n_repeated : conditions, and those with >= 2 runs
    reason : why there is no test (None when tested)
    """

    flagged: bool | None
    ratio: float = math.nan
    p_value: float = math.nan
    f_stat: float = math.nan
    systematic: float = math.nan
    df_lof: int = 0
    df_pe: int = 0
    n_conditions: int = 0
    n_repeated: int = 0
    reason: str | None = None


def lack_of_fit_test(residual_mm3_s, conditions, *, sigma_mm3_s=None, flow_mm3_s=None,
                     n_params: int = 2) -> LackOfFit:
    """Lack-of-fit F test from the residuals (measured - model) of a fitted model.

    The weighted residual sum of squares splits exactly into pure error
    (repeats about their condition's weighted mean residual) and lack of fit
    (the conditions' mean residuals)::

        SS_pe  = sum_ij w_ij (r_ij - rbar_i)^2,   df_pe  = N - m
        SS_lof = sum_i W_i rbar_i^2,              df_lof = m - n_params
        F = (SS_lof / df_lof) / (SS_pe / df_pe)

    with w = 1 / sigma^2 (equal weights without ``sigma_mm3_s``), W_i the sum
    of w over condition i, N runs, m conditions. Working on residuals rather
    than on the measured flows lets repeats differ a little in their
    covariates (pressures, measured cam angle): the model accounts for that.
    The systematic part, sum_i W_i b_i^2 ~ SS_lof - df_lof SS_pe / df_pe, is
    compared with sum w Q^2 (``systematic``).

    Parameters
    ----------
    residual_mm3_s : measured - model per run [mm^3/s]
    conditions : one label per run (runs with the same label are repeats)
    sigma_mm3_s : per-run noise scale [mm^3/s] (weights 1/sigma^2); None: equal
    flow_mm3_s : model flow per run [mm^3/s], for ``systematic``; None: not judged
    n_params : parameters fitted (z0 and C: 2)

    Returns
    -------
    LackOfFit; ``flagged`` None (with ``reason``) when no condition is
    repeated, there are too few conditions for the parameters, or the
    repeats agree exactly.

    Examples
    --------
    >>> r = [1.0, -1.0, 1.0, -1.0, 1.0, -1.0]          # repeats scatter, means on the model
    >>> lack_of_fit_test(r, ["a", "a", "b", "b", "c", "c"], n_params=1).flagged
    False
    """
    r = np.asarray(residual_mm3_s, dtype=float)
    w = np.ones_like(r) if sigma_mm3_s is None else 1.0 / np.asarray(sigma_mm3_s, float) ** 2
    q = np.full_like(r, np.nan) if flow_mm3_s is None else np.asarray(flow_mm3_s, float)
    labels = np.asarray([str(c) for c in conditions], dtype=object)
    ok = np.isfinite(r) & np.isfinite(w) & (w > 0)
    r, w, q, labels = r[ok], w[ok], q[ok], labels[ok]
    if not r.size:
        return LackOfFit(None, reason="no residuals")
    _, inv = np.unique(labels.astype(str), return_inverse=True)
    m = int(inv.max()) + 1
    counts = np.bincount(inv, minlength=m)
    wsum = np.bincount(inv, weights=w, minlength=m)
    rbar = np.bincount(inv, weights=w * r, minlength=m) / wsum
    ss_pe = float(np.sum(w * (r - rbar[inv]) ** 2))
    ss_lof = float(np.sum(wsum * rbar ** 2))
    df_pe, df_lof = int(r.size - m), int(m - n_params)
    base = {"df_lof": max(df_lof, 0), "df_pe": df_pe, "n_conditions": m,
            "n_repeated": int(np.sum(counts >= 2))}
    if df_pe <= 0:
        return LackOfFit(None, reason="no repeated condition (load level x commanded cam): "
                                      "no repeats' scatter to compare with", **base)
    if df_lof <= 0:
        return LackOfFit(None, reason=f"{m} condition(s) for {n_params} parameters: no "
                                      "degree of freedom left for lack of fit", **base)
    if not ss_pe > 0:
        return LackOfFit(None, reason="repeats agree exactly: no repeats' scatter", **base)
    ms_pe = ss_pe / df_pe
    f_stat = (ss_lof / df_lof) / ms_pe
    from scipy.special import fdtrc  # F survival function, as scipy.stats.f.sf (0.2 s lighter)
    p = float(fdtrc(df_lof, df_pe, f_stat))   # = scipy.stats.f.sf(f_stat, df_lof, df_pe)
    ratio = math.sqrt(f_stat)
    flow2 = float(np.sum(w * q ** 2))
    systematic = (math.sqrt(max(ss_lof - df_lof * ms_pe, 0.0) / flow2)
                  if math.isfinite(flow2) and flow2 > 0 else math.nan)
    material = ratio > LOF_RATIO_MIN and not systematic <= LOF_SYSTEMATIC_MIN
    return LackOfFit(bool(p < LOF_P_MAX and material), ratio, p, float(f_stat), systematic,
                     **base)
