"""Issue 34, point 3 (the pipeline memo): ``.cache/pipeline.json`` and the
``result.json`` it vouches for are untrusted input: a matching memo with a
malformed ``result.json`` (nested too deep, a field missing or mistyped, a
path outside --out) is a miss and the pipeline runs."""
from __future__ import annotations

import json
import os
import shutil

import pytest
from click.testing import CliRunner

from seanv_analysis.batch.memo import MEMO_NAME
from seanv_analysis.cli import cli


def copy_out(src, tmp_path):
    """A copy of the shared output folder to plant files in."""
    dst = tmp_path / "out"
    shutil.copytree(src, dst, symlinks=True)
    return dst


def _rewrite_result(out, doc_text: str) -> None:
    """Replace result.json and make the memo match it (size and mtime)."""
    path = out / "result.json"
    path.write_text(doc_text)
    memo_path = out / ".cache" / MEMO_NAME
    memo = json.loads(memo_path.read_text())
    st = path.stat()
    memo["outputs"][str(path.resolve())] = [st.st_size, st.st_mtime_ns]
    memo_path.write_text(json.dumps(memo))


def _bad_results(good: dict) -> list[str]:
    failed = {**good, "failed": [{"x": 1}]}
    found = {**good, "runs_found": "9"}
    outside = {**good, "outputs": [*good["outputs"], "/etc/passwd"]}
    figure = {**good, "figures": {"fig4": ["/etc/passwd"]}}
    return ["[" * 100000 + "]" * 100000, "{}", "[]", json.dumps(failed), json.dumps(found),
            json.dumps(outside), json.dumps(figure), '{"schema": "seanv-pipeline-result/2"}']


def _copy_with_memo(flowfit_out, tmp_path):
    """A copy of the finished run whose memo describes the copy's files."""
    out = copy_out(flowfit_out, tmp_path)
    memo_path = out / ".cache" / MEMO_NAME
    memo = json.loads(memo_path.read_text())
    memo["outputs"] = {str(out / os.path.relpath(p, flowfit_out)): st
                       for p, st in memo["outputs"].items()}
    memo_path.write_text(json.dumps(memo))
    _rewrite_result(out, (out / "result.json").read_text().replace(str(flowfit_out), str(out)))
    return out, memo["key"]


@pytest.mark.parametrize("case", range(8))
def test_a_matching_memo_with_a_malformed_result_is_a_miss(flowfit_out, tmp_path, case):
    from seanv_analysis.batch.memo import recorded_run

    out, key = _copy_with_memo(flowfit_out, tmp_path)
    assert recorded_run(out, key) is not None
    good = json.loads((out / "result.json").read_text())
    _rewrite_result(out, _bad_results(good)[case])
    assert recorded_run(out, key) is None


def test_a_matching_memo_with_a_malformed_result_runs_again(flowfit_out, hostile_data, tmp_path):
    """The probe: a matching memo with a malformed result.json gave
    RecursionError/TypeError/KeyError on every re-run."""
    out, _ = _copy_with_memo(flowfit_out, tmp_path)
    good = json.loads((out / "result.json").read_text())
    _rewrite_result(out, json.dumps({**good, "failed": [{"x": 1}], "outputs": ["/etc/passwd"]}))
    res = CliRunner().invoke(cli, ["run", "flowfit", str(hostile_data), "--out", str(out),
                                   "-q", "--workers", "1"])
    assert res.exit_code == 0, res.output
    assert "nothing changed since the last run" not in res.output
    assert "/etc/passwd" not in res.output
    assert json.loads((out / "result.json").read_text())["runs_found"] == 8


def test_a_memo_naming_files_outside_out_is_a_miss(flowfit_out, tmp_path):
    from seanv_analysis.batch.memo import recorded_run

    out = copy_out(flowfit_out, tmp_path)
    memo_path = out / ".cache" / MEMO_NAME
    memo = json.loads(memo_path.read_text())
    st = os.stat("/etc/hostname") if os.path.exists("/etc/hostname") else os.stat(__file__)
    memo["outputs"] = {"/etc/hostname" if os.path.exists("/etc/hostname") else __file__:
                       [st.st_size, st.st_mtime_ns]}
    memo_path.write_text(json.dumps(memo))
    assert recorded_run(out, memo["key"]) is None


