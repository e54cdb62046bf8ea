"""Stage ``validate``: free-run closed-loop validation of the valve model.

Each position-control run's controller (Kp, flow model on/off from run.json)
is re-run on the simulated plant with the same reference and load steps, and
simulated and measured position, flow and cam angle are compared (fit %,
RMSE, convergence, overshoot, settling:
:func:`seanv_analysis.analysis.validate.validate_run`). The simulation is the
costly part: one per-run task each, through the context's mapper.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

from ..errors import DataError
from ..jsonable import JsonResult
from ..report import ReportSection, sections
from .base import Context, FailedRun, Result, one_line, with_path

__all__ = ["NAME", "NEEDS", "WRITES", "OPTIONS", "ValidateResult", "check_option", "run", "write",
           "validate_model",
           "validate_one", "controller_numbers"]

NAME = "validate"
ORDER = 50
NEEDS = ("ingest",)
FOLDER = "validate"
RESULTS = (Result("validation", "Validation", get=lambda value, ctx: value.validation,
                   module="seanv_analysis.analysis.validate"),)
SECTION = ReportSection("validation", "Closed-loop validation", sections.validation_section)
WRITES = ("validate/validate.json", "validate/validate.txt", "validate/validate_table.parquet",
          "validate/validate_steps.parquet", "validate/validate_<run>.parquet")
DESCRIPTION = "re-run each position-control run's controller on the simulated plant; fit %"
#: threshold_pct: runs whose position fit is below it are flagged [%];
#: controller_model: the valve model inside the flow-model controller, the
#: rig config's ('rig', what the rig ran) or the identified one ('plant');
#: effects: effects the simulated plant has beside the valve model
#: (``models.effects`` specs, e.g. a model file's: ``validate --model``)
OPTIONS: dict[str, Any] = {"threshold_pct": 80.0, "controller_model": "rig", "effects": []}


#: what its code imports only when it runs (scipy.ndimage: the load
#: steps' onsets; pyarrow.parquet: the overlays' tables), imported
#: beside ingest (:func:`~seanv_analysis.stages.catalogue.stage_imports`)
IMPORTS = ("scipy.ndimage", "pyarrow.parquet")
def check_option(key: str, value: Any) -> Any:
    if key == "threshold_pct":
        if (not isinstance(value, (int, float)) or isinstance(value, bool)
                or not math.isfinite(value) or not 0 <= value <= 100):
            raise ValueError("a fit percentage between 0 and 100 (the NRMSE fit is at most 100 %)")
        return float(value)
    if key == "controller_model" and value not in ("rig", "plant"):
        raise ValueError("'rig' or 'plant'")
    if key == "effects":
        from ..models.effects import parse_effect

        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise ValueError("a list of effect specs such as \"backlash:width_deg=1.0\"")
        for spec in value:
            parse_effect(spec)   # its ValueError says what is wrong
        return list(value)
    return value


@dataclass(frozen=True)
class ValidateResult(JsonResult):
    """The validation of the position-control runs and the runs that failed."""

    validation: Any
    failed: tuple[FailedRun, ...] = ()

    def report(self) -> str:
        return self.validation.report()

    def skipped_runs(self) -> dict[str, str]:
        return self.validation.skipped_runs()

    def __repr__(self) -> str:
        return repr(self.validation)

    def to_frame(self):
        return self.validation.to_frame()

    def to_json_dict(self) -> dict[str, Any]:
        return self.validation.to_json_dict()


def validate_one(run, *, rig, model: Mapping[str, Any], effects: Sequence[str], seed: int,
                 threshold_pct: float, controller_model: str) -> dict[str, Any]:
    """Per-run function: :func:`~seanv_analysis.analysis.validate.validate_run`
    of one run with ``model`` (a :meth:`ValveModel.to_dict`, so the task and
    its cache key are plain data). A run that cannot be validated
    (DataError) is ``{'skipped': reason}``."""
    import warnings

    from ..analysis.validate import validate_run
    from ..models import ValveModel

    valve = ValveModel.from_dict(dict(model), rig=rig)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            rv = validate_run(run, valve, rig=rig, seed=seed, effects=tuple(effects),
                              threshold_pct=threshold_pct, controller_model=controller_model)
        rv.simulated = None  # the simulated run is large and not needed downstream
        return {"validation": rv, "notes": [f"{run.run_id}: {w.message}" for w in caught]}
    except DataError as exc:
        return {"skipped": one_line(exc), "run_id": run.run_id}


#: the metrics of a run's validation row (:func:`~seanv_analysis.analysis.validate.validate_run`)
_ROW_NUMBERS = ("kp_mm3_s_per_mm", "kp_deg_per_mm", "fit_position_pct", "rmse_position_mm",
                "fit_flow_pct", "rmse_flow_mm3_s", "fit_cam_pct", "rmse_cam_deg",
                "fit_position_segments_pct", "rmse_position_segments_mm", "fit_flow_segments_pct",
                "rmse_flow_segments_mm3_s", "n_segments", "steps", "converged_measured_frac",
                "converged_simulated_frac", "convergence_time_measured_s",
                "convergence_time_simulated_s", "overshoot_measured_mm", "overshoot_simulated_mm",
                "settling_measured_s", "settling_simulated_s")


def is_validation_entry(value: Any) -> bool:
    """A cached result of :func:`validate_one` has its shape (a malformed
    cache entry is recomputed, never used)."""
    import pandas as pd

    from ..analysis.validate import RunValidation
    from ..io.readback import conforms

    if conforms(value, {"skipped": str, "run_id": str}):
        return True
    row = {"run_id": str, "controller": ("flow_model", "cam").__contains__, "flagged": bool,
           **{k: (float, int) for k in _ROW_NUMBERS}}
    return conforms(value, {"validation": lambda v: (
        isinstance(v, RunValidation) and isinstance(v.run_id, str) and conforms(v.row, row)
        and all(isinstance(f, pd.DataFrame)
                for f in (v.steps_measured, v.steps_simulated, v.overlay))),
        "notes": [str]})


def position_paths(ctx: Context) -> list[Path]:
    ds = ctx.result("ingest")
    if ds is None:
        return []
    return [Path(p) for p in ds.kind("position_control")["path"].tolist()]


def validate_model(ctx: Context, model, effects: Sequence[str] = (), *, seed: int = 0,
                   options: Mapping[str, Any] | None = None, stage: str = NAME,
                   plant_overrides: Mapping[str, Any] | None = None):
    """Validation of every position-control run with ``model`` (and the
    simulator's ``effects``) on the context's twin (:attr:`Context.plant_rig`,
    with ``plant_overrides`` applied), and the runs that failed.

    Returns
    -------
    ValidateResult

    Raises
    ------
    DataError
        no position-control run could be validated.
    """
    import pandas as pd

    from ..analysis.validate import Validation

    base = {k: v for k, v in OPTIONS.items() if k != "effects"}   # effects: the argument
    opts = {**base, **{k: v for k, v in (options or {}).items() if k != "effects"}}
    paths = position_paths(ctx)
    plant = ctx.plant_rig
    ctx.log(f"{stage}: re-running the controller of {len(paths)} position-control run(s) on "
            "the simulated plant" + (f" with {', '.join(effects)}" if effects else ""))
    if plant_overrides:
        plant = plant.with_overrides(dict(plant_overrides), where="discover")
    params = {"model": model.to_dict(), "effects": list(effects), "seed": seed}
    if plant is not ctx.rig:      # the identified twin: part of the cache key
        params["plant_rig"] = plant.to_dict()
    if opts != base:
        params.update(opts)
    res = ctx.map_runs(stage, validate_one, paths, rig=ctx.rig, params=params,
                       kwargs={"rig": plant, "model": model.to_dict(),
                               "effects": tuple(effects),
                               "seed": seed, "threshold_pct": opts["threshold_pct"],
                               "controller_model": opts["controller_model"]},
                       valid=is_validation_entry)
    results, skipped, notes, failed = [], {}, [], []
    for p in paths:
        r = res[str(p)]
        if not r.ok:
            failed.append(FailedRun(str(p), stage, with_path(p, r.error)))
        elif "skipped" in r.value:
            skipped[r.value["run_id"]] = r.value["skipped"]
        else:
            results.append(r.value["validation"])
            notes += r.value.get("notes", [])
    if not results:
        why = next(iter(skipped.values()), "")
        raise DataError("no position_control run could be validated"
                        + (f" ({len(skipped)} skipped; first: {why})" if skipped else ""))
    table = pd.DataFrame([r.row for r in results])
    flagged = [r.run_id for r in results if r.row["flagged"]]
    return ValidateResult(Validation(table, flagged, float(opts["threshold_pct"]), results, skipped,
                                     notes, opts["controller_model"]), tuple(failed))


def run(ctx: Context, options: Mapping[str, Any]):
    """:class:`ValidateResult` of the context's model on the position-control
    runs; None when the data has none."""
    if not position_paths(ctx):
        return None
    options = dict(options)
    effects = options.pop("effects", [])
    return validate_model(ctx, ctx.valve, effects, options=options)


def write(result: ValidateResult, folder: Path) -> list[Path]:
    """validate.json, validate.txt, validate_table.parquet, validate_steps.parquet
    and ``validate_<run_id>.parquet`` (overlay data), atomically."""
    from ..io import write_json_atomic, write_table_parquet, write_text_atomic
    from ..io.names import safe_name

    validation = result.validation
    out = Path(folder)
    paths = [write_json_atomic(out / "validate.json", validation.to_json_dict()),
             write_text_atomic(out / "validate.txt", validation.report() + "\n")]
    if not validation.table.empty:
        paths.append(write_table_parquet(validation.table, out / "validate_table.parquet"))
    steps = validation.steps()
    if not steps.empty:
        paths.append(write_table_parquet(steps, out / "validate_steps.parquet"))
    for r in validation.runs:
        paths.append(write_table_parquet(r.overlay, out / f"validate_{safe_name(r.run_id)}.parquet"))
    return paths


def controller_numbers(validation) -> dict[str, dict[str, Any]] | None:
    """Mean closed-loop fit per controller of a validation (what the discovery
    result quotes before/after): {controller: {fit_position_pct,
    rmse_position_mm, fit_flow_pct, rmse_flow_mm3_s}} of whole runs, and the
    same of the per-segment re-runs (``*_segments_*``) when there are any."""
    if validation is None:
        return None
    doc = validation.to_json_dict()
    keys = ("fit_position_pct", "rmse_position_mm", "fit_flow_pct", "rmse_flow_mm3_s",
            "fit_position_segments_pct", "rmse_position_segments_mm", "fit_flow_segments_pct",
            "rmse_flow_segments_mm3_s")
    return {c: {k: row.get(k) for k in keys} for c, row in doc["by_controller"].items()}
