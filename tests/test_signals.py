"""signals: the shared-search interpolation equals np.interp bit for bit."""
from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from seanv_analysis.signals import _bracket, interp_sorted


@settings(max_examples=200, deadline=None)
@given(n=st.integers(1, 40), m=st.integers(0, 60), seed=st.integers(0, 2**32 - 1),
       sort=st.booleans())
def test_interp_sorted_is_np_interp(n, m, seed, sort):
    rng = np.random.default_rng(seed)
    tk = np.cumsum(rng.uniform(1e-4, 1.0, n))
    t = np.concatenate([rng.uniform(tk[0] - 1, tk[-1] + 1, m), tk,
                        np.nextafter(tk, -np.inf), np.nextafter(tk, np.inf)])
    if sort:
        t.sort()
    v = rng.normal(size=n)
    np.testing.assert_array_equal(interp_sorted(t, tk, v), np.interp(t, tk, v))
    if n >= 2:
        np.testing.assert_array_equal(_bracket(tk, t), np.searchsorted(tk, t, side="right") - 1)


def test_same_clock_is_taken_as_is():
    tk = np.arange(100) / 1000.0
    v = np.sin(tk)
    out = interp_sorted(tk[10:60], tk, v)
    np.testing.assert_array_equal(out, v[10:60])
    assert not np.shares_memory(out, v)
