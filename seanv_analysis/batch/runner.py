"""Run a pipeline on a data set: the stages of :mod:`seanv_analysis.stages` in
order, per-run work in parallel and cached per run, one record at the end.

A stage that fails on the data (e.g. too few runs to fit) is recorded in
:attr:`PipelineResult.stage_errors` and the later stages go on with what they
have (e.g. the rig's valve model). A bad run is listed and skipped.
"""
from __future__ import annotations

import json
import os
import sys
import time
import traceback
import warnings
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import pandas as pd

from .. import __version__
from ..config import RigConfig
from ..errors import ConfigError, DataError, OutputError, SeanvError
from ..io.atomic import atomic_folder, check_not_foreign, is_owned, remove_stale_temps, retire_folder
from ..io.outdir import check_out_dir, out_lock
from ..jsonable import JsonResult
from ..stages import STAGES, Context, FailedRun, RunOutcome, execute, one_blas_thread, results_of
from ..stages.base import stage_info
from ..stages.catalogue import has_role
from ..stages.pipeline import Pipeline, load_pipeline
from .cache import CACHE_DIRNAME, RunCache, run_key
from .executor import Executor, TaskResult, make_executor, one_line_error
from .memo import forget_run, pipeline_key, record_run, recorded_run
from .stage_memo import StageMemo
from .tasks import cached_run_task

__all__ = ["PipelineResult", "FailedRun", "run_pipeline", "CachedMapper", "owned_outputs"]

def stage_folder(name: str) -> str:
    """Where stage ``name`` writes, under the output folder (its ``FOLDER``):
    a stage with a folder of its own owns it: the folder is written anew and
    swapped in whole (:func:`_write_stage_folder`); "." means files directly
    in the output folder."""
    return STAGES[name].FOLDER


#: the files a run writes directly into the output folder (besides the report)
TOP_LEVEL_FILES = ("summary.parquet", "manifest.json", "result.json")


def owned_outputs(pipe: Pipeline) -> list[str]:
    """Names under the output folder that a run of ``pipe`` replaces,
    deletes or writes over: every stage folder (a stage's folder of an
    earlier pipeline may be retired), the per-run cache and the top-level
    files. No input may be or lie inside one of them
    (:func:`~seanv_analysis.io.outdir.check_out_dir`)."""
    report = [s.options.get("filename", "report.html") for s in pipe.stages
              if has_role(s.name, "report")]
    folders = sorted({m.FOLDER for m in STAGES.values() if m.FOLDER != "."})
    return [*folders, CACHE_DIRNAME, *TOP_LEVEL_FILES, *report]


