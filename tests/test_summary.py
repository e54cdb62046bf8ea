"""summary.summarize_dataset: the data-set stage shared by flowfit, discover and batch."""
from __future__ import annotations

import pandas as pd
import pytest

from seanv_analysis.errors import DataError
from seanv_analysis.summary import summarize_dataset


@pytest.fixture
def dataset_with_bad_runs(tmp_path, make_dataset, make_run):
    root = make_dataset(tmp_path / "ds", n_flow=6, n_position=2)
    bad = make_run(root, run_id="zz-bad-table", started_at="2026-03-02T12:00:00Z")
    (bad / "encoder.csv").write_text("t_s,position_mm\n0.0,1.0\n0.0,1.0\n")  # repeated time
    make_run(root, run_id="aa-bad-json").joinpath("run.json").write_text("{not json")
    return root


def test_processes_give_the_same_summary_and_errors(dataset_with_bad_runs):
    serial = summarize_dataset(dataset_with_bad_runs, workers=1)
    parallel = summarize_dataset(dataset_with_bad_runs, workers=2)
    pd.testing.assert_frame_equal(serial.summary, parallel.summary, check_exact=True)
    assert [(str(e.path), e.message) for e in serial.errors] == \
        [(str(e.path), e.message) for e in parallel.errors]
    assert len(serial.summary) == 8
    assert {e.path.name for e in serial.errors} == {"zz-bad-table", "aa-bad-json"}
    assert list(serial.summary["run_index"]) == list(range(8))


@pytest.mark.parametrize("keep, kinds", [(False, set()), (True, {"flow_step", "position_control"}),
                                         ({"position_control"}, {"position_control"})])
def test_keep_runs_by_kind(dataset_with_bad_runs, keep, kinds):
    for workers in (1, 2):
        ds = summarize_dataset(dataset_with_bad_runs, keep_runs=keep, workers=workers)
        assert {r.kind for r in ds.runs} == kinds
        assert len(ds.runs) == {frozenset(): 0, frozenset({"position_control"}): 2}.get(
            frozenset(kinds), 8)


def test_no_valid_run_is_data_error(tmp_path, make_run):
    bad = make_run(tmp_path / "ds", run_id="only")
    (bad / "pressure.csv").write_text("")
    with pytest.raises(DataError, match="no valid runs"):
        summarize_dataset(tmp_path / "ds", workers=2)
