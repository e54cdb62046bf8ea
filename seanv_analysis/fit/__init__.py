"""Flow-model identification (paper Sec. II-C/D, eq. 3-5): ``fit_flow``.

- :func:`fit_flow` (per-run summary -> :class:`FlowFit`) and
- :class:`FlowFit`, :class:`SideFit`: parameters, 95 % intervals, per-run
  and per-load tables, ``fit.params["supply.C"]`` (:class:`Parameter`:
  value, stderr, ci95, as lmfit) and ``fit.eval(theta, dp, side)``, ``.report()``, ``.to_json_dict()`` (files are written by
  :mod:`seanv_analysis.stages.flowfit`).
"""
from .flowfit import PEAK_BIAS, PROCEDURES, UNITS, FlowFit, Parameter, SideFit, fit_flow

__all__ = ["FlowFit", "SideFit", "Parameter", "fit_flow", "PROCEDURES", "UNITS", "PEAK_BIAS"]
