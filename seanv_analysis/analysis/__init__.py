"""Closed-loop analyses of position-control runs (paper Sec. III).

- :mod:`.lag`: delay of the actual behind the target flow (cross-correlation):
  :func:`estimate_lag`, :func:`estimate_lag_segments`, :class:`LagEstimate`.
- :mod:`.tracking`: flow tracking, delay compensation and RMSE (Fig. 7):
  :func:`tracking_runs`, :class:`Tracking`.
- :mod:`.validate`: re-running the controllers on the simulated plant and
  comparing with the measured runs: :func:`validate_runs`, :class:`Validation`.
- :mod:`.limitcycle`: a sustained oscillation's amplitude, period and mean
  error: :func:`limit_cycle`, :func:`compare_limit_cycles`, :class:`LimitCycle`.
"""
from .lag import LagEstimate, estimate_lag, estimate_lag_segments
from .limitcycle import LimitCycle, compare_limit_cycles, limit_cycle
from .tracking import RunTracking, Tracking, run_flows, tracking_runs
from .validate import RunValidation, Validation, fit_percent, validate_runs

__all__ = ["LagEstimate", "estimate_lag", "estimate_lag_segments", "RunTracking", "Tracking",
           "run_flows", "tracking_runs", "RunValidation", "Validation",
           "fit_percent", "validate_runs", "LimitCycle", "limit_cycle", "compare_limit_cycles"]
