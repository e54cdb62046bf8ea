"""``seanv-analyze tracking``: flow delay, delay compensation, RMSE, Fig. 6/7."""
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

__all__ = ["tracking_cmd"]


@cli.command("tracking", short_help="Flow delay, lag compensation and tracking RMSE (Sec. III-C); Fig. 6/7.")
@verbosity
@click.argument("data", required=False, type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--shift", "shift_s", type=float, default=None, metavar="0..2",
              help="Delay [s] to compensate, from 0 to 2 (the paper's: 0.25). Default: "
                   "estimated by cross-correlation of actual vs target flow, with a 95 % "
                   "interval.")
@click.option("--range", "q_range", type=(float, float), default=(-2.5e3, 8e3), show_default=True,
              metavar="LO HI", help="Target-flow range [mm^3/s] of the RMSE (inclusive).")
@click.option("--model", "model_file", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Valve model file (JSON/TOML from flowfit): target flow of runs without "
                   "q_ref and without flow model.")
@click.option("--rig", "rig_file", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Rig config TOML. Default: the shipped one.")
@click.option("--out", "out_dir", type=OUT_FOLDER,
              help="Output folder. Default: outputs/<dataset>/tracking/.")
@figure_options
@click.option("--json", "as_json", is_flag=True, help="Print the result as one JSON document on stdout.")
def tracking_cmd(data, shift_s, q_range, model_file, rig_file, out_dir, no_figures, formats, as_json):
    """Flow tracking of the position-control runs in DATA (paper Sec. III-C.2, Fig. 6/7).

    Actual flow from the encoder (same derivative as ingest), target flow
    from controller.csv q_ref (or Kp e, or the --model's flow at the
    commanded cam). The actual flow is shifted earlier by the delay (given
    with --shift, else estimated) and the RMSE of actual - target is taken
    over the samples whose target lies in --range.

    \b
    Writes: tracking.json, tracking_details.json, tracking_runs.parquet,
    tracking_<run>.parquet, fig6*.png/.svg, fig7*.png/.svg, tracking.txt,
    manifest.json.
    Example: seanv-analyze tracking data/position --shift 0.25 --json
    """
    from ..config import load_rig
    from ..io.model_file import read_model

    rig = load_rig(rig_file)
    if data is None:
        data = sim_default_dataset("paper-position")
        click.echo(f"no DATA given: using the built-in simulated paper position-control data "
                   f"set ({data})", err=True)
    out = Path(out_dir) if out_dir else default_out_dir(data, "tracking")
    check_out_dir(data, out, files=[rig_file, model_file], owned=(".",))
    model = read_model(model_file, rig=rig) if model_file else None
    options = {"shift_s": shift_s, "q_range": list(q_range)}
    pipe = command_pipeline("tracking", [{"name": "tracking", **options}],
                            ingest={"derive": True}, figures=not no_figures, formats=formats,
                            flags={"shift_s": "--shift", "q_range": "--range"})
    run = run_command(pipe, data, rig=rig, out=out, model=model,
                      missing="no position_control run in the data set; expected runs with "
                              "run.json kind = 'position_control'",
                      manifest={"shift_s": shift_s, "range_mm3_s": list(q_range),
                                "model": str(model_file) if model_file else None})
    if isinstance(run, int):
        return run
    if as_json:
        click.echo(result_json(run.value, run.ds))
    else:
        click.echo(run.value.report())
        click.echo(f"outputs: {out}")
    return echo_bad_runs(run.ds.failed)
