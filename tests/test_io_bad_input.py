"""Every documented bad input raises DataError naming file, column, row, value.

``CASES`` is shared with tests/test_cli_ingest.py, which runs each of them
through the CLI (exit 2, one stderr line, nothing written into the data).
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
from conftest import DROP, synthetic_tables, write_synthetic_run

from seanv_analysis.errors import DataError
from seanv_analysis.io import read_run

DURATION_S = 0.2  # small runs: 201 encoder rows, 20 servo rows


def set_cell(path: Path, row: int, column: str, value: str) -> None:
    """Set a CSV cell; ``row`` is the 1-based data row (header not counted)."""
    lines = path.read_text().splitlines()
    header = lines[0].split(",")
    fields = lines[row].split(",")
    fields[header.index(column)] = value
    lines[row] = ",".join(fields)
    path.write_text("\n".join(lines) + "\n")


def drop_column(path: Path, column: str) -> None:
    lines = [l.split(",") for l in path.read_text().splitlines()]
    i = lines[0].index(column)
    path.write_text("\n".join(",".join(f[:i] + f[i + 1:]) for f in lines) + "\n")


def scale_column(path: Path, column: str, factor: float) -> None:
    lines = [l.split(",") for l in path.read_text().splitlines()]
    i = lines[0].index(column)
    for f in lines[1:]:
        f[i] = repr(float(f[i]) * factor)
    path.write_text("\n".join(",".join(f) for f in lines) + "\n")


def edit_meta(run_dir: Path, **changes) -> None:
    path = run_dir / "run.json"
    doc = json.loads(path.read_text())
    for k, v in changes.items():
        if v is DROP:
            doc.pop(k, None)
        else:
            doc[k] = v
    path.write_text(json.dumps(doc))


@dataclass(frozen=True)
class Case:
    id: str
    mutate: Callable[[Path], None]
    match: str
    kind: str = "flow_step"
    fmt: str = "csv"

    def build(self, root: Path) -> Path:
        run_dir = write_synthetic_run(root, self.kind, run_id="run", fmt=self.fmt,
                                      duration_s=DURATION_S, seed=1)
        self.mutate(run_dir)
        return run_dir


def _swap_rows(path: Path, a: int, b: int) -> None:
    lines = path.read_text().splitlines()
    lines[a], lines[b] = lines[b], lines[a]
    path.write_text("\n".join(lines) + "\n")


def _dup_timestamp(path: Path) -> None:
    lines = path.read_text().splitlines()
    t = lines[9].split(",")[0]
    set_cell(path, 10, "t_s", t)


def _garbage(path: Path) -> None:
    path.write_bytes(np.random.default_rng(7).integers(0, 256, 4096, dtype=np.uint8).tobytes())


def _garbage_cell(path: Path) -> None:
    data = path.read_bytes().split(b"\n")
    data[12] = b"0.011,\xff\xfe\x80\x91"
    path.write_bytes(b"\n".join(data))


def _parquet_with_string(run_dir: Path) -> None:
    df = synthetic_tables(duration_s=DURATION_S)["encoder"].astype({"position_mm": object})
    df.loc[6, "position_mm"] = "n/a"
    df["position_mm"] = df["position_mm"].astype(str)
    (run_dir / "encoder.parquet").unlink()
    df.to_parquet(run_dir / "encoder.parquet", index=False)


def _both_raw(run_dir: Path) -> None:
    p = run_dir / "pressure.csv"
    lines = p.read_text().splitlines()
    lines[0] = lines[0].replace("p_supply_mpag", "p_supply_v")
    lines = [l + ("," + ("p_supply_kpag" if i == 0 else "3300")) for i, l in enumerate(lines)]
    p.write_text("\n".join(lines) + "\n")


CASES = [
    # files
    Case("missing_file", lambda d: (d / "servo.csv").unlink(), r"servo\.csv: missing required file"),
    Case("missing_controller_file", lambda d: (d / "controller.csv").unlink(),
         r"controller\.csv: missing required file", kind="position_control"),
    Case("csv_and_parquet", lambda d: (d / "encoder.parquet").write_bytes(b"PAR1"),
         r"encoder\.csv: both encoder\.csv and encoder\.parquet exist"),
    Case("empty_file", lambda d: (d / "encoder.csv").write_text(""), r"encoder\.csv: empty file"),
    Case("header_only", lambda d: (d / "pressure.csv").write_text(
        "t_s,p_supply_mpag,p_head_mpag,p_load_mpag\n"), r"pressure\.csv: header only, no data rows"),
    Case("binary_garbage", lambda d: _garbage(d / "encoder.csv"),
         r"encoder\.csv.*binary data \(NUL byte"),
    Case("binary_cell", lambda d: _garbage_cell(d / "encoder.csv"),
         r"encoder\.csv, column 'position_mm', row 12: value .* is not a number"),
    Case("ragged_row", lambda d: set_cell(d / "servo.csv", 4, "cam_deg", "1,2"),
         r"servo\.csv, row 4: row has 4 fields, the header has 3"),
    Case("not_parquet", lambda d: (d / "servo.parquet").write_bytes(b"this is not parquet" * 10),
         r"servo\.parquet: not a readable Parquet file", fmt="parquet"),
    # columns
    Case("missing_column", lambda d: drop_column(d / "pressure.csv", "p_head_mpag"),
         r"pressure\.csv, column 'p_head_mpag': missing .*expected 'p_head_mpag' \[MPaG\]"),
    Case("missing_t_s", lambda d: drop_column(d / "servo.csv", "t_s"),
         r"servo\.csv, column 't_s': missing"),
    Case("duplicate_column", lambda d: (d / "encoder.csv").write_text(
        "t_s,position_mm,position_mm\n0,1,2\n0.001,1,2\n"),
         r"encoder\.csv, column 'position_mm': appears twice in the header"),
    Case("both_raw_alternatives", _both_raw,
         r"pressure\.csv, column 'p_supply_mpag': raw columns p_supply_v, p_supply_kpag both given"),
    # values
    Case("non_numeric", lambda d: set_cell(d / "pressure.csv", 5, "p_supply_mpag", "abc"),
         r"pressure\.csv, column 'p_supply_mpag', row 5: value \"abc\" is not a number; "
         r"expected a decimal number \[MPaG\]"),
    Case("non_numeric_parquet", _parquet_with_string,
         r"encoder\.parquet, column 'position_mm', row 7: value \"n/a\" is not a number", fmt="parquet"),
    Case("nan_required", lambda d: set_cell(d / "encoder.csv", 7, "position_mm", "nan"),
         r"encoder\.csv, column 'position_mm', row 7: empty cell or NaN; expected a finite number"),
    Case("empty_cell_required", lambda d: set_cell(d / "pressure.csv", 3, "p_load_mpag", ""),
         r"pressure\.csv, column 'p_load_mpag', row 3: empty cell or NaN"),
    Case("inf_required", lambda d: set_cell(d / "servo.csv", 2, "cam_cmd_deg", "inf"),
         r"servo\.csv, column 'cam_cmd_deg', row 2: value inf; expected a finite number"),
    Case("inf_in_nullable", lambda d: set_cell(d / "servo.csv", 2, "cam_deg", "-inf"),
         r"servo\.csv, column 'cam_deg', row 2: value -inf; expected a finite number or an empty cell"),
    Case("nan_timestamp", lambda d: set_cell(d / "encoder.csv", 1, "t_s", "nan"),
         r"encoder\.csv, column 't_s', row 1: empty cell or NaN"),
    Case("non_monotonic", lambda d: _swap_rows(d / "encoder.csv", 20, 21),
         r"encoder\.csv, column 't_s', row 21: timestamp 0\.019 is before the previous row's 0\.02"),
    Case("duplicated_timestamp", lambda d: _dup_timestamp(d / "pressure.csv"),
         r"pressure\.csv, column 't_s', row 10: duplicated timestamp 0\.008"),
    Case("kpa_pressure", lambda d: scale_column(d / "pressure.csv", "p_supply_mpag", 1000.0),
         r"pressure\.csv, column 'p_supply_mpag', row 1: value 33\d\d\.\d+ is above the plausible "
         r"50 MPaG .*looks like kPa or Pa"),
    Case("pa_pressure", lambda d: scale_column(d / "pressure.csv", "p_load_mpag", 1e6),
         r"pressure\.csv, column 'p_load_mpag', row 1: value .* looks like kPa or Pa"),
    # run.json
    Case("run_json_missing", lambda d: (d / "run.json").unlink(), r"run\.json: missing; expected a run folder holding run\.json"),
    Case("run_json_not_json", lambda d: (d / "run.json").write_text('{"schema": "seanv-run/1",'),
         r"run\.json: not valid JSON \(line 1, column 26"),
    Case("run_json_binary", lambda d: (d / "run.json").write_bytes(b"\xff\xfe{\x00}"),
         r"run\.json: not UTF-8 text"),
    Case("run_json_list", lambda d: (d / "run.json").write_text("[1, 2]"),
         r"run\.json: top level is a JSON list; expected a JSON object"),
    Case("missing_run_id", lambda d: edit_meta(d, run_id=DROP), r"field 'run_id': missing"),
    Case("unsafe_run_id", lambda d: edit_meta(d, run_id="../evil"),
         r"field 'run_id': \"\.\./evil\" is not a safe file name"),
    Case("wrong_schema", lambda d: edit_meta(d, schema="seanv-run/2"),
         r"run\.json: field 'schema': \"seanv-run/2\" is not supported; expected 'seanv-run/1'"),
    Case("unknown_kind", lambda d: edit_meta(d, kind="sweep"),
         r"field 'kind': \"sweep\" is unknown; expected one of flow_step, position_control"),
    Case("missing_side", lambda d: edit_meta(d, side=DROP),
         r"field 'side': missing; required for kind 'flow_step'"),
    Case("bad_side", lambda d: edit_meta(d, side="up"), r"field 'side': \"up\" is unknown"),
    Case("missing_cam", lambda d: edit_meta(d, cam_deg=DROP),
         r"field 'cam_deg': missing; required for kind 'flow_step'"),
    Case("cam_not_number", lambda d: edit_meta(d, cam_deg="-8"),
         r"field 'cam_deg': \"-8\" is not a finite number"),
    Case("missing_controller", lambda d: edit_meta(d, controller=DROP),
         r"field 'controller': missing; required for kind 'position_control'", kind="position_control"),
    Case("bad_controller", lambda d: edit_meta(d, controller={"kp": 480, "flow_model": "yes"}),
         r"field 'controller\.flow_model': \"yes\" is not a boolean", kind="position_control"),
    Case("bad_started_at", lambda d: edit_meta(d, started_at="yesterday"),
         r"field 'started_at': \"yesterday\" is not an ISO 8601 time"),
    Case("started_at_number", lambda d: edit_meta(d, started_at=20260302),
         r"field 'started_at': 20260302 is not a string"),
    Case("load_in_kpa", lambda d: edit_meta(d, load_mpag=350),
         r"field 'load_mpag': 350 is above the plausible 50 MPaG"),
    Case("rig_unknown_key", lambda d: edit_meta(d, rig={"valve": {"z0": 1.0}}),
         r"run\.json: field 'rig\.valve\.z0': unknown rig key; expected one of"),
    Case("rig_unknown_section", lambda d: edit_meta(d, rig={"pump": {}}),
         r"field 'rig\.pump': unknown rig key"),
    Case("rig_wrong_type", lambda d: edit_meta(d, rig={"supply": {"pressure_mpag": "3.3"}}),
         r"field 'rig\.supply\.pressure_mpag': \"3\.3\" is not a finite number"),
    Case("rig_not_object", lambda d: edit_meta(d, rig=[1]), r"field 'rig': \[1\] is not an object"),
]


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_input_raises_data_error(tmp_path, case):
    run_dir = case.build(tmp_path)
    with pytest.raises(DataError, match=case.match) as info:
        read_run(run_dir)
    message = str(info.value)
    assert "\n" not in message
    assert str(run_dir) in message  # names the file


def test_row_is_data_row_excluding_header(tmp_path):
    run_dir = write_synthetic_run(tmp_path, run_id="r", duration_s=DURATION_S)
    set_cell(run_dir / "encoder.csv", 1, "position_mm", "x")
    with pytest.raises(DataError, match="row 1: ") as info:
        read_run(run_dir)
    assert info.value.row == 1 and info.value.column == "position_mm"


def test_non_numeric_far_down_a_large_file(tmp_path):
    run_dir = write_synthetic_run(tmp_path, run_id="r", duration_s=100.0, noise=False)
    set_cell(run_dir / "pressure.csv", 87_654, "p_head_mpag", "1.2.3")
    with pytest.raises(DataError, match=r"column 'p_head_mpag', row 87654: value \"1\.2\.3\""):
        read_run(run_dir)


def test_rig_max_plausible_pressure_is_used(tmp_path, rig):
    run_dir = write_synthetic_run(tmp_path, run_id="r", duration_s=DURATION_S)
    strict = rig.with_overrides({"analysis": {"max_plausible_pressure_mpag": 2.0}})
    with pytest.raises(DataError, match=r"p_supply_mpag', row 1: .* plausible 2 MPaG"):
        read_run(run_dir, rig=strict)


def test_good_variants_do_not_raise(tmp_path):
    """The cases that look odd but are allowed by the contract."""
    t = synthetic_tables(duration_s=DURATION_S)
    servo = t["servo"].assign(cam_deg=np.nan, comment="x")
    run_dir = write_synthetic_run(tmp_path, run_id="r", duration_s=DURATION_S,
                                  tables={"servo": servo}, meta={"unknown_field": [1, 2]},
                                  rig={"supply": {"pressure_mpag": 3.2}})
    run = read_run(run_dir)
    assert run.rig["supply"]["pressure_mpag"] == 3.2
    assert run.meta.extra == {"unknown_field": [1, 2]}
