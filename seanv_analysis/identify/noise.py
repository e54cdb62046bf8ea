"""Effective sample size of autocorrelated residuals (for honest intervals).

Simulation-error residuals of a sampled signal are strongly correlated in
time (quantisation, timing jitter, unmodelled dynamics), so n samples carry
far fewer than n independent errors. With the integrated autocorrelation
time tau_int = 1 + 2 sum_k rho_k (up to the first non-positive rho_k), the
effective count is n / tau_int; Jacobian covariances are scaled by tau_int.
"""
from __future__ import annotations

import numpy as np

__all__ = ["integrated_autocorrelation"]


def integrated_autocorrelation(r: np.ndarray) -> float:
    """1 + 2 sum of the residual's autocorrelation up to its first zero (>= 1)."""
    x = np.asarray(r, float)
    x = x[np.isfinite(x)] - np.mean(x[np.isfinite(x)]) if x.size else x
    if x.size < 3:
        return 1.0
    from scipy.fft import irfft, next_fast_len, rfft

    m = next_fast_len(2 * x.size, real=True)   # a prime-factor length costs 10-100x
    f = rfft(x, m)
    acf = irfft(f * np.conj(f), m)[:x.size]
    if acf[0] <= 0:
        return 1.0
    acf = acf / acf[0]
    below = np.flatnonzero(acf <= 0)
    k = int(below[0]) if below.size else x.size
    return max(1.0, 1.0 + 2.0 * float(np.sum(acf[1:k])))

