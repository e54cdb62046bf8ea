"""What the stages share: the context they run in, the per-run mapper, failed runs.

A stage is a module of this package; it declares itself once, and the
catalogue (:mod:`.catalogue`) finds it:

``NAME``         its name in pipelines and on the command line
``ORDER``        where it runs in a pipeline (stages run in increasing ``ORDER``)
``DESCRIPTION``  one line (``--list-stages``)
``NEEDS``        the stages whose results it reads ("ingest", "flowfit", ...)
``WRITES``       what :func:`write` puts in its output folder (for ``--list-stages``)
``FOLDER``       its folder under the output folder ("." for files directly in it)
``RESULTS``      the results it gives (:class:`Result`: name, type, JSON key; figures
                 and the report ask for results by name)
``SECTION``      optional: its section of the report (``report.ReportSection``)
``RECORD``       optional: {field of the pipeline record: attribute of its value}
``OPTIONS``      its options and their defaults (pipeline files are checked against them)
``check_option`` ``(key, value) -> value``: type check of one option, ValueError if bad
``run(ctx, options) -> result``   the work (a result object, never written by itself)
``write(result, folder) -> list[Path]``   its files, each written atomically
``expected(ds) -> bool``   optional: whether the data set would give its result
                 (a figure missing it is then worth a note)
``start_ahead(ctx, options)``   optional: start on the workers, without waiting,
                 the part of its work whose inputs exist already (called after
                 each stage that ends at least one stage before it; the
                 figures: :func:`.figures.start_ahead`)
``raw_inputs(ctx, options) -> [run folder]``   optional, a data-set stage: the runs
                 whose files it reads itself, beyond the per-run summary; the
                 batch runner then reuses its last value while its inputs are
                 unchanged (:mod:`seanv_analysis.batch.stage_memo`)
``ROLE``         optional, what the batch runner treats apart (:data:`.catalogue.ROLES`):
                 "reads_runs" (a data error in it ends the pipeline: there is no
                 data set; the workers are idle after it), "draws_figures" (the
                 workers warm matplotlib up for it), "report" (runs after the
                 manifest is written; its last output is the report, its
                 ``filename`` option a file the run owns)

Per-run work goes through :attr:`Context.map_runs`: in a notebook or a single
command it reads and processes the runs here (:func:`serial_map`); the batch
runner passes a mapper that runs the same functions in worker processes or
on a Dask cluster, with a per-run cache.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Protocol, Sequence

from ..config import RigConfig, load_rig
from ..errors import DataError, SeanvError
from ..io.outdir import check_out_dir
from ..io.validate import one_line
from ..models import ValveModel

__all__ = ["Context", "FailedRun", "RunOutcome", "RunMapper", "TaskMapper", "serial_map",
           "serial_tasks", "tasks_beside", "one_line",
           "with_path", "find_run_dirs", "one_blas_thread", "Result", "stage_info"]


@dataclass(frozen=True)
class Result:
    """One result a stage gives, by name: what figures' ``needs`` and the
    report ask for, ``PipelineResult[name]``, and its key in ``result.json``.

    Attributes
    ----------
    name : the result's name ("flowfit", "validation", ...)
    type : the class it is (for ``--list-stages`` and the docs)
    get : ``get(value, ctx) -> result`` from the stage's return value (None:
        the value itself; a result that is None is absent)
    json : recorded in ``result.json`` under ``name`` (``to_json_dict()``)
    module : the module that defines ``type`` (None: none to name): the
        figure workers import it while the analysis runs
        (:func:`~seanv_analysis.stages.figures.warm_figure_worker`), so a
        result sent to them is read without its imports (a ``Discovery``:
        ``seanv_analysis.discover`` with scipy.optimize, 0.5 s)
    """

    name: str
    type: str
    get: Callable[[Any, Any], Any] | None = None
    json: bool = True
    module: str | None = None

    def of(self, value: Any, ctx: Any = None) -> Any:
        """This result from a stage's return value (None when absent)."""
        if value is None:
            return None
        return value if self.get is None else self.get(value, ctx)


