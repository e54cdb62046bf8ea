"""The notebook API (issue 33, point 3): a top-level function per command
with the command's option names, checked exactly as the CLI and a pipeline
TOML are; ``run_stages`` refuses an unknown stage or option with the TOML's
messages."""
from __future__ import annotations

import inspect
import json

import pytest
from click.testing import CliRunner

import seanv_analysis as sa
from seanv_analysis.cli import cli
from seanv_analysis.errors import ConfigError
from seanv_analysis.stages import run_stages
from seanv_analysis.stages.pipeline import load_pipeline

#: command -> the function's keyword arguments, each the CLI option's name
#: (--n-boot: n_boot); the CLI options that only the CLI has are left out
CLI_ONLY = {"out", "json", "no_figures", "formats", "quiet", "verbose", "help", "list_stages"}


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    from conftest import write_synthetic_dataset

    return write_synthetic_dataset(tmp_path_factory.mktemp("api") / "d", n_flow=6, n_position=2,
                                   duration_s=1.0)


@pytest.mark.parametrize("command", ["flowfit", "tracking", "validate", "identify", "discover",
                                     "run"])
def test_every_command_is_a_function_with_its_option_names(command):
    func = getattr(sa, command)
    assert command in sa.__all__ and func.__doc__
    params = {p.name for p in inspect.signature(func).parameters.values()
              if p.kind is p.KEYWORD_ONLY}
    options = {p.name for p in cli.commands[command].params if p.param_type_name == "option"}
    flags = {opt.lstrip("-").replace("-", "_") for p in cli.commands[command].params
             if p.param_type_name == "option" for opt in p.opts if opt.startswith("--")}
    assert options  # the CLI command exists
    missing = flags - params - CLI_ONLY
    assert not missing, f"sa.{command} lacks the CLI's {sorted(missing)}"
    assert params <= flags | {"out"}, f"sa.{command} has {sorted(params - flags)} the CLI has not"


def test_tracking_function_is_the_command(data, tmp_path):
    res = CliRunner().invoke(cli, ["tracking", str(data), "--shift", "0.25", "--json",
                                   "--no-figures", "--out", str(tmp_path / "o")])
    assert res.exit_code == 0, res.output
    tr = sa.tracking(data, shift=0.25)
    assert json.loads(res.stdout)["rmse_mm3_s"] == tr.rmse_mm3_s
    assert sa.tracking(sa.load_dataset(data), shift=0.25).rmse_mm3_s == tr.rmse_mm3_s


def test_a_misspelt_or_bad_option_is_refused(data):
    with pytest.raises(TypeError, match="shfit"):
        sa.tracking(data, shfit=0.25)
    with pytest.raises(ConfigError, match=r"'shift_s' \(shift=\) = 25"):
        sa.tracking(data, shift=25)
    with pytest.raises(ConfigError, match="'n_boot' = -1"):
        sa.flowfit(data, n_boot=-1)
    with pytest.raises(ConfigError, match="side = 'both sides'"):
        sa.flowfit(data, side="both sides")


@pytest.mark.parametrize("names,options,toml", [
    (["ingest", "tracking"], {"tracking": {"shift": 0.25}},
     '[[stages]]\nname = "ingest"\n[[stages]]\nname = "tracking"\nshift = 0.25\n'),
    (["ingest", "trackin"], None, '[[stages]]\nname = "ingest"\n[[stages]]\nname = "trackin"\n'),
    (["ingest", "tracking"], {"tracking": {"shift_s": "0.25"}},
     '[[stages]]\nname = "ingest"\n[[stages]]\nname = "tracking"\nshift_s = "0.25"\n'),
], ids=["misspelt option", "unknown stage", "bad value"])
def test_run_stages_refuses_as_a_pipeline_file_does(data, tmp_path, names, options, toml):
    path = tmp_path / "p.toml"
    path.write_text('[pipeline]\nname = "p"\n' + toml)
    with pytest.raises(ConfigError) as from_toml:
        load_pipeline(path)
    with pytest.raises(ConfigError) as from_call:
        run_stages(data, names, options=options)
    said = str(from_toml.value).split(": ", 1)[1]
    assert str(from_call.value) == f"run_stages: {said}"
    assert not isinstance(from_call.value, KeyError)


def test_identify_and_discover_are_commands_and_their_subpackages():
    """``seanv_analysis.identify`` and ``.discover`` are also subpackages,
    which the import system sets on the package when imported: they are
    callable (the command) and stay the modules (their names)."""
    import seanv_analysis.discover
    import seanv_analysis.identify  # noqa: F401
    from seanv_analysis import api
    from seanv_analysis.identify import identify_rig

    for name in ("identify", "discover"):
        func = getattr(sa, name)
        assert callable(func)
        assert inspect.signature(func) == inspect.signature(getattr(api, name))
    assert sa.identify.identify_rig is identify_rig
    assert sa.discover.__name__ == "seanv_analysis.discover"
