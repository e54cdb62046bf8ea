"""``seanv-analyze ingest``: outputs, exit codes and one-line errors."""
from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner
from conftest import snapshot
from json_schemas import check_schema, keys_without_unit
from test_io_bad_input import CASES

from seanv_analysis.cli import cli
from seanv_analysis.io import SUMMARY_COLUMNS, read_dataset
from seanv_analysis.io.atomic import OWNER_MARKER
from seanv_analysis.signals.align import align_run

CLI_MATCH = {  # where the CLI sees a different first problem than read_run
    "run_json_missing": r"no run\.json found at any depth",
}


def invoke(*args):
    return CliRunner().invoke(cli, ["ingest", *map(str, args)])


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_single_run_exits_2_with_one_line(tmp_path, case):
    run_dir = case.build(tmp_path / "data")
    before = snapshot(tmp_path / "data")
    result = invoke(run_dir, "--out", tmp_path / "out", "--json")
    assert result.exit_code == 2, result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("error: ")
    assert "Traceback" not in result.stderr and result.stdout == ""
    assert pd.Series(lines[0]).str.contains(CLI_MATCH.get(case.id, case.match)).all(), lines[0]
    assert snapshot(tmp_path / "data") == before
    assert not (tmp_path / "out").exists() or snapshot(tmp_path / "out") == {}


def test_dataset_writes_tables_summary_manifest(tmp_path, make_dataset):
    data = make_dataset(tmp_path / "data" / "flow", n_flow=4, n_position=2, duration_s=0.3)
    before = snapshot(data)
    out = tmp_path / "out"
    result = invoke(data, "--out", out, "--json", "--samples")
    assert result.exit_code == 0, result.output
    assert result.stderr == ""
    doc = json.loads(result.stdout)
    assert doc["runs"] == 6 and doc["runs_by_kind"] == {"flow_step": 4, "position_control": 2}
    assert doc["bad_runs"] == []
    assert doc["inputs"] == {"runs_found": 6, "runs_read": 6, "failed": [], "skipped": []}
    check_schema("ingest", doc)  # data_schema/json/ingest.schema.json
    assert keys_without_unit(doc) == []
    assert snapshot(data) == before
    assert sorted(p.name for p in out.iterdir() if p.name != OWNER_MARKER) == [
        "flow_step.parquet", "manifest.json", "position_control.parquet", "summary.parquet"]
    ds = read_dataset(data)
    # aligned samples: run_id + the run's aligned columns, units in the schema metadata
    for kind in ("flow_step", "position_control"):
        table = pq.read_table(out / f"{kind}.parquet")
        assert table.column_names[0] == "run_id"
        units = json.loads(table.schema.metadata[b"seanv.units"])
        assert units["t_s"] == "s" and units["p_supply_mpag"] == "MPaG"
        assert table.schema.field("position_mm").metadata[b"unit"] == b"mm"
        df = table.to_pandas()
        runs = [r for r in ds.runs if r.kind == kind]
        assert list(df["run_id"].unique()) == [r.run_id for r in runs]
        first = df[df["run_id"] == runs[0].run_id]
        aligned = align_run(runs[0])
        pd.testing.assert_frame_equal(first[aligned.columns].reset_index(drop=True), aligned)
    summary = pd.read_parquet(out / "summary.parquet")
    assert list(summary.columns) == list(SUMMARY_COLUMNS)
    assert list(summary["run_id"]) == [r.run_id for r in ds.runs]
    assert list(summary["run_index"]) == list(range(6))
    assert summary["started_at"].is_monotonic_increasing
    assert str(summary["started_at"].dtype) == "datetime64[ns, UTC]"
    manifest = json.loads((out / "manifest.json").read_text())
    hashes = {i["path"]: i["sha256"] for i in manifest["inputs"]}
    files = [p for p in data.rglob("*") if p.is_file()]
    assert hashes == {str(p): hashlib.sha256(p.read_bytes()).hexdigest() for p in files}
    assert manifest["version"] and manifest["config"]["calibration"]["kpa_per_mpa"] == 1000.0
    assert manifest["extra"]["ingest"]["runs"] == 6