def with_path(path: str | Path, message: str) -> str:
    """``message`` prefixed with the run folder unless it names it already."""
    return message if str(path) in message else f"{path}: {message}"


@dataclass(frozen=True)
class FailedRun:
    """A run that could not be processed: its folder, the stage and one line why."""

    path: str
    stage: str
    message: str

    def to_json_dict(self) -> dict[str, str]:
        return {"path": self.path, "stage": self.stage, "message": self.message}


@dataclass(frozen=True)
class RunOutcome:
    """What a per-run function gave for one run folder: its value, or one line
    why it failed; ``hashes`` are {file name: SHA-256} of the files the run
    was read from; ``computed`` is False when the value came from a cache."""

    item: str
    ok: bool
    value: Any = None
    error: str = ""
    hashes: Mapping[str, str] = field(default_factory=dict)
    computed: bool = True


class RunMapper(Protocol):
    """Applies ``func(run, **kwargs)`` to the run read from each folder.

    ``stage`` names the work (progress bars, the cache); ``params`` are the
    options that change ``func``'s result (the cache key); ``valid`` tells
    whether a cached value can still be used (e.g. its figure files exist).
    """

    def __call__(self, stage: str, func: Callable[..., Any], run_dirs: Sequence[Path], *,
                 rig: RigConfig, params: Mapping[str, Any], kwargs: Mapping[str, Any],
                 valid: Callable[[Any], bool] | None = None) -> dict[str, RunOutcome]: ...


class TaskMapper(Protocol):
    """Applies ``func(item, **kwargs)`` to each item, independent tasks
    (figures, ...): ``[(ok, value or one-line error)]`` in the order of
    ``items``. The batch runner and the commands pass their executor's
    (worker processes or Dask); :func:`serial_tasks` runs them here."""

    def __call__(self, func: Callable[..., Any], items: Sequence[Any], *,
                 kwargs: Mapping[str, Any], desc: str = "") -> list[tuple[bool, Any]]: ...


def serial_tasks(func: Callable[..., Any], items: Sequence[Any], *,
                 kwargs: Mapping[str, Any], desc: str = "") -> list[tuple[bool, Any]]:
    """The :class:`TaskMapper` of a single process: each task in turn here;
    a task that raises a :class:`~seanv_analysis.errors.SeanvError` gives
    (False, its line), any other exception propagates."""
    out: list[tuple[bool, Any]] = []
    for item in items:
        try:
            out.append((True, func(item, **kwargs)))
        except SeanvError as exc:
            out.append((False, one_line(exc)))
    return out


def tasks_beside(ctx) -> TaskMapper | None:
    """The context's task mapper where its tasks run beside this process (more
    than one slot: the executor's workers), for a data-set stage to send its
    independent pieces of work to; None: they run here, as the stage's own
    code."""
    return ctx.map_tasks if getattr(ctx, "task_slots", 1) > 1 else None


def one_blas_thread():
    """Context in which the BLAS libraries numpy and scipy loaded use one
    thread (threadpoolctl), as the batch's worker processes and dask's do:
    for a process whose numpy is already loaded (why one thread:
    :func:`seanv_analysis.config.default_one_blas_thread`)."""
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=1, user_api="blas")


