"""Delay between a target and an actual signal by cross-correlation.

The paper (Sec. III-C.2, Fig. 7(a)) reads a delay of about 0.25 s between
the target flow Q_ref and the actual flow Q during position control. This
module estimates that delay from the data:

- both signals are put on a uniform grid (linear interpolation, NaN gaps kept
  as gaps);
- the masked correlation r(tau) between target(t) and actual(t + tau) is
  computed for every lag |tau| <= ``max_lag_s`` (only pairs where both
  samples are valid count, so NaN gaps and the edges of the record never
  enter), pooled over blocks of ``block_s`` with each block's covariance
  taken about its own means (as Welch's method detrends each segment: the
  levels of holds, which differ from block to block, carry no timing and
  would otherwise bias the peak toward zero lag);
- the lag is the peak of r(tau), refined below the sample step by a
  parabola through the peak and its two neighbours;
- the 95 % interval comes from a seeded moving-block bootstrap over
  non-overlapping blocks of the record (default 5 s; the per-block sums of
  the correlation are resampled, so each resample costs no FFT). The
  bootstrap is stratified: blocks over which the target varies and blocks
  over which it is constant (holds) are resampled separately, each in its
  own number, so every resample keeps the record's timing information (an
  unstratified resample made of holds alone, a few per cent of them when a
  record is mostly holds, "finds" a lag anywhere in the search range and
  stretches the interval over it).

Positive lag = the actual signal is *behind* the target (it must be shifted
earlier by ``lag_s`` to line up). Units: s, and whatever unit the signals
carry (the correlation is dimensionless).
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from ..errors import DataError
from ..estimate import Estimate
from ..jsonable import JsonResult, json_num

__all__ = ["LagEstimate", "estimate_lag", "estimate_lag_segments", "DEFAULT_BLOCK_S",
           "DEFAULT_N_BOOT"]

#: Length of the bootstrap blocks [s] (longer than the flow's correlation time).
DEFAULT_BLOCK_S = 5.0
#: Bootstrap resamples.
DEFAULT_N_BOOT = 200

_METHOD = ("masked cross-correlation pooled over block-detrended blocks, parabolic peak "
           "interpolation; 95 % CI: moving-block bootstrap ({n_boot} resamples of "
           "{block_s:g} s blocks, stratified by target varying / held, seed {seed}), "
           "percentile interval")


@dataclass(frozen=True)
class LagEstimate(JsonResult):
    """Delay of ``actual`` behind ``target``.

    Attributes
    ----------
    lag_s : delay [s]; positive = actual behind target (NaN when it failed)
    ci95_s : (lo, hi) 95 % bootstrap interval [s], or None (fewer than two blocks over which the target varies)
    peak_correlation : pooled within-block correlation at the peak [-]
    method : how it was computed (estimator, interval method, seed)
    dt_s : grid step [s]
    n_samples : valid (target, actual) pairs at zero lag
    n_blocks : bootstrap blocks
    lags_s, correlation : the correlation curve r(tau) (for plots)
    success : False when no peak could be found
    message : what went wrong or what to watch (peak at the search edge ...)
    """

    lag_s: float
    ci95_s: tuple[float, float] | None
    peak_correlation: float
    method: str
    dt_s: float
    n_samples: int
    n_blocks: int
    lags_s: np.ndarray = field(repr=False, default_factory=lambda: np.empty(0))
    correlation: np.ndarray = field(repr=False, default_factory=lambda: np.empty(0))
    success: bool = True
    message: str = ""

    def estimate(self, name: str = "lag", *, constrained_by: str = "") -> Estimate:
        """The delay as an :class:`~seanv_analysis.estimate.Estimate` [s]
        named ``name`` (its key ``lag_s``, its interval's ``lag_ci95_s``):
        'identified', or 'not_estimated' when no peak was found."""
        ci = self.ci95_s if self.ci95_s is not None else (math.nan, math.nan)
        ok = self.success and math.isfinite(self.lag_s)
        return Estimate(name, self.lag_s, "s", tuple(ci), method=self.method,
                        constrained_by=constrained_by or f"{self.n_samples} samples, "
                                                         f"{self.n_blocks} blocks",
                        source="identified" if ok else "not_estimated", note=self.message)

    def to_json_dict(self) -> dict[str, Any]:
        """JSON-ready dict (without the correlation curve)."""
        return {"lag_s": json_num(self.lag_s),
                "ci95_s": None if self.ci95_s is None else [json_num(v) for v in self.ci95_s],
                "peak_correlation": json_num(self.peak_correlation), "method": self.method,
                "dt_s": self.dt_s, "n_samples": self.n_samples, "n_blocks": self.n_blocks,
                "success": self.success, "message": self.message}

    def report(self) -> str:
        """One line: lag, interval, correlation."""
        ci = ("no CI" if self.ci95_s is None
              else f"95 % CI [{self.ci95_s[0]:.4f}, {self.ci95_s[1]:.4f}] s")
        text = (f"lag {self.lag_s:.4f} s ({ci}), peak correlation {self.peak_correlation:.3f}, "
                f"{self.n_samples} samples, {self.n_blocks} blocks")
        return text + (f"; {self.message}" if self.message else "")


def _uniform(t_s, target, actual, dt_s: float | None):
    """Both signals on a uniform grid; invalid (NaN) where either source sample is."""
    t = np.asarray(t_s, dtype=np.float64).ravel()
    x = np.asarray(target, dtype=np.float64).ravel()
    y = np.asarray(actual, dtype=np.float64).ravel()
    if not (t.size == x.size == y.size):
        raise DataError(f"t_s, target, actual have {t.size}, {x.size}, {y.size} samples; "
                        "expected equal lengths")
    ok_t = np.isfinite(t)
    t, x, y = t[ok_t], x[ok_t], y[ok_t]
    if t.size < 3:
        raise DataError(f"{t.size} samples; expected at least 3", column="t_s")
    if np.any(np.diff(t) <= 0):
        raise DataError("timestamps not strictly increasing", column="t_s")
    dt = float(np.median(np.diff(t))) if dt_s is None else float(dt_s)
    n = int(math.floor((t[-1] - t[0]) / dt + 1e-9)) + 1
    grid = t[0] + dt * np.arange(n)
    out = []
    for v in (x, y):
        good = np.isfinite(v)
        if good.sum() < 2:
            out.append(np.full(n, np.nan))
            continue
        vi = np.interp(grid, t[good], v[good])
        # a grid point is valid only when both bracketing samples are valid
        idx = np.clip(np.searchsorted(t, grid, side="right") - 1, 0, t.size - 1)
        idx2 = np.clip(idx + 1, 0, t.size - 1)
        exact = np.isclose(t[idx], grid, rtol=0, atol=1e-9 * max(dt, 1e-12))
        valid = good[idx] & (good[idx2] | exact)
        vi[~valid] = np.nan
        out.append(vi)
    return grid, out[0], out[1], dt


def _block_sums(x: np.ndarray, y: np.ndarray, n_lag: int, block_n: int) -> np.ndarray:
    """Per-block correlation sums, shape (n_blocks, 6, 2 n_lag + 1).

    For block b and lag k (in samples, -n_lag..n_lag) the six sums over the
    target samples i in b with both x_i and y_{i+k} valid: n, Sx, Sy, Sxx,
    Syy, Sxy.
    """
    mx = np.isfinite(x)
    my = np.isfinite(y)
    x0 = np.where(mx, x, 0.0)
    y0 = np.where(my, y, 0.0)
    n = x.size
    pad = np.zeros(n_lag)
    ypad = np.concatenate((pad, y0, pad))
    mypad = np.concatenate((pad, my.astype(float), pad))
    out = []
    for i0 in range(0, n, block_n):
        i1 = min(i0 + block_n, n)
        if i1 - i0 < 2 or not mx[i0:i1].any():
            continue
        a_m = mx[i0:i1].astype(float)
        a_x = x0[i0:i1]
        # y samples i0 - n_lag .. i1 - 1 + n_lag (ypad is offset by n_lag)
        b_y = ypad[i0:i1 + 2 * n_lag]
        b_m = mypad[i0:i1 + 2 * n_lag]
        sums = _valid_correlations((b_m, b_y, b_y * b_y), (a_m, a_x, a_x * a_x),
                                   ((0, 0), (0, 1), (1, 0), (0, 2), (2, 0), (1, 1)))
        sums[0] = np.rint(sums[0])    # counts of valid pairs: whole numbers
        out.append(sums)
    return np.array(out) if out else np.empty((0, 6, 2 * n_lag + 1))


def _valid_correlations(longs, shorts, pairs) -> np.ndarray:
    """``scipy.signal.correlate(longs[i], shorts[j], mode="valid")`` for each
    (i, j) of ``pairs``, as rows: c[k] = sum_m long[m + k] short[m], k = 0 ..
    len(long) - len(short). By FFT with numpy, each signal transformed once
    (scipy.signal is not imported: ~1 s, it pulls in scipy.stats, for what
    ``tracking`` needs of it)."""
    n_long, n_short = longs[0].size, shorts[0].size
    nfft = 1 << int(n_long + n_short - 1).bit_length()
    fl = [np.fft.rfft(v, nfft) for v in longs]
    fs = [np.conj(np.fft.rfft(v, nfft)) for v in shorts]
    return np.array([np.fft.irfft(fl[i] * fs[j], nfft)[:n_long - n_short + 1] for i, j in pairs])


def _centred(per_block: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each block's (n, C_xy, C_xx, C_yy), shape (n_blocks, 2 n_lag + 1)
    each: its co- and variances' sums about the block's own means (as
    Welch's cross-spectrum detrends each segment), from its sums
    (:func:`_block_sums`). Computed once: a bootstrap resample sums the
    blocks it picks (:func:`_pearson`)."""
    n, sx, sy, sxx, syy, sxy = np.moveaxis(per_block, 1, 0)
    inv = np.where(n > 0, 1.0 / np.where(n > 0, n, 1.0), 0.0)
    return (n, sxy - sx * sy * inv, np.maximum(sxx - sx * sx * inv, 0.0),
            np.maximum(syy - sy * sy * inv, 0.0))


def _pearson(centred: tuple[np.ndarray, ...], pick: np.ndarray | None = None,
             min_pairs: int = 3) -> np.ndarray:
    """Pooled within-block correlation r(tau) of the blocks ``pick`` (all
    when None) from their centred sums (:func:`_centred`):
    r = sum_b C_xy,b / sqrt(sum_b C_xx,b sum_b C_yy,b). Levels that differ
    from block to block (holds at different Q_ref) carry no timing and do
    not enter; for a single block this is the plain Pearson correlation.
    """
    n, cxy, cxx, cyy = centred if pick is None else (a[pick] for a in centred)
    cxy, cxx, cyy = (np.sum(a, axis=0) for a in (cxy, cxx, cyy))
    var = cxx * cyy
    with np.errstate(invalid="ignore", divide="ignore"):
        r = cxy / np.sqrt(np.where(var > 0, var, np.nan))
    r[n.sum(axis=0) < min_pairs] = np.nan
    return r


def _target_varies(per_block: np.ndarray, n_lag: int, rel: float = 1e-9) -> np.ndarray:
    """Blocks whose target varies (zero-lag variance above ``rel`` of the
    largest block's); the others are holds, constant up to rounding."""
    n, sx, sxx = per_block[:, 0, n_lag], per_block[:, 1, n_lag], per_block[:, 3, n_lag]
    safe = np.where(n > 0, n, 1.0)
    var = np.where(n > 1, (sxx - sx * sx / safe) / safe, 0.0)
    top = float(var.max()) if var.size else 0.0
    return (var > rel * top) & (var > 0.0)


def _peak(r: np.ndarray, lags_n: np.ndarray, dt: float) -> tuple[float, float, bool]:
    """(lag [s], peak r, at_edge) with parabolic sub-sample refinement."""
    if not np.isfinite(r).any():
        return math.nan, math.nan, False
    k = int(np.nanargmax(r))
    edge = k == 0 or k == r.size - 1
    delta = 0.0
    if not edge and np.isfinite(r[k - 1]) and np.isfinite(r[k + 1]):
        den = r[k - 1] - 2.0 * r[k] + r[k + 1]
        if den < 0:
            delta = float(np.clip(0.5 * (r[k - 1] - r[k + 1]) / den, -0.5, 0.5))
    return (lags_n[k] + delta) * dt, float(r[k]), edge


def estimate_lag_segments(segments: Sequence[tuple[Any, Any, Any]], *, max_lag_s: float = 1.0,
                          dt_s: float | None = None, block_s: float = DEFAULT_BLOCK_S,
                          n_boot: int = DEFAULT_N_BOOT, seed: int = 0) -> LagEstimate:
    """Pooled delay of several records (e.g. the runs of a data set).

    Parameters
    ----------
    segments : sequence of ``(t_s, target, actual)`` arrays, one per record;
        pairs never cross records
    max_lag_s, dt_s, block_s, n_boot, seed : see :func:`estimate_lag`;
        ``dt_s`` defaults to the first record's median step

    Returns
    -------
    LagEstimate
        Correlation sums are added over records before the peak search
        (the pooled r(tau)); bootstrap blocks are drawn from all records.

    Raises
    ------
    DataError
        no segment, or a segment with unequal lengths / non-increasing time.
    ValueError
        ``max_lag_s``, ``block_s`` not positive or ``n_boot`` negative.
    """
    if not segments:
        raise DataError("segments: expected at least one (t_s, target, actual) record")
    if not max_lag_s > 0:
        raise ValueError(f"max_lag_s: expected > 0, got {max_lag_s}")
    if not block_s > 0:
        raise ValueError(f"block_s: expected > 0, got {block_s}")
    if n_boot < 0:
        raise ValueError(f"n_boot: expected >= 0, got {n_boot}")
    dt = None if dt_s is None else float(dt_s)
    blocks = []
    n_pairs = 0
    n_lag = None
    for t, x, y in segments:
        _, xg, yg, dt = _uniform(t, x, y, dt)
        if n_lag is None:
            n_lag = max(1, int(round(max_lag_s / dt)))
        block_n = max(2 * n_lag + 1, int(round(block_s / dt)))
        b = _block_sums(xg, yg, n_lag, block_n)
        if b.size:
            blocks.append(b)
        n_pairs += int(np.sum(np.isfinite(xg) & np.isfinite(yg)))
    method = _METHOD.format(n_boot=n_boot, block_s=block_s, seed=seed)
    lags_n = np.arange(-n_lag, n_lag + 1)
    if not blocks:
        return LagEstimate(math.nan, None, math.nan, method, dt, 0, 0, lags_n * dt,
                           np.full(lags_n.size, np.nan), False, "no valid samples")
    per_block = np.concatenate(blocks)
    centred = _centred(per_block)
    r = _pearson(centred)
    lag, peak, edge = _peak(r, lags_n, dt)
    messages = []
    success = math.isfinite(lag)
    if not success:
        messages.append("correlation undefined (a signal is constant)")
    if edge:
        messages.append(f"peak at the edge of the search range +-{max_lag_s:g} s: "
                        "increase max_lag_s")
        warnings.warn(f"estimate_lag: peak at the edge of +-{max_lag_s:g} s", stacklevel=2)
    ci = None
    nb = per_block.shape[0]
    varying = np.flatnonzero(_target_varies(per_block, n_lag))
    held = np.setdiff1d(np.arange(nb), varying)
    if success and varying.size >= 2 and n_boot > 0:
        rng = np.random.default_rng(seed)
        boot = np.empty(n_boot)
        for j in range(n_boot):
            pick = np.concatenate((rng.choice(varying, varying.size),
                                   rng.choice(held, held.size) if held.size else held))
            boot[j] = _peak(_pearson(centred, pick), lags_n, dt)[0]
        boot = boot[np.isfinite(boot)]
        if boot.size >= 10:
            lo, hi = np.percentile(boot, [2.5, 97.5])
            ci = (float(min(lo, lag)), float(max(hi, lag)))
    elif success:
        messages.append("fewer than two blocks over which the target varies: "
                        "no confidence interval")
    return LagEstimate(float(lag), ci, float(peak), method, float(dt), n_pairs, nb,
                       lags_n * dt, r, success, "; ".join(messages))


def estimate_lag(t_s, target, actual, *, max_lag_s: float = 1.0, dt_s: float | None = None,
                 block_s: float = DEFAULT_BLOCK_S, n_boot: int = DEFAULT_N_BOOT,
                 seed: int = 0) -> LagEstimate:
    """Delay of ``actual`` behind ``target`` by cross-correlation.

    r(tau) = corr(target(t), actual(t + tau)) over valid pairs, |tau| <=
    ``max_lag_s``; lag = argmax r, refined by a parabola through the peak
    and its neighbours: tau* = tau_k + dt (r_{k-1} - r_{k+1}) /
    (2 (r_{k-1} - 2 r_k + r_{k+1})).

    Parameters
    ----------
    t_s : sample times [s], strictly increasing
    target : target signal (e.g. Q_ref [mm^3/s]); NaN = missing
    actual : actual signal, same unit; NaN = missing
    max_lag_s : largest |lag| searched [s]
    dt_s : grid step [s] (default: median step of ``t_s``)
    block_s : bootstrap block length [s] (at least 2 max_lag + 1 samples)
    n_boot : bootstrap resamples (0: no interval)
    seed : seed of the bootstrap's ``numpy.random.default_rng``

    Returns
    -------
    LagEstimate
        positive ``lag_s``: actual behind target.

    Raises
    ------
    DataError
        unequal lengths, fewer than 3 samples, non-increasing time.
    ValueError
        ``max_lag_s`` or ``block_s`` not positive, ``n_boot`` negative.

    Notes
    -----
    Hold periods (target constant, e.g. Q_ref = 0 while the cam is held)
    carry no timing information but do not bias the peak: they only lower
    the correlation's magnitude. A peak at the search edge is warned about.

    Examples
    --------
    >>> t = np.arange(0, 20, 0.01)
    >>> x = np.sin(2 * np.pi * 0.3 * t) + np.sin(2 * np.pi * 0.71 * t)
    >>> y = np.sin(2 * np.pi * 0.3 * (t - 0.2)) + np.sin(2 * np.pi * 0.71 * (t - 0.2))
    >>> round(estimate_lag(t, x, y, n_boot=0).lag_s, 2)
    0.2
    """
    return estimate_lag_segments([(t_s, target, actual)], max_lag_s=max_lag_s, dt_s=dt_s,
                                 block_s=block_s, n_boot=n_boot, seed=seed)