@dataclass
class PipelineResult(JsonResult):
    """Everything a pipeline run produced.

    Attributes
    ----------
    pipeline : the pipeline that ran
    data : the data set folder(s)
    out_dir : output folder
    executor : back end used ('serial (1 process)', 'process pool (2 workers)', ...)
    runs_found : run folders found; ``runs_read`` of them were read and summarised
    summary : per-run summary (``SUMMARY_COLUMNS`` + ``path``), filters applied
    failed : runs that could not be read or processed (one line each)
    excluded : {reason: count} of the paper's filters (flow-step runs)
    results : {result name: result} of the stages that ran (the catalogue's
        ``RESULTS``: "flowfit", "validation", "discovery"...); the record is a
        mapping of them (``res["flowfit"]``, ``res.get("tracking")``), and
        ``res.flowfit`` reads the same (None when absent)
    figures : {figure name: [paths]}
    stage_errors : {stage: one-line error} of stages that failed on the data
    computed, cached : per-run tasks computed / taken from the cache, per stage
    timings_s : wall time per stage [s]
    outputs : files written
    input_hashes : {file path: SHA-256} of every input file of the runs read
    """

    pipeline: Pipeline
    data: list[Path]
    out_dir: Path
    executor: str = ""
    runs_found: int = 0
    runs_read: int = 0
    summary: pd.DataFrame = field(default_factory=pd.DataFrame)
    failed: list[FailedRun] = field(default_factory=list)
    excluded: dict[str, int] = field(default_factory=dict)
    model: Any = None
    results: dict[str, Any] = field(default_factory=dict)
    figures: dict[str, list[Path]] = field(default_factory=dict)
    stage_errors: dict[str, str] = field(default_factory=dict)
    stage_notes: dict[str, str] = field(default_factory=dict)
    computed: dict[str, int] = field(default_factory=dict)
    cached: dict[str, int] = field(default_factory=dict)
    timings_s: dict[str, float] = field(default_factory=dict)
    outputs: list[Path] = field(default_factory=list)
    input_hashes: dict[str, str] = field(default_factory=dict)
    rig: RigConfig | None = None
    command: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    report_path: Path | None = None
    manifest_path: Path | None = None
    manifest_created_utc: str | None = field(default=None, repr=False)
    #: the last run's result.json when this run reused it (``reuse=True``,
    #: nothing changed); the stage results are then None
    recorded: dict | None = field(default=None, repr=False)

    @classmethod
    def from_recorded(cls, pipe: Pipeline, ctx: Context, out: Path, doc: dict,
                      command: list[str]) -> "PipelineResult | None":
        """The result of a run that reused the last one (:mod:`.memo`): its
        numbers and paths from ``result.json``, no stage result objects;
        None when its ``summary.parquet`` cannot be read (the run then runs)."""
        r = cls(pipe, ctx.data, out, rig=ctx.rig, command=command, recorded=doc)
        r.executor = "none: nothing changed since the last run"
        r.runs_found, r.runs_read = int(doc["runs_found"]), int(doc["runs_read"])
        r.failed = [FailedRun(**f) for f in doc.get("failed", [])]
        r.excluded = dict(doc.get("excluded", {}))
        r.figures = {k: [Path(p) for p in v] for k, v in doc.get("figures", {}).items()}
        r.stage_errors = dict(doc.get("stage_errors", {}))
        r.stage_notes = {"reused": f"inputs, pipeline, rig and code unchanged since the last "
                                   f"run: its results in {out} are reused (--force recomputes)",
                         **doc.get("stage_notes", {})}
        r.outputs = [Path(p) for p in doc.get("outputs", [])]
        r.report_path = Path(doc["report"]) if doc.get("report") else None
        summary = out / "summary.parquet"
        if summary.is_file():
            from ..io.readback import regular_file_inside

            try:
                if not regular_file_inside(summary, out):
                    raise ValueError(f"{summary}: not a regular file")
                r.summary = pd.read_parquet(summary)
            except Exception:  # unreadable: the run is not reused, it runs
                return None
        return r

    def __getitem__(self, name: str) -> Any:
        """The result called ``name``; KeyError when no stage gave it."""
        return self.results[name]

    def get(self, name: str, default: Any = None) -> Any:
        return self.results.get(name, default)

    def __contains__(self, name: object) -> bool:
        return name in self.results

    def keys(self):
        return self.results.keys()

    def __getattr__(self, name: str) -> Any:
        """``res.flowfit``: a result of the catalogue by name (None when absent)."""
        if name.startswith("_") or name == "results":
            raise AttributeError(name)
        from ..stages import result_names

        if name in result_names():
            return self.results.get(name)
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    def __setattr__(self, name: str, value: Any) -> None:
        """``res.flowfit = fit`` keeps ``fit`` among the results (a result of
        the catalogue by name); any other attribute as usual."""
        from ..stages import result_names

        if name in result_names() and name not in self.__dataclass_fields__:
            if value is None:
                self.results.pop(name, None)
            else:
                self.results[name] = value
            return
        object.__setattr__(self, name, value)

    @property
    def success(self) -> bool:
        """True when every run was read and every stage succeeded."""
        return not self.failed and not self.stage_errors

    def summary_text(self) -> str:
        """The end-of-run summary: runs read, excluded by reason, failed with
        their one-line errors, stage problems, outputs written."""
        lines = [f"pipeline '{self.pipeline.name}' on {', '.join(str(d) for d in self.data)} "
                 f"[{self.executor}]"]
        kinds = {}
        if not self.summary.empty:
            kinds = self.summary["kind"].value_counts().to_dict()
        k = ", ".join(f"{n} {kind}" for kind, n in sorted(kinds.items()))
        lines.append(f"runs: {self.runs_found} found, {self.runs_read} read"
                     + (f" ({k})" if k else "") + f", {len(self.failed)} failed")
        comp = sum(self.computed.values())
        hit = sum(self.cached.values())
        if comp or hit:
            lines.append(f"per-run work: {comp} computed, {hit} from the cache ({self.out_dir / CACHE_DIRNAME})")
        ex = {r: n for r, n in self.excluded.items() if n}
        lines.append("excluded from the flow fit: " + (", ".join(f"{r}: {n}" for r, n in ex.items())
                                                       if ex else "none"))
        for name, msg in self.stage_notes.items():
            lines.append(f"note: {name}: {msg}")
        for name, msg in self.stage_errors.items():
            lines.append(f"stage {name} FAILED: {msg}")
        if self.failed:
            lines.append(f"{len(self.failed)} run(s) failed:")
            lines += [f"  [{f.stage}] {f.message}" for f in self.failed]
        shown = [p for p in self.outputs if p.suffix != ".svg"]
        lines.append(f"outputs ({len(self.outputs)} files) in {self.out_dir}:")
        lines += [f"  {p.relative_to(self.out_dir) if p.is_relative_to(self.out_dir) else p}"
                  for p in shown[:40]]
        if len(shown) > 40:
            lines.append(f"  ... {len(shown) - 40} more")
        if self.report_path:
            lines.append(f"report: {self.report_path}")
        return "\n".join(lines)

    def __repr__(self) -> str:
        return (f"<PipelineResult {self.pipeline.name}: {self.runs_read}/{self.runs_found} runs "
                f"read, {len(self.failed)} failed, {len(self.stage_errors)} stage errors; "
                f"out={self.out_dir}>")

    def skipped(self) -> list[dict[str, str]]:
        """Runs read but left out of a stage's result: run id, stage and why
        (the flow fit's filters, tracking's and validate's unusable runs)."""
        out = []
        seen = set()
        for stage, mod in STAGES.items():
            for res in mod.RESULTS:
                obj = self.results.get(res.name)
                fn = getattr(obj, "skipped_runs", None)
                if not res.json or res.name in seen or not callable(fn):
                    continue
                seen.add(res.name)
                out += [{"run_id": k, "stage": stage, "reason": v} for k, v in fn().items()]
        return out

    def to_json_dict(self) -> dict[str, Any]:
        """Numbers and paths as one JSON document (``result.json``)."""
        if self.recorded is not None:
            return {**self.recorded, "reused": True}

        def j(obj):
            return obj.to_json_dict() if obj is not None else None

        return {
            "schema": "seanv-pipeline-result/2",
            "version": __version__,
            "pipeline": self.pipeline.to_dict(),
            "data": [str(d) for d in self.data],
            "out": str(self.out_dir),
            "executor": self.executor,
            "runs_found": self.runs_found,
            "runs_read": self.runs_read,
            "failed": [f.to_json_dict() for f in self.failed],
            "skipped": self.skipped(),
            "excluded": self.excluded,
            **{name: j(self.results.get(name)) for name in json_results()},
            "figures": {k: [str(p) for p in v] for k, v in self.figures.items()},
            "stage_errors": self.stage_errors,
            "stage_notes": self.stage_notes,
            "computed": self.computed,
            "cached": self.cached,
            "timings_s": {k: round(v, 3) for k, v in self.timings_s.items()},
            "outputs": [str(p) for p in self.outputs],
            "report": str(self.report_path) if self.report_path else None,
        }


