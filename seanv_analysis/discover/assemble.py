"""Discovery on a whole data set, assembled here: the static candidates on
the flow steps (:func:`.engine.discover_flow_steps`, the needle geometry
decided with them) and, on the position-control runs, the dynamic
candidates a twin search fits on a twin of the rig identified from the same
data (passed in by the caller: the package's is
:func:`seanv_analysis.identify.dynamic.closed_loop_effects`, replaying the
logged cam command), in one :class:`~.result.Discovery`. No effect is named
against a rig file's nominal value. A plain result: no stage or identify type.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable, Sequence

from ..errors import FitError
from .result import Discovery, EffectFinding
from .split import split_position_runs

__all__ = ["discover_dataset", "MIN_FLOW_RUNS", "CLOSED_LOOP_EVIDENCE", "DynamicSearch", "NoTwin"]


class NoTwin(FitError):
    """A dynamic search found no twin of the rig to test effects on (the logs
    cannot tell its servo, say): the position-control runs are untested."""

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


def discover_dataset(runs, summary, *, rig, model=None, holdout: str = "chrono", seed: int = 0,
                     dynamic_search: DynamicSearch | None = None, twin_model=None,
                     twin_note: str = "") -> Discovery:
    """Discovery on runs already read and summarised: the static candidates
    on the flow steps (the needle geometry decided with them); on the
    position-control runs, the dynamic candidates ``dynamic_search`` fits on
    the twin ``rig`` (an identified one: a dynamic effect is only ever named
    against a twin the data identified, never against a rig file's nominal).
    Without a search (no twin could be identified) the position-control runs
    are said to be untested, with ``twin_note`` saying why.

    ``model``: the valve to start the static fit from (its geometry is the one
    the data's own is compared with: the rig file's); ``twin_model``: the
    twin's valve for the dynamic search (default: the static fit's model).

    Raises
    ------
    FitError
        neither >= 12 usable flow-step runs nor a position-control run.
    """
    from ..models import ValveModel
    from .engine import discover_flow_steps

    model = model or ValveModel.from_rig(rig)
    position = [r for r in runs if r.kind == "position_control"]
    n_steps = _usable_flow_steps(summary)
    if n_steps < MIN_FLOW_RUNS and not position:
        raise FitError(f"discover: {n_steps} usable flow_step runs (need >= {MIN_FLOW_RUNS}) and "
                       "no position_control run")
    result = None
    if n_steps >= MIN_FLOW_RUNS:
        result = discover_flow_steps(
            summary, model=model, holdout=holdout, seed=seed,
            leakage_mm3_s=float(rig.analysis.get("leakage_flow_mm3_s", 50.0)))
    if not position:
        return result
    if dynamic_search is None:
        note = {"n_runs": len(position), "found": False, "tested": False,
                "message": ("dynamic effects not tested: " + (twin_note or "no identified twin of "
                            "the rig to test them on"))}
        if result is None:
            return Discovery(verdict="none", effects=[], n_heldout_runs=0,
                             rmse_before_mm3_s=float("nan"), rmse_after_mm3_s=float("nan"),
                             trend_variable=None, base_model=model, model=model,
                             holdout="position-control runs: not tested",
                             heldout_source="closed_loop_heldout", position_control=note)
        return dataclasses.replace(result, position_control=note)
    valve = twin_model or (result.model if result is not None else model)
    try:
        return _closed_loop_dynamic(position, result, rig=rig, model=model, valve=valve,
                                    seed=seed, search=dynamic_search)
    except NoTwin as exc:
        return discover_dataset(runs, summary, rig=rig, model=model, holdout=holdout, seed=seed,
                                twin_note=str(exc)) if result is None else dataclasses.replace(
            result, position_control={"n_runs": len(position), "found": False, "tested": False,
                                      "message": f"dynamic effects not tested: {exc}"})


def changed_with_use(result) -> list[tuple[str, str]]:
    """(side, valve key) of each named static effect that moves a valve
    constant with use (a drift's C, a threshold shift's z0:
    ``Effect.CHANGES_WITH_USE``): the position-control runs, outside the
    flow-step sequence, set that constant's value for the dynamic search."""
    from ..models.effects import EFFECTS

    out = []
    for e in (result.effects if result is not None else ()):
        key = getattr(EFFECTS.get(e.name), "CHANGES_WITH_USE", None)
        if key and e.side in ("supply", "drain") and (e.side, key) not in out:
            out.append((e.side, key))
    return out


def _closed_loop_dynamic(position, result, *, rig, model, valve, seed, search: DynamicSearch):
    """The dynamic candidates fitted on the identified twin (logged cam
    command replayed) beside the static ``result`` (None: no flow steps); a
    dynamic effect found makes the held-out closed-loop flow RMSE the
    headline."""
    train, held = split_position_runs(position)
    findings, base_held = search(train, held, valve, rig, seed=seed,
                                 free_valve=changed_with_use(result))
    named = [f for f in findings if f.named]
    if result is None:
        rmse = base_held.get("rmse_flow_mm3_s", float("nan"))
        result = Discovery(verdict="none", effects=[], n_heldout_runs=len(held),
                           rmse_before_mm3_s=rmse, rmse_after_mm3_s=rmse, trend_variable=None,
                           base_model=model, model=valve,
                           holdout="position-control runs: every other one held out",
                           heldout_source="closed_loop_heldout")
    msg = "; ".join(f"{f.name} {f.param} {f.value:g} (p = {f.p_value:.2g}"
                    + (f", held-out flow RMSE {-f.replay_improvement:+.0%} replayed, "
                       f"{-f.heldout_improvement:+.0%} in closed loop" if f.heldout_before
                       else "")
                    + (f", its 95 % interval [{f.ci95[0]:.3g}, {f.ci95[1]:.3g}] holds 0"
                       if f.interval_holds_null else "") + ")" for f in findings)
    refit = findings[0].valve_refit if findings else []
    if refit:
        msg = findings[0].valve_refit_sentence() + "; " + (msg or "no candidate")
    change: dict[str, Any] = {"position_control": {
        "method": ("dynamic effects fitted on the identified twin replaying the logged cam "
                   "command (open loop), checked on held-out runs replayed and re-run in "
                   "closed loop (each segment from the logged state; whole runs as free_*)"),
        "n_runs": len(position), "n_heldout_runs": len(held), "found": bool(named),
        "message": msg or "no candidate", "candidates": [f.to_json_dict() for f in findings],
        "valve_at_position_runs": refit,
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
