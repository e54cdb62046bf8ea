"""``seanv-analyze simulate``: write a built-in scenario as a data set."""
from __future__ import annotations

from pathlib import Path

import click

from . import cli
from ._common import OUT_FOLDER, probe_writable, verbosity

__all__ = ["simulate_cmd"]


@cli.command("simulate")
@verbosity
@click.argument("scenario", type=click.Choice(["paper-flowsteps", "paper-flowsteps-small",
                                               "paper-position", "paper-position-model"]))
@click.option("--out", "out_dir", required=True, type=OUT_FOLDER,
              help="Data set folder to create (must not hold runs yet).")
@click.option("--seed", type=int, default=0, show_default=True,
              help="Noise seed; the same seed writes the same files bit for bit.")
@click.option("--effect", "effects", multiple=True, metavar="NAME[:param=value,...]",
              help="Inject an effect into the plant (repeatable): drift, threshold_shift, "
                   "backlash, pressure_law, saturation, delay, sensor_gain, or term (a "
                   "closed-form correction of one valve side). "
                   "Example: --effect drift:side=drain,step=0.05,every=3. "
                   "A term's expr comes last and runs to the end of the spec, commas "
                   "included (or quote it): --effect "
                   "\"term:side=supply,mode=mul,expr=-0.2*clip(dp, 0, 1.5)\" "
                   "(mode mul: Q (1 + expr); add: Q + expr [mm^3/s]; threshold: theta_d + "
                   "expr [deg]). expr may use numbers, + - * / ** (constant exponent), "
                   "tanh exp log sqrt abs sign min max clip, and dp, p1 [MPa], dtheta "
                   "(opening past theta_d), theta [deg], q (the side's eq. 5 flow) "
                   "[mm^3/s], load [MPaG], run, approach (+1/-1) [-]. "
                   "See --list-effects.")
@click.option("--write-truth", is_flag=True,
              help="Also write <out>/_truth.json with every plant parameter and effect.")
@click.option("--rig", "rig_file", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Rig config TOML (only the keys you change). Default: data_schema/rig/default.toml.")
@click.option("--format", "fmt", type=click.Choice(["csv", "parquet"]), default="csv",
              show_default=True, help="Table file format.")
@click.option("--list-effects", is_flag=True, is_eager=True, expose_value=False,
              callback=lambda ctx, _p, v: _list_effects(ctx) if v else None,
              help="List the effects, their parameters and defaults, and exit.")
def simulate_cmd(scenario, out_dir, seed, effects, write_truth, rig_file, fmt, quiet):
    """Simulate SCENARIO on the built-in plant and write it as a data set.

    \b
    Scenarios:
      paper-flowsteps        flow steps over the paper's grid (both sides,
                             cam -42.5..12.5 deg, 5 loads, 3 sweeps; 345 runs)
      paper-flowsteps-small  the same on a coarser grid (4 loads, 5 deg; 144 runs)
      paper-position         position control (Sec. III-C) with and
                             without the flow model
      paper-position-model   position control with the flow model only
    The plant: valve (eq. 3-5, leakage), 20 m tube (R, I, C), actuator with
    friction and end stops, pneumatic load, servo (dead time, lag, rate
    limit, 0.0879 deg steps), sensors with noise. Effects change the plant
    only: nothing in run.json or the tables names them.
    Example: seanv-analyze simulate paper-flowsteps --out data/sim --effect drift:side=drain
    """
    from ..config import load_rig
    from ..errors import ConfigError
    from ..models.effects import parse_effects
    from ..sim.scenarios import simulate_scenario

    rig = load_rig(rig_file)
    try:   # before --out is made: a typo leaves no empty folder behind
        parsed = parse_effects(effects)
    except ValueError as exc:  # the CLI's one-line error
        raise ConfigError(str(exc)) from None
    made = not Path(out_dir).exists()
    probe_writable(out_dir)
    from ..log import progress as progress_bar
    from ..sim.scenarios import scenario_size

    # drawn on a terminal unless -q (tqdm and its ~40 ms import only if seen)
    bar = progress_bar(total=scenario_size(scenario), desc=scenario)
    done_runs = [0]

    def progress(done, total):
        bar.update(done - done_runs[0])
        done_runs[0] = done

    try:
        path = simulate_scenario(scenario, out_dir, seed=seed, effects=parsed, rig=rig,
                                 write_truth=write_truth, fmt=fmt, progress=progress)
    except BaseException:
        if made and not any(Path(out_dir).iterdir()):   # ours, and nothing in it
            Path(out_dir).rmdir()
        raise
    finally:
        bar.close()
    n = sum(1 for _ in path.rglob("run.json"))
    click.echo(f"wrote {n} runs of {scenario} to {path}"
               + (f" with {', '.join(e.spec() for e in parsed)}" if parsed else ""))


def effect_summary(cls) -> str:
    """The first paragraph of an effect's docstring, on one line: whole
    sentences, never cut at the docstring's first line break."""
    import inspect

    paragraph = inspect.cleandoc(cls.__doc__ or "").split("\n\n", 1)[0]
    return " ".join(paragraph.split())


def _list_effects(ctx: click.Context) -> None:
    import shutil

    from ..models.effects import EFFECTS

    width = min(100, shutil.get_terminal_size((100, 24)).columns)
    for name, cls in EFFECTS.items():
        click.echo(click.wrap_text(f"{name}: {effect_summary(cls)}", width=width,
                                   subsequent_indent="    "))
        for param, meaning in cls.PARAMS.items():
            default = getattr(cls, param, None)
            click.echo(f"    {param} = {default!r}   {meaning}")
    ctx.exit(0)
