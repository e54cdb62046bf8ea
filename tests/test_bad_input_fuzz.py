"""Hostile and careless inputs through every data command.

The rule: a bad single run gives exactly one line on stderr naming the file
(and the column and row where they apply), exit code 2, no traceback and
nothing written into the data folder; a data set goes on past bad runs, lists
them at the end and exits 1. Inputs a user would reasonably expect to work
(a UTF-8 BOM, CRLF line ends, blanks or another case in the header, quoted
numbers, integer Parquet columns, "Supply", ...) are read as if written to
the contract; where accepting would mean guessing (decimal commas, another
separator or encoding), the message says what was expected.
"""
from __future__ import annotations

import atexit
import functools
import json
import os
import re
import shutil
import signal
import tempfile
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner
from conftest import snapshot, write_synthetic_dataset, write_synthetic_run
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from seanv_analysis.cli import cli
from seanv_analysis.errors import DataError
from seanv_analysis.io import read_run
from seanv_analysis.io.validate import read_run_json

DURATION_S = 0.3
COMMANDS = {
    "ingest": ["ingest"],
    "flowfit": ["flowfit", "--n-boot", "0"],
    "tracking": ["tracking", "--no-figures"],
    "validate": ["validate", "--no-figures"],
    "discover": ["discover"],
    "run": ["run", "paper", "--workers", "1", "-q"],
    "plots": ["plots", "--workers", "1", "-q"],
}


# helpers ---------------------------------------------------------------------

@contextmanager
def deadline(seconds: int):
    """Fail instead of hanging (e.g. on a FIFO opened for reading)."""
    def boom(*_):
        raise TimeoutError(f"no answer within {seconds} s")
    old = signal.signal(signal.SIGALRM, boom)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def invoke(command: str, data: Path, out: Path, *extra: str):
    with deadline(60):
        return CliRunner().invoke(cli, [*COMMANDS[command], str(data), "--out", str(out), *extra])


def assert_one_line(result, *patterns: str, code: int = 2) -> str:
    """Exit ``code``, exactly one 'error: ' line on stderr matching every pattern."""
    assert "Traceback" not in result.stderr, result.stderr
    assert result.exception is None or isinstance(result.exception, SystemExit), result.exception
    assert result.exit_code == code, result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("error: "), lines[0]
    for pattern in patterns:
        assert re.search(pattern, lines[0]), (pattern, lines[0])
    return lines[0]


def make(root: Path, kind: str = "flow_step", fmt: str = "csv", **kw) -> Path:
    return write_synthetic_run(root, kind, run_id="run", fmt=fmt, duration_s=DURATION_S,
                               seed=1, **kw)


def edit_lines(path: Path, func) -> None:
    lines = path.read_text().splitlines()
    path.write_text("\n".join(func(i, line) for i, line in enumerate(lines)) + "\n")


def edit_header(path: Path, func) -> None:
    edit_lines(path, lambda i, line: func(line) if i == 0 else line)


def edit_meta(run_dir: Path, **changes) -> None:
    doc = json.loads((run_dir / "run.json").read_text())
    doc.update(changes)
    (run_dir / "run.json").write_text(json.dumps(doc))


def raw_meta(run_dir: Path, field: str, literal: str) -> None:
    """Replace a run.json field's value by a raw JSON literal (e.g. a 400-digit integer)."""
    path = run_dir / "run.json"
    doc = json.loads(path.read_text())
    doc[field] = "@@"
    path.write_text(json.dumps(doc).replace('"@@"', literal))


def replace_parquet(path: Path, func) -> None:
    table = func(pq.read_table(path))
    path.unlink()
    pq.write_table(table, path)


def set_column(table: pa.Table, name: str, values) -> pa.Table:
    return table.set_column(table.column_names.index(name), name, values)


def shift_time(run_dir: Path, offset_s: float) -> None:
    for path in run_dir.glob("*.csv"):
        edit_lines(path, lambda i, line: line if i == 0 else
                   ",".join([repr(float(line.split(",")[0]) + offset_s), *line.split(",")[1:]]))


# accepted as a user would expect ------------------------------------------------

def _bom(d):
    for name in ("encoder.csv", "pressure.csv", "run.json"):
        (d / name).write_bytes(b"\xef\xbb\xbf" + (d / name).read_bytes())