def test_dataset_with_bad_runs_exits_1_and_lists_them(tmp_path, make_dataset):
    data = make_dataset(tmp_path / "data", n_flow=3, duration_s=0.2)
    (data / "z002-drain" / "servo.csv").unlink()
    (data / "z001-supply" / "run.json").write_text("{")
    result = invoke(data, "--out", tmp_path / "out")
    assert result.exit_code == 1
    lines = result.stderr.strip().splitlines()
    assert lines[0] == "2 bad run(s) skipped:"
    assert "z001-supply/run.json: not valid JSON" in lines[1]
    assert "z002-drain/servo.csv: missing required file" in lines[2]
    assert len(lines) == 3 and "Traceback" not in result.stderr
    assert "ingested 1 run(s)" in result.stdout
    summary = pd.read_parquet(tmp_path / "out" / "summary.parquet")
    assert list(summary["run_id"]) == ["z003-supply"]


def test_all_runs_bad_writes_nothing(tmp_path, make_dataset):
    data = make_dataset(tmp_path / "data", n_flow=2, duration_s=0.2)
    for run in data.iterdir():
        (run / "encoder.csv").write_text("")
    result = invoke(data, "--out", tmp_path / "out", "--json")
    assert result.exit_code == 1
    assert json.loads(result.stdout)["runs"] == 0
    assert not (tmp_path / "out").exists() or snapshot(tmp_path / "out") == {}


def test_default_out_dir(tmp_path, make_run, monkeypatch):
    run_dir = make_run(tmp_path / "data", run_id="one", duration_s=0.2)
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    result = invoke(run_dir, "--samples")
    assert result.exit_code == 0, result.output
    assert (work / "outputs" / "one" / "ingest" / "flow_step.parquet").is_file()
    assert (work / "outputs" / "one" / "ingest" / "manifest.json").is_file()


@pytest.mark.parametrize("args, match", [
    (["{data}/nope"], r"nope: not found"),
    (["{data}", "--out", "{data}/out"], r"--out: .* is inside the data folder"),
    (["{data}", "--rig", "{tmp}/rig.toml"], r"unknown rig key 'pump'"),
    (["{data}", "--rig", "{tmp}/missing.toml"], r"rig config not found"),
])
def test_usage_problems_exit_2(tmp_path, make_run, args, match):
    data = tmp_path / "data"
    make_run(data, run_id="one", duration_s=0.2)
    (tmp_path / "rig.toml").write_text("[pump]\nrate_hz = 1\n")
    before = snapshot(data)
    result = invoke(*[a.format(data=data, tmp=tmp_path) for a in args])
    assert result.exit_code == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and pd.Series(lines).str.contains(match).all(), result.stderr
    assert snapshot(data) == before


def test_rig_file_changes_plausibility_limit(tmp_path, make_run):
    run_dir = make_run(tmp_path / "data", run_id="one", duration_s=0.2)
    (tmp_path / "rig.toml").write_text("[analysis]\nmax_plausible_pressure_mpag = 2.0\n")
    result = invoke(run_dir, "--rig", tmp_path / "rig.toml", "--out", tmp_path / "out")
    assert result.exit_code == 2 and "plausible 2 MPaG" in result.stderr


def test_help_teaches():
    result = CliRunner().invoke(cli, ["ingest", "--help"])
    assert result.exit_code == 0
    for text in ("MPa gauge", "outputs/<dataset-name>/ingest/", "Example", "Exit codes",
                 "[deg]", "--json"):
        assert text in result.output


def test_end_to_end_subprocess(tmp_path, make_dataset):
    data = make_dataset(tmp_path / "data", n_flow=2, n_position=1, duration_s=0.2, fmt="parquet")
    env = {k: v for k, v in os.environ.items() if k != "CI"}
    proc = subprocess.run([sys.executable, "-m", "seanv_analysis", "ingest", str(data),
                           "--out", str(tmp_path / "out"), "--json"],
                          capture_output=True, text=True, env=env, timeout=120)
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(proc.stdout)
    assert doc["runs"] == 3 and Path(doc["manifest"]).is_file()
    manifest = json.loads(Path(doc["manifest"]).read_text())
    assert manifest["command"][-3:] == ["--out", str(tmp_path / "out"), "--json"]
