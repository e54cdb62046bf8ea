"""Data-set stage: read every run, summarise it (per-run flow, dp) and filter.

One entry point shared by flowfit, discover, the batch pipeline and the
report, so they all see the same per-run numbers
(:data:`seanv_analysis.io.run.SUMMARY_COLUMNS`).
"""
from __future__ import annotations

import multiprocessing as mp
import os
from collections.abc import Collection
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

from .config import RigConfig, load_rig
from .errors import DataError, SeanvError

__all__ = ["DatasetSummary", "summarize_runs", "summarize_dataset", "dataset_errors",
           "AUTO_PARALLEL_MIN_RUNS"]


@dataclass
class DatasetSummary:
    """Per-run summary of a data set (filters applied), the runs that failed
    (:class:`seanv_analysis.io.RunError` or objects with a ``message``) and,
    when asked for, the validated runs themselves."""

    summary: pd.DataFrame
    errors: list = field(default_factory=list)
    runs: list = field(default_factory=list)
    path: Path | None = None

    @property
    def flow_steps(self) -> pd.DataFrame:
        return self.summary[self.summary["kind"] == "flow_step"]


#: data sets with at least this many runs are summarised on all cores when
#: ``workers`` is None (below it a process pool costs more than it saves)
AUTO_PARALLEL_MIN_RUNS = 64


def _summary_frame(rows: list[dict], rig: RigConfig) -> pd.DataFrame:
    from .signals.filters import apply_filters

    if not rows:
        return pd.DataFrame()
    frame = pd.DataFrame(rows)
    frame.insert(4, "run_index", range(len(frame)))
    return apply_filters(frame, rig)


def _summary_error(run, exc: SeanvError):
    """RunError of a run that could be read but not summarised: one line,
    prefixed with the run folder unless the message already names it."""
    from .io.reader import RunError

    msg = " ".join(str(exc).split())
    where = str(run.meta.path)
    return RunError(Path(where), msg if where in msg else f"{where}: {msg}")


def summarize_runs(runs, rig: RigConfig, *, method: str = "steady") -> tuple[pd.DataFrame, list]:
    """Summary rows of runs already read (in ``started_at`` order), filters applied.

    A run whose summary fails (e.g. no cam hold in a flow step) is dropped and
    reported in the returned error list; the others go on.
    """
    from .signals.derive import summarize_run

    rows, errors = [], []
    for run in runs:
        try:
            rows.append(summarize_run(run, method=method))
        except SeanvError as exc:
            errors.append(_summary_error(run, exc))
    return _summary_frame(rows, rig), errors


def _summarize_read(run, *, method: str, keep_kinds: frozenset[str], derive_all: bool = False):
    """One run (or the RunError of its reading): (row or None, read error or
    None, summary error or None, the run when its kind is kept, {file:
    SHA-256} of what was read). Errors are values, so a bad run never aborts
    the others. ``derive_all``: derive position-control runs too (their
    summary does not need it), so a run whose streams cannot be aligned is
    reported."""
    from .signals.derive import derive_samples, summarize_run
    from .io.reader import RunError

    if isinstance(run, RunError):
        return None, run, None, None, {}
    try:
        derived = derive_samples(run) if derive_all else None
        row, err = summarize_run(run, method=method, derived=derived), None
    except SeanvError as exc:
        row, err = None, _summary_error(run, exc)
    return row, None, err, (run if run.kind in keep_kinds else None), dict(run.file_sha256)


def _read_and_summarize(meta, *, rig: RigConfig, method: str, keep_kinds: frozenset[str],
                        derive_all: bool = False):
    """:func:`_summarize_read` of one run read here (a worker process's task)."""
    from .io.reader import read_run_tables

    return _summarize_read(read_run_tables(meta, rig), method=method, keep_kinds=keep_kinds,
                           derive_all=derive_all)


