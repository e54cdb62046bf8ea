"""Stage ``discover``: residual -> missing effect -> refit, error before/after.

Flow-step runs drive the static model (eq. 5) and its candidate effects
(:func:`seanv_analysis.discover.discover_flow_steps`; every effect of the
registry in :mod:`seanv_analysis.models.effects`), the needle geometry
decided with them; position-control runs the dynamic candidates (delay,
backlash) fitted on a twin of the rig identified from the same logs (the
``identify`` stage's, or one identified here: servo, controller, friction,
load regulator, line), replaying the logged cam command
(:func:`seanv_analysis.identify.dynamic.closed_loop_effects`); never against
the rig file's nominal values. When an effect is found and the data holds
position-control runs, the closed-loop check re-runs them with the base and
with the augmented model on that twin (the ``validate`` stage's work).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Mapping

from ..errors import SeanvError
from ..jsonable import JsonResult
from ..report import ReportSection, sections
from .base import Context, FailedRun, Result, one_line, tasks_beside
from .dataset import position_runs
from .pipeline import MAX_SEED, check_count
from .validate import controller_numbers, position_paths, validate_model

__all__ = ["NAME", "NEEDS", "WRITES", "OPTIONS", "DiscoverResult", "check_option", "run", "write"]

NAME = "discover"
ORDER = 60
NEEDS = ("ingest",)
FOLDER = "discover"
#: where the ``Validation`` results are defined (:attr:`Result.module`)
_VALIDATION = "seanv_analysis.analysis.validate"
#: the closed-loop check's validations (with the base model, which is validate's
#: when that stage ran, and with the augmented one) and the discovery
RESULTS = (Result("validation", "Validation", get=lambda value, ctx: getattr(value.before,
                                                                             "validation", None),
                  module=_VALIDATION),
           Result("validation_augmented", "Validation",
                  get=lambda value, ctx: getattr(value.after, "validation", None),
                  module=_VALIDATION),
           Result("discovery", "Discovery", get=lambda value, ctx: value.discovery,
                  module="seanv_analysis.discover.result"))
SECTION = ReportSection("discovery", "Discovery: what the model misses",
                        sections.discovery_section, sections.discovery_cards)
WRITES = ("discover/discover.json", "discover/model_augmented.json", "discover/discover.txt",
          "discover/validate_augmented/ (the closed-loop check)")
DESCRIPTION = "what the model misses: residual -> effect -> refit, held-out error before/after"
#: holdout: 'chrono' (the last 30 % of each side's runs) or 'kfold' (5 folds
#: by run); seed: of the permutation check
OPTIONS: dict[str, Any] = {"holdout": "chrono", "seed": 0}
#: where its tasks run (the twin's identification, when no identify stage
#: gave one: :func:`seanv_analysis.identify.identify_rig`'s ``map_tasks``)
TASK_MODULES = ("seanv_analysis.identify.engine",)

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
    #: the rig's twin discover identified itself to test dynamic effects on
    #: (None: the ``identify`` stage's, or none)
    twin: Any = None

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


def closed_loop(ctx: Context, discovery, twin: Any = None) -> DiscoverResult:
    """The closed-loop check of a discovery: the position-control runs
    validated with the base model and with the augmented model and effects
    (a proposed closed-form term included; a constant that changes with use
    at the value the position runs set: ``position_run_model_and_effects``),
    on ``twin`` (the rig identified for the dynamic search when discover did
    it itself: its keys over the context's twin; None: the context's)."""
    if not position_paths(ctx) or not (discovery.effects or discovery.proposed_term):
        return DiscoverResult(discovery, twin=twin)
    note = ""
    base = _twin_overrides(twin)
    extra = getattr(discovery, "twin_overrides", None)
    overrides = _merge(base, extra or {})
    try:
        augmented, specs = discovery.position_run_model_and_effects(ctx.plant_rig)
    except SeanvError as exc:
        note = f"effects not simulated in the closed-loop check: {one_line(exc)}"
        augmented, specs = discovery.model, []
    # before: validate's when it ran on the same twin, else the base model
    # discovery started from (z0 and C fitted, the rig file's geometry): the
    # model one has without discovery, on the twin discovery tests on
    given = ctx.result("validate") if twin is None else None
    try:
        before = given or validate_model(ctx, discovery.base_model, plant_overrides=base or None)
        after = validate_model(ctx, augmented, specs, stage="validate_augmented",
                               plant_overrides=overrides or None)
    except SeanvError as exc:
        return DiscoverResult(discovery, note=("closed-loop check with the augmented model "
                                               f"failed: {one_line(exc)}"), twin=twin)
    checked = discovery.with_closed_loop(controller_numbers(before.validation),
                                         controller_numbers(after.validation))
    failed = (*(() if given else before.failed), *after.failed)
    return DiscoverResult(checked, before, after, note, failed, twin)


def _twin_overrides(twin) -> dict[str, Any]:
    """The identified keys of a twin discover identified itself ({}: none)."""
    return twin.overrides() if twin is not None else {}


def _merge(a: Mapping[str, Any], b: Mapping[str, Any]) -> dict[str, Any]:
    """``a`` with ``b``'s keys over it, section by section."""
    out = {k: dict(v) if isinstance(v, Mapping) else v for k, v in a.items()}
    for k, v in b.items():
        out[k] = {**out.get(k, {}), **v} if isinstance(v, Mapping) else v
    return out


