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
from ..stages import FailedRun
from ..stages.pipeline import (
                               STAGE_NAMES,
                               Pipeline,
                               Stage,
                               load_pipeline,
                               parse_pipeline,
                               shipped_pipelines,
                               stage_options,
)
from .cache import RunCache, run_key
from .executor import Executor, TaskResult, make_executor
from .runner import CachedMapper, PipelineResult, run_pipeline

__all__ = ["run_pipeline", "PipelineResult", "FailedRun", "Pipeline", "Stage", "load_pipeline",
           "parse_pipeline", "shipped_pipelines", "STAGE_NAMES", "stage_options", "Executor",
           "TaskResult", "make_executor", "RunCache", "run_key", "CachedMapper"]
