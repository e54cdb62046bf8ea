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

from ..models import ValveSide, signed_power
from ..models.sealing import fluid_force_n
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

    from scipy.optimize import least_squares  # lazy: reading a fit needs no scipy

    return least_squares(fun, x0, loss="soft_l1", f_scale=f_scale,
                         x_scale=[0.01, max(abs(x0[1]), 1e-3)], diff_step=[1e-5, 1e-6])


class _Eq5Residual:
    """Scaled residual r = (q - Q(z0, C)) / sigma of eq. (5) on fixed runs, and
    its analytic Jacobian [d r / d z0 (1/mm), d r / d C].

    Q = C o^2 dp^n with o = max(s (theta - theta_d), 0), s = +1 supply, -1
    drain, theta_d = table inverse of eq. (4) at z0 - F_w / k (eq. 1, 3). The
    table is linear between its nodes, so d theta_d / d z0 is the node
    interval's slope (0 outside the table, where theta_d is clipped):
    dQ/dz0 = -2 s C o dp^n d theta_d/dz0, dQ/dC = o^2 dp^n. ``fun`` gives
    the same values as :func:`~._perload.side_flow` (same arithmetic).
    """

    def __init__(self, side: ValveSide, theta, p1, dp, q, sigma):
        geo = side.geometry
        self.force_k = fluid_force_n(p1, dp, geo) / geo.spring_constant_n_per_mm   # [mm]
        self.z_tab, self.th_tab = geo.height_table
        self.sign = 1.0 if side.opens_upward else -1.0
        self.theta, self.q, self.sigma = theta, q, sigma
        self.dpn = signed_power(dp, side.dp_exponent)
        self._at: tuple[float, np.ndarray, np.ndarray] | None = None

    def _opening(self, z0: float) -> tuple[np.ndarray, np.ndarray]:
        """(opening [deg], z_threshold [mm]) at z0, kept for the Jacobian of the same z0."""
        if self._at is None or self._at[0] != z0:
            z = z0 - self.force_k
            d = self.theta - np.interp(z, self.z_tab, self.th_tab)
            self._at = (z0, np.maximum(d if self.sign > 0 else -d, 0.0), z)
        return self._at[1], self._at[2]

    def fun(self, x: np.ndarray) -> np.ndarray:
        o, _ = self._opening(float(x[0]))
        return (self.q - x[1] * o * o * self.dpn) / self.sigma

    def jac(self, x: np.ndarray) -> np.ndarray:
        o, z = self._opening(float(x[0]))
        k = np.clip(np.searchsorted(self.z_tab, z), 1, self.z_tab.size - 1)
        slope = (self.th_tab[k] - self.th_tab[k - 1]) / (self.z_tab[k] - self.z_tab[k - 1])
        slope[(z < self.z_tab[0]) | (z > self.z_tab[-1])] = 0.0
        jac = np.empty((self.q.size, 2))
        jac[:, 0] = 2.0 * self.sign * x[1] * o * self.dpn * slope / self.sigma
        jac[:, 1] = -(o * o * self.dpn) / self.sigma
        return jac


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
    ``x_hat`` (the main fit) with the same per-run noise scales and
    ``f_scale``, with the analytic Jacobian of eq. (5) (:class:`_Eq5Residual`). Returns an
    (n_ok, 2) array; resamples with fewer than 2 distinct cam angles or a
    failed fit are left out.
    """
    theta, p1, dp, q, sigma = (np.asarray(a, dtype=float)
                               for a in (theta_deg, p1_mpa, dp_mpa, q_mm3_s, sigma_mm3_s))
    rng = np.random.default_rng(seed)
    members = _cluster_members(q.size, clusters)
    x0 = np.asarray(x_hat, dtype=float)
    x_scale = [0.01, max(abs(x0[1]), 1e-3)]
    out = []
    from scipy.optimize import least_squares  # lazy: reading a fit needs no scipy
    for _ in range(n_boot):
        idx = resample_indices(rng, members)
        if np.unique(theta[idx]).size < 2:
            continue
        r = _Eq5Residual(side, theta[idx], p1[idx], dp[idx], q[idx], sigma[idx])
        res = least_squares(r.fun, x0, jac=r.jac, loss="soft_l1", f_scale=f_scale,
                            x_scale=x_scale)
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
