"""``seanv-analyze run``: run a pipeline (``pipelines/*.toml``) on a data set."""
from __future__ import annotations

import os
import sys
from pathlib import Path

import click

from . import cli
from ._common import OUT_FOLDER, check_out_dir, default_out_dir, figure_options, unusable, verbosity

__all__ = ["run_cmd", "failures_to_stderr"]


@cli.command("run")
@verbosity
@click.argument("pipeline", required=False)
@click.argument("data", required=False, type=click.Path(path_type=Path))
@click.option("--out", "out_dir", type=OUT_FOLDER,
              help="Output folder. Default: outputs/<dataset-name>/run-<pipeline>/.")
@click.option("--workers", type=click.IntRange(min=1), default=None,
              help="Local worker processes for the per-run work (1: serial, in this process). "
                   "Default: the CPU count.")
@click.option("--scheduler", metavar="tcp://HOST:PORT", default=None,
              help="Run the per-run work on a running dask.distributed cluster. Default: the "
                   "DASK_SCHEDULER_ADDRESS environment variable, if set (and --workers not given). "
                   "The cluster is never shut down by this command.")
@click.option("--force", is_flag=True,
              help="Recompute instead of reusing the last run, the per-run results or the "
                   "data-set stages' in <out>/.cache (a figure whose inputs are unchanged and "
                   "whose files are untouched is still reused).")
@click.option("--rig", "rig_file", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Rig config TOML with only the keys you change. Default: data_schema/rig/default.toml.")
@click.option("--json", "as_json", is_flag=True,
              help="Print the result (numbers, paths) as one JSON document on stdout.")
@click.option("--list-stages", is_flag=True,
              help="List the stages a pipeline can hold: what each does, needs, takes as options "
                   "and writes; then exit.")
@figure_options
def run_cmd(pipeline: str | None, data: Path | None, out_dir: Path | None, workers: int | None,
            scheduler: str | None, force: bool, quiet: bool, rig_file: Path | None,
            as_json: bool, list_stages: bool, no_figures: bool = False,
            formats: tuple[str, ...] = ("png", "svg")) -> int:
    """Run PIPELINE (a TOML file, or a shipped name: paper, flowfit, tracking) on DATA.

    DATA is a data set folder (run folders at any depth; flow-step and
    position-control runs may sit side by side) or one run folder. Without
    DATA the built-in simulated paper data sets are used.

    Per-run work (reading, summarising, Fig. 6, closed-loop validation) runs
    in parallel; data-set stages (flow fit, identify, tracking, discovery)
    run here, their independent fits and the figures on the workers.
    Results are identical whichever executor ran them. Per-run results are
    cached in <out>/.cache keyed by the input files' SHA-256, the stage
    options, the rig config and the package version: a killed run picks up
    where it stopped. A data-set stage whose inputs did not change (the
    per-run summary, the runs it reads itself, the stages before it) is
    reused too: an edit that leaves a flow step's summary as it was redoes
    only that run. When nothing changed since the last successful run into
    --out (the inputs' content, the pipeline, the rig, the code, the library
    versions) and its outputs are untouched, the run reuses them and writes
    nothing (about 1 s; --force recomputes).

    \b
    Writes (under --out): summary.parquet, flowfit/, tracking/, validate/,
    discover/, figures/ (PNG + SVG), report.html (self-contained),
    manifest.json (version, git SHA, rig config, input hashes, command
    line), result.json.

    \b
    Exit codes: 0 all runs and stages fine; 1 some runs or stages failed
    (listed at the end, the rest processed); 2 bad input or pipeline.

    \b
    Examples:
      seanv-analyze run paper data/ --out outputs/paper
      seanv-analyze run pipelines/flowfit.toml data/flow --workers 1
      dask scheduler &  dask worker tcp://127.0.0.1:8786 --nworkers 2 &
      seanv-analyze run paper data/ --scheduler tcp://127.0.0.1:8786
      seanv-analyze run --list-stages
    """
    from ..batch import load_pipeline, run_pipeline
    from ..batch.runner import owned_outputs
    from ..errors import DataError

    if list_stages:
        from ..stages import describe_stages
        click.echo(describe_stages())
        return 0
    if pipeline is None:
        raise click.UsageError("Missing argument 'PIPELINE' (a TOML file or a shipped name: "
                               "paper, flowfit, tracking).")
    pipe = with_figure_options(load_pipeline(pipeline), no_figures=no_figures, formats=formats)
    datas: list[Path]
    if data is None:
        from ..demo import demo_datasets
        datas = demo_datasets()
        click.echo("no DATA given: using the built-in simulated paper data sets "
                   f"({', '.join(map(str, datas))})", err=True)
        out = Path(out_dir) if out_dir else Path("outputs") / "demo" / f"run-{pipe.name}"
    else:
        datas = [data]
        out = Path(out_dir) if out_dir else default_out_dir(data, f"run-{pipe.name}")
    check_out_dir(datas, out, files=[pipe.source, rig_file], owned=owned_outputs(pipe))
    if scheduler is None and workers is None and os.environ.get("DASK_SCHEDULER_ADDRESS"):
        scheduler = os.environ["DASK_SCHEDULER_ADDRESS"]
    try:
        result = run_pipeline(pipe, datas, out_dir=out, workers=workers, scheduler=scheduler,
                              force=force, quiet=quiet, rig=rig_file, command=sys.argv,
                              reuse=True)
    except DataError as exc:  # no run could be read: say which runs were bad and why
        return unusable(data, bad_runs(datas, rig_file, exc), exc)
    if as_json:
        click.echo(result.to_json())
    else:
        click.echo(result.summary_text())
    failures_to_stderr(result)   # what went wrong is an error: on stderr, -q or not
    return 0 if result.success else 1


def failures_to_stderr(result) -> None:
    """The bad runs and the failed stages of ``result``, one line each, on
    stderr (the exit code 1 says there are some; the summary on stdout lists
    them too)."""
    if result.stage_errors:
        click.echo(f"{len(result.stage_errors)} stage(s) failed:", err=True)
        for name, msg in result.stage_errors.items():
            click.echo(f"  {name}: {msg}", err=True)
    if result.failed:
        click.echo(f"{len(result.failed)} bad run(s) skipped:", err=True)
        for f in result.failed:
            click.echo(f"  [{f.stage}] {f.message}", err=True)


def with_figure_options(pipe, *, no_figures: bool, formats: tuple[str, ...]):
    """The pipeline without its figures stage (``--no-figures``), or with
    the figures stage writing ``formats`` when they differ from the default."""
    from ..batch import parse_pipeline

    if not no_figures and formats == ("png", "svg"):
        return pipe
    doc = pipe.to_dict()
    if no_figures:
        doc["stages"] = [s for s in doc["stages"] if s["name"] != "figures"]
    else:
        for s in doc["stages"]:
            if s["name"] == "figures":
                s["formats"] = list(formats)
    return parse_pipeline(doc, source=pipe.source)


def bad_runs(datas: list[Path], rig_file: Path | None, exc: Exception) -> list:
    """The runs of DATA that cannot be read or summarised (the failure path:
    read again to list every one), or ``exc`` raised when DATA holds none."""
    from ..errors import DataError
    from ..stages import Context, dataset

    try:
        ctx = Context.for_data(datas, rig=rig_file)
    except DataError:
        raise exc from None
    return list(dataset.collect(ctx, {}).failed)
