"""Issue 34, point 4 (rig files): a rig file, a --rig of any command and a
run.json "rig" object are checked against the rig schema
(``_data_schema/rig/schema.toml``: known keys, types, finite values within
ranges with units, the schema version, the keys that bound each other). NaN,
lists, 0, 1e308, inf, 1e9 segments, deep nesting, a negative stroke, a zero
mass, 2.5 tube segments, ``schema = "seanv-rig/99"``, a 1e-9 s time step:
one line naming the file, the key and what is expected, exit 2, nothing run."""
from __future__ import annotations

import math
import tomllib

import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from seanv_analysis.cli import cli
from seanv_analysis.config import check_rig, load_rig, load_schema
from seanv_analysis.errors import ConfigError, DataError

BAD = [
    ("[valve.supply]\nneedle_x_c_mm = nan\n", r"valve\.supply\.needle_x_c_mm = nan is not a finite number"),
    ("[valve]\nneedle_diameter_mm = [3.0]\n", r"valve\.needle_diameter_mm = \[3\.0\] is not a finite"),
    ("[actuator]\nmoving_mass_kg = 0\n", r"actuator\.moving_mass_kg = 0 is not positive"),
    ("[tube]\nlength_m = 1e308\n", r"tube\.length_m = 1e\+308 is outside the plausible range"),
    ("[supply]\npressure_mpag = inf\n", r"supply\.pressure_mpag = inf is not a finite number"),
    ("[sim]\ntube_segments = 1000000000\n", r"sim\.tube_segments = 1000000000 is outside"),
    ("[sim]\ntube_segments = 2.5\n", r"sim\.tube_segments = 2\.5 is not an integer"),
    ("[sim]\ntime_step_s = 1e-9\n", r"sim\.time_step_s = 1e-09 is outside the plausible range; "
                                    r"expected a finite number >= 1e-05 and <= 0\.01 \[s\]"),
    ("[actuator]\nstroke_mm = -75.0\n", r"actuator\.stroke_mm = -75\.0 is not positive"),
    ("[actuator]\npiston_diameter_mm = -16.0\n", r"actuator\.piston_diameter_mm = -16\.0 is not positive"),
    ('schema = "seanv-rig/99"\n', r"schema = 'seanv-rig/99' is not a schema this version reads"),
    ("name = 5\n", r"name = 5 is not a string"),
    ("[valve]\ncam_min_deg = 20.0\n", r"valve\.cam_min_deg = 20\.0 is not below valve\.cam_max_deg"),
    ("[sensors]\nencoder_rate_hz = 100000.0\n",
     r"analysis\.max_run_duration_s x sensors\.encoder_rate_hz = 3\.6e\+08 samples"),
    ("[sim.deeper]\nx = 1\n", r"unknown rig key 'deeper'"),
    ("[valve]\nsupply = 3\n", r"rig key 'supply' must be a table"),
    ("a = " + "[" * 2000 + "]" * 2000 + "\n", r"not a valid TOML file \(nested too deeply\)"),
    (b"[sim]\n# \xff\xfe\n", r"not a valid TOML file \(not UTF-8"),
    ("[analysis]\ncam_range_deg = [10.0, -40.0]\n", r"analysis\.cam_range_deg = \[10\.0, -40\.0\] is not increasing"),
]


@pytest.mark.parametrize("text, match", BAD, ids=range(len(BAD)))
def test_a_bad_rig_file_is_one_config_error(tmp_path, text, match):
    path = tmp_path / "rig.toml"
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    with pytest.raises(ConfigError, match=match) as info:
        load_rig(path)
    assert "\n" not in str(info.value) and str(path) in str(info.value)


@pytest.mark.parametrize("command", [["simulate", "paper-position", "--out", "{tmp}/sim"],
                                     ["flowfit", "{data}", "--out", "{tmp}/o"],
                                     ["identify", "{data}", "--out", "{tmp}/o"],
                                     ["run", "paper", "{data}", "--out", "{tmp}/o"]],
                         ids=lambda c: c[0])
def test_commands_refuse_a_nan_rig_before_any_work(hostile_data, tmp_path, command):
    """The probe: `simulate --rig` with a NaN needle exited 0 and wrote
    position 9e15; identify, flowfit and run gave tracebacks."""
    (tmp_path / "rig.toml").write_text("[valve.supply]\nneedle_x_c_mm = nan\n")
    args = [a.format(tmp=tmp_path, data=hostile_data) for a in command]
    res = CliRunner().invoke(cli, [*args, "--rig", str(tmp_path / "rig.toml"), "-q"])
    assert res.exit_code == 2, res.output
    assert "Traceback" not in res.output and res.output.count("\n") == 1, res.output
    assert "needle_x_c_mm = nan is not a finite number" in res.output
    for folder in (tmp_path / "sim", tmp_path / "o"):   # nothing written (at most the folder)
        assert not folder.exists() or not any(folder.iterdir())


