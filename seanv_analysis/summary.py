"""Data-set stage: read every run, summarise it (per-run flow, dp) and filter.

One entry point shared by flowfit, discover, the batch pipeline and the
report, so they all see the same per-run numbers
(:data:`seanv_analysis.io.run.SUMMARY_COLUMNS`).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

from .config import RigConfig, load_rig
from .errors import DataError, SeanvError

__all__ = ["DatasetSummary", "summarize_runs", "summarize_dataset"]


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


def summarize_runs(runs, rig: RigConfig, *, method: str = "steady") -> tuple[pd.DataFrame, list]:
    """Summary rows of runs already read (in ``started_at`` order), filters applied.

    A run whose summary fails (e.g. no cam hold in a flow step) is dropped and
    reported in the returned error list; the others go on.
    """
    from .derive import summarize_run
    from .filters import apply_filters
    from .io.reader import RunError

    rows, errors = [], []
    for run in runs:
        try:
            row = summarize_run(run, method=method)
        except SeanvError as exc:
            errors.append(RunError(Path(run.meta.path), f"{run.meta.path}: {exc}"))
            continue
        rows.append(row)
    if not rows:
        return pd.DataFrame(), errors
    frame = pd.DataFrame(rows)
    frame.insert(4, "run_index", range(len(frame)))
    return apply_filters(frame, rig), errors


def summarize_dataset(path: str | Path, *, rig: RigConfig | None = None, method: str = "steady",
                      keep_runs: bool = False) -> DatasetSummary:
    """Read, summarise and filter every run of a data set folder.

    ``run_index`` is the 0-based position of a run in ``started_at`` order
    among the runs that could be read (the "use" count of drift effects).

    Raises
    ------
    DataError
        when no run of the data set could be read and summarised.
    """
    from .io.reader import read_dataset

    rig = rig or load_rig()
    read = read_dataset(path, rig=rig)
    summary, errors = summarize_runs(read.runs, rig, method=method)
    errors = list(read.errors) + errors
    if summary.empty:
        raise DataError("no valid runs in the data set", path=path)
    return DatasetSummary(summary, errors, read.runs if keep_runs else [], Path(path))
