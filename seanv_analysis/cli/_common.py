"""Small helpers shared by the CLI commands (output folders, bad-run lists,
the built-in simulated data sets)."""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import click

__all__ = ["default_out_dir", "check_out_dir", "echo_bad_runs", "explain_unusable",
           "sim_default_dataset", "OUTPUTS_ROOT"]

OUTPUTS_ROOT = Path("outputs")


def default_out_dir(data: str | Path, command: str) -> Path:
    """``outputs/<dataset-name>/<command>/`` (never inside the data folder)."""
    name = Path(data).resolve().name or "dataset"
    return OUTPUTS_ROOT / name / command


def check_out_dir(data: str | Path | None, out: str | Path) -> None:
    """Refuse an output folder inside (or equal to) the data folder.

    Raises
    ------
    DataError
        ``out`` is ``data`` or lies under it (symbolic links resolved).
    """
    from ..errors import DataError

    if data is None or not Path(data).is_dir():
        return
    d, o = Path(data).resolve(), Path(out).resolve()
    if o == d or d in o.parents:
        raise DataError(f"--out: {out} is inside the data folder; outputs never go into raw "
                        "data: choose another --out (default: outputs/<dataset>/<command>/ under "
                        "the current folder)", path=data)


def explain_unusable(data: str | Path | None, rig, exc: Exception) -> int:
    """After a command's library call refused DATA (``exc``, e.g. "no valid
    runs"), say which runs were bad and why.

    A single run folder that is bad: its own one-line DataError is raised
    (exit 2). A data set with bad runs: ``exc``'s line, then the bad runs
    listed; returns 1. Otherwise (or without DATA) ``exc`` is raised again.
    """
    from ..errors import DataError
    from ..io.reader import is_run_dir

    if data is None or not Path(data).is_dir():
        raise exc
    if rig is None or isinstance(rig, (str, Path)):
        from ..config import load_rig
        rig = load_rig(rig)
    from ..summary import dataset_errors

    errors = [e.message for e in dataset_errors(data, rig=rig)]
    single = is_run_dir(data)
    if not errors:
        msg = " ".join(str(exc).split())
        if single and isinstance(exc, DataError) and str(data) not in msg:
            raise DataError(msg, path=data) from None  # name the run folder at least
        raise exc
    if single:
        raise DataError(errors[0]) from None
    click.echo(f"error: {' '.join(str(exc).split())}", err=True)
    return echo_bad_runs(errors)


def echo_bad_runs(errors) -> int:
    """List bad runs on stderr, one line each; return the exit code (1 if any)."""
    if not errors:
        return 0
    click.echo(f"{len(errors)} bad run(s) skipped:", err=True)
    for err in errors:
        click.echo(f"  {getattr(err, 'message', err)}", err=True)
    return 1


def sim_default_dataset(scenario: str, *, seed: int = 0, effects: tuple[str, ...] = ()) -> Path:
    """Path of a built-in simulated data set, generated on first use and cached
    under ``outputs/_builtin/`` (keyed by scenario, seed, effects and the
    simulator's version: package version + hash of its sources and rig)."""
    from ..batch.cache import simulator_version
    from ..sim import simulate_scenario

    key = hashlib.sha256(json.dumps([scenario, seed, list(effects),
                                     simulator_version()]).encode()).hexdigest()[:10]
    path = OUTPUTS_ROOT / "_builtin" / f"{scenario}-{key}"
    done = path / ".complete"
    if not done.exists():
        simulate_scenario(scenario, path, seed=seed, effects=list(effects))
        done.write_text("ok\n")
    return path
