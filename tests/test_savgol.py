"""Savitzky-Golay derivative and moving average without scipy
(:mod:`seanv_analysis.signals.savgol`) against scipy.signal / scipy.ndimage
and exact cases."""
import numpy as np
import pytest
from fresh_process import modules_after
from numpy.testing import assert_allclose
from scipy.ndimage import uniform_filter1d
from scipy.signal import savgol_coeffs, savgol_filter

from seanv_analysis.signals.savgol import moving_average, savgol_coefficients, savgol_derivative


@pytest.mark.parametrize("window, polyorder, deriv", [
    (51, 2, 1), (51, 3, 1), (5, 2, 0), (7, 3, 1), (11, 4, 2), (3, 1, 1), (9, 2, 3), (1, 0, 0)])
def test_equals_scipy_savgol_filter_interp_including_the_ends(window, polyorder, deriv):
    rng = np.random.default_rng(window * 10 + polyorder)
    x = 30.0 + np.cumsum(rng.normal(size=600))             # position-like [mm]
    dt = 0.001
    ours = savgol_derivative(x, window, polyorder, deriv=deriv, delta=dt)
    ref = savgol_filter(x, window, polyorder, deriv=deriv, delta=dt, mode="interp")
    scale = np.max(np.abs(ref)) or 1.0
    assert_allclose(ours, ref, rtol=0, atol=1e-12 * scale)
    half = window // 2                                       # the off-centre ends too
    assert_allclose(ours[:half], ref[:half], rtol=0, atol=1e-12 * scale)
    assert_allclose(ours[-half or None:], ref[-half or None:], rtol=0, atol=1e-12 * scale)


def test_coefficients_equal_scipy_savgol_coeffs():
    assert_allclose(savgol_coefficients(51, 2, deriv=1, delta=0.001),
                    savgol_coeffs(51, 2, deriv=1, delta=0.001, use="dot"), rtol=1e-12, atol=1e-9)


def test_exact_for_a_quadratic_motion():
    t = np.arange(0, 0.5, 0.001)
    x = 10 + 5.0 * t - 3.0 * t ** 2                          # [mm]
    v = savgol_derivative(x, 51, 2, deriv=1, delta=0.001)   # [mm/s]
    assert_allclose(v, 5.0 - 6.0 * t, atol=1e-9)


@pytest.mark.parametrize("size", [1, 2, 5, 101, 102, 700])
def test_moving_average_equals_uniform_filter1d_nearest(size):
    x = np.random.default_rng(size).normal(size=500) * 5 + 20
    assert_allclose(moving_average(x, size), uniform_filter1d(x, size, mode="nearest"),
                    rtol=0, atol=1e-12)


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="window: 4"):
        savgol_derivative(np.zeros(10), 4, 2)
    with pytest.raises(ValueError, match="polyorder: 5"):
        savgol_derivative(np.zeros(10), 5, 5)
    with pytest.raises(ValueError, match="x: "):
        savgol_derivative(np.zeros(3), 5, 2)
    with pytest.raises(ValueError, match="size: 0"):
        moving_average(np.zeros(3), 0)


def test_per_run_path_imports_neither_scipy_signal_nor_ndimage():
    """Reading and summarising a run (the pool workers' job) stays light."""
    assert modules_after("import seanv_analysis.signals.derive, seanv_analysis.stages.dataset",
                         ["scipy.signal", "scipy.ndimage", "scipy.stats", "matplotlib"]) == []
