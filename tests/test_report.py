"""report.html: self-contained, expected sections, embedded figures, provenance."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from seanv_analysis import __version__
from seanv_analysis.batch import load_pipeline, run_pipeline
from seanv_analysis.batch.runner import FailedRun, PipelineResult
from seanv_analysis.report import render_report, write_report
from seanv_analysis.stages import report_sections

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
                          runs_found=3, runs_read=2, summary=summary, results={"flowfit": fit},
                          excluded={"leakage": 1, "friction": 0}, figures={"fig4": [fig]},
                          failed=[FailedRun("/d/c", "ingest", "/d/c/encoder.csv: not found")],
                          rig=rig, command=["x"])


def test_report_fit_without_error_bars_says_so(tmp_path, rig):
    html = render_report(_fake_result(tmp_path, rig), report_sections())
    assert "no interval (singular covariance" in html        # drain side: NaN intervals
    assert "[0.4, 0.42]" in html or "[0.40000, 0.42000]" in html or "0.42" in html
    assert "bootstrap over runs" in html                      # interval method named
    assert "measured &minus; model" in html                   # residual sign
    assert "<svg" in html                                     # SVG-only figure inlined
    assert "Fig. 4: flow characterisation" in html            # with its registered title
    assert "leakage: |Q| = 42.0" in html                      # why a run was excluded
    assert "/d/c/encoder.csv: not found" in html


def test_write_report_atomic(tmp_path, rig):
    path = write_report(_fake_result(tmp_path, rig), tmp_path / "r" / "report.html", sections=report_sections())
    assert path.is_file()
    assert not list(path.parent.glob(".*.tmp"))


def _drift(side: str = "drain"):
    """An effect as discovery reports it: drift of one side's C."""
    from types import SimpleNamespace

    return SimpleNamespace(name="drift", side=side, params={"step": 0.005, "every": 3},
                           params_ci95={"step": (0.004, 0.006)}, p_value=0.01, f_p_value=0.02,
                           sentence=lambda: f"C of the {side} side falls 0.5 % every 3 runs")


def _discovery(verdict="effect_found", effects=None, position_control=None):
    from types import SimpleNamespace

    effects = [_drift()] if effects is None else effects
    text = "Discovery: the base model misses drift (drain)."
    if position_control:  # the line discover's own report writes (discover/result.py)
        n = position_control["n_runs"]
        text += f"\nPosition control ({n} run{'s' if n != 1 else ''} with a target flow; ...)"
    return SimpleNamespace(
        verdict=verdict, effects=effects, trend_variable="run_index" if verdict == "unexplained"
        else None, rmse_before_mm3_s=245.0, rmse_after_mm3_s=4.0, holdout="chrono",
        n_heldout_runs=52, improvement=0.98, validation=None, report=lambda: text)


def _validation(fit_pct=(96.1, 93.6)):
    from seanv_analysis.analysis.validate import Validation

    table = pd.DataFrame({"run_id": ["position-with-flow-model", "position-without-flow-model"],
                          "controller": ["flow_model", "cam"], "fit_position_pct": list(fit_pct),
                          "rmse_position_mm": [0.48, 0.84], "fit_flow_pct": [77.2, 64.2],
                          "rmse_flow_mm3_s": [226.1, 418.0], "fit_cam_pct": [77.2, 67.5],
                          "steps": [5, 5], "overshoot_measured_mm": [0.0, 2.75],
                          "overshoot_simulated_mm": [0.0, 2.55], "flagged": [False, False]})
    return Validation(table, [], 80.0)


def _identification(rig):
    from seanv_analysis.identify.result import Constant, Identification

    consts = [Constant("valve.drain.needle_y_c_mm", "drain needle centre y_c", 20.0, 20.0, "mm",
                       False, "threshold vs fluid force over 3 load levels (42 flow steps)",
                       note="the fluid force spans 3.0 N only"),
              Constant("actuator.viscous_friction_n_s_per_mm", "viscous friction", 2.0, 2.0,
                       "N s/mm", True, "force balance of 116 training flow steps", (1.98, 2.02)),
              Constant("valve.supply.c_flow", "supply C", 17.45, 17.43, "mm^3/(s deg^2 MPa^0.5)",
                       True, "flowfit with the identified geometry", (17.37, 17.54))]
    fits = {"flow_path": {"replay": {"metric": "open-loop replay flow fit [%]", "train": 79.1,
                                     "train_default": 78.3, "heldout": 78.6,
                                     "heldout_default": 77.5}}}
    return Identification(consts, rig, fits=fits)


