"""``seanv-analyze flowfit``: outputs, JSON contract, exit codes, built-in data set."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner
from conftest import write_synthetic_run
from fresh_process import cli_call, modules_after
from json_schemas import check_schema, keys_without_unit

from seanv_analysis.cli import cli
from seanv_analysis.config import load_rig
from seanv_analysis.io.model_file import read_model
from seanv_analysis.models import ValveModel, side_pressures

CAMS = {"supply": (-12.0, -7.5, -5.0, -2.5, 0.0, 2.5, 5.0),
        "drain": (-18.0, -22.5, -25.0, -27.5, -30.0, -35.0)}
LOADS = (0.3, 0.5)


def write_flow_dataset(root: Path) -> Path:
    """Flow-step runs whose flow follows eq. (5) of the rig's valve at the
    fixture's pressures (supply 3.3 MPaG; head 4 x load, + 0.3 on the supply side)."""
    model = ValveModel.from_rig(load_rig())
    k = 0
    for side, cams in CAMS.items():
        for load in LOADS:
            p_head = 4 * load + (0.3 if side == "supply" else 0.0)
            p1, dp = side_pressures(side, 3.3, p_head, 0.0)
            for cam in cams:
                q = float(model.side(side).flow(cam, p1, dp))
                write_synthetic_run(root, side=side, cam_deg=cam, load_mpag=load, flow_mm3_s=q,
                                    seed=k, duration_s=0.5, run_id=f"{side}-l{load}-c{cam}",
                                    started_at=f"2026-03-02T10:{k // 60:02d}:{k % 60:02d}Z")
                k += 1
    return root


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return write_flow_dataset(tmp_path_factory.mktemp("flowdata") / "flow")


def invoke(*args):
    return CliRunner().invoke(cli, ["flowfit", *map(str, args)])


def test_json_outputs_and_manifest(dataset, tmp_path):
    out = tmp_path / "out"
    # the fixture's flows follow the commanded cam (its feedback lags)
    res = invoke(dataset, "--out", out, "--json", "--n-boot", 30, "--cam", "commanded")
    assert res.exit_code == 0, res.output + res.stderr
    doc = json.loads(res.stdout)
    assert list(doc) == ["supply", "drain", "excluded", "units", "flow_method", "inputs"]
    check_schema("flowfit", doc)  # data_schema/json/flowfit.schema.json
    assert keys_without_unit(doc) == []
    truth = ValveModel.from_rig(load_rig())
    for side in ("supply", "drain"):
        assert abs(doc[side]["z0_mm"] - truth.side(side).z0_mm) < 0.01
        assert doc[side]["C_mm3_s_deg2_sqrtMPa"] == pytest.approx(truth.side(side).c_flow, rel=0.03)
    import pandas as pd
    per_run = pd.read_parquet(out / "per_run.parquet")
    for side in ("supply", "drain"):
        assert doc[side]["n_runs"] == int(per_run["used"][per_run["side"] == side].sum())
    assert doc["excluded"]["leakage"] == 4
    assert sum(doc["excluded"].values()) == int((~per_run["used"]).sum())
    # every run kept out is listed with the filter's reason
    skipped = {s["run_id"]: s["reason"] for s in doc["inputs"]["skipped"]}
    assert set(skipped) == set(per_run.run_id[~per_run["used"]])
    assert sum(r.startswith("leakage") for r in skipped.values()) == 4
    for name in ("flowfit.json", "model.toml", "model.json", "per_run.parquet",
                 "fig4.png", "fig4.svg", "manifest.json"):
        assert (out / name).is_file(), name
    assert json.loads((out / "flowfit.json").read_text()) == {k: v for k, v in doc.items()
                                                               if k != "inputs"}
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["extra"]["flowfit"]["side"] == "both"
    assert len(manifest["inputs"]) >= 4 * 2 * sum(map(len, CAMS.values()))
    m = read_model(out / "model.toml", rig=load_rig())
    assert m.supply.c_flow == pytest.approx(doc["supply"]["C_mm3_s_deg2_sqrtMPa"])


def test_report_and_one_side(dataset, tmp_path):
    res = invoke(dataset, "--out", tmp_path, "--side", "drain", "--n-boot", 0, "--formats", "png")
    assert res.exit_code == 0, res.output
    assert "drain: ok" in res.stdout and "supply" not in res.stdout.split("excluded")[0]
    assert "z0 =" in res.stdout and f"outputs: {tmp_path}" in res.stdout
    doc = json.loads((tmp_path / "flowfit.json").read_text())
    assert list(doc) == ["drain", "excluded", "units", "flow_method"]


