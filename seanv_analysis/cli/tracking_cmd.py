"""``seanv-analyze tracking``: flow delay, delay compensation, RMSE, Fig. 6/7."""
from __future__ import annotations

import json
import sys
import warnings
from pathlib import Path

import click

from . import cli
from ._common import (check_out_dir, default_out_dir, echo_bad_runs, explain_unusable,
                      sim_default_dataset)

__all__ = ["tracking_cmd"]


@cli.command("tracking", short_help="Flow delay, lag compensation and tracking RMSE (Sec. III-C); Fig. 6/7.")
@click.argument("data", required=False, type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--shift", "shift_s", type=float, default=None,
              help="Delay [s] to compensate (the paper's: 0.25). Default: estimated by "
                   "cross-correlation of actual vs target flow, with a 95 % interval.")
@click.option("--range", "q_range", type=(float, float), default=(-2.5e3, 8e3), show_default=True,
              metavar="LO HI", help="Target-flow range [mm^3/s] of the RMSE (inclusive).")
@click.option("--model", "model_file", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Valve model file (JSON/TOML from flowfit): target flow of runs without "
                   "q_ref and without flow model.")
@click.option("--rig", "rig_file", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Rig config TOML. Default: the shipped one.")
@click.option("--out", "out_dir", type=click.Path(file_okay=False, path_type=Path),
              help="Output folder. Default: outputs/<dataset>/tracking/.")
@click.option("--no-figures", is_flag=True, help="Skip the Fig. 6/7 figures.")
@click.option("--json", "as_json", is_flag=True, help="Print the result as one JSON document on stdout.")
def tracking_cmd(data, shift_s, q_range, model_file, rig_file, out_dir, no_figures, as_json):
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
    from ..analysis.tracking import tracking_runs
    from ..io import read_dataset
    from ..config import load_rig
    from ..errors import DataError
    from ..io.atomic import write_text_atomic
    from ..models import ValveModel

    rig = load_rig(rig_file)
    if data is None:
        data = sim_default_dataset("paper-position")
        click.echo(f"no DATA given: using the built-in simulated paper position-control data "
                   f"set ({data})", err=True)
    out = Path(out_dir) if out_dir else default_out_dir(data, "tracking")
    check_out_dir(data, out)
    model = ValveModel.load(model_file, rig=rig) if model_file else None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # collected in the result (skipped, warnings)
        ds = read_dataset(data, rig=rig)
        try:
            result = tracking_runs(ds.runs, shift_s=shift_s, q_range=q_range, model=model)
        except DataError as exc:  # nothing usable: say which runs were bad and why
            return explain_unusable(data, rig, exc)
    errors = ds.errors
    result.write(out)
    write_text_atomic(out / "tracking.txt", result.report() + "\n")
    if not no_figures:
        from ..plots.fig6 import plot_fig6, plot_fig6_dataset
        from ..plots.fig7 import plot_fig7

        runs = [r for r in ds.runs if r.kind == "position_control"]
        # the paper's order: (a) without, (b) with the flow model
        plot_fig6_dataset(sorted(runs, key=lambda r: bool((r.meta.controller or {})
                                                          .get("flow_model", True))), out)
        for run in runs:
            plot_fig6(run, out)
        plot_fig7(result, out)
    from ..manifest import write_manifest
    write_manifest(out, config=rig.to_dict(), inputs=[data], command=sys.argv,
                   extra={"shift_s": shift_s, "range_mm3_s": list(q_range),
                          "model": str(model_file) if model_file else None,
                          "bad_runs": [str(e) for e in errors]})
    if as_json:
        click.echo(json.dumps(result.to_json()))
    else:
        click.echo(result.report())
        click.echo(f"outputs: {out}")
    return echo_bad_runs(errors)
