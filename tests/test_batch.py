"""Batch runner: pipelines, executors (serial / process pool / dask), cache, resume."""
from __future__ import annotations

import json
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pandas as pd
import pytest
from pandas.testing import assert_frame_equal

from seanv_analysis.batch import STAGE_NAMES, load_pipeline, parse_pipeline, run_pipeline, shipped_pipelines
from seanv_analysis.batch.cache import RunCache, run_key
from seanv_analysis.batch.executor import make_executor
from seanv_analysis.errors import ConfigError, DataError

INGEST_ONLY = {"pipeline": {"name": "ingest-only"}, "stages": [{"name": "ingest"}]}
FIT = {"pipeline": {"name": "fit"}, "stages": [{"name": "ingest"}, {"name": "flowfit"}]}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """14 flow-step runs (supply/drain) and one bad run (no encoder file)."""
    from conftest import write_synthetic_dataset, write_synthetic_run

    root = tmp_path_factory.mktemp("batch") / "data"
    write_synthetic_dataset(root, n_flow=14)
    write_synthetic_run(root, "flow_step", run_id="broken", tables={"encoder": None},
                        started_at="2026-03-02T11:00:00Z", duration_s=0.5)
    return root


def _summary(res) -> pd.DataFrame:
    return res.summary.drop(columns=["flow_model"]).reset_index(drop=True)


# pipelines -----------------------------------------------------------------

def test_shipped_pipelines_load():
    shipped = shipped_pipelines()
    assert {"paper", "flowfit", "tracking"} <= set(shipped)
    paper = load_pipeline("paper")
    assert paper.stage_names == list(STAGE_NAMES)
    assert paper.stage("discover").options["holdout"] == "chrono"
    assert load_pipeline(shipped["flowfit"]).stage("figures").options["figs"] == [4]


@pytest.mark.parametrize("doc, match", [
    ({"stages": [{"name": "ingest"}, {"name": "fitflow"}]}, r"unknown stage 'fitflow'"),
    ({"stages": [{"name": "ingest", "methd": "peak"}]}, r"stage 'ingest' has unknown option 'methd'"),
    ({"stages": [{"name": "ingest", "method": "mean"}]}, r"option 'method' = 'mean'"),
    ({"stages": [{"name": "flowfit"}, {"name": "ingest"}]}, r"stages out of order"),
    ({"stages": [{"name": "ingest"}, {"name": "ingest"}]}, r"listed twice"),
    ({"stages": []}, r"no \[\[stages\]\]"),
    ({"stages": [{"name": "tracking", "q_range": [5, 1]}]}, r"option 'q_range'"),
    ({"stages": [{"name": "figures", "figs": [5]}]}, r"option 'figs'"),
])
def test_bad_pipeline_is_config_error(doc, match):
    with pytest.raises(ConfigError, match=match):
        parse_pipeline(doc)


def test_pipeline_file_errors(tmp_path):
    with pytest.raises(ConfigError, match=r"neither a file nor a shipped pipeline"):
        load_pipeline("no-such-pipeline")
    bad = tmp_path / "bad.toml"
    bad.write_text("[pipeline\nname=")
    with pytest.raises(ConfigError, match=r"not a valid TOML file"):
        load_pipeline(bad)


def test_out_dir_inside_data_refused(dataset):
    with pytest.raises(DataError, match=r"inside the data folder"):
        run_pipeline(INGEST_ONLY, dataset, out_dir=dataset / "out", workers=1, quiet=True)


# executors -------------------------------------------------------------------

def test_serial_process_dask_identical(dataset, tmp_path, dask_cluster):
    from dask.distributed import Client

    serial = run_pipeline(FIT, dataset, out_dir=tmp_path / "serial", workers=1, quiet=True)
    pool = run_pipeline(FIT, dataset, out_dir=tmp_path / "pool", workers=2, quiet=True)
    with Client(dask_cluster) as client:
        dask = run_pipeline(FIT, dataset, out_dir=tmp_path / "dask", client=client, quiet=True)
        assert client.status == "running"  # not closed by the runner
    assert serial.executor.startswith("serial")
    assert pool.executor.startswith("process pool (2")
    assert dask.executor.startswith("dask")
    for other in (pool, dask):
        assert_frame_equal(_summary(serial), _summary(other))
        assert [f.message for f in other.failed] == [f.message for f in serial.failed]
        assert other.stage_errors == serial.stage_errors
        if serial.flowfit is not None:
            assert other.flowfit.to_json_dict() == serial.flowfit.to_json_dict()
    assert serial.runs_read == 14
    assert serial.computed["ingest"] == 14 and dask.computed["ingest"] == 14


