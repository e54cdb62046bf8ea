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

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

from ..errors import SeanvError
from ..jsonable import JsonResult
from ..report import ReportSection, sections
from .base import Context, FailedRun, Result, one_line
from .dataset import position_runs
from .pipeline import MAX_SEED, check_count
from .validate import controller_numbers, position_paths, validate_model

__all__ = ["NAME", "NEEDS", "WRITES", "OPTIONS", "DiscoverResult", "check_option", "run", "write"]

NAME = "discover"
ORDER = 60
NEEDS = ("ingest",)
FOLDER = "discover"
#: the closed-loop check's validations (with the base model, which is validate's
#: when that stage ran, and with the augmented one) and the discovery
RESULTS = (Result("validation", "Validation", get=lambda value, ctx: getattr(value.before,
                                                                             "validation", None)),
           Result("validation_augmented", "Validation",
                  get=lambda value, ctx: getattr(value.after, "validation", None)),
           Result("discovery", "Discovery", get=lambda value, ctx: value.discovery))
SECTION = ReportSection("discovery", "Discovery: what the model misses",
                        sections.discovery_section, sections.discovery_cards)
WRITES = ("discover/discover.json", "discover/model_augmented.json", "discover/discover.txt",
          "discover/validate_augmented/ (the closed-loop check)")
DESCRIPTION = "what the model misses: residual -> effect -> refit, held-out error before/after"
#: holdout: 'chrono' (the last 30 % of each side's runs) or 'kfold' (5 folds
#: by run); seed: of the permutation check
OPTIONS: dict[str, Any] = {"holdout": "chrono", "seed": 0}

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
    """Discovery on the data set (:func:`seanv_analysis.discover.discover_dataset`),
    with the closed-loop check.

    Raises
    ------
    FitError
        too few usable runs (see :func:`discover_runs`).
    """
    from ..discover import discover_dataset
    from ..identify.dynamic import closed_loop_effects

    opts = {**OPTIONS, **options}
    ds = ctx.result("ingest")
    ctx.log("discover: residual of the base model -> candidate effects -> held-out check")
    twin = ctx.result("identify") is not None   # dynamic effects only on an identified twin
    disc = discover_dataset(position_runs(ctx), ds.summary, rig=ctx.plant_rig, model=ctx.valve,
                            holdout=opts["holdout"], seed=opts["seed"],
                            dynamic_search=closed_loop_effects if twin else None)
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
