"""plots.registry: the figure entries, the formats they write, and the recipe
"a new figure = one module + one entry" (a toy figure reaches the report
without any other module edited)."""
from __future__ import annotations

import base64
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
from fresh_process import modules_after

from seanv_analysis.plots import FIGURES, Figure, describe_figures, register_figure
from seanv_analysis.report import render_report, write_report
from seanv_analysis.stages import report_sections, result_names

TOY_TITLE = "Toy figure: one line drawn for the recipe test"


def _draw_toy(results, folder: Path, *, formats=("png", "svg")) -> list[Path]:
    """The whole of a toy figure module: draw from the flow fit, write each format."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure as MplFigure

    fig = MplFigure(figsize=(2.0, 1.5))
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    ax.plot([0, 1], [0, results["flowfit"].slope])
    ax.set_xlabel("Cam angle [deg]")
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for ext in formats:
        path = folder / f"toy.{ext}"
        fig.savefig(path, format=ext, dpi=50)
        paths.append(path)
    return paths


TOY = Figure(name="toy", title=TOY_TITLE, needs=("flowfit",), draw=_draw_toy)


@pytest.fixture
def toy(monkeypatch):
    """The toy figure registered for one test, removed afterwards."""
    monkeypatch.setitem(FIGURES, TOY.name, TOY)
    return TOY


@pytest.fixture
def restored_registry():
    """The registry as it was, after a test that registers figures itself."""
    saved = dict(FIGURES)
    yield FIGURES
    FIGURES.clear()
    FIGURES.update(saved)


def _record(tmp_path: Path, figures: dict[str, list[Path]]) -> SimpleNamespace:
    """A pipeline record with every attribute the report reads (duck-typed:
    no stage ran, only figure files exist)."""
    pipeline = SimpleNamespace(name="toy-pipeline", description="figures only", source=None,
                               to_dict=lambda: {"name": "toy-pipeline"})
    return SimpleNamespace(
        pipeline=pipeline, data=[tmp_path / "data"], executor="serial", command=["toy"],
        rig=None, runs_found=0, runs_read=0, summary=pd.DataFrame(), excluded={}, failed=[],
        flowfit=None, tracking=None, validation=None, validation_augmented=None, discovery=None,
        figures=figures, stage_errors={}, stage_notes={}, warnings=[], input_hashes={},
        manifest_path=None, timings_s={}, computed={}, cached={})


# --- the registry -----------------------------------------------------------------

def test_registered_figures_are_consistent():
    assert list(FIGURES)[:6] == ["fig4", "fig6", "fig6_runs", "fig7", "validate_fit",
                                 "discover_residuals"]
    numbers = [f.number for f in FIGURES.values() if f.number is not None]
    assert len(numbers) == len(set(numbers)), numbers
    assert {f.number for f in FIGURES.values()} >= {4, 6, 7}
    for name, fig in FIGURES.items():
        assert fig.name == name
        assert fig.needs and set(fig.needs) <= {*result_names(), "runs"}, (name, fig.needs)
        assert fig.title.strip() and "\n" not in fig.title
        if fig.per_run:
            assert fig.draw_run is not None and fig.draw is None and fig.run_kind
            assert fig.needs == ("runs",)
        else:
            assert fig.draw is not None and fig.draw_run is None and "runs" not in fig.needs
    assert FIGURES["fig6"].per_run and FIGURES["fig6"].run_kind == "position_control"
    text = describe_figures()
    assert all(f.title in text for f in FIGURES.values())


def test_figure_entry_errors():
    with pytest.raises(ValueError, match="needs"):
        Figure(name="x", title="x", needs=(), draw=_draw_toy)
    with pytest.raises(ValueError, match="name"):
        Figure(name="a/b", title="x", needs=("flowfit",), draw=_draw_toy)
    with pytest.raises(ValueError, match="title"):
        Figure(name="x", title="two\nlines", needs=("flowfit",), draw=_draw_toy)
    with pytest.raises(ValueError, match="per-run figure has draw_run"):
        Figure(name="x", title="x", needs=("runs",), per_run=True, run_kind="position_control",
               draw=_draw_toy)
    with pytest.raises(ValueError, match="data-set figure has draw"):
        Figure(name="x", title="x", needs=("flowfit",))
    with pytest.raises(ValueError, match="per-run figures"):
        Figure(name="x", title="x", needs=("runs",), draw=_draw_toy)


def test_register_figure(restored_registry):
    fig = register_figure(Figure(name="toy2", title="t", needs=("tracking",), draw=_draw_toy))
    assert list(FIGURES)[-1] == "toy2" and FIGURES["toy2"] is fig
    with pytest.raises(ValueError, match="already registered"):
        register_figure(Figure(name="toy2", title="t", needs=("tracking",), draw=_draw_toy))
    with pytest.raises(ValueError, match="number 4 is already figure 'fig4'"):
        register_figure(Figure(name="toy3", number=4, title="t", needs=("tracking",),
                               draw=_draw_toy))
    register_figure(Figure(name="toy2", title="u", needs=("tracking",), draw=_draw_toy),
                    replace=True)
    assert FIGURES["toy2"].title == "u"


def test_import_does_not_load_matplotlib():
    assert modules_after("import seanv_analysis.plots, seanv_analysis.report",
                         ["matplotlib"]) == []


# --- the toy-figure recipe ----------------------------------------------------------

def test_toy_figure_reaches_the_report(toy, tmp_path):
    folder = tmp_path / "figures"
    paths = toy.draw({"flowfit": SimpleNamespace(slope=2.0)}, folder, formats=["png"])
    assert [p.name for p in paths] == ["toy.png"]
    record = _record(tmp_path, {"toy": paths})
    html = render_report(record, report_sections())
    assert TOY_TITLE in html
    assert "id='fig-toy'" in html
    assert base64.b64encode(paths[0].read_bytes()).decode("ascii") in html  # embedded, not linked
    written = write_report(record, tmp_path / "out" / "report.html", sections=report_sections())
    assert TOY_TITLE in written.read_text()


def test_report_follows_registry_order_and_skips_unknown(toy, tmp_path):
    svg = tmp_path / "x.svg"
    svg.write_text("<svg xmlns='http://www.w3.org/2000/svg' width='4' height='4'></svg>")
    toy_png = _draw_toy({"flowfit": SimpleNamespace(slope=1.0)}, tmp_path, formats=["png"])
    record = _record(tmp_path, {"toy": toy_png, "fig4": [svg], "not_registered": [svg]})
    html = render_report(record, report_sections())
    # fig4 is registered before the toy, so it comes first, each with its title
    assert html.index(FIGURES["fig4"].title) < html.index(TOY_TITLE)
    assert "not_registered" not in html


def test_report_without_figures_says_why(tmp_path):
    record = _record(tmp_path, {})
    record.stage_notes = {"figures": "fig 4: no flow fit"}
    html = render_report(record, report_sections())
    assert "id='figures'" in html and "No figure (fig 4: no flow fit)" in html


# --- the real figures write exactly the formats asked ---------------------------------

@pytest.fixture(scope="module")
def position_runs(tmp_path_factory):
    from conftest import write_synthetic_dataset

    from seanv_analysis.io import read_dataset

    root = write_synthetic_dataset(tmp_path_factory.mktemp("figs") / "data", n_flow=0,
                                   n_position=2, duration_s=1.0)
    return read_dataset(root).runs


def _flowfit(rig):
    """A FlowFit built from the rig's valve model (exact flows), enough to draw Fig. 4."""
    from seanv_analysis.fit import FlowFit, SideFit
    from seanv_analysis.models import ValveModel

    model = ValveModel.from_rig(rig)
    rows = []
    for side, cams in (("supply", (-5.0, 0.0, 5.0, 10.0)), ("drain", (-40.0, -32.5, -25.0, -20.0))):
        vs = model.side(side)
        for load in (0.3, 0.5):
            p1, dp = (0.9, 0.9 - load - 0.1) if side == "supply" else (load + 0.1, load + 0.1)
            for cam in cams:
                rows.append({"side": side, "load_level_mpag": load, "theta_deg": cam,
                             "q_mm3_s": float(vs.flow(cam, p1, dp)), "p1_mpa": p1, "dp_mpa": dp,
                             "used": True, "excluded": "",
                             "theta_d_implied_deg": float(vs.threshold_deg(p1, dp))})
    per_load = pd.DataFrame(columns=["side", "success", "dp_mpa", "theta_d_deg", "theta_d_se_deg"])
    sides = {s: SideFit(s, z0_mm=model.side(s).z0_mm, c_flow=model.side(s).c_flow, success=True)
             for s in ("supply", "drain")}
    return FlowFit(sides, model, pd.DataFrame(rows), per_load, {}, True)