def _crlf(d):
    for path in d.glob("*.csv"):
        path.write_bytes(path.read_bytes().replace(b"\n", b"\r\n"))


ACCEPTED = {
    "bom_csv_and_run_json": _bom,
    "crlf": _crlf,
    "cr_only": lambda d: (d / "servo.csv").write_bytes((d / "servo.csv").read_bytes()
                                                      .replace(b"\n", b"\r")),
    "header_blanks": lambda d: edit_header(d / "pressure.csv",
                                           lambda h: ",".join(f" {x} " for x in h.split(","))),
    "header_upper_case": lambda d: edit_header(d / "encoder.csv", str.upper),
    "header_mixed_case_servo": lambda d: edit_header(d / "servo.csv",
                                                     lambda h: "T_s, Cam_Cmd_Deg ,CAM_DEG"),
    "quoted_numbers": lambda d: edit_lines(d / "encoder.csv", lambda i, line: ",".join(
        f'"{x}"' for x in line.split(","))),
    "trailing_comma_every_line": lambda d: edit_lines(d / "encoder.csv",
                                                      lambda i, line: line + ","),
    "scientific_notation": lambda d: edit_lines(d / "encoder.csv", lambda i, line: line if i == 0
                                                else ",".join(f"{float(x):.17e}"
                                                              for x in line.split(","))),
    "blanks_around_values": lambda d: edit_lines(d / "pressure.csv", lambda i, line: line if i == 0
                                                 else ", ".join(line.split(","))),
    "side_capitalised": lambda d: edit_meta(d, side=" Supply"),
    "kind_capitalised": lambda d: edit_meta(d, kind="Flow_Step"),
    "started_at_space_no_zone": lambda d: edit_meta(d, started_at="2026-03-02 10:14:05"),
    "started_at_date_only": lambda d: edit_meta(d, started_at="2026-03-02"),
    "leading_blank_line": lambda d: (d / "encoder.csv").write_text(
        "\n" + (d / "encoder.csv").read_text()),
}


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The unmodified run read once: accepted variants must read the same."""
    root = tmp_path_factory.mktemp("reference")
    return read_run(make(root), hash_files=False)


@pytest.mark.parametrize("name", list(ACCEPTED))
def test_reasonable_variants_read_as_the_contract_form(tmp_path, reference, name):
    run_dir = make(tmp_path / "data")
    ACCEPTED[name](run_dir)
    run = read_run(run_dir, hash_files=False)
    assert run.meta.side == "supply" and run.meta.kind == "flow_step"
    for table, df in reference.tables.items():
        got = run.tables[table][list(df.columns)]
        np.testing.assert_allclose(got.to_numpy(float), df.to_numpy(float), rtol=1e-15,
                                   err_msg=f"{name}: {table}")


@pytest.mark.parametrize("name, mutate", [
    ("int64", lambda t: set_column(t, "position_mm", pa.array(
        np.round(t.column("position_mm").to_numpy()).astype(np.int64)))),
    ("float32", lambda t: t.cast(pa.schema([pa.field(n, pa.float32()) for n in t.column_names]))),
    ("strings", lambda t: t.cast(pa.schema([pa.field(n, pa.string()) for n in t.column_names]))),
    ("header_case_and_blanks", lambda t: t.rename_columns([" T_S", "Position_mm "])),
])
def test_parquet_types_and_names_accepted(tmp_path, name, mutate):
    run_dir = make(tmp_path / "data", fmt="parquet")
    replace_parquet(run_dir / "encoder.parquet", mutate)
    enc = read_run(run_dir, hash_files=False).tables["encoder"]
    assert list(enc.columns[:2]) == ["t_s", "position_mm"]
    assert enc["t_s"].dtype == np.float64 and enc["position_mm"].dtype == np.float64


@pytest.mark.parametrize("kind", ["flow_step", "position_control"])
@pytest.mark.parametrize("offset_s", [1.7e9, -5.0])
def test_clock_not_starting_at_zero(tmp_path, kind, offset_s):
    """Epoch-second or negative time stamps are fine (validate simulates on the run's own clock)."""
    run_dir = make(tmp_path / "data", kind)
    shift_time(run_dir, offset_s)
    before = snapshot(tmp_path / "data")
    command = "ingest" if kind == "flow_step" else "validate"
    res = invoke(command, run_dir, tmp_path / "out")
    assert res.exit_code == 0 and "Traceback" not in res.stderr, res.output
    assert snapshot(tmp_path / "data") == before


def test_short_run_and_servo_off_target_are_not_errors(tmp_path):
    short = write_synthetic_run(tmp_path / "data", run_id="short", duration_s=0.05)
    off = make(tmp_path / "data")  # servo feedback never reaches cam_deg
    edit_lines(off / "servo.csv", lambda i, line: line if i == 0 else
               ",".join([*line.split(",")[:2], "-15.0"]))
    for run_dir in (short, off):
        res = invoke("ingest", run_dir, tmp_path / f"out-{run_dir.name}")
        assert res.exit_code == 0 and res.stderr == "", res.output


# rejected: one line, the file (column, row), exit 2 ----------------------------

def _latin1_header(d):
    p = d / "encoder.csv"
    p.write_bytes(p.read_bytes().replace(b"position_mm", b"position_mm,temp\xe9rature", 1)
                  .replace(b"\n", b",20\n").replace(b"rature,20\n", b"rature\n", 1))


def _fifo(d):
    (d / "encoder.csv").unlink()
    os.mkfifo(d / "encoder.csv")


def _link(d, name, target):
    (d / name).unlink()
    os.symlink(target, d / name)


def _blank_line_then_bad_number(d):
    p = d / "pressure.csv"
    lines = p.read_text().splitlines()
    lines[5] = lines[5].split(",")[0] + ",x,1,0.3"
    p.write_text("\n" + "\n".join(lines) + "\n")


def _parquet_column(name, values):
    def mutate(d):
        replace_parquet(d / "encoder.parquet", lambda t: set_column(t, name, values(t.num_rows)))
    return mutate


BIG = "1" * 400  # a JSON integer no float holds
REJECTED = [
    # CSV dialects that would need a guess
    ("semicolon", lambda d: (d / "encoder.csv").write_text(
        (d / "encoder.csv").read_text().replace(",", ";")),
     [r"encoder\.csv: header \"t_s;position_mm\" is semicolon-separated; expected "
      r"comma-separated"]),
    ("semicolon_decimal_comma", lambda d: (d / "encoder.csv").write_text(
        (d / "encoder.csv").read_text().replace(",", ";").replace(".", ",")),
     [r"encoder\.csv: .*semicolon-separated.*'\.' as the decimal point"]),
    ("tab", lambda d: (d / "servo.csv").write_text((d / "servo.csv").read_text()
                                                   .replace(",", "\t")),
     [r"servo\.csv: .* is tab-separated"]),
    ("decimal_comma_quoted", lambda d: edit_lines(d / "pressure.csv", lambda i, line: line if i != 4
                                                  else line.split(",")[0] + ',"3,3",1.7,0.35'),
     [r"pressure\.csv, column 'p_supply_mpag', row 4: value \"3,3\" is not a number "
      r"\(decimal comma\? write '\.' as the decimal point\)"]),
    ("latin1_header", _latin1_header,
     [r"encoder\.csv: header line is not UTF-8 text .*Latin-1"]),
    ("only_bom", lambda d: (d / "encoder.csv").write_bytes(b"\xef\xbb\xbf\r\n"),
     [r"encoder\.csv: empty file"]),
    ("names_equal_after_case", lambda d: edit_lines(d / "encoder.csv", lambda i, line: line + (
        ",T_S" if i == 0 else ",0")),
     [r"encoder\.csv, column 't_s': appears twice in the header"]),
    ("blank_first_line_and_bad_number", _blank_line_then_bad_number,
     [r"pressure\.csv, column 'p_supply_mpag', row 5: value \"x\" is not a number"]),
    # entries that are not regular files
    ("folder_named_encoder_csv", lambda d: ((d / "encoder.csv").unlink(),
                                            (d / "encoder.csv").mkdir()),
     [r"encoder\.csv: is a folder"]),
    ("looping_link", lambda d: _link(d, "servo.csv", "servo.csv"),
     [r"servo\.csv: is a broken or looping symbolic link"]),
    ("fifo", _fifo, [r"encoder\.csv: is not a regular file"]),
    ("device", lambda d: _link(d, "pressure.csv", os.devnull),
     [r"pressure\.csv: is not a regular file"]),
    ("run_json_looping_link", lambda d: _link(d, "run.json", "run.json"),
     [r"run\.json: cannot read file"]),
    ("run_json_folder", lambda d: ((d / "run.json").unlink(), (d / "run.json").mkdir()),
     [r"run\.json: is a folder"]),
    # Parquet integers a float64 cannot hold
    ("parquet_epoch_ns", _parquet_column("t_s", lambda n: pa.array(
        1_772_446_445_000_000_001 + np.arange(n, dtype=np.int64) * 1_000_000)),
     [r"encoder\.parquet, column 't_s', row 1: value 1772446445000000001 \(int64\) does not "
      r"convert exactly to float64"]),
    ("parquet_uint64_max", _parquet_column("position_mm", lambda n: pa.array(
        np.full(n, 2**64 - 1, dtype=np.uint64))),
     [r"encoder\.parquet, column 'position_mm', row 1: value 18446744073709551615"]),
    # run.json that json.loads or float() choke on
    ("run_json_deep", lambda d: (d / "run.json").write_text("[" * 100_000 + "]" * 100_000),
     [r"run\.json: not usable JSON \(nested too deeply\)"]),
    ("run_json_5000_digits", lambda d: (d / "run.json").write_text('{"a": ' + "9" * 5000 + "}"),
     [r"run\.json: not usable JSON"]),
    ("cam_huge_integer", lambda d: raw_meta(d, "cam_deg", BIG),
     [r"run\.json: field 'cam_deg': 1111.* is not a finite number"]),
    ("load_huge_integer", lambda d: raw_meta(d, "load_mpag", BIG),
     [r"run\.json: field 'load_mpag': 1111.* is not a finite number"]),
    ("kp_huge_integer", lambda d: raw_meta(d, "controller", '{"kp": %s, "flow_model": true}' % BIG),
     [r"run\.json: field 'controller\.kp': .* is not a finite number"]),
    ("rate_huge_integer", lambda d: raw_meta(
        d, "controller", '{"kp": 480, "flow_model": true, "rate_hz": %s}' % BIG),
     [r"run\.json: field 'controller\.rate_hz': .* is not a positive number"]),
    ("rig_huge_integer", lambda d: raw_meta(d, "rig", '{"supply": {"pressure_mpag": %s}}' % BIG),
     [r"run\.json: field 'rig\.supply\.pressure_mpag': .* is not a finite number"]),
    ("rig_zero_piston", lambda d: edit_meta(d, rig={"actuator": {"piston_diameter_mm": 0}}),
     [r"run\.json: field 'rig\.actuator\.piston_diameter_mm': 0 is not positive"]),
    ("rig_zero_c_flow", lambda d: edit_meta(d, rig={"valve": {"supply": {"c_flow": 0.0}}}),
     [r"run\.json: field 'rig\.valve\.supply\.c_flow': 0(\.0)? gives no flow"]),
    ("started_at_past_9999_in_utc", lambda d: edit_meta(d, started_at="9999-12-31T23:59:59-23:59"),
     [r"run\.json: field 'started_at': .* is out of range"]),
    ("started_at_year_1", lambda d: edit_meta(d, started_at="0001-01-01T00:00:00+01:00"),
     [r"run\.json: field 'started_at': .* is out of range"]),
    ("started_at_2300", lambda d: edit_meta(d, started_at="2300-01-01T00:00:00Z"),
     [r"run\.json: field 'started_at': \"2300-01-01T00:00:00Z\" is out of range"]),
    ("unicode_minus_cam", lambda d: edit_meta(d, cam_deg="\u22128"),
     [r"run\.json: field 'cam_deg': .* is not a finite number"]),
    # runs the analysis cannot use
    ("single_encoder_row", lambda d: (d / "encoder.csv").write_text("t_s,position_mm\n0,10\n"),
     [r"data/run: streams do not overlap in time"]),
    ("command_never_at_cam_deg", lambda d: edit_lines(d / "servo.csv", lambda i, line: line
                                                      if i == 0 else line.split(",")[0]
                                                      + ",-15.0,-15.0"),
     [r"servo\.csv, column 'cam_cmd_deg': no command within"]),
]
KIND = {"kp_huge_integer": "position_control", "rate_huge_integer": "position_control"}
FMT = {"parquet_epoch_ns": "parquet", "parquet_uint64_max": "parquet"}


@pytest.mark.parametrize("name, mutate, patterns", REJECTED, ids=[c[0] for c in REJECTED])
def test_bad_single_run_one_line_exit_2(tmp_path, name, mutate, patterns):
    run_dir = make(tmp_path / "data", KIND.get(name, "flow_step"), FMT.get(name, "csv"))
    mutate(run_dir)
    before = snapshot(tmp_path / "data")
    res = invoke("ingest", run_dir, tmp_path / "out")
    line = assert_one_line(res, *patterns)
    assert str(run_dir) in line and res.stdout == ""
    assert snapshot(tmp_path / "data") == before
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


# every command ---------------------------------------------------------------------

def _nan_cell(d):
    edit_lines(d / "pressure.csv", lambda i, line: line if i != 7 else
               line.split(",")[0] + ",nan," + ",".join(line.split(",")[2:]))


EVERY_COMMAND = [
    ("nan_cell", _nan_cell, [r"pressure\.csv, column 'p_supply_mpag', row 7: empty cell or NaN"]),
    ("run_json_list", lambda d: (d / "run.json").write_text("[]"),
     [r"run\.json: top level is a JSON list"]),
    ("run_json_deep", lambda d: (d / "run.json").write_text("[" * 50_000 + "]" * 50_000),
     [r"run\.json: not usable JSON"]),
    ("streams_apart", lambda d: edit_lines(d / "servo.csv", lambda i, line: line if i == 0 else
                                           ",".join([repr(float(line.split(",")[0]) + 100),
                                                     *line.split(",")[1:]])),
     [r"data/run: streams do not overlap in time"]),
    ("latin1_header", _latin1_header, [r"encoder\.csv: header line is not UTF-8"]),
]


@pytest.mark.parametrize("command", list(COMMANDS))
@pytest.mark.parametrize("name, mutate, patterns", EVERY_COMMAND, ids=[c[0] for c in EVERY_COMMAND])
def test_every_command_bad_single_run(tmp_path, command, name, mutate, patterns):
    kind = "position_control" if command in ("tracking", "validate") else "flow_step"
    run_dir = make(tmp_path / "data", kind)
    mutate(run_dir)
    before = snapshot(tmp_path / "data")
    res = invoke(command, run_dir, tmp_path / "out")
    assert_one_line(res, *patterns)
    assert snapshot(tmp_path / "data") == before


@pytest.fixture
def small_dataset(tmp_path):
    return write_synthetic_dataset(tmp_path / "data", n_flow=2, n_position=1, duration_s=0.2)


@pytest.mark.parametrize("command", list(COMMANDS))
def test_every_run_bad_lists_them_exit_1(tmp_path, small_dataset, command):
    runs = sorted(p for p in small_dataset.iterdir())
    (runs[0] / "run.json").write_text("{")
    for run in runs[1:]:
        (run / "encoder.csv").write_text("")
    before = snapshot(small_dataset)
    res = invoke(command, small_dataset, tmp_path / "out")
    assert res.exit_code == 1, res.output
    assert "Traceback" not in res.stderr
    text = res.stderr
    assert f"{len(runs)} bad run(s) skipped:" in text
    assert f"{runs[0]}/run.json: not valid JSON" in text
    for run in runs[1:]:
        assert f"{run}/encoder.csv: empty file" in text
    assert snapshot(small_dataset) == before


@pytest.mark.parametrize("command", list(COMMANDS))
def test_out_inside_data_refused(tmp_path, small_dataset, command):
    before = snapshot(small_dataset)
    res = invoke(command, small_dataset, small_dataset / "results")
    assert_one_line(res, r"--out: .* is inside the data folder")
    assert snapshot(small_dataset) == before


@pytest.mark.parametrize("command", ["tracking", "validate", "discover", "plots"])
@pytest.mark.parametrize("what", ["missing", "file"])
def test_data_path_missing_or_a_file_one_line(tmp_path, small_dataset, command, what):
    data = tmp_path / "nope" if what == "missing" else next(small_dataset.glob("*/run.json"))
    res = invoke(command, data, tmp_path / "out")
    assert_one_line(res, re.escape(str(data)), r"does not exist" if what == "missing" else "file")


def test_duplicate_run_ids_listed(tmp_path, small_dataset):
    shutil.copytree(small_dataset / "pos000", small_dataset / "copy-of-pos")
    res = invoke("ingest", small_dataset, tmp_path / "out")
    assert res.exit_code == 1
    assert "field 'run_id': 'pos000' is also the run id of" in res.stderr


def test_links_and_fifos_in_a_data_set_neither_crash_nor_hang(tmp_path):
    data = write_synthetic_dataset(tmp_path / "data", n_flow=1, n_position=1, duration_s=0.3)
    os.symlink("..", data / "pos000" / "up")          # a folder loop
    os.symlink("loop", data / "loop")                  # a looping file link
    os.mkfifo(data / "pos000" / "notes.fifo")          # never opened
    before = snapshot(data)
    for command in ("tracking", "ingest"):
        res = invoke(command, data, tmp_path / f"out-{command}")
        assert res.exit_code == 0 and "Traceback" not in res.stderr, res.output
    assert snapshot(data) == before


def test_validate_absurd_time_span_one_line(tmp_path):
    run_dir = make(tmp_path / "data", "position_control")
    for path in run_dir.glob("*.csv"):  # 0, 1e297, 2e297, ... "seconds"
        edit_lines(path, lambda i, line: line if i == 0 else ",".join(
            [repr(float(line.split(",")[0]) * 1e300), *line.split(",")[1:]]))
    res = invoke("validate", run_dir, tmp_path / "out")
    assert_one_line(res, r"encoder\.csv, column 't_s', row 2: median sample interval .* outside "
                         r"the plausible")


# generated variants -------------------------------------------------------------

_CELLS = st.one_of(
    st.sampled_from(["", " ", "nan", "inf", "-inf", "1e308", "-1e308", "1e-320", "0x10", "1,5",
                     '"1.5"', "1.5.3", "\u22128", "TRUE", "NA", "1e", ".", "+1", " 2 ", "1_000",
                     "\u00bd", "9" * 400]),
    st.floats().map(repr), st.integers().map(str), st.text(max_size=5))


@st.composite
def _mutated_table(draw):
    sources = _sources()
    kind = draw(st.sampled_from(sorted(sources)))
    src = sources[kind]
    table = draw(st.sampled_from(sorted(p.name for p in src.glob("*.csv"))))
    lines = (src / table).read_text().split("\n")
    ops = draw(st.lists(st.sampled_from(["cell", "drop", "dup", "swap", "header", "col", "blank",
                                         "cut", "trunc", "crlf", "bom", "bytes"]),
                        min_size=1, max_size=4))
    for op in ops:
        i = draw(st.integers(0, max(0, len(lines) - 1)))
        if op == "cell" and len(lines) > 1:
            j = draw(st.integers(1, len(lines) - 1))
            f = lines[j].split(",")
            f[draw(st.integers(0, len(f) - 1))] = draw(_CELLS)
            lines[j] = ",".join(f)
        elif op == "drop" and lines:
            lines.pop(i)
        elif op == "dup" and lines:
            lines.insert(i, lines[i])
        elif op == "swap" and len(lines) > 2:
            j = draw(st.integers(0, len(lines) - 1))
            lines[i], lines[j] = lines[j], lines[i]
        elif op == "header" and lines:
            h = lines[0].split(",")
            k = draw(st.integers(0, len(h) - 1))
            h[k] = draw(st.sampled_from([h[k].upper(), f" {h[k]} ", h[k] + "x", "", h[0],
                                         f'"{h[k]}"', "p_supply_kpag", "encoder_counts",
                                         "cam_pulse", "p_load_v"]))
            lines[0] = ",".join(h)
        elif op == "col":
            lines = [f"{line},{draw(_CELLS)}" if line else line for line in lines]
        elif op == "blank":
            lines.insert(i, "")
        elif op == "cut":
            lines = lines[: i + 1]
        elif op == "trunc" and lines and lines[i]:
            lines[i] = lines[i][: draw(st.integers(0, len(lines[i])))]
    raw = "\n".join(lines).encode("utf-8", errors="surrogatepass")
    if "crlf" in ops:
        raw = raw.replace(b"\n", b"\r\n")
    if "bom" in ops:
        raw = b"\xef\xbb\xbf" + raw
    if "bytes" in ops and raw:
        k = draw(st.integers(0, len(raw) - 1))
        raw = raw[:k] + draw(st.binary(min_size=1, max_size=4)) + raw[k + 1:]
    return src, table, raw


@functools.lru_cache(maxsize=1)
def _sources() -> dict[str, Path]:
    """One good short run of each kind to damage (written once, removed at exit)."""
    root = Path(tempfile.mkdtemp(prefix="seanv-fuzz-"))
    atexit.register(shutil.rmtree, root, True)
    return {kind: write_synthetic_run(root, kind, run_id=kind, duration_s=0.1, seed=1)
            for kind in ("flow_step", "position_control")}


@settings(max_examples=150, deadline=None, database=None,
          suppress_health_check=list(HealthCheck))
@given(_mutated_table())
def test_generated_csv_damage_is_data_error_or_read(tmp_path_factory, case):
    """Any damage to a table gives a one-line DataError naming that file, or a run that reads."""
    src, table, raw = case
    run_dir = tmp_path_factory.mktemp("gen") / src.name
    shutil.copytree(src, run_dir)
    (run_dir / table).write_bytes(raw)
    try:
        read_run(run_dir, hash_files=False)
    except DataError as exc:
        assert "\n" not in str(exc) and str(run_dir / table) in str(exc), str(exc)


_JSON = st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=6)
                     | st.integers(min_value=10**308, max_value=10**330),
                     lambda c: st.lists(c, max_size=3) | st.dictionaries(st.text(max_size=4), c,
                                                                         max_size=3),
                     max_leaves=5)
