"""Run a pipeline on a data set: per-run work in parallel, data-set stages in
this process, results cached per run, one summary at the end.

Stages (in this order; a pipeline lists a subset):

``ingest``    read + validate + summarise every run (in parallel, cached);
              filters applied; ``summary.parquet``
``flowfit``   z0, C per side with 95 % intervals on the flow-step summary
              (``fit.fit_flow``); ``flowfit/``
``tracking``  flow delay and tracking RMSE of the position-control runs
              (``analysis.tracking.tracking_runs``); ``tracking/``
``validate``  free-run validation of the model on the position-control runs
              (``analysis.validate.validate_runs``); ``validate/``
``discover``  residual -> missing effect -> refit, error before/after on
              held-out runs (``discover.discover_flow_steps``); the
              position-control runs are validated again with the augmented
              model; ``discover/``
``figures``   Fig. 4 (flow fit), Fig. 6 (one per position-control run, in
              parallel), Fig. 7 (tracking), the discovery residuals; ``figures/``
``report``    one self-contained ``report.html``

A stage whose module is not installed is a :class:`ConfigError` naming it,
raised before any work. A stage that fails on the data (e.g. too few runs
to fit) is recorded in :attr:`PipelineResult.stage_errors` and the later
stages go on with what they have (e.g. the rig's valve model).
"""
from __future__ import annotations

import importlib
import inspect
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import pandas as pd

from .. import __version__
from ..config import RigConfig, load_rig
from ..errors import ConfigError, DataError, SeanvError
from .cache import CACHE_DIRNAME, RunCache, run_key
from .executor import Executor, TaskResult, make_executor, one_line_error
from .pipeline import Pipeline, load_pipeline

__all__ = ["PipelineResult", "FailedRun", "run_pipeline", "STAGE_REQUIREMENTS"]

#: What each stage needs from the package: (module, attribute) pairs.
STAGE_REQUIREMENTS: dict[str, tuple[tuple[str, str], ...]] = {
    "ingest": (("signals.derive", "summarize_run"), ("signals.filters", "apply_filters")),
    "flowfit": (("fit", "fit_flow"),),
    "tracking": (("analysis.tracking", "tracking_runs"),),
    "validate": (("analysis.validate", "validate_run"),),
    "discover": (("discover", "discover_flow_steps"),),
    "figures": (),
    "report": (("report", "write_report"),),
}

_FIGURE_MODULES = {4: ("plots.fig4", "plot_fig4"), 6: ("plots.fig6", "plot_fig6"),
                   7: ("plots.fig7", "plot_fig7")}


@dataclass(frozen=True)
class FailedRun:
    """A run that could not be processed: its folder, the stage and one line why."""

    path: str
    stage: str
    message: str

    def to_json(self) -> dict[str, str]:
        return {"path": self.path, "stage": self.stage, "message": self.message}


@dataclass
class PipelineResult:
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
    flowfit, tracking, validation, validation_augmented, discovery : the
        stage results (None when the stage did not run or failed)
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
    flowfit: Any = None
    tracking: Any = None
    validation: Any = None
    validation_augmented: Any = None
    discovery: Any = None
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

    @property
    def success(self) -> bool:
        """True when every run was read and every stage succeeded."""
        return not self.failed and not self.stage_errors

    def position_runs(self) -> pd.DataFrame:
        s = self.summary
        return s[s["kind"] == "position_control"] if not s.empty else s

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

    def to_json(self) -> dict[str, Any]:
        """Numbers and paths as one JSON document (``result.json``)."""
        def j(obj):
            return obj.to_json() if obj is not None and hasattr(obj, "to_json") else None

        return {
            "schema": "seanv-pipeline-result/1",
            "version": __version__,
            "pipeline": self.pipeline.to_dict(),
            "data": [str(d) for d in self.data],
            "out": str(self.out_dir),
            "executor": self.executor,
            "runs_found": self.runs_found,
            "runs_read": self.runs_read,
            "failed": [f.to_json() for f in self.failed],
            "excluded": self.excluded,
            "flowfit": j(self.flowfit),
            "tracking": j(self.tracking),
            "validation": j(self.validation),
            "validation_augmented": j(self.validation_augmented),
            "discovery": j(self.discovery),
            "figures": {k: [str(p) for p in v] for k, v in self.figures.items()},
            "stage_errors": self.stage_errors,
            "stage_notes": self.stage_notes,
            "computed": self.computed,
            "cached": self.cached,
            "timings_s": {k: round(v, 3) for k, v in self.timings_s.items()},
            "outputs": [str(p) for p in self.outputs],
            "report": str(self.report_path) if self.report_path else None,
        }


