"""``seanv-analyze discover``: residual -> missing effect -> refit -> error before/after."""
from __future__ import annotations

from pathlib import Path

import click

from . import cli
from ._common import (
    OUT_FOLDER,
    check_out_dir,
    command_pipeline,
    default_out_dir,
    echo_bad_runs,
    figure_options,
    result_json,
    run_command,
    sim_default_dataset,
    verbosity,
)

__all__ = ["discover_cmd"]


@cli.command("discover", short_help="What the model misses: residual -> effect -> refit, error before/after.")
@verbosity
@click.argument("data", required=False, type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--model", "model_file", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Valve model file (JSON/TOML from flowfit) used as the starting point. "
                   "Default: the rig config's valve (the paper's z0, C).")
@click.option("--rig", "rig_file", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Rig config TOML (only the keys you change). Default: data_schema/rig/default.toml.")
@click.option("--holdout", type=click.Choice(["chrono", "kfold"]), default="chrono", show_default=True,
              help="chrono: the last 30 % of each side's runs (time order) are held out; "
                   "kfold: 5 folds by run.")
@click.option("--out", "out_dir", type=OUT_FOLDER,
              help="Output folder. Default: outputs/<dataset>/discover/.")
@click.option("--seed", type=click.IntRange(0, 2**32 - 1), default=0, show_default=True,
              help="Seed of the permutation check.")  # stages.pipeline.MAX_SEED
@click.option("--identify", "identify_first", is_flag=True,
              help="Identify the rig from DATA first (as `seanv-analyze identify`) and discover on "
                   "the identified twin: its valve with the identified needle geometry, and in "
                   "position-control runs delay/backlash fitted on it, replaying the logged cam command.")
@figure_options
@click.option("--json", "as_json", is_flag=True, help="Print the result as one JSON document on stdout.")
def discover_cmd(data, model_file, rig_file, holdout, out_dir, seed, identify_first, no_figures,
                 formats, as_json):
    """Find what the flow model (eq. 5) misses in DATA and report the error before/after.

    Fits the base model on the fit part of the flow-step runs, looks at the
    residual (measured - model) against run order, dp, opening, cam approach
    direction and flow, tries the candidate effects (drift, threshold_shift,
    backlash, pressure_law, saturation, sensor_gain) and keeps one only when
    it lowers the error materially and passes an F-test and a permutation
    check. Held-out runs are never used for fitting or selection.

    \b
    The needle centre of eq. (4) (not published) is fitted as part of the
    base model when the runs span enough fluid force, so a rig whose
    geometry differs from the rig file's is not blamed on an effect.

    \b
    Verdicts: effect_found | none | unexplained (structured residual, no
    candidate explains it; the variable it trends with is named).
    Writes: discover.json, model_augmented.json, discover_residuals.png/.svg,
    discover.txt (a paragraph for a lab note), manifest.json.
    Example: seanv-analyze discover data/flow --json
    """
    from ..config import load_rig
    from ..io.model_file import read_model

    rig = load_rig(rig_file)
    if data is None:
        from ..sim.scenarios import PAPER_DRAIN_DRIFT
        data = sim_default_dataset("paper-flowsteps", effects=(PAPER_DRAIN_DRIFT,))
        click.echo(f"no DATA given: using the built-in simulated paper flow-step data set ({data})",
                   err=True)
    out = Path(out_dir) if out_dir else default_out_dir(data, "discover")
    check_out_dir(data, out, files=[rig_file, model_file], owned=(".",))
    model = read_model(model_file, rig=rig) if model_file else None
    stages = ([{"name": "identify"}] if identify_first else []) + [
        {"name": "discover", "holdout": holdout, "seed": seed}]
    pipe = command_pipeline("discover", stages, figures=not no_figures, formats=formats)
    run = run_command(pipe, data, rig=rig, out=out, model=model, folders={"identify": "identify"},
                      missing="nothing to discover",
                      manifest={"holdout": holdout, "seed": seed, "identify": identify_first,
                                "model": str(model_file) if model_file else None})
    if isinstance(run, int):
        return run
    result = run.value
    if as_json:
        click.echo(result_json(result, run.ds, failed=result.failed, filtered=True))
    else:
        click.echo(result.report())
        if result.note:
            click.echo(f"note: {result.note}")
        click.echo(f"outputs: {out}")
    return echo_bad_runs([*run.ds.failed, *result.failed])