def json_results() -> list[str]:
    """The results recorded in ``result.json`` (each under its name), in run order."""
    return list(dict.fromkeys(r.name for m in STAGES.values() for r in m.RESULTS if r.json))


class CachedMapper:
    """The batch :class:`~seanv_analysis.stages.RunMapper`: per-run functions
    run by an executor (serial, local processes, Dask), each run's result
    cached by the content of its files, the stage and its parameters
    (``cache`` None: no cache, e.g. for a single command)."""

    def __init__(self, ex: Executor, cache: RunCache | None, *, force: bool = False,
                 quiet: bool = True):
        self.ex, self.cache, self.force, self.quiet = ex, cache, force, quiet
        self.computed: dict[str, int] = {}
        self.cached: dict[str, int] = {}

    def __call__(self, stage: str, func: Callable[..., Any], run_dirs: Sequence[Path], *,
                 rig: RigConfig, params: Mapping[str, Any], kwargs: Mapping[str, Any],
                 valid: Callable[[Any], bool] | None = None) -> dict[str, RunOutcome]:
        rig_dict = rig.to_dict()
        done: dict[str, RunOutcome] = {}
        todo: list[str] = []
        for d in run_dirs:
            hashes = None if self.force or self.cache is None else self.cache.known_hashes(d)
            if hashes is not None:
                key = run_key(hashes, stage=stage, params=dict(params), rig=rig_dict)
                hit = self.cache.get(key)
                if hit is not None and (valid is None or valid(hit)):
                    done[str(d)] = RunOutcome(str(d), True, hit, hashes=hashes, computed=False)
                    continue
                if hit is not None:
                    self.cache.reject(key, f"not what stage '{stage}' stores")
            todo.append(str(d))

        def on_result(res: TaskResult) -> None:
            if res.ok and self.cache is not None:
                self.cache.rejected += res.value.get("rejected", [])
                self.cache.remember(res.item, res.value["hashes"], res.value["stats"])
                self.cache.save_index()

        task_kwargs = {"func": func, "func_kwargs": dict(kwargs), "stage": stage,
                       "params": dict(params), "rig": rig,
                       "entries": None if self.cache is None else str(self.cache.entries),
                       "use_cache": not self.force, "valid": valid}
        try:
            for res in self.ex.map(cached_run_task, todo, kwargs=task_kwargs, desc=stage,
                                   quiet=self.quiet, on_result=on_result):
                done[res.item] = (RunOutcome(res.item, True, res.value["value"],
                                             hashes=res.value["hashes"],
                                             computed=res.value["computed"])
                                  if res.ok else RunOutcome(res.item, False, error=res.error))
        finally:  # also on Ctrl-C: what was done is found again next time
            if self.cache is not None:
                self.cache.save_index(force=True)
        self.computed[stage] = self.computed.get(stage, 0) + sum(
            1 for r in done.values() if r.ok and r.computed)
        self.cached[stage] = self.cached.get(stage, 0) + sum(
            1 for r in done.values() if r.ok and not r.computed)
        return done