# helpers ----------------------------------------------------------------------

def _optional(module: str, name: str) -> Any | None:
    """``seanv_analysis.<module>.<name>`` or None when that module is absent."""
    try:
        mod = importlib.import_module(f"seanv_analysis.{module}")
    except ModuleNotFoundError as exc:
        if exc.name and (f"seanv_analysis.{module}".startswith(exc.name)):
            return None
        raise
    return getattr(mod, name, None)


def _require(pipeline: Pipeline) -> None:
    """ConfigError naming every stage whose code is not installed."""
    missing = []
    for stage in pipeline.stages:
        for module, name in STAGE_REQUIREMENTS.get(stage.name, ()):
            if _optional(module, name) is None:
                missing.append(f"stage '{stage.name}' needs seanv_analysis.{module}.{name}")
        if stage.name == "figures":
            for fig in stage.options["figs"]:
                module, name = _FIGURE_MODULES[fig]
                if _optional(module, name) is None:
                    missing.append(f"stage 'figures' (fig {fig}) needs seanv_analysis.{module}.{name}")
    if missing:
        src = pipeline.source or pipeline.name
        raise ConfigError(f"pipeline {src}: " + "; ".join(missing) + ", which this installation "
                          "lacks; remove the stage from the pipeline or update seanv-analysis")


def _call_kw(func: Callable, *args: Any, **kwargs: Any) -> Any:
    """Call ``func`` with only the keyword arguments its signature accepts."""
    try:
        params = inspect.signature(func).parameters
    except (TypeError, ValueError):
        return func(*args, **kwargs)
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
        return func(*args, **kwargs)
    return func(*args, **{k: v for k, v in kwargs.items() if k in params})


def _as_paths(obj: Any) -> list[Path]:
    if obj is None:
        return []
    if isinstance(obj, (str, Path)):
        return [Path(obj)]
    if isinstance(obj, dict):
        obj = obj.values()
    out = []
    for item in obj:
        out += _as_paths(item) if not isinstance(item, (str, Path)) else [Path(item)]
    return out


def _summary_frame(rows: list[dict[str, Any]], rig: RigConfig) -> pd.DataFrame:
    """Rows -> summary in ``started_at`` order with ``run_index`` and filters.

    ``run_index`` counts the runs of each data set given (``dataset``: its
    position in the ``data`` list) in ``started_at`` order, as
    :func:`seanv_analysis.summary.summarize_dataset` does for one data set:
    data sets recorded separately each start at use 0.
    """
    from ..signals.filters import apply_filters

    frame = pd.DataFrame(rows)
    frame["started_at"] = pd.to_datetime(frame["started_at"], utc=True)
    frame = frame.sort_values(["started_at", "run_id", "path"], kind="stable").reset_index(drop=True)
    frame.insert(4, "run_index", frame.groupby("dataset").cumcount().astype("int64"))
    return apply_filters(frame, rig)


class _Log:
    def __init__(self, log: Callable[[str], None] | None):
        self.log = log

    def __call__(self, msg: str) -> None:
        if self.log is not None:
            self.log(msg)


# the runner -------------------------------------------------------------------