def _per_load() -> pd.DataFrame:
    """flowfit's per-load table as a paper run has it: 16 columns, too wide
    for an 800 px window without scrolling."""
    rng = np.random.default_rng(0)
    cols = ["load_level_mpag", "n_runs", "p1_mpa", "dp_mpa", "p1_threshold_mpa",
            "dp_threshold_mpa", "theta_d_deg", "theta_d_se_deg", "alpha_mm3_s_deg2",
            "alpha_se_mm3_s_deg2", "rmse_mm3_s", "theta_d_model_deg", "alpha_model_mm3_s_deg2"]
    df = pd.DataFrame(rng.uniform(-30.0, 30.0, (10, len(cols))) * 1.2345678, columns=cols)
    df.insert(0, "side", ["supply"] * 5 + ["drain"] * 5)
    df["success"], df["message"] = True, ""
    return df


def _full_result(base, tmp_path, rig):
    """``base`` (a real pipeline record) with every section a paper run has:
    flow fit (drain lacking fit), the rig identified, validation of the
    identified and the augmented model, discovery finding drift (drain)."""
    import copy

    res = copy.copy(base)
    fake = _fake_result(tmp_path, rig)
    fake.flowfit.sides["drain"].lack_of_fit = True
    fake.flowfit.per_load = _per_load()
    res.flowfit, res.identify, res.discovery = fake.flowfit, _identification(rig), _discovery()
    means = {c: {k: float(v) for k, v in row.items() if k != "controller"} for c, row in
             _validation().by_controller().reset_index().set_index("controller").iterrows()}
    res.discovery.validation = {"before": means, "after": means}
    res.validation, res.validation_augmented = _validation(), _validation((96.6, 98.6))
    return res


def test_model_table_shows_flowfit_lack_of_fit(tmp_path, rig):
    """Without discovery, flowfit's own lack-of-fit verdict marks the side."""
    res = _fake_result(tmp_path, rig)
    res.flowfit.sides["drain"].lack_of_fit = True
    res.flowfit.sides["supply"].lack_of_fit = False
    html = render_report(res, report_sections())
    assert "lack of fit" in _row(html, "drain") and "class='ok'" not in _row(html, "drain")
    assert "class='ok'>ok<" in _row(html, "supply")


def test_model_table_unexplained_residual_flags_every_side(tmp_path, rig):
    res = _fake_result(tmp_path, rig)
    res.flowfit.sides["supply"].lack_of_fit = False
    res.discovery = _discovery("unexplained", effects=[])
    html = render_report(res, report_sections())
    for side in ("supply", "drain"):
        assert "no known effect explains it" in _row(html, side)
        assert "class='ok'" not in _row(html, side)
    assert "structured, but no known effect explains it; it trends with run_index" in html


def test_report_counts_runs_from_the_data(tmp_path, rig):
    """Run counts come from the data and the results, in words: 2
    position-control runs re-run of 2 in the data set; 52 held-out runs; a
    single run is '1 run'."""
    res = _fake_result(tmp_path, rig)
    res.summary = pd.concat([res.summary, pd.DataFrame(
        {"run_id": ["p1", "p2"], "kind": ["position_control"] * 2, "side": [None, None],
         "excluded": ["", ""], "run_index": [2, 3]})], ignore_index=True)
    res.validation = _validation()
    res.discovery = _discovery(position_control={"n_runs": 1})
    html = render_report(res, report_sections())
    assert "2 position-control runs re-run (of 2 in the data set)" in html
    assert "52 runs (chrono)" in html
    assert "Position control (1 run with a target flow" in html
    assert not re.search(r"n = 1 runs|\b1 runs\b", html)


def test_validation_section_tables_and_figures(tmp_path, rig, monkeypatch):
    """Validate's table for the identified twin and the augmented model, in
    words ('measured', 'simulated', never 'm/s'), each linking its drawn
    figures; an augmented model without figures says so."""
    from seanv_analysis.plots import FIGURES, Figure

    res = _full_result(_fake_result(tmp_path, rig), tmp_path, rig)
    png = tmp_path / "validate_fit.png"
    png.write_bytes(b"\x89PNG\r\n\x1a\n")
    res.figures = {"validate_fit": [png]}
    html = render_report(res, report_sections()).replace("<wbr>", "")
    val = html.split("id='validation'")[1].split("id='discovery'")[0]
    ident, aug = val.split("Augmented model")
    assert "identified twin" in ident and "href='#fig-validate_fit'" in ident
    assert "No validation figure drawn for the augmented model" in aug
    for part in (ident, aug):
        assert "overshoot, measured [mm]" in part and "overshoot, simulated [mm]" in part
        assert "position-without-flow-model" in part and "position fit [%]" in part
    assert "98.6" in aug and "98.6" not in ident
    assert "m/s" not in val.replace("mm³/s", "")
    # a figure of the augmented model's validation, when one is drawn, is linked there
    monkeypatch.setitem(FIGURES, "validate_augmented_fit", Figure(
        name="validate_augmented_fit", needs=("discovery",), draw=lambda *a, **k: [],
        title="Closed-loop validation of the augmented model"))
    res.figures["validate_augmented_fit"] = [png]
    val = render_report(res, report_sections()).split("id='validation'")[1].split("id='discovery'")[0]
    ident, aug = val.split("Augmented model")
    assert "href='#fig-validate_augmented_fit'" in aug
    assert "validate_augmented_fit" not in ident and "href='#fig-validate_fit'" in ident