def summarize_dataset(path: str | Path, *, rig: RigConfig | None = None, method: str = "steady",
                      keep_runs: bool | Collection[str] = False,
                      workers: int | None = 1) -> DatasetSummary:
    """Read, summarise and filter every run of a data set folder.

    ``run_index`` is the 0-based position of a run in ``started_at`` order
    among the runs that could be read (the "use" count of drift effects).
    Runs are streamed: only the summary rows (and the runs asked for with
    ``keep_runs``) stay in memory.

    Parameters
    ----------
    keep_runs : keep the validated runs in ``DatasetSummary.runs``: True (all),
        False (none) or a collection of kinds (e.g. ``{"position_control"}``)
    workers : local processes reading and summarising runs; 1 (default) in
        this process; None: all cores for data sets of at least
        :data:`AUTO_PARALLEL_MIN_RUNS` runs. The result does not depend on it.

    Returns
    -------
    DatasetSummary
        ``errors``: runs that could not be read (sorted by path), then runs
        that could not be summarised (in time order).

    Raises
    ------
    DataError
        when no run of the data set could be read and summarised.
    """
    rig = rig or load_rig()
    rows, errors, runs = _collect(path, rig=rig, method=method, keep_runs=keep_runs,
                                  workers=workers)
    summary = _summary_frame(rows, rig)
    if summary.empty:
        raise DataError("no valid runs in the data set", path=path)
    return DatasetSummary(summary, errors, runs, Path(path))


def dataset_errors(path: str | Path, *, rig: RigConfig | None = None,
                   method: str = "steady") -> list:
    """The runs of a data set that cannot be read or summarised
    (:class:`seanv_analysis.io.RunError`, as :func:`summarize_dataset` lists
    them), without raising when none is usable: what a command says after
    it found nothing to work on. Every run is derived, position-control runs
    too."""
    return _collect(path, rig=rig or load_rig(), method=method, keep_runs=False, workers=1,
                    derive_all=True)[1]


def _collect(path, *, rig: RigConfig, method: str, keep_runs, workers: int | None,
             derive_all: bool = False):
    """(summary rows, errors, kept runs) of a data set: the work of
    :func:`summarize_dataset` before the filters. Errors: runs that could not
    be read (sorted by path), then runs that could not be summarised."""
    from .io.hashing import remember_sha256
    from .io.reader import RunError, dataset_plan, read_runs

    metas, read_errors, base = dataset_plan(path, rig=rig)
    keep = frozenset(("flow_step", "position_control") if keep_runs is True
                     else () if keep_runs is False else keep_runs)
    if workers is None:  # auto: never from inside a worker process (no nested pools)
        big = len(metas) >= AUTO_PARALLEL_MIN_RUNS and mp.parent_process() is None
        workers = (os.cpu_count() or 1) if big else 1
    kwargs = {"rig": base, "method": method, "keep_kinds": keep, "derive_all": derive_all}
    if workers > 1 and len(metas) > 1:
        from .batch.executor import make_executor

        with make_executor(workers=workers) as ex:
            results = ex.map(_read_and_summarize, metas, kwargs=kwargs, quiet=True)
        outcomes = []
        for r in results:
            if not r.ok:  # a bug or a dead worker: still one line for that run
                outcomes.append((None, RunError(r.item.path, r.error), None, None, {}))
                continue
            outcomes.append(r.value)
            for file, digest in r.value[4].items():  # the manifest reuses them
                remember_sha256(file, digest)
    else:  # this process, the next run read ahead on a thread
        outcomes = (_summarize_read(run, method=method, keep_kinds=keep, derive_all=derive_all)
                    for run in read_runs(metas, base))
    rows, summary_errors, runs = [], [], []
    for row, read_error, summary_error, run, _ in outcomes:
        if row is not None:
            rows.append(row)
        if read_error is not None:
            read_errors.append(read_error)
        if summary_error is not None:
            summary_errors.append(summary_error)
        if run is not None:
            runs.append(run)
    return rows, sorted(read_errors, key=lambda e: str(e.path)) + summary_errors, runs