#: the parts of the rig discover identifies for its twin when no ``identify``
#: stage ran (the valve's geometry is decided by discover's own static fit)
TWIN_PARTS = ("servo", "friction", "load", "flow_path")


def _valve_keys(valve) -> dict[str, Any]:
    """The rig-file keys of a valve model: z0, C and the needle centre per side."""
    return {"valve": {s: {"z0_mm": float(valve.side(s).z0_mm),
                          "c_flow": float(valve.side(s).c_flow),
                          "needle_x_c_mm": float(valve.side(s).geometry.needle_x_c_mm),
                          "needle_y_c_mm": float(valve.side(s).geometry.needle_y_c_mm)}
                      for s in ("supply", "drain")}}


def _twin_search(ctx: Context, summary, runs, held: dict[str, Any]):
    """The dynamic search of :func:`seanv_analysis.discover.discover_dataset`:
    on the ``identify`` stage's twin when it ran, else on a twin identified
    here from the same logs (servo, controller, friction, load regulator,
    line) with the valve discover's static fit decided; ``held['twin']``
    keeps the identification made here. A twin whose servo the logs cannot
    tell (no cam feedback) is no twin: the search says so instead."""
    from ..discover import NoTwin
    from ..identify import identify_rig
    from ..identify.dynamic import closed_loop_effects
    from .identify import servo_flow_runs

    given = ctx.result("identify")

    def search(train, held_runs, valve, rig, *, seed: int = 0, free_valve=()):
        if given is not None:
            twin_rig = given.rig
        else:
            ctx.log("discover: identifying the rig's twin from its logs (servo, controller, "
                    "friction, load regulator, line) to test dynamic effects on")
            start = ctx.rig.with_overrides(_valve_keys(valve), where="discover")
            ident = identify_rig(summary, start, position_runs=runs,
                                 flow_runs=servo_flow_runs(ctx, runs), parts=TWIN_PARTS,
                                 n_boot=0, seed=seed, log=ctx.log,
                                 map_tasks=tasks_beside(ctx))
            if not any(c.key.startswith("servo.") for c in ident.identified()):
                raise NoTwin("the servo cannot be identified from these logs (no cam "
                             "feedback), so neither can a twin to test dynamic effects on")
            held["twin"] = ident
            twin_rig = ident.rig
        return closed_loop_effects(train, held_runs, valve, twin_rig, seed=seed,
                                   free_valve=free_valve)

    return search


def run(ctx: Context, options: Mapping[str, Any]) -> DiscoverResult:
    """Discovery on the data set (:func:`seanv_analysis.discover.discover_dataset`),
    with the closed-loop check. Dynamic effects are tested on a twin the data
    identified: the ``identify`` stage's, or one identified here.

    Raises
    ------
    FitError
        too few usable runs.
    """
    from ..discover import discover_dataset
    from ..models import ValveModel

    opts = {**OPTIONS, **options}
    ds = ctx.result("ingest")
    ctx.log("discover: residual of the base model -> candidate effects -> held-out check")
    runs = position_runs(ctx)
    kept: dict[str, Any] = {}
    # the static fit starts from the rig file's geometry (or the --model's):
    # the data's own needle centre is decided there, with the effects
    start = ctx.start_model or ValveModel.from_rig(ctx.rig)
    # the twin's valve: identify's when that stage ran (fitted with the whole
    # rig it identified), else the static fit's
    given = ctx.result("identify")
    disc = discover_dataset(runs, ds.summary, rig=ctx.plant_rig, model=start,
                            holdout=opts["holdout"], seed=opts["seed"],
                            dynamic_search=_twin_search(ctx, ds.summary, runs, kept),
                            twin_model=ctx.valve if given is not None else None)
    if given is not None and disc.geometry:
        disc = replace(disc, geometry=geometry_readings(disc.geometry, given.constants))
    return closed_loop(ctx, disc, kept.get("twin"))


def geometry_readings(geometry: Mapping[str, Any], constants) -> dict[str, Any]:
    """discover's needle centres (fitted with the named effects) with the
    ``identify`` stage's beside them (``identified_mm``,
    ``identified_ci95_mm``: fitted before and without any effect; the twin's):
    two readings of one constant, both reported (the selection of the
    centre and the effects is discover's; identify decides first, alone)."""
    out = {s: dict(g) for s, g in geometry.items()}
    for c in constants:
        side = c.key.split(".")[1] if c.key and c.key.endswith(".needle_y_c_mm") else None
        if side in out and c.identified:
            out[side]["identified_mm"] = float(c.value)
            out[side]["identified_ci95_mm"] = [float(v) if math.isfinite(v) else None
                                               for v in c.ci95]
    return out


def raw_inputs(ctx: Context, options: Mapping[str, Any]) -> list[str]:
    """The run folders this stage reads itself, beyond the per-run summary
    (the data-set stage cache's key, :mod:`seanv_analysis.batch.stage_memo`):
    the position-control runs, and without an ``identify`` stage those its
    own twin is identified from (:data:`TWIN_PARTS`)."""
    from . import identify

    if ctx.result("identify") is not None:
        return [str(p) for p in position_paths(ctx)]
    return identify.raw_inputs(ctx, {"parts": list(TWIN_PARTS)})


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
