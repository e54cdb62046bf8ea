"""The recipes of docs/architecture.md, each followed here with a toy item:
a stage, a figure and an input format are one new file each (dropped on
the package's path, nothing else edited), a term variable is one call, a
valve effect one class (tests/test_effect_registry.py), a plant effect its
class and its kernel term (tests/test_plant_recipe.py).
"""
from __future__ import annotations

import importlib
import json
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

TOY_STAGE = '''
"""Stage ``toy``: the flow-step runs counted (the recipe's one file)."""
from dataclasses import dataclass
from pathlib import Path

from seanv_analysis.io import write_json_atomic
from seanv_analysis.report import ReportSection
from seanv_analysis.stages.base import Result

NAME = "toy"
ORDER = 65
DESCRIPTION = "the flow-step runs counted"
NEEDS = ("ingest",)
WRITES = ("toy/toy.json",)
FOLDER = "toy"
OPTIONS = {"scale": 1}


@dataclass(frozen=True)
class ToyCount:
    n_runs: int

    def to_json_dict(self):
        return {"n_runs": self.n_runs}


RESULTS = (Result("toy_count", "ToyCount"),)
SECTION = ReportSection("toy", "Toy: the flow steps counted",
                        lambda r: f"<p>{r.toy_count.n_runs} flow steps</p>" if r.toy_count
                        else "<p>no toy count</p>")


def check_option(key, value):
    if key == "scale" and (not isinstance(value, int) or isinstance(value, bool)):
        raise ValueError("a whole number")
    return value


def run(ctx, options):
    summary = ctx.result("ingest").summary
    return ToyCount(int((summary["kind"] == "flow_step").sum()) * options.get("scale", 1))


def write(result, folder):
    return [write_json_atomic(Path(folder) / "toy.json", result.to_json_dict())]
'''

TOY_FIGURE = '''
"""A toy figure: the toy stage's count as one bar (the recipe's one file)."""
from seanv_analysis.plots._style import new_figure, save_figure
from seanv_analysis.plots.registry import Figure, register_figure


def draw(results, folder, *, formats):
    fig = new_figure(figsize=(1.0, 1.0))
    fig.subplots().bar([0], [results["toy_count"].n_runs])
    return save_figure(fig, folder, "toybar", formats=formats, dpi=30)


register_figure(Figure(name="toybar", title="Toy: the count as a bar", needs=("toy_count",),
                       draw=draw))
'''

TOY_FORMAT = '''
"""Tab-separated tables (the recipe's one file)."""
import pandas as pd
import pyarrow as pa

from seanv_analysis.errors import DataError
from seanv_analysis.io.contract import canonical_names
from seanv_analysis.io.formats import TableFormat, register_format


def parse_tsv(path, spec, head, pool):
    try:
        df = pd.read_csv(path, sep="\\t")
    except (ValueError, UnicodeDecodeError) as exc:
        raise DataError(f"not a readable TSV table ({exc})", path=path) from None
    table = pa.Table.from_pandas(df, preserve_index=False)
    return table.rename_columns(canonical_names(table.column_names, spec))


register_format(TableFormat("tsv", "TSV", (".tsv",), parse_tsv, text=True))
'''


@pytest.fixture
def plugged(tmp_path):
    """``plug(package, module_name, source)``: one file dropped on a package's
    path; everything is unplugged (path, module, registries) afterwards."""
    added = []

    def plug(package: str, name: str, source: str) -> Path:
        pkg = importlib.import_module(package)
        folder = tmp_path / package.replace(".", "_")
        folder.mkdir(exist_ok=True)
        path = folder / f"{name}.py"
        path.write_text(textwrap.dedent(source))
        if str(folder) not in pkg.__path__:
            pkg.__path__.append(str(folder))
        added.append((pkg, str(folder), f"{package}.{name}"))
        return path

    yield plug
    from seanv_analysis.io import formats
    from seanv_analysis.plots import FIGURES
    from seanv_analysis.stages import catalogue

    for pkg, folder, module in added:
        if folder in pkg.__path__:
            pkg.__path__.remove(folder)
        sys.modules.pop(module, None)
    FIGURES.pop("toybar", None)
    for suffix in [s for s, f in formats.FORMATS.items() if f.name == "tsv"]:
        del formats.FORMATS[suffix]
    catalogue.refresh()


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    from conftest import write_synthetic_dataset

    return write_synthetic_dataset(tmp_path_factory.mktemp("recipes") / "data", n_flow=4)


