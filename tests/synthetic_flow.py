"""Synthetic per-run summaries from the valve model with known truth, for
``tests/test_flowfit.py`` and ``benchmarks/bench_flowfit.py`` (not part of
the package).

The flow of each run is eq. (5) of ``model`` at the run's cam angle and
pressures, plus Gaussian noise of ``noise_floor_mm3_s + noise_rel |Q|``;
sealed runs get leakage-level flow (|Q| well under 50 mm^3/s). Rows carry
the summary columns flowfit needs (``seanv_analysis.io.SUMMARY_COLUMNS``) and are
passed through :func:`seanv_analysis.signals.filters.apply_filters`.
"""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np
import pandas as pd

from seanv_analysis.models import ValveModel, side_pressures
from seanv_analysis.signals.filters import apply_filters

__all__ = ["PAPER_LOADS_MPAG", "PAPER_CAMS_DEG", "synthetic_flow_summary"]

#: Load levels of the paper's flow experiments [MPaG] (Fig. 4a)
PAPER_LOADS_MPAG = (0.1, 0.2, 0.3, 0.35, 0.4, 0.45, 0.5)
#: Cam grid [deg]: -40 .. 10 every 2.5 deg
PAPER_CAMS_DEG = tuple(np.round(np.arange(-40.0, 10.0 + 1e-9, 2.5), 3))


def synthetic_flow_summary(model: ValveModel, rig: Any, *, seed: int = 0,
                           sides: Sequence[str] = ("supply", "drain"),
                           loads_mpag: Sequence[float] = PAPER_LOADS_MPAG,
                           cams_deg: Sequence[float] = PAPER_CAMS_DEG, repeats: int = 3,
                           p_supply_mpag: float = 3.3, head_per_load: float = 4.0,
                           head_noise_mpa: float = 0.02, noise_floor_mm3_s: float = 20.0,
                           noise_rel: float = 0.03, friction_drain_load_mpag: float = 0.0,
                           ) -> pd.DataFrame:
    """A filtered per-run summary of a flow-step campaign simulated at summary level.

    Parameters
    ----------
    model : the true valve (z0, C per side)
    rig : rig config (filter thresholds)
    seed : seed of ``numpy.random.default_rng``
    sides, loads_mpag, cams_deg, repeats : the grid (every side x load x cam, ``repeats`` times)
    p_supply_mpag : supply pressure [MPaG]
    head_per_load : head pressure = this x load [MPaG] (+ Gaussian ``head_noise_mpa`` per run)
    noise_floor_mm3_s, noise_rel : flow noise sigma = floor + rel |Q| [mm^3/s]
    friction_drain_load_mpag : drain runs at loads <= this [MPaG] stall
        (friction): |Q| is capped at 300 mm^3/s, as in the paper's low-load drain data

    Returns
    -------
    DataFrame with run_id, kind, side, started_at, run_index, load_mpag,
    cam_deg, cam_measured_deg, q_mm3_s, dp_mpa, p1_mpa, flow_method,
    excluded, excluded_detail (and ``q_true_mm3_s``).
    """
    rng = np.random.default_rng(seed)
    rows = []
    t0 = pd.Timestamp("2026-03-02T09:00:00Z")
    for rep in range(repeats):
        for side in sides:
            for load in loads_mpag:
                for cam in cams_deg:
                    p_head = head_per_load * load + rng.normal(0.0, head_noise_mpa)
                    p1, dp = side_pressures(side, p_supply_mpag, p_head, 0.0)
                    q_true = float(model.side(side).flow(cam, p1, dp))
                    if side == "drain" and load <= friction_drain_load_mpag:
                        q_true = max(q_true, -300.0)
                    sigma = noise_floor_mm3_s + noise_rel * abs(q_true)
                    q = q_true + rng.normal(0.0, sigma)
                    if q_true == 0.0:  # sealed: leakage-level flow only
                        q = rng.normal(0.0, 8.0)
                    rows.append({"run_id": f"{side}-load{load:g}-cam{cam:g}-r{rep}",
                                 "kind": "flow_step", "side": side,
                                 "started_at": t0 + pd.Timedelta(seconds=30 * len(rows)),
                                 "load_mpag": float(load), "cam_deg": float(cam),
                                 "cam_measured_deg": float(cam), "cam_approach": 1.0,
                                 "q_mm3_s": q, "q_peak_mm3_s": q, "q_steady_mm3_s": q,
                                 "dp_mpa": float(dp), "p1_mpa": float(p1),
                                 "flow_method": "steady", "q_true_mm3_s": q_true})
    frame = pd.DataFrame(rows)
    frame.insert(4, "run_index", np.arange(len(frame), dtype=np.int64))
    return apply_filters(frame, rig)