def _pid_or_fail(item: int) -> tuple[int, int]:
    import os

    if item % 7 == 3:
        raise ValueError(f"item {item} fails")
    return item, os.getpid()


def test_dask_tasks_go_in_chunks_each_item_its_own_outcome(dask_cluster):
    """A long list goes to a Dask cluster in chunks, as to the process pool
    (one task per item cost ingest of the paper's 242 runs 3.5-5.1 s against
    1.1-1.4 s on 2 local workers): fewer tasks than items, every item's
    outcome in the order of the items, a failing item's error its own."""
    from dask.distributed import Client

    from seanv_analysis.batch.executor import Executor

    items = list(range(100))
    with Client(dask_cluster) as client, Executor("dask", client=client) as ex:
        submitted, submit = [], client.submit

        def counted(*args, **kwargs):
            submitted.append(args[0])
            return submit(*args, **kwargs)

        client.submit = counted
        out = ex.map(_pid_or_fail, items, quiet=True)
    assert 1 < len(submitted) < len(items) / 4, len(submitted)
    assert [r.item for r in out] == items
    for r in out:
        if r.item % 7 == 3:
            assert not r.ok and f"item {r.item} fails" in r.error
        else:
            assert r.ok and r.value[0] == r.item
    assert len({r.value[1] for r in out if r.ok}) == 2      # both workers took chunks


def test_a_dask_cluster_runs_the_data_set_stages_parts_too(dataset, tmp_path, dask_cluster,
                                                          monkeypatch):
    """The tasks that run at once (``Context.task_slots``) on a Dask cluster
    are its worker threads, as the workers of a local pool: with more than
    one, identify's parts (geometry's flow fits, the servo, ...) are tasks
    there. The runner gave the cluster 0 slots, so they ran here one after
    another (``run paper``'s identify 12-14 s against 8-10 s locally)."""
    from dask.distributed import Client

    from seanv_analysis.batch.executor import make_executor
    from seanv_analysis.stages import flowfit
    from seanv_analysis.stages.base import tasks_beside

    seen = []
    fit = flowfit.run
    monkeypatch.setattr(flowfit, "run", lambda ctx, options: (
        seen.append((ctx.task_slots, tasks_beside(ctx) is ctx.map_tasks)), fit(ctx, options))[1])
    with Client(dask_cluster) as client:
        run_pipeline(FIT, dataset, out_dir=tmp_path / "dask", client=client, quiet=True)
    run_pipeline(FIT, dataset, out_dir=tmp_path / "one", workers=1, quiet=True)
    assert seen == [(2, True), (1, False)]
    with make_executor(workers=2) as ex:
        assert ex.slots == 2


def _pid_and_nice(_item) -> tuple[int, int]:
    import os

    return os.getpid(), os.nice(0)


def test_background_worker_beside_a_dask_client(dask_cluster):
    """With a Dask cluster the data-set stages run in this process, so work a
    later stage starts ahead (the figures) goes to a background worker here:
    a process of its own, spawned (not forked beside the client's threads),
    at a lower CPU priority; not with a serial executor."""
    import os

    from dask.distributed import Client

    from seanv_analysis.batch.executor import BACKGROUND_NICE, Executor, usable_cpus

    with Client(dask_cluster) as client, Executor("dask", client=client) as ex:
        assert ex.can_start == (usable_cpus() > 1)
        if not ex.can_start:
            pytest.skip("one processor: nothing runs beside this process")
        (ok, (pid, nice)), = ex.start(_pid_and_nice, [0]).results()
    assert ok and pid != os.getpid() and nice == os.nice(0) + BACKGROUND_NICE
    with make_executor(workers=1) as serial:
        assert not serial.can_start