def test_headers_are_words_with_units(tmp_path, rig):
    """No snake_case column name reaches a header; units in brackets."""
    res = _full_result(_fake_result(tmp_path, rig), tmp_path, rig)
    html = render_report(res, report_sections()).replace("<wbr>", "")
    heads = re.findall(r"<th[^>]*>([^<]*)</th>", html)
    assert heads and not [h for h in heads if "_" in h.replace("Q_ref", "").replace("θ_d", "")]
    for h in ("z0 [mm]", "C [mm³/(s·deg²·MPa^0.5)]", "C 95 % interval [mm³/(s·deg²·MPa^0.5)]",
              "RMSE [mm³/s]", "flow RMSE, augmented [mm³/s]"):
        assert f">{h}</th>" in html, h
    assert "mm³/(s·deg²·MPa^0.5)</td>" in html and "N·s/mm</td>" in html   # identify's units


def _row(html: str, side: str) -> str:
    """The model table's row of ``side``."""
    return html[html.index(f"<td class='l'>{side}</td>"):].split("</tr>")[0]


@pytest.mark.skipif(not (__import__("shutil").which("chromium")
                         or __import__("shutil").which("chromium-browser")),
                    reason="Chromium not installed (apt-get install chromium)")
def test_report_renders_in_headless_chromium(report_run, tmp_path, rig):
    """A report with every section (the pipeline's figures, the paper run's
    wide tables) lays out at 1280 and 800 px: the page never scrolls
    sideways, no table is wider than its container without a box that
    scrolls it, every embedded image decodes; at 1280 px no table needs
    scrolling at all. One Chromium launch per width."""
    import importlib.util

    script = Path(__file__).resolve().parents[1] / "scripts" / "check_report_browser.py"
    spec = importlib.util.spec_from_file_location("check_report_browser", script)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    path = write_report(_full_result(report_run, tmp_path, rig), tmp_path / "report.html", sections=report_sections())
    for width in (1280, 800):
        lay = mod.layout(path, width=width)
        assert lay["inner"] == width, lay
        assert lay["page"] <= lay["inner"] and lay["cut_tables"] == 0, (width, lay)
        assert lay["tables"] >= 10 and lay["images"] >= 3 and lay["broken_images"] == 0, lay
        if width == 1280:
            assert lay["scrolling_tables"] == 0, lay


def test_model_table_never_ok_beside_a_discovery_finding(tmp_path, rig):
    """The drain side that discovery says drifts is marked in the model table
    with the effect named, the verdict is said in words, and headers are
    words with units."""
    res = _fake_result(tmp_path, rig)
    res.discovery = _discovery()
    html = render_report(res, report_sections())
    drain = _row(html, "drain")
    assert "discovery found drift: C of the drain side falls 0.5 % every 3 runs" in drain
    assert "class='warn'" in drain and "class='ok'" not in drain
    assert "the model misses drift (drain)" in html and "effect_found" not in html
    assert "<th>why</th>" in html and "run_id" not in html.split("id='runs'")[1].split("<pre")[0]
    assert html.count("<div class='scroll'><table>") == html.count("<table>")


def test_identify_table_gives_no_reason_of_its_own_for_a_missing_interval(rig):
    """Issue 33, point 6: the identify table said 'no interval (singular
    covariance)' where the constant's note (beside it) gives the reason."""
    from types import SimpleNamespace

    from seanv_analysis.report.sections import identify_section

    html = identify_section(SimpleNamespace(identify=_identification(rig), stage_errors={}))
    assert "singular covariance" not in html
    assert "no interval" in html and "the fluid force spans 3.0 N only" in html


def test_moving_mass_note_says_small_accelerations(rig, monkeypatch):
    """Issue 33, point 6: '95th percentile |a| 0 mm/s^2' for accelerations
    under 0.5 mm/s^2: three significant digits now."""
    from types import SimpleNamespace

    from seanv_analysis.identify import engine

    t = np.linspace(0.0, 10.0, 1001)
    fake = pd.DataFrame({"t_s": t, "velocity_mm_s": 5.0 + 0.15 * t})   # a = 0.15 mm/s^2
    monkeypatch.setattr("seanv_analysis.signals.derive.derive_samples", lambda run: fake)
    c = engine._mass([SimpleNamespace()], rig, rig)
    assert "95th percentile |a| 0.15 mm/s^2" in c.note, c.note
