"""Names from user files cannot put an output anywhere but inside --out (issue 16, point 1).

Each case is refused with one line and exit 2 before any work, and nothing
outside the output folder changes (the raw data above all).
"""
from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner
from conftest import snapshot

from seanv_analysis.cli import cli
from seanv_analysis.errors import ConfigError


@pytest.fixture
def workspace(tmp_path, make_dataset):
    """tmp_path/data (a small data set) and tmp_path/victim.html (a file a
    hostile name would aim at)."""
    make_dataset(tmp_path / "data", n_flow=2)
    (tmp_path / "victim.html").write_text("do not touch\n")
    return tmp_path


def _run(tmp_path, pipeline_text: str, *extra: str):
    (tmp_path / "p.toml").write_text(pipeline_text)
    return CliRunner().invoke(cli, ["run", str(tmp_path / "p.toml"), str(tmp_path / "data"),
                                    "--out", str(tmp_path / "out" / "o"), "--workers", "1", "-q",
                                    *extra])


def _outside_out(tmp_path):
    snap = snapshot(tmp_path)
    return {k: v for k, v in snap.items() if not k.startswith("out") and k != "p.toml"}


REPORT_NAMES = [
    "{tmp}/victim.html",              # absolute
    "../victim.html",                 # up one
    "../../victim.html",
    "../../data/z001-drain/encoder.csv",  # a raw file of the data set
    "sub/../../../victim.html",
    "",                               # empty: would replace --out itself
    ".html",
    "report.html\n",                  # a newline is not part of a name
    "re port.html",
]


@pytest.mark.parametrize("name", REPORT_NAMES)
def test_report_filename_cannot_leave_out(workspace, name):
    name = name.format(tmp=workspace)
    before = _outside_out(workspace)
    toml_name = name.replace("\\", "\\\\").replace("\n", "\\n").replace('"', '\\"')
    res = _run(workspace, f'[pipeline]\nname = "p"\n[[stages]]\nname = "ingest"\n'
                          f'[[stages]]\nname = "report"\nfilename = "{toml_name}"\n')
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "filename" in lines[0]
    assert "Traceback" not in res.output
    assert _outside_out(workspace) == before
    assert not (workspace / "out").exists() or not any((workspace / "out").rglob("*.html"))


@pytest.mark.parametrize("name", ["../../evil", "../x", "a/b", "..", ".hidden", "a\nb", "x" * 65])
def test_pipeline_name_cannot_leave_outputs(workspace, name, monkeypatch):
    """The default output folder is outputs/<ds>/run-<name>: a name with a
    separator or '..' would escape outputs/."""
    monkeypatch.chdir(workspace)
    toml_name = name.replace("\n", "\\n")
    (workspace / "p.toml").write_text(f'[pipeline]\nname = "{toml_name}"\n[[stages]]\nname = "ingest"\n')
    before = snapshot(workspace)
    res = CliRunner().invoke(cli, ["run", "p.toml", "data", "--workers", "1", "-q"])
    assert res.exit_code == 2, res.output
    assert len(res.output.strip().splitlines()) == 1 and "[pipeline] name" in res.output
    assert snapshot(workspace) == before          # no folder made, inside outputs/ or not


@pytest.mark.parametrize("value", ['["ingest"]', "3", "true"])
def test_pipeline_name_of_the_wrong_type(workspace, value):
    res = _run(workspace, f'[pipeline]\nname = {value}\n[[stages]]\nname = "ingest"\n')
    assert res.exit_code == 2 and "[pipeline] name" in res.output, res.output


def test_report_write_checks_the_resolved_path(tmp_path):
    """Defence in depth: a ReportResult built by hand (no option check) with
    a name that leaves the folder is refused at write time."""
    from seanv_analysis.stages import report

    (tmp_path / "victim.html").write_text("keep")
    folder = tmp_path / "out"
    folder.mkdir()
    for name in ("../victim.html", str(tmp_path / "victim.html"), ""):
        with pytest.raises(ConfigError):
            report.write(report.ReportResult(record=None, filename=name), folder)
    assert (tmp_path / "victim.html").read_text() == "keep"
    assert list(folder.iterdir()) == []


def test_a_plain_report_name_is_accepted(workspace):
    res = _run(workspace, '[pipeline]\nname = "p-1.x"\n[[stages]]\nname = "ingest"\n'
                          '[[stages]]\nname = "report"\nfilename = "my_report-2.html"\n')
    assert res.exit_code == 0, res.output
    assert (workspace / "out" / "o" / "my_report-2.html").is_file()


# symbolic links (point 10) ------------------------------------------------------

SECRET = "TOPSECRET-first-line,never-echoed"


@pytest.fixture
def linked(tmp_path, make_dataset):
    """A data set with: a table linked to a file outside it (a secret first
    line), a run folder linked from outside, a run folder linked from inside."""
    data = make_dataset(tmp_path / "data", n_flow=3)
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    (outside / "secret.csv").write_text(SECRET + "\n1,2\n")
    enc = data / "z002-drain" / "encoder.csv"
    enc.unlink()
    enc.symlink_to(outside / "secret.csv")
    make_dataset(outside / "ext", n_flow=1)
    (data / "zz-linked-out").symlink_to(outside / "ext" / "z001-supply")
    (data / "zz-linked-in").symlink_to(data / "z003-supply")
    return data


def test_links_out_of_the_data_set_are_refused_and_named(linked, tmp_path):
    res = CliRunner().invoke(cli, ["ingest", str(linked), "--out", str(tmp_path / "out"), "--json"])
    assert res.exit_code == 1, res.output        # some runs bad, the others ingested
    assert SECRET.split(",")[0] not in res.output
    doc = json.loads(res.stdout)
    bad = {Path(b["path"]).name: b["message"] for b in doc["bad_runs"]}
    assert "symbolic link to a file outside the data set" in bad["z002-drain"]
    assert "encoder.csv" in bad["z002-drain"]
    for name in ("zz-linked-out", "zz-linked-in"):    # never skipped without a word
        assert "symbolic link to a folder" in bad[name]
    assert doc["runs"] == 2
    for f in (tmp_path / "out").rglob("*"):
        if f.is_file():
            assert SECRET.split(",")[0].encode() not in f.read_bytes(), f


def test_data_given_as_a_link_is_followed(tmp_path, make_dataset):
    data = make_dataset(tmp_path / "data", n_flow=2)
    (tmp_path / "link").symlink_to(data)
    res = CliRunner().invoke(cli, ["ingest", str(tmp_path / "link"), "--out", str(tmp_path / "o")])
    assert res.exit_code == 0, res.output
    assert "ingested 2 run(s)" in res.output


def test_a_link_inside_the_data_set_is_followed(tmp_path, make_dataset):
    data = make_dataset(tmp_path / "data", n_flow=2)
    (data / "shared").mkdir()
    table = data / "z002-supply" / "servo.csv"
    table.rename(data / "shared" / "servo.csv")
    table.symlink_to(data / "shared" / "servo.csv")     # inside the data set: read
    res = CliRunner().invoke(cli, ["ingest", str(data), "--out", str(tmp_path / "o")])
    assert res.exit_code == 0, res.output