@pytest.mark.parametrize("name, formats", [("fig4", ["svg"]), ("fig7", ["png"])])
def test_dataset_figures_write_exactly_the_formats_asked(name, formats, rig, position_runs,
                                                         tmp_path):
    from seanv_analysis.analysis.tracking import tracking_runs

    results = ({"flowfit": _flowfit(rig)} if name == "fig4"
               else {"tracking": tracking_runs(position_runs, shift_s=0.25)})
    folder = tmp_path / name
    paths = FIGURES[name].draw(results, folder, formats=formats)
    assert paths and all(p.is_file() and p.stat().st_size > 500 for p in paths)
    assert {p.suffix.lstrip(".") for p in paths} == set(formats)
    assert sorted(folder.iterdir()) == sorted(paths)  # nothing else written
    stems = {p.stem for p in paths}
    assert stems == ({"fig4"} if name == "fig4" else {"fig7", "fig7_pos000", "fig7_pos001"})


def test_per_run_figure_writes_the_formats_asked(rig, position_runs, tmp_path):
    fig6 = FIGURES["fig6"]
    paths = fig6.draw_run(position_runs[0], tmp_path, formats=("svg",), rig=rig)
    assert [p.name for p in paths] == [f"fig6_{position_runs[0].run_id}.svg"]
    assert sorted(tmp_path.iterdir()) == paths
    assert np.all([p.read_text().lstrip().startswith("<?xml") for p in paths])


