"""Stage ``ingest``: read, validate and summarise every run; the paper's filters.

The one path from run folders to the per-run summary that flowfit, tracking,
validate, discover, the figures and the report all read: each run is read
(checked against the data contract), its flow derived and summarised
(:func:`seanv_analysis.signals.derive.summarize_run`); the rows are put in
``started_at`` order with ``run_index`` (the "use" count of drift effects,
per data folder) and the filters applied (leakage |Q| <= 50 mm^3/s,
friction, cam range: :func:`seanv_analysis.signals.filters.apply_filters`).
A run that cannot be read or summarised is a :class:`FailedRun`; the others
go on.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import pandas as pd

from ..errors import DataError
from ..jsonable import JsonResult
from .base import Context, FailedRun, Result, with_path

__all__ = ["NAME", "NEEDS", "WRITES", "OPTIONS", "DatasetResult", "NoRunsRead", "check_option",
           "run", "collect",
           "summarize_runs", "summarize_derived",
           "write",
           "summarize", "summary_frame", "position_runs"]

NAME = "ingest"
ORDER = 10
NEEDS: tuple[str, ...] = ()
WRITES = ("summary.parquet",)
FOLDER = "."
ROLE = "reads_runs"
DESCRIPTION = "read, validate and summarise every run (per-run flow, dp); the paper's filters"
#: the data set's position-control runs, read once (figures draw them)
RESULTS = (Result("position_runs", "list[Run]", get=lambda value, ctx: position_runs(ctx) or None,
                  json=False),)
#: what the pipeline record keeps of the per-run summary
RECORD = {"summary": "summary", "excluded": "excluded", "runs_read": "runs_read",
          "input_hashes": "input_hashes"}
#: method: per-run flow estimate, 'steady' (robust) or the paper's 'peak';
#: derive: also align and derive the samples of the position-control runs, so
#: a run whose streams cannot be aligned fails here rather than later
OPTIONS: dict[str, Any] = {"method": "steady", "derive": False}


def check_option(key: str, value: Any) -> Any:
    if key == "method" and value not in ("steady", "peak"):
        raise ValueError("'steady' or 'peak'")
    if key == "derive" and not isinstance(value, bool):
        raise ValueError("true or false")
    return value


class NoRunsRead(DataError):
    """No run of the data set could be read: the ingest result (every bad run
    and why) rides along, so a command can list them."""

    def __init__(self, message: str, result: "DatasetResult", **kwargs):
        super().__init__(message, **kwargs)
        self.result = result


@dataclass(frozen=True)
class DatasetResult(JsonResult):
    """The per-run summary of a data set and what could not be read.

    Attributes
    ----------
    summary : one row per run read (``io.run.SUMMARY_COLUMNS`` + ``path``,
        ``dataset``, ``flow_model``), ``started_at`` order, filters applied
    failed : runs that could not be read or summarised, sorted by folder
    excluded : {reason: count} of the filters (flow-step runs)
    runs_found, runs_read : run folders found / read and summarised
    input_hashes : {file path: SHA-256} of every file of the runs read
    """

    summary: pd.DataFrame
    failed: tuple[FailedRun, ...] = ()
    excluded: Mapping[str, int] = field(default_factory=dict)
    runs_found: int = 0
    runs_read: int = 0
    input_hashes: Mapping[str, str] = field(default_factory=dict)
    #: the rig config the runs were read with (set by ``seanv_analysis.load_dataset``)
    rig: Any = field(default=None, repr=False, compare=False)
    #: the data folders read (set by ``seanv_analysis.load_dataset``: the
    #: notebook's commands take the result in place of the folders)
    folders: tuple = field(default=(), repr=False, compare=False)

    def to_frame(self) -> pd.DataFrame:
        """The per-run summary (one row per run read)."""
        return self.summary

    def plot(self, ax=None):
        """Steady flow of every flow-step run vs its commanded cam angle, the
        excluded ones hollow, on ``ax`` (a new pyplot figure when None)."""
        from ..plotting import plot

        return plot(self, ax)

    def __repr__(self) -> str:
        kinds = self.summary["kind"].value_counts().to_dict() if not self.summary.empty else {}
        k = ", ".join(f"{n} {kind}" for kind, n in sorted(kinds.items())) or "no runs"
        bad = f", {len(self.failed)} bad" if self.failed else ""
        return f"<DatasetResult {self.runs_read}/{self.runs_found} runs read ({k}){bad}>"

    def _repr_html_(self) -> str:
        bad = "".join(f"<li>{f.message}</li>" for f in self.failed)
        return (f"<p><b>{repr(self)[1:-1]}</b></p>"
                + (f"<p>bad runs:</p><ul>{bad}</ul>" if bad else "")
                + self.summary.head(20).to_html(max_cols=12))

    def kind(self, kind: str) -> pd.DataFrame:
        """Rows of one run kind ('flow_step', 'position_control')."""
        s = self.summary
        return s[s["kind"] == kind] if not s.empty else s.assign(path=[])

    def contract_table(self) -> pd.DataFrame:
        """The summary with exactly the data contract's columns
        (``io.run.SUMMARY_COLUMNS``), in order and typed: ``summary.parquet``
        of ``seanv-analyze ingest``."""
        from ..io.run import SUMMARY_COLUMNS

        df = self.summary.copy()
        for col, dtype in SUMMARY_COLUMNS.items():
            if col not in df:
                df[col] = ("" if dtype == "str" else 0 if dtype == "int64"
                           else False if dtype == "bool" else math.nan)
        df = df[list(SUMMARY_COLUMNS)]
        for col, dtype in SUMMARY_COLUMNS.items():
            if dtype == "str":
                df[col] = df[col].fillna("").astype(str)
            elif dtype == "bool":
                df[col] = df[col].fillna(False).astype(bool)
            elif dtype.startswith("datetime64"):
                df[col] = pd.to_datetime(df[col], utc=True).astype(dtype)
            else:
                df[col] = df[col].astype(dtype)
        return df.reset_index(drop=True)

    def report(self) -> str:
        kinds = self.summary["kind"].value_counts().to_dict() if not self.summary.empty else {}
        k = ", ".join(f"{n} {kind}" for kind, n in sorted(kinds.items()))
        ex = ", ".join(f"{r}: {n}" for r, n in self.excluded.items() if n) or "none"
        return (f"runs: {self.runs_found} found, {self.runs_read} read" + (f" ({k})" if k else "")
                + f", {len(self.failed)} failed\nexcluded from the flow fit: {ex}")

    def to_json_dict(self) -> dict[str, Any]:
        return {"runs_found": self.runs_found, "runs_read": self.runs_read,
                "excluded": dict(self.excluded), "failed": [f.to_json_dict() for f in self.failed]}

    def excluded_runs(self) -> dict[str, str]:
        """{run_id: why} of the flow-step runs the paper's filters exclude."""
        df = self.summary
        if df.empty or "excluded" not in df:
            return {}
        out = df[df["excluded"].fillna("").astype(str) != ""]
        col = "excluded_detail" if "excluded_detail" in out else "excluded"
        return dict(zip(out["run_id"].astype(str), out[col].astype(str)))

    def runs_json(self, *, failed: Sequence[FailedRun] = (),
                  skipped: Mapping[str, str] | None = None) -> dict[str, Any]:
        """The ``inputs`` block every command's ``--json`` carries: runs found
        and read, every failed run (its folder, the stage, why) and every run
        read but left out of the result (``skipped``: run id and why)."""
        return {"runs_found": int(self.runs_found), "runs_read": int(self.runs_read),
                "failed": [f.to_json_dict() for f in (*self.failed, *failed)],
                "skipped": [{"run_id": str(k), "reason": str(v)}
                            for k, v in (skipped or {}).items()]}


