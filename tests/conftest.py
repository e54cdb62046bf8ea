"""Shared fixtures: small synthetic runs written through ``io.writer.write_run``.

Use the fixtures (``make_run``, ``make_dataset``, ``rig``) from any test:

    def test_something(tmp_path, make_run):
        run_dir = make_run(tmp_path, kind="flow_step", cam_deg=-5.0, side="supply")
        ...

``make_run(root, kind=..., **overrides)`` writes ``root/<run_id>/`` and returns
that folder. Overrides:

- run.json fields: ``run_id``, ``side``, ``cam_deg``, ``load_mpag``,
  ``started_at``, ``controller``, ``rig``; ``meta={...}`` merges any other
  fields (``DROP`` as a value removes a field, e.g. ``meta={"side": DROP}``);
- tables: ``tables={"servo": df}`` replaces a table, ``{"servo": None}``
  omits its file; ``fmt="parquet"`` writes Parquet;
- signal shape: ``duration_s``, ``seed``, ``flow_mm3_s``, rates
  (``encoder_rate_hz`` ...) and start instants (``servo_start_s`` ...),
  ``noise`` (False: exact, noise-free signals). See :func:`synthetic_tables`.

The signals are plausible, not simulated: a flow step holds the cam at the
servo neutral (-15 deg, both needles closed) for the first 20 % of the run,
then commands ``cam_deg``; the actuator moves at ``flow_mm3_s / 201.06 mm^2``
after a 50 ms dead time. Pressures are near the paper's (supply 3.3 MPaG,
head ~ 4 x load).
"""
from __future__ import annotations

from seanv_analysis.config import default_one_blas_thread

# one BLAS thread per test process, set before numpy loads, as the CLI does:
# two xdist workers on two cores with multi-threaded BLAS spin against each
# other (library calls the tests make directly are not inside the stages'
# own one_blas_thread)
default_one_blas_thread()

import math  # noqa: E402
import os  # noqa: E402
from contextlib import contextmanager  # noqa: E402
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest

from seanv_analysis.config import load_rig
from seanv_analysis.io.writer import write_run

DROP = object()  # marker: remove a run.json field
PISTON_AREA_MM2 = math.pi / 4 * 16.0 ** 2


def _times(start_s: float, duration_s: float, rate_hz: float) -> np.ndarray:
    n = int(math.floor((duration_s - start_s) * rate_hz + 1e-9)) + 1
    return start_s + np.arange(n) / rate_hz


def synthetic_tables(kind: str = "flow_step", *, duration_s: float = 1.0, seed: int = 0,
                     side: str = "supply", cam_deg: float = -8.0, load_mpag: float | None = 0.35,
                     flow_mm3_s: float | None = None, noise: bool = True,
                     encoder_rate_hz: float = 1000.0, pressure_rate_hz: float = 1000.0,
                     servo_rate_hz: float = 100.0, controller_rate_hz: float = 100.0,
                     encoder_start_s: float = 0.0, pressure_start_s: float = 0.0,
                     servo_start_s: float = 0.002, controller_start_s: float = 0.004,
                     ) -> dict[str, pd.DataFrame]:
    """Tables of one synthetic run (engineering units), seeded."""
    rng = np.random.default_rng(seed)
    load = 0.35 if load_mpag is None else load_mpag
    t_step = 0.2 * duration_s

    t_enc = _times(encoder_start_s, duration_s, encoder_rate_hz)
    t_p = _times(pressure_start_s, duration_s, pressure_rate_hz)
    t_sv = _times(servo_start_s, duration_s, servo_rate_hz)

    def n(size, sigma):
        return rng.normal(0.0, sigma, size) if noise else np.zeros(size)

    pressure = pd.DataFrame({
        "t_s": t_p,
        "p_supply_mpag": 3.3 + n(t_p.size, 0.005),
        "p_head_mpag": 4 * load + (0.3 if side == "supply" else 0.0) + n(t_p.size, 0.005),
        "p_load_mpag": load + n(t_p.size, 0.002),
    })

    if kind == "flow_step":
        q = flow_mm3_s if flow_mm3_s is not None else (2000.0 if side == "supply" else -2000.0)
        v = q / PISTON_AREA_MM2
        x0 = 10.0 if side == "supply" else 60.0
        x = x0 + v * np.clip(t_enc - t_step - 0.05, 0.0, None)
        cmd = np.where(t_sv < t_step, -15.0, cam_deg)
        fb = np.where(t_sv < t_step, -15.0,
                      cam_deg + (-15.0 - cam_deg) * np.exp(-(t_sv - t_step) / 0.06))
        tables = {
            "encoder": pd.DataFrame({"t_s": t_enc, "position_mm": np.round(x, 3)}),
            "pressure": pressure,
            "servo": pd.DataFrame({"t_s": t_sv, "cam_cmd_deg": cmd,
                                   "cam_deg": fb + n(t_sv.size, 0.02)}),
        }
        return tables
    if kind != "position_control":
        raise ValueError(f"kind: expected flow_step or position_control, got {kind!r}")
    t_c = _times(controller_start_s, duration_s, controller_rate_hz)
    x_ref = np.where(t_c < t_step, 10.0, 40.0)
    x = 10.0 + 30.0 * (1 - np.exp(-np.clip(t_enc - t_step, 0.0, None) / 0.3))
    x_at_c = np.interp(t_c, t_enc, x)
    q_ref = np.clip(480.0 * (x_ref - x_at_c), -6000.0, 6000.0)
    cmd = np.clip(-15.0 + q_ref / 600.0, -40.0, 10.0)
    cmd_sv = np.interp(t_sv, t_c, cmd)
    return {
        "encoder": pd.DataFrame({"t_s": t_enc, "position_mm": np.round(x, 3)}),
        "pressure": pressure,
        "servo": pd.DataFrame({"t_s": t_sv, "cam_cmd_deg": cmd_sv,
                               "cam_deg": cmd_sv + n(t_sv.size, 0.02)}),
        "controller": pd.DataFrame({"t_s": t_c, "x_ref_mm": x_ref, "q_ref_mm3_s": q_ref}),
    }