def test_discovery_residuals_keep_only_the_formats_asked(rig, tmp_path):
    from synthetic_flow import synthetic_flow_summary

    from seanv_analysis.discover import discover_flow_steps
    from seanv_analysis.models import ValveModel

    truth = ValveModel.from_rig(rig)
    disc = discover_flow_steps(synthetic_flow_summary(truth, rig, seed=1), model=truth)
    paths = FIGURES["discover_residuals"].draw({"discovery": disc}, tmp_path, formats=["svg"])
    assert [p.name for p in paths] == ["discover_residuals.svg"]
    assert [p.name for p in tmp_path.iterdir()] == ["discover_residuals.svg"]
    assert paths[0].read_text().lstrip().startswith("<?xml")
    with pytest.raises(ValueError, match="formats"):
        FIGURES["discover_residuals"].draw({"discovery": disc}, tmp_path, formats=[".pdf"])


def test_formats_errors(rig, position_runs, tmp_path):
    with pytest.raises(ValueError, match="formats: expected at least one"):
        FIGURES["fig6"].draw_run(position_runs[0], tmp_path, formats=[], rig=rig)
    with pytest.raises(ValueError, match="formats: '.svg' is not a file format"):
        FIGURES["fig6"].draw_run(position_runs[0], tmp_path, formats=[".svg"], rig=rig)


def test_fig4_draws_into_a_given_figure(rig):
    from seanv_analysis.plots._style import new_figure
    from seanv_analysis.plots.fig4 import draw_fig4

    fig = new_figure(figsize=(8, 4), layout="constrained")
    assert draw_fig4(_flowfit(rig), fig) is fig
    assert len(fig.axes) == 3  # (a) and (b) per side
    assert fig.axes[0].get_ylabel() == "Flow rate [mm$^3$/s]"


def test_per_run_figures_drawn_by_worker_processes(tmp_path, make_dataset):
    """With worker processes the per-run Fig. 6 task (and its cache check) is
    sent to them: a lambda there made every Fig. 6 fail ("Can't pickle
    local object") whenever run used more than one worker."""
    from seanv_analysis.batch import run_pipeline

    make_dataset(tmp_path / "data", n_flow=2, n_position=2)
    pipe = {"pipeline": {"name": "f"}, "stages": [{"name": "ingest"}, {"name": "tracking"},
                                                   {"name": "figures", "figs": [6]}]}
    res = run_pipeline(pipe, tmp_path / "data", out_dir=tmp_path / "out", workers=2, quiet=True)
    assert not res.stage_errors, res.stage_errors
    fig6 = sorted(p.name for p in (tmp_path / "out" / "figures").rglob("fig6_pos*.png"))
    assert fig6 == ["fig6_pos000.png", "fig6_pos001.png"], res.summary_text()


