"""report.html: self-contained, expected sections, embedded figures, provenance."""
from __future__ import annotations

import re
from pathlib import Path

import pandas as pd
import pytest

from seanv_analysis import __version__
from seanv_analysis.batch import load_pipeline, run_pipeline
from seanv_analysis.batch.runner import FailedRun, PipelineResult
from seanv_analysis.report import render_report, write_report

SECTIONS = ("overview", "flowfit", "tracking", "validation", "discovery", "runs", "provenance")


@pytest.fixture(scope="module")
def report_run(tmp_path_factory):
    from conftest import write_synthetic_dataset, write_synthetic_run

    root = tmp_path_factory.mktemp("report")
    data = write_synthetic_dataset(root / "data", n_flow=8, n_position=2)
    write_synthetic_run(data, "flow_step", run_id="bad-run", tables={"servo": None},
                        started_at="2026-03-02T12:00:00Z", duration_s=0.5)
    doc = {"pipeline": {"name": "report-test", "description": "test"},
           "stages": [{"name": "ingest"}, {"name": "tracking", "shift_s": 0.05},
                      {"name": "figures", "figs": [6, 7]}, {"name": "report"}]}
    res = run_pipeline(doc, data, out_dir=root / "out", workers=1, quiet=True,
                       command=["seanv-analyze", "run", "report-test", str(data)])
    return res


def test_report_written_with_sections(report_run):
    path = report_run.report_path
    assert path == report_run.out_dir / "report.html" and path.is_file()
    html = path.read_text()
    for sid in SECTIONS:
        assert f"id='{sid}'" in html
    assert html.startswith("<!DOCTYPE html>")
    assert f"seanv-analysis {__version__}" in html


def test_report_is_self_contained(report_run):
    html = report_run.report_path.read_text()
    assert html.count("data:image/png;base64,") >= 3  # fig 7 + two fig 6
    assert not re.search(r"""(src|href)\s*=\s*['"]?(https?:|//|file:)""", html)
    assert "<script" not in html and "<link" not in html


def test_report_figures_follow_the_registry(report_run):
    from seanv_analysis.plots import FIGURES

    html = report_run.report_path.read_text()
    drawn = [f for f in FIGURES.values() if report_run.figures.get(f.name)]
    assert {f.name for f in drawn} >= {"fig6", "fig7"}
    positions = [html.index(f"id='fig-{f.name}'") for f in drawn]
    assert positions == sorted(positions)                   # registry order
    for f in drawn:
        assert f.title in html                              # title as heading and caption
    assert FIGURES["fig4"].title not in html                # not drawn: not shown
    assert "href='#fig-fig7'" in html                       # linked from the tracking section


def test_report_lists_failed_and_provenance(report_run):
    html = report_run.report_path.read_text()
    assert "bad-run" in html and "servo" in html          # the failed run and why
    assert "seanv-analyze run report-test" in html          # command line
    some_hash = next(iter(report_run.input_hashes.values()))
    assert some_hash in html                                # input hashes
    assert "leakage_flow_mm3_s" in html                     # rig config
    assert "Flow tracking" in html and "RMSE" in html
    assert "No flow fit" in html                            # stage not in the pipeline


def _fake_result(tmp_path, rig) -> PipelineResult:
    from seanv_analysis.fit import FlowFit, SideFit
    from seanv_analysis.models import ValveModel

    model = ValveModel.from_rig(rig)
    sides = {"supply": SideFit("supply", z0_mm=0.41, c_flow=17.4, z0_ci95=(0.40, 0.42),
                               c_ci95=(16.9, 17.9), rmse_mm3_s=120.0, n_runs=30,
                               ci_method="bootstrap over runs, percentile", success=True),
             "drain": SideFit("drain", z0_mm=0.38, c_flow=-15.0, rmse_mm3_s=200.0, n_runs=12,
                              success=True, message="singular covariance")}
    fit = FlowFit(sides, model, pd.DataFrame(), pd.DataFrame(), {"leakage": 2}, True)
    summary = pd.DataFrame({"run_id": ["a", "b"], "kind": ["flow_step"] * 2,
                            "side": ["supply", "drain"], "excluded": ["", "leakage"],
                            "excluded_detail": ["", "leakage: |Q| = 42.0 mm^3/s <= 50 mm^3/s"],
                            "run_index": [0, 1], "load_mpag": [0.35, 0.35], "cam_deg": [-8, -30],
                            "q_mm3_s": [2000.0, 42.0]})
    fig = tmp_path / "fig4.svg"
    fig.write_text("<?xml version='1.0'?><svg xmlns='http://www.w3.org/2000/svg' width='10' "
                   "height='10'><rect width='10' height='10'/></svg>")
    return PipelineResult(load_pipeline("flowfit"), [tmp_path / "data"], tmp_path, executor="serial",
                          runs_found=3, runs_read=2, summary=summary, flowfit=fit,
                          excluded={"leakage": 1, "friction": 0}, figures={"fig4": [fig]},
                          failed=[FailedRun("/d/c", "ingest", "/d/c/encoder.csv: not found")],
                          rig=rig, command=["x"])


