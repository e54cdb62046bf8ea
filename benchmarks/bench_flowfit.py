"""flowfit on a 500-run data set: time, peak memory, parameter recovery,
interval coverage and the pull of one outlier run.

- ``summary``: ``fit.fit_flow`` on a synthetic 500-run per-run summary
  (2 sides x 5 loads x 25 cam angles x 2 repeats, eq. 5 of the paper's valve
  plus noise sigma = 20 + 3 % |Q| mm^3/s), 200 bootstrap resamples;
- ``disk``: the whole path from disk (read + validate + derive + filter +
  fit + write outputs + Fig. 4) on 500 synthetic flow-step runs written with
  the test fixtures' writer (``tests/conftest.py``), when available;
- ``recovery``: over ``N_SEEDS`` seeds x 3 truth sets, the largest |z0 error|
  [mm] and |C error| [%], and how often the 95 % interval holds the truth
  (joint and two-step);
- ``outlier``: one run's flow x 3 (the largest flow of a side): change of C [%].

Time: untraced call. Peak memory: ``tracemalloc`` peak of Python
allocations during a second, traced call, and the process's peak RSS
(``ru_maxrss``).
Usage: ``python -m benchmarks.bench_flowfit`` (or ``python -m benchmarks flowfit``).
"""
from __future__ import annotations

import importlib.util
import json
import resource
import tempfile
import time
import tracemalloc
import warnings
from pathlib import Path

import numpy as np

from . import tests_module

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "flowfit.json"
N_SEEDS = 12
TRUTHS = {"paper": {"supply": (-0.155, 17.435), "drain": (-0.026, -22.636)},
          "set_a": {"supply": (-0.12, 14.0), "drain": (-0.06, -27.0)},
          "set_b": {"supply": (-0.19, 21.0), "drain": (0.01, -18.0)}}
CAMS_500 = tuple(np.round(np.arange(-42.5, 17.5 + 1e-9, 2.5), 3))  # 25 angles
LOADS_500 = (0.1, 0.2, 0.3, 0.4, 0.5)


def _model(rig, name):
    from seanv_analysis.models import ValveModel

    m = ValveModel.from_rig(rig)
    for side, (z0, c) in TRUTHS[name].items():
        m = m.with_side(side, z0_mm=z0, c_flow=c)
    return m


def _measure(fn):
    """(result, seconds, tracemalloc peak [MiB]): timed untraced (tracemalloc
    slows allocation-heavy code several-fold), then run again traced."""
    t0 = time.perf_counter()
    out = fn()
    dt = time.perf_counter() - t0
    tracemalloc.start()
    fn()
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return out, dt, peak / 2 ** 20


def bench_summary(rig) -> dict:
    from seanv_analysis.fit import fit_flow
    synthetic_flow_summary = tests_module("synthetic_flow").synthetic_flow_summary

    summary = synthetic_flow_summary(_model(rig, "paper"), rig, seed=0, loads_mpag=LOADS_500,
                                     cams_deg=CAMS_500, repeats=2)
    fit, dt, peak = _measure(lambda: fit_flow(summary, rig, n_boot=200))
    _, dt0, peak0 = _measure(lambda: fit_flow(summary, rig, n_boot=0))
    return {"runs": len(summary), "runs_fitted": int((summary["excluded"] == "").sum()),
            "time_s": round(dt, 3), "tracemalloc_peak_mib": round(peak, 2),
            "time_no_bootstrap_s": round(dt0, 3), "tracemalloc_peak_no_bootstrap_mib":
                round(peak0, 2), "result": fit.to_json_dict()}


