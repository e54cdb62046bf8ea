"""Issue 35: figures off the critical path.

Each figure is a task on the run's executor (worker processes, Dask) and
gives the same bytes as drawn in this process; long time traces are
decimated to the pixel columns they fill, min and max per column, so every
peak stays; a figure that cannot be written on a worker still ends the
command with exit 2 naming the file.
"""
from __future__ import annotations

import errno
import os
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from click.testing import CliRunner

from seanv_analysis.plots._style import TRACE_PIXELS, trace


def test_trace_keeps_every_peak_and_is_bounded_by_the_pixels():
    t = np.arange(200_000) / 1000.0                       # 200 s at 1 kHz
    y = np.sin(2 * np.pi * 0.05 * t)
    y[123_457] = 7.5                                      # a one-sample spike
    y[150_001] = -3.25                                    # and a dip
    y[90_000:90_020] = np.nan                             # a gap
    td, yd = trace(t, y, pixels=1000)
    assert td.size <= 4 * 1000 + 1 and td.size < t.size / 40
    assert np.all(np.diff(td) > 0)                        # in time order, no repeats
    assert td[0] == 0.0 and td[-1] == t[-1]
    assert np.nanmax(yd) == 7.5 and np.nanmin(yd) == -3.25
    assert td[np.nanargmax(yd)] == pytest.approx(123.457)
    assert np.isnan(yd).sum() == 1 and td[np.isnan(yd)][0] == pytest.approx(90.0)   # gap kept
    # per pixel column the drawn range is the full trace's: the envelope is exact
    col = np.minimum((t / t[-1] * 1000).astype(int), 999)
    cold = np.minimum((td / t[-1] * 1000).astype(int), 999)
    for c in (0, 123, 617, 999):
        full, kept = y[col == c], yd[cold == c]
        assert np.nanmax(full) == np.nanmax(kept) and np.nanmin(full) == np.nanmin(kept)


def test_a_short_trace_is_drawn_whole():
    t = np.linspace(0.0, 1.0, 4 * TRACE_PIXELS)
    td, yd = trace(t, t ** 2)
    np.testing.assert_array_equal(td, t)
    np.testing.assert_array_equal(yd, t ** 2)


@pytest.fixture(scope="module")
def position_ctx(tmp_path_factory):
    """Two synthetic position-control runs read and summarised (ingest)."""
    from conftest import write_synthetic_dataset

    from seanv_analysis.stages import run_stages

    root = write_synthetic_dataset(tmp_path_factory.mktemp("par") / "data", n_flow=0,
                                   n_position=2, duration_s=1.0)
    return run_stages(root, ["ingest"])


def _draw(ctx, folder: Path, map_tasks):
    from seanv_analysis.stages.figures import draw_figures

    ctx.map_tasks = map_tasks
    return draw_figures(ctx, ["fig6", "fig6_runs"], folder, formats=("png", "svg"),
                        per_run_folders=False)


def test_figures_drawn_on_worker_processes_are_the_same_bytes(position_ctx, tmp_path):
    """Fig. 6 per run and the runs side by side, drawn here and as tasks of
    a 2-process pool: the same files, byte for byte, listed in the same order."""
    from seanv_analysis.batch.executor import Executor
    from seanv_analysis.stages import serial_tasks

    here = _draw(position_ctx, tmp_path / "here", serial_tasks)
    with Executor("process", workers=2) as ex:
        pooled = _draw(position_ctx, tmp_path / "pool", ex.tasks)
    assert not here.problems and not pooled.problems
    assert list(here.paths) == list(pooled.paths) == ["fig6", "fig6_runs"]
    assert len(here.paths["fig6"]) == 4       # 2 runs x (png, svg)
    for name in here.paths:
        assert [p.name for p in here.paths[name]] == [p.name for p in pooled.paths[name]]
        for a, b in zip(here.paths[name], pooled.paths[name]):
            assert a.read_bytes() == b.read_bytes(), a.name


def test_a_figure_that_fails_on_a_worker_is_a_note_and_the_others_are_drawn(position_ctx,
                                                                            tmp_path):
    """A per-run figure whose run cannot be read is one line naming the run;
    the other figures are drawn."""
    import shutil

    from seanv_analysis.batch.executor import Executor

    bad = sorted(position_ctx.run_dirs)[0]
    position_ctx.result_named("position_runs")   # read once, as a run's ingest has them
    ctx = SimpleNamespace(**{k: getattr(position_ctx, k) for k in ("rig", "log", "result",
                                                                     "result_named",
                                                                     "map_runs")})
    moved = tmp_path / "moved"
    shutil.move(str(bad), moved)
    try:
        with Executor("process", workers=2) as ex:
            res = _draw(ctx, tmp_path / "out", ex.tasks)
    finally:
        shutil.move(str(moved), bad)
    assert len(res.problems) == 1 and res.problems[0].startswith(f"fig6: {bad}")
    assert len(res.paths["fig6"]) == 2 and len(res.paths["fig6_runs"]) == 2