def run_pipeline(pipeline: str | Path | Pipeline | Mapping[str, Any],
                 data: str | Path | Sequence[str | Path], *,
                 out_dir: str | Path, workers: int | None = None, scheduler: str | None = None,
                 force: bool = False, quiet: bool = False, rig: RigConfig | str | Path | None = None,
                 client: Any = None, log: Callable[[str], None] | None = None,
                 reuse: bool = False,
                 command: Sequence[str] | None = None) -> PipelineResult:
    """Run a pipeline on a data set and write its outputs.

    Parameters
    ----------
    pipeline : pipeline file, shipped name ('paper', 'flowfit', 'tracking'),
        a :class:`~seanv_analysis.stages.pipeline.Pipeline` or its dict
    data : data set folder (run folders at any depth), a run folder, or several
    out_dir : output folder (``<out>/.cache`` holds the per-run cache)
    workers : local processes for per-run work; 1 = serial in this process;
        None = the CPU count (or the dask cluster of ``DASK_SCHEDULER_ADDRESS``
        when that variable is set)
    scheduler : dask scheduler address ``tcp://host:port`` (per-run work
        runs on that cluster; it is not closed afterwards)
    force : ignore cached per-run results (they are recomputed and re-stored)
    quiet : no progress bars
    rig : rig config or rig TOML path (default: the shipped one)
    client : an existing ``dask.distributed.Client`` (never closed)
    log : called with one plain line per stage (default: INFO on the
        ``seanv_analysis.stages`` logger, printed where logging is configured:
        the CLI on a terminal, or with -v)
    command : command line for the manifest (default: ``sys.argv``)
    reuse : when nothing changed since the last successful run into
        ``out_dir`` (inputs' content, pipeline, rig, code, library versions;
        :mod:`.memo`) and its outputs are untouched, return its numbers from
        ``result.json`` without running (stage result objects None; what
        ``seanv-analyze run`` does). ``force`` runs anyway.

    Returns
    -------
    PipelineResult

    Raises
    ------
    ConfigError
        bad pipeline file or option, no dask scheduler at ``scheduler``.
    DataError
        ``data`` missing, holding no run, or no run could be read.

    Examples
    --------
    >>> res = run_pipeline("paper", "data/flow", out_dir="outputs/flow/run")  # doctest: +SKIP
    >>> print(res.summary_text())                                             # doctest: +SKIP
    """
    t_start = time.perf_counter()
    pipe = load_pipeline(pipeline)
    say = log or stage_info
    say(f"[{pipe.name}] {len(pipe.stages)} stage(s) on {', '.join(map(str, _as_list(data)))}")
    datas = [data] if isinstance(data, (str, Path)) else list(data)
    check_out_dir(out_dir, data=datas, owned=owned_outputs(pipe), label="out_dir",
                  files=[pipe.source, rig if isinstance(rig, (str, Path)) else None])
    for stage in pipe.stages:   # a folder of the user's where a stage folder goes: refused now
        if stage_folder(stage.name) != ".":
            check_not_foreign(Path(out_dir) / stage_folder(stage.name))
    ctx = Context.for_data(data, rig=rig, out_dir=out_dir, quiet=quiet, log=say)
    from ..models import ValveModel

    ctx.start_model = ValveModel.from_rig(ctx.rig)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    with out_lock(out):       # one run at a time in an output folder
        return _run_locked(pipe, ctx, out, command=command, reuse=reuse, force=force,
                           workers=workers, scheduler=scheduler, client=client, quiet=quiet,
                           say=say, t_start=t_start)


