"""Stage ``discover``: residual -> missing effect -> refit, error before/after.

Flow-step runs drive the static model (eq. 5) and its candidate effects
(:func:`seanv_analysis.discover.discover_flow_steps`; every effect of the
registry in :mod:`seanv_analysis.models.effects`); position-control runs with
Q_ref the delay check against the nominal lag
(:func:`seanv_analysis.discover.dynamic.discover_delay`), or, when the
``identify`` stage ran, the dynamic candidates (delay, backlash) fitted on
the identified twin replaying the logged cam command
(:func:`seanv_analysis.identify.dynamic.closed_loop_effects`). When an effect is
found and the data holds position-control runs, the closed-loop check re-runs
them with the base and with the augmented model (the ``validate`` stage's
work) and the held-out error quoted is the closed-loop one.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

from ..errors import FitError, SeanvError
from ..jsonable import JsonResult
from .base import Context, FailedRun, one_line
from .dataset import position_runs
from .pipeline import MAX_SEED, check_count
from .validate import controller_numbers, position_paths, validate_model

__all__ = ["NAME", "NEEDS", "WRITES", "OPTIONS", "DiscoverResult", "check_option", "run", "write",
           "discover_runs", "MIN_FLOW_RUNS"]

NAME = "discover"
NEEDS = ("ingest",)
WRITES = ("discover/discover.json", "discover/model_augmented.json", "discover/discover.txt",
          "discover/validate_augmented/ (the closed-loop check)")
DESCRIPTION = "what the model misses: residual -> effect -> refit, held-out error before/after"
#: holdout: 'chrono' (the last 30 % of each side's runs) or 'kfold' (5 folds
#: by run); seed: of the permutation check
OPTIONS: dict[str, Any] = {"holdout": "chrono", "seed": 0}

#: fewest usable flow-step runs for the static discovery
MIN_FLOW_RUNS = 12


def check_option(key: str, value: Any) -> Any:
    if key == "holdout" and value not in ("chrono", "kfold"):
        raise ValueError("'chrono' or 'kfold'")
    if key == "seed":
        return check_count(value, most=MAX_SEED, what="a seed")
    return value


@dataclass(frozen=True)
class DiscoverResult(JsonResult):
    """The discovery, and when it ran, the closed-loop check: the validation
    of the position-control runs with the base model (``before``) and with
    the augmented one (``after``); ``note`` says why the check did not run."""

    discovery: Any
    before: Any = None
    after: Any = None
    note: str = ""
    failed: tuple[FailedRun, ...] = ()

    def report(self) -> str:
        return self.discovery.report()

    def to_json_dict(self) -> dict[str, Any]:
        return self.discovery.to_json_dict()

    def __repr__(self) -> str:
        return repr(self.discovery)

    def to_frame(self):
        return self.discovery.to_frame()

    def skipped_runs(self) -> dict[str, str]:
        """{run_id: why} of the position-control runs validate could not re-run."""
        return {} if self.before is None else dict(getattr(self.before, "skipped", {}))


def _usable_flow_steps(summary) -> int:
    if summary.empty:
        return 0
    ok = (summary["kind"] == "flow_step") & (summary["excluded"].fillna("") == "")
    return int(ok.sum())


def discover_runs(runs, summary, *, rig, model=None, holdout: str = "chrono",
                  nominal_lag_s: float | None = None, seed: int = 0, twin: bool = False):
    """Discovery on runs already read and summarised: the static candidates on
    the flow steps; on the position-control runs the delay check, or with
    ``twin`` (``rig`` is an identified twin: the ``identify`` stage ran) the
    dynamic effects fitted on it (open-loop replay of the logged cam command)
    (:func:`seanv_analysis.identify.dynamic.closed_loop_effects`).

    Raises
    ------
    FitError
        neither >= 12 usable flow-step runs nor a position-control run with Q_ref.
    """
    from ..discover import Discovery, discover_flow_steps
    from ..discover.dynamic import discover_delay
    from ..models import ValveModel

    model = model or ValveModel.from_rig(rig)
    analysis = rig.analysis
    lag0 = float(analysis.get("nominal_flow_lag_s", 0.25) if nominal_lag_s is None else nominal_lag_s)
    position = [r for r in runs if r.kind == "position_control"]
    if twin and position:
        return _closed_loop_dynamic(position, summary, rig=rig, model=model, holdout=holdout,
                                    seed=seed)
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
    if delay is None:
        return result
    change: dict[str, Any] = {"position_control": {**delay.to_json_dict(), "message": delay.message}}
    if delay.finding is not None:
        change["effects"] = [*result.effects, delay.finding]
        if result.verdict != "effect_found":
            change["verdict"], change["trend_variable"] = "effect_found", None
        if result.heldout_source == "position_control_shift":
            # the shift's held-out error, until the closed-loop check gives its own
            change["rmse_after_mm3_s"] = delay.rmse_after_mm3_s
    return dataclasses.replace(result, **change)


def _closed_loop_dynamic(position, summary, *, rig, model, holdout, seed):
    """Static discovery on the flow steps (if enough) plus the dynamic
    candidates fitted on the identified twin (logged cam command replayed); a dynamic effect
    found makes the held-out closed-loop flow RMSE the headline."""
    from ..discover import Discovery, EffectFinding, discover_flow_steps
    from ..identify import split_runs
    from ..identify.dynamic import closed_loop_effects

    analysis = rig.analysis
    train, held = split_runs(position)
    findings, base_held = closed_loop_effects(train, held, model, rig, seed=seed)
    named = [f for f in findings if f.named]
    if _usable_flow_steps(summary) >= MIN_FLOW_RUNS:
        result = discover_flow_steps(summary, model=model, holdout=holdout, seed=seed,
                                     leakage_mm3_s=float(analysis.get("leakage_flow_mm3_s", 50.0)))
    else:
        rmse = base_held.get("rmse_flow_mm3_s", float("nan"))
        result = Discovery(verdict="none", effects=[], n_heldout_runs=len(held),
                           rmse_before_mm3_s=rmse, rmse_after_mm3_s=rmse, trend_variable=None,
                           base_model=model, model=model,
                           holdout="position-control runs: every other one held out",
                           heldout_source="closed_loop_heldout")
    msg = "; ".join(f"{f.name} {f.param} {f.value:g} (p = {f.p_value:.2g}"
                    + (f", held-out flow RMSE {-f.replay_improvement:+.0%} replayed, "
                       f"{-f.heldout_improvement:+.0%} in closed loop" if f.heldout_before
                       else "") + ")" for f in findings)
    change: dict[str, Any] = {"position_control": {
        "method": ("dynamic effects fitted on the identified twin replaying the logged cam "
                   "command (open loop), checked on held-out runs replayed and re-run in "
                   "closed loop (each segment from the logged state; whole runs as free_*)"),
        "n_runs": len(position), "n_heldout_runs": len(held), "found": bool(named),
        "message": msg or "no candidate", "candidates": [f.to_json_dict() for f in findings],
        "heldout_twin": base_held}}
    for f in named:
        change["effects"] = [*result.effects, EffectFinding(
            f.name, "both", {f.param: f.value}, {f.param: f.ci95}, p_value=f.p_value,
            f_p_value=f.p_value, evidence=CLOSED_LOOP_EVIDENCE)]
        change["twin_overrides"] = {"tube": {"effective_bulk_modulus_mpa": f.bulk_mpa}}
        if result.verdict != "effect_found":
            # the headline: the held-out runs re-run in closed loop, each
            # segment from the logged state (the controller in the loop, no
            # hold's end carried into the next step); the replayed and the
            # whole-run numbers are in the candidates
            # (the replayed numbers when no held-out run could be re-run)
            closed = "rmse_flow_mm3_s" in f.heldout_before and "rmse_flow_mm3_s" in f.heldout_after
            before, after = (f.heldout_before, f.heldout_after) if closed else \
                (f.replay_before, f.replay_after)
            change.update(verdict="effect_found", trend_variable=None,
                          rmse_before_mm3_s=before["rmse_flow_mm3_s"],
                          rmse_after_mm3_s=after["rmse_flow_mm3_s"], n_heldout_runs=len(held),
                          heldout_source="closed_loop_heldout" if closed else "replay_heldout",
                          holdout="position-control runs: every other one held out")
    return dataclasses.replace(result, **change)


#: the report's clause on a dynamic effect found in closed loop
CLOSED_LOOP_EVIDENCE = ("fitted on the identified twin driven by the logged cam command "
                        "(training runs, p = {p_value:.2g}) and confirmed on held-out runs")


def closed_loop(ctx: Context, discovery) -> DiscoverResult:
    """The closed-loop check of a discovery: the position-control runs
    validated with the base model and with the augmented model and effects
    (a proposed closed-form term included: ``augmented_model_and_effects``)."""
    if not position_paths(ctx) or not (discovery.effects or discovery.proposed_term):
        return DiscoverResult(discovery)
    note = ""
    twin = getattr(discovery, "twin_overrides", None)
    try:
        augmented, specs = discovery.augmented_model_and_effects(ctx.plant_rig)
    except SeanvError as exc:
        note = f"effects not simulated in the closed-loop check: {one_line(exc)}"
        augmented, specs = discovery.model, []
    given = ctx.result("validate")
    try:
        before = given or validate_model(ctx, ctx.valve)
        after = validate_model(ctx, augmented, specs, stage="validate_augmented",
                               plant_overrides=twin)
    except SeanvError as exc:
        return DiscoverResult(discovery, note=("closed-loop check with the augmented model "
                                               f"failed: {one_line(exc)}"))
    checked = discovery.with_closed_loop(controller_numbers(before.validation),
                                         controller_numbers(after.validation))
    failed = (*(() if given else before.failed), *after.failed)
    return DiscoverResult(checked, before, after, note, failed)


def run(ctx: Context, options: Mapping[str, Any]) -> DiscoverResult:
    """Discovery on the data set, with the closed-loop check.

    Raises
    ------
    FitError
        too few usable runs (see :func:`discover_runs`).
    """
    opts = {**OPTIONS, **options}
    ds = ctx.result("ingest")
    ctx.log("discover: residual of the base model -> candidate effects -> held-out check")
    disc = discover_runs(position_runs(ctx), ds.summary, rig=ctx.plant_rig, model=ctx.valve,
                         holdout=opts["holdout"], seed=opts["seed"],
                         twin=ctx.result("identify") is not None)
    return closed_loop(ctx, disc)


def write(result: DiscoverResult, folder: Path) -> list[Path]:
    """discover.json, model_augmented.json, discover.txt (a paragraph for a
    lab note); the closed-loop check's validation with the augmented model
    under ``validate_augmented/``."""
    from ..io import write_json_atomic, write_text_atomic
    from . import validate

    out = Path(folder)
    disc = result.discovery
    paths = [write_json_atomic(out / "discover.json", disc.to_json_dict()),
             write_json_atomic(out / "model_augmented.json", disc.augmented_model_dict()),
             write_text_atomic(out / "discover.txt", disc.report() + "\n")]
    if result.after is not None:
        paths += validate.write(result.after, out / "validate_augmented")
    return paths