def test_fig7_scatter_is_the_commanded_target_run_with_the_headline_rmse(position_runs, tmp_path):
    """As the paper's Fig. 7(b): the scatter holds the runs whose Q_ref the
    controller commanded, and its RMSE is the tracking headline (issue 33,
    point 2: one number everywhere); a target only implied by a model is
    labelled so."""
    import dataclasses

    import matplotlib

    matplotlib.use("Agg")
    from seanv_analysis.analysis.tracking import tracking_runs
    from seanv_analysis.plots.fig7 import TARGET_LABELS, plot_fig7, scatter_runs

    tr = tracking_runs(position_runs, shift_s=0.25)
    logged, implied = tr.runs[0], dataclasses.replace(tr.runs[1], target_source="model")
    tr = dataclasses.replace(tr, runs=[implied, logged], pooled_runs=[logged.run_id],
                             rmse_mm3_s=logged.rmse_mm3_s)
    runs, which = scatter_runs(tr)
    assert runs == [logged] and which == tr.pooled == "runs with a commanded Q_ref"
    assert [p.name for p in plot_fig7(tr, tmp_path, per_run=False, formats=("png",))] == [
        "fig7.png"]
    from seanv_analysis.plots._style import new_figure
    from seanv_analysis.plots.fig7 import draw_flow_time

    f = new_figure()
    ax = f.subplots()
    draw_flow_time(ax, implied)
    assert TARGET_LABELS["model"] in [t.get_text() for t in ax.get_legend().get_texts()]


def test_dataset_figure_not_redrawn_when_its_inputs_are_unchanged(position_runs, tmp_path,
                                                                   monkeypatch, rig):
    """A second draw with equal inputs (new objects) writes nothing; another
    input, another rig or other formats draw again."""
    import dataclasses
    import json
    from types import SimpleNamespace

    import seanv_analysis.stages.figures as stage
    from seanv_analysis.analysis.tracking import tracking_runs

    def tiny_fig7(results, folder, *, formats):   # the registry's draw, but light: fast test
        from seanv_analysis.plots._style import new_figure, save_figure

        fig = new_figure(figsize=(1.0, 1.0))
        fig.subplots().plot([0, 1], [0, results["tracking"].lag_s])
        return save_figure(fig, folder, "fig7", formats=formats, dpi=30)

    monkeypatch.setitem(FIGURES, "fig7", dataclasses.replace(FIGURES["fig7"], draw=tiny_fig7,
                                                            parts=None))  # one file

    def draw(tracking, rig=rig, formats=("png",)):
        ctx = SimpleNamespace(log=lambda msg: None, result=lambda name: None, rig=rig)
        monkeypatch.setattr(stage, "results_for_figures",
                            lambda c, names=None: {"tracking": tracking})
        res = stage.draw_figures(ctx, ["fig7"], tmp_path, formats=formats)
        return res.paths["fig7"], res.keys_file

    first, keys_file = draw(tracking_runs(position_runs, shift_s=0.25))
    stamps = {p: p.stat().st_mtime_ns for p in first}
    keys_stamp = keys_file.stat().st_mtime_ns
    assert json.loads(keys_file.read_text())["fig7"]["key"] == stage.figure_key(
        "fig7", {"tracking": tracking_runs(position_runs, shift_s=0.25)}, ("png",), rig)
    again, _ = draw(tracking_runs(position_runs, shift_s=0.25))  # equal inputs: files reused
    assert again == first and {p: p.stat().st_mtime_ns for p in again} == stamps
    assert keys_file.stat().st_mtime_ns == keys_stamp            # nothing written at all
    redrawn, _ = draw(tracking_runs(position_runs, shift_s=0.20))  # another shift: drawn again
    assert all(p.stat().st_mtime_ns != stamps[p] for p in redrawn)
    stamps = {p: p.stat().st_mtime_ns for p in redrawn}
    other_rig = dataclasses.replace(rig, data={**rig.data, "name": "another rig"})
    redrawn, _ = draw(tracking_runs(position_runs, shift_s=0.20), rig=other_rig)
    assert all(p.stat().st_mtime_ns != stamps[p] for p in redrawn)
    assert stage.figure_key("fig7", {"x": 1}, ("png",), rig) != stage.figure_key(
        "fig7", {"x": 1}, ("svg",), rig)
    assert stage.figure_key("fig7", {"x": object()}, ("png",), rig) is None  # not hashable: drawn


