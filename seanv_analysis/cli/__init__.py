"""Command-line interface ``seanv-analyze``: a thin click layer.

Each subcommand lives in its own module (``*_cmd.py``) and only parses
options, calls library functions and formats their results. Library errors
(:class:`~seanv_analysis.errors.SeanvError`) become one line on stderr and
exit code 2, with no traceback; any other exception (a bug) one line naming
the command, the stage and the data, exit code 3, its traceback only with
``-v``. A command may return an int exit code
(e.g. 1 when a batch had bad runs). Ctrl-C exits 130 and SIGTERM 143 (queued
per-run work cancelled, worker processes killed; what was done is cached).
"""
from __future__ import annotations

import sys

import click

from ..errors import SeanvError, os_error_line

__all__ = ["cli", "main"]

class Terminated(BaseException):
    """Raised in the main thread by the SIGTERM handler :func:`main` installs,
    so the command unwinds (queued work cancelled, workers killed) and exits
    143; a BaseException like KeyboardInterrupt, so no "except Exception" of a
    stage takes it for a failure of the stage."""


def _stop_simulations() -> None:
    """Stop the compiled simulations running on any thread of this process
    (they would finish their runs first: a kernel does not see Python's
    signals), and refuse new ones: the command is ending."""
    compiled = sys.modules.get("seanv_analysis.sim.compiled")
    if compiled is not None:
        compiled.stop_all()


def _on_sigterm(signum, frame):  # pragma: no cover - exercised through a subprocess
    _stop_simulations()
    raise Terminated()


def _on_sigint(signum, frame):  # pragma: no cover - exercised through a subprocess
    _stop_simulations()
    raise KeyboardInterrupt()


class _SeanvGroup(click.Group):
    """Group that turns SeanvError into 'error: ...' + exit 2, Ctrl-C into
    exit 130, SIGTERM into exit 143, and int returns into exit codes."""

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        ctx.meta["seanv.args"] = list(args)   # the command line, for an internal error's line
        return super().parse_args(ctx, args)

    def invoke(self, ctx: click.Context):
        try:
            rv = super().invoke(ctx)
        except KeyboardInterrupt:
            click.echo("interrupted (Ctrl-C): queued work cancelled; a re-run resumes from "
                       "the cache", err=True)
            ctx.exit(130)
        except Terminated:
            click.echo("terminated (SIGTERM): queued work cancelled; a re-run resumes from "
                       "the cache", err=True)
            ctx.exit(143)
        except SeanvError as exc:
            click.echo(f"error: {exc}", err=True)
            ctx.exit(2)
        except BrokenPipeError:
            raise
        except OSError as exc:
            # output side (read-only folder, disk full, --out under a file):
            # one line naming the path, not a traceback after all the work
            click.echo(f"error: {os_error_line(exc)}", err=True)
            ctx.exit(2)
        except click.BadParameter as exc:
            if isinstance(exc, click.MissingParameter):
                raise  # click's usage block says what is missing
            # a bad path or value (DATA not found, a file given as DATA, ...): one
            # line like the data errors, not click's usage block
            click.echo(f"error: {' '.join(exc.format_message().split())}", err=True)
            ctx.exit(2)
        except (click.exceptions.Exit, click.ClickException, click.Abort):
            raise
        except Exception as exc:   # a bug: one line, exit 3; the traceback with -v
            click.echo(internal_error_line(exc, ctx), err=True)
            if _verbose():
                import traceback

                traceback.print_exception(exc, file=sys.stderr)
            ctx.exit(3)
        if isinstance(rv, int) and rv:
            ctx.exit(rv)
        return rv


