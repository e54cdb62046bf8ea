"""Does the rig's controller hold the cam once converged?

The paper's flow-model controller holds the cam at 3 deg below the supply
sealing threshold once |e| <= 0.5 mm (rig ``controller.convergence_band_mm``;
Sec. III-B says the valve was "held"). A lab's controller may instead keep
commanding eq. (6) for Kp e however small e is. The logs tell which: inside
the band, the commanded cam either sits at the hold angle or follows
eq. (6) of Kp e at the measured pressures (identified valve). When it
follows eq. (6) the band is 0 (no hold); when it holds, the rig file's band
stays.
"""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from .result import Constant

__all__ = ["controller_constants", "hold_evidence"]


def hold_evidence(run, valve, rig) -> tuple[float, float, int] | None:
    """(median |cam_cmd - hold angle|, median |cam_cmd - eq. 6 of Kp e|) [deg]
    and the number of in-band controller samples of one flow-model run."""
    c = run.meta.controller or {}
    ctrl, servo, enc, pres = (run.tables.get(k) for k in ("controller", "servo", "encoder",
                                                           "pressure"))
    if not c.get("flow_model", True) or ctrl is None or servo is None or enc is None or pres is None:
        return None
    kp = float(c.get("kp") or rig["controller"]["kp_flow_mm3_s_per_mm"])
    band = float(rig["controller"]["convergence_band_mm"])
    hold_below = float(rig["controller"]["hold_below_supply_threshold_deg"])
    t = ctrl["t_s"].to_numpy(float)
    x_ref = ctrl["x_ref_mm"].to_numpy(float)
    x = np.interp(t, enc["t_s"].to_numpy(float), enc["position_mm"].to_numpy(float))
    e = x_ref - x
    ts = servo["t_s"].to_numpy(float)
    k = np.clip(np.searchsorted(ts, t, side="right") - 1, 0, ts.size - 1)
    cmd = servo["cam_cmd_deg"].to_numpy(float)[k]
    tp = pres["t_s"].to_numpy(float)
    ps = np.interp(t, tp, pres["p_supply_mpag"].to_numpy(float))
    ph = np.interp(t, tp, pres["p_head_mpag"].to_numpy(float))
    pt = (np.interp(t, tp, pres["p_tank_mpag"].to_numpy(float)) if "p_tank_mpag" in pres
          else np.zeros_like(t))
    pt = np.where(np.isfinite(pt), pt, 0.0)
    # in the band, and settled: 0.5 s after the last reference change
    changes = t[np.flatnonzero(np.diff(x_ref) != 0) + 1]
    since = t - np.concatenate(([-np.inf], changes))[np.searchsorted(changes, t, side="right")]
    m = (np.abs(e) <= band) & (since > 0.5) & np.isfinite(cmd) & np.isfinite(ps) & np.isfinite(ph)
    if m.sum() < 20:
        return None
    p1, dp = ps[m], ps[m] - ph[m]
    hold = valve.supply.threshold_deg(p1, dp) - hold_below
    eq6 = valve.cam_for_flow(kp * e[m], ps[m], ph[m], pt[m])
    return (float(np.median(np.abs(cmd[m] - hold))), float(np.median(np.abs(cmd[m] - eq6))),
            int(m.sum()))


def controller_constants(runs: Sequence[Any], valve, rig) -> tuple[list[Constant], dict, list[str]]:
    """controller.convergence_band_mm: 0 when the commanded cam follows eq. (6)
    inside the band in the position-control runs, else the rig file's."""
    default = float(rig["controller"]["convergence_band_mm"])
    ev = [h for h in (hold_evidence(r, valve, rig) for r in runs) if h is not None]
    key, name = "controller.convergence_band_mm", "controller hold band"
    if not ev:
        return ([Constant(key, name, default, default, "mm", False, "controller and servo logs",
                          note="no flow-model run with a controller log settles in the band")],
                {}, [])
    d_hold = float(np.median([h[0] for h in ev]))
    d_eq6 = float(np.median([h[1] for h in ev]))
    n = sum(h[2] for h in ev)
    by = (f"{n} settled controller samples inside the band: cam command {d_eq6:.2f} deg from "
          f"eq. (6) of Kp e, {d_hold:.2f} deg from the hold angle")
    fits = {"metric": "median |cam command - law| inside the band [deg]",
            "hold_angle_deg": d_hold, "eq6_deg": d_eq6, "n_samples": n}
    if d_eq6 < 0.5 * d_hold:
        return ([Constant(key, name, 0.0, default, "mm", True, by,
                          note="the controller does not hold: it follows eq. (6) down to e = 0")],
                fits, [])
    return ([Constant(key, name, default, default, "mm", False, by,
                      note="the controller holds as the rig file says")], fits, [])