def test_a_stage_is_one_file(plugged, data, tmp_path):
    """Its module on the stages' path: pipelines, --list-stages, the runner
    (its folder, its result in result.json, the record by name), the report
    (its section) and the figures (a toy figure of its result) take it."""
    from seanv_analysis.batch import load_pipeline, run_pipeline
    from seanv_analysis.plots import load_figure_modules
    from seanv_analysis.stages import catalogue, describe_stages, figures_reading

    plugged("seanv_analysis.stages", "toy", TOY_STAGE)
    plugged("seanv_analysis.plots", "toybar", TOY_FIGURE)
    catalogue.refresh()
    load_figure_modules()
    assert list(catalogue.STAGES)[-3:] == ["toy", "figures", "report"]
    assert "toy: the flow-step runs counted" in describe_stages()
    assert figures_reading("toy") == ["toybar"]
    pipe = load_pipeline({"pipeline": {"name": "toy"}, "stages": [
        {"name": "ingest"}, {"name": "toy", "scale": 2}, {"name": "figures"}, {"name": "report"}]})
    res = run_pipeline(pipe, data, out_dir=tmp_path / "out", workers=1, quiet=True)
    assert res.success, res.summary_text()
    assert res["toy_count"].n_runs == 8 and res.toy_count.n_runs == 8
    out = tmp_path / "out"
    assert json.loads((out / "toy" / "toy.json").read_text()) == {"n_runs": 8}
    assert json.loads((out / "result.json").read_text())["toy_count"] == {"n_runs": 8}
    assert (out / "figures" / "toybar.png").is_file()
    html = (out / "report.html").read_text()
    assert "id='toy'" in html and "<p>8 flow steps</p>" in html and "Toy: the count as a bar" in html


def test_a_figure_is_one_file(plugged, tmp_path):
    from seanv_analysis.plots import FIGURES, load_figure_modules

    plugged("seanv_analysis.plots", "toybar", TOY_FIGURE)
    load_figure_modules()
    fig = FIGURES["toybar"]
    paths = fig.draw({"toy_count": type("C", (), {"n_runs": 3})()}, tmp_path, formats=["png"])
    assert [p.name for p in paths] == ["toybar.png"] and paths[0].stat().st_size > 0
    assert list(FIGURES)[-1] == "toybar"


def test_a_format_is_one_file(plugged, tmp_path, make_run):
    """Tab-separated tables read beside the contract's CSV and Parquet."""
    import pandas as pd

    from seanv_analysis.io import read_run
    from seanv_analysis.io.formats import load_format_modules, table_formats

    run_dir = make_run(tmp_path, duration_s=0.3)
    before = read_run(run_dir)
    enc = run_dir / "encoder.csv"
    pd.read_csv(enc).to_csv(run_dir / "encoder.tsv", sep="\t", index=False, float_format="%.17g")
    enc.unlink()
    plugged("seanv_analysis.io", "format_tsv", TOY_FORMAT)
    load_format_modules()
    assert [f.name for f in table_formats()] == ["csv", "parquet", "tsv"]
    after = read_run(run_dir)
    np.testing.assert_allclose(after.tables["encoder"]["position_mm"],
                               before.tables["encoder"]["position_mm"], rtol=1e-12)