def _run_locked(pipe: Pipeline, ctx: Context, out: Path, *, command, reuse: bool, force: bool,
                workers, scheduler, client, quiet: bool, say, t_start: float) -> PipelineResult:
    """:func:`run_pipeline`'s work, the output folder held."""
    result = PipelineResult(pipe, ctx.data, out, rig=ctx.rig,
                            command=list(command) if command is not None else list(sys.argv))
    result.runs_found = len(ctx.run_dirs)
    ctx.record = result
    key = None
    if reuse:
        key = pipeline_key(pipe.to_dict(), ctx.rig.to_dict(), ctx.data, ctx.run_dirs)
        doc = None if force else recorded_run(out, key)
        reused = None if doc is None else PipelineResult.from_recorded(pipe, ctx, out, doc,
                                                                       result.command)
        if reused is not None:
            say(f"[{pipe.name}] nothing changed since the last run: reusing {out / 'result.json'}")
            return reused
    forget_run(out)  # this run replaces the outputs the memo describes
    cache = RunCache(out / CACHE_DIRNAME)
    removed = cache.removed_partial + remove_stale_temps(out, {m.FOLDER for m in STAGES.values()})
    if removed:
        result.stage_notes["resume"] = (f"removed {removed} partial temp file(s) or folder(s) "
                                        "left by an interrupted run")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with make_executor(workers=workers, scheduler=scheduler, client=client) as ex:
            result.executor = ex.describe()
            say(f"[{pipe.name}] {len(ctx.run_dirs)} run folder(s), executor: {result.executor}")
            mapper = CachedMapper(ex, cache, force=force, quiet=quiet)
            ctx.map_runs = mapper
            ctx.map_tasks = partial(ex.tasks, quiet=quiet)   # the figures, each a task
            ctx.task_slots = ex.slots     # > 1: identify's parts are tasks there too
            if ex.can_start:       # figures whose inputs exist start while the analysis runs
                ctx.start_tasks = ex.start
            from ..stages.catalogue import task_modules
            from ..stages.figures import figure_imports, figure_input_modules, warm_figure_worker

            worker_modules = figure_input_modules(pipe) + task_modules(pipe)
            ex.preload(worker_modules)    # the workers start with them (forked at ingest)
            warm = None
            if any(has_role(s.name, "draws_figures") for s in pipe.stages):
                warm = partial(ex.warm, partial(warm_figure_worker,
                                                worker_modules + figure_imports(pipe)))
            stages = StageMemo(out / CACHE_DIRNAME, enabled=not force)
            with one_blas_thread():     # the data-set stages, here (the workers have one)
                _run_stages(pipe, ctx, result, after_ingest=warm, run=stages.run)
            ctx.start_tasks = None      # the executor ends with this block
            result.computed, result.cached = mapper.computed, mapper.cached
            cache.save_index(force=True)
            rejected = cache.rejected + stages.rejected
            if rejected:
                n = len(rejected)
                result.stage_notes["cache"] = (
                    f"{n} malformed cache {'entry' if n == 1 else 'entries'} removed and "
                    f"recomputed (first: {rejected[0]})")
            if stages.reused:
                result.stage_notes["stage_cache"] = (
                    f"inputs unchanged since the last run: {', '.join(stages.reused)} "
                    f"reused from {out / CACHE_DIRNAME / 'stages'}")
        result.warnings += [f"{w.category.__name__}: {w.message}" for w in caught
                            if not issubclass(w.category, (DeprecationWarning, ResourceWarning))]
    result.model = ctx.model
    _retire_other_stages(pipe, out)
    _write_result(result, ctx, pipe, time.perf_counter() - t_start)
    if key is not None and result.success:
        record_run(out, key, result.outputs)
    return result


