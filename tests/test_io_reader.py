"""Reader, calibration, alignment and manifest on synthetic runs with known values."""
from __future__ import annotations

import hashlib
import json

import numpy as np
import pandas as pd
import pytest
from conftest import synthetic_tables
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose, assert_array_equal

from seanv_analysis.errors import DataError
from seanv_analysis.io import DatasetRead, RunError, find_runs, read_dataset, read_run, write_run
from seanv_analysis.io import hashing as _hashing
from seanv_analysis.io.manifest import build_manifest, write_manifest
from seanv_analysis.signals import align_streams
from seanv_analysis.signals.align import align_run


def _csv_rounded(values) -> np.ndarray:
    """What a value written with '%.9g' reads back as (independent of the reader)."""
    return np.array([float("%.9g" % v) for v in np.asarray(values, dtype=float)])


# round trip -------------------------------------------------------------------

@pytest.mark.parametrize("fmt", ["csv", "parquet"])
@pytest.mark.parametrize("kind", ["flow_step", "position_control"])
def test_written_run_reads_back_exactly(tmp_path, make_run, fmt, kind):
    tables = synthetic_tables(kind, duration_s=0.3, seed=3)
    run_dir = make_run(tmp_path, kind, fmt=fmt, duration_s=0.3, seed=3, run_id="r1",
                       started_at="2026-03-02T10:14:05Z")
    run = read_run(run_dir)
    assert run.run_id == "r1" and run.kind == kind
    assert run.meta.started_at == pd.Timestamp("2026-03-02T10:14:05Z").to_pydatetime()
    assert run.meta.load_mpag == 0.35
    if kind == "flow_step":
        assert (run.meta.side, run.meta.cam_deg) == ("supply", -8.0)
    else:
        assert run.meta.controller == {"kp": 480, "flow_model": True, "rate_hz": 100}
    assert set(run.tables) == set(tables)
    for name, df in tables.items():
        got = run.tables[name]
        for col in df.columns:
            expected = _csv_rounded(df[col]) if fmt == "csv" else df[col].to_numpy()
            assert_array_equal(got[col].to_numpy(), expected, err_msg=f"{name}.{col}")
    # tank pressure added (atmospheric) for downstream code
    assert list(run.tables["pressure"].columns) == ["t_s", "p_supply_mpag", "p_head_mpag",
                                                    "p_load_mpag", "p_tank_mpag"]
    assert (run.tables["pressure"]["p_tank_mpag"] == 0.0).all()
    assert set(run.file_sha256) == {str(p) for p in run.files.values()}
    for path in run.files.values():
        assert run.file_sha256[str(path)] == hashlib.sha256(path.read_bytes()).hexdigest()


def test_tank_column_kept_when_present(tmp_path, make_run):
    t = synthetic_tables(duration_s=0.2)
    p = t["pressure"].assign(p_tank_mpag=0.01)
    run = read_run(make_run(tmp_path, duration_s=0.2, tables={"pressure": p}))
    assert_allclose(run.tables["pressure"]["p_tank_mpag"], 0.01)


def test_extra_columns_and_fields_are_kept(tmp_path, make_run):
    t = synthetic_tables(duration_s=0.2)
    enc = t["encoder"].assign(note="ok", temperature_c=21.5)
    run = read_run(make_run(tmp_path, duration_s=0.2, tables={"encoder": enc},
                            meta={"operator": "sk", "valve_serial": 7}))
    assert list(run.tables["encoder"].columns) == ["t_s", "position_mm", "note", "temperature_c"]
    assert run.meta.extra == {"operator": "sk", "valve_serial": 7}
    assert "note" not in align_run(run).columns  # extras are ignored by the analysis


def test_nullable_columns_may_be_entirely_empty(tmp_path, make_run):
    t = synthetic_tables("position_control", duration_s=0.3)
    servo = t["servo"].assign(cam_deg=np.nan)
    ctrl = t["controller"].assign(q_ref_mm3_s=np.nan)
    run = read_run(make_run(tmp_path, "position_control", duration_s=0.3,
                            controller={"kp": 15, "flow_model": False},
                            tables={"servo": servo, "controller": ctrl}))
    assert run.tables["servo"]["cam_deg"].isna().all()
    aligned = align_run(run)
    assert aligned["q_ref_mm3_s"].isna().all() and aligned["cam_deg"].isna().all()
    assert aligned["x_ref_mm"].notna().all()