def test_a_full_disk_on_a_figure_worker_ends_the_command_with_exit_2(make_dataset, tmp_path,
                                                                     monkeypatch):
    """`tracking` draws its figures on worker processes: a figure that cannot
    be written there (disk full) is exit 2, one line naming the file, and the
    output folder is not swapped in (nothing of the command in it)."""
    from matplotlib.figure import Figure

    from seanv_analysis.cli import cli

    data = make_dataset(tmp_path / "data", n_flow=0, n_position=2, duration_s=1.0)

    def full(self, fname, *args, **kwargs):
        with open(fname, "wb") as fh:
            fh.write(b"x")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(Figure, "savefig", full)     # before the pool forks: its workers too
    out = tmp_path / "out"
    res = CliRunner().invoke(cli, ["tracking", str(data), "--out", str(out), "-q",
                                   "--shift", "0.1"])
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in res.output, res.output
    assert "No space left on device" in lines[0] and ".png" in lines[0], lines[0]
    assert not [p for p in out.rglob("*") if p.suffix in (".png", ".svg", ".json")]


def test_a_lone_figure_is_split_by_format_on_idle_workers(position_ctx, tmp_path):
    """One data-set figure and two workers: its PNG and its SVG are two tasks
    (``_split_formats``), each laid out on its own worker: the same bytes
    as drawn in one task here, listed in the formats' order, and its key
    remembered (a second draw into the folder reuses the files)."""
    from seanv_analysis.batch.executor import Executor
    from seanv_analysis.stages import serial_tasks
    from seanv_analysis.stages.figures import _split_formats, draw_figures

    jobs = [("dataset", "fig6_runs", {}, "f")]
    assert _split_formats(jobs, ("png", "svg"), 2) == [(*jobs[0], ("png",)), (*jobs[0], ("svg",))]
    assert _split_formats(jobs * 2, ("png", "svg"), 2) == [(*j, ("png", "svg")) for j in jobs * 2]
    assert _split_formats(jobs, ("svg",), 2) == [(*jobs[0], ("svg",))]
    run_job = [("run", "fig6", "run-folder", "f")]
    assert _split_formats(run_job, ("png", "svg"), 2) == [(*run_job[0], ("png", "svg"))]

    def draw(folder, map_tasks, slots):
        position_ctx.map_tasks, position_ctx.task_slots = map_tasks, slots
        try:
            return draw_figures(position_ctx, ["fig6_runs"], folder, formats=("png", "svg"),
                                per_run_folders=False)
        finally:
            position_ctx.map_tasks, position_ctx.task_slots = serial_tasks, 1

    here = draw(tmp_path / "here", serial_tasks, 1)
    with Executor("process", workers=2) as ex:
        split = draw(tmp_path / "split", ex.tasks, 2)
        again = draw(tmp_path / "split", ex.tasks, 2)
    assert not here.problems and not split.problems
    assert [p.name for p in split.paths["fig6_runs"]] == ["fig6.png", "fig6.svg"]
    for a, b in zip(here.paths["fig6_runs"], split.paths["fig6_runs"], strict=True):
        assert a.read_bytes() == b.read_bytes(), a.name
    assert again.paths == split.paths
    assert {p: p.stat().st_mtime_ns for p in again.paths["fig6_runs"]} == \
        {p: p.stat().st_mtime_ns for p in split.paths["fig6_runs"]}


