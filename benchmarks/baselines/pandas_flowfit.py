"""Baseline: the flow-model fit as a competent pandas/scipy user writes it
from the paper alone (Sec. II-C, II-D), for ``benchmarks/bench_commands.py``.

Per flow-step run (run.json kind; position-control runs are left out): pandas.read_csv of the three tables, velocity by a Savitzky-Golay
derivative (51 samples, order 2), Q = v x 201.06 mm^2, one steady value per
run (median over the second half of the cam hold, dp and p1 likewise), the
measured cam angle (median over the hold). Then the paper's filters and
``scipy.optimize.curve_fit`` of Q = C (theta - theta_d)^2 sqrt(dp) per side,
theta_d from eq. (3) + (4) inverted by interpolation, z0 and C fitted.
No intervals, no lack-of-fit check, no figure, no files written.

Usage: ``python benchmarks/baselines/pandas_flowfit.py DATA`` (numpy, scipy
and pandas only; not seanv_analysis).
"""
import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.optimize import curve_fit
from scipy.signal import savgol_filter

AREA_MM2 = np.pi / 4 * 16.0 ** 2              # 201.06 mm^2
DN, DO, K = 3.0, 2.27, 544.0                  # needle, seat [mm], spring [N/mm]
R, PHI, ZP, ZC0 = 20.0, np.radians(1.0), 51.848, 31.848
CENTRE = {"supply": (-7.10, -20.0), "drain": (-9.30, 20.0)}   # (x_c, y_c) [mm]
P0 = {"supply": (-0.155, 17.435), "drain": (-0.026, -22.636)}  # paper's values as start


def height_table(side):
    """Eq. (4) tabulated over -60..35 deg, sorted by height (for np.interp)."""
    xc, yc = CENTRE[side]
    th = np.linspace(-60.0, 35.0, 1901)
    t, tp = np.radians(th), np.tan(PHI)
    z = ((xc - R * np.sin(PHI) * np.cos(t)) * tp * np.cos(t)
         - (yc - R * tp * np.sin(t)) * tp * np.sin(t) + (ZP - R * np.cos(PHI)) - ZC0)
    order = np.argsort(z)
    return z[order], th[order]


def summarise(run_dir):
    """One row per run: side, load, cam, steady Q [mm^3/s], dp, p1 [MPa]."""
    meta = json.loads((run_dir / "run.json").read_text())
    enc = pd.read_csv(run_dir / "encoder.csv")
    prs = pd.read_csv(run_dir / "pressure.csv")
    srv = pd.read_csv(run_dir / "servo.csv")
    t = enc["t_s"].to_numpy()
    dt = np.median(np.diff(t))
    v = savgol_filter(enc["position_mm"].to_numpy(), 51, 2, deriv=1, delta=dt)
    hold = srv[np.isclose(srv["cam_cmd_deg"], meta["cam_deg"])]
    t0, t1 = hold["t_s"].iloc[0], hold["t_s"].iloc[-1]
    mid = t0 + 0.5 * (t1 - t0)
    sel = (t >= mid) & (t <= t1)
    p = prs.set_index("t_s").reindex(t, method="nearest")
    if meta["side"] == "supply":
        p1 = p["p_supply_mpag"].to_numpy()
        dp = p1 - p["p_head_mpag"].to_numpy()
    else:
        p1 = dp = p["p_head_mpag"].to_numpy()
    return {"side": meta["side"], "load": meta["load_mpag"], "cam_cmd": meta["cam_deg"],
            "cam": hold["cam_deg"].median(), "q": np.median(v[sel]) * AREA_MM2,
            "dp": np.median(dp[sel]), "p1": np.median(p1[sel]), "started": meta["started_at"]}


def fit_side(df, side):
    z_tab, th_tab = height_table(side)
    up = side == "supply"

    def model(x, z0, c):
        theta, p1, dp = x
        zc = z0 - np.pi / 4 * (DN ** 2 * p1 - DO ** 2 * dp) / K     # eq. (3)
        theta_d = np.interp(zc, z_tab, th_tab)                        # eq. (4) inverted
        opening = np.maximum(theta - theta_d if up else theta_d - theta, 0.0)
        return c * opening ** 2 * np.sqrt(np.maximum(dp, 0.0))       # eq. (5)

    d = df[df["side"] == side]
    x = np.vstack([d["cam"].fillna(d["cam_cmd"]), d["p1"], d["dp"]])
    (z0, c), _ = curve_fit(model, x, d["q"].to_numpy(), p0=P0[side])
    rmse = np.sqrt(np.mean((d["q"] - model(x, z0, c)) ** 2))
    return z0, c, rmse, len(d)


def is_flow_step(run_dir):
    """The flow-step runs: what the flow fit reads (a data set may hold
    position-control runs too)."""
    return json.loads((run_dir / "run.json").read_text()).get("kind") == "flow_step"


def main(data):
    runs = sorted(p.parent for p in Path(data).rglob("run.json") if is_flow_step(p.parent))
    df = pd.DataFrame([summarise(r) for r in runs]).sort_values("started")
    keep = (df["q"].abs() > 50) & df["cam_cmd"].between(-40, 10)
    keep &= ~((df["side"] == "drain") & (df["load"] <= 0.2) & (df["q"].abs() <= 500))
    df = df[keep]
    for side in ("supply", "drain"):
        z0, c, rmse, n = fit_side(df, side)
        print(f"{side}: z0 = {z0:.4f} mm, C = {c:.3f} mm^3/(s deg^2 MPa^0.5), "
              f"RMSE {rmse:.1f} mm^3/s over {n} runs")


if __name__ == "__main__":
    main(sys.argv[1])
