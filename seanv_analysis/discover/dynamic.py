"""Discovery on position-control runs: is the flow later than the model says?

The base model of a closed-loop run is "actual flow = Q_ref delayed by the
nominal lag" (rig ``analysis.nominal_flow_lag_s``, the paper's 0.25 s, or a
lag measured earlier by ``tracking``). The candidate is ``delay``: an extra
transport delay. Each run is split in time: the lag is estimated by
cross-correlation (:func:`seanv_analysis.analysis.lag.estimate_lag`, with a
block-bootstrap 95 % interval) on the first part only; the last
``fraction`` of every run is held out and scores the flow RMSE with the
nominal lag (before) and with the estimated lag (after).

A delay is reported only when (1) the interval excludes the nominal lag,
(2) the extra delay is at least ``min_extra_s`` (physically material at
100 Hz control) and (3) the held-out tails, on their own, show a lag beyond
the nominal one in the same direction.

The shifted-flow RMSE is reported for the held-out tails, but in closed
loop a delay also changes the loop itself, so "shift the flow" is a poor
predictor: the error before/after that matters is the free-run
closed-loop one, which ``validate`` computes with the base and the
augmented model (the CLI and the pipeline call it; this module stays free
of the simulator).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import special

from ..jsonable import json_num
from .result import EffectFinding

__all__ = ["DelayDiscovery", "discover_delay", "flow_signals", "DELAY_EVIDENCE"]

#: the report's clause on how a delay is backed: the normal p-value of the
#: extra lag from the block-bootstrap interval
DELAY_EVIDENCE = "p = {p_value:.2g} (lag vs nominal, from the block-bootstrap interval)"


@dataclass
class DelayDiscovery:
    """Outcome of the delay check on position-control runs."""

    finding: EffectFinding | None
    nominal_lag_s: float
    lag_s: float
    lag_ci95_s: tuple[float, float] | None
    n_runs: int
    rmse_before_mm3_s: float
    rmse_after_mm3_s: float
    message: str = ""

    def to_json_dict(self) -> dict:
        return {"n_runs": self.n_runs, "nominal_lag_s": self.nominal_lag_s,
                "lag_s": json_num(self.lag_s),
                "lag_ci95_s": None if self.lag_ci95_s is None else [json_num(v) for v in self.lag_ci95_s],
                "shifted_rmse_nominal_mm3_s": json_num(self.rmse_before_mm3_s),
                "shifted_rmse_estimated_mm3_s": json_num(self.rmse_after_mm3_s),
                "found": self.finding is not None}


def flow_signals(run) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(t [s], Q_ref [mm^3/s], actual Q [mm^3/s]) of a position-control run on
    the encoder's time base, the target built as ``tracking`` builds it
    (:func:`seanv_analysis.analysis.tracking.run_flows`: logged Q_ref, else
    Kp e of a flow-model controller), or None when the run has no target flow."""
    from ..analysis.tracking import run_flows
    from ..errors import DataError

    try:
        flows, _ = run_flows(run)
    except DataError:
        return None
    return (flows["t_s"].to_numpy(float), flows["q_ref_mm3_s"].to_numpy(float),
            flows["q_mm3_s"].to_numpy(float))


def _shifted_rmse(t, q_ref, q, lag, q_range, min_abs=0.0) -> tuple[float, int]:
    """RMSE of actual(t + lag) - Q_ref(t) over Q_ref in ``q_range`` with
    |Q_ref| >= ``min_abs`` (samples where the valve is commanded open)."""
    inside = (t + lag <= t[-1]) & (t + lag >= t[0])
    shifted = np.interp(t + lag, t, q)
    m = (inside & (q_ref >= q_range[0]) & (q_ref <= q_range[1]) & (np.abs(q_ref) >= min_abs)
         & np.isfinite(q_ref) & np.isfinite(shifted))
    if not m.any():
        return math.nan, 0
    return float(np.sqrt(np.mean((shifted[m] - q_ref[m]) ** 2))), int(m.sum())


def discover_delay(runs, *, nominal_lag_s: float, q_range=(-2.5e3, 8e3), fraction: float = 0.3,
                   min_extra_s: float = 0.03, min_abs_q_mm3_s: float = 500.0, seed: int = 0) -> DelayDiscovery | None:
    """Look for an extra flow delay in position-control runs.

    Parameters
    ----------
    runs : position-control :class:`~seanv_analysis.io.Run` objects
    nominal_lag_s : the model's flow delay [s]
    q_range : Q_ref range scored [mm^3/s]
    fraction : held-out tail of every run (time order)
    min_extra_s : smallest extra delay worth reporting [s]
    min_abs_q_mm3_s : held-out samples count only where |Q_ref| >= this
        (the valve is commanded open; during holds Q_ref = Kp e is not a
        flow the valve is asked for) [mm^3/s]

    Returns
    -------
    DelayDiscovery, or None when no run carries Q_ref.
    """
    from ..analysis.lag import estimate_lag_segments

    fit_segments, held = [], []
    for run in runs:
        sig = flow_signals(run)
        if sig is None:
            continue
        t, q_ref, q = sig
        cut = t[0] + (1.0 - fraction) * (t[-1] - t[0])
        f = t < cut
        fit_segments.append((t[f], q_ref[f], q[f]))
        held.append((t[~f], q_ref[~f], q[~f]))
    if not fit_segments:
        return None
    est = estimate_lag_segments(fit_segments, seed=seed)
    lag, ci = float(est.lag_s), est.ci95_s
    # held-out confirmation: the tails alone, never used for the estimate
    held_est = estimate_lag_segments(held, seed=seed + 1, n_boot=0)
    held_lag = float(held_est.lag_s)

    def pooled(lag_s):
        sq, n = 0.0, 0
        for t, q_ref, q in held:
            r, k = _shifted_rmse(t, q_ref, q, lag_s, q_range, min_abs_q_mm3_s)
            if k:
                sq += r * r * k
                n += k
        return math.sqrt(sq / n) if n else math.nan

    before, after = pooled(nominal_lag_s), pooled(lag)
    extra = lag - nominal_lag_s
    excludes = ci is not None and not (ci[0] <= nominal_lag_s <= ci[1])
    confirmed = (np.isfinite(held_lag) and np.sign(held_lag - nominal_lag_s) == np.sign(extra)
                 and abs(held_lag - nominal_lag_s) >= 0.5 * min_extra_s)
    finding = None
    if excludes and abs(extra) >= min_extra_s and confirmed:
        se = (ci[1] - ci[0]) / (2 * 1.959964)
        p = float(2 * special.ndtr(-abs(extra) / se)) if se > 0 else 0.0   # two-sided normal
        finding = EffectFinding("delay", "both", {"delay_s": extra},
                                {"delay_s": (ci[0] - nominal_lag_s, ci[1] - nominal_lag_s)},
                                p_value=p, f_p_value=p, evidence=DELAY_EVIDENCE)
    else:
        after = before   # nothing added: the model is unchanged
    msg = (f"flow lag {lag:.3f} s (95 % CI {ci[0]:.3f}..{ci[1]:.3f} s)" if ci else
           f"flow lag {lag:.3f} s (no interval)") + f" vs nominal {nominal_lag_s:.3f} s"
    return DelayDiscovery(finding, float(nominal_lag_s), lag, ci, len(fit_segments), before, after, msg)
