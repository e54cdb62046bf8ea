"""The ingest stage (stages.dataset): the one path from run folders to the
per-run summary that every later stage, command and the pipeline read."""
from __future__ import annotations

import pandas as pd
import pytest

from seanv_analysis.batch import CachedMapper, make_executor
from seanv_analysis.errors import DataError
from seanv_analysis.stages import Context, dataset, run_stages


@pytest.fixture
def dataset_with_bad_runs(tmp_path, make_dataset, make_run):
    root = make_dataset(tmp_path / "ds", n_flow=6, n_position=2)
    bad = make_run(root, run_id="zz-bad-table", started_at="2026-03-02T12:00:00Z")
    (bad / "encoder.csv").write_text("t_s,position_mm\n0.0,1.0\n0.0,1.0\n")  # repeated time
    make_run(root, run_id="aa-bad-json").joinpath("run.json").write_text("{not json")
    return root


def test_processes_give_the_same_summary_and_errors(dataset_with_bad_runs):
    serial = run_stages(dataset_with_bad_runs, ["ingest"]).result("ingest")
    with make_executor(workers=2) as ex:
        parallel = run_stages(dataset_with_bad_runs, ["ingest"],
                              map_runs=CachedMapper(ex, None)).result("ingest")
    pd.testing.assert_frame_equal(serial.summary, parallel.summary, check_exact=True)
    assert serial.failed == parallel.failed
    assert len(serial.summary) == 8 and serial.runs_read == 8 and serial.runs_found == 10
    assert {f.path.rsplit("/", 1)[-1] for f in serial.failed} == {"zz-bad-table", "aa-bad-json"}
    assert all(f.stage == "ingest" and "\n" not in f.message for f in serial.failed)
    assert list(serial.summary["run_index"]) == list(range(8))
    assert len(serial.input_hashes) == 6 * 4 + 2 * 5  # run.json + 3 tables (+ controller)


def test_position_runs_read_once(dataset_with_bad_runs):
    ctx = run_stages(dataset_with_bad_runs, ["ingest"])
    runs = dataset.position_runs(ctx)
    assert [r.kind for r in runs] == ["position_control"] * 2
    assert dataset.position_runs(ctx)[0] is runs[0]


def test_no_valid_run_is_data_error(tmp_path, make_run):
    bad = make_run(tmp_path / "ds", run_id="only")
    (bad / "pressure.csv").write_text("")
    ctx = Context.for_data(tmp_path / "ds")
    with pytest.raises(DataError, match="no run could be read"):
        dataset.run(ctx, {})
    assert dataset.collect(ctx, {}).runs_read == 0
