"""The needles' seat leakage in the flow steps, fitted with the sides' z0 and C.

Each needle leaks past its seat, open or sealed (laminar, g dp), so a flow
step's actuator flow is the open side's eq. (5) plus the leakage of both
(:func:`seanv_analysis.models.seat_leakage_mm3_s`)::

    q_i = C_s max(+-(theta_i - theta_d(p1_i, dp_i; z0_s)), 0)^2 dp_i^n
          + g (dp_supply,i - dp_drain,i)                (s: the run's side)

g [mm^3/(s MPa)] is one conductance for both needles, so it is fitted once,
with (z0, C) of every side present, on all their runs (robust ``soft_l1``
loss, residuals divided by each run's noise scale, as the joint fit). The
leakage is a few mm^3/s, but it moves with the head pressure from load to
load, which is the threshold's dependence on the pressures (eq. 3): left
out, it shifts z0 and, with the needle centre free (``identify``), y_c
(simulator, clean: y_c -20.27 [-20.31, -20.23] mm for -20).

The rig file's conductance enters as a prior, g ~ N(g_rig, s^2) with s =
the paper's leakage band (+-50 mm^3/s at the supply pressure, 3 mm^3/(s MPa)
on the paper's rig) / 5, one more residual (g - g_rig) / s beside the runs'
scaled ones: where the runs tell g (the simulator's 345 flow steps: s.e.
0.2 mm^3/(s MPa)) it does not matter; where they do not (24 flow steps per
side at 4 cam angles: the leakage trades off against the threshold's
pressure dependence and ran to its bound, 15 mm^3/(s MPa)) g stays near the
rig file's with an interval of about +-2 s.

Its 95 % interval is a cluster-robust sandwich (repeats of one condition,
load level x commanded cam, share their errors: on the simulator they agree
to the bit; the prior is one more cluster), normal quantile, clipped at 0.

Units: deg, MPa, mm^3/s, mm; g in mm^3/(s MPa).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from ..estimate import Estimate
from ..models import ValveSide
from ._joint import Eq5Residual

__all__ = ["SideRuns", "LeakageFit", "leak_dp_mpa", "fit_leakage", "cluster_covariance",
           "soft_l1_weights", "prior_sd_mm3_s_per_mpa"]


def prior_sd_mm3_s_per_mpa(leakage_flow_mm3_s: float, p_supply_mpag: float) -> float:
    """Standard deviation of the seat leakage's prior [mm^3/(s MPa)]: the
    paper's leakage band (``analysis.leakage_flow_mm3_s`` at the supply
    pressure) taken as 5 of them."""
    return float(leakage_flow_mm3_s) / max(float(p_supply_mpag), 0.1) / 5.0


def leak_dp_mpa(side: np.ndarray, p1_mpa, dp_mpa, dp_sealed_mpa, *, p_supply_mpag: float,
                p_tank_mpag: float) -> np.ndarray:
    """dp_supply - dp_drain of each flow step [MPa], the pressure term of the seat leakage.

    A supply run logs dp_supply (its dp) and, as ``dp_sealed_mpa``, the
    drain needle's dp_drain = p_head - p_tank; a drain run the other way
    round. Where ``dp_sealed_mpa`` is missing, the sealed needle's dp comes
    from the run's head pressure and the rig's ``p_supply_mpag`` /
    ``p_tank_mpag`` [MPaG].
    """
    side = np.asarray(side).astype(str)
    p1, dp, sealed = (np.asarray(a, float) for a in (p1_mpa, dp_mpa, dp_sealed_mpa))
    sup = side == "supply"
    p_head = np.where(sup, p1 - dp, p1)
    fallback = np.where(sup, p_head - p_tank_mpag, p_supply_mpag - p_head)
    other = np.where(np.isfinite(sealed), sealed, fallback)
    return np.where(sup, dp - other, other - dp)


@dataclass
class SideRuns:
    """One side's flow steps for a fit of eq. (5) with the seat leakage
    (:func:`fit_leakage`; ``identify``'s needle-geometry fit): the side's
    model (geometry, exponent; its z0 and C are where the fit starts,
    :attr:`start`) and per run the cam [deg], p1 and dp [MPa], flow
    [mm^3/s], noise scale [mm^3/s], the leakage's pressure term dp_supply -
    dp_drain [MPa] (:func:`leak_dp_mpa`), load level [MPaG] (NaN: not
    given) and condition label (repeats share it; default: each run its
    own); ``heldout``: (theta, p1, dp, q, dp_leak) of runs kept out of the
    fit, for the RMSEs (None: none)."""

    side: ValveSide
    theta_deg: np.ndarray
    p1_mpa: np.ndarray
    dp_mpa: np.ndarray
    q_mm3_s: np.ndarray
    sigma_mm3_s: np.ndarray
    dp_leak_mpa: np.ndarray
    load_level: np.ndarray | None = None
    clusters: np.ndarray | None = None
    heldout: tuple | None = None

    def __post_init__(self):
        if self.load_level is None:
            self.load_level = np.full(np.shape(self.q_mm3_s), np.nan)
        for name in ("theta_deg", "p1_mpa", "dp_mpa", "q_mm3_s", "sigma_mm3_s", "dp_leak_mpa",
                     "load_level"):
            setattr(self, name, np.asarray(getattr(self, name), float))
        if self.clusters is None:
            self.clusters = np.arange(self.q_mm3_s.size)

    @property
    def start(self) -> tuple[float, float]:
        """(z0 [mm], C) the fit starts from: the side model's."""
        return float(self.side.z0_mm), float(self.side.c_flow)


@dataclass
class LeakageFit:
    """Seat-leakage conductance g of the needles [mm^3/(s MPa)] with its 95 %
    interval; ``fitted`` False when the rig file's value was kept
    (``message`` says why); ``sides`` {side: (z0 [mm], C)} of the joint fit."""

    conductance_mm3_s_per_mpa: float
    ci95: tuple[float, float] = (math.nan, math.nan)
    se: float = math.nan
    fitted: bool = False
    n_runs: int = 0
    n_conditions: int = 0
    method: str = ""
    message: str = ""
    sides: dict[str, tuple[float, float]] = field(default_factory=dict)

    @property
    def half_width95(self) -> float:
        """Half the 95 % interval [mm^3/(s MPa)] (NaN when not fitted)."""
        lo, hi = self.ci95
        return 0.5 * (hi - lo) if self.fitted else math.nan

    def estimate(self, *, modelled: bool = True) -> Estimate:
        """g as an :class:`~seanv_analysis.estimate.Estimate` named
        'leakage.g' [mm^3/(s MPa)]: 'identified' when fitted, else the rig
        file's kept ('rig_file'), or 'not_estimated' (0) when the leakage is
        not ``modelled`` (``leakage='none'``)."""
        source = "identified" if self.fitted else ("rig_file" if modelled else "not_estimated")
        return Estimate("leakage.g", self.conductance_mm3_s_per_mpa, "mm^3/(s MPa)",
                        tuple(self.ci95), self.se, method=self.method,
                        constrained_by=(f"{self.n_runs} flow steps ({self.n_conditions} "
                                        "conditions), both sides" if self.fitted else ""),
                        source=source,
                        default=math.nan if self.fitted else self.conductance_mm3_s_per_mpa,
                        note=self.message)

    def to_dict(self, *, modelled: bool = True) -> dict[str, Any]:
        """:meth:`estimate`'s record (``value_mm3_s_per_mpa``,
        ``ci95_mm3_s_per_mpa``, ``stderr_mm3_s_per_mpa``...) with fitted,
        n_runs, n_conditions and message."""
        return {**self.estimate(modelled=modelled).to_json_dict(), "fitted": bool(self.fitted),
                "n_runs": int(self.n_runs), "n_conditions": int(self.n_conditions),
                "message": self.message}


def cluster_covariance(jac: np.ndarray, resid: np.ndarray, weights: np.ndarray,
                       clusters: Sequence) -> np.ndarray | None:
    """Cluster-robust (sandwich) covariance of an M-estimate.

    ``jac`` the Jacobian of the scaled residuals ``resid``, ``weights`` the
    loss's IRLS weights rho'(r^2) (1 for least squares); runs with the same
    ``clusters`` label share their errors. cov = A^-1 B A^-1 G/(G - 1) with
    A = sum w J J', B = sum over clusters of (sum w r J)(sum w r J)', G
    clusters. None when A is singular or there are fewer than 3 clusters.
    """
    labels = np.asarray([str(c) for c in clusters], dtype=object)
    _, inv = np.unique(labels.astype(str), return_inverse=True)
    n_c = int(inv.max()) + 1 if inv.size else 0
    if n_c < 3:
        return None
    wj = jac * weights[:, None]
    a = jac.T @ wj
    score = np.zeros((n_c, jac.shape[1]))
    np.add.at(score, inv, wj * resid[:, None])
    b = score.T @ score
    try:
        if not np.all(np.isfinite(a)) or np.linalg.cond(a) > 1e12:
            return None
        a_inv = np.linalg.inv(a)
    except np.linalg.LinAlgError:
        return None
    return a_inv @ b @ a_inv * (n_c / (n_c - 1.0))


def soft_l1_weights(scaled_resid: np.ndarray, f_scale: float) -> np.ndarray:
    """IRLS weights rho'(z) of scipy's ``soft_l1`` loss, z = (r / f_scale)^2."""
    return 1.0 / np.sqrt(1.0 + (scaled_resid / f_scale) ** 2)


def fit_leakage(parts: Sequence[SideRuns], *, upper_mm3_s_per_mpa: float,
                default_mm3_s_per_mpa: float, prior_sd_mm3_s_per_mpa: float,
                min_runs: int = 12) -> LeakageFit:
    """Fit the seat-leakage conductance g with (z0, C) of each side in ``parts``.

    Parameters
    ----------
    parts : the sides' runs (:class:`SideRuns`; each side's z0 and C the start)
    upper_mm3_s_per_mpa : bound of g [mm^3/(s MPa)] (g >= 0)
    default_mm3_s_per_mpa : the rig file's g: the prior's mean, and g kept
        when it cannot be fitted
    prior_sd_mm3_s_per_mpa : the prior's standard deviation (module notes)
    min_runs : fewer runs in all: not fitted

    Returns
    -------
    LeakageFit; not ``fitted`` (with the default) when there are too few
    runs, the leakage's pressure term does not vary, or the covariance is
    singular.
    """
    parts = [p for p in parts if p.q_mm3_s.size]
    n = int(sum(p.q_mm3_s.size for p in parts))
    keep = LeakageFit(float(default_mm3_s_per_mpa), n_runs=n)
    if n < min_runs:
        keep.message = f"{n} flow step(s): too few to fit the seat leakage"
        return keep
    xl_all = np.concatenate([p.dp_leak_mpa for p in parts])
    if not np.all(np.isfinite(xl_all)) or float(np.ptp(xl_all)) < 0.2:
        keep.message = ("the leakage's pressure term dp_supply - dp_drain spans "
                        f"{float(np.ptp(xl_all)) if np.all(np.isfinite(xl_all)) else math.nan:.2f} "
                        "MPa only: the seat leakage cannot be told from eq. (5)")
        return keep
    models = [Eq5Residual(p.side, p.theta_deg, p.p1_mpa, p.dp_mpa, p.q_mm3_s, p.sigma_mm3_s)
              for p in parts]
    k = len(parts)
    g_prior, s_prior = float(default_mm3_s_per_mpa), float(prior_sd_mm3_s_per_mpa)

    def fun(x):
        g = x[-1]
        return np.concatenate([m.fun(x[2 * i:2 * i + 2]) - g * p.dp_leak_mpa / p.sigma_mm3_s
                               for i, (m, p) in enumerate(zip(models, parts))]
                              + [[(g - g_prior) / s_prior]])

    def jac(x):
        out = np.zeros((n + 1, 2 * k + 1))
        row = 0
        for i, (m, p) in enumerate(zip(models, parts)):
            rows = slice(row, row + p.q_mm3_s.size)
            out[rows, 2 * i:2 * i + 2] = m.jac(x[2 * i:2 * i + 2])
            out[rows, -1] = -p.dp_leak_mpa / p.sigma_mm3_s
            row += p.q_mm3_s.size
        out[-1, -1] = 1.0 / s_prior
        return out

    g0 = min(max(float(default_mm3_s_per_mpa), 0.0), upper_mm3_s_per_mpa)
    x = np.array([v for p in parts for v in p.start] + [g0], dtype=float)
    lo = np.full(x.size, -np.inf)
    hi = np.full(x.size, np.inf)
    lo[-1], hi[-1] = 0.0, float(upper_mm3_s_per_mpa)
    x_scale = [v for p in parts for v in (0.01, max(abs(p.start[1]), 1e-3))] + [1.0]
    res = None
    from scipy.optimize import least_squares  # lazy: reading a fit needs no scipy
    for _ in range(2):       # f_scale from the start, then from the first solution
        f_scale = max(1.4826 * float(np.median(np.abs(fun(x)))), 1e-6)
        res = least_squares(fun, x, jac=jac, bounds=(lo, hi), loss="soft_l1", f_scale=f_scale,
                            x_scale=x_scale)
        x = res.x
    r = fun(x)
    clusters = np.concatenate([np.asarray([f"{p.side.side}|{c}" for c in p.clusters], object)
                               for p in parts] + [np.asarray(["prior"], object)])
    cov = cluster_covariance(jac(x), r, soft_l1_weights(r, f_scale), clusters)
    n_c = int(np.unique(clusters.astype(str)).size) - 1
    if cov is None or not np.isfinite(cov[-1, -1]):
        keep.message = "the seat leakage's covariance is singular: the rig file's value is kept"
        keep.n_conditions = n_c
        return keep
    g, se = float(x[-1]), float(math.sqrt(max(cov[-1, -1], 0.0)))
    ci = (max(g - 1.96 * se, 0.0), g + 1.96 * se)
    sides = {p.side.side: (float(x[2 * i]), float(x[2 * i + 1])) for i, p in enumerate(parts)}
    return LeakageFit(g, ci, se, True, n, n_c,
                      "joint fit with (z0, C) of " + " and ".join(sides) + " (soft_l1, "
                      f"per-run noise scale; prior N({g_prior:g}, {s_prior:.2g}^2), the rig "
                      "file's); 95 %: cluster-robust sandwich over conditions (load level x "
                      "commanded cam), normal quantile, clipped at 0",
                      "" if res.success else str(res.message), sides)
