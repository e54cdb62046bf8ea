"""Flow-model identification (paper Sec. II-C/D, eq. 3-5): ``fit_flow``.

- :func:`fit_flow` (per-run summary -> :class:`FlowFit`) and
- :class:`FlowFit`, :class:`SideFit`: parameters, 95 % intervals, per-run
  and per-load tables, ``fit.params["supply.C"]`` (:class:`Parameter`:
  value, stderr, ci95, as lmfit) and ``fit.eval(theta, dp, side)``,
  ``.report()``, ``.to_json_dict()`` (files are written by
  :mod:`seanv_analysis.stages.flowfit`);
- :class:`LeakageFit`: the needles' seat-leakage conductance fitted beside
  eq. (5), and the helpers ``identify`` and ``discover`` share with it
  (:func:`cluster_covariance`, :func:`soft_l1_weights`,
  :func:`prior_sd_mm3_s_per_mpa`, and :class:`SideRuns`: one side's flow
  steps for a fit of eq. (5) with the seat leakage, which ``identify``'s
  needle-geometry fit takes too), and :class:`Eq5Residual`: eq. (5)'s
  scaled residual on fixed runs with its analytic Jacobian in z0 and C.
"""
from ._joint import Eq5Residual
from ._leakage import (
    LeakageFit,
    SideRuns,
    cluster_covariance,
    prior_sd_mm3_s_per_mpa,
    soft_l1_weights,
)
from .flowfit import (
    LEAKAGE_MODES,
    PEAK_BIAS,
    PROCEDURES,
    UNITS,
    FlowFit,
    Parameter,
    SideFit,
    fit_flow,
)

__all__ = ["FlowFit", "SideFit", "Parameter", "LeakageFit", "fit_flow", "PROCEDURES",
           "LEAKAGE_MODES", "UNITS", "PEAK_BIAS", "cluster_covariance", "soft_l1_weights",
           "prior_sd_mm3_s_per_mpa", "SideRuns", "Eq5Residual"]
