"""signals: interpolation equals np.interp bit for bit; one clock and constants cost no copy."""
from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from seanv_analysis.signals import align_streams, interp_sorted


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
    if n > 2 and seed % 3 == 0:   # non-finite samples: np.interp's NaN rules
        v[seed % n] = (np.nan, np.inf, -np.inf)[seed % 5 % 3]
    np.testing.assert_array_equal(interp_sorted(t, tk, v), np.interp(t, tk, v))


def test_same_clock_is_taken_as_is():
    tk = np.arange(100) / 1000.0
    v = np.sin(tk)
    out = interp_sorted(tk[10:60], tk, v)
    np.testing.assert_array_equal(out, v[10:60])
    assert not np.shares_memory(out, v)


def test_same_clock_view_when_asked():
    tk = np.arange(100) / 1000.0
    v = np.sin(tk)
    out = interp_sorted(tk[10:60], tk, v, copy=False)
    assert np.shares_memory(out, v)
    np.testing.assert_array_equal(out, v[10:60])


def test_constant_column_stays_a_view():
    enc = {"t_s": np.arange(10) / 1000.0, "position_mm": np.arange(10.0)}
    pr = {"t_s": np.arange(10) / 1000.0 + 3e-4, "p_head_mpag": np.linspace(1, 2, 10),
          "p_tank_mpag": np.broadcast_to(np.float64(0.05), 10)}
    out = align_streams({"encoder": enc, "pressure": pr})
    tank = out["p_tank_mpag"].to_numpy()
    assert tank.strides == (0,) and len(tank) == 9
    np.testing.assert_array_equal(tank, np.full(9, 0.05))
    np.testing.assert_array_equal(out["p_head_mpag"].to_numpy(),
                                  np.interp(out["t_s"].to_numpy(), pr["t_s"], pr["p_head_mpag"]))