@pytest.fixture(scope="module")
def paper_position(tmp_path_factory):
    """The demo's position-control runs (Sec. III-C, loads 0.35/0.45 MPaG),
    simulated on the built-in plant: what Fig. 6, 7 and validate draw."""
    from seanv_analysis.io import read_dataset
    from seanv_analysis.sim import simulate_scenario

    root = simulate_scenario("paper-position", tmp_path_factory.mktemp("pp") / "position", seed=0)
    return read_dataset(root).runs


def _legends_over_axes(fig) -> list[str]:
    """Each legend that covers any axes' area (the data), as 'legend "first
    label" over axes "title"'; the layout as it is saved."""
    from matplotlib.transforms import Bbox

    fig.draw_without_rendering()
    renderer = fig.canvas.get_renderer()
    legends = [ax.get_legend() for ax in fig.axes if ax.get_legend() is not None] + fig.legends
    out = []
    for leg in legends:
        box = leg.get_window_extent(renderer)
        for ax in fig.axes:
            if not ax.get_visible():
                continue
            inter = Bbox.intersection(box, ax.get_window_extent(renderer))
            if inter is not None and inter.width > 1 and inter.height > 1:
                first = leg.get_texts()[0].get_text() if leg.get_texts() else ""
                out.append(f"legend {first!r} over axes {ax.get_title(loc='left') or ax.get_title()!r}")
    return out


def _legend_texts(fig) -> set[str]:
    legends = [ax.get_legend() for ax in fig.axes if ax.get_legend() is not None] + fig.legends
    return {t.get_text() for leg in legends for t in leg.get_texts()}


def test_legends_never_cover_data_and_both_loads_are_named(rig, paper_position, tmp_path,
                                                           monkeypatch):
    """Issue 33, point 5: every figure of the demo keeps its legends off the
    axes (the position traces at 30-33 mm between 35 and 80 s, the Q_ref
    peaks, the scatter were covered), and the load shading has one label,
    ``load 0.45 MPaG (shaded)``, with the 0.35 MPaG load named too."""
    import importlib

    from synthetic_flow import synthetic_flow_summary

    from seanv_analysis.analysis.tracking import tracking_runs
    from seanv_analysis.analysis.validate import validate_runs
    from seanv_analysis.discover import discover_flow_steps
    from seanv_analysis.models import ValveModel
    from seanv_analysis.plots import _style

    drawn: dict[str, object] = {}

    def capture(fig, out_dir, stem, **kwargs):
        drawn[stem] = fig
        return [Path(out_dir) / f"{stem}.png"]

    for name in ("fig4", "fig6", "fig7", "validate", "residuals"):
        monkeypatch.setattr(importlib.import_module(f"seanv_analysis.plots.{name}"),
                            "save_figure", capture)
    monkeypatch.setattr(_style, "save_figure", capture)
    truth = ValveModel.from_rig(rig)
    tracking = tracking_runs(paper_position, model=truth)
    validation = validate_runs(paper_position[:1], truth, rig=rig)
    discovery = discover_flow_steps(synthetic_flow_summary(truth, rig, seed=1), model=truth)
    results = {"flowfit": _flowfit(rig), "tracking": tracking, "validation": validation,
               "discovery": discovery, "position_runs": paper_position}
    for name in ("fig4", "fig7", "validate_fit", "discover_residuals", "fig6_runs"):
        FIGURES[name].draw(results, tmp_path, formats=("png",))
    FIGURES["fig6"].draw_run(paper_position[0], tmp_path, formats=("png",), rig=rig)
    assert {"fig4", "fig7", "validate_fit", "discover_residuals", "fig6"} <= set(drawn) and \
        any(s.startswith("fig7_") for s in drawn) and any(s.startswith("fig6_") for s in drawn)
    for stem, fig in drawn.items():
        assert _legends_over_axes(fig) == [], stem
    for stem in [s for s in drawn if s.startswith(("fig6_", "fig7", "validate_position"))]:
        texts = _legend_texts(drawn[stem])
        assert {"load 0.45 MPaG (shaded)", "load 0.35 MPaG"} <= texts, (stem, texts)
        assert not any("higher load" in t for t in texts), stem