def test_scheduler_address_connects_and_leaves_cluster_running(dataset, tmp_path, dask_cluster):
    res = run_pipeline(INGEST_ONLY, dataset, out_dir=tmp_path / "o", quiet=True,
                       scheduler=dask_cluster.scheduler_address)
    assert res.executor == f"dask.distributed ({dask_cluster.scheduler_address})"
    assert res.runs_read == 14
    assert dask_cluster.status.name == "running"


def test_scheduler_from_environment(dataset, tmp_path, dask_cluster, monkeypatch):
    monkeypatch.setenv("DASK_SCHEDULER_ADDRESS", dask_cluster.scheduler_address)
    with make_executor() as ex:
        assert ex.kind == "dask"
    with make_executor(workers=1) as ex:  # an explicit --workers wins
        assert ex.kind == "serial"


def test_bad_runs_listed_good_runs_processed(dataset, tmp_path):
    res = run_pipeline(INGEST_ONLY, dataset, out_dir=tmp_path / "o", workers=2, quiet=True)
    assert res.runs_found == 15 and res.runs_read == 14
    assert len(res.failed) == 1
    bad = res.failed[0]
    assert bad.stage == "ingest" and "broken" in bad.path
    assert "encoder" in bad.message and "\n" not in bad.message
    text = res.summary_text()
    assert "1 failed" in text and "[ingest]" in text and "encoder" in text
    assert not res.success
    doc = json.loads((tmp_path / "o" / "result.json").read_text())
    assert doc["failed"][0]["stage"] == "ingest"
    manifest = json.loads((tmp_path / "o" / "manifest.json").read_text())
    assert len(manifest["inputs"]) == 14 * 4  # run.json + 3 tables per good run


def test_task_exception_collected_not_raised():
    with make_executor(workers=1) as ex:
        out = ex.map(_maybe_fail, [1, 0, 2], quiet=True)
    assert [r.ok for r in out] == [True, False, True]
    assert out[1].error.startswith("ZeroDivisionError")
    with make_executor(workers=2) as ex:
        out2 = ex.map(_maybe_fail, [1, 0, 2], quiet=True)
    assert [r.value for r in out2] == [r.value for r in out]


def _maybe_fail(x):
    return 1 / x


def _imported(name):
    return name in sys.modules


