"""Issue 34, point 5: a figure that cannot be written (disk full, file too
large) ends the run with exit 2 and one line naming the file, like any
output error; an error of the disk that names no file names the output."""
from __future__ import annotations

import dataclasses
import errno
import os
import resource
import subprocess
import sys

import pytest
from click.testing import CliRunner

from seanv_analysis.cli import cli
from seanv_analysis.errors import OutputError
from seanv_analysis.io.atomic import write_text_atomic


def _one_error_line(res) -> str:
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), res.output
    assert "Traceback" not in res.output
    return lines[0]


def _disk_full_after(n_bytes: int):
    """A stand-in for matplotlib's savefig: writes a little, then the disk is full
    (an OSError without a file name, as a write() gives)."""
    def savefig(self, fname, *args, **kwargs):
        with open(fname, "wb") as fh:
            fh.write(b"x" * n_bytes)
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    return savefig


def test_a_full_disk_while_a_figure_is_written_is_exit_2_naming_it(hostile_data, tmp_path,
                                                                   monkeypatch):
    """The probe: a figure write error was a note, exit 0."""
    from matplotlib.figure import Figure

    monkeypatch.setattr(Figure, "savefig", _disk_full_after(10))
    out = tmp_path / "out"
    res = CliRunner().invoke(cli, ["run", "flowfit", str(hostile_data), "--out", str(out), "-q",
                                   "--workers", "1"])
    assert res.exit_code == 2, res.output
    line = _one_error_line(res)
    assert f"{out / 'figures' / 'fig4.png'}: No space left on device" in line
    assert not [p for p in (out / "figures").glob(".*.tmp")]   # no temp file left


def test_a_full_disk_in_a_per_run_figure_is_exit_2(tmp_path, monkeypatch):
    from conftest import write_synthetic_dataset

    from seanv_analysis.plots import FIGURES

    data = write_synthetic_dataset(tmp_path / "data", n_flow=0, n_position=1)

    def full(run, folder, *, formats, rig):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setitem(FIGURES, "fig6", dataclasses.replace(FIGURES["fig6"], draw_run=full))
    pipe = tmp_path / "p.toml"
    pipe.write_text('[[stages]]\nname = "ingest"\n[[stages]]\nname = "figures"\nfigs = [6]\n')
    res = CliRunner().invoke(cli, ["run", str(pipe), str(data), "--out", str(tmp_path / "o"),
                                   "-q", "--workers", "1"])
    assert res.exit_code == 2, res.output
    assert "No space left on device" in _one_error_line(res)
    res = CliRunner().invoke(cli, ["run", str(pipe), str(data), "--out", str(tmp_path / "o"),
                                   "-q", "--workers", "1"])
    assert res.exit_code == 2, res.output    # the error was not cached as a result


def test_an_atomic_write_names_the_file_when_the_disk_says_nothing(tmp_path, monkeypatch):
    import pathlib

    def full(self, data):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(pathlib.Path, "write_bytes", full)
    with pytest.raises(OutputError, match=rf"{tmp_path / 'a.txt'}: No space left on device"):
        write_text_atomic(tmp_path / "a.txt", "x")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX file size limit")
def test_a_file_too_large_is_exit_2_naming_it(hostile_data, tmp_path):
    """RLIMIT_FSIZE below a figure's size: write() fails with EFBIG (Python
    ignores SIGXFSZ), the first file too large is named."""
    out = tmp_path / "out"
    limit = 60_000   # the JSON and Parquet files fit, Fig. 4 does not

    def small_files():
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    exe = os.path.join(os.path.dirname(sys.executable), "seanv-analyze")
    proc = subprocess.run([exe, "run", "flowfit", str(hostile_data), "--out", str(out), "-q",
                           "--workers", "1"], capture_output=True, text=True, timeout=300,
                          preexec_fn=small_files)
    assert proc.returncode == 2, (proc.stdout, proc.stderr)
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert "File too large" in lines[0] and str(out / "figures" / "fig4.") in lines[0]