def test_report_fit_without_error_bars_says_so(tmp_path, rig):
    html = render_report(_fake_result(tmp_path, rig))
    assert "no interval (singular covariance" in html        # drain side: NaN intervals
    assert "[0.4, 0.42]" in html or "[0.40000, 0.42000]" in html or "0.42" in html
    assert "bootstrap over runs" in html                      # interval method named
    assert "measured &minus; model" in html                   # residual sign
    assert "<svg" in html                                     # SVG-only figure inlined
    assert "Fig. 4: flow characterisation" in html            # with its registered title
    assert "leakage: |Q| = 42.0" in html                      # why a run was excluded
    assert "/d/c/encoder.csv: not found" in html


def test_write_report_atomic(tmp_path, rig):
    path = write_report(_fake_result(tmp_path, rig), tmp_path / "r" / "report.html")
    assert path.is_file()
    assert not list(path.parent.glob(".*.tmp"))


@pytest.mark.skipif(not (__import__("shutil").which("chromium")
                         or __import__("shutil").which("chromium-browser")),
                    reason="Chromium not installed (apt-get install chromium)")
def test_report_renders_in_headless_chromium(report_run, tmp_path):
    import importlib.util

    script = Path(__file__).resolve().parents[1] / "scripts" / "check_report_browser.py"
    spec = importlib.util.spec_from_file_location("check_report_browser", script)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    shot = mod.screenshot(report_run.report_path, tmp_path / "shot.png", height=2000)
    from PIL import Image

    with Image.open(shot) as im:
        assert im.size == (1280, 2000)
        colours = im.convert("RGB").resize((64, 100)).getcolors(64 * 100)
    assert colours is None or len(colours) > 20  # not a blank page
    # nothing sticks out sideways or is cut, on a laptop and on a narrow window
    for width in (1280, 800):
        lay = mod.layout(report_run.report_path, width=width)
        assert lay["page"] <= lay["inner"] and lay["cut_tables"] == 0, (width, lay)


def test_model_table_never_ok_beside_a_discovery_finding(tmp_path, rig):
    """The drain side that discovery says drifts is marked in the model table,
    the verdict is said in words, and headers are words with units."""
    from types import SimpleNamespace

    res = _fake_result(tmp_path, rig)
    effect = SimpleNamespace(name="drift", side="drain", params={"step": 0.005},
                             params_ci95={"step": (0.004, 0.006)}, p_value=0.01, f_p_value=0.02,
                             sentence=lambda: "C of the drain side falls 0.5 % every 3 runs")
    res.discovery = SimpleNamespace(
        verdict="effect_found", effects=[effect], trend_variable=None, rmse_before_mm3_s=245.0,
        rmse_after_mm3_s=4.0, holdout="chrono", n_heldout_runs=52, improvement=0.98,
        validation=None, report=lambda: "Discovery: the base model misses drift (drain).")
    html = render_report(res)
    drain_row = html[html.index("<td class='l'>drain</td>"):].split("</tr>")[0]
    assert "discovery: drift" in drain_row and "class='ok'" not in drain_row
    assert "the model misses drift (drain)" in html and "effect_found" not in html
    assert "<th>why</th>" in html and "run_id" not in html.split("id='runs'")[1].split("<pre")[0]
    assert html.count("<div class='scroll'><table>") == html.count("<table>")
