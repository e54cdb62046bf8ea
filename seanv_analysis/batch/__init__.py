"""Batch processing: the stages of :mod:`seanv_analysis.stages` over whole data sets.

- :mod:`.executor`: map per-run tasks over serial / local processes / a
  dask.distributed cluster, errors collected per task, progress on stderr;
- :mod:`.cache`: per-run results keyed by content hashes, config and version
  (a re-run with nothing changed does no per-run work; a killed run resumes);
- :mod:`.tasks`: the per-run task the workers run (read, cache, compute);
- :mod:`.runner`: :func:`run_pipeline` -> :class:`PipelineResult`.

Pipeline files (stages and their options) are read by
:mod:`seanv_analysis.stages.pipeline`, re-exported here.
"""
from __future__ import annotations

import importlib
from typing import Any

#: public name -> the module that defines it, imported on first use (PEP 562),
#: so that importing a light submodule (process_setup, at every CLI start)
#: does not load the stages, pandas and scipy
_LAZY = {
    "FailedRun": "..stages",
    **{n: "..stages.pipeline" for n in ("STAGE_NAMES", "Pipeline", "Stage", "load_pipeline",
                                        "parse_pipeline", "shipped_pipelines", "stage_options")},
    "RunCache": ".cache", "run_key": ".cache",
    "Executor": ".executor", "TaskResult": ".executor", "make_executor": ".executor",
    "CachedMapper": ".runner", "PipelineResult": ".runner", "run_pipeline": ".runner",
}

__all__ = ["run_pipeline", "PipelineResult", "FailedRun", "Pipeline", "Stage", "load_pipeline",
           "parse_pipeline", "shipped_pipelines", "STAGE_NAMES", "stage_options", "Executor",
           "TaskResult", "make_executor", "RunCache", "run_key", "CachedMapper"]


def __getattr__(name: str) -> Any:
    if name not in _LAZY:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(_LAZY[name], __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