def serial_map(stage: str, func: Callable[..., Any], run_dirs: Sequence[Path], *,
               rig: RigConfig, params: Mapping[str, Any], kwargs: Mapping[str, Any],
               valid: Callable[[Any], bool] | None = None) -> dict[str, RunOutcome]:
    """The :class:`RunMapper` of a single process: each run read here (the
    next one on a helper thread while this one is processed), no cache."""
    from ..log import progress

    out: dict[str, RunOutcome] = {}
    for path, run in progress(_read_ahead(list(run_dirs), rig), total=len(run_dirs), desc=stage):
        key = str(path)
        if isinstance(run, SeanvError):
            out[key] = RunOutcome(key, False, error=with_path(path, one_line(run)))
            continue
        hashes = {os.path.basename(p): h for p, h in run.file_sha256.items()}  # file paths
        try:
            out[key] = RunOutcome(key, True, func(run, **kwargs), hashes=hashes)
        except SeanvError as exc:
            out[key] = RunOutcome(key, False, error=with_path(path, one_line(exc)), hashes=hashes)
    return out


def stage_info(msg: str) -> None:
    """INFO on the ``seanv_analysis.stages`` logger."""
    import logging

    logging.getLogger("seanv_analysis.stages").info(msg)


def _read_ahead(run_dirs: list[Path], rig: RigConfig):
    """(folder, Run or the SeanvError of reading it) in order; the next run is
    read on a helper thread (the reader parses without the GIL) while the
    caller works on this one."""
    from concurrent.futures import ThreadPoolExecutor

    from ..io.reader import read_run

    def read(path: Path):
        try:
            return read_run(path, rig=rig)
        except SeanvError as exc:
            return exc

    if not run_dirs:
        return
    with ThreadPoolExecutor(max_workers=1) as pool:
        pending = pool.submit(read, run_dirs[0])
        for i, path in enumerate(run_dirs):
            run = pending.result()
            if i + 1 < len(run_dirs):
                pending = pool.submit(read, run_dirs[i + 1])
            yield path, run


def find_run_dirs(data: Sequence[Path]) -> tuple[list[Path], dict[str, int]]:
    """Run folders under each data folder (sorted) and the index of the data
    folder each belongs to (runs of separately recorded data sets each start at
    use 0).

    Raises
    ------
    DataError
        a data folder is missing, or none holds a run.
    """
    from ..io.reader import find_runs

    run_dirs: list[Path] = []
    dataset_of: dict[str, int] = {}
    for i, d in enumerate(data):
        for p in find_runs(d):
            if str(p) not in dataset_of:
                dataset_of[str(p)] = i
                run_dirs.append(p)
    run_dirs.sort()
    if not run_dirs:
        raise DataError("no run.json found at any depth; expected a data set folder (sub-folders "
                        "holding run.json) or a run folder", path=data[0])
    return run_dirs, dataset_of


