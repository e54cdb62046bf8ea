"""Savitzky-Golay derivative and moving average on numpy arrays, without scipy.

:func:`savgol_derivative` gives what ``scipy.signal.savgol_filter(x, n, p,
deriv=d, delta=dt, mode='interp')`` gives (to rounding, ~1e-12 relative:
tested in ``tests/test_savgol.py``) and :func:`moving_average` what
``scipy.ndimage.uniform_filter1d(x, size, mode='nearest')`` gives, so the
per-run path (:mod:`.derive`) never imports scipy.signal or scipy.ndimage
(0.6 s of imports per worker process). The filter coefficients are computed
once per (window, order, derivative) and the filter is one ``np.correlate``.
"""
from __future__ import annotations

import functools
import math

import numpy as np

__all__ = ["savgol_coefficients", "savgol_derivative", "moving_average"]


@functools.lru_cache(maxsize=32)
def _weights(window: int, polyorder: int, deriv: int) -> tuple[np.ndarray, np.ndarray]:
    """(centre, edge) weights for unit sample spacing.

    centre : (window,) weights of the d-th derivative at the window's centre
    edge : (window // 2, window) weights of the d-th derivative at the first
        ``window // 2`` samples of a window (the polynomial fitted to the whole
        window, evaluated off-centre, as scipy's ``mode='interp'``)
    """
    half = window // 2
    k = np.arange(-half, half + 1, dtype=np.float64)        # centred: well conditioned
    vander = k[:, None] ** np.arange(polyorder + 1)          # (window, p+1)
    fit = np.linalg.pinv(vander)                             # polynomial coefficients = fit @ x
    # d-th derivative of sum_j a_j s^j at s: sum_j a_j j!/(j-d)! s^(j-d)
    j = np.arange(polyorder + 1)
    factor = np.array([math.perm(int(i), deriv) if i >= deriv else 0 for i in j], dtype=np.float64)
    powers = np.maximum(j - deriv, 0)
    at = k[:half]                                            # the first half-window positions
    deriv_rows = np.where(j >= deriv, factor * at[:, None] ** powers, 0.0)   # (half, p+1)
    centre = factor[deriv] * fit[deriv] if deriv <= polyorder else np.zeros(window)
    edge = deriv_rows @ fit
    centre.setflags(write=False)
    edge.setflags(write=False)
    return centre, edge


def savgol_coefficients(window: int, polyorder: int, *, deriv: int = 0,
                        delta: float = 1.0) -> np.ndarray:
    """Weights w with ``y[i] = sum_k w[k] x[i - half + k]`` (correlation
    order: w[0] multiplies the earliest sample); as
    ``scipy.signal.savgol_coeffs(..., use='dot')`` [1/delta^deriv]."""
    _check(window, polyorder, deriv)
    return _weights(window, polyorder, deriv)[0] / delta ** deriv


def _check(window: int, polyorder: int, deriv: int) -> None:
    if window < 1 or window % 2 == 0:
        raise ValueError(f"window: {window}; expected a positive odd number of samples")
    if polyorder < 0 or polyorder >= window:
        raise ValueError(f"polyorder: {polyorder}; expected 0 <= polyorder < window ({window})")
    if deriv < 0:
        raise ValueError(f"deriv: {deriv}; expected >= 0")


def savgol_derivative(x: np.ndarray, window: int, polyorder: int, *, deriv: int = 1,
                      delta: float = 1.0) -> np.ndarray:
    """Savitzky-Golay smoothing (``deriv=0``) or derivative of ``x`` [x units / delta^deriv].

    Each sample gets the ``deriv``-th derivative of the least-squares
    polynomial of order ``polyorder`` fitted to the ``window`` samples centred
    on it; the first and last ``window // 2`` samples get that of the
    polynomial fitted to the first/last full window, evaluated off-centre
    (scipy's ``mode='interp'``).

    Parameters
    ----------
    x : 1-D array, uniformly sampled, at least ``window`` samples
    window : odd window length [samples]
    polyorder : polynomial order, < window
    deriv : derivative order
    delta : sample spacing (e.g. [s])
    """
    _check(window, polyorder, deriv)
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 1 or x.size < window:
        raise ValueError(f"x: {x.shape}; expected a 1-D array of at least {window} samples")
    centre, edge = _weights(window, polyorder, deriv)
    half = window // 2
    y = np.empty_like(x)
    y[half:x.size - half] = np.correlate(x, centre, mode="valid")
    if half:
        y[:half] = edge @ x[:window]
        # the end: positions +1..+half of the last window = mirrored start with
        # the derivative's sign (-1)^deriv
        y[x.size - half:] = ((-1.0) ** deriv * (edge @ x[-1:-window - 1:-1]))[::-1]
    if delta != 1.0:
        y /= delta ** deriv
    return y


def moving_average(x: np.ndarray, size: int) -> np.ndarray:
    """Centred moving average of ``size`` samples, the ends extended with the
    first/last value (``scipy.ndimage.uniform_filter1d(x, size,
    mode='nearest')``; for even sizes the window reaches one sample further
    back than forward) [x units]."""
    x = np.asarray(x, dtype=np.float64)
    if size < 1:
        raise ValueError(f"size: {size}; expected >= 1")
    if size == 1 or x.size == 0:
        return x.copy()
    before = size // 2
    after = size - 1 - before
    padded = np.concatenate((np.full(before, x[0]), x, np.full(after, x[-1])))
    return np.correlate(padded, np.full(size, 1.0 / size), mode="valid")
