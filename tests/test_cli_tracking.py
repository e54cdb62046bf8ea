"""``seanv-analyze tracking`` / ``validate``: thin CLI, one JSON document with --json."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest
from click.testing import CliRunner
from fresh_process import cli_call, modules_after
from json_schemas import check_schema, keys_without_unit
from numpy.testing import assert_allclose
from test_tracking import write_delayed_run

from seanv_analysis.cli import cli
from seanv_analysis.stages import run_stages


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("cli_tracking") / "position"
    for j in range(2):
        write_delayed_run(root, f"pos{j}", seed=10 + j, duration_s=12.0,
                          started_at=f"2026-03-02T10:0{j}:00Z")
    return root


def test_tracking_json_shift(dataset, tmp_path):
    out = tmp_path / "out"
    res = CliRunner().invoke(cli, ["tracking", str(dataset), "--shift", "0.25", "--json",
                                   "--out", str(out), "--no-figures"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)  # nothing else on stdout
    expected = run_stages(dataset, ["ingest", "tracking"],
                          options={"tracking": {"shift_s": 0.25}}).result("tracking")
    assert doc["shift_source"] == "given" and doc["shift_s"] == 0.25
    assert_allclose(doc["rmse_mm3_s"], expected.rmse_mm3_s, rtol=1e-12)
    assert doc["n_samples"] == expected.n_samples
    assert [r["run_id"] for r in doc["runs"]] == ["pos0", "pos1"]
    assert (out / "tracking.json").exists() and (out / "manifest.json").exists()
    inputs = doc.pop("inputs")  # --json adds the inputs block to tracking.json
    assert json.loads((out / "tracking.json").read_text()) == doc
    assert (inputs["runs_found"], inputs["runs_read"], inputs["failed"]) == (2, 2, [])


def test_tracking_estimated_and_range(dataset, tmp_path):
    out = tmp_path / "out"
    res = CliRunner().invoke(cli, ["tracking", str(dataset), "--range", "-2000", "6000",
                                   "--json", "--no-figures", "--out", str(out)])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    assert doc["shift_source"] == "estimated" and abs(doc["lag_s"] - 0.237) < 0.005
    assert doc["shift_s"] == doc["lag_s"]
    assert len(doc["lag_ci95_s"]) == 2 and doc["range_mm3_s"] == [-2000.0, 6000.0]


def test_tracking_text_report_and_bad_range(dataset, tmp_path):
    res = CliRunner().invoke(cli, ["tracking", str(dataset), "--out", str(tmp_path / "o"),
                                   "--no-figures"])
    assert res.exit_code == 0 and "RMSE" in res.stdout
    res = CliRunner().invoke(cli, ["tracking", str(dataset), "--range", "5", "1",
                                   "--out", str(tmp_path / "o2"), "--no-figures"])
    assert res.exit_code == 2 and "error: q_range" in res.stderr


def test_tracking_subprocess_end_to_end(dataset, tmp_path):
    proc = subprocess.run([sys.executable, "-m", "seanv_analysis", "tracking", str(dataset),
                           "--shift", "0.25", "--json", "--no-figures", "--out",
                           str(tmp_path / "sp")], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["shift_s"] == 0.25


def test_tracking_estimates_the_lag_without_scipy_signal(dataset, tmp_path):
    """The lag estimate's correlations are numpy FFTs: importing scipy.signal
    (with scipy.stats: ~1 s, a third of the command) for them is not paid."""
    code = cli_call("tracking", dataset, "--out", tmp_path / "o", "--no-figures", "-q")
    assert modules_after(code, ["scipy.signal", "scipy.stats", "matplotlib"]) == []
    assert json.loads((tmp_path / "o" / "tracking.json").read_text())["shift_source"] == "estimated"


# --- on simulated data sets ------------------------------------------------------

@pytest.fixture(scope="module")
def sim_sets(tmp_path_factory):
    sim = pytest.importorskip("seanv_analysis.sim")
    root = tmp_path_factory.mktemp("cli_sim")
    clean = sim.simulate_scenario("paper-position", root / "clean", seed=3)
    delayed = sim.simulate_scenario("paper-position", root / "delayed", seed=3,
                                    effects=["delay:delay_s=0.3"])
    return clean, delayed


def test_validate_json_same_plant_and_injected_delay(sim_sets, tmp_path):
    clean, delayed = sim_sets
    res = CliRunner().invoke(cli, ["validate", str(clean), "--json", "--no-figures",
                                   "--out", str(tmp_path / "v1")])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    assert doc["flagged"] == [] and len(doc["runs"]) == 2
    check_schema("validate", doc)  # data_schema/json/validate.schema.json
    assert keys_without_unit(doc) == []
    assert all(r["fit_position_pct"] > 90 for r in doc["runs"])
    assert {r["controller"] for r in doc["runs"]} == {"flow_model", "cam"}
    assert (tmp_path / "v1" / "manifest.json").exists()

    res = CliRunner().invoke(cli, ["validate", str(delayed), "--json", "--no-figures", "--out",
                                   str(tmp_path / "v2")])
    assert res.exit_code == 0, res.output
    bad = json.loads(res.stdout)
    assert len(bad["flagged"]) >= 1
    for r_bad, r_ok in zip(bad["runs"], doc["runs"]):
        assert r_bad["fit_position_pct"] < r_ok["fit_position_pct"]
    assert (tmp_path / "v2" / "validate.json").exists()


def test_tracking_on_simulated_paper_position(sim_sets, tmp_path):
    clean, _ = sim_sets
    out = tmp_path / "t"
    res = CliRunner().invoke(cli, ["tracking", str(clean), "--json", "--out", str(out)])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    assert abs(doc["lag_s"] - 0.25) < 0.05
    # the run without flow model has no q_ref: skipped (no --model), listed in the details
    details = json.loads((tmp_path / "t" / "tracking_details.json").read_text())
    assert list(details["skipped"]) == ["position-without-flow-model"]
    (skipped,) = doc["inputs"]["skipped"]  # and in --json, with why
    assert skipped["run_id"] == "position-without-flow-model" and skipped["reason"]
    check_schema("tracking", doc)  # data_schema/json/tracking.schema.json
    assert keys_without_unit(doc) == []
    # Fig. 6 shows both runs ((a) without, (b) with the flow model), Fig. 7 the tracked one
    for name in ("fig6.png", "fig6.svg", "fig7.png", "fig7.svg",
                 "fig6_position-without-flow-model.png", "fig7_position-with-flow-model.svg"):
        assert (out / name).stat().st_size > 1000


def test_no_data_uses_builtin_dataset(sim_sets, tmp_path, monkeypatch):
    clean, _ = sim_sets
    asked = []

    def builtin(scenario, **kw):  # stands in for the cached built-in data set
        asked.append(scenario)
        out = tmp_path / "outputs" / "_builtin" / "paper-position-x"
        if not out.exists():
            import shutil
            shutil.copytree(clean, out)
        return out

    monkeypatch.setattr("seanv_analysis.cli.tracking_cmd.sim_default_dataset", builtin)
    monkeypatch.chdir(tmp_path)
    res = CliRunner().invoke(cli, ["tracking", "--shift", "0.25", "--json", "--no-figures"])
    assert res.exit_code == 0, res.output
    assert "built-in simulated paper position-control data set" in res.stderr
    assert json.loads(res.stdout)["shift_source"] == "given"
    assert asked == ["paper-position"]
    assert (tmp_path / "outputs" / "paper-position-x" / "tracking" / "tracking.json").exists()


def test_one_tracking_number_everywhere(tmp_path):
    """Issue 33, point 2: ``tracking`` alone (which skips a run whose Q_ref
    is only implied), the pipeline (which tracks it with the rig's model),
    its report and its Fig. 7(b) give one RMSE: the runs with a commanded
    Q_ref, in the range."""
    from seanv_analysis.batch import run_pipeline
    from seanv_analysis.report._format import _fmt

    root = tmp_path / "pos"
    write_delayed_run(root, "commanded", seed=21, duration_s=8.0)
    write_delayed_run(root, "implied", seed=22, duration_s=8.0, q_ref_empty=True,
                      flow_model=False, started_at="2026-03-02T10:05:00Z")
    alone = CliRunner().invoke(cli, ["tracking", str(root), "--json", "--no-figures",
                                     "--out", str(tmp_path / "t")])
    assert alone.exit_code == 0, alone.output
    alone = json.loads(alone.stdout)
    pipe = {"pipeline": {"name": "t"}, "stages": [{"name": "ingest"}, {"name": "tracking"},
                                                   {"name": "report"}]}
    res = run_pipeline(pipe, root, out_dir=tmp_path / "run", workers=1, quiet=True)
    doc = json.loads((tmp_path / "run" / "result.json").read_text())["tracking"]
    assert [r["target_source"] for r in doc["runs"]] == ["q_ref", "model"]
    assert doc["pooled_runs"] == alone["pooled_runs"] == ["commanded"]
    assert doc["rmse_mm3_s"] == alone["rmse_mm3_s"] == res["tracking"].rmse_mm3_s
    html = res.report_path.read_text()
    assert f"{_fmt(doc['rmse_mm3_s'], 4)} mm" in html and "runs with a commanded Q_ref" in html
    from seanv_analysis.plots.fig7 import scatter_runs

    assert [r.run_id for r in scatter_runs(res["tracking"])[0]] == ["commanded"]


@pytest.mark.parametrize("shift", ["25", "-1", "2.5"])
def test_a_shift_outside_0_to_2_s_is_refused_with_its_range(dataset, tmp_path, shift):
    """Issue 33, point 6: --shift 25 exited 0 with RMSE 1144 and no word."""
    out = tmp_path / "o"
    res = CliRunner().invoke(cli, ["tracking", str(dataset), f"--shift={shift}", "--out", str(out),
                                   "--no-figures"])
    assert res.exit_code == 2, res.output
    assert res.stderr.count("\n") == 1 and "(--shift)" in res.stderr
    assert "from 0 to 2" in res.stderr and not (out / "tracking.json").exists()
    assert "--shift 0..2" in CliRunner().invoke(cli, ["tracking", "--help"]).output
