"""Names from user files cannot put an output anywhere but inside --out (issue 16, point 1).

Each case is refused with one line and exit 2 before any work, and nothing
outside the output folder changes (the raw data above all).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
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


# the run cache (points 2 and 5) --------------------------------------------------

def _cache_run(data, out, workers=1):
    from seanv_analysis.batch import run_pipeline

    pipe = {"pipeline": {"name": "i"}, "stages": [{"name": "ingest"}, {"name": "flowfit"}]}
    return run_pipeline(pipe, data, out_dir=out, workers=workers, quiet=True)


def test_a_pickle_planted_in_the_cache_never_runs(tmp_path, make_dataset):
    """Whatever sits in <out>/.cache, under any name the cache reads, no code
    runs and the numbers are those of a clean run."""
    import pickle

    data = make_dataset(tmp_path / "data", n_flow=6)
    clean = _cache_run(data, tmp_path / "clean")
    out = tmp_path / "out"
    first = _cache_run(data, out)
    marker = tmp_path / "pwned"

    class Planted:
        def __reduce__(self):
            return (marker.write_text, ("ran",))

    bomb = pickle.dumps(Planted())
    entries = out / ".cache" / "runs"
    names = [p.name for p in entries.iterdir()]
    assert names and all(n.endswith(".json") for n in names)
    for name in names:                    # every entry the next run would read
        (entries / name).write_bytes(bomb)
        (entries / (name[:-5] + ".pkl")).write_bytes(b"\0" * 32 + bomb)
    (out / ".cache" / "index.json").write_bytes(bomb)
    again = _cache_run(data, out)
    assert not marker.exists()
    assert again.computed["ingest"] == 6          # every planted entry was a miss
    for res in (first, again):
        assert res.flowfit.sides["supply"].c_flow == clean.flowfit.sides["supply"].c_flow
    assert not list(entries.glob("*.pkl"))


def test_a_tampered_entry_is_a_miss(tmp_path):
    from seanv_analysis.batch.cache import read_entry, write_entry

    entries = tmp_path / "runs"
    entries.mkdir()
    value = {"row": [1.5, "x", float("nan")], "a": np.arange(3.0)}
    assert write_entry(entries, "k", value)
    got = read_entry(entries, "k")
    assert got["row"][:2] == [1.5, "x"] and np.isnan(got["row"][2])
    assert np.array_equal(got["a"], np.arange(3.0))
    path = entries / "k.json"
    head, payload = path.read_bytes().split(b"\n", 1)
    path.write_bytes(head + b"\n" + payload.replace(b"1.5", b"2.5"))    # hash left as it was
    assert read_entry(entries, "k") is None and not path.exists()


def test_a_same_size_edit_with_the_mtime_put_back_is_seen(tmp_path, make_dataset):
    """The cache trusted size + mtime: an edit of the same size with the
    mtime restored reused the old result, and the manifest recorded the old
    SHA-256."""
    import os

    data = make_dataset(tmp_path / "data", n_flow=6)
    out = tmp_path / "out"
    first = _cache_run(data, out)
    enc = data / "z004-supply" / "encoder.csv"
    st = os.stat(enc)
    text = enc.read_text()
    lines = text.splitlines()
    # the last sample's position, digits swapped: same size, another value
    t, x = lines[-1].split(",")
    x2 = x[::-1] if x[::-1] != x else x[:-1] + ("1" if x[-1] != "1" else "2")
    assert len(x2) == len(x)
    lines[-1] = f"{t},{x2}"
    new = "\n".join(lines) + ("\n" if text.endswith("\n") else "")
    assert len(new) == len(text)
    enc.write_text(new)
    os.utime(enc, ns=(st.st_atime_ns, st.st_mtime_ns))
    again = _cache_run(data, out)
    assert again.computed["ingest"] == 1 and again.cached["ingest"] == 5
    man = json.loads((out / "manifest.json").read_text())
    import hashlib
    digest = hashlib.sha256(enc.read_bytes()).hexdigest()
    assert digest in json.dumps(man["inputs"] if "inputs" in man else man)
    assert first.input_hashes != again.input_hashes
