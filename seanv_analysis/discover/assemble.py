"""Discovery on a whole data set, assembled here: the static candidates on
the flow steps (:func:`.engine.discover_flow_steps`) and, on the
position-control runs, either the delay check against the nominal lag
(:func:`.dynamic.discover_delay`) or the dynamic candidates a twin search
fits (passed in by the caller: the package's is
:func:`seanv_analysis.identify.dynamic.closed_loop_effects`, fitted on the
identified twin replaying the logged cam command), in one
:class:`~.result.Discovery`. A plain result: no stage or identify type.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable, Sequence

from ..errors import FitError
from .result import Discovery, EffectFinding
from .split import split_position_runs

__all__ = ["discover_dataset", "MIN_FLOW_RUNS", "CLOSED_LOOP_EVIDENCE", "DynamicSearch"]

#: fewest usable flow-step runs for the static discovery
MIN_FLOW_RUNS = 12

#: ``search(train, held, model, rig, *, seed) -> (findings, base_heldout)``:
#: the dynamic candidates fitted on a twin of the rig (training runs) and
#: checked on held-out runs; each finding has ``name``, ``param``, ``value``,
#: ``ci95``, ``p_value``, ``named``, ``bulk_mpa``, the held-out and replayed
#: errors before/after and ``to_json_dict()``
DynamicSearch = Callable[..., tuple[Sequence[Any], dict]]

#: the report's clause on a dynamic effect found in closed loop
CLOSED_LOOP_EVIDENCE = ("fitted on the identified twin driven by the logged cam command "
                        "(training runs, p = {p_value:.2g}) and confirmed on held-out runs")


def _usable_flow_steps(summary) -> int:
    if summary.empty:
        return 0
    ok = (summary["kind"] == "flow_step") & (summary["excluded"].fillna("") == "")
    return int(ok.sum())


def discover_dataset(runs, summary, *, rig, model=None, holdout: str = "chrono",
                     nominal_lag_s: float | None = None, seed: int = 0,
                     dynamic_search: DynamicSearch | None = None) -> Discovery:
    """Discovery on runs already read and summarised: the static candidates on
    the flow steps; on the position-control runs the delay check, or with a
    ``dynamic_search`` (``rig`` is then the twin it searches on, e.g. the
    identified one) the dynamic effects it fits (:data:`DynamicSearch`).

    Raises
    ------
    FitError
        neither >= 12 usable flow-step runs nor a position-control run with Q_ref.
    """
    from ..models import ValveModel
    from .dynamic import discover_delay
    from .engine import discover_flow_steps

    model = model or ValveModel.from_rig(rig)
    analysis = rig.analysis
    lag0 = float(analysis.get("nominal_flow_lag_s", 0.25) if nominal_lag_s is None else nominal_lag_s)
    position = [r for r in runs if r.kind == "position_control"]
    if dynamic_search is not None and position:
        return _closed_loop_dynamic(position, summary, rig=rig, model=model, holdout=holdout,
                                    seed=seed, search=dynamic_search)
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


def _closed_loop_dynamic(position, summary, *, rig, model, holdout, seed, search: DynamicSearch):
    """Static discovery on the flow steps (if enough) plus the dynamic
    candidates fitted on the identified twin (logged cam command replayed); a dynamic effect
    found makes the held-out closed-loop flow RMSE the headline."""
    from .engine import discover_flow_steps

    analysis = rig.analysis
    train, held = split_position_runs(position)
    findings, base_held = search(train, held, model, rig, seed=seed)
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