def test_preloaded_modules_are_inherited_by_the_forked_workers(tmp_path, monkeypatch):
    """``Executor.preload`` imports the stages' task and figure-input modules
    here before the pool forks its workers, which then start with them
    (issue 35: each worker imported identify's, 0.7 s, while the main
    process fitted on the same two cores); a no-op once the workers run."""
    import uuid

    name = f"seanv_probe_{uuid.uuid4().hex}"
    (tmp_path / f"{name}.py").write_text("X = 1\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    with make_executor(workers=2) as ex:
        if ex.kind != "process" or ex._process_pool()._mp_context.get_start_method() != "fork":
            pytest.skip("workers are not forked here")
    with make_executor(workers=2) as ex:
        ex.preload([name])
        assert name in sys.modules
        assert [v for _, v in ex.tasks(_imported, [name, name])] == [True, True]
        later = f"{name}_late"
        (tmp_path / f"{later}.py").write_text("X = 2\n")
        ex.preload([later])      # the workers run: nothing imported
        assert later not in sys.modules
    sys.modules.pop(name, None)


def test_progress_off_when_quiet_or_ci(monkeypatch):
    """The batch's bars are the package's (:func:`seanv_analysis.log.progress`,
    the one place that decides): none when quiet, under CI or off a terminal."""
    import io

    from seanv_analysis import log
    from seanv_analysis.batch.executor import _bar

    class Tty(io.StringIO):
        def isatty(self):
            return True

    monkeypatch.setattr(log, "progress_enabled", lambda: True)
    bar = _bar(3, "runs", quiet=False)
    assert not isinstance(bar, log._NoBar)
    bar.close()
    assert isinstance(_bar(3, "runs", quiet=True), log._NoBar)
    monkeypatch.undo()
    monkeypatch.setattr("sys.stderr", Tty())
    monkeypatch.setenv("CI", "true")
    assert not log.progress_enabled()


def test_workers_must_be_positive():
    with pytest.raises(ConfigError, match=r"workers: 0"):
        make_executor(workers=0)


# cache ---------------------------------------------------------------------------

@pytest.fixture
def counted(monkeypatch):
    """Count derive.summarize_run calls (serial runs call it in this process)."""
    from seanv_analysis.signals import derive

    calls = []
    real = derive.summarize_run

    def counting(run, **kw):
        calls.append(run.meta.run_id)
        return real(run, **kw)

    monkeypatch.setattr(derive, "summarize_run", counting)
    return calls


def test_cached_rerun_does_no_per_run_work(dataset, tmp_path, counted, monkeypatch):
    out = tmp_path / "o"
    first = run_pipeline(INGEST_ONLY, dataset, out_dir=out, workers=1, quiet=True)
    assert len(counted) == 14
    # the second run reads no log: hashes come from the stat index
    from seanv_analysis.io import reader
    monkeypatch.setattr(reader, "_read_tables", _no_read)
    second = run_pipeline(INGEST_ONLY, dataset, out_dir=out, workers=1, quiet=True)
    assert len(counted) == 14
    assert second.computed["ingest"] == 0 and second.cached["ingest"] == 14
    assert_frame_equal(_summary(first), _summary(second))
    assert second.input_hashes == first.input_hashes  # provenance intact without reading
    manifest = json.loads((out / "manifest.json").read_text())
    assert len(manifest["inputs"]) == 14 * 4


def _no_read(*a, **k):
    raise AssertionError("a run was read although nothing changed")


def test_cache_invalidated_by_input_option_and_force(dataset, tmp_path, counted):
    import shutil

    data = tmp_path / "data"
    shutil.copytree(dataset, data)
    out = tmp_path / "o"
    run_pipeline(INGEST_ONLY, data, out_dir=out, workers=1, quiet=True)
    assert len(counted) == 14
    # one changed log file: only that run is recomputed
    enc = data / "z001-drain" / "encoder.csv"
    lines = enc.read_text().splitlines()
    t, x = lines[-1].split(",")
    lines[-1] = f"{t},{float(x) + 0.001:.3f}"
    enc.write_text("\n".join(lines) + "\n")
    res = run_pipeline(INGEST_ONLY, data, out_dir=out, workers=1, quiet=True)
    assert counted[14:] == ["z001-drain"] and res.computed["ingest"] == 1
    # a changed option: every run
    peak = {"pipeline": {"name": "p"}, "stages": [{"name": "ingest", "method": "peak"}]}
    res = run_pipeline(peak, data, out_dir=out, workers=1, quiet=True)
    assert res.computed["ingest"] == 14
    # a changed rig constant: every run
    from seanv_analysis.config import load_rig
    rig2 = load_rig(overrides={"analysis": {"leakage_flow_mm3_s": 51.0}})
    res = run_pipeline(peak, data, out_dir=out, workers=1, quiet=True, rig=rig2)
    assert res.computed["ingest"] == 14
    # --force: every run, results unchanged
    before = len(counted)
    res2 = run_pipeline(peak, data, out_dir=out, workers=1, quiet=True, rig=rig2, force=True)
    assert len(counted) - before == 14
    assert_frame_equal(_summary(res), _summary(res2))


def test_run_key_depends_on_everything():
    base = dict(stage="ingest", params={"method": "steady"}, rig={"a": 1}, version="1")
    k = run_key({"encoder.csv": "aa"}, **base)
    assert k == run_key({"encoder.csv": "aa"}, **base)
    assert k != run_key({"encoder.csv": "ab"}, **base)
    assert k != run_key({"encoder.csv": "aa"}, **{**base, "params": {}})  # removed parameter
    assert k != run_key({"encoder.csv": "aa"}, **{**base, "rig": {"a": 2}})
    assert k != run_key({"encoder.csv": "aa"}, **{**base, "version": "2"})


def test_run_key_default_tracks_the_code(monkeypatch):
    """Without an explicit version the key holds a hash of the package's
    sources, so an edited stage is recomputed even if the version is not bumped."""
    from seanv_analysis import __version__
    from seanv_analysis.batch import cache

    assert cache.code_version().startswith(__version__ + "+")
    args = ({"encoder.csv": "aa"},)
    kw = dict(stage="ingest", params={}, rig={})
    k = run_key(*args, **kw)
    assert k == run_key(*args, **kw, version=cache.code_version())
    monkeypatch.setattr(cache, "code_version", lambda: __version__ + "+edited")
    assert run_key(*args, **kw) != k


def test_resume_after_partial_cache(dataset, tmp_path, counted):
    """A run killed half-way leaves some entries, temp files and maybe a torn
    entry; the next run cleans up and computes only what is missing."""
    out = tmp_path / "o"
    clean = run_pipeline(INGEST_ONLY, dataset, out_dir=out, workers=1, quiet=True)
    cache = out / ".cache"
    entries = sorted((cache / "runs").glob("*.json"))
    assert len(entries) == 14
    (cache / "index.json").unlink()                       # index not saved yet
    for e in entries[:5]:
        e.unlink()                                        # never written
    entries[5].write_bytes(entries[5].read_bytes()[:10])  # torn (not via atomic write)
    (cache / "runs" / ".deadbeef.json.abc.tmp").write_bytes(b"partial")
    (out / ".summary.parquet.xyz.tmp").write_bytes(b"partial")
    n0 = len(counted)
    res = run_pipeline(INGEST_ONLY, dataset, out_dir=out, workers=1, quiet=True)
    assert len(counted) - n0 == 6
    assert res.computed["ingest"] == 6 and res.cached["ingest"] == 8
    assert not list((cache / "runs").glob(".*.tmp"))
    assert "resume" in res.stage_notes
    assert_frame_equal(_summary(clean), _summary(res))


SLOW_RUN = textwrap.dedent("""
    import sys, time
    from seanv_analysis.signals import derive
    real = derive.summarize_run
    def slow(run, **kw):
        time.sleep(0.3)
        return real(run, **kw)
    derive.summarize_run = slow
    from seanv_analysis.batch import run_pipeline
    run_pipeline({"pipeline": {"name": "x"}, "stages": [{"name": "ingest"}]}, sys.argv[1],
                 out_dir=sys.argv[2], workers=1, quiet=True)
""")


def test_resume_after_sigkill(dataset, tmp_path, counted):
    out = tmp_path / "o"
    proc = subprocess.Popen([sys.executable, "-c", SLOW_RUN, str(dataset), str(out)])
    entries = out / ".cache" / "runs"
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        if entries.is_dir() and len(list(entries.glob("*.json"))) >= 4:
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    done = len(list(entries.glob("*.json")))
    assert 4 <= done < 14, "the run finished before it could be killed"
    assert not (out / "summary.parquet").exists()
    res = run_pipeline(INGEST_ONLY, dataset, out_dir=out, workers=1, quiet=True)
    assert res.computed["ingest"] == 14 - done
    assert res.cached["ingest"] == done
    clean = run_pipeline(INGEST_ONLY, dataset, out_dir=tmp_path / "clean", workers=1, quiet=True)
    assert_frame_equal(_summary(clean), _summary(res))
    pd.read_parquet(out / "summary.parquet")  # whole and readable


def test_cache_index_survives_garbage(tmp_path):
    (tmp_path / "index.json").write_text("{not json")
    cache = RunCache(tmp_path)
    assert cache.known_hashes(tmp_path) is None


def test_demo_data_is_remade_when_the_simulator_changes(tmp_path, monkeypatch):
    """The demo's simulated data sets are keyed by the simulator's sources, so
    a changed plant or integrator never serves data of the old one."""
    from seanv_analysis import demo
    from seanv_analysis.batch import cache

    real = cache.simulator_version()
    assert real.startswith("0.") and "+sim" in real and real != cache.code_version()
    made = []

    def fake_simulate(scenario, folder, **kw):
        Path(folder).mkdir(parents=True)
        made.append(scenario)
        return Path(folder)

    monkeypatch.setattr("seanv_analysis.sim.simulate_scenario", fake_simulate)
    demo.demo_datasets(tmp_path)
    n = len(made)
    assert n >= 1
    demo.demo_datasets(tmp_path)
    assert len(made) == n                                  # cached
    monkeypatch.setattr(cache, "simulator_version", lambda: "0.0.0+simother")
    demo.demo_datasets(tmp_path)
    assert len(made) == 2 * n                              # re-simulated