def internal_error_line(exc: BaseException, ctx: click.Context) -> str:
    """One line for an exception that is not the package's own: the command,
    its arguments, the stage it happened in (the innermost frame under
    ``seanv_analysis/stages/``) and where, and what to do."""
    import traceback
    from pathlib import Path

    frames = traceback.extract_tb(exc.__traceback__)
    stage = next((Path(f.filename).stem for f in reversed(frames)
                  if Path(f.filename).parent.name == "stages"), None)
    where = f" at {Path(frames[-1].filename).name}:{frames[-1].lineno}" if frames else ""
    import shlex

    args = shlex.join(ctx.meta.get("seanv.args", []))
    message = " ".join(str(exc).split()) or "(no message)"
    return (f"internal error in 'seanv-analyze {args}'"
            + (f", stage {stage}" if stage else "")
            + f": {type(exc).__name__}: {message}{where}. This is a bug of seanv-analysis, "
            "not of your data: run again with -v for the traceback and report it")


def _verbose() -> bool:
    """-v was given: the package's logger shows details."""
    import logging

    return logging.getLogger("seanv_analysis").isEnabledFor(logging.DEBUG)


def _print_version(ctx: click.Context, _param, value: bool) -> None:
    """``--version``: the package's version (looked up only when asked)."""
    if not value or ctx.resilient_parsing:
        return
    from .. import __version__

    click.echo(f"seanv-analyze, version {__version__}")
    ctx.exit()


@click.group(cls=_SeanvGroup,
             context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.option("--version", is_flag=True, expose_value=False, is_eager=True,
              callback=_print_version, help="Show the version and exit.")
def cli() -> None:
    """Analyse SEANV water-hydraulic valve rig logs.

    Units everywhere: mm, MPa gauge, deg, s, mm^3/s.

    \b
    Typical session:
      seanv-analyze simulate paper-flowsteps --out data/flow   # or use your rig's logs
      seanv-analyze ingest data/flow                           # validate, derive flow, filter
      seanv-analyze flowfit data/flow                          # z0, C per side (eq. 3-5)
      seanv-analyze simulate paper-position --out data/pos
      seanv-analyze tracking data/pos --shift 0.25             # the paper's procedure
      seanv-analyze identify data/flow data/pos                # your rig: geometry, servo, line
      seanv-analyze validate data/pos --model outputs/flow/flowfit/model.toml
      seanv-analyze discover data/flow                         # what the model misses
      seanv-analyze run paper data                             # all of it + report.html
    Without DATA, flowfit/tracking/validate/discover use a built-in simulated set.
    Every command writes under outputs/<dataset>/ and prints JSON with --json.

    \b
    Exit codes: 0 done; 1 some runs or stages failed (listed, the rest done);
    2 bad input, one line naming the file; 3 a bug of the package, one line
    (-v for the traceback); 130 Ctrl-C; 143 SIGTERM.
    """


# the subcommands register themselves on ``cli`` when imported
from . import (  # noqa: E402,F401
    discover_cmd,
    flowfit_cmd,
    identify_cmd,
    ingest_cmd,
    plots_cmd,
    run_cmd,
    simulate_cmd,
    tracking_cmd,
    validate_cmd,
)


def main(argv: list[str] | None = None) -> None:
    """Console-script entry point (SIGTERM unwinds like Ctrl-C: exit 143).

    At exit the garbage collector's objects are frozen (``gc.freeze``, the
    last exit handler): the interpreter's final collections then skip the
    objects the command made (pandas, scipy, matplotlib modules and data),
    which took 0.3-0.5 s of a 4-6 s ``run flowfit`` (0.05-0.07 s frozen,
    measured on 2 cores). Objects are still freed by reference counting;
    only reference cycles left at exit are not collected, which Python does
    not promise either."""
    import atexit
    import gc
    import signal

    from ..config import default_one_blas_thread

    default_one_blas_thread()   # before numpy loads; a user's setting wins
    from ..batch.process_setup import return_large_blocks_to_os

    atexit.register(gc.freeze)   # registered first: runs after the other exit handlers
    return_large_blocks_to_os()
    signal.signal(signal.SIGTERM, _on_sigterm)
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:   # not ignored (nohup, &)
        signal.signal(signal.SIGINT, _on_sigint)
    cli.main(args=argv, prog_name="seanv-analyze")


if __name__ == "__main__":  # pragma: no cover
    main(sys.argv[1:])
