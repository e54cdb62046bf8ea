"""Issue 34, points 4 and 6 (pipeline files): a pipeline file is read as a
regular UTF-8 TOML file not nested too deeply, and each stage's options are
checked with their bounds (``seed`` a seed, ``n_boot`` at most 10 000
resamples) before any work: one line, exit 2."""
from __future__ import annotations

import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from seanv_analysis.cli import cli
from seanv_analysis.errors import ConfigError
from seanv_analysis.stages.pipeline import (
    MAX_N_BOOT,
    MAX_SEED,
    STAGE_NAMES,
    load_pipeline,
    parse_pipeline,
    stage_options,
)

HEAD = '[pipeline]\nname = "p"\n[[stages]]\nname = "ingest"\n'


@pytest.mark.parametrize("text, match", [
    (HEAD.encode() + b"# caf\xe9\n", r"not a valid TOML file \(not UTF-8: byte \d+\)"),
    ("x = " + "[" * 5000 + "]" * 5000 + "\n", r"not a valid TOML file \(nested too deeply\)"),
    ("x = " + "{a=" * 3000 + "1" + "}" * 3000 + "\n", r"nested too deeply"),
    (HEAD + '[[stages]]\nname = "discover"\nseed = -5\n',
     r"stage 'discover' option 'seed' = -5; expected a seed from 0 to 4294967295"),
    (HEAD + '[[stages]]\nname = "flowfit"\nn_boot = 1e9\n',
     r"option 'n_boot' = 1000000000\.0; expected a number of resamples from 0 to 10000"),
    (HEAD + '[[stages]]\nname = "flowfit"\nn_boot = 1000000000\n', r"from 0 to 10000"),
    (HEAD + '[[stages]]\nname = "flowfit"\nseed = 18446744073709551616\n', r"a seed from 0"),
    (HEAD + '[[stages]]\nname = "identify"\nn_boot = -1\n', r"from 0 to 10000"),
])
def test_a_bad_pipeline_file_is_one_config_error(tmp_path, text, match):
    path = tmp_path / "p.toml"
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    with pytest.raises(ConfigError, match=match) as info:
        load_pipeline(path)
    assert "\n" not in str(info.value) and str(path) in str(info.value)


def test_a_pipeline_that_is_a_device_is_refused():
    with pytest.raises(ConfigError, match="/dev/zero is neither a file nor a shipped pipeline"):
        load_pipeline("/dev/zero")


@pytest.mark.parametrize("args, match", [
    (["flowfit", "{data}", "--n-boot", "1000000000"], "--n-boot"),
    (["flowfit", "{data}", "--seed", "-5"], "--seed"),
    (["identify", "{data}", "--n-boot", "100000"], "--n-boot"),
    (["discover", "{data}", "--seed", "-5"], "--seed"),
])
def test_commands_bound_their_counts(hostile_data, tmp_path, args, match):
    res = CliRunner().invoke(cli, [a.format(data=hostile_data) for a in args]
                             + ["--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and match in res.output and "Traceback" not in res.output


def test_the_command_bounds_are_the_stages():
    from seanv_analysis.cli import discover_cmd, flowfit_cmd, identify_cmd

    def bound(cmd, name):
        opt = next(p for p in cmd.params if p.name == name)
        return opt.type.max

    assert bound(flowfit_cmd.flowfit_cmd, "n_boot") == MAX_N_BOOT
    assert bound(identify_cmd.identify_cmd, "n_boot") == MAX_N_BOOT
    assert bound(flowfit_cmd.flowfit_cmd, "seed") == MAX_SEED
    assert bound(discover_cmd.discover_cmd, "seed") == MAX_SEED


_leaf = st.one_of(st.none(), st.booleans(), st.integers(min_value=-10**20, max_value=10**20),
                  st.floats(allow_nan=True), st.text(max_size=8),
                  st.lists(st.one_of(st.integers(-5, 10), st.text(max_size=5)), max_size=3))


def _stage():
    names = st.one_of(st.sampled_from(STAGE_NAMES), st.text(max_size=6), st.integers())
    keys = st.sampled_from(sorted({k for o in stage_options().values() for k in o} | {"x"}))
    return st.builds(lambda name, opts: {"name": name, **opts}, names,
                     st.dictionaries(keys, _leaf, max_size=3))


@settings(max_examples=200, deadline=None, database=None,
          suppress_health_check=[HealthCheck.too_slow])
@given(st.fixed_dictionaries({}, optional={
    "pipeline": st.one_of(_leaf, st.dictionaries(st.sampled_from(["name", "description", "x"]),
                                                 _leaf, max_size=3)),
    "stages": st.one_of(_leaf, st.lists(st.one_of(_stage(), _leaf), max_size=4)),
    "other": _leaf}))
def test_fuzzed_pipelines_parse_or_fail_in_one_line(doc):
    try:
        pipe = parse_pipeline(doc, source="fuzz.toml")
    except ConfigError as exc:
        assert "\n" not in str(exc) and str(exc).startswith("fuzz.toml: ")
        return
    for stage in pipe.stages:
        for key in ("seed", "n_boot"):
            if key in stage.options:
                assert 0 <= stage.options[key] <= (MAX_SEED if key == "seed" else MAX_N_BOOT)
