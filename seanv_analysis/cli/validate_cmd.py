"""``seanv-analyze validate``: re-run the measured position-control tests on
the simulated plant with the identified valve model and compare."""
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

__all__ = ["validate_cmd"]


@cli.command("validate")
@verbosity
@click.argument("data", required=False, type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--model", "model_file", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Identified valve model (JSON/TOML from flowfit): the plant's valve and the "
                   "flow-model controller's model; the effects and proposed term of discover's "
                   "model_augmented.json are simulated too. Default: the rig config's valve.")
@click.option("--rig", "rig_file", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Rig config TOML. Default: the shipped one.")
@click.option("--threshold", "threshold_pct", type=float, default=80.0, show_default=True,
              help="Flag runs whose position fit % is below this.")
@click.option("--controller-model", type=click.Choice(["rig", "plant"]), default="rig",
              show_default=True,
              help="Valve model inside the flow-model controller: the rig config's (what the "
                   "rig ran) or the --model (plant) one.")
@click.option("--out", "out_dir", type=OUT_FOLDER,
              help="Output folder. Default: outputs/<dataset>/validate/.")
@figure_options
@click.option("--json", "as_json", is_flag=True, help="Print the result as one JSON document on stdout.")
def validate_cmd(data, model_file, rig_file, threshold_pct, controller_model, out_dir, no_figures,
                 formats, as_json):
    """Closed-loop validation of the position-control runs in DATA.

    Each run's controller (Kp, flow model on/off from run.json) is re-run on
    the simulated plant with the same reference and load steps; simulated and
    measured position, flow and cam angle are compared (fit %, RMSE), with
    convergence (+-0.5 mm), overshoot and settling time per step. Runs with
    position fit below --threshold are flagged. A run that hunts (a limit
    cycle: the cam swinging for as long as the reference stays) is judged by
    the cycle's amplitude, period and mean error (limit_cycle_* columns; its
    phase cannot be reproduced): not flagged when both records hold the same
    limit cycle (within 20 %), flagged when only one does or they differ.

    Each run is also re-run segment by segment, from the logged state where
    the rig rests before each reference step and load change (the *_segments_*
    columns): with stick-slip, a whole re-run carries where each hold ended
    into every later step; per segment, the fit measures the twin's response
    to the inputs.

    \b
    The plant is built from the rig config (tube, actuator, friction, load,
    servo): for logs from another rig pass that rig's file with --rig (e.g.
    the rig-identified.toml of `seanv-analyze identify`), or the comparison
    measures the difference between the rigs, not the valve model.

    \b
    Writes: validate.json, validate.txt, validate_table.parquet,
    validate_<run>.parquet/.png/.svg, validate_fit.png/.svg, manifest.json.
    Example: seanv-analyze validate data/position --model outputs/flow/flowfit/model.json
    """
    from ..config import load_rig
    from ..io.model_file import read_model_file

    rig = load_rig(rig_file)
    if data is None:
        data = sim_default_dataset("paper-position")
        click.echo(f"no DATA given: using the built-in simulated paper position-control data "
                   f"set ({data})", err=True)
    out = Path(out_dir) if out_dir else default_out_dir(data, "validate")
    check_out_dir(data, out, files=[rig_file, model_file], owned=(".",))
    # a model file's effects and proposed term (discover's model_augmented.json) are simulated
    model, effects = read_model_file(model_file, rig=rig) if model_file else (None, ())
    options = {"threshold_pct": threshold_pct, "controller_model": controller_model,
               **({"effects": list(effects)} if effects else {})}
    pipe = command_pipeline("validate", [{"name": "validate", **options}],
                            ingest={"derive": True}, figures=not no_figures, formats=formats,
                            flags={"threshold_pct": "--threshold"})
    run = run_command(pipe, data, rig=rig, out=out, model=model,
                      missing="no position_control run could be validated",
                      manifest={"model": str(model_file) if model_file else None,
                                "effects": list(effects), "threshold_pct": threshold_pct,
                                "controller_model": controller_model})
    if isinstance(run, int):
        return run
    if as_json:
        click.echo(result_json(run.value, run.ds, failed=run.value.failed))
    else:
        click.echo(run.value.report())
        click.echo(f"outputs: {out}")
    return echo_bad_runs([*run.ds.failed, *run.value.failed])
