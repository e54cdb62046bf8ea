"""Small helpers shared by the CLI commands (output folders, bad-run lists,
the built-in simulated data sets)."""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import click

__all__ = ["default_out_dir", "echo_bad_runs", "sim_default_dataset", "OUTPUTS_ROOT"]

OUTPUTS_ROOT = Path("outputs")


def default_out_dir(data: str | Path, command: str) -> Path:
    """``outputs/<dataset-name>/<command>/`` (never inside the data folder)."""
    name = Path(data).resolve().name or "dataset"
    return OUTPUTS_ROOT / name / command


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
    under ``outputs/_builtin/`` (keyed by scenario, seed, effects and package version)."""
    from .. import __version__
    from ..sim import simulate_scenario

    key = hashlib.sha256(json.dumps([scenario, seed, list(effects), __version__]).encode()).hexdigest()[:10]
    path = OUTPUTS_ROOT / "_builtin" / f"{scenario}-{key}"
    done = path / ".complete"
    if not done.exists():
        simulate_scenario(scenario, path, seed=seed, effects=list(effects))
        done.write_text("ok\n")
    return path
