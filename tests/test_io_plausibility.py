"""One bad run never sinks a data set; implausible times are refused early
(issue 16, points 4, 9 and 12)."""
from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from seanv_analysis.cli import cli
from seanv_analysis.errors import DataError
from seanv_analysis.io.validate import check_time_plausible, parse_run_json


def _edit_t(path, func):
    """Rewrite column 1 (t_s) of a CSV table: ``func(row index from 0, t) -> t``."""
    lines = path.read_text().splitlines()
    out = [lines[0]]
    for i, line in enumerate(lines[1:]):
        head, _, rest = line.partition(",")
        out.append(f"{func(i, float(head))!r},{rest}")
    path.write_text("\n".join(out) + "\n")


def _ingest(data, out):
    return CliRunner().invoke(cli, ["ingest", str(data), "--out", str(out), "--json"])


@pytest.mark.parametrize("jump", [1e9, 3e4])
def test_a_timestamp_jump_in_one_run_leaves_the_others(tmp_path, make_dataset, jump):
    """An encoder t_s of 1e9 (or 3e4) in the last row of one run: before, 1e9
    ended ingest with a traceback (7 TiB alignment grid) and nothing written,
    3e4 was accepted at 5x the memory."""
    data = make_dataset(tmp_path / "data", n_flow=4)
    enc = data / "z002-supply" / "encoder.csv"
    n = len(enc.read_text().splitlines()) - 1
    _edit_t(enc, lambda i, t: jump if i == n - 1 else t)
    res = _ingest(data, tmp_path / "out")
    assert res.exit_code == 1, res.output
    doc = json.loads(res.stdout)
    assert doc["runs"] == 3 and (tmp_path / "out" / "summary.parquet").is_file()
    (bad,) = doc["bad_runs"]
    assert "encoder.csv" in bad["message"] and "column 't_s'" in bad["message"]
    assert f"row {n}" in bad["message"] and "max_run_duration_s" in bad["message"]


def test_times_in_milliseconds_are_named(tmp_path, make_dataset):
    data = make_dataset(tmp_path / "data", n_flow=2)
    for table in ("encoder", "pressure", "servo"):
        _edit_t(data / "z001-drain" / f"{table}.csv", lambda i, t: t * 1000.0)
    res = _ingest(data, tmp_path / "out")
    assert res.exit_code == 1
    (bad,) = json.loads(res.stdout)["bad_runs"]
    assert "column 't_s', row 2" in bad["message"]
    assert "look like milliseconds" in bad["message"]


def test_limits_come_from_the_rig_file(tmp_path, make_dataset):
    """A rig file allowing long runs accepts the 3e4 s jump (a user's choice)."""
    data = make_dataset(tmp_path / "data", n_flow=1)
    enc = data / "z001-supply" / "encoder.csv"
    n = len(enc.read_text().splitlines()) - 1
    _edit_t(enc, lambda i, t: 3e4 if i == n - 1 else t)
    (tmp_path / "rig.toml").write_text("[analysis]\nmax_run_duration_s = 1e5\n")
    res = CliRunner().invoke(cli, ["ingest", str(data), "--out", str(tmp_path / "o"),
                                   "--rig", str(tmp_path / "rig.toml")])
    assert "max_run_duration_s" not in res.output


@pytest.mark.parametrize("t,row,what", [
    (np.arange(0, 10, 0.001) * 1000, 2, "milliseconds"),
    (np.r_[np.arange(0, 1, 0.01), 5e3], 101, "max_run_duration_s"),
    (np.arange(0, 100, 2.0), 2, "max_sample_interval_s"),
])
def test_time_plausibility_unit(t, row, what):
    with pytest.raises(DataError, match=rf"row {row}: .*{what}"):
        check_time_plausible(t, path="x.csv", column="t_s")
    check_time_plausible(np.arange(0, 600, 0.001), path="x.csv", column="t_s")   # 10 min at 1 kHz


@pytest.mark.parametrize("run_id", ["abc\n", "abc\r", "a/b", "../x", "", "a b"])
def test_run_id_is_fully_matched(run_id):
    """``$`` matched before a final newline: "abc\\n" passed and put a newline
    into file names and log lines."""
    doc = {"schema": "seanv-run/1", "run_id": run_id, "kind": "flow_step",
           "started_at": "2026-03-02T10:00:00Z", "side": "supply", "cam_deg": 0.0}
    with pytest.raises(DataError, match="run_id"):
        parse_run_json(doc, path="run.json")
