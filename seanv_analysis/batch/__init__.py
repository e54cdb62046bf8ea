"""Batch processing: declarative pipelines over whole data sets.

- :mod:`.pipeline`: pipeline TOML files (stages and their options);
- :mod:`.executor`: map per-run tasks over serial / local processes / a
  dask.distributed cluster, errors collected per task, progress on stderr;
- :mod:`.cache`: per-run results keyed by content hashes, config and version
  (a re-run with nothing changed does no per-run work; a killed run resumes);
- :mod:`.runner`: :func:`run_pipeline` -> :class:`PipelineResult`.
"""
from .cache import RunCache, run_key
from .executor import Executor, TaskResult, make_executor
from .pipeline import (STAGE_NAMES, STAGE_OPTIONS, Pipeline, Stage, load_pipeline,
                       parse_pipeline, shipped_pipelines)
from .runner import FailedRun, PipelineResult, run_pipeline

__all__ = ["run_pipeline", "PipelineResult", "FailedRun", "Pipeline", "Stage", "load_pipeline",
           "parse_pipeline", "shipped_pipelines", "STAGE_NAMES", "STAGE_OPTIONS", "Executor",
           "TaskResult", "make_executor", "RunCache", "run_key"]