def test_started_at_without_zone_is_utc(tmp_path, make_run):
    run = read_run(make_run(tmp_path, duration_s=0.2, started_at="2026-03-02T10:14:05"))
    assert run.meta.started_at.utcoffset().total_seconds() == 0


def test_blank_lines_and_crlf_are_read(tmp_path, make_run):
    run_dir = make_run(tmp_path, duration_s=0.2, noise=False)
    enc = run_dir / "encoder.csv"
    lines = enc.read_text().splitlines()
    enc.write_bytes(("\r\n".join(lines[:5] + [""] + lines[5:]) + "\r\n").encode())
    assert len(read_run(run_dir).tables["encoder"]) == len(lines) - 1


# calibration ------------------------------------------------------------------

def _raw_tables(n=11):
    t = np.arange(n) / 1000.0
    ts = 0.0005 + np.arange(n // 2) / 500.0
    return {
        "encoder": pd.DataFrame({"t_s": t, "encoder_counts": np.arange(n) * 1000 + 12345}),
        "pressure": pd.DataFrame({"t_s": t, "p_supply_v": np.full(n, 3.64),
                                  "p_head_kpag": np.full(n, 1600.0),
                                  "p_load_v": np.full(n, 1.28), "p_tank_kpag": np.full(n, 5.0)}),
        "servo": pd.DataFrame({"t_s": ts, "cam_cmd_pulse": np.full(ts.size, 2048 - 91),
                               "cam_pulse": np.full(ts.size, 2048 + 91)}),
    }


@pytest.mark.parametrize("fmt", ["csv", "parquet"])
def test_raw_units_are_calibrated(tmp_path, fmt):
    meta = {"run_id": "raw", "kind": "flow_step", "started_at": "2026-03-02T10:00:00Z",
            "load_mpag": 0.35, "side": "supply", "cam_deg": -8.0}
    run = read_run(write_run(tmp_path / "raw", meta, _raw_tables(), fmt=fmt))
    enc, pr, sv = run.tables["encoder"], run.tables["pressure"], run.tables["servo"]
    # default.toml [calibration]: 0.001 mm/count, (V - 1.0) * 1.25 MPa/V, 1000 kPa/MPa,
    # servo centre 2048 pulses, 0.0879 deg/pulse
    assert_allclose(enc["position_mm"], 12.345 + np.arange(11) * 1.0, rtol=1e-12)
    assert_allclose(pr["p_supply_mpag"], 3.3, rtol=1e-12)
    assert_allclose(pr["p_head_mpag"], 1.6, rtol=1e-12)
    assert_allclose(pr["p_load_mpag"], 0.35, rtol=1e-12)
    assert_allclose(pr["p_tank_mpag"], 0.005, rtol=1e-12)
    assert_allclose(sv["cam_cmd_deg"], -7.9989, rtol=1e-12)
    assert_allclose(sv["cam_deg"], 7.9989, rtol=1e-12)
    assert list(enc.columns) == ["t_s", "position_mm"]  # raw column replaced by its conversion


def test_run_rig_overrides_apply_to_calibration(tmp_path):
    meta = {"run_id": "raw", "kind": "flow_step", "started_at": "2026-03-02T10:00:00Z",
            "load_mpag": 0.35, "side": "supply", "cam_deg": -8.0,
            "rig": {"calibration": {"encoder_mm_per_count": 0.002, "encoder_offset_mm": 1.0}}}
    run = read_run(write_run(tmp_path / "raw", meta, _raw_tables()))
    assert_allclose(run.tables["encoder"]["position_mm"], 1.0 + 0.002 * (12345 + 1000 * np.arange(11)))
    assert run.rig["calibration"]["encoder_mm_per_count"] == 0.002


def test_engineering_column_wins_over_raw(tmp_path, make_run):
    t = synthetic_tables(duration_s=0.2)
    enc = t["encoder"].assign(encoder_counts=1)
    run = read_run(make_run(tmp_path, duration_s=0.2, tables={"encoder": enc}))
    assert_array_equal(run.tables["encoder"]["position_mm"], _csv_rounded(enc["position_mm"]))


def test_rig_argument_used_for_calibration(tmp_path, rig):
    meta = {"run_id": "raw", "kind": "flow_step", "started_at": "2026-03-02T10:00:00Z",
            "side": "supply", "cam_deg": -8.0}
    custom = rig.with_overrides({"calibration": {"pressure_mpa_per_v": 1.0}})
    run = read_run(write_run(tmp_path / "raw", meta, _raw_tables()), rig=custom)
    assert_allclose(run.tables["pressure"]["p_supply_mpag"], 2.64, rtol=1e-12)
    assert run.meta.load_mpag is None


# finding and reading data sets ----------------------------------------------

def test_find_runs_any_depth(tmp_path, make_run):
    a = make_run(tmp_path / "day1", run_id="a", duration_s=0.1)
    b = make_run(tmp_path / "day2" / "rig" / "x", run_id="b", duration_s=0.1)
    make_run(tmp_path / ".trash", run_id="c", duration_s=0.1)
    (tmp_path / "notes").mkdir()
    assert find_runs(tmp_path) == [a, b]
    assert find_runs(a) == [a]
    with pytest.raises(DataError, match="not found"):
        find_runs(tmp_path / "nope")
    with pytest.raises(DataError, match="no run.json found at any depth"):
        read_dataset(tmp_path / "notes")


def test_read_dataset_orders_runs_and_collects_errors(tmp_path, make_dataset, make_run):
    make_dataset(tmp_path, n_flow=4, n_position=1, duration_s=0.2)
    bad = make_run(tmp_path, run_id="broken", duration_s=0.2, started_at="2026-03-02T09:00:00Z")
    (bad / "servo.csv").unlink()
    dup = make_run(tmp_path / "copy", run_id="z004-supply", duration_s=0.2,
                   started_at="2026-03-02T11:00:00Z")
    ds = read_dataset(tmp_path)
    assert isinstance(ds, DatasetRead) and not ds.success
    assert [r.run_id for r in ds.runs] == ["z004-supply", "z003-drain", "z002-supply",
                                           "z001-drain", "pos000"]
    starts = [r.meta.started_at for r in ds.runs]
    assert starts == sorted(starts)
    assert [e.path for e in ds.errors] == [bad, dup]
    assert all(isinstance(e, RunError) and "\n" not in e.message for e in ds.errors)
    assert "servo.csv: missing required file" in ds.errors[0].message
    assert "also the run id of" in ds.errors[1].message
    assert set(ds.file_sha256()) == {str(p) for r in ds.runs for p in r.files.values()}
    assert "5 run(s) read, 2 bad" in ds.report()


def test_read_dataset_single_run_folder(tmp_path, make_run):
    run_dir = make_run(tmp_path, duration_s=0.1)
    ds = read_dataset(run_dir)
    assert [r.meta.path for r in ds.runs] == [run_dir] and ds.success


# alignment --------------------------------------------------------------------

def _streams():
    k = np.arange(2001)
    t_enc = k / 1000.0                        # 1 kHz from 0
    t_p = 0.0004 + np.arange(2000) / 1000.0   # 1 kHz from 0.4 ms
    j = np.arange(200)
    t_sv = 0.0053 + j / 100.0                 # 100 Hz from 5.3 ms
    return {
        "encoder": pd.DataFrame({"t_s": t_enc, "position_mm": np.sin(t_enc)}),
        "pressure": pd.DataFrame({"t_s": t_p, "p_supply_mpag": 2.0 + 0.5 * t_p}),
        "servo": pd.DataFrame({"t_s": t_sv, "cam_cmd_deg": -15.0 + (j % 7),
                               "cam_deg": -10.0 + 3.0 * t_sv}),
    }


def test_align_1khz_and_100hz_with_different_starts():
    streams = _streams()
    out = align_streams(streams)
    assert list(out.columns) == ["t_s", "position_mm", "p_supply_mpag", "cam_cmd_deg", "cam_deg"]
    # overlap: starts 0, 0.4 ms, 5.3 ms; ends 2.0 s, 1.9994 s, 1.9953 s -> encoder samples
    # 6 ms .. 1995 ms
    k = np.arange(6, 1996)
    assert_array_equal(out["t_s"].to_numpy(), k / 1000.0)
    assert_array_equal(out["position_mm"].to_numpy(), np.sin(k / 1000.0))  # base: untouched
    assert_allclose(out["p_supply_mpag"], 2.0 + 0.5 * k / 1000.0, rtol=1e-13)
    assert_allclose(out["cam_deg"], -10.0 + 3.0 * k / 1000.0, rtol=1e-13)
    j = (10 * k - 53) // 100  # last servo sample at or before k ms: 5.3 + 10 j <= k
    assert_array_equal(out["cam_cmd_deg"].to_numpy(), -15.0 + (j % 7))


def test_align_given_time_base_is_trimmed_not_extrapolated():
    out = align_streams(_streams(), t_s=np.array([0.0, 0.005, 0.0053, 0.1, 1.9953, 1.999]))
    assert_array_equal(out["t_s"].to_numpy(), [0.0053, 0.1, 1.9953])
    assert_allclose(out["p_supply_mpag"], 2.0 + 0.5 * out["t_s"], rtol=1e-13)
    assert out["cam_cmd_deg"].iloc[0] == -15.0


def test_align_errors():
    s = _streams()
    s["servo"] = s["servo"].assign(t_s=s["servo"]["t_s"] + 10.0)
    with pytest.raises(DataError, match="streams do not overlap"):
        align_streams(s)
    with pytest.raises(ValueError, match="column 'position_mm' is in both"):
        align_streams({"encoder": _streams()["encoder"], "b": _streams()["encoder"]})
    with pytest.raises(ValueError, match="base: no stream named"):
        align_streams(_streams(), base="nope")


def test_run_aligned_position_control_holds_commands(tmp_path, make_run):
    run = read_run(make_run(tmp_path, "position_control", duration_s=0.5, noise=False))
    a = align_run(run)
    assert list(a.columns) == ["t_s", "position_mm", "p_supply_mpag", "p_head_mpag",
                               "p_load_mpag", "p_tank_mpag", "cam_cmd_deg", "cam_deg",
                               "x_ref_mm", "q_ref_mm3_s"]
    lo, hi = run.span_s
    assert a["t_s"].iloc[0] >= lo and a["t_s"].iloc[-1] <= hi
    ctrl = run.tables["controller"]
    for t, x in zip(a["t_s"].to_numpy()[::37], a["x_ref_mm"].to_numpy()[::37]):
        assert x == ctrl["x_ref_mm"][ctrl["t_s"] <= t].iloc[-1]


_times = st.tuples(st.floats(-5, 5), st.floats(1.0, 2000.0), st.integers(2, 60))


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(a=_times, b=_times, seed=st.integers(0, 2**31 - 1),
       extra=st.lists(st.floats(-20, 20), max_size=20))
def test_alignment_never_extrapolates(a, b, seed, extra):
    rng = np.random.default_rng(seed)
    (s0, r0, n0), (s1, r1, n1) = a, b
    t0 = s0 + np.arange(n0) / r0
    t1 = s1 + np.arange(n1) / r1
    v1 = rng.normal(size=n1)
    h1 = rng.integers(-5, 5, size=n1).astype(float)
    streams = {"encoder": pd.DataFrame({"t_s": t0, "position_mm": rng.normal(size=n0)}),
               "servo": pd.DataFrame({"t_s": t1, "cam_deg": v1, "cam_cmd_deg": h1})}
    lo, hi = max(t0[0], t1[0]), min(t0[-1], t1[-1])
    if lo > hi:
        with pytest.raises(DataError):
            align_streams(streams)
        return
    for t_s in (None, np.array(extra)):
        out = align_streams(streams, t_s=t_s)
        t = out["t_s"].to_numpy()
        assert ((t >= lo) & (t <= hi)).all()
        for ti, v, h in zip(t, out["cam_deg"], out["cam_cmd_deg"]):
            i = np.searchsorted(t1, ti, side="right") - 1  # last sample at or before ti
            assert h == h1[i]
            nxt = v1[min(i + 1, n1 - 1)]
            assert min(v1[i], nxt) - 1e-12 <= v <= max(v1[i], nxt) + 1e-12


# hashing and manifest -----------------------------------------------------------

def test_manifest_reuses_reader_hashes(tmp_path, make_dataset, monkeypatch):
    data = make_dataset(tmp_path / "data", n_flow=2, duration_s=0.2)
    ds = read_dataset(data)

    def no_reread(*a, **k):
        raise AssertionError("file hashed twice")

    monkeypatch.setattr(_hashing, "open", no_reread, raising=False)
    doc = build_manifest(config={"x": 1}, inputs=[data], command=["seanv-analyze", "ingest", "d"])
    hashes = {i["path"]: i["sha256"] for i in doc["inputs"]}
    assert hashes == {k: v for k, v in sorted(ds.file_sha256().items())}
    assert doc["version"] and doc["command_line"] == "seanv-analyze ingest d"


def test_write_manifest(tmp_path):
    f = tmp_path / "a.txt"
    f.write_bytes(b"hello")
    path = write_manifest(tmp_path / "out", config={"k": 2}, inputs=[f], command="x y",
                          extra={"runs": 3})
    doc = json.loads(path.read_text())
    assert doc["inputs"] == [{"path": str(f), "sha256": hashlib.sha256(b"hello").hexdigest()}]
    assert doc["config"] == {"k": 2} and doc["extra"] == {"runs": 3}
    assert doc["command_line"] == "x y" and doc["schema"] == "seanv-manifest/1"
    assert len(doc["inputs_sha256"]) == 64 and "git_sha" in doc
    # the environment a result was made with, as pip freeze lists it
    import numpy
    import scipy

    assert f"numpy=={numpy.__version__}" in doc["packages"]
    assert f"scipy=={scipy.__version__}" in doc["packages"]
    assert doc["packages"] == sorted(doc["packages"], key=lambda s: s.split("==")[0].lower())


# long-log paths (threads, purging pool): same tables, same first error ------------

def _tables_equal(a, b):
    assert set(a.tables) == set(b.tables)
    for name in a.tables:
        pd.testing.assert_frame_equal(a.tables[name], b.tables[name], check_exact=True)


@pytest.mark.parametrize("fmt", ["csv", "parquet"])
def test_concurrent_and_purging_pool_read_the_same(tmp_path, make_run, monkeypatch, fmt):
    from seanv_analysis.io import reader, scan

    run_dir = make_run(tmp_path, fmt=fmt, duration_s=2.0, seed=5)
    plain = read_run(run_dir)
    monkeypatch.setattr(reader, "_CONCURRENT_MIN_BYTES", 0)   # tables on threads
    monkeypatch.setattr(scan, "_LARGE_FILE", 0)               # every file in the purging pool
    fast = read_run(run_dir)
    _tables_equal(plain, fast)
    assert fast.file_sha256 == plain.file_sha256


def test_concurrent_read_reports_the_first_bad_table_in_contract_order(tmp_path, make_run,
                                                                        monkeypatch):
    from seanv_analysis.io import reader

    t = synthetic_tables(duration_s=0.3)
    enc = t["encoder"].copy()
    enc.loc[5, "t_s"] = enc.loc[4, "t_s"]                     # duplicated timestamp, row 6
    pr = t["pressure"].drop(columns=["p_head_mpag"])          # missing column
    run_dir = make_run(tmp_path, duration_s=0.3, tables={"encoder": enc, "pressure": pr})
    with pytest.raises(DataError) as sequential:
        read_run(run_dir)
    monkeypatch.setattr(reader, "_CONCURRENT_MIN_BYTES", 0)
    with pytest.raises(DataError) as concurrent:
        read_run(run_dir)
    assert str(concurrent.value) == str(sequential.value)
    assert "encoder.csv" in str(concurrent.value) and "row 6" in str(concurrent.value)


def test_default_tank_pressure_is_a_constant_view(tmp_path, make_run):
    run = read_run(make_run(tmp_path, duration_s=0.2))
    tank = run.tables["pressure"]["p_tank_mpag"].to_numpy()
    assert tank.strides == (0,) and (tank == 0.0).all()
    aligned = align_run(run)
    assert aligned["p_tank_mpag"].to_numpy().strides == (0,)


def test_return_large_blocks_to_os_is_idempotent():
    import sys

    from seanv_analysis.batch.process_setup import return_large_blocks_to_os

    first = return_large_blocks_to_os()
    assert return_large_blocks_to_os() is first
    if sys.platform.startswith("linux"):
        import platform
        if platform.libc_ver()[0] == "glibc":
            assert first is True
