"""A run's tables as numpy columns (io.run_tables.RunTables) and the per-run
path on numpy arrays: the same numbers, bit for bit, as the DataFrame API."""
from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from fresh_process import cli_call, modules_after

from seanv_analysis.io import Run, read_run, write_run
from seanv_analysis.io.format_csv import write_csv
from seanv_analysis.io.run_tables import RunTables, table_columns
from seanv_analysis.signals.align import align_run, align_run_columns
from seanv_analysis.signals.derive import (
    derive_columns,
    derive_flow,
    derive_samples,
    estimate_flow,
    summarize_run,
)


def _columns():
    return {"t_s": np.array([0.0, 0.001, 0.002]), "position_mm": np.array([5.0, 5.25, 5.5])}


def test_frame_built_on_first_use_from_the_same_arrays():
    cols = _columns()
    tables = RunTables({"encoder": cols})
    assert tables.columns("encoder")["position_mm"] is cols["position_mm"]   # no frame, no copy
    assert tables.n_rows("encoder") == 3 and list(tables) == ["encoder"] and "encoder" in tables
    frame = tables["encoder"]
    assert list(frame.columns) == ["t_s", "position_mm"]
    assert frame["position_mm"].tolist() == [5.0, 5.25, 5.5]
    assert tables["encoder"] is frame   # built once


def test_a_frame_changed_in_place_is_what_columns_gives():
    tables = RunTables({"encoder": _columns()})
    tables["encoder"].loc[1, "position_mm"] = -1.0
    assert tables.columns("encoder")["position_mm"].tolist() == [5.0, -1.0, 5.5]
    tables["encoder"] = pd.DataFrame({"t_s": [0.0], "position_mm": [7.0]})
    assert tables.columns("encoder")["position_mm"].tolist() == [7.0]
    del tables["encoder"]
    with pytest.raises(KeyError):
        tables.columns("encoder")
    assert len(tables) == 0


def test_run_wraps_a_plain_dict(make_run, tmp_path):
    run = read_run(make_run(tmp_path, duration_s=0.3))
    frames = {name: run.tables[name] for name in run.tables}
    again = Run(meta=run.meta, tables=frames, rig=run.rig)
    assert isinstance(again.tables, RunTables) and again.tables["encoder"] is frames["encoder"]
    for name in frames:
        for col, values in table_columns(frames, name).items():
            np.testing.assert_array_equal(again.tables.columns(name)[col], values)


def test_numpy_path_equals_dataframe_path_bit_for_bit(make_run, tmp_path):
    for side, cam in (("supply", -8.0), ("drain", 12.0)):
        path = make_run(tmp_path / side, side=side, cam_deg=cam, duration_s=1.0)
        lazy, framed = read_run(path), read_run(path)
        for name in framed.tables:   # every frame built: the DataFrame route throughout
            framed.tables[name]
        frame = derive_samples(framed)
        cols, info = derive_columns(lazy)
        assert list(cols) == list(frame.columns)
        for col in frame.columns:
            assert np.array_equal(cols[col], frame[col].to_numpy(), equal_nan=True), col
        assert info.to_dict() == frame.attrs["velocity"]
        aligned = align_run_columns(lazy)
        pd.testing.assert_frame_equal(pd.DataFrame(aligned), align_run(framed), check_exact=True)
        assert summarize_run(lazy) == summarize_run(framed, derived=frame)
        assert summarize_run(lazy, method="peak") == summarize_run(framed, method="peak",
                                                                    derived=frame)
        assert estimate_flow(lazy) == estimate_flow(framed, derived=frame)


def test_flow_columns_alone_equal_the_full_derivation(make_run, tmp_path):
    """derive_flow (the replays' path: time, position, flow only) gives
    derive_samples' numbers on its time base: a position-control run whose
    servo log starts later and ends sooner than the encoder's (the span
    every stream bounds), its encoder clock jittered (the derivative
    resampled), and a simulated replay."""
    from seanv_analysis.sim.run import simulate_cam_replay

    run = read_run(make_run(tmp_path / "pos", kind="position_control", duration_s=3.0))
    jittered = run.tables.columns("encoder")
    t = jittered["t_s"].copy()
    t[1::7] += 0.3 * (t[1] - t[0])      # 30 % of a step: beyond the uniform tolerance
    run.tables["encoder"] = pd.DataFrame({**jittered, "t_s": t})
    sim, _ = simulate_cam_replay(run.rig, cam_cmd=([0.0, 1.0], [-15.0, 5.0]), load=0.3,
                                 duration_s=2.0, x0_mm=20.0)
    for r in (read_run(make_run(tmp_path / "pos2", kind="position_control", duration_s=3.0)),
              run, sim):
        frame = derive_samples(r)
        flow = derive_flow(r)
        assert list(flow) == ["t_s", "position_mm", "q_mm3_s"]
        for col, values in flow.items():
            assert np.array_equal(values, frame[col].to_numpy(), equal_nan=True), col
    assert derive_samples(run).attrs["velocity"]["resampled"]


def test_csv_from_columns_equals_csv_from_frame(tmp_path):
    rng = np.random.default_rng(3)
    cols = {"t_s": np.arange(0, 2.0, 0.001), "p_head_mpag": rng.normal(0.4, 0.01, 2000)}
    cols["p_head_mpag"][[0, 7, 1999]] = np.nan
    write_csv(cols, tmp_path / "a.csv")
    write_csv(pd.DataFrame(cols), tmp_path / "b.csv")
    assert (tmp_path / "a.csv").read_bytes() == (tmp_path / "b.csv").read_bytes()
    text = (tmp_path / "a.csv").read_text().splitlines()
    assert text[:2] == ["t_s,p_head_mpag", "0,"] and text[-1] == "1.999,"   # NaN: empty cell
    assert float(text[2].split(",")[1]) == float(f"{cols['p_head_mpag'][1]:.9g}")


def test_written_run_reads_back_the_same_columns(make_run, tmp_path):
    run = read_run(make_run(tmp_path / "in", duration_s=0.3))
    out = write_run(tmp_path / "out", run.meta.to_json_dict(), run.tables)
    back = read_run(out)
    for name in run.tables:
        for col, values in run.tables.columns(name).items():
            np.testing.assert_array_equal(back.tables.columns(name)[col], values)


def test_simulate_loads_no_pandas(tmp_path):
    """``simulate`` writes its CSV files from numpy arrays: pandas (~0.3 s) is
    never imported (benchmarks/bench_commands.py times the command)."""
    code = cli_call("simulate", "paper-position-model", "--out", tmp_path, "-q")
    assert modules_after(code, ["pandas", "matplotlib"]) == []
    assert (tmp_path / "position-with-flow-model" / "encoder.csv").read_text().startswith(
        "t_s,position_mm\n0,")