def test_a_special_file_as_rig_is_refused(tmp_path):
    with pytest.raises(ConfigError, match="not a regular file"):
        load_rig("/dev/zero")


def test_the_schema_covers_every_key_of_the_default_rig():
    with open(load_rig.__globals__["default_rig_path"](), "rb") as fh:
        default = tomllib.load(fh)

    def flat(d, prefix=""):
        for k, v in d.items():
            if isinstance(v, dict):
                yield from flat(v, f"{prefix}{k}.")
            else:
                yield f"{prefix}{k}"

    assert set(flat(default)) == set(load_schema("rig"))
    check_rig(load_rig().data)


def _run_with_rig(tmp_path, rig_object):
    from conftest import write_synthetic_run

    from seanv_analysis.io.reader import read_run

    run = write_synthetic_run(tmp_path, "flow_step", rig=rig_object)
    return lambda: read_run(run)


@pytest.mark.parametrize("rig_object, match", [
    ({"analysis": {"max_run_duration_s": 1e12}},
     r"field 'rig\.analysis\.max_run_duration_s': a run may not change this plausibility guard"),
    ({"analysis": {"min_sample_interval_s": 1e-12}}, r"may not change this plausibility guard"),
    ({"sensors": {"encoder_rate_hz": 1e9}},
     r"field 'rig\.sensors\.encoder_rate_hz': 1000000000\.0 is outside the plausible range"),
    ({"sensors": {"encoder_rate_hz": 5e4}}, r"run\.json: field 'rig': analysis\.max_run_duration_s x "
                                            r"sensors\.encoder_rate_hz = 1\.8e\+08 samples"),
    ({"sim": {"tube_segments": 2.5}}, r"field 'rig\.sim\.tube_segments': 2\.5 is not an integer"),
    ({"actuator": {"stroke_mm": -1}}, r"field 'rig\.actuator\.stroke_mm': -1 is not positive"),
])
def test_a_run_json_rig_override_cannot_lift_the_guards(tmp_path, rig_object, match):
    """The probe: a run.json rig override lifted the time-span guard
    (MemoryError traceback after asking for 7.28 TiB)."""
    read = _run_with_rig(tmp_path, rig_object)
    with pytest.raises(DataError, match=match):
        read()


# fuzz --------------------------------------------------------------------------

_SCHEMA = load_schema("rig")
_KEYS = sorted(k for k in _SCHEMA if k not in ("schema", "name"))
_values = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True), st.integers(min_value=-10**30, max_value=10**30),
    st.booleans(), st.text(max_size=5), st.lists(st.floats(allow_nan=False), max_size=3),
    st.sampled_from([0, -1, 1e308, -1e308, 1e-9, 2.5, 3, 1e9, 0.01]),
    st.dictionaries(st.text(max_size=3), st.integers(), max_size=2))


def _nest(flat: dict) -> dict:
    out: dict = {}
    for key, value in flat.items():
        *tables, last = key.split(".")
        d = out
        for t in tables:
            d = d.setdefault(t, {})
            if not isinstance(d, dict):
                break
        else:
            d[last] = value
    return out


@settings(max_examples=120, deadline=None, database=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(st.dictionaries(st.sampled_from(_KEYS + ["valve.nope", "sim.x.y", "extra"]), _values,
                       min_size=1, max_size=4))
def test_fuzzed_rig_files_load_valid_or_fail_in_one_line(tmp_path, flat):
    path = tmp_path / "rig.toml"
    from seanv_analysis.io.model_file import dumps_toml

    try:
        text = dumps_toml(_nest(flat))
        tomllib.loads(text)
    except (tomllib.TOMLDecodeError, TypeError, ValueError):
        return   # a document the writer cannot spell in TOML: not the point here
    path.write_text(text)
    try:
        rig = load_rig(path)
    except ConfigError as exc:
        assert "\n" not in str(exc) and str(path) in str(exc)
        return
    for key, spec in _SCHEMA.items():   # whatever loads is within the schema
        if spec["type"] == "number" and not spec.get("inf"):
            d = rig.data
            for part in key.split("."):
                d = d[part]
            assert math.isfinite(d)