def _as_list(data) -> list:
    return [data] if isinstance(data, (str, Path)) else list(data)


def _run_stages(pipe: Pipeline, ctx: Context, result: PipelineResult, *,
                after_ingest: Callable[[], None] | None = None,
                run: Callable[..., Any] | None = None) -> None:
    """Each stage of ``pipe`` in order (:func:`~seanv_analysis.stages.execute`),
    timed and logged; a stage that fails on the data is recorded and the
    others go on; each value is recorded and written. ``after_ingest``:
    called once the runs are read (the workers are idle from then on while
    the data-set stages run here: they load matplotlib for the figures);
    ``run``: how a stage is run (:meth:`.stage_memo.StageMemo.run`)."""
    started: dict[str, float] = {}

    def start(name: str) -> None:   # the stage's lines: stages.execute
        if has_role(name, "report"):
            _write_manifest(result, ctx)
        started[name] = time.perf_counter()

    def finish(name: str) -> None:
        result.timings_s[name] = time.perf_counter() - started[name]

    def on_error(name: str, exc: BaseException) -> bool:
        if isinstance(exc, (ConfigError, OutputError, OSError)) or (
                isinstance(exc, DataError) and has_role(name, "reads_runs")):
            return False   # the pipeline or the output side: ends the run, one line
        _stage_failed(result, name, exc)   # a bug in one stage must not lose the others'
        finish(name)
        return True

    def done(name: str, value: Any) -> None:
        if has_role(name, "reads_runs") and after_ingest is not None:
            after_ingest()
        if value is None:
            result.stage_notes[name] = "no position-control runs in the data: skipped"
            _retire_stage_folder(result.out_dir, name)
        else:
            _record(result, name, value, ctx)
            for p in _write_stage(STAGES[name], value, result.out_dir):
                if p not in result.outputs:
                    result.outputs.append(p)
            if has_role(name, "report"):
                result.report_path = result.outputs[-1]
        finish(name)

    execute(pipe, ctx, start=start, on_error=on_error, done=done, run=run)


def _retire_other_stages(pipe: Pipeline, out: Path) -> None:
    """Remove the folders of the catalogue's stages this pipeline does not
    have that an earlier run (another pipeline) left in ``out``: only
    folders of this package's (the marker; a folder of the user's stays)."""
    ours = {s.name for s in pipe.stages}
    for name, mod in STAGES.items():
        if name not in ours and mod.FOLDER != "." and is_owned(out / mod.FOLDER):
            retire_folder(out / mod.FOLDER)


def _stage_failed(result: PipelineResult, name: str, exc: BaseException) -> None:
    """Record a stage that failed on the data; its folder (of an earlier run) goes."""
    result.stage_errors[name] = _error_line(exc)
    _retire_stage_folder(result.out_dir, name)


def _retire_stage_folder(out: Path, name: str) -> None:
    """Remove the folder of a stage that gave nothing this time, so no file of
    an earlier run stands beside this run's results."""
    if stage_folder(name) != ".":
        retire_folder(out / stage_folder(name))