def test_bad_run_exit_1_results_still_written(dataset, tmp_path):
    import shutil

    data = tmp_path / "data"
    shutil.copytree(dataset, data)
    clean = json.loads(invoke(data, "--out", tmp_path / "clean", "--json", "--n-boot", 0,
                              "--no-figures").stdout)
    bad = data / "supply-l0.3-c0.0"
    (bad / "encoder.csv").unlink()
    out = tmp_path / "out"
    res = invoke(data, "--out", out, "--json", "--n-boot", 0, "--formats", "png")
    assert res.exit_code == 1
    assert "1 bad run(s) skipped" in res.stderr and "supply-l0.3-c0.0" in res.stderr
    doc = json.loads(res.stdout)
    assert doc["supply"]["n_runs"] == clean["supply"]["n_runs"] - 1
    (failed,) = doc["inputs"]["failed"]  # the bad run, with why
    assert "supply-l0.3-c0.0" in failed["path"] and "encoder" in failed["message"]
    assert doc["inputs"]["runs_read"] == clean["inputs"]["runs_read"] - 1
    assert (out / "flowfit.json").is_file() and (out / "fig4.png").is_file()


def test_bad_input_exit_2(tmp_path):
    res = invoke(tmp_path / "missing", "--out", tmp_path / "o")
    assert res.exit_code == 2
    assert res.stderr.startswith("error: ") and "not found" in res.stderr


def test_no_data_uses_builtin(monkeypatch, dataset, tmp_path):
    pytest.importorskip("seanv_analysis.sim")
    import seanv_analysis.cli.flowfit_cmd as cmd

    calls = []
    monkeypatch.setattr(cmd, "sim_default_dataset", lambda name: calls.append(name) or dataset)
    res = invoke("--out", tmp_path, "--n-boot", 0, "--no-figures")
    assert res.exit_code == 0, res.output
    assert calls == ["paper-flowsteps"]
    first = res.stdout.splitlines()[0]
    assert first.startswith("no DATA given: using the built-in simulated data set")
    res = invoke("--out", tmp_path, "--n-boot", 0, "--json", "--no-figures")  # pure JSON
    assert json.loads(res.stdout)["units"]["z0_mm"] == "mm"


def test_subprocess_end_to_end(dataset, tmp_path):
    env = dict(os.environ, MPLBACKEND="Agg")
    proc = subprocess.run([sys.executable, "-m", "seanv_analysis", "flowfit", str(dataset),
                           "--out", str(tmp_path), "--json", "--n-boot", "0"],
                          capture_output=True, text=True, env=env, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["drain"]["C_mm3_s_deg2_sqrtMPa"] < 0


def test_figure_options(dataset, tmp_path):
    """--formats picks the files; --no-figures draws none and never loads matplotlib."""
    res = invoke(dataset, "--out", tmp_path / "png", "--n-boot", 0, "--formats", "png")
    assert res.exit_code == 0, res.output
    assert (tmp_path / "png" / "fig4.png").is_file() and not (tmp_path / "png" / "fig4.svg").exists()
    assert invoke(dataset, "--out", tmp_path / "x", "--formats", "pdf").exit_code == 2
    code = cli_call("flowfit", dataset, "--out", tmp_path / "none", "--n-boot", 0,
                    "--no-figures", "-q")
    assert modules_after(code, ["matplotlib"]) == []
    assert (tmp_path / "none" / "flowfit.json").is_file()
    assert not list((tmp_path / "none").glob("fig4.*"))


def test_peak_method_says_its_bias(dataset, tmp_path):
    """Issue 33, point 6: --method peak said 'ok' with intervals that can
    exclude the truth and no word of the estimate's known bias."""
    res = invoke(dataset, "--method", "peak", "--n-boot", "0", "--no-figures",
                 "--out", tmp_path / "o")
    assert res.exit_code == 0, res.output
    assert "fitted on the biased 'peak' flow estimate" in res.stdout
    assert "supply: ok" not in res.stdout and "+16 %" in res.stdout
    doc = json.loads(invoke(dataset, "--method", "peak", "--n-boot", "0", "--no-figures",
                            "--json", "--out", tmp_path / "j").stdout)
    assert doc["flow_method"] == "peak"
    check_schema("flowfit", doc)
    steady = json.loads(invoke(dataset, "--n-boot", "0", "--no-figures", "--json",
                               "--out", tmp_path / "s").stdout)
    assert steady["flow_method"] == "steady"
