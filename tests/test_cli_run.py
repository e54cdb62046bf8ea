"""``seanv-analyze run`` and ``seanv-analyze plots``: thin click layers."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from seanv_analysis.cli import cli


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    from conftest import write_synthetic_dataset

    return write_synthetic_dataset(tmp_path_factory.mktemp("cli") / "data", n_flow=6, n_position=2)


def invoke(*args, env=None):
    return CliRunner().invoke(cli, [*map(str, args)], env=env)


def test_run_shipped_pipeline_by_name(data, tmp_path):
    out = tmp_path / "o"
    r = invoke("run", "tracking", data, "--out", out, "--workers", "1", "--quiet", "--formats", "png")
    assert r.exit_code == 0, r.output
    assert "runs: 8 found, 8 read (6 flow_step, 2 position_control), 0 failed" in r.output
    assert f"report: {out / 'report.html'}" in r.output
    assert (out / "report.html").is_file() and (out / "manifest.json").is_file()
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["command"] and manifest["version"]
    assert manifest["extra"]["pipeline"]["pipeline"]["name"] == "tracking"


def test_run_json_and_cache(data, tmp_path):
    out = tmp_path / "o"
    r1 = invoke("run", "tracking", data, "--out", out, "--workers", "2", "-q", "--json",
                "--no-figures")
    assert r1.exit_code == 0, r1.output
    doc = json.loads(r1.stdout)
    assert doc["runs_read"] == 8 and doc["computed"]["ingest"] == 8
    stamp = (out / "result.json").stat().st_mtime_ns
    # nothing changed (the executor is not an input): the last run is reused, nothing written
    r2 = invoke("run", "tracking", data, "--out", out, "--workers", "1", "-q", "--json",
                "--no-figures")
    doc2 = json.loads(r2.stdout)
    assert doc2.pop("reused") is True and doc2 == doc
    assert (out / "result.json").stat().st_mtime_ns == stamp
    # an output removed: the run runs, its per-run work from the cache
    (out / "report.html").unlink()
    r3 = invoke("run", "tracking", data, "--out", out, "--workers", "1", "-q", "--json",
                "--no-figures")
    doc3 = json.loads(r3.stdout)
    assert "reused" not in doc3 and (out / "report.html").is_file()
    assert doc3["computed"]["ingest"] == 0 and doc3["cached"]["ingest"] == 8
    assert doc3["tracking"] == doc["tracking"]
    r4 = invoke("run", "tracking", data, "--out", out, "--workers", "1", "-q", "--json",
                "--force", "--no-figures")
    assert json.loads(r4.stdout)["computed"]["ingest"] == 8


def test_run_reuses_nothing_after_an_input_changed(data, tmp_path):
    import shutil

    copy = tmp_path / "data"
    shutil.copytree(data, copy)
    out = tmp_path / "o"
    assert invoke("run", "tracking", copy, "--out", out, "-q", "--workers", "1", "--no-figures").exit_code == 0
    assert "reused" in invoke("run", "tracking", copy, "--out", out, "-q", "--workers", "1",
                              "--no-figures").output
    table = next(copy.rglob("encoder.csv"))
    lines = table.read_text().splitlines()
    head, value = lines[1].rsplit(",", 1)
    lines[1] = f"{head},{float(value) + 0.001}"  # one value of one log
    table.write_text("\n".join(lines) + "\n")
    r = invoke("run", "tracking", copy, "--out", out, "-q", "--workers", "1", "--no-figures", "--json")
    doc = json.loads(r.stdout)
    assert "reused" not in doc and doc["computed"]["ingest"] == 1 and doc["cached"]["ingest"] == 7


def test_run_pipeline_file_and_bad_runs_exit_1(data, tmp_path):
    import shutil

    from conftest import write_synthetic_run

    d = tmp_path / "data"
    shutil.copytree(data, d)
    write_synthetic_run(d, "flow_step", run_id="nopressure", tables={"pressure": None},
                        started_at="2026-03-02T11:00:00Z", duration_s=0.5)
    pipe = tmp_path / "mine.toml"
    pipe.write_text('[pipeline]\nname = "mine"\n[[stages]]\nname = "ingest"\n[[stages]]\n'
                    'name = "report"\n')
    r = invoke("run", pipe, d, "--out", tmp_path / "o", "--workers", "1", "-q")
    assert r.exit_code == 1
    assert "1 failed" in r.output and "nopressure" in r.output and "pressure" in r.output
    # issue 33, point 6: with -q too, what went wrong is on stderr, not on stdout only
    assert "1 bad run(s) skipped:" in r.stderr and "nopressure" in r.stderr
    assert "outputs (" not in r.stderr                      # the summary stays on stdout


@pytest.mark.parametrize("args, match", [
    (["run", "no-such-pipeline"], r"error: pipeline: no-such-pipeline is neither a file nor a "
                                  r"shipped pipeline"),
    (["run", "paper", "/no/such/folder"], r"error: /no/such/folder: not found"),
])
def test_run_bad_input_exit_2(args, match):
    r = invoke(*args, "--workers", "1", "-q")
    assert r.exit_code == 2
    assert __import__("re").search(match, r.output)
    assert "Traceback" not in r.output


@pytest.mark.parametrize("args", [["run", "paper"], ["ingest"], ["flowfit"]])
def test_missing_data_makes_no_output_folder(args, tmp_path, monkeypatch):
    """DATA that is not there: exit 2 and one line naming it, before any
    output folder is made (the default ``outputs/<name>/<command>/`` was
    created, empty, by the writability probe)."""
    monkeypatch.chdir(tmp_path)
    r = invoke(*args, tmp_path / "nope", "--workers", "1", "-q") if args[0] == "run" else \
        invoke(*args, tmp_path / "nope", "-q")
    assert r.exit_code == 2 and "nope: not found" in r.output and "Traceback" not in r.output
    assert not (tmp_path / "outputs").exists(), sorted(tmp_path.rglob("*"))


def test_run_bad_pipeline_option_exit_2(data, tmp_path):
    pipe = tmp_path / "bad.toml"
    pipe.write_text('[[stages]]\nname = "ingest"\nmethod = "mean"\n')
    r = invoke("run", pipe, data, "--out", tmp_path / "o", "-q")
    assert r.exit_code == 2
    assert "stage 'ingest' option 'method' = 'mean'" in r.output


def test_plots_command(data, tmp_path):
    out = tmp_path / "p"
    r = invoke("plots", data, "--fig", "6", "--fig", "7", "--out", out, "--workers", "1", "-q")
    assert r.exit_code == 0, r.output
    pngs = sorted(p.name for p in (out / "figures").rglob("*.png"))
    assert "fig6_pos000.png" in pngs and "fig6_pos001.png" in pngs and "fig7.png" in pngs
    assert sorted(p.name for p in (out / "figures").rglob("*.svg"))
    assert not (out / "report.html").exists()


def test_help_mentions_dask_and_cache():
    r = invoke("run", "--help")
    assert r.exit_code == 0
    assert "--scheduler" in r.output and "DASK_SCHEDULER_ADDRESS" in r.output
    assert ".cache" in r.output


def test_run_end_to_end_subprocess(data, tmp_path):
    out = tmp_path / "o"
    env = {**os.environ, "CI": "true", "MPLBACKEND": "Agg"}
    exe = Path(sys.executable).with_name("seanv-analyze")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-c",
                                           "from seanv_analysis.cli import main; main()"]
    proc = subprocess.run([*cmd, "run", "tracking", str(data), "--out", str(out), "--workers", "2",
                           "-v"], capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "stage ingest done" in proc.stderr       # plain line per stage with -v
    assert "\r" not in proc.stderr                  # no progress bar
    assert "report:" in proc.stdout


def test_run_figure_options(data, tmp_path):
    r = invoke("run", "tracking", data, "--out", tmp_path / "svg", "-q", "--workers", "1",
               "--formats", "svg", "--json")
    assert r.exit_code == 0, r.output
    files = [Path(p) for paths in json.loads(r.stdout)["figures"].values() for p in paths]
    assert files and {p.suffix for p in files} == {".svg"}
    r = invoke("run", "tracking", data, "--out", tmp_path / "none", "-q", "--workers", "1",
               "--no-figures", "--json")
    assert r.exit_code == 0, r.output
    doc = json.loads(r.stdout)
    assert doc["figures"] == {} and "figures" not in [s["name"] for s in doc["pipeline"]["stages"]]
    assert (tmp_path / "none" / "report.html").is_file()


def test_plots_says_what_it_runs_and_fails_when_nothing_is_drawn(tmp_path):
    """Issue 33, point 6: ``plots --fig 7`` on flow steps wrote 0 files and
    exited 0; ``--fig all`` re-ran four analyses without a word."""
    from conftest import write_synthetic_dataset

    from seanv_analysis.cli.plots_cmd import analyses_run, plots_pipeline

    flow = write_synthetic_dataset(tmp_path / "flow", n_flow=6)
    r = invoke("plots", flow, "--fig", "7", "--out", tmp_path / "p7", "--workers", "1")
    assert r.exit_code == 2, r.output
    assert "error: " in r.stderr and "no figure written: fig 7 (tracking: no position-control " \
        "runs" in " ".join(r.stderr.split())
    assert "need the results of tracking: running them first" in r.stderr
    r = invoke("plots", flow, "--fig", "4", "--fig", "7", "--out", tmp_path / "p47",
               "--workers", "1")
    assert r.exit_code == 0, r.output
    assert "note: not drawn: fig 7 (tracking:" in r.stderr and "fig4.png" in r.stdout
    assert analyses_run(plots_pipeline("all")) == ["flowfit", "tracking", "validate", "discover"]
    assert "need the results" not in invoke("plots", flow, "--fig", "4", "--out",
                                            tmp_path / "q", "--workers", "1", "-q").stderr