def run_pipeline(pipeline: str | Path | Pipeline, data: str | Path | Sequence[str | Path], *,
                 out_dir: str | Path, workers: int | None = None, scheduler: str | None = None,
                 force: bool = False, quiet: bool = False, rig: RigConfig | str | Path | None = None,
                 client: Any = None, log: Callable[[str], None] | None = None,
                 command: Sequence[str] | None = None) -> PipelineResult:
    """Run a pipeline on a data set and write its outputs.

    Parameters
    ----------
    pipeline : pipeline file, shipped name ('paper', 'flowfit', 'tracking')
        or a :class:`Pipeline`
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
    log : called with one plain line per stage (e.g. ``print`` to stderr)
    command : command line for the manifest (default: ``sys.argv``)

    Returns
    -------
    PipelineResult

    Raises
    ------
    ConfigError
        bad pipeline file or option, a stage not installed, no dask
        scheduler at ``scheduler``.
    DataError
        ``data`` missing, holding no run, or no run could be read.

    Examples
    --------
    >>> res = run_pipeline("paper", "data/flow", out_dir="outputs/flow/run")  # doctest: +SKIP
    >>> print(res.summary_text())                                             # doctest: +SKIP
    """
    t_start = time.perf_counter()
    pipe = load_pipeline(pipeline)
    _require(pipe)
    if rig is None or isinstance(rig, (str, Path)):
        rig = load_rig(rig)
    datas = [Path(data)] if isinstance(data, (str, Path)) else [Path(d) for d in data]
    out = Path(out_dir)
    for d in datas:
        d_res, o_res = d.resolve(), out.resolve()
        if o_res == d_res or d_res in o_res.parents:
            raise DataError(f"out_dir: {out} is inside the data folder; outputs never go into raw "
                            "data: choose another output folder", path=d)
    from ..io.reader import find_runs

    run_dirs: list[Path] = []
    dataset_of: dict[str, int] = {}
    for i, d in enumerate(datas):
        for p in find_runs(d):
            if str(p) not in dataset_of:
                dataset_of[str(p)] = i
                run_dirs.append(p)
    run_dirs.sort()
    if not run_dirs:
        raise DataError("no run.json found at any depth; expected a data set folder (sub-folders "
                        "holding run.json) or a run folder", path=datas[0])
    out.mkdir(parents=True, exist_ok=True)
    say = _Log(log)
    result = PipelineResult(pipe, datas, out, rig=rig,
                            command=list(command) if command is not None else list(sys.argv))
    result.runs_found = len(run_dirs)
    cache = RunCache(out / CACHE_DIRNAME)
    if cache.removed_partial:
        result.stage_notes["resume"] = (f"removed {cache.removed_partial} partial temp file(s) "
                                        "left by an interrupted run")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with make_executor(workers=workers, scheduler=scheduler, client=client) as ex:
            result.executor = ex.describe()
            say(f"[{pipe.name}] {len(run_dirs)} run folder(s), executor: {result.executor}")
            ctx = _Context(pipe, result, cache, ex, rig, run_dirs, force=force, quiet=quiet, say=say)
            ctx.dataset_of = dataset_of
            for stage in pipe.stages:
                t0 = time.perf_counter()
                say(f"[{pipe.name}] stage {stage.name} ...")
                try:
                    getattr(ctx, f"stage_{stage.name}")(stage.options)
                except ConfigError:
                    raise
                except DataError:
                    if stage.name == "ingest":
                        raise
                    result.stage_errors[stage.name] = _error_line(sys.exc_info()[1])
                except Exception as exc:  # a bug in one stage must not lose the others' results
                    result.stage_errors[stage.name] = _error_line(exc)
                result.timings_s[stage.name] = time.perf_counter() - t0
                status = "FAILED: " + result.stage_errors[stage.name] \
                    if stage.name in result.stage_errors else "done"
                say(f"[{pipe.name}] stage {stage.name} {status} ({result.timings_s[stage.name]:.1f} s)")
            cache.save_index(force=True)
        result.warnings += [f"{w.category.__name__}: {w.message}" for w in caught
                            if not issubclass(w.category, (DeprecationWarning, ResourceWarning))]
    ctx.write_result(time.perf_counter() - t_start)
    return result