def test_a_term_variable_is_one_call(monkeypatch):
    """A derived variable: the grammar, both evaluators and discover's library
    take it; the simulator's kernel runs it without being compiled again."""
    from seanv_analysis.discover.terms import library
    from seanv_analysis.models import expr

    monkeypatch.setattr(expr, "DERIVED", dict(expr.DERIVED))
    monkeypatch.setattr(expr, "VARIABLE_UNITS", dict(expr.VARIABLE_UNITS))
    expr.define_variable("p2", "p1 - dp", "MPa, the side's downstream pressure", search=True)
    prog = expr.compile_expr("0.05*p2**2")
    values = {"p1": np.array([3.3, 2.0]), "dp": np.array([1.0, 0.5])}
    np.testing.assert_allclose(expr.evaluate(prog, values), 0.05 * (values["p1"] - values["dp"]) ** 2)
    scalar = {k: float(v[0]) for k, v in values.items()}
    full = {name: scalar.get(name, 0.0) for name in expr.VARIABLES}
    assert expr.evaluate_scalar(prog, full) == pytest.approx(0.05 * 2.3 ** 2)
    rng = np.random.default_rng(0)
    lib = library({"dp": rng.uniform(0.5, 3.0, 20), "p1": rng.uniform(2.5, 3.5, 20),
                   "dtheta": np.ones(20),
                   "q": np.ones(20), "load": np.ones(20), "run": np.arange(20.0),
                   "approach": np.ones(20), "theta": np.ones(20)})
    assert "p1 - dp" in lib and "(p1 - dp)**2" in lib   # searched, written out
    with pytest.raises(ValueError, match="unknown name 'p3'; expected one of .*p2"):
        expr.compile_expr("p3")
    with pytest.raises(ValueError, match="expected a new identifier"):
        expr.define_variable("dp", "p1", "MPa")


def test_a_term_variable_runs_in_the_simulator(monkeypatch):
    """The kernel evaluates a term written with the derived variable as the
    same term written out (it is expanded before the kernel sees it)."""
    from seanv_analysis.models import expr
    from seanv_analysis.sim.run import simulate_flow_step

    monkeypatch.setattr(expr, "DERIVED", dict(expr.DERIVED))
    monkeypatch.setattr(expr, "VARIABLE_UNITS", dict(expr.VARIABLE_UNITS))
    expr.define_variable("p2", "p1 - dp", "MPa, the side's downstream pressure")
    assert expr.compile_expr("0.05*p2") == expr.compile_expr("0.05*(p1 - dp)")
    runs = [simulate_flow_step(side="supply", cam_deg=0.0, load_mpag=0.35, seed=1,
                               effects=[f"term:side=supply,mode=mul,expr={e}"])[0]
            for e in ("0.05*p2", "0.05*(p1 - dp)", "0")]
    pos = [r.tables["encoder"]["position_mm"].to_numpy() for r in runs]
    np.testing.assert_array_equal(pos[0], pos[1])
    assert not np.array_equal(pos[0], pos[2])       # the term acts


def test_stage_roles_are_declared_once():
    """What the batch runner treats apart (the stage that reads the runs, the
    one drawing figures, the report) is each a stage's ``ROLE``, not a name
    the runner knows; a role no runner knows, or a role two stages claim, is
    refused when the catalogue is checked."""
    import types

    from seanv_analysis.stages.catalogue import ROLES, STAGES, check_catalogue, has_role

    assert sorted(m.ROLE for m in STAGES.values() if hasattr(m, "ROLE")) == \
        sorted(ROLES)
    assert has_role("ingest", "reads_runs") and not has_role("flowfit", "reads_runs")

    def twin_of(name, **changes):
        mod = types.ModuleType(f"toy_{name}")
        mod.__dict__.update({k: getattr(STAGES[name], k) for k in dir(STAGES[name])
                             if k.isupper() or k in ("check_option", "run", "write")})
        mod.__dict__.update(changes)
        return mod

    bad = dict(STAGES, toy=twin_of("figures", NAME="toy", ORDER=91, ROLE="sings"))
    with pytest.raises(TypeError, match="ROLE 'sings' is none of"):
        check_catalogue(bad)
    twice = dict(STAGES, toy=twin_of("figures", NAME="toy", ORDER=91))
    with pytest.raises(TypeError, match="ROLE 'draws_figures' is also stage"):
        check_catalogue(twice)
