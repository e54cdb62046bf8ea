"""``seanv-analyze plots``: the paper-style figures for a whole data set."""
from __future__ import annotations

import sys
from pathlib import Path

import click

from . import cli
from ._common import OUT_FOLDER, check_out_dir, default_out_dir, formats_option, unusable, verbosity

__all__ = ["plots_cmd", "plots_pipeline", "analyses_run", "not_drawn"]


def plots_pipeline(figs: list[int | str]) -> dict:
    """The pipeline document behind ``plots``: ingest, the stages giving the
    results the chosen figures need (the catalogue's producers, in run order)
    and figures."""
    from ..stages import STAGES, producers_of
    from ..stages.figures import selected_figures

    needed = {stage for f in selected_figures(figs) if not f.per_run for n in f.needs
              for stage in producers_of(n)[:1]}
    stages: list[dict] = [{"name": s} for s in STAGES if s in needed | {"ingest"}]
    stages.append({"name": "figures", "figs": list(figs)})
    return {"pipeline": {"name": "plots", "description": f"figures {', '.join(map(str, figs))}"},
            "stages": stages}


def _figure_choices() -> list[str]:
    from ..plots import FIGURES

    return [str(f.number) if f.number is not None else f.name for f in FIGURES.values()] + ["all"]


class _FigureChoice(click.Choice):
    """The registry's figures, read when first needed (not when the CLI is
    imported: ``seanv-analyze --help`` must not load the figures and pandas)."""

    def __init__(self) -> None:
        super().__init__([])

    @property
    def choices(self):  # type: ignore[override]
        return _figure_choices()

    @choices.setter
    def choices(self, _value) -> None:
        pass


@cli.command("plots")
@verbosity
@click.argument("data", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--fig", "fig", type=_FigureChoice(), multiple=True,
              default=("4", "6", "7"), show_default=True,
              help="Figure(s) of the registry (seanv_analysis.plots.FIGURES): 4 flow "
                   "characterisation of the data set (fit + threshold), 6 one per "
                   "position-control run, 7 flow tracking (data set + one per run), others by "
                   "name; 'all' for every one. Repeat for several.")
@click.option("--out", "out_dir", type=OUT_FOLDER,
              help="Output folder. Default: outputs/<dataset-name>/plots/.")
@click.option("--workers", type=click.IntRange(min=1), default=None,
              help="Worker processes for the per-run work (1: serial). Default: the CPU count.")
@click.option("--rig", "rig_file", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Rig config TOML with only the keys you change.")
@formats_option
def plots_cmd(data: Path, fig: tuple[str, ...], out_dir: Path | None, workers: int | None,
              rig_file: Path | None, quiet: bool, formats: tuple[str, ...] = ("png", "svg")
              ) -> int:
    """Draw the paper's figures for every run / the whole data set in DATA (PNG + SVG).

    \b
    Writes under --out/figures/:
      fig4.png/.svg            flow rate vs cam angle per load, threshold vs dp (Fig. 4)
      fig6/fig6_<run>.png/.svg position, pressures, cam, error of each
                               position-control run (Fig. 6)
      fig7*.png/.svg           target vs actual flow, delay-shifted (Fig. 7)
    Figures whose runs are missing (e.g. Fig. 6 without position-control
    runs) are skipped with a note. Per-run work is cached in --out/.cache.

    \b
    Example:
      seanv-analyze plots data/ --fig 4 --fig 7
    """
    from ..batch import run_pipeline
    from ..errors import DataError
    from ..stages.figures import selected_figures

    chosen = "all" if "all" in fig else [int(f) if f.isdigit() else f for f in fig]
    figs = [f.number if f.number is not None else f.name for f in selected_figures(chosen)]
    out = Path(out_dir) if out_dir else default_out_dir(data, "plots")
    check_out_dir(data, out)
    pipe = plots_pipeline(figs)
    analyses = analyses_run(pipe)
    if analyses and not quiet:   # said, not done silently: they may take a minute
        click.echo(f"plots: the figures asked for need the results of {', '.join(analyses)}: "
                   "running them first (seanv-analyze run keeps them, with its report)",
                   err=True)
    try:
        pipe["stages"][-1]["formats"] = list(formats)
        result = run_pipeline(pipe, data, out_dir=out, workers=workers,
                              quiet=quiet, rig=rig_file, command=sys.argv)
    except DataError as exc:  # no run could be read: say which runs were bad and why
        from .run_cmd import bad_runs
        return unusable(data, bad_runs([data], rig_file, exc), exc)
    n = 0
    for p in (p for paths in result.figures.values() for p in paths):
        click.echo(str(p))
        n += 1
    missing = not_drawn(figs, result)
    if n == 0:   # nothing the user asked for could be drawn: not a success
        from ..errors import DataError

        raise DataError("no figure written: " + "; ".join(missing), path=data)
    click.echo(f"{n} figure file(s) under {out / 'figures'}", err=True)
    for line in missing:
        click.echo(f"note: not drawn: {line}", err=True)
    for stage, msg in {**result.stage_notes, **result.stage_errors}.items():
        click.echo(f"note: {stage}: {msg}", err=True)
    for f in result.failed:
        click.echo(f"  failed [{f.stage}] {f.message}", err=True)
    return 0 if result.success else 1


def analyses_run(pipe: dict) -> list[str]:
    """The analysis stages ``plots`` runs to get its figures' inputs (all
    but ingest and figures)."""
    return [s["name"] for s in pipe["stages"] if s["name"] not in ("ingest", "figures")]


def not_drawn(figs: list, result) -> list[str]:
    """One phrase per figure of ``figs`` that wrote no file, with why (the
    note or error of the stage that gives its input)."""
    from ..stages import producers_of
    from ..stages.figures import selected_figures

    out = []
    for f in selected_figures(figs):
        if result.figures.get(f.name):
            continue
        label = f"fig {f.number}" if f.number is not None else f.name
        whys = [f"{stage}: {msg}" for need in f.needs for stage in producers_of(need)
                for msg in [result.stage_errors.get(stage) or result.stage_notes.get(stage)]
                if msg]
        if f.per_run and f.run_kind:
            whys = whys or [f"no {f.run_kind} run in the data"]
        out.append(f"{label} ({'; '.join(whys) or 'nothing to draw it from'})")
    return out
