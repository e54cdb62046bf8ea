"""``seanv-analyze ingest`` (issue 35; issue 34, point 5): the per-run
samples only with ``--samples``, the summary and the manifest always, the
per-run work on the executor with the same numbers, and the output folder
written whole and swapped in, so no file of an earlier data set stays."""
from __future__ import annotations

import json
import os
from pathlib import Path

import pandas as pd
import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner

from seanv_analysis.cli import cli
from seanv_analysis.io.atomic import OWNER_MARKER


def _ingest(*args) -> dict:
    res = CliRunner().invoke(cli, ["ingest", *map(str, args), "--json"])
    assert res.exit_code == 0, res.output
    return json.loads(res.stdout)


def _files(out: Path) -> set[str]:
    found = set()
    for dirpath, _, filenames in os.walk(out):
        found |= {str((Path(dirpath) / f).relative_to(out)) for f in filenames}
    return found - {OWNER_MARKER}


@pytest.fixture(scope="module")
def mixed(tmp_path_factory):
    from conftest import write_synthetic_dataset

    return write_synthetic_dataset(tmp_path_factory.mktemp("ing") / "data", n_flow=5,
                                   n_position=2, duration_s=0.3)


def test_the_samples_are_written_only_when_asked(mixed, tmp_path):
    plain = _ingest(mixed, "--out", tmp_path / "plain")
    assert _files(tmp_path / "plain") == {"summary.parquet", "manifest.json"}
    assert plain["tables"] == {} and plain["rows"] == {} and plain["samples"] is False
    assert plain["runs"] == 7 and plain["runs_by_kind"] == {"flow_step": 5, "position_control": 2}
    full = _ingest(mixed, "--out", tmp_path / "full", "--samples")
    assert _files(tmp_path / "full") == {"summary.parquet", "manifest.json", "flow_step.parquet",
                                         "position_control.parquet"}
    assert full["samples"] is True and full["tables"]["flow_step"] == str(
        tmp_path / "full" / "flow_step.parquet")
    assert full["rows"] == {k: pq.read_metadata(v).num_rows for k, v in full["tables"].items()}
    assert not [p for p in (tmp_path / "full").iterdir() if p.name.startswith(".samples")]
    # the same summary either way (the samples derived once, or derived in place)
    pd.testing.assert_frame_equal(pd.read_parquet(tmp_path / "plain" / "summary.parquet"),
                                  pd.read_parquet(tmp_path / "full" / "summary.parquet"))
    manifest = json.loads((tmp_path / "plain" / "manifest.json").read_text())
    assert {e["path"] for e in manifest["outputs"]} == {"summary.parquet"}
    # the manifest names the folder as it is, not the one it was written in
    assert manifest["extra"]["ingest"]["out"] == str(tmp_path / "plain")
    assert manifest["extra"]["ingest"]["summary"] == str(tmp_path / "plain" / "summary.parquet")


def test_the_executor_gives_the_same_tables(mixed, tmp_path, monkeypatch):
    """Per-run work on worker processes (a data set of 64 runs or more; here
    the threshold lowered) writes the same summary and samples, rows in the
    same order, as in this process."""
    from seanv_analysis.cli import _common

    serial = _ingest(mixed, "--out", tmp_path / "serial", "--samples")
    monkeypatch.setattr(_common, "AUTO_PARALLEL_MIN_RUNS", 1)
    pooled = _ingest(mixed, "--out", tmp_path / "pooled", "--samples")
    for name in ("summary.parquet", "flow_step.parquet", "position_control.parquet"):
        a = pq.read_table(tmp_path / "serial" / name)
        b = pq.read_table(tmp_path / "pooled" / name)
        assert a.equals(b), name
        assert a.schema.metadata[b"seanv.units"] == b.schema.metadata[b"seanv.units"]
    assert serial["rows"] == pooled["rows"] and serial["rows"]["flow_step"] > 0
    ids = pq.read_table(tmp_path / "pooled" / "flow_step.parquet").column("run_id").to_pylist()
    summary = pd.read_parquet(tmp_path / "pooled" / "summary.parquet")
    order = [r for r in summary["run_id"] if r in set(ids)]
    assert list(dict.fromkeys(ids)) == order          # samples in started_at order


def test_a_second_data_set_leaves_no_file_of_the_first(mixed, tmp_path, make_dataset):
    out = tmp_path / "out"
    _ingest(mixed, "--out", out, "--samples")
    assert "position_control.parquet" in _files(out)
    flows = make_dataset(tmp_path / "flows", n_flow=2, duration_s=0.3)
    doc = _ingest(flows, "--out", out)
    assert _files(out) == {"summary.parquet", "manifest.json"}, "a file of the first remains"
    assert doc["runs"] == 2 and len(pd.read_parquet(out / "summary.parquet")) == 2
    assert not [p for p in tmp_path.iterdir() if ".tmp-" in p.name or ".old-" in p.name]


def test_a_folder_of_the_users_is_refused_and_kept(mixed, tmp_path):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    res = CliRunner().invoke(cli, ["ingest", str(mixed), "--out", str(out)])
    assert res.exit_code == 2 and "Traceback" not in res.output, res.output
    assert (out / "notes.txt").read_text() == "mine" and _files(out) == {"notes.txt"}
