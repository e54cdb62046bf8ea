"""Issue 34, point 7: no command prints a traceback without -v. An exception
that is not the package's own (a bug) is one line naming the command, the
stage and the data, exit code 3; with -v the traceback follows."""
from __future__ import annotations

import pytest
from click.testing import CliRunner

from seanv_analysis.cli import cli
from seanv_analysis.stages.base import Context


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    from conftest import write_synthetic_dataset

    return write_synthetic_dataset(tmp_path_factory.mktemp("bug") / "data", n_flow=3,
                                   n_position=1)


def _bug(*args, **kwargs):
    raise ZeroDivisionError("a bug\nover two lines")


COMMANDS = [["flowfit", "{data}"], ["tracking", "{data}"], ["validate", "{data}"],
            ["discover", "{data}"], ["identify", "{data}"], ["ingest", "{data}"],
            ["plots", "{data}"], ["run", "paper", "{data}"], ["simulate", "paper-position"]]


@pytest.mark.parametrize("command", COMMANDS, ids=lambda c: c[0])
def test_a_bug_is_one_line_and_exit_3(command, data, tmp_path, monkeypatch):
    monkeypatch.setattr(Context, "for_data", classmethod(_bug))
    monkeypatch.setattr("seanv_analysis.sim.scenarios.simulate_scenario", _bug)
    args = [a.format(data=data) for a in command] + ["--out", str(tmp_path / "o")]
    res = CliRunner().invoke(cli, args)
    assert res.exit_code == 3, res.output
    # plots first says which analyses it runs (one line), then the bug
    lines = [ln for ln in res.output.splitlines()
             if ln.strip() and not ln.startswith("plots: the figures asked for need")]
    assert "Traceback" not in res.output
    assert len(lines) == 1, res.output
    assert lines[0].startswith(f"internal error in 'seanv-analyze {command[0]}")
    assert "ZeroDivisionError: a bug over two lines" in lines[0]
    assert str(data) in lines[0] or command[0] == "simulate"
    verbose = CliRunner().invoke(cli, [*args, "-v"])
    assert verbose.exit_code == 3 and "Traceback (most recent call last)" in verbose.output


def test_the_line_names_the_stage(data, tmp_path, monkeypatch):
    monkeypatch.setattr("seanv_analysis.fit.fit_flow", _bug)
    res = CliRunner().invoke(cli, ["flowfit", str(data), "--out", str(tmp_path / "o")])
    assert res.exit_code == 3, res.output
    assert ", stage flowfit: ZeroDivisionError" in res.output
