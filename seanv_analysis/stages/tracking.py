"""Stage ``tracking``: flow delay and tracking error of the position-control runs.

The actual flow is shifted by the delay behind Q_ref (given, e.g. the
paper's 0.25 s, or estimated per run), and the RMSE of actual - target is
taken over the samples whose target lies in the Q_ref range
(:func:`seanv_analysis.analysis.tracking.tracking_runs`; paper Sec. III-C:
0.25 s, 0.516e3 mm^3/s).
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Mapping

from ..report import ReportSection, sections
from .base import Context, Result
from .dataset import position_runs

__all__ = ["NAME", "NEEDS", "WRITES", "OPTIONS", "check_option", "run", "write"]

NAME = "tracking"
ORDER = 40
NEEDS = ("ingest",)
FOLDER = "tracking"
RESULTS = (Result("tracking", "Tracking", module="seanv_analysis.analysis.tracking"),)
SECTION = ReportSection("tracking", "Flow tracking during position control (Sec. III-C)",
                        sections.tracking_section, sections.tracking_cards)
WRITES = ("tracking/tracking.json", "tracking/tracking_details.json", "tracking/tracking.txt",
          "tracking/tracking_runs.parquet", "tracking/tracking_<run>.parquet")
DESCRIPTION = "flow delay behind Q_ref and tracking RMSE of the position-control runs"
#: shift_s: delay of the flow behind Q_ref [s], 0..MAX_SHIFT_S (None: estimated);
#: q_range: the Q_ref band of the RMSE [mm^3/s] (Fig. 7(b))
OPTIONS: dict[str, Any] = {"shift_s": None, "q_range": [-2.5e3, 8e3]}
#: what its code imports only when it runs (scipy.ndimage: the load
#: levels' median filter; pyarrow.parquet: the per-run tables), imported
#: beside ingest (:func:`~seanv_analysis.stages.catalogue.stage_imports`)
IMPORTS = ("scipy.ndimage", "pyarrow.parquet")
#: the largest delay a shift may compensate [s]: the paper's is 0.25 s; a
#: shift of seconds compares the flow with a target it never followed
#: (--shift 25 gave RMSE 1144 without a word)
MAX_SHIFT_S = 2.0


def check_option(key: str, value: Any) -> Any:
    if key == "shift_s" and value is not None:
        if (not isinstance(value, (int, float)) or isinstance(value, bool)
                or not 0 <= value <= MAX_SHIFT_S):
            raise ValueError(f"a delay in s from 0 to {MAX_SHIFT_S:g} (the paper's: 0.25; leave "
                             "it out to estimate it)")
        return float(value)
    if key == "q_range":
        if (not isinstance(value, list) or len(value) != 2
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                           and math.isfinite(v) for v in value) or value[0] >= value[1]):
            raise ValueError("[min, max] flow in mm^3/s with min < max")
        return [float(v) for v in value]
    return value


def expected(ds) -> bool:
    """The data set has position-control runs, so a tracking result was to be expected."""
    return not ds.kind("position_control").empty


def run(ctx: Context, options: Mapping[str, Any]):
    """:func:`~seanv_analysis.analysis.tracking.tracking_runs` on the
    position-control runs with the context's model; None when the data has none.

    Raises
    ------
    DataError
        no position-control run could be analysed.
    """
    from ..analysis.tracking import tracking_runs

    opts = {**OPTIONS, **options}
    runs = position_runs(ctx)
    if not runs:
        return None
    ctx.log(f"tracking: flow delay and tracking RMSE of {len(runs)} position-control run(s)")
    return tracking_runs(runs, shift_s=opts["shift_s"], q_range=tuple(opts["q_range"]),
                         model=ctx.model)


def write(result, folder: Path) -> list[Path]:
    """tracking.json, tracking_details.json, tracking.txt, tracking_runs.parquet
    and ``tracking_<run_id>.parquet`` (aligned target/actual per run)."""
    from ..io import write_json_atomic, write_table_parquet, write_text_atomic

    out = Path(folder)
    paths = [write_json_atomic(out / "tracking.json", result.to_json_dict()),
             write_json_atomic(out / "tracking_details.json", result.details()),
             write_text_atomic(out / "tracking.txt", result.report() + "\n")]
    if result.runs:
        paths.append(write_table_parquet(result.per_run, out / "tracking_runs.parquet"))
    for r in result.runs:
        paths.append(write_table_parquet(
            r.data, out / f"tracking_{r.run_id}.parquet",
            metadata={"run_id": r.run_id, "shift_s": r.shift_s,
                      "target_source": r.target_source}))
    return paths
