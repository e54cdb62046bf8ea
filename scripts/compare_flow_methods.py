"""Compare the paper's peak-velocity flow estimate with the steady-motion one
on simulated truth (writes the table quoted in docs/flow_estimate.md).

Usage: python scripts/compare_flow_methods.py [--seeds 3]
"""
from __future__ import annotations

import argparse

import numpy as np
import pandas as pd

from seanv_analysis import load_rig
from seanv_analysis.fit import fit_flow
from seanv_analysis.models import ValveModel
from seanv_analysis.sim.scenarios import iter_scenario_runs
from seanv_analysis.stages.dataset import summarize_runs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seeds", type=int, default=3)
    args = ap.parse_args()
    rig = load_rig()
    truth = ValveModel.from_rig(rig)
    per_run, fits = [], []
    for seed in range(args.seeds):
        runs = list(iter_scenario_runs("paper-flowsteps", rig=rig, seed=seed))
        for method in ("peak", "steady"):
            summary, _ = summarize_runs(runs, rig, method=method)
            ok = summary[(summary["excluded"] == "") & (summary["kind"] == "flow_step")]
            for side in ("supply", "drain"):
                d = ok[ok["side"] == side]
                q_true = truth.side(side).flow(d["cam_deg"].to_numpy(), d["p1_mpa"].to_numpy(),
                                               d["dp_mpa"].to_numpy())
                rel = (d["q_mm3_s"].to_numpy() - q_true) / np.abs(q_true)
                small = np.abs(q_true) < 1500
                per_run.append({"seed": seed, "method": method, "side": side, "n_runs": len(d),
                                "median_bias_pct": 100 * np.median(rel),
                                "median_bias_small_q_pct": 100 * np.median(rel[small]),
                                "rms_rel_error_pct": 100 * np.sqrt(np.mean(rel ** 2))})
            fit = fit_flow(summary, rig, n_boot=0)
            for side in ("supply", "drain"):
                s = fit.sides[side]
                t = truth.side(side)
                fits.append({"seed": seed, "method": method, "side": side,
                             "z0_error_mm": s.z0_mm - t.z0_mm,
                             "C_error_pct": 100 * (s.c_flow / t.c_flow - 1)})
    print("Per-run flow vs the plant's valve at the measured pressures (relative, magnitude sign):")
    print(pd.DataFrame(per_run).groupby(["method", "side"]).mean(numeric_only=True)
          .drop(columns="seed").round(2).to_string())
    print("\nFlowfit (joint) parameter errors vs truth:")
    print(pd.DataFrame(fits).groupby(["method", "side"]).agg(["mean", "max"])
          .drop(columns="seed").round(4).to_string())


if __name__ == "__main__":
    main()