_META_KEYS = ("side", "cam_deg", "load_mpag")


def write_synthetic_run(root: str | Path, kind: str = "flow_step", *, run_id: str | None = None,
                        fmt: str = "csv", started_at: str = "2026-03-02T10:14:05Z",
                        meta: dict[str, Any] | None = None,
                        tables: dict[str, pd.DataFrame | None] | None = None,
                        controller: dict[str, Any] | None = None, rig: dict | None = None,
                        **params: Any) -> Path:
    """Write one valid synthetic run under ``root`` and return its folder."""
    side = params.get("side", "supply")
    cam = params.get("cam_deg", -8.0)
    load = params.get("load_mpag", 0.35)
    if run_id is None:
        run_id = (f"{side}-load{load}-cam{cam}" if kind == "flow_step" else "position") \
            + f"-s{params.get('seed', 0)}"
    data = synthetic_tables(kind, **params)
    for name, df in (tables or {}).items():
        if df is None:
            data.pop(name, None)
        else:
            data[name] = df
    doc: dict[str, Any] = {"schema": "seanv-run/1", "run_id": run_id, "kind": kind,
                           "started_at": started_at, "load_mpag": load}
    if kind == "flow_step":
        doc.update(side=side, cam_deg=cam)
    else:
        doc["controller"] = controller or {"kp": 480, "flow_model": True, "rate_hz": 100}
    if rig is not None:
        doc["rig"] = rig
    for key, value in (meta or {}).items():
        if value is DROP:
            doc.pop(key, None)
        else:
            doc[key] = value
    return write_run(Path(root) / run_id, doc, data, fmt=fmt)


def write_synthetic_dataset(root: str | Path, *, n_flow: int = 3, n_position: int = 0,
                            fmt: str = "csv", duration_s: float = 0.5, **params: Any) -> Path:
    """A small data set: ``n_flow`` flow-step runs (alternating supply/drain)
    and ``n_position`` position-control runs, one minute apart, written in
    reverse time order of their folder names so ordering is exercised."""
    root = Path(root)
    k = 0
    for i in range(n_flow):
        side = "supply" if i % 2 == 0 else "drain"
        cam = -8.0 + i if side == "supply" else -30.0 + i
        write_synthetic_run(root, "flow_step", run_id=f"z{n_flow - i:03d}-{side}", side=side,
                            cam_deg=cam, seed=i, fmt=fmt, duration_s=duration_s,
                            started_at=f"2026-03-02T10:{k:02d}:00Z", **params)
        k += 1
    for i in range(n_position):
        write_synthetic_run(root, "position_control", run_id=f"pos{i:03d}", seed=100 + i,
                            fmt=fmt, duration_s=duration_s,
                            started_at=f"2026-03-02T10:{k:02d}:00Z", **params)
        k += 1
    return root


