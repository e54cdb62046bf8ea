"""Data-set entry points of discovery: flow-step runs drive the static model
(:mod:`.engine`), position-control runs the delay check (:mod:`.dynamic`)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..config import RigConfig, load_rig
from ..errors import FitError
from ..models import ValveModel
from ..summary import DatasetSummary, summarize_dataset, summarize_runs
from .dynamic import discover_delay
from .engine import discover_flow_steps
from .result import Discovery

__all__ = ["summarize_dataset", "discover_dataset", "discover_runs", "DatasetSummary"]

#: fewest usable flow-step runs for the static discovery
MIN_FLOW_RUNS = 12


def _usable_flow_steps(summary) -> int:
    if summary.empty:
        return 0
    ok = (summary["kind"] == "flow_step") & (summary["excluded"].fillna("") == "")
    return int(ok.sum())


def discover_runs(runs, summary, *, rig: RigConfig, model: ValveModel | None = None,
                  holdout: str = "chrono", nominal_lag_s: float | None = None,
                  seed: int = 0) -> Discovery:
    """Discovery on runs already read and summarised (see :func:`discover_dataset`).

    Raises
    ------
    FitError
        neither >= 12 usable flow-step runs nor a position-control run with Q_ref.
    """
    model = model or ValveModel.from_rig(rig)
    analysis = rig.analysis
    lag0 = float(analysis.get("nominal_flow_lag_s", 0.25) if nominal_lag_s is None else nominal_lag_s)
    position = [r for r in runs if r.kind == "position_control"]
    delay = discover_delay(position, nominal_lag_s=lag0, seed=seed) if position else None
    if _usable_flow_steps(summary) >= MIN_FLOW_RUNS:
        result = discover_flow_steps(summary, model=model, holdout=holdout, seed=seed,
                                     leakage_mm3_s=float(analysis.get("leakage_flow_mm3_s", 50.0)))
    elif delay is not None:
        result = Discovery(verdict="none", effects=[], n_heldout_runs=delay.n_runs,
                           rmse_before_mm3_s=delay.rmse_before_mm3_s,
                           rmse_after_mm3_s=delay.rmse_before_mm3_s, trend_variable=None,
                           base_model=model, model=model, holdout="chrono (last 30 % of each run)",
                           heldout_source="position_control_shift")
    else:
        raise FitError(f"discover: {_usable_flow_steps(summary)} usable flow_step runs (need "
                       f">= {MIN_FLOW_RUNS}) and no position_control run with q_ref_mm3_s")
    if delay is not None:
        result.position_control = {**delay.to_json(), "message": delay.message}
        if delay.finding is not None:
            result.effects.append(delay.finding)
            if result.verdict != "effect_found":
                result.verdict, result.trend_variable = "effect_found", None
            if result.heldout_source == "position_control_shift":
                # until validate replaces it (Discovery.use_closed_loop_heldout)
                result.rmse_after_mm3_s = delay.rmse_after_mm3_s
    return result


def discover_dataset(path: str | Path, *, model: ValveModel | None = None,
                     rig: RigConfig | None = None, holdout: str = "chrono",
                     nominal_lag_s: float | None = None, seed: int = 0,
                     workers: int | None = None) -> tuple[Discovery, DatasetSummary]:
    """Discovery on a data set folder.

    Flow-step runs: the static model (eq. 5) and its candidate effects
    (drift, threshold_shift, backlash, pressure_law, saturation,
    sensor_gain); position-control runs with Q_ref: the ``delay`` check
    against the nominal lag (rig ``analysis.nominal_flow_lag_s``).
    ``workers``: processes reading the runs
    (:func:`seanv_analysis.summary.summarize_dataset`; None: all cores for
    large data sets). The returned summary's ``runs`` are the
    position-control runs (what ``validate`` re-runs for the closed-loop
    error before/after).
    """
    rig = rig or load_rig()
    ds = summarize_dataset(path, rig=rig, keep_runs={"position_control"}, workers=workers)
    result = discover_runs(ds.runs, ds.summary, rig=rig, model=model, holdout=holdout,
                           nominal_lag_s=nominal_lag_s, seed=seed)
    return result, ds
