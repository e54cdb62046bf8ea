"""Output-side failures are one line and exit 2, found before the work where
possible (issue 16, point 7). Exit 1 stays "some runs bad"."""
from __future__ import annotations

import errno
import os

import pytest
from click.testing import CliRunner

from seanv_analysis.cli import cli


def _one_error_line(res) -> str:
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), res.output
    assert "Traceback" not in res.output
    return lines[0]


@pytest.mark.parametrize("command", [["run", "flowfit"], ["ingest"], ["flowfit"]])
def test_out_under_a_file_is_refused_before_the_work(tmp_path, make_dataset, command):
    make_dataset(tmp_path / "data", n_flow=2)
    (tmp_path / "afile").write_text("x")
    out = tmp_path / "afile" / "sub"
    res = CliRunner().invoke(cli, [*command, str(tmp_path / "data"), "--out", str(out)])
    assert res.exit_code == 2
    line = _one_error_line(res)
    assert str(out) in line and "Not a directory" in line


def test_simulate_into_a_path_under_a_file(tmp_path):
    (tmp_path / "afile").write_text("x")
    res = CliRunner().invoke(cli, ["simulate", "paper-position", "--out", str(tmp_path / "afile" / "d")])
    assert res.exit_code == 2
    assert "Not a directory" in _one_error_line(res)


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_read_only_out_is_refused_before_the_work(tmp_path, make_dataset):
    make_dataset(tmp_path / "data", n_flow=2)
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        res = CliRunner().invoke(cli, ["run", "flowfit", str(tmp_path / "data"), "--out", str(ro)])
    finally:
        ro.chmod(0o700)
    assert res.exit_code == 2
    assert "Permission denied" in _one_error_line(res)


def test_disk_full_after_the_work_is_one_line(tmp_path, make_dataset, monkeypatch):
    """An OSError while writing (here: the flow fit's files, disk full) after
    the work: one line naming the file and why, exit 2 (not 1, not a traceback)."""
    from seanv_analysis.stages import flowfit

    make_dataset(tmp_path / "data", n_flow=8)
    target = tmp_path / "out" / "flowfit" / "flowfit.json"

    def full(result, folder):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(target))

    monkeypatch.setattr(flowfit, "write", full)
    for argv in (["flowfit", str(tmp_path / "data"), "--out", str(tmp_path / "out")],
                 ["run", "flowfit", str(tmp_path / "data"), "--out", str(tmp_path / "out2"),
                  "--workers", "1", "-q"]):
        res = CliRunner().invoke(cli, argv)
        assert res.exit_code == 2, res.output
        line = _one_error_line(res)
        assert str(target) in line and "No space left on device" in line