def test_result_modules_define_their_results():
    """Each stage result's ``module`` (what the figure workers import while
    the analysis runs) defines the result's type; a pipeline's are those of
    the results its figures read, in stage order, each once (not identify's,
    which no figure reads; none without a figures stage)."""
    import importlib

    from seanv_analysis.stages import STAGES
    from seanv_analysis.stages.catalogue import task_modules
    from seanv_analysis.stages.figures import figure_input_modules
    from seanv_analysis.stages.pipeline import load_pipeline

    named = [(s, r) for s, m in STAGES.items() for r in getattr(m, "RESULTS", ()) if r.module]
    assert {r.name for _, r in named} >= {"flowfit", "tracking", "validation", "discovery",
                                          "identify"}
    for _, r in named:
        assert hasattr(importlib.import_module(r.module), r.type), (r.name, r.module)
    assert figure_input_modules(load_pipeline("paper")) == (
        "seanv_analysis.fit.flowfit", "seanv_analysis.analysis.tracking",
        "seanv_analysis.analysis.validate", "seanv_analysis.discover.result")
    assert figure_input_modules(load_pipeline({"stages": [
        {"name": "ingest"}, {"name": "flowfit"}, {"name": "identify"},
        {"name": "figures", "figs": [4]}]})) == ("seanv_analysis.fit.flowfit",)
    assert figure_input_modules(load_pipeline({"stages": [{"name": "ingest"},
                                                          {"name": "flowfit"}]})) == ()
    # identify's tasks (its servo and flow fits) run on the workers too: they
    # import its module while they wait, only where a stage sends them
    for m in ("identify", "discover"):
        assert "seanv_analysis.identify.engine" in getattr(STAGES[m], "TASK_MODULES", ())
    assert task_modules(load_pipeline("paper")) == ("seanv_analysis.identify.engine",)
    assert task_modules(load_pipeline({"stages": [{"name": "ingest"}, {"name": "flowfit"},
                                                  {"name": "figures"}]})) == ()


def test_a_flow_fit_is_read_without_scipy(tmp_path):
    """A figure worker sent a FlowFit unpickles it: that imports
    ``seanv_analysis.fit`` and must not import scipy.optimize with it (1.1 s
    of a lone Fig. 4's task): the fit functions import it when they fit."""
    import pickle

    from conftest import write_synthetic_dataset
    from fresh_process import modules_after

    from seanv_analysis.stages import run_stages

    root = write_synthetic_dataset(tmp_path / "data", n_flow=8, n_position=0)
    fit = run_stages(root, ["ingest", "flowfit"], options={"flowfit": {"n_boot": 0}}
                     ).result("flowfit")
    assert type(fit).__name__ == "FlowFit"
    (tmp_path / "fit.pkl").write_bytes(pickle.dumps(fit))
    code = f"import pickle\nfit = pickle.loads(open({str(tmp_path / 'fit.pkl')!r}, 'rb').read())"
    assert modules_after(code, ["seanv_analysis.fit", "scipy.optimize"]) == ["seanv_analysis.fit"]


def test_a_warmed_worker_draws_fig6_without_importing_scipy(position_ctx, tmp_path):
    """A figure worker warmed for ``tracking``'s figures (what its worker
    processes run while the analysis goes on) has imported what Fig. 6
    imports when it first draws (the load levels' running median,
    ``scipy.ndimage``: 0.3-0.5 s of the first Fig. 6 a worker drew): drawing
    it then imports no scipy module (without the figures' ``imports`` in
    its warm-up, the figure imported scipy.ndimage)."""
    import pickle

    from fresh_process import last_literal

    from seanv_analysis.cli._common import command_pipeline
    from seanv_analysis.stages.figures import figure_imports, figure_input_modules

    pipe = command_pipeline("tracking", [{"name": "tracking"}], ingest={"derive": True})
    assert figure_imports(pipe) == ("seanv_analysis.analysis.tracking", "scipy.ndimage")
    run = next(r for r in position_ctx.result_named("position_runs"))
    (tmp_path / "run.pkl").write_bytes(pickle.dumps(run))

    warm = figure_input_modules(pipe) + figure_imports(pipe)
    code = (f"import pickle, sys\n"
            f"from seanv_analysis.stages.figures import warm_figure_worker\n"
            f"warm_figure_worker({warm!r})\n"
            f"run = pickle.loads(open({str(tmp_path / 'run.pkl')!r}, 'rb').read())\n"
            f"before = set(sys.modules)\n"
            f"from seanv_analysis.plots import FIGURES\n"
            f"FIGURES['fig6'].draw_run(run, {str(tmp_path / 'f')!r}, formats=('png',), "
            f"rig=None)\n"
            f"print(sorted(m for m in set(sys.modules) - before if m.startswith('scipy')))")
    assert last_literal(code) == []


