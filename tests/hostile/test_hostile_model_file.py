"""Issue 34, point 4 (model files): a --model file is checked against the
model schema (``_data_schema/model/schema.toml``): known keys, finite values
in range, the schema version, an increasing cam range, a side's geometry
whole. Discover's effects and proposed term are simulated by
`validate --model` and refused, one line, by the commands that cannot
apply them; never ignored."""
from __future__ import annotations

import json
import tomllib

import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from seanv_analysis.cli import cli
from seanv_analysis.config import load_rig
from seanv_analysis.errors import ConfigError
from seanv_analysis.io.model_file import read_model, read_model_file
from seanv_analysis.models import ValveModel

RIG = load_rig()
GOOD = ValveModel.from_rig(RIG).to_dict()
EFFECTS = [{"name": "backlash", "side": "both", "params": {"width_deg": 2.0},
            "params_ci95": {}, "params_units": {}, "p_value": 0.01}]
TERM = "term:side=supply,mode=mul,expr=-0.2*tanh(dp/0.5)"


def _write(tmp_path, doc, name="model.json"):
    path = tmp_path / name
    path.write_text(json.dumps(doc))
    return path


def _with(**changes):
    doc = json.loads(json.dumps(GOOD))
    for dotted, value in changes.items():
        *tables, last = dotted.split("__")
        d = doc
        for t in tables:
            d = d[t]
        if value is DROP:
            d.pop(last)
        else:
            d[last] = value
    return doc


DROP = object()


@pytest.mark.parametrize("changes, match", [
    ({"supply__c_flow": float("nan")}, r"supply\.c_flow = nan is not a finite number"),
    ({"drain__c_flow": 0}, r"drain\.c_flow = 0 gives no flow"),
    ({"supply__z0_mm": 1e308}, r"supply\.z0_mm = 1e\+308 is outside the plausible range"),
    ({"cam_range_deg": [10.0, -40.0]}, r"cam_range_deg = \[10\.0, -40\.0\] is not increasing"),
    ({"cam_range_deg": [-40.0]}, r"cam_range_deg = \[-40\.0\] is not two finite numbers"),
    ({"schema": "seanv-valve-model/9"}, r"schema = 'seanv-valve-model/9' is not a schema"),
    ({"supply__dp_exponent": -1}, r"supply\.dp_exponent = -1 is not positive"),
    ({"supply__geometry__needle_diameter_mm": "3"}, r"needle_diameter_mm = '3' is not a finite"),
    ({"supply__geometry__spring_constant_n_per_mm": DROP}, r"supply\.geometry lacks spring_constant"),
    ({"drain__z0_mm": DROP}, r"drain\.z0_mm is missing"),
    ({"supply__extra_key": 1}, r"unknown key 'supply\.extra_key'"),
    ({"effect": []}, r"unknown key 'effect'"),
    ({"effects": [{"name": "gremlin", "side": "supply", "params": {}}]},
     r"effects\[0\]: unknown effect 'gremlin'"),
    ({"effects": [{"name": "backlash", "side": "both", "params": {"width_deg": -3}}]},
     r"effects\[0\]: backlash"),
    ({"effects": "backlash"}, r"effects = 'backlash' is not a list"),
    ({"proposed_term": "backlash:width_deg=1"}, r"proposed_term = .*expected a term:"),
    ({"proposed_term": "term:side=supply,mode=mul,expr=import os"}, r"proposed_term = "),
])
def test_a_bad_model_file_is_one_config_error(tmp_path, changes, match):
    path = _write(tmp_path, _with(**changes))
    with pytest.raises(ConfigError, match=match) as info:
        read_model_file(path, rig=RIG)
    assert "\n" not in str(info.value) and str(path) in str(info.value)


@pytest.mark.parametrize("content, match", [
    ("[" * 100000 + "]" * 100000, r"nested too deeply"),
    ("[1, 2]", r"not a valve model file \(a list"),
    ('{"supply": 1, "drain": 2}', r"supply = 1 is not a table"),
    (b"\xff\xfe{}", r"not a valve model file"),
    (b"{\"a\": \"\xff\"}", r"not UTF-8"),
])
def test_unreadable_model_files(tmp_path, content, match):
    path = tmp_path / "m.json"
    path.write_bytes(content if isinstance(content, bytes) else content.encode())
    with pytest.raises(ConfigError, match=match):
        read_model_file(path, rig=RIG)
    with pytest.raises(ConfigError, match="not a regular file"):
        read_model_file("/dev/zero", rig=RIG)


def test_a_hand_written_model_with_c_takes_the_rigs_geometry(tmp_path):
    path = tmp_path / "m.toml"
    path.write_text("[supply]\nz0_mm = -0.1\nC = 17.0\n[drain]\nz0_mm = -0.02\nC = -22.0\n")
    model, effects = read_model_file(path, rig=RIG)
    assert model.supply.c_flow == 17.0 and effects == ()
    path.write_text("[supply]\nz0_mm = -0.1\nC = 17.0\nc_flow = 17.0\n[drain]\nz0_mm = 0\nC = -2.0\n")
    with pytest.raises(ConfigError, match="both C and c_flow"):
        read_model_file(path, rig=RIG)