def _write_stage(mod: Any, value: Any, out: Path) -> list[Path]:
    """Write a stage's files; a stage with a folder of its own gets it anew
    (written beside, then swapped in whole). Returns the final paths."""
    if mod.FOLDER == ".":
        return [Path(p) for p in mod.write(value, out)]
    return _write_stage_folder(mod, value, out / mod.FOLDER)


def _write_stage_folder(mod: Any, value: Any, folder: Path) -> list[Path]:
    """``mod.write`` into a temp folder beside ``folder``, then swapped in.

    Files the stage wrote into ``folder`` while it ran (figures drawn as they
    are made, per-run figures the cache knows by their final path) are moved
    into the new folder first, so they stay where the cache expects them;
    every other file of the old folder goes with it.
    """
    final: list[Path] = []
    with atomic_folder(folder) as tmp:
        for p in map(Path, mod.write(value, tmp)):
            if p in final or not p.is_file():
                continue  # listed twice, or nothing there to keep
            if p.is_relative_to(tmp):
                final.append(folder / p.relative_to(tmp))
            elif p.is_relative_to(folder):
                target = tmp / p.relative_to(folder)
                target.parent.mkdir(parents=True, exist_ok=True)
                os.replace(p, target)
                final.append(p)
            else:
                final.append(p)
    return final


def _record(result: PipelineResult, name: str, value: Any, ctx: Context) -> None:
    """Keep a stage's value in the record: its failed runs, its results by
    name (the catalogue's ``RESULTS``), the record fields it declares
    (``RECORD``) and its note."""
    mod = STAGES[name]
    result.failed += list(getattr(value, "failed", ()))
    result.failed.sort(key=lambda f: f.path)
    result.results.update(results_of(name, value, ctx, json_only=True))
    for fld, attr in getattr(mod, "RECORD", {}).items():
        new = getattr(value, attr)
        old = getattr(result, fld)
        if isinstance(old, dict):
            old.update({k: list(v) if isinstance(v, tuple) else v for k, v in new.items()})
        else:
            setattr(result, fld, new)
    note = getattr(value, "note", "")
    if isinstance(note, str) and note:
        result.stage_notes[name] = note


def _write_manifest(result: PipelineResult, ctx: Context, *, final: bool = False) -> None:
    """``manifest.json`` with the outputs so far: once before the report (which
    quotes it), then again at the end (``final``) listing every output."""
    from ..io.manifest import write_manifest

    if result.manifest_path is not None and not final:
        return
    extra = {"pipeline": result.pipeline.to_dict(),
             "pipeline_file": str(result.pipeline.source) if result.pipeline.source else None,
             "executor": result.executor, "runs_found": result.runs_found,
             "runs_read": result.runs_read, "failed": [f.to_json_dict() for f in result.failed],
             "excluded": result.excluded, "model_source": ctx.model_source}
    result.manifest_path = write_manifest(result.out_dir, config=ctx.rig, inputs=result.input_hashes,
                                          command=result.command, extra=extra,
                                          outputs=result.outputs,
                                          created_utc=result.manifest_created_utc)
    if result.manifest_created_utc is None:
        result.manifest_created_utc = json.loads(result.manifest_path.read_text())["created_utc"]
    if result.manifest_path not in result.outputs:
        result.outputs.append(result.manifest_path)


def _write_result(result: PipelineResult, ctx: Context, pipe: Pipeline, elapsed_s: float) -> None:
    from ..io.atomic import write_json_atomic

    path = result.out_dir / "result.json"
    if path not in result.outputs:
        result.outputs.append(path)
    _write_manifest(result, ctx, final=True)
    result.timings_s["total"] = elapsed_s
    write_json_atomic(path, result.to_json_dict())


def _error_line(exc: BaseException) -> str:
    """One line: the message, and for unexpected errors where they happened."""
    msg = one_line_error(exc)
    if not isinstance(exc, SeanvError):
        tb = traceback.extract_tb(exc.__traceback__)
        if tb:
            msg += f" (internal error at {Path(tb[-1].filename).name}:{tb[-1].lineno})"
    return msg
