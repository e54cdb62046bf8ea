"""Stages of the analysis, shared by the CLI commands and the pipeline runner.

Each stage is a module with ``NAME``, ``NEEDS``, ``WRITES``, ``OPTIONS``,
``DESCRIPTION``, ``check_option(key, value)``, ``run(ctx, options) -> result``
and ``write(result, folder) -> paths`` (see :mod:`.base`). :data:`STAGES`
lists them in the order a pipeline runs them:

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

from types import ModuleType

from . import dataset, discover, figures, flowfit, identify, report, tracking, validate
from .base import Context, FailedRun, RunMapper, RunOutcome, one_blas_thread, serial_map

__all__ = ["STAGES", "Context", "FailedRun", "RunMapper", "RunOutcome", "serial_map", "dataset",
           "flowfit", "identify", "tracking", "validate", "discover", "figures", "report", "describe_stages",
           "run_stages"]

#: {name: stage module}, in run order
STAGES: dict[str, ModuleType] = {m.NAME: m for m in (dataset, flowfit, identify, tracking,
                                                     validate, discover, figures, report)}


def describe_stages() -> str:
    """One paragraph per stage: name, what it does, needs, options, writes."""
    lines = []
    for name, mod in STAGES.items():
        lines.append(f"{name}: {mod.DESCRIPTION}")
        lines.append(f"  needs:   {', '.join(mod.NEEDS) or '(the run folders)'}")
        opts = ", ".join(f"{k}={v!r}" for k, v in mod.OPTIONS.items())
        lines.append(f"  options: {opts or '(none)'}")
        lines.append(f"  writes:  {', '.join(mod.WRITES)}")
    return "\n".join(lines)


def run_stages(data, names=("ingest", "flowfit"), *, rig=None, model=None,
               options: dict | None = None, map_runs: RunMapper = serial_map) -> Context:
    """Run stages in this process (nothing written) and return the context
    holding their results (``ctx.result("flowfit")``, ...): the notebook form
    of a pipeline. ``options``: {stage name: {option: value}}; ``model``: the
    valve model to start from (default: none, the rig's where one is needed).

    Raises
    ------
    DataError, FitError, ConfigError
        as the stages do; a stage that returns nothing (e.g. tracking without
        position-control runs) leaves no result.
    """
    ctx = Context.for_data(data, rig=rig, model=model, map_runs=map_runs)
    with one_blas_thread():
        for name in names:
            value = STAGES[name].run(ctx, (options or {}).get(name, {}))
            if value is not None:
                ctx.add(name, value)
    return ctx
