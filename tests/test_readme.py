"""The README's notebook snippet runs verbatim on the data set it names
(``data/flow``, made as the README says with
``seanv-analyze simulate paper-flowsteps-small``) and gives the truth."""
from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from fresh_process import cli_call, modules_after

README = Path(__file__).resolve().parents[1] / "README.md"


def _snippet() -> str:
    text = README.read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    return next(b for b in blocks if "sa.load_dataset" in b)


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    from seanv_analysis.sim import simulate_scenario

    root = tmp_path_factory.mktemp("readme")
    simulate_scenario("paper-flowsteps-small", root / "data" / "flow", seed=0)
    simulate_scenario("paper-position", root / "data" / "pos", seed=0)
    return root


def test_readme_snippet_runs_and_recovers_the_paper_values(folder, monkeypatch, capsys):
    import matplotlib

    matplotlib.use("Agg")
    monkeypatch.chdir(folder)
    scope: dict = {}
    exec(compile(_snippet(), str(README), "exec"), scope)
    out = capsys.readouterr().out
    assert "<DatasetResult 144/144 runs read (144 flow_step)>" in out
    frame = scope["fit"].to_frame()
    assert frame.loc["supply", "z0_mm"] == pytest.approx(-0.155, abs=0.002)
    assert frame.loc["drain", "C_mm3_s_deg2_sqrtMPa"] == pytest.approx(-22.636, rel=0.02)
    assert "<Estimate supply.C = 17." in out and scope["q"] > 0
    assert scope["ax"].get_xlabel() == "Cam rotation angle [deg]"
    assert "Discovery:" in out
    assert "<Tracking shift 0.250 s (given)" in out
    assert scope["res"].success and (folder / "outputs" / "flow" / "report.html").is_file()


def test_import_loads_no_plotting_library():
    # a matplotlib submodule brings its package: 'matplotlib' stands for any
    assert modules_after("import seanv_analysis as sa; sa.load_dataset", ["matplotlib"]) == []


def test_results_draw_on_the_callers_axes_and_render_as_tables(folder):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    import seanv_analysis as sa

    ds = sa.load_dataset(folder / "data" / "flow")
    fit = sa.flowfit(ds, n_boot=0)
    fig, (a, b, c) = plt.subplots(3, 1)
    assert fit.plot(ax=a) is a and a.get_ylabel() == "Flow rate [mm$^3$/s]"
    assert fit.plot(ax=[b, c], panel="b") == [b, c]
    assert ds.plot(ax=a) is a
    plt.close(fig)
    assert repr(fit).startswith("<FlowFit supply z0=") and len(repr(fit)) < 200
    assert "<table" in fit._repr_html_() and "<table" in ds._repr_html_()
    assert list(fit.to_frame().index) == ["supply", "drain"]
    assert len(ds.to_frame()) == 144
    with pytest.raises(ValueError, match="panel"):
        fit.plot(panel="c")
    text = fit.to_json()
    assert isinstance(text, str) and json.loads(text) == fit.to_json_dict()
    assert json.loads(text)["supply"]["n_runs"] == fit.sides["supply"].n_runs
    assert json.loads(ds.to_json())["runs_read"] == 144


def test_readme_headline_numbers_are_the_recorded_demo_output():
    """README's headline block is headline() of the demo result recorded in
    docs/demo_headline.json (scripts/update_readme_numbers.py writes both;
    `make demo` says when a run no longer matches them)."""
    from seanv_analysis.demo import RECORDED_HEADLINE, headline, readme_headline

    root = README.parent
    record = json.loads((root / RECORDED_HEADLINE).read_text())
    shown = readme_headline(README.read_text()).splitlines()
    assert shown[1:] == headline(record).splitlines()
    # how long make demo took: what make demo measured itself (issue 33, point 6)
    from seanv_analysis.demo import README_TIME_END, README_TIME_START, timing_text

    text = README.read_text()
    said = text.split(README_TIME_START, 1)[1].split(README_TIME_END, 1)[0]
    assert said == timing_text(record["timings"]) and "fresh clone" in said
    assert "45 s" not in text.split("## What `make demo` shows", 1)[1].split("```", 1)[0]
    # the record is a real pipeline result: the paper's supply side, the drift found
    assert record["flowfit"]["supply"]["z0_mm"] == pytest.approx(-0.155, abs=0.002)
    assert [e["name"] for e in record["discovery"]["effects"]] == ["drift"]


def test_demo_timing_sentence():
    from seanv_analysis.demo import timing_text

    said = timing_text({"fresh": {"total_s": 110.4, "install_s": 82.0, "simulation_s": 8.2,
                                  "analysis_s": 20.1, "cores": 2},
                        "reused": {"total_s": 2.2, "install_s": 0.0, "simulation_s": 0.1,
                                   "analysis_s": 1.5, "cores": 2}})
    assert said == ("On 2 cores, `make demo` took 1 min 50 s on a fresh clone (1 min 22 s "
                    "creating `.venv`, installing and compiling the simulator, 28 s for the demo "
                    "itself: simulating the data sets 8 s, the analysis 20 s); 2 s when run again "
                    "with nothing changed (measured by `make demo` itself: "
                    "outputs/demo/timings.json)")
    assert timing_text({}) == ""


def test_cli_help_loads_no_heavy_library():
    """`seanv-analyze --help` and a command's --help answer without importing
    pandas, scipy, numba or matplotlib (benchmarks/bench_commands.py times it)."""
    code = "\n".join(cli_call(*args, exits=True)
                     for args in (["--help"], ["flowfit", "--help"], ["run", "--help"]))
    assert modules_after(code, ["pandas", "scipy", "numba", "matplotlib"]) == []
