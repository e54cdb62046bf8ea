"""``seanv-analyze identify``: the rig's unpublished constants from its own logs."""
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
    result_json,
    run_command,
    sim_default_dataset,
    verbosity,
)

__all__ = ["identify_cmd"]

_PARTS = ("geometry", "servo", "friction", "load", "flow_path")


@cli.command("identify", short_help="Identify the rig (needle geometry, servo, friction, line) "
                                    "from its logs.")
@verbosity
@click.argument("data", nargs=-1, type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--rig", "rig_file", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Rig config TOML to start from (its values stay where the data cannot tell). "
                   "Default: the shipped one.")
@click.option("--part", "parts", type=click.Choice(_PARTS), multiple=True,
              help="Identify only this part (repeatable). Default: all.")
@click.option("--n-boot", type=click.IntRange(0, 10_000), default=100, show_default=True,  # stages.pipeline.MAX_N_BOOT
              help="Bootstrap resamples of the z0/C refit with the identified geometry.")
@click.option("--out", "out_dir", type=OUT_FOLDER,
              help="Output folder. Default: outputs/<dataset>/identify/.")
@click.option("--json", "as_json", is_flag=True, help="Print identify.json on stdout.")
def identify_cmd(data, rig_file, parts, n_boot, out_dir, as_json, quiet):
    """Identify what the paper does not publish about the rig in DATA, from its own logs.

    DATA: one or more data set folders; flow-step runs give the needle
    geometry (eq. 4's centre, with z0 and C refitted) and the Coulomb and
    viscous friction, position-control runs give the servo (dead time, time
    constant, rate limit, from its logs), the breakaway force, the
    controller's law (gain, hold band and angle, whether the hold latches
    or lets go, cam limits), the load regulator's time constant
    (from the logged load pressure) and the line (its bulk modulus, fitted so
    the twin driven by the logged cam command moves like the runs); both give the
    supply pressure the runs were made at. Each constant comes with
    a 95 % interval, what constrains it and its training vs held-out error
    with the rig file's value and the identified one; what the data cannot
    tell keeps the rig file's value and says why.

    \b
    Writes: rig-identified.toml (only the identified keys, the rig file's
    schema: give it to any command with --rig), identify.json,
    identify.txt, manifest.json.
    Example: seanv-analyze identify data/flow data/position
             seanv-analyze validate data/position --rig outputs/flow/identify/rig-identified.toml
    """
    from ..config import load_rig

    rig = load_rig(rig_file)
    if not data:
        data = (sim_default_dataset("paper-flowsteps-small"), sim_default_dataset("paper-position"))
        click.echo("no DATA given: using the built-in simulated flow-step and position-control "
                   f"data sets ({data[0]}, {data[1]})", err=True)
    out = Path(out_dir) if out_dir else default_out_dir(data[0], "identify")
    check_out_dir(list(data), out, files=[rig_file], owned=(".",))
    options = {"n_boot": n_boot, **({"parts": list(parts)} if parts else {})}
    pipe = command_pipeline("identify", [{"name": "identify", **options}], figures=False)
    run = run_command(pipe, list(data), rig=rig, out=out, quiet=quiet,
                      missing="no flow_step or position_control run to identify from",
                      manifest={"parts": pipe.stage("identify").options["parts"],
                                "n_boot": n_boot})
    if isinstance(run, int):
        return run
    if as_json:
        click.echo(result_json(run.value, run.ds))
    else:
        click.echo(run.value.report())
        click.echo(f"outputs: {out}  (use --rig {out / 'rig-identified.toml'})")
    return echo_bad_runs(run.ds.failed)