def test_a_figure_declares_its_first_draw_imports_as_module_names():
    """``Figure.imports``: module names (a single one as a tuple of one);
    a pipeline's are its selected figures', each once; none without figures."""
    from seanv_analysis.plots import FIGURES, Figure
    from seanv_analysis.stages.figures import figure_imports
    from seanv_analysis.stages.pipeline import load_pipeline

    def draw(results, folder, *, formats):
        return []

    assert Figure(name="x", title="x", needs=("flowfit",), draw=draw,
                  imports="scipy.ndimage").imports == ("scipy.ndimage",)
    with pytest.raises(ValueError, match="imports"):
        Figure(name="x", title="x", needs=("flowfit",), draw=draw, imports=("", 3))
    assert FIGURES["validate_fit"].imports == FIGURES["fig6"].imports
    assert figure_imports(load_pipeline("paper")) == ("seanv_analysis.analysis.tracking",
                                                      "scipy.ndimage")
    assert figure_imports(load_pipeline("flowfit")) == ()
    assert figure_imports(load_pipeline({"stages": [{"name": "ingest"},
                                                    {"name": "flowfit"}]})) == ()


def test_a_figure_drawn_in_parts_is_a_task_per_part_and_the_same_files(tmp_path):
    """Fig. 7 (the data set's, then one per run) and validate's figure (an
    overlay per run, then the fit % chart) declare independent parts
    (``Figure.parts``): each part is a task of its own, side by side on the
    workers (issue 35: validate's three figures were one task, laid out
    twice, once per format), and the files are those the figure writes
    whole, byte for byte, in the same order."""
    from conftest import write_synthetic_dataset

    from seanv_analysis.plots import FIGURES
    from seanv_analysis.stages import run_stages, serial_tasks
    from seanv_analysis.stages.figures import draw_figures, results_for_figures

    root = write_synthetic_dataset(tmp_path / "data", n_flow=0, n_position=2, duration_s=1.0)
    ctx = run_stages(root, ["ingest", "tracking", "validate"],
                     options={"tracking": {"shift_s": 0.1}})
    jobs = []

    def recording(func, items, **kwargs):
        jobs.extend((kind, name, what[1]) for kind, name, what, *_ in items)
        return serial_tasks(func, items, **kwargs)

    ctx.map_tasks, ctx.task_slots = recording, 2
    res = draw_figures(ctx, ["fig7", "validate_fit"], tmp_path / "parts", formats=("png",))
    n_track, n_val = len(ctx.result("tracking").runs), len(ctx.result_named("validation").runs)
    assert n_track >= 1 and n_val == 2 and not res.problems
    assert jobs == ([("part", "fig7", "dataset")] + [("part", "fig7", i) for i in range(n_track)]
                    + [("part", "validate_fit", i) for i in range(n_val)]
                    + [("part", "validate_fit", "summary")])
    results = results_for_figures(ctx)
    for name in ("fig7", "validate_fit"):
        whole = FIGURES[name].draw(results, tmp_path / "whole", formats=("png",))
        assert [p.name for p in res.paths[name]] == [p.name for p in whole]
        for a, b in zip(res.paths[name], whole, strict=True):
            assert a.read_bytes() == b.read_bytes(), a.name

    # started ahead, its first part drawn there and the others not begun
    # when the figures stage came (run paper: validate's figure, drawn ahead
    # during discover, was drawn again whole): the part drawn is taken, the
    # two others are drawn here, and the files are those of the whole figure
    from concurrent.futures import Future

    from seanv_analysis.batch.executor import Started
    from seanv_analysis.stages.figures import _jobs_of, draw_figure_task, figure_key

    folder = tmp_path / "ahead"
    inputs = {"validation": results["validation"]}
    tasks = [(*job, ("png",)) for job in _jobs_of(FIGURES["validate_fit"], inputs, folder)]
    futures = [Future() for _ in tasks]
    futures[0].set_result((True, draw_figure_task(tasks[0], formats=("png",), rig=ctx.rig)))
    for fut in futures[1:]:
        fut.cancel()
    key = figure_key("validate_fit", inputs, ("png",), ctx.rig)
    ctx.ahead = {"figures": {"validate_fit": (key, str(folder), tasks, Started(futures))}}
    jobs.clear()
    res = draw_figures(ctx, ["validate_fit"], folder, formats=("png",))
    assert jobs == [("part", "validate_fit", 1), ("part", "validate_fit", "summary")]
    assert [p.name for p in res.paths["validate_fit"]] == [p.name for p in whole]  # (drawn above)
    for a, b in zip(res.paths["validate_fit"], whole, strict=True):
        assert a.read_bytes() == b.read_bytes(), a.name


def _sleep(seconds: float) -> float:
    import time

    time.sleep(seconds)
    return seconds