def summarize(run, *, method: str) -> dict[str, Any]:
    """Per-run function of the stage: the run's summary row and the metadata
    later stages need (its controller)."""
    from ..signals.derive import summarize_run

    meta = run.meta
    return {"row": summarize_run(run, method=method),
            "meta": {"path": str(Path(meta.path)), "run_id": meta.run_id, "kind": meta.kind,
                     "controller": dict(meta.controller or {})}}


def is_summary_entry(value: Any) -> bool:
    """A cached result of :func:`summarize` has its shape: the summary row
    with every column :func:`summarize_run` gives, typed, and the run's
    metadata (a malformed cache entry is recomputed, never used)."""
    from ..io.readback import conforms
    from ..io.run import SUMMARY_COLUMNS

    types = {"str": str, "bool": bool, "float64": (float, int),
             "datetime64[ns, UTC]": pd.Timestamp}
    row = {col: types[dtype] for col, dtype in SUMMARY_COLUMNS.items()
           if col not in ("run_index", "excluded", "excluded_detail")}
    return conforms(value, {"row": row, "meta": {"path": str, "run_id": str, "kind": str,
                                                 "controller": (dict, type(None))}})


def summarize_derived(run, *, method: str) -> dict[str, Any]:
    """:func:`summarize` of a run whose samples are derived first, position-control
    runs too (their summary does not need it), so a run whose streams cannot
    be aligned is a failed run here rather than later. A flow step's
    summary derives its samples itself (:func:`~seanv_analysis.signals.derive.summarize_run`,
    the same :func:`~seanv_analysis.signals.derive.derive_columns`): they
    are not derived twice."""
    from ..signals.derive import derive_columns

    if run.meta.kind != "flow_step":
        derive_columns(run)
    return summarize(run, method=method)


def summary_frame(rows: list[dict[str, Any]], rig) -> pd.DataFrame:
    """Rows -> summary in ``started_at`` order with ``run_index`` and filters.

    ``run_index`` counts the runs of each data folder (``dataset``: its
    position in the data list) in ``started_at`` order: data sets recorded
    separately each start at use 0.
    """
    from ..signals.filters import apply_filters

    frame = pd.DataFrame(rows)
    frame["started_at"] = pd.to_datetime(frame["started_at"], utc=True)
    frame = frame.sort_values(["started_at", "run_id", "path"], kind="stable").reset_index(drop=True)
    frame.insert(4, "run_index", frame.groupby("dataset").cumcount().astype("int64"))
    return apply_filters(frame, rig)


