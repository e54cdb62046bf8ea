"""``seanv-analyze discover``: residual -> missing effect -> refit -> error before/after."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import click

from . import cli
from ._common import (check_out_dir, default_out_dir, echo_bad_runs, explain_unusable,
                      sim_default_dataset)

__all__ = ["discover_cmd"]


@cli.command("discover", short_help="What the model misses: residual -> effect -> refit, error before/after.")
@click.argument("data", required=False, type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--model", "model_file", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Valve model file (JSON/TOML from flowfit) used as the starting point. "
                   "Default: the rig config's valve (the paper's z0, C).")
@click.option("--rig", "rig_file", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Rig config TOML (only the keys you change). Default: data_schema/rig/default.toml.")
@click.option("--holdout", type=click.Choice(["chrono", "kfold"]), default="chrono", show_default=True,
              help="chrono: the last 30 % of each side's runs (time order) are held out; "
                   "kfold: 5 folds by run.")
@click.option("--out", "out_dir", type=click.Path(file_okay=False, path_type=Path),
              help="Output folder. Default: outputs/<dataset>/discover/.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the permutation check.")
@click.option("--json", "as_json", is_flag=True, help="Print the result as one JSON document on stdout.")
def discover_cmd(data, model_file, rig_file, holdout, out_dir, seed, as_json):
    """Find what the flow model (eq. 5) misses in DATA and report the error before/after.

    Fits the base model on the fit part of the flow-step runs, looks at the
    residual (measured - model) against run order, dp, opening, cam approach
    direction and flow, tries the candidate effects (drift, threshold_shift,
    backlash, pressure_law, saturation, sensor_gain) and keeps one only when
    it lowers the error materially and passes an F-test and a permutation
    check. Held-out runs are never used for fitting or selection.

    \b
    Verdicts: effect_found | none | unexplained (structured residual, no
    candidate explains it; the variable it trends with is named).
    Writes: discover.json, model_augmented.json, discover_residuals.png/.svg,
    discover.txt (a paragraph for a lab note), manifest.json.
    Example: seanv-analyze discover data/flow --json
    """
    from ..config import load_rig
    from ..discover.dataset import discover_dataset
    from ..errors import DataError
    from ..io.atomic import write_json_atomic, write_text_atomic
    from ..models import ValveModel
    from ..plots.residuals import plot_discovery_residuals

    rig = load_rig(rig_file)
    if data is None:
        from ..sim.scenarios import PAPER_DRAIN_DRIFT
        data = sim_default_dataset("paper-flowsteps", effects=(PAPER_DRAIN_DRIFT,))
        click.echo(f"no DATA given: using the built-in simulated paper flow-step data set ({data})",
                   err=True)
    out = Path(out_dir) if out_dir else default_out_dir(data, "discover")
    check_out_dir(data, out)
    model = ValveModel.load(model_file, rig=rig) if model_file else ValveModel.from_rig(rig)
    try:
        result, ds = discover_dataset(data, model=model, rig=rig, holdout=holdout, seed=seed)
    except DataError as exc:  # nothing usable: say which runs were bad and why
        return explain_unusable(data, rig, exc)
    if result.effects and ds.runs:  # position-control runs: closed-loop check via validate
        result.validation = _closed_loop(result, ds.runs, model, rig)
        result.use_closed_loop_heldout()
    write_json_atomic(out / "discover.json", result.to_json())
    write_json_atomic(out / "model_augmented.json", result.augmented_model_dict())
    write_text_atomic(out / "discover.txt", result.report() + "\n")
    plot_discovery_residuals(result, out_dir=out)
    try:
        from ..manifest import write_manifest
        write_manifest(out, config=rig.to_dict(), inputs=[data], command=sys.argv)
    except ImportError:  # pragma: no cover - manifest module not present
        pass
    if as_json:
        click.echo(json.dumps(result.to_json()))
    else:
        click.echo(result.report())
        click.echo(f"outputs: {out}")
    return echo_bad_runs(ds.errors)


def _closed_loop(result, runs, model, rig) -> dict:
    """Closed-loop fit (validate) of the position-control runs with the base
    and with the augmented model: {"before": {controller: numbers}, "after": ...}."""
    from ..analysis.validate import validate_runs
    from ..batch.runner import _validation_numbers

    augmented, specs = result.augmented_model_and_effects(rig)
    before = validate_runs(runs, model, rig=rig)
    after = validate_runs(runs, augmented, rig=rig, effects=specs)
    return {"before": _validation_numbers(before), "after": _validation_numbers(after)}