class _Context:
    """State shared by the stages of one pipeline run."""

    def __init__(self, pipe: Pipeline, result: PipelineResult, cache: RunCache, ex: Executor,
                 rig: RigConfig, run_dirs: list[Path], *, force: bool, quiet: bool, say: _Log):
        self.pipe, self.result, self.cache, self.ex, self.rig = pipe, result, cache, ex, rig
        self.run_dirs = run_dirs
        self.dataset_of: dict[str, int] = {}
        self.force, self.quiet, self.say = force, quiet, say
        self._runs: dict[str, Any] = {}
        from ..models import ValveModel

        self.model = ValveModel.from_rig(rig)
        self.model_source = "rig config (paper's z0, C)"

    # per-run machinery -------------------------------------------------------
    def _map_cached(self, stage: str, func: Callable, dirs: Sequence[Path], params: dict[str, Any],
                    task_kwargs: dict[str, Any], *, valid: Callable[[Any], bool] = lambda v: True
                    ) -> dict[str, TaskResult]:
        """Per-run results of ``func`` for every folder: from the cache when the
        folder's files are unchanged and the entry exists, else by a task."""
        rig_dict = self.rig.to_dict()
        done: dict[str, TaskResult] = {}
        todo: list[str] = []
        for d in dirs:
            hashes = None if self.force else self.cache.known_hashes(d)
            if hashes is not None:
                key = run_key(hashes, stage=stage, params=params, rig=rig_dict)
                hit = self.cache.get(key)
                if hit is not None and valid(hit):
                    done[str(d)] = TaskResult(str(d), {**hit, "hashes": hashes, "computed": False})
                    continue
            todo.append(str(d))

        def on_result(res: TaskResult) -> None:
            if res.ok:
                self.cache.remember(res.item, res.value["hashes"], res.value["stats"])
                self.cache.save_index()

        kwargs = {**task_kwargs, "entries": str(self.cache.entries), "use_cache": not self.force}
        try:
            for res in self.ex.map(func, todo, kwargs=kwargs, desc=stage, quiet=self.quiet,
                                   on_result=on_result):
                done[res.item] = res
        finally:  # also on Ctrl-C: what was done is found again next time
            self.cache.save_index(force=True)
        n_comp = sum(1 for r in done.values() if r.ok and r.value.get("computed"))
        self.result.computed[stage] = self.result.computed.get(stage, 0) + n_comp
        self.result.cached[stage] = self.result.cached.get(stage, 0) + sum(
            1 for r in done.values() if r.ok and not r.value.get("computed"))
        return done

    def _fail_stage(self, name: str, exc: BaseException) -> None:
        self.result.stage_errors[name] = one_line_error(exc)

    def _position_paths(self) -> list[str]:
        s = self.result.summary
        if s.empty or "path" not in s:
            return []
        return s.loc[s["kind"] == "position_control", "path"].tolist()

    def _position_runs(self) -> list[Any]:
        """The position-control runs, read once in this process (few, short)."""
        from ..io.reader import read_run

        runs = []
        for p in self._position_paths():
            if p not in self._runs:
                self._runs[p] = read_run(p, rig=self.rig)
            runs.append(self._runs[p])
        return runs

    def _write(self, path: Path) -> Path:
        self.result.outputs.append(Path(path))
        return Path(path)

    # stages ---------------------------------------------------------------------
    def stage_ingest(self, opts: dict[str, Any]) -> None:
        from ._tasks import ingest_task
        from ..signals.filters import exclusion_counts
        from ..io.writer import write_table_parquet

        method = opts["method"]
        res = self._map_cached("ingest", ingest_task, self.run_dirs, {"method": method},
                               {"rig": self.rig, "method": method})
        rows, seen = [], {}
        for d in self.run_dirs:
            r = res[str(d)]
            if not r.ok:
                self.result.failed.append(FailedRun(str(d), "ingest", _with_path(d, r.error)))
                continue
            row = {**r.value["row"], "path": str(d), "dataset": self.dataset_of.get(str(d), 0)}
            for name, sha in r.value.get("hashes", {}).items():
                self.result.input_hashes[str(Path(d) / name)] = sha
            rows.append((row, r.value.get("meta", {})))
        rows.sort(key=lambda rm: (pd.Timestamp(rm[0]["started_at"]), rm[0]["run_id"], rm[0]["path"]))
        kept = []
        for row, meta in rows:
            if row["run_id"] in seen:
                self.result.failed.append(FailedRun(row["path"], "ingest", (
                    f"{row['path']}/run.json: field 'run_id': '{row['run_id']}' is also the run id "
                    f"of {seen[row['run_id']]}; expected run ids unique in the data set")))
                continue
            seen[row["run_id"]] = row["path"]
            row["flow_model"] = (meta.get("controller") or {}).get("flow_model")
            kept.append(row)
        self.result.failed.sort(key=lambda f: f.path)
        self.result.runs_read = len(kept)
        if not kept:
            raise DataError("no run could be read; " + (self.result.failed[0].message
                                                         if self.result.failed else ""),
                            path=self.result.data[0])
        summary = _summary_frame(kept, self.rig)
        self.result.summary = summary
        self.result.excluded = exclusion_counts(summary)
        self._write(write_table_parquet(summary.drop(columns=["flow_model"]),
                                        self.result.out_dir / "summary.parquet",
                                        metadata={"pipeline": self.pipe.name}))

    def _need_summary(self) -> pd.DataFrame:
        if self.result.summary.empty:
            raise ConfigError(f"pipeline {self.pipe.source or self.pipe.name}: this stage needs "
                              "the per-run summary; add an 'ingest' stage first")
        return self.result.summary

    def stage_flowfit(self, opts: dict[str, Any]) -> None:
        fit_flow = _optional("fit", "fit_flow")
        summary = self._need_summary()
        folder = self.result.out_dir / "flowfit"
        try:
            fit = _call_kw(fit_flow, summary, self.rig, sides=tuple(opts["sides"]))
        except SeanvError as exc:
            self._fail_stage("flowfit", exc)
            return
        self.result.flowfit = fit
        if getattr(fit, "model", None) is not None and getattr(fit, "success", True):
            self.model = fit.model
            self.model_source = "flowfit (this data set)"
        self.result.model = self.model
        if hasattr(fit, "write"):
            written = fit.write(folder)
            for p in _as_paths(written):
                self._write(p)
        else:
            from ..io.atomic import write_json_atomic
            self._write(write_json_atomic(folder / "flowfit.json", fit.to_json()))

    def stage_tracking(self, opts: dict[str, Any]) -> None:
        tracking_runs = _optional("analysis.tracking", "tracking_runs")
        runs = self._position_runs()
        if not runs:
            self.result.stage_notes["tracking"] = "no position-control runs in the data: skipped"
            return
        try:
            tr = _call_kw(tracking_runs, runs, shift_s=opts["shift_s"],
                          q_range=tuple(opts["q_range"]), model=self.model)
        except SeanvError as exc:
            self._fail_stage("tracking", exc)
            return
        self.result.tracking = tr
        from ..io.atomic import write_json_atomic, write_text_atomic

        folder = self.result.out_dir / "tracking"
        if hasattr(tr, "write"):
            for p in _as_paths(tr.write(folder)):
                self._write(p)
        else:
            self._write(write_json_atomic(folder / "tracking.json", tr.to_json()))

    def _validate(self, model: Any, effects: Sequence[str] = ()) -> Any:
        """``analysis.validate`` on the position-control runs, one task per run
        (the free-run simulation is the costly part), assembled as
        ``validate_runs`` does."""
        from ..analysis.validate import DEFAULT_THRESHOLD_PCT, Validation
        from ._tasks import validate_task

        paths = [Path(p) for p in self._position_paths()]
        params = {"model": model.to_dict(), "effects": list(effects), "seed": 0}
        stage = "validate" if not effects else "validate_augmented"
        res = self._map_cached(stage, validate_task, paths, params,
                               {"rig": self.rig, "model": model.to_dict(),
                                "effects": tuple(effects), "seed": 0})
        results, skipped, notes = [], {}, []
        for p in paths:
            r = res[str(p)]
            if not r.ok:
                self.result.failed.append(FailedRun(str(p), stage, _with_path(p, r.error)))
            elif "skipped" in r.value:
                skipped[r.value["run_id"]] = r.value["skipped"]
            else:
                results.append(r.value["validation"])
                notes += r.value.get("notes", [])
        if not results:
            raise DataError("no position_control run could be validated"
                            + (f" ({len(skipped)} skipped)" if skipped else ""))
        table = pd.DataFrame([r.row for r in results])
        flagged = [r.run_id for r in results if r.row["flagged"]]
        return Validation(table, flagged, float(DEFAULT_THRESHOLD_PCT), results, skipped, notes)

    def stage_validate(self, opts: dict[str, Any]) -> None:
        if not self._position_paths():
            self.result.stage_notes["validate"] = "no position-control runs in the data: skipped"
            return
        try:
            val = self._validate(self.model)
        except SeanvError as exc:
            self._fail_stage("validate", exc)
            return
        self.result.validation = val
        from ..io.atomic import write_json_atomic, write_text_atomic

        for p in _as_paths(val.write(self.result.out_dir / "validate")):
            self._write(p)

    def stage_discover(self, opts: dict[str, Any]) -> None:
        discover = _optional("discover", "discover_flow_steps")
        summary = self._need_summary()
        try:
            from ..discover.dataset import discover_runs

            # flow steps from the summary; position-control runs (a few) are
            # read here for the delay check against the nominal lag
            disc = discover_runs(self._position_runs(), summary, rig=self.rig, model=self.model,
                                 holdout=opts["holdout"], seed=opts["seed"])
        except SeanvError as exc:
            self._fail_stage("discover", exc)
            return
        self.result.discovery = disc
        from ..io.atomic import write_json_atomic, write_text_atomic

        folder = self.result.out_dir / "discover"
        # closed loop: the position-control runs with the old and the augmented model
        if self._position_paths() and _optional("analysis.validate", "validate_run") is not None \
                and disc.effects:
            try:
                augmented, specs = self._augmented_model(disc)
                after = self._validate(augmented, specs)
                before = self.result.validation or self._validate(self.model)
                self.result.validation = before
                self.result.validation_augmented = after
                disc.validation = {"before": _validation_numbers(before),
                                   "after": _validation_numbers(after)}
                disc.use_closed_loop_heldout()
                for p in _as_paths(after.write(self.result.out_dir / "validate_augmented")):
                    self._write(p)
            except SeanvError as exc:
                self.result.stage_notes["discover"] = ("closed-loop check with the augmented "
                                                       f"model failed: {one_line_error(exc)}")
        self._write(write_json_atomic(folder / "discover.json", disc.to_json()))
        self._write(write_json_atomic(folder / "model_augmented.json", disc.augmented_model_dict()))
        self._write(write_text_atomic(folder / "discover.txt", disc.report() + "\n"))

    def _augmented_model(self, disc: Any) -> tuple[Any, list[str]]:
        """The refitted :class:`ValveModel` and the effects found as
        ``models.effects`` specs (what the simulator's plant takes)."""
        try:
            return disc.augmented_model_and_effects(self.rig)
        except SeanvError as exc:
            self.result.stage_notes["discover"] = (f"effects not simulated in the closed-loop "
                                                   f"check: {one_line_error(exc)}")
            return disc.model, []

    def stage_figures(self, opts: dict[str, Any]) -> None:
        folder = self.result.out_dir / "figures"
        figs = opts["figs"]
        problems = []

        def keep(name: str, paths: Any) -> None:
            ps = [p for p in _as_paths(paths) if p.suffix.lstrip(".") in opts["formats"] or
                  p.suffix not in (".png", ".svg")]
            for p in _as_paths(paths):
                self._write(p)
            self.result.figures.setdefault(name, []).extend(ps)

        if 4 in figs:
            if self.result.flowfit is not None:
                try:
                    keep("fig4", _optional("plots.fig4", "plot_fig4")(self.result.flowfit, folder))
                except Exception as exc:  # a figure must not sink the run
                    problems.append(f"fig 4: {one_line_error(exc)}")
            else:
                problems.append("fig 4: no flow fit (stage flowfit absent or failed)")
        if 6 in figs and self._position_paths():
            from ._tasks import fig6_task

            out6 = folder / "fig6"
            res = self._map_cached("fig6", fig6_task, [Path(p) for p in self._position_paths()],
                                   {"out_dir": str(out6), "formats": list(opts["formats"])},
                                   {"rig": self.rig, "out_dir": str(out6),
                                    "formats": tuple(opts["formats"])},
                                   valid=lambda v: all(Path(p).is_file() for p in v["paths"]))
            for d in self._position_paths():
                r = res[str(Path(d))]
                if r.ok:
                    keep("fig6", r.value["paths"])
                else:
                    problems.append(f"fig 6: {_with_path(d, r.error)}")
        if 7 in figs:
            if self.result.tracking is not None:
                try:
                    keep("fig7", _optional("plots.fig7", "plot_fig7")(self.result.tracking, folder))
                except Exception as exc:
                    problems.append(f"fig 7: {one_line_error(exc)}")
            elif self._position_paths():
                problems.append("fig 7: no tracking result (stage tracking absent or failed)")
        if self.result.discovery is not None:
            try:
                from ..plots.residuals import plot_discovery_residuals
                keep("discover", plot_discovery_residuals(self.result.discovery, out_dir=folder))
            except Exception as exc:
                problems.append(f"discovery residuals: {one_line_error(exc)}")
        if problems:
            self.result.stage_notes["figures"] = "; ".join(problems)

    def stage_report(self, opts: dict[str, Any]) -> None:
        write_report = _optional("report", "write_report")
        self._write_manifest()
        path = write_report(self.result, self.result.out_dir / opts["filename"])
        self.result.report_path = Path(path)
        self._write(Path(path))

    # provenance -------------------------------------------------------------------
    def _write_manifest(self) -> None:
        from ..manifest import write_manifest

        r = self.result
        if r.manifest_path is not None:
            return
        extra = {"pipeline": self.pipe.to_dict(),
                 "pipeline_file": str(self.pipe.source) if self.pipe.source else None,
                 "executor": r.executor, "runs_found": r.runs_found, "runs_read": r.runs_read,
                 "failed": [f.to_json() for f in r.failed], "excluded": r.excluded,
                 "model_source": self.model_source}
        r.manifest_path = write_manifest(r.out_dir, config=self.rig, inputs=r.input_hashes,
                                         command=r.command, extra=extra)
        if r.manifest_path not in r.outputs:
            r.outputs.append(r.manifest_path)

    def write_result(self, elapsed_s: float) -> None:
        from ..io.atomic import write_json_atomic

        self._write_manifest()
        self.result.timings_s["total"] = elapsed_s
        path = self.result.out_dir / "result.json"
        if path not in self.result.outputs:
            self.result.outputs.append(path)
        write_json_atomic(path, self.result.to_json())


def _with_path(path: str | Path, message: str) -> str:
    """``message`` prefixed with the run folder unless it names it already."""
    return message if str(path) in message else f"{path}: {message}"


def _error_line(exc: BaseException) -> str:
    """One line: the message, and for unexpected errors where they happened."""
    import traceback

    msg = one_line_error(exc)
    if not isinstance(exc, SeanvError):
        tb = traceback.extract_tb(exc.__traceback__)
        if tb:
            msg += f" (internal error at {Path(tb[-1].filename).name}:{tb[-1].lineno})"
    return msg


def _validation_numbers(val: Any) -> Any:
    """Mean closed-loop fit per controller [%] of a validation (for the
    discovery result): {controller: {fit_position_pct, fit_flow_pct, ...}}."""
    if val is None:
        return None
    doc = val.to_json() if hasattr(val, "to_json") else val
    if isinstance(doc, dict) and "by_controller" in doc:
        keys = ("fit_position_pct", "rmse_position_mm", "fit_flow_pct", "rmse_flow_mm3_s")
        return {c: {k: row.get(k) for k in keys} for c, row in doc["by_controller"].items()}
    return doc
