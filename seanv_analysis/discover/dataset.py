"""Dataset-level entry point of discovery: read, summarise, filter, discover."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

from ..config import RigConfig, load_rig
from ..errors import DataError
from ..models import ValveModel
from .engine import discover_flow_steps
from .result import Discovery

__all__ = ["summarize_dataset", "discover_dataset", "DatasetSummary"]


@dataclass
class DatasetSummary:
    """Per-run summary of a data set (filters applied) plus the runs that failed."""

    summary: pd.DataFrame
    errors: list = field(default_factory=list)
    runs: list = field(default_factory=list)


def summarize_dataset(path: str | Path, *, rig: RigConfig | None = None,
                      keep_runs: bool = False) -> DatasetSummary:
    """Read every run of a data set, summarise it (per-run flow, dp) and filter.

    Bad runs are collected in ``errors`` (path, message); the rest go on.
    """
    from ..io.reader import read_dataset
    from ..derive import summarize_run
    from ..filters import apply_filters

    rig = rig or load_rig()
    read = read_dataset(path, rig=rig)
    rows = []
    for i, run in enumerate(read.runs):
        row = summarize_run(run)
        row["run_index"] = i
        rows.append(row)
    if not rows:
        raise DataError("no valid runs in the data set", path=path)
    summary = apply_filters(pd.DataFrame(rows), rig)
    return DatasetSummary(summary, list(read.errors), read.runs if keep_runs else [])


def discover_dataset(path: str | Path, *, model: ValveModel | None = None,
                     rig: RigConfig | None = None, holdout: str = "chrono",
                     seed: int = 0) -> tuple[Discovery, DatasetSummary]:
    """Discovery on a data set folder: flow-step runs drive the static model."""
    rig = rig or load_rig()
    ds = summarize_dataset(path, rig=rig)
    model = model or ValveModel.from_rig(rig)
    return discover_flow_steps(ds.summary, model=model, holdout=holdout, seed=seed), ds