@pytest.fixture
def make_run():
    """``make_run(root, kind='flow_step', **overrides) -> run folder``."""
    return write_synthetic_run


@pytest.fixture
def make_dataset():
    """``make_dataset(root, n_flow=3, n_position=0, fmt='csv', **params) -> root``."""
    return write_synthetic_dataset


def snapshot(folder: Path) -> dict[str, str]:
    """Every entry under ``folder`` (hidden ones too) with its content hash, to
    show a command left a data folder untouched (FIFOs and links not opened)."""
    import hashlib
    import os

    out = {}
    for dirpath, dirnames, filenames in os.walk(folder):
        for d in dirnames:
            out[os.path.relpath(os.path.join(dirpath, d), folder)] = "dir"
        for f in filenames:
            p = Path(dirpath) / f
            out[str(p.relative_to(folder))] = (hashlib.sha256(p.read_bytes()).hexdigest()
                                               if p.is_file() else "special")
    return out


@pytest.fixture(scope="session")
def rig():
    """The shipped default rig config."""
    return load_rig()


#: the paper's drain drift, strong enough to show in 24 flow steps
GOLDEN_DRIFT = "drift:side=drain,step=0.05,every=3"


@contextmanager
def _shared_once(tmp_path_factory, name: str):
    """(folder, done) for a session fixture computed once per test run, not
    once per xdist worker: the folder lies in the run's temporary root,
    shared by its workers, and the block runs under an exclusive file lock
    (the first worker computes, the others wait and read). ``done`` is True
    when an earlier worker finished it (its ``.done`` marker is there).
    Without xdist the folder is this session's own.

    (pytest-xdist's ``--dist loadgroup`` cannot keep such tests on one
    worker under pytest 9.2: its ``xdist_group`` suffix is written to
    ``item._nodeid``, which pytest no longer reads.)
    """
    import fcntl

    base = tmp_path_factory.getbasetemp()
    # an xdist worker's base is <run>/popen-gwN: the run's root is shared
    root = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base
    folder = root / f"shared-{name}"
    with open(root / f"shared-{name}.lock", "w") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        marker = folder / ".done"
        done = marker.is_file()
        yield folder, done
        if not done:
            folder.mkdir(parents=True, exist_ok=True)   # (nothing made: still done)
            marker.write_text("")


@pytest.fixture(scope="session")
def golden_data(tmp_path_factory):
    """The golden data set (tests/test_golden.py): 24 flow steps on both sides
    at two loads with a drain drift, and the position-control test with and
    without the flow model, simulated with the built-in plant (seed 5).
    Made once per test run (read it, do not write into it)."""
    from datetime import datetime, timedelta, timezone

    from seanv_analysis.sim import simulate_flow_step, simulate_scenario

    with _shared_once(tmp_path_factory, "golden-data") as (folder, done):
        root = folder / "data"
        if done:
            return root
        t = datetime(2026, 3, 2, 9, 0, tzinfo=timezone.utc)
        grid = [(side, cam, load) for load in (0.3, 0.5) for rep in range(2)
                for side, cams in (("supply", (-5.0, 0.0, 5.0)), ("drain", (-40.0, -32.5, -25.0)))
                for cam in cams]
        for i, (side, cam, load) in enumerate(grid):
            run, _ = simulate_flow_step(side=side, cam_deg=cam, load_mpag=load, seed=5, run_index=i,
                                        effects=[GOLDEN_DRIFT], run_id=f"fs{i:02d}-{side}",
                                        started_at=t + timedelta(minutes=i))
            write_run(root / "flow" / run.meta.run_id, run.meta.to_json_dict(), run.tables)
        simulate_scenario("paper-position", root / "position", seed=5)
        return root


@pytest.fixture(scope="session")
def field_root(tmp_path_factory):
    """The field data (logs from a rig nobody here wrote, with truth;
    ``tests/field_data.py``) unpacked once per test run into its temporary
    root, shared by the xdist workers; skipped where the archive
    (``../shared/field-data``) is not. Read it, do not write into it."""
    from field_data import unpack_field_data

    with _shared_once(tmp_path_factory, "field-data") as (folder, done):
        root = folder if done else unpack_field_data(folder)
    # (a worker after the first finds the folder "done" even when there was
    # no archive to unpack: the truth files say whether it holds the data)
    if root is None or not (root / "_truth").is_dir():
        pytest.skip("the field data archive (../shared/field-data) is not here")
    return root


