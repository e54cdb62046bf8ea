"""Median and NaN-skipping mean and median of one 1-D float array: numpy's numbers, less overhead.

The per-run path takes a handful of these statistics per run over a few
thousand samples or fewer, where ``np.median``, ``np.nanmedian`` and
``np.nanmean`` spend most of their time in their general (any axis, any
dtype, masked arrays) Python layers: ~25, ~40 and ~25 us a call, against
~5-10 us here. Each function gives what the numpy one gives for a 1-D float
array, bit for bit (the same partition and the same mean of the middle
pair; for the NaN-skipping ones numpy's own function is called whenever
the array holds a NaN), and leaves its argument unchanged.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["median", "nanmedian", "nanmean"]


def median(x: np.ndarray) -> float:
    """``float(np.median(x))`` of a 1-D float array [x units]: its middle
    value, or the mean of the middle two; NaN when ``x`` holds a NaN."""
    n = x.size
    if n == 0:
        return float(np.median(x))  # NaN, with numpy's warning
    k = n // 2
    # np.median's partition: the middle index (or pair) and the last, where a NaN would sort
    part = np.partition(x, [k, -1] if n % 2 else [k - 1, k, -1])
    if math.isnan(part[-1]):
        return float(part[-1])
    # as np.median, the mean of the middle slice (which also turns -0.0 into 0.0)
    return float(np.mean(part[k:k + 1] if n % 2 else part[k - 1:k + 1]))


def nanmedian(x: np.ndarray) -> float:
    """``float(np.nanmedian(x))`` of a 1-D float array [x units]: the median
    of its values other than NaN (NaN, with numpy's warning, when all are)."""
    if x.size == 0 or np.isnan(x).any():
        return float(np.nanmedian(x))
    return median(x)


def nanmean(x: np.ndarray) -> float:
    """``float(np.nanmean(x))`` of a 1-D float array [x units]: the mean of
    its values other than NaN (NaN, with numpy's warning, when all are).

    Without NaN, ``np.nanmean`` sums a copy of ``x`` and divides by its
    size, as ``np.mean`` sums ``x``: the same pairwise sum, the same number.
    """
    if x.size:
        m = float(np.mean(x))
        if not math.isnan(m):
            return m
    return float(np.nanmean(x))  # NaN in x (or inf - inf, which gives NaN here too)
