"""The stage layer: the stage list, ``run --list-stages``, the figure recipe
through the pipeline runner, and stages run one by one in a notebook."""
from __future__ import annotations

import json
import math

import pytest
from click.testing import CliRunner

from seanv_analysis.batch import STAGE_NAMES, load_pipeline, run_pipeline
from seanv_analysis.cli import cli
from seanv_analysis.errors import ConfigError
from seanv_analysis.stages import STAGES, Context, dataset, run_stages, tracking


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    from conftest import write_synthetic_dataset

    return write_synthetic_dataset(tmp_path_factory.mktemp("stages") / "data", n_flow=2,
                                   n_position=2)


def test_stage_modules_follow_the_protocol():
    assert tuple(STAGES) == STAGE_NAMES
    for name, mod in STAGES.items():
        assert mod.NAME == name and mod.DESCRIPTION and mod.WRITES
        assert all(n in STAGES for n in mod.NEEDS), name
        assert callable(mod.run) and callable(mod.write) and callable(mod.check_option)
        for key, value in mod.OPTIONS.items():  # the defaults pass their own check
            assert mod.check_option(key, value) == value or value is None


def test_list_stages_prints_needs_and_writes():
    res = CliRunner().invoke(cli, ["run", "--list-stages"])
    assert res.exit_code == 0, res.output
    for name, mod in STAGES.items():
        assert f"{name}: {mod.DESCRIPTION}" in res.output
    assert "writes:  flowfit/flowfit.json" in res.output
    assert "options: holdout='chrono', seed=0" in res.output


def test_run_without_pipeline_is_usage_error():
    res = CliRunner().invoke(cli, ["run"])
    assert res.exit_code == 2 and "PIPELINE" in res.output


def test_pipeline_option_checked_by_its_stage():
    with pytest.raises(ConfigError, match="stage 'figures' option 'figs'.*expected"):
        load_pipeline({"stages": [{"name": "ingest"}, {"name": "figures", "figs": ["nope"]}]})
    with pytest.raises(ConfigError, match="option 'n_boot' = -1"):
        load_pipeline({"stages": [{"name": "ingest"}, {"name": "flowfit", "n_boot": -1}]})


def test_toy_figure_drawn_by_the_pipeline_and_in_the_report(data, tmp_path, monkeypatch):
    """The figure recipe: one registry entry, no other module edited."""
    from seanv_analysis import plots

    def draw(results, folder, *, formats):
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        tr = results["tracking"]
        fig, ax = plt.subplots(figsize=(2, 2))
        ax.bar(range(len(tr.runs)), [r.rmse_mm3_s for r in tr.runs])
        folder.mkdir(parents=True, exist_ok=True)
        paths = [folder / f"toy.{f}" for f in formats]
        for p in paths:
            fig.savefig(p)
        plt.close(fig)
        return paths

    toy = plots.Figure(name="toy", title="Toy: tracking RMSE per run", needs=("tracking",),
                       draw=draw)
    monkeypatch.setitem(plots.FIGURES, "toy", toy)
    doc = {"pipeline": {"name": "toy"},
           "stages": [{"name": "ingest"}, {"name": "tracking", "shift_s": 0.05},
                      {"name": "figures", "figs": ["toy"], "formats": ["png"]},
                      {"name": "report"}]}
    res = run_pipeline(doc, data, out_dir=tmp_path / "o", workers=1, quiet=True)
    assert res.stage_errors == {}
    assert res.figures == {"toy": [tmp_path / "o" / "figures" / "toy.png"]}
    assert (tmp_path / "o" / "figures" / "toy.png").stat().st_size > 500
    html = res.report_path.read_text()
    assert "Toy: tracking RMSE per run" in html


def test_stages_one_by_one_in_a_notebook(data):
    ctx = Context.for_data(data)
    ds = dataset.run(ctx, {})
    ctx.add("ingest", ds)
    assert ds.runs_read == 4 and len(ds.kind("position_control")) == 2
    tr = tracking.run(ctx, {"shift_s": 0.05})
    same = run_stages(data, ["ingest", "tracking"], options={"tracking": {"shift_s": 0.05}})
    assert tr.to_json_dict() == same.result("tracking").to_json_dict()
    assert math.isfinite(tr.rmse_mm3_s)
    # notebook display: a one-line repr with units, a table, JSON text
    assert repr(tr).startswith("<Tracking shift 0.050 s (given), RMSE ") and "mm^3/s" in repr(tr)
    assert len(tr.to_frame()) == 2 and "<table" in tr._repr_html_()
    assert json.loads(tr.to_json())["shift_s"] == 0.05
    assert repr(ctx.rig).startswith("<RigConfig ") and len(repr(ctx.rig)) < 120
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2)
    assert tr.plot(ax=a) is a and a.get_xlabel().startswith("Target flow rate")
    assert tr.plot(ax=b, panel="a", run=tr.runs[0].run_id) is b
    with pytest.raises(ValueError, match="run"):
        tr.plot(panel="a", run="nope")
    plt.close(fig)
    assert ctx.model is None and ctx.valve is not None  # no model given: the rig's where needed