@pytest.fixture(scope="session")
def golden_run(golden_data, tmp_path_factory):
    """The paper pipeline on the golden data set, serial: (result.json
    document, out folder). Run once per test run (read it, do not write)."""
    import json

    from seanv_analysis.batch import run_pipeline

    with _shared_once(tmp_path_factory, "golden-run") as (folder, done):
        out = folder / "out"
        if not done:
            run_pipeline("paper", [golden_data / "flow", golden_data / "position"], out_dir=out,
                         workers=1, quiet=True, command=["golden"])
    return json.loads((out / "result.json").read_text()), out


# ---------------------------------------------------------------------------
# `make test-fast` (pytest -m "not slow"): the tests below take 2 s or more
# each on the 2-core machine (whole modules of end-to-end simulations, and
# single tests elsewhere; measured with --durations=0). `make test` runs all.
# ---------------------------------------------------------------------------
SLOW_MODULES = {"test_batch.py", "test_batch_signals.py", "test_discover_sim.py", "test_wheel.py",
                "test_discover_twin.py", "test_foreign_rig.py", "test_golden.py",
                "test_identify.py", "test_discover_terms.py", "test_sim_truth.py",
                "test_discover_terms_closed_loop.py", "test_identify_dynamic.py"}
SLOW_TESTS = (
    "test_cli_run.py::test_run_json_and_cache", "test_cli_run.py::test_run_end_to_end_subprocess",
    "test_cli_run.py::test_run_shipped_pipeline_by_name", "test_cli_run.py::test_plots_command",
    "test_discover_engine.py::test_load_dependence_is_not_passed_off_as_wear",
    "test_discover_engine.py::test_names_injected_effect_and_cuts_heldout_error",
    "test_discover_engine.py::test_drift_still_named_when_loads_step_with_time",
    "test_discover_engine.py::test_heldout_runs_are_never_fitted",
    "test_io_plausibility.py::test_limits_come_from_the_rig_file",
    "test_cli_tracking.py::test_tracking_on_simulated_paper_position",
    "test_outputs.py::test_command_manifest_lists_outputs_with_hashes",
    "test_outputs.py::test_second_dataset_leaves_no_file_of_the_first",
    "test_outputs.py::test_figures_are_byte_identical_across_runs",
    "test_flowfit.py::test_paper_flowsteps_simulated_recovers_truth",
    "test_flowfit.py::test_recovers_truth_with_interval",
    "test_tracking.py::test_write_and_figures",
    "test_report.py::", "test_cli_flowfit.py::test_subprocess_end_to_end",
    "test_readme.py::test_readme_snippet_runs",
    "test_cli_flowfit.py::test_no_data_uses_builtin",
    "test_cli_flowfit.py::test_bad_run_exit_1_results_still_written",
    "test_sim.py::test_seed_reproduces_dataset_bit_for_bit",
)


def pytest_collection_modifyitems(config, items):
    for item in items:
        rel = item.nodeid.split("tests/", 1)[-1]
        if rel.split("::", 1)[0] in SLOW_MODULES or rel.startswith(SLOW_TESTS):
            item.add_marker(pytest.mark.slow)


@pytest.fixture(scope="module")
def dask_cluster():
    """One LocalCluster for the module (2 worker processes, 1 thread each)."""
    distributed = pytest.importorskip("dask.distributed")
    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                       dashboard_address=None)
    yield cluster
    cluster.close()


@pytest.fixture(scope="session")
def hostile_data(tmp_path_factory):
    """tests/hostile: 8 synthetic flow steps (4 a side), made once per test run."""
    with _shared_once(tmp_path_factory, "hostile-data") as (folder, done):
        if not done:
            write_synthetic_dataset(folder / "data", n_flow=8)
    return folder / "data"


@pytest.fixture(scope="session")
def flowfit_out(hostile_data, tmp_path_factory):
    """tests/hostile: the output folder of `run flowfit` on :func:`hostile_data`
    (ingest, flow fit, Fig. 4 as PNG and SVG, report, the memo), made once per
    test run and never changed: a test that plants files copies it first."""
    from click.testing import CliRunner

    from seanv_analysis.cli import cli

    with _shared_once(tmp_path_factory, "hostile-flowfit") as (folder, done):
        if not done:
            res = CliRunner().invoke(cli, ["run", "flowfit", str(hostile_data), "--out",
                                           str(folder / "out"), "-q", "--workers", "1"])
            assert res.exit_code == 0, res.output
    return folder / "out"