@dataclass
class Context:
    """What a stage runs with: the rig, the data, where outputs go, how per-run
    work is mapped, the valve model to start from (None: the rig config's
    where a stage needs one) and the results of the stages before it (by
    stage name); ``record`` is the batch runner's record of the whole run
    (what the report renders).

    Build one with :meth:`for_data`; a stage adds nothing to it itself: the
    caller stores each result with :meth:`add`.
    """

    rig: RigConfig
    data: list[Path]
    run_dirs: list[Path]
    dataset_of: dict[str, int] = field(default_factory=dict)
    out_dir: Path | None = None
    map_runs: RunMapper = serial_map
    start_model: ValveModel | None = None
    start_model_source: str = "rig config (paper's z0, C)"
    results: dict[str, Any] = field(default_factory=dict)
    loaded_runs: dict[str, Any] = field(default_factory=dict)  # {folder: Run} read in this process
    record: Any = None
    quiet: bool = True
    #: one plain line per step (default: INFO on the ``seanv_analysis.stages``
    #: logger, which prints nothing until logging is configured, as the CLI does)
    log: Callable[[str], None] = field(default_factory=lambda: stage_info)
    #: independent tasks of a data-set stage (the figures): here by default,
    #: on the run's executor (worker processes, Dask) in a command or ``run``
    map_tasks: TaskMapper = serial_tasks
    #: how many of ``map_tasks``' tasks run at once (the executor's workers;
    #: 1 here): the figures stage splits a figure's formats into tasks of
    #: their own when fewer figures than this are to be drawn
    task_slots: int = 1
    #: ``start_tasks(func, items, *, kwargs) -> started``: submits tasks to a
    #: background worker without waiting (``started.cancel_waiting()``, then
    #: ``started.results()``: what ``map_tasks`` would give, None for a task
    #: cancelled; ``batch.executor.Executor.start``); None here: a later
    #: stage then starts nothing ahead
    start_tasks: Callable[..., Any] | None = None
    #: work a later stage started ahead on the workers, by stage name
    #: (the figures whose inputs existed, drawn while the analysis went on)
    ahead: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def for_data(cls, data: str | Path | Sequence[str | Path], *, rig: RigConfig | str | Path | None = None,
                 out_dir: str | Path | None = None, model: ValveModel | None = None,
                 model_source: str | None = None, map_runs: RunMapper = serial_map,
                 quiet: bool = True, log: Callable[[str], None] | None = None) -> Context:
        """Context for a data set folder, a run folder, or several.

        Raises
        ------
        DataError
            a data folder is missing or holds no run; ``out_dir`` lies inside one.
        """
        if rig is None or isinstance(rig, (str, Path)):
            rig = load_rig(rig)
        datas = [Path(data)] if isinstance(data, (str, Path)) else [Path(d) for d in data]
        out = Path(out_dir) if out_dir is not None else None
        if out is not None:
            check_out_dir(out, data=datas, label="out_dir")
        run_dirs, dataset_of = find_run_dirs(datas)
        source = model_source or ("given model" if model is not None
                                  else "rig config (paper's z0, C)")
        return cls(rig, datas, run_dirs, dataset_of, out, map_runs, model, source,
                   quiet=quiet, log=log or stage_info)

    def add(self, name: str, result: Any) -> None:
        """Store a stage's result for the stages after it."""
        self.results[name] = result

    def result(self, name: str) -> Any:
        """The value of stage ``name``, or None when it did not run (or failed)."""
        return self.results.get(name)

    def result_named(self, name: str) -> Any:
        """The result called ``name`` (a :class:`Result` of some stage:
        "flowfit", "validation", "position_runs"...) from the stages run so
        far, the last stage giving it first; None when none has."""
        from .catalogue import STAGES

        for stage in reversed(list(STAGES)):
            if stage not in self.results:
                continue
            for res in STAGES[stage].RESULTS:
                if res.name == name:
                    value = res.of(self.results[stage], self)
                    if value is not None:
                        return value
        return None

    @property
    def plant_rig(self) -> RigConfig:
        """The rig the twin is simulated with: the identified one when the
        ``identify`` stage ran, else :attr:`rig`."""
        ident = self.results.get("identify")
        return ident.rig if ident is not None and ident.rig is not None else self.rig

    @property
    def model(self) -> ValveModel | None:
        """The valve model later stages use: ``identify``'s (refitted with the
        identified needle geometry) when it ran, else the flow fit's when it
        succeeded, else the one the context started with (None: none given)."""
        ident = self.results.get("identify")
        if ident is not None and ident.model is not None:
            return ident.model
        fit = self.results.get("flowfit")
        if fit is not None and getattr(fit, "success", False) and fit.model is not None:
            return fit.model
        return self.start_model

    @property
    def valve(self) -> ValveModel:
        """:attr:`model`, or the rig config's valve (the paper's z0, C) when none."""
        return self.model if self.model is not None else ValveModel.from_rig(self.rig)

    @property
    def model_source(self) -> str:
        ident = self.results.get("identify")
        if ident is not None and ident.model is not None:
            return "identify (this data set, identified needle geometry)"
        fit = self.results.get("flowfit")
        if fit is not None and getattr(fit, "success", False) and fit.model is not None:
            return "flowfit (this data set)"
        return self.start_model_source if self.start_model is not None \
            else "rig config (paper's z0, C)"
