"""Stages of the analysis, shared by the CLI commands and the pipeline runner.

Each stage is a module that declares itself once (``NAME``, ``ORDER``,
``FOLDER``, ``RESULTS``, ``run(ctx, options) -> value``, ``write(value,
folder) -> paths``...; see :mod:`.base`); :data:`STAGES` is the catalogue
of them (:mod:`.catalogue`), in the order a pipeline runs them
(``seanv-analyze run --list-stages`` prints it):

============  ===============================================================
``ingest``    read, validate, summarise every run; the paper's filters
``flowfit``   z0, C per side with 95 % intervals (eq. 3-5)
``identify``  the rig's unpublished constants (needle geometry, servo, friction,
              line) from its logs; later stages simulate the identified twin
``tracking``  flow delay and tracking RMSE of the position-control runs
``validate``  the controller re-run on the simulated plant, fit %
``discover``  residual -> missing effect -> refit, error before/after
``figures``   the registered figures (Fig. 4, 6, 7, discovery residuals, ...)
``report``    one self-contained report.html
============  ===============================================================

Every command, the batch runner and :func:`run_stages` run stages through
one path, :func:`execute`, on a pipeline checked like a pipeline file. The
stage modules are attributes of this package once the catalogue has found
them (``stages.flowfit.run(ctx, {})``).

Examples
--------
>>> from seanv_analysis.stages import run_stages
>>> ctx = run_stages("data/flow", ["ingest", "flowfit"])          # doctest: +SKIP
>>> print(ctx.result("flowfit").report())                         # doctest: +SKIP

or stage by stage:

>>> from seanv_analysis.stages import Context, dataset, flowfit   # doctest: +SKIP
>>> ctx = Context.for_data("data/flow")                           # doctest: +SKIP
>>> ctx.add("ingest", dataset.run(ctx, {}))                       # doctest: +SKIP
>>> fit = flowfit.run(ctx, {"n_boot": 100})                       # doctest: +SKIP
"""
from __future__ import annotations

from .base import (
    Context,
    FailedRun,
    Result,
    RunMapper,
    RunOutcome,
    TaskMapper,
    one_blas_thread,
    serial_map,
    serial_tasks,
)
from .catalogue import (
    STAGES,
    describe_stages,
    figures_reading,
    producers_of,
    report_sections,
    result_names,
    results_of,
    stage_names,
)
from .execute import execute, run_stages

__all__ = ["STAGES", "Context", "FailedRun", "Result", "RunMapper", "RunOutcome", "serial_map",
           "TaskMapper", "serial_tasks",
           "one_blas_thread", "describe_stages", "run_stages", "execute", "stage_names",
           "result_names", "results_of", "producers_of", "report_sections", "figures_reading"]
