"""Delay estimation by cross-correlation (analysis.lag)."""
import numpy as np
import pytest
from scipy.signal import butter, filtfilt

from seanv_analysis.analysis.lag import LagEstimate, estimate_lag, estimate_lag_segments
from seanv_analysis.errors import DataError


def _lowpass_noise(t, delay_s, *, seed=0, cutoff_hz=2.0, noise=0.05):
    """target(t) = w(t), actual(t) = w(t - delay) + noise; w low-pass white noise."""
    rng = np.random.default_rng(seed)
    dt_fine = 1e-3
    base = np.arange(-2.0, t[-1] + 2.0, dt_fine)
    b, a = butter(2, cutoff_hz * 2 * dt_fine)
    w = filtfilt(b, a, rng.standard_normal(base.size))
    target = np.interp(t, base, w)
    actual = np.interp(t - delay_s, base, w) + noise * w.std() * rng.standard_normal(t.size)
    return target, actual


@pytest.mark.parametrize("dt", [0.001, 0.01])
def test_recovers_known_delay_subsample(dt):
    t = np.arange(0.0, 60.0, dt)
    target, actual = _lowpass_noise(t, 0.237)
    est = estimate_lag(t, target, actual)
    assert isinstance(est, LagEstimate) and est.success
    assert abs(est.lag_s - 0.237) < 0.005
    lo, hi = est.ci95_s
    assert lo <= est.lag_s <= hi and hi - lo < 0.02
    assert est.peak_correlation > 0.9


def test_sign_convention_actual_ahead_is_negative():
    t = np.arange(0.0, 30.0, 0.01)
    target, actual = _lowpass_noise(t, -0.1, seed=3)
    assert abs(estimate_lag(t, target, actual, n_boot=0).lag_s + 0.1) < 0.005


def test_nan_gaps_and_hold_periods():
    t = np.arange(0.0, 60.0, 0.001)
    target, actual = _lowpass_noise(t, 0.237, seed=1)
    hold = (t % 10.0) > 7.0  # q_ref zero while held, actual near zero
    target[hold] = 0.0
    actual[np.roll(hold, 237)] = 0.01 * np.random.default_rng(2).standard_normal(hold.sum())
    target[5000:6500] = np.nan
    actual[30000:30400] = np.nan
    est = estimate_lag(t, target, actual)
    assert abs(est.lag_s - 0.237) < 0.005
    assert est.n_samples < t.size


def test_segments_pool_without_crossing():
    segs = []
    for seed in range(3):
        t = np.arange(0.0, 20.0, 0.01)
        segs.append((t, *_lowpass_noise(t, 0.25, seed=seed)))
    est = estimate_lag_segments(segs)
    assert abs(est.lag_s - 0.25) < 0.005
    assert est.n_blocks >= 3


def test_seeded_interval_is_reproducible():
    t = np.arange(0.0, 30.0, 0.01)
    target, actual = _lowpass_noise(t, 0.2, seed=4, noise=0.5)
    a = estimate_lag(t, target, actual, seed=7)
    b = estimate_lag(t, target, actual, seed=7)
    assert a.ci95_s == b.ci95_s
    assert "bootstrap" in a.method and "seed 7" in a.method
    assert a.to_json_dict()["ci95_s"] == list(a.ci95_s)


def test_peak_at_edge_warns():
    t = np.arange(0.0, 30.0, 0.01)
    target, actual = _lowpass_noise(t, 0.6, seed=5)
    with pytest.warns(UserWarning, match="edge"):
        est = estimate_lag(t, target, actual, max_lag_s=0.3, n_boot=0)
    assert "edge" in est.message


def test_errors():
    t = np.arange(10.0)
    with pytest.raises(DataError, match="equal lengths"):
        estimate_lag(t, t[:-1], t)
    with pytest.raises(DataError, match="strictly increasing"):
        estimate_lag(t[::-1], t, t)
    with pytest.raises(ValueError, match="max_lag_s"):
        estimate_lag(t, t, t, max_lag_s=0)
    with pytest.raises(DataError, match="at least one"):
        estimate_lag_segments([])


def test_record_mostly_holds_at_different_levels():
    """3 active 5 s blocks among 11 holds, each hold at its own level in
    both signals (a position-control run is mostly holds, Q_ref = Kp e held
    at a level, the flow at another). Level changes between blocks carry no
    timing: pooled as raw sums they pulled the peak to 0.265 s with an
    interval 0.00..0.29 s that excluded the truth, and resamples made of
    holds alone stretched the interval over the whole search range."""
    dt = 0.01
    t = np.arange(0.0, 70.0, dt)
    wave, _ = _lowpass_noise(t, 0.0, seed=7)
    active = ((t >= 10) & (t < 15)) | ((t >= 35) & (t < 40)) | ((t >= 55) & (t < 60))
    level = np.floor(t / 5.0) * 0.05
    target = np.where(active, wave, level)
    actual = np.where(active, np.interp(t - 0.3, t, wave), 0.3 * level)
    for seed in range(3):
        est = estimate_lag(t, target, actual, seed=seed)
        lo, hi = est.ci95_s
        assert abs(est.lag_s - 0.3) < 0.01, est.report()
        assert lo - 0.01 <= 0.3 <= hi + 0.01 and hi - lo < 0.05, est.report()