def test_figures_started_ahead_are_taken_redrawn_or_drawn_here(position_ctx, tmp_path):
    """A figure started ahead on the background worker (``start_ahead``,
    while the analysis runs) is taken when its inputs are unchanged, drawn
    again when they changed since, and drawn on the pool when it had not
    begun; the files are the bytes drawn here, and the background worker
    runs at a lower CPU priority."""
    from seanv_analysis.batch.executor import BACKGROUND_NICE, Executor
    from seanv_analysis.stages import serial_tasks
    from seanv_analysis.stages.figures import draw_figures, start_ahead

    opts = {"figs": ["fig6_runs"], "formats": ["png"], "layout": "flat"}
    ctx = position_ctx
    here = draw_figures(ctx, ["fig6_runs"], tmp_path / "here", formats=("png",),
                        per_run_folders=False).paths["fig6_runs"]
    drawn: list[str] = []

    def recording(func, items, **kwargs):
        drawn.extend(name for _, name, *_ in items)
        return serial_tasks(func, items, **kwargs)

    def draw(folder: Path, *, stale: bool = False, busy: bool = False):
        ctx.out_dir = folder
        ctx.start_tasks = ex.start
        if busy:   # the background worker is busy: the figure has not begun when drawn
            ex.start(_sleep, [3.0])
        start_ahead(ctx, opts)
        entry = ctx.ahead["figures"]["fig6_runs"]
        if not busy:   # the analysis took longer than the figure
            entry[3].results()
        if stale:  # its inputs changed since it was started
            ctx.ahead["figures"]["fig6_runs"] = ("another key", *entry[1:])
        ctx.map_tasks, ctx.task_slots = recording, 2
        try:
            return draw_figures(ctx, ["fig6_runs"], folder, formats=("png",),
                                per_run_folders=False)
        finally:
            ctx.map_tasks, ctx.task_slots, ctx.start_tasks = serial_tasks, 1, None
            ctx.out_dir = None

    with Executor("process", workers=2) as ex:
        assert ex.can_start
        nice = ex.start(os.nice, [0]).results()
        taken = draw(tmp_path / "taken")
        assert drawn == []
        redrawn = draw(tmp_path / "stale", stale=True)
        assert drawn == ["fig6_runs"]
        busy = draw(tmp_path / "busy", busy=True)
        assert drawn == ["fig6_runs", "fig6_runs"]
    assert nice == [(True, os.nice(0) + BACKGROUND_NICE)]
    assert not Executor("serial").can_start
    for res in (taken, redrawn, busy):
        assert not res.problems and [p.name for p in res.paths["fig6_runs"]] == ["fig6.png"]
        assert res.paths["fig6_runs"][0].read_bytes() == here[0].read_bytes()


@pytest.mark.parametrize("stage", ["flowfit", "tracking", "validate"])
def test_a_stage_imports_what_it_declares_to_import_beside_ingest(tmp_path, stage):
    """A stage's ``IMPORTS`` (what a command's process imports on a thread
    while its workers read the runs: ``stage_imports``) are what the stage
    imports when it runs and writes, and ingest had not imported: a stale
    entry would be imported for nothing, a missing one paid after ingest.
    In a fresh interpreter."""
    import json

    import pandas as pd
    from conftest import write_synthetic_dataset
    from fresh_process import last_literal

    from seanv_analysis.stages import STAGES
    from seanv_analysis.stages.catalogue import stage_imports
    from seanv_analysis.stages.pipeline import load_pipeline

    root = write_synthetic_dataset(tmp_path / "data", n_flow=8, n_position=1, duration_s=2.0)
    run = root / "pos000"                  # a load step (validate finds its onset)
    p = pd.read_csv(run / "pressure.csv")
    p.loc[p["t_s"] >= 1.0, "p_load_mpag"] += 0.1
    p.to_csv(run / "pressure.csv", index=False)
    meta = json.loads((run / "run.json").read_text())
    (run / "run.json").write_text(json.dumps({**meta, "load_mpag": None}))
    mods = STAGES[stage].IMPORTS
    assert mods and set(mods) <= set(stage_imports(load_pipeline("paper")))
    code = f"""
import sys
from seanv_analysis.stages import STAGES
from seanv_analysis.stages.execute import run_stages
ctx = run_stages({str(root)!r}, ["ingest"])
after_ingest = [m for m in {mods!r} if m in sys.modules]
ctx = run_stages({str(root)!r}, ["ingest", {stage!r}], options={{"flowfit": {{"n_boot": 0}}}}
                 if {stage!r} == "flowfit" else None)
STAGES[{stage!r}].write(ctx.result({stage!r}), __import__("pathlib").Path({str(tmp_path)!r}))
print((after_ingest, [m for m in {mods!r} if m in sys.modules]))
"""
    after_ingest, after_stage = last_literal(code)
    assert after_ingest == []
    assert after_stage == list(mods)
