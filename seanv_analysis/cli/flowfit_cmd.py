"""``seanv-analyze flowfit``: identify z0 and C of each side (paper eq. 3-5),
with 95 % intervals; write the model file, tables and Fig. 4."""
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

__all__ = ["flowfit_cmd", "BUILTIN_SCENARIO"]

#: Built-in simulated data set used when DATA is not given.
BUILTIN_SCENARIO = "paper-flowsteps"


@cli.command("flowfit", short_help="Fit z0 and C per valve side (eq. 3-5) with 95 % intervals; Fig. 4.")
@verbosity
@click.argument("data", required=False, type=click.Path(path_type=Path))
@click.option("--rig", "rig_file", type=click.Path(dir_okay=False, path_type=Path),
              help="Rig config TOML with only the keys you change. Default: the shipped rig.")
@click.option("--out", "out_dir", type=OUT_FOLDER,
              help="Output folder. Default: outputs/<dataset-name>/flowfit/.")
@click.option("--json", "as_json", is_flag=True,
              help="Print only the result JSON (stable contract) on stdout.")
@click.option("--side", type=click.Choice(["supply", "drain", "both"]), default="both",
              show_default=True, help="Side(s) to fit.")
@click.option("--method", type=click.Choice(["steady", "peak"]), default="steady",
              show_default=True,
              help="Per-run flow: steady-motion estimate, or the paper's peak velocity x area.")
@click.option("--procedure", type=click.Choice(["joint", "two_step"]), default="joint",
              show_default=True,
              help="joint: z0 and C on all runs with eq. (5), robust soft_l1 loss; "
                   "two_step: the paper's per-load quadratics, then z0, then C.")
@click.option("--cam", type=click.Choice(["measured", "commanded"]), default="measured",
              show_default=True,
              help="Cam angle theta of each run: servo feedback (median over the hold; the "
                   "command where missing), or the commanded angle.")
@click.option("--n-boot", type=click.IntRange(0, 10_000), default=200, show_default=True,  # stages.pipeline.MAX_N_BOOT
              help="Bootstrap resamples for the 95 % intervals (0: none).")
@click.option("--seed", type=click.IntRange(0, 2**32 - 1), default=0, show_default=True,
              help="Bootstrap seed.")  # stages.pipeline.MAX_SEED
@figure_options
def flowfit_cmd(data: Path | None, rig_file: Path | None, out_dir: Path | None, as_json: bool,
                side: str, method: str, procedure: str, cam: str, n_boot: int, seed: int,
                no_figures: bool = False, formats: tuple[str, ...] = ("png", "svg")) -> int:
    """Fit the sealing threshold (z0, eq. 3+4) and flow coefficient (C, eq. 5) per side.

    DATA is a data set folder of flow-step runs. Without DATA the built-in
    simulated paper data set (paper-flowsteps, generated once and cached) is used.
    Runs are summarised, filtered (leakage, friction, cam range, invalid),
    fitted per load (Q = alpha (theta - theta_d)^2) and jointly (eq. 5); 95 %
    intervals come from a bootstrap over runs. A lack-of-fit check per side
    compares the residual scatter with the repeats' scatter (runs of the same
    load and cam angle): lack_of_fit true means eq. (5) does not describe the
    runs (drift, or another effect) and the intervals, which assume it does,
    are not to be trusted (try `seanv-analyze discover`); null means it could
    not be tested (no condition was repeated).

    \b
    Writes (under --out, default outputs/<dataset-name>/flowfit/):
      flowfit.json          z0_mm, C, 95 % intervals, RMSE, runs, lack_of_fit
                            (+ _ratio, _p) per side; exclusions
      flowfit_details.json  both procedures, noise model, lack-of-fit test, per-load
                            table, warnings
      model.toml, model.json  valve model file for tracking / validate / the controller
      per_run.parquet       per run: measured and model flow, residual (measured - model)
      per_load.parquet      per side and load: theta_d, alpha (+- s.e.)
      fig4.png, fig4.svg    Fig. 4 (a) flow vs cam angle, (b) threshold vs dp
      manifest.json         version, rig config, input hashes, command line

    \b
    Exit codes: 0 all runs read; 1 some runs bad (listed on stderr, results
    still written); 2 bad input or no side could be fitted.

    \b
    Example:
      seanv-analyze flowfit data/flow --side both --json
    """
    from ..config import load_rig

    rig = load_rig(rig_file)
    if data is None:
        data = sim_default_dataset(BUILTIN_SCENARIO)
        click.echo(f"no DATA given: using the built-in simulated data set "
                   f"'{BUILTIN_SCENARIO}' ({data})", err=as_json)
    out = Path(out_dir) if out_dir else default_out_dir(data, "flowfit")
    check_out_dir(data, out, files=[rig_file], owned=(".",))
    sides = ["supply", "drain"] if side == "both" else [side]
    options = {"sides": sides, "procedure": procedure, "cam": cam, "n_boot": n_boot, "seed": seed}
    pipe = command_pipeline("flowfit", [{"name": "flowfit", **options}],
                            ingest={"method": method}, figures=not no_figures, formats=formats)
    run = run_command(pipe, data, rig=rig, out=out, missing="no flow_step runs in the data set",
                      manifest={"flowfit": {"data": str(data), "side": side, "method": method,
                                            **options}})
    if isinstance(run, int):
        return run
    if as_json:
        click.echo(result_json(run.value, run.ds, filtered=True))
    else:
        click.echo(run.value.report())
        click.echo(f"outputs: {out}")
    return echo_bad_runs(run.ds.failed)