def run(ctx: Context, options: Mapping[str, Any]) -> DatasetResult:
    """Summarise every run of the context's data.

    Raises
    ------
    DataError
        no run could be read (the first bad run's line says why).
    """
    result = collect(ctx, options)
    if result.runs_read == 0:
        raise NoRunsRead("no run could be read; " + (result.failed[0].message if result.failed
                                                      else ""), result, path=ctx.data[0])
    return result


def collect(ctx: Context, options: Mapping[str, Any], *, func=None,
            kwargs: Mapping[str, Any] | None = None) -> DatasetResult:
    """:func:`run` without raising when no run is usable (empty summary): a
    command can then list every bad run. ``func``: per-run function in place
    of :func:`summarize` (same result, e.g. also writing the derived
    samples; module level, so the context's mapper can run it in worker
    processes), called with ``method`` and ``kwargs`` (also part of the
    cache key)."""
    from ..signals.filters import exclusion_counts

    method = options.get("method", OPTIONS["method"])
    derive = bool(options.get("derive", OPTIONS["derive"]))
    if func is None:
        func = summarize_derived if derive else summarize
    ctx.log(f"ingest: reading, checking and summarising {len(ctx.run_dirs)} run folder(s)")
    res = ctx.map_runs("ingest", func, ctx.run_dirs, rig=ctx.rig,
                       params={"method": method, **({"derive": True} if derive else {}),
                               **dict(kwargs or {})},
                       kwargs={"method": method, **dict(kwargs or {})}, valid=is_summary_entry)
    failed: list[FailedRun] = []
    hashes: dict[str, str] = {}
    rows = []
    for d in ctx.run_dirs:
        r = res[str(d)]
        if not r.ok:
            failed.append(FailedRun(str(d), "ingest", with_path(d, r.error)))
            continue
        row = {**r.value["row"], "path": str(d), "dataset": ctx.dataset_of.get(str(d), 0)}
        folder = Path(d)
        for name, sha in r.hashes.items():
            hashes[str(folder / name)] = sha
        rows.append((row, r.value.get("meta", {})))
    rows.sort(key=lambda rm: (pd.Timestamp(rm[0]["started_at"]), rm[0]["run_id"], rm[0]["path"]))
    kept, seen = [], {}
    for row, meta in rows:
        if row["run_id"] in seen:
            failed.append(FailedRun(row["path"], "ingest", (
                f"{row['path']}/run.json: field 'run_id': '{row['run_id']}' is also the run id "
                f"of {seen[row['run_id']]}; expected run ids unique in the data set")))
            continue
        seen[row["run_id"]] = row["path"]
        row["flow_model"] = (meta.get("controller") or {}).get("flow_model")
        kept.append(row)
    failed.sort(key=lambda f: f.path)
    if not kept:
        return DatasetResult(pd.DataFrame(), tuple(failed), {}, len(ctx.run_dirs), 0, hashes)
    summary = summary_frame(kept, ctx.rig)
    return DatasetResult(summary, tuple(failed), exclusion_counts(summary), len(ctx.run_dirs),
                         len(kept), hashes)


def write(result: DatasetResult, folder: Path) -> list[Path]:
    """``summary.parquet`` (the per-run summary, filters applied)."""
    from ..io.writer import write_table_parquet

    return [write_table_parquet(result.summary.drop(columns=["flow_model"]),
                                Path(folder) / "summary.parquet")]


def position_runs(ctx: Context) -> list:
    """The position-control runs of the data set, read once per context (few, short)."""
    from ..io.reader import read_run

    ds = ctx.result(NAME)
    if ds is None:
        return []
    cache = ctx.loaded_runs
    out = []
    for p in ds.kind("position_control")["path"].tolist():
        if p not in cache:
            cache[p] = read_run(p, rig=ctx.rig)
        out.append(cache[p])
    return out


def summarize_runs(runs, rig, *, method: str = "steady") -> tuple[pd.DataFrame, list[FailedRun]]:
    """Summary of runs already in memory (e.g. straight from the simulator), as
    :func:`run` makes it from folders: (summary, runs that could not be summarised)."""
    from ..errors import SeanvError
    from .base import one_line

    rows, failed = [], []
    for r in runs:
        path = str(r.meta.path) if r.meta.path is not None else r.run_id
        try:
            value = summarize(r, method=method)
        except SeanvError as exc:
            failed.append(FailedRun(path, NAME, with_path(path, one_line(exc))))
            continue
        rows.append({**value["row"], "path": path, "dataset": 0,
                     "flow_model": value["meta"]["controller"].get("flow_model")})
    return (summary_frame(rows, rig) if rows else pd.DataFrame()), failed
