"""Flow-model identification (paper Sec. II-C/D, eq. 3-5): ``fit_flow``.

- :func:`fit_flow` (per-run summary -> :class:`FlowFit`) and
  :func:`flowfit_dataset` (data set folder -> (FlowFit, DatasetSummary));
- :class:`FlowFit`, :class:`SideFit`: parameters, 95 % intervals, per-run
  and per-load tables, ``.report()``, ``.to_json()``, ``.write()``, ``.plot()``;
- :mod:`.synthetic`: summaries simulated at summary level with known truth.
"""
from .flowfit import PROCEDURES, UNITS, FlowFit, SideFit, fit_flow, flowfit_dataset

__all__ = ["FlowFit", "SideFit", "fit_flow", "flowfit_dataset", "PROCEDURES", "UNITS"]
