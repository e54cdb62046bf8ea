"""Joint fit of z0 and C on all runs of one side with eq. (5), robust loss,
and its bootstrap over runs.

Q_i = C max(+-(theta_i - theta_d(p1_i, dp_i; z0)), 0)^2 dp_i^n  (eq. 5, theta_d from eq. 3+4)

Residuals are divided by the run's noise scale sigma_i (a robust noise model,
:class:`~._perload.NoiseModel`) and passed through scipy's ``soft_l1`` loss
with ``f_scale`` = 1.4826 MAD of the scaled residuals, so one bad run has a
bounded influence. Q = 0 below the threshold makes the problem piecewise in
z0: the start comes from a grid over z0 (C solved linearly at each node)
around the two-step estimate.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from ..models import ValveSide
from ._perload import _stderr, side_flow

__all__ = ["JointFit", "fit_joint", "bootstrap_joint", "resample_indices"]

#: half-width [mm] and nodes of the start grid over z0
_GRID_HALF_MM = 0.15
_GRID_NODES = 61


@dataclass
class JointFit:
    """Result of :func:`fit_joint` (one side)."""

    z0_mm: float
    c_flow: float
    z0_se_mm: float
    c_se: float
    f_scale: float
    cost: float
    nfev: int
    success: bool
    message: str
    residual_mm3_s: np.ndarray = field(repr=False)
    q_model_mm3_s: np.ndarray = field(repr=False)


def _c_linear(basis: np.ndarray, q: np.ndarray, sigma: np.ndarray) -> float:
    """Weighted least-squares C for Q = C * basis (basis: eq. 5 with C = 1)."""
    w = 1.0 / sigma ** 2
    den = float(np.sum(w * basis * basis))
    return float(np.sum(w * basis * q) / den) if den > 0 else math.nan


def _soft_l1(z: np.ndarray) -> float:
    return float(np.sum(2.0 * (np.sqrt(1.0 + z * z) - 1.0)))


def _start(side, theta, p1, dp, q, sigma, z0_guess: float) -> tuple[float, float]:
    """Best (z0, C) on a z0 grid around ``z0_guess`` (C linear at each node)."""
    best = (math.inf, z0_guess, math.nan)
    mad_scale = None
    for z0 in z0_guess + np.linspace(-_GRID_HALF_MM, _GRID_HALF_MM, _GRID_NODES):
        basis = side_flow(side, z0, 1.0, theta, p1, dp)
        c = _c_linear(basis, q, sigma)
        if not math.isfinite(c):
            continue
        z = (q - c * basis) / sigma
        if mad_scale is None:
            mad_scale = max(1.4826 * float(np.median(np.abs(z))), 1e-6)
        cost = _soft_l1(z / mad_scale)
        if cost < best[0]:
            best = (cost, float(z0), c)
    return best[1], best[2]


def _solve(side, theta, p1, dp, q, sigma, x0, f_scale):
    def fun(x):
        return (q - side_flow(side, x[0], x[1], theta, p1, dp)) / sigma

    return least_squares(fun, x0, loss="soft_l1", f_scale=f_scale,
                         x_scale=[0.01, max(abs(x0[1]), 1e-3)], diff_step=[1e-5, 1e-6])


def fit_joint(side: ValveSide, theta_deg, p1_mpa, dp_mpa, q_mm3_s, sigma_mm3_s, *,
              z0_start_mm: float) -> JointFit:
    """Fit (z0, C) of one side on all its runs, eq. (5), soft_l1 loss.

    Parameters
    ----------
    side : the side's model (geometry, dp exponent); its z0/C are not used
    theta_deg, p1_mpa, dp_mpa, q_mm3_s : per run: cam [deg], p1 and dp [MPa], flow [mm^3/s]
    sigma_mm3_s : per-run noise scale [mm^3/s] (residuals are divided by it)
    z0_start_mm : centre of the start grid [mm]

    Notes
    -----
    ``f_scale`` is 1.4826 MAD of the scaled residuals at the start, then
    re-estimated once at the first solution and the fit repeated.
    Standard errors are asymptotic (Gauss-Newton on the robust loss); NaN
    when the covariance is singular.
    """
    theta, p1, dp, q, sigma = (np.asarray(a, dtype=float)
                               for a in (theta_deg, p1_mpa, dp_mpa, q_mm3_s, sigma_mm3_s))
    z0, c = _start(side, theta, p1, dp, q, sigma, z0_start_mm)
    if not math.isfinite(c):
        nan = np.full(q.shape, np.nan)
        return JointFit(math.nan, math.nan, math.nan, math.nan, math.nan, math.nan, 0, False,
                        "no start: eq. (5) predicts no flow for any run", nan, nan)
    x = np.array([z0, c])
    nfev = 0
    res = None
    for _ in range(2):
        r = (q - side_flow(side, x[0], x[1], theta, p1, dp)) / sigma
        f_scale = max(1.4826 * float(np.median(np.abs(r))), 1e-6)
        res = _solve(side, theta, p1, dp, q, sigma, x, f_scale)
        nfev += res.nfev
        x = res.x
    q_model = side_flow(side, x[0], x[1], theta, p1, dp)
    resid = q - q_model
    se = _stderr(res.jac, resid / sigma, n_par=2)
    return JointFit(float(x[0]), float(x[1]), float(se[0]), float(se[1]), f_scale,
                    float(res.cost), nfev, bool(res.success),
                    "" if res.success else str(res.message), resid, q_model)


def bootstrap_joint(side: ValveSide, theta_deg, p1_mpa, dp_mpa, q_mm3_s, sigma_mm3_s, *,
                    x_hat: tuple[float, float], f_scale: float, n_boot: int = 200,
                    seed: int = 0, clusters=None) -> np.ndarray:
    """(z0, C) refitted on ``n_boot`` resamples of the runs (with replacement).

    With ``clusters`` (one label per run) whole clusters are resampled (all
    their runs together): repeats of one condition share its systematic
    errors, so they are not independent. Each resample starts from
    ``x_hat`` with the same per-run noise scales and ``f_scale``. Returns an
    (n_ok, 2) array; resamples with fewer than 2 distinct cam angles or a
    failed fit are left out.
    """
    theta, p1, dp, q, sigma = (np.asarray(a, dtype=float)
                               for a in (theta_deg, p1_mpa, dp_mpa, q_mm3_s, sigma_mm3_s))
    rng = np.random.default_rng(seed)
    members = _cluster_members(q.size, clusters)
    out = []
    for _ in range(n_boot):
        idx = resample_indices(rng, members)
        if np.unique(theta[idx]).size < 2:
            continue
        res = _solve(side, theta[idx], p1[idx], dp[idx], q[idx], sigma[idx],
                     np.asarray(x_hat, dtype=float), f_scale)
        if res.status > 0 and np.all(np.isfinite(res.x)):
            out.append(res.x)
    return np.asarray(out, dtype=float).reshape(-1, 2)


def _cluster_members(n: int, clusters) -> list[np.ndarray]:
    if clusters is None:
        return [np.array([i]) for i in range(n)]
    _, inverse = np.unique(np.asarray(clusters), return_inverse=True)
    return [np.flatnonzero(inverse == k) for k in range(inverse.max() + 1)]


def resample_indices(rng: np.random.Generator, members: list[np.ndarray]) -> np.ndarray:
    """Run indices of one bootstrap resample: len(members) clusters drawn with
    replacement, all runs of each."""
    pick = rng.integers(0, len(members), len(members))
    return np.concatenate([members[k] for k in pick])