def test_effects_and_the_proposed_term_are_read_as_simulator_specs(tmp_path):
    path = _write(tmp_path, {**GOOD, "effects": EFFECTS, "proposed_term": TERM})
    model, effects = read_model_file(path, rig=RIG)
    assert effects == ("backlash:width_deg=2.0", TERM)
    with pytest.raises(ConfigError, match=r"holds effects or a proposed term \(backlash:width_deg"
                                          r"=2\.0, term:.*use `validate --model`"):
        read_model(path, rig=RIG)


@pytest.fixture(scope="module")
def position_data(tmp_path_factory):
    from conftest import write_synthetic_dataset

    return write_synthetic_dataset(tmp_path_factory.mktemp("pos") / "data", n_flow=0,
                                   n_position=1)


def test_validate_model_simulates_the_files_effects(position_data, tmp_path, monkeypatch):
    """The probe: `validate --model` silently ignored effects and proposed_term."""
    import seanv_analysis.stages.validate as stage

    seen = []
    real = stage.validate_model

    def spy(ctx, model, effects=(), **kwargs):
        seen.append(tuple(effects))
        return real(ctx, model, effects, **kwargs)

    monkeypatch.setattr(stage, "validate_model", spy)
    path = _write(tmp_path, {**GOOD, "effects": EFFECTS, "proposed_term": TERM})
    res = CliRunner().invoke(cli, ["validate", str(position_data), "--model", str(path),
                                   "--out", str(tmp_path / "o"), "--no-figures", "-q"])
    assert res.exit_code in (0, 1), res.output
    assert seen == [("backlash:width_deg=2.0", TERM)]
    manifest = json.loads((tmp_path / "o" / "manifest.json").read_text())
    assert manifest["extra"]["effects"] == ["backlash:width_deg=2.0", TERM]


@pytest.mark.parametrize("command", ["tracking", "discover"])
def test_commands_that_cannot_apply_effects_refuse_them(position_data, tmp_path, command):
    path = _write(tmp_path, {**GOOD, "effects": EFFECTS})
    res = CliRunner().invoke(cli, [command, str(position_data), "--model", str(path),
                                   "--out", str(tmp_path / "o"), "-q"])
    assert res.exit_code == 2 and res.output.count("\n") == 1, res.output
    assert "which this command cannot apply" in res.output


@pytest.mark.parametrize("changes", [{"supply__c_flow": float("nan")},
                                     {"cam_range_deg": [10.0, -40.0]}])
def test_validate_refuses_a_nan_or_inverted_model(position_data, tmp_path, changes):
    """The probe: c_flow = NaN gave 'position fit -7.3e16 %' and exit 0; an
    inverted cam range was accepted."""
    path = _write(tmp_path, _with(**changes))
    res = CliRunner().invoke(cli, ["validate", str(position_data), "--model", str(path),
                                   "--out", str(tmp_path / "o"), "-q"])
    assert res.exit_code == 2 and res.output.count("\n") == 1, res.output
    assert "Traceback" not in res.output


# fuzz ----------------------------------------------------------------------------

_number = st.one_of(st.floats(allow_nan=True, allow_infinity=True),
                    st.integers(min_value=-10**20, max_value=10**20),
                    st.sampled_from([0, -1, 1e308, 2.5, 17.435, -22.6, -0.1]))
_leaf = st.one_of(_number, st.text(max_size=4), st.booleans(), st.none(),
                  st.lists(_number, max_size=3))
_side_keys = st.sampled_from(["z0_mm", "c_flow", "C", "dp_exponent", "geometry", "x"])


def _docs():
    side = st.dictionaries(_side_keys, st.one_of(_leaf, st.dictionaries(
        st.sampled_from(["needle_diameter_mm", "seat_diameter_mm", "z_p_mm", "q"]), _leaf,
        max_size=3)), max_size=5)
    return st.fixed_dictionaries(
        {"supply": side, "drain": side},
        optional={"schema": st.sampled_from(["seanv-valve-model/1", "x", 1]),
                  "cam_range_deg": st.lists(_number, max_size=3),
                  "effects": st.lists(st.dictionaries(
                      st.sampled_from(["name", "side", "params"]),
                      st.one_of(st.sampled_from(["backlash", "drift", "term", "supply", "both"]),
                                st.dictionaries(st.sampled_from(["width_deg", "step", "every"]),
                                                _number, max_size=2))), max_size=2),
                  "proposed_term": st.one_of(st.text(max_size=10), st.just(TERM)),
                  "extras": st.dictionaries(st.text(max_size=3), _leaf, max_size=2)})


@settings(max_examples=150, deadline=None, database=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(_docs())
def test_fuzzed_model_files_read_or_fail_in_one_line(tmp_path, doc):
    path = tmp_path / "m.json"
    try:
        path.write_text(json.dumps(doc, allow_nan=True))
    except ValueError:
        return
    try:
        model, _ = read_model_file(path, rig=RIG)
    except ConfigError as exc:
        assert "\n" not in str(exc) and str(path) in str(exc)
        return
    for side in (model.supply, model.drain):
        assert side.c_flow != 0 and abs(side.c_flow) < float("inf")
    assert model.cam_min_deg < model.cam_max_deg


def test_the_model_schema_is_a_toml_file():
    from seanv_analysis.config import schema_dir

    with open(schema_dir() / "model" / "schema.toml", "rb") as fh:
        assert tomllib.load(fh)["version"] == "seanv-valve-model/1"
