"""Residual diagnostics: does the residual trend with a variable, is it white?

Residual sign everywhere: measured - model.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import special

__all__ = ["Trend", "trend_tests", "ljung_box", "robust_scale", "spearman"]


def robust_scale(x: np.ndarray) -> float:
    """1.4826 x median absolute deviation (sigma of Gaussian data), >= tiny."""
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return 1.0
    return max(float(1.4826 * np.median(np.abs(x - np.median(x)))), 1e-12)


def _average_ranks(x: np.ndarray) -> np.ndarray:
    """Ranks 1..n of ``x``, ties given their average rank."""
    _, inverse, counts = np.unique(x, return_inverse=True, return_counts=True)
    last = np.cumsum(counts)
    return (last - 0.5 * (counts - 1))[inverse]


def spearman(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Spearman rank correlation of ``x`` and ``y`` and its two-sided
    p-value (t with n - 2 degrees of freedom), what
    ``scipy.stats.spearmanr`` gives, without importing ``scipy.stats``
    (~0.5-0.9 s of a ``discover`` command's start)."""
    n = np.size(x)
    rho = float(np.corrcoef(_average_ranks(x), _average_ranks(y))[0, 1])
    if not np.isfinite(rho):
        return float("nan"), float("nan")
    if abs(rho) >= 1.0:
        return rho, 0.0
    t = rho * np.sqrt((n - 2) / ((1.0 - rho) * (1.0 + rho)))
    return rho, float(2.0 * special.stdtr(n - 2, -abs(t)))


@dataclass(frozen=True)
class Trend:
    """Association of the residual with one explanatory variable.

    ``rho``: Spearman rank correlation; ``p_value``: its two-sided p-value;
    ``binned``: (variable bin centres, residual bin medians) for the figure.
    """

    variable: str
    rho: float
    p_value: float
    n: int
    binned: tuple[np.ndarray, np.ndarray]


def trend_tests(residual: np.ndarray, variables: dict[str, np.ndarray], *,
                n_bins: int = 8) -> list[Trend]:
    """Spearman test of ``residual`` against each variable (constant ones skipped).

    Sorted by p-value, most significant first.
    """
    residual = np.asarray(residual, dtype=float)
    out = []
    for name, values in variables.items():
        v = np.asarray(values, dtype=float)
        ok = np.isfinite(v) & np.isfinite(residual)
        if ok.sum() < 8 or np.ptp(v[ok]) == 0:
            continue
        rho, p = spearman(v[ok], residual[ok])
        if not np.isfinite(rho):
            continue
        edges = np.unique(np.quantile(v[ok], np.linspace(0, 1, n_bins + 1)))
        idx = np.clip(np.searchsorted(edges, v[ok], side="right") - 1, 0, max(edges.size - 2, 0))
        centres, medians = [], []
        for b in range(max(edges.size - 1, 1)):
            sel = idx == b
            if sel.any():
                centres.append(float(np.median(v[ok][sel])))
                medians.append(float(np.median(residual[ok][sel])))
        out.append(Trend(name, float(rho), float(p), int(ok.sum()),
                         (np.array(centres), np.array(medians))))
    return sorted(out, key=lambda t: t.p_value)


def ljung_box(residual: np.ndarray, *, lags: int = 10) -> tuple[float, float]:
    """Ljung-Box whiteness test of a residual sequence (in time order).

    Q = n (n + 2) sum_{k=1..h} r_k^2 / (n - k), chi-square with h dof.
    Returns (Q, p_value); a small p-value means the residual is not white.
    """
    x = np.asarray(residual, dtype=float)
    x = x[np.isfinite(x)]
    n = x.size
    h = min(lags, max(n // 4, 1))
    if n < 8:
        return 0.0, 1.0
    x = x - x.mean()
    denom = float(np.dot(x, x))
    if denom == 0:
        return 0.0, 1.0
    r = np.array([np.dot(x[:-k], x[k:]) / denom for k in range(1, h + 1)])
    q = float(n * (n + 2) * np.sum(r ** 2 / (n - np.arange(1, h + 1))))
    return q, float(special.chdtrc(h, q))   # chi-square survival