_FIELDS = {
    "schema": st.sampled_from(["seanv-run/1", "SEANV-RUN/1"]) | _JSON,
    "run_id": st.sampled_from(["r1", "a/b", ".x", "x" * 201]) | _JSON,
    "kind": st.sampled_from(["flow_step", "position_control", " Flow_Step", "FLOW"]) | _JSON,
    "started_at": st.sampled_from(["2026-03-02T10:14:05Z", "9999-12-31T23:59:59-23:59",
                                   "2026-13-01", "2026-03-02T10:14:05.1234567Z"])
    | st.datetimes().map(lambda d: d.isoformat()) | _JSON,
    "load_mpag": st.sampled_from([0.35, -0.35, None, 350]) | _JSON,
    "side": st.sampled_from(["supply", "Drain ", "up"]) | _JSON,
    "cam_deg": st.sampled_from([-8.0, -8]) | _JSON,
    "controller": st.fixed_dictionaries({"kp": _JSON, "flow_model": st.booleans() | _JSON},
                                        optional={"rate_hz": _JSON}) | _JSON,
    "rig": st.sampled_from([{}, None, {"actuator": {"piston_diameter_mm": -1}}]) | _JSON,
}


_VALID = {
    "flow_step": {"schema": "seanv-run/1", "run_id": "r1", "kind": "flow_step",
                  "started_at": "2026-03-02T10:14:05Z", "load_mpag": 0.35, "side": "supply",
                  "cam_deg": -8.0, "rig": {}},
    "position_control": {"schema": "seanv-run/1", "run_id": "r1", "kind": "position_control",
                         "started_at": "2026-03-02T10:14:05Z", "load_mpag": None,
                         "controller": {"kp": 480, "flow_model": True, "rate_hz": 100}},
}


@st.composite
def _run_json_docs(draw):
    """A valid run.json with one to three fields replaced (or dropped)."""
    doc = dict(_VALID[draw(st.sampled_from(sorted(_VALID)))])
    for name in draw(st.lists(st.sampled_from(sorted(_FIELDS)), min_size=1, max_size=3,
                              unique=True)):
        if draw(st.integers(0, 9)) == 0:
            doc.pop(name, None)
        else:
            doc[name] = draw(_FIELDS[name])
    return doc


@settings(max_examples=300, deadline=None, database=None,
          suppress_health_check=list(HealthCheck))
@given(_run_json_docs())
def test_generated_run_json_is_data_error_or_valid(tmp_path_factory, doc):
    import pandas as pd

    run_dir = tmp_path_factory.mktemp("meta")
    (run_dir / "run.json").write_text(json.dumps(doc))
    try:
        meta = read_run_json(run_dir, max_pressure_mpag=50.0)
    except DataError as exc:
        assert "\n" not in str(exc) and str(run_dir / "run.json") in str(exc), str(exc)
        return
    pd.Timestamp(meta.started_at)  # the summary's datetime64[ns] holds it
    json.dumps(meta.to_json_dict(), default=str)