def _conftest_writer():
    path = HERE.parent / "tests" / "conftest.py"
    if not path.is_file():
        return None
    spec = importlib.util.spec_from_file_location("_seanv_conftest", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.write_synthetic_run


def bench_disk(rig) -> dict:
    from seanv_analysis.fit import fit_flow
    from seanv_analysis.models import ValveModel, side_pressures
    from seanv_analysis.plots.fig4 import plot_fig4
    from seanv_analysis.stages import run_stages
    from seanv_analysis.stages.flowfit import write as write_flowfit

    write = _conftest_writer()
    if write is None:
        return {"skipped": "tests/conftest.py not found"}
    model = ValveModel.from_rig(rig)
    cams = {"supply": np.arange(-12.0, 3.0, 0.6), "drain": np.arange(-31.0, -16.0, 0.6)}
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "flow500"
        k = 0
        t0 = time.perf_counter()
        for side in ("supply", "drain"):
            for load in LOADS_500:
                p_head = 4 * load + (0.3 if side == "supply" else 0.0)
                p1, dp = side_pressures(side, 3.3, p_head, 0.0)
                for _rep in range(2):
                    for cam in cams[side]:
                        q = float(model.side(side).flow(cam, p1, dp))
                        write(root, side=side, cam_deg=round(float(cam), 2), load_mpag=load,
                              flow_mm3_s=q, seed=k, duration_s=0.5, run_id=f"r{k:04d}",
                              started_at=f"2026-03-02T{10 + k // 3600:02d}:"
                                         f"{k // 60 % 60:02d}:{k % 60:02d}Z")
                        k += 1
        t_write = time.perf_counter() - t0

        calls: list[dict] = []

        def run():
            stages: dict = {}
            calls.append(stages)
            t = time.perf_counter()
            ds = run_stages(root, ["ingest"], rig=rig).result("ingest")
            stages["read_derive_filter_s"] = round(time.perf_counter() - t, 2)
            t = time.perf_counter()
            fit = fit_flow(ds.summary, rig, cam="commanded", n_boot=200)
            stages["fit_s"] = round(time.perf_counter() - t, 2)
            t = time.perf_counter()
            write_flowfit(fit, Path(tmp) / "out")
            plot_fig4(fit, Path(tmp) / "out")
            stages["write_and_fig4_s"] = round(time.perf_counter() - t, 2)
            return fit, ds

        (fit, ds), dt, peak = _measure(run)
        stages = calls[0]  # the untraced call
        size = sum(p.stat().st_size for p in root.rglob("*") if p.is_file())
    return {"runs": k, "bad_runs": len(ds.failed), "data_mib": round(size / 2 ** 20, 2),
            "write_data_s": round(t_write, 2), "time_s": round(dt, 2), **stages,
            "tracemalloc_peak_mib": round(peak, 2), "result": fit.to_json_dict()}


def bench_recovery(rig) -> dict:
    from seanv_analysis.fit import fit_flow
    synthetic_flow_summary = tests_module("synthetic_flow").synthetic_flow_summary

    out = {}
    for procedure in ("joint", "two_step"):
        stats = {s: {"n": 0, "z0_in": 0, "c_in": 0, "z0_err": [], "c_err": []}
                 for s in ("supply", "drain")}
        for name in TRUTHS:
            truth = _model(rig, name)
            for seed in range(N_SEEDS):
                fit = fit_flow(synthetic_flow_summary(truth, rig, seed=100 + seed), rig,
                               procedure=procedure, n_boot=200)
                for s, d in stats.items():
                    f, t = fit.sides[s], truth.side(s)
                    d["n"] += 1
                    d["z0_in"] += f.z0_ci95[0] <= t.z0_mm <= f.z0_ci95[1]
                    d["c_in"] += min(f.c_ci95) <= t.c_flow <= max(f.c_ci95)
                    d["z0_err"].append(abs(f.z0_mm - t.z0_mm))
                    d["c_err"].append(abs(f.c_flow / t.c_flow - 1) * 100)
        out[procedure] = {s: {"fits": d["n"], "z0_ci95_coverage": d["z0_in"] / d["n"],
                              "C_ci95_coverage": d["c_in"] / d["n"],
                              "max_abs_z0_err_mm": round(max(d["z0_err"]), 5),
                              "rms_z0_err_mm": round(float(np.sqrt(np.mean(np.square(
                                  d["z0_err"])))), 5),
                              "max_abs_C_err_pct": round(max(d["c_err"]), 3),
                              "rms_C_err_pct": round(float(np.sqrt(np.mean(np.square(
                                  d["c_err"])))), 3)}
                          for s, d in stats.items()}
    return out


def bench_outlier(rig) -> dict:
    from seanv_analysis.fit import fit_flow
    synthetic_flow_summary = tests_module("synthetic_flow").synthetic_flow_summary

    out = {}
    summary = synthetic_flow_summary(_model(rig, "paper"), rig, seed=3)
    for side in ("supply", "drain"):
        clean = fit_flow(summary, rig, sides=(side,), n_boot=0).sides[side]
        s = summary.copy()
        used = s[(s["side"] == side) & (s["excluded"] == "")]
        s.loc[used["q_mm3_s"].abs().idxmax(), "q_mm3_s"] *= 3.0
        bad = fit_flow(s, rig, sides=(side,), n_boot=0).sides[side]
        out[side] = {"C_change_pct": round((bad.c_flow / clean.c_flow - 1) * 100, 3),
                     "z0_change_mm": round(bad.z0_mm - clean.z0_mm, 5), "loss": "soft_l1"}
    return out


def main() -> dict:
    from seanv_analysis.config import load_rig

    warnings.simplefilter("ignore")
    rig = load_rig()
    result = {"summary_500": bench_summary(rig), "disk_500": bench_disk(rig),
              "outlier_x3": bench_outlier(rig), "recovery": bench_recovery(rig)}
    result["peak_rss_mib"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
    RESULTS.parent.mkdir(exist_ok=True)
    RESULTS.write_text(json.dumps(result, indent=2, default=str) + "\n")
    return result


if __name__ == "__main__":
    print(json.dumps(main(), indent=2, default=str))
