"""-q/--quiet and -v/--verbose on every command, logging underneath.

On a terminal a command says on stderr what it is doing (one line per step)
unless given -q; piped (as here) its stderr holds only what went wrong
unless given -v; -vv puts the time and module on each line; stdout (the
result, or the --json document) is the same either way. Library calls print
nothing until logging is configured.
"""
from __future__ import annotations

import json
import logging

import pytest
from click.testing import CliRunner

from seanv_analysis.cli import cli

COMMANDS = ("ingest", "flowfit", "tracking", "validate", "discover", "identify", "simulate",
            "plots", "run")


@pytest.mark.parametrize("command", COMMANDS)
def test_every_command_has_quiet_and_verbose(command):
    res = CliRunner().invoke(cli, [command, "--help"])
    assert res.exit_code == 0
    assert "-q, --quiet" in res.output and "-v, --verbose" in res.output


@pytest.fixture
def flow(tmp_path, make_dataset):
    return make_dataset(tmp_path / "data", n_flow=14)


def _flowfit(flow, tmp_path, *extra):
    return CliRunner().invoke(cli, ["flowfit", str(flow), "--out", str(tmp_path / "out"),
                                    "--n-boot", "0", "--json", *extra])


def test_steps_on_stderr_with_verbose_none_by_default_when_piped(flow, tmp_path):
    loud = _flowfit(flow, tmp_path, "-v")
    quiet = _flowfit(flow, tmp_path)
    assert loud.exit_code == quiet.exit_code == _flowfit(flow, tmp_path, "-q").exit_code
    assert "ingest: reading, checking and summarising 14 run folder(s)" in loud.stderr
    assert "flowfit: eq. (3)-(5) per side" in loud.stderr
    assert quiet.stderr == "" and _flowfit(flow, tmp_path, "-q").stderr == ""
    strip = ("created_at", "elapsed_s")
    a, b = json.loads(loud.stdout), json.loads(quiet.stdout)
    assert {k: v for k, v in a.items() if k not in strip} == \
        {k: v for k, v in b.items() if k not in strip}


def test_very_verbose_lines_carry_time_and_module(flow, tmp_path):
    res = _flowfit(flow, tmp_path, "-vv")
    line = next(s for s in res.stderr.splitlines() if "ingest: reading" in s)
    assert "seanv_analysis.stages INFO:" in line and line[:4].isdigit()


def test_library_calls_print_nothing_until_configured(flow, capsys):
    from seanv_analysis.stages import run_stages

    logger = logging.getLogger("seanv_analysis")
    saved = (list(logger.handlers), logger.level, logger.propagate)
    for h in list(logger.handlers):          # as in a fresh interpreter
        if h.get_name() == "seanv-analyze-stderr":
            logger.removeHandler(h)
    logger.setLevel(logging.NOTSET)
    logger.propagate = True
    try:
        run_stages(flow, ["ingest"])
        assert capsys.readouterr().err == ""
    finally:
        logger.handlers[:], logger.level, logger.propagate = saved


def test_steps_shown_by_default_on_a_terminal(monkeypatch):
    import io

    from seanv_analysis import log

    class Tty(io.StringIO):
        def isatty(self):
            return True

    tty = Tty()
    monkeypatch.setattr("sys.stderr", tty)
    monkeypatch.delenv("CI", raising=False)
    logger = logging.getLogger("seanv_analysis")
    saved = (list(logger.handlers), logger.level, logger.propagate)
    try:
        assert log.configure() == logging.INFO
        logging.getLogger("seanv_analysis.stages").info("a step")
        assert tty.getvalue() == "a step\n"
        assert log.configure(quiet=True) == logging.WARNING
    finally:
        logger.handlers[:], logger.level, logger.propagate = saved
