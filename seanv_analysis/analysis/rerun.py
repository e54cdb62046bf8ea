"""Closed-loop re-run per segment: the twin re-started from the logged state
at each change of the run's inputs (multiple shooting).

A free re-run of a whole position-control run (:func:`.validate.validate_run`)
carries every difference forward: with stick-slip, where a hold ends is
decided by a few hundredths of a millimetre, and on which side of its
friction band the piston sticks (the head pressure, anywhere within
+-F_s / A of the load's) decides how the next load change or step moves it.
A free re-run's error after the first hold is then mostly that carried-over
state, not the twin's response to the inputs.

Here the run is cut just before each reference step and each load change
where the rig is at rest (piston still, servo still: :func:`segment_starts`),
and each segment is re-run closed loop on the twin from the rig's logged
state there: position (encoder), line and head pressure (head pressure
sensor, all tube nodes at it, piston at rest), servo angle (servo
feedback) and the controller's hold (held at the logged command when the
logged position had converged on the reference, :func:`_holding`), with
the segment's own reference and load steps. A change without such a rest
before it (a hunting loop) continues the segment before it. The
controller is in the loop, so the twin's response to each input change is
tested as ``validate`` does, but no segment inherits another's end state. This is the simulation from a
measured initial state per experiment of system identification practice
(MATLAB ``compare`` with estimated initial conditions per segment;
multiple shooting).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import pandas as pd

__all__ = ["segment_starts", "SegmentRerun", "rerun_segments", "DEFAULT_LEAD_S"]

#: a segment starts this long before the input change it follows [s]
DEFAULT_LEAD_S = 0.1
#: changes closer than this to each other or to the run's ends start no segment [s]
_MIN_SEGMENT_S = 0.5
#: at rest: |Q| at most the rig's leakage limit (``analysis.leakage_flow_mm3_s``) ...
#: ... over this long [s] ...
_REST_S = 0.2
#: ... with the servo angle within this [deg] (it holds the state the logs do not give:
#: the piston's speed, the pressures along the line, commands in flight)
_CAM_STILL_DEG = 0.5
#: how far before a change [s] (beyond the lead) a rest is looked for, and in which steps
_SEARCH_S = 2.0
_SEARCH_STEP_S = 0.05
#: the head pressure at a segment's start: median over this window before it [s]
_P0_WINDOW_S = 0.03


def segment_starts(t: np.ndarray, q: np.ndarray, cam: np.ndarray, changes: Sequence[float], *,
                   rest_mm3_s: float, lead_s: float = DEFAULT_LEAD_S) -> np.ndarray:
    """Start times [s] of the segments of a run sampled at ``t`` [s], with
    actuator flow ``q`` [mm^3/s] and servo angle ``cam`` [deg], whose inputs
    change at ``changes`` [s]: the first sample, then, for each change, the
    latest instant between ``lead_s`` and ``lead_s`` + :data:`_SEARCH_S`
    before it where the rig is at rest (over the :data:`_REST_S` before it
    |q| <= ``rest_mm3_s`` and the servo still within :data:`_CAM_STILL_DEG`;
    a state the logs give whole). A change with no such instant (the rig
    moving, e.g. a hunting loop) starts no segment, nor does one within
    :data:`_MIN_SEGMENT_S` of the previous start or of the run's end."""
    t, q, cam = (np.asarray(a, float) for a in (t, q, cam))
    qa = np.where(np.isfinite(q), np.abs(q), np.inf)
    out = [float(t[0])]
    for c in np.sort(np.asarray(changes, float)):
        for a in np.arange(c - lead_s, c - lead_s - _SEARCH_S, -_SEARCH_STEP_S):
            if a - out[-1] < _MIN_SEGMENT_S or t[-1] - a < _MIN_SEGMENT_S:
                break
            w = (t >= a - _REST_S) & (t <= a)
            cw = cam[w][np.isfinite(cam[w])]
            if w.sum() >= 3 and qa[w].max() <= rest_mm3_s and (
                    cw.size == 0 or np.ptp(cw) <= _CAM_STILL_DEG):
                out.append(float(a))
                break
    return np.asarray(out)


def _from(t: np.ndarray, v: np.ndarray, a: float) -> tuple[np.ndarray, np.ndarray]:
    """The step sequence (t, v) seen from time ``a``: the value holding at
    ``a`` at 0, then the later steps, on a clock starting at ``a``."""
    i = max(int(np.searchsorted(t, a, side="right")) - 1, 0)
    later = t > a
    return np.r_[0.0, t[later] - a], np.r_[v[i], v[later]]


@dataclass(frozen=True)
class SegmentRerun:
    """Position [mm] and actuator flow [mm^3/s] of the segment re-runs on the
    measured time base (NaN outside the re-run span), and the segment starts [s]."""

    position_mm: np.ndarray
    q_mm3_s: np.ndarray
    starts_s: np.ndarray

    @property
    def n_segments(self) -> int:
        return int(self.starts_s.size)


def _holding(controller, t: np.ndarray, x: np.ndarray, ref_t: np.ndarray, ref_v: np.ndarray,
             a: float) -> bool:
    """Whether the paper's controller holds its cam at ``a`` [s]: the
    position came within its convergence band of the reference set last
    before ``a`` and has not left the release band since (the rule of
    :func:`~seanv_analysis.sim.control.controller_step`, on the logged
    position)."""
    band = getattr(controller, "convergence_band_mm", None)
    if band is None or not band > 0:
        return False
    i = max(int(np.searchsorted(ref_t, a, side="right")) - 1, 0)
    w = (t >= ref_t[i]) & (t <= a) & np.isfinite(x)
    e = np.abs(ref_v[i] - x[w])
    inside = np.flatnonzero(e <= band)
    if inside.size == 0:
        return False
    release = getattr(controller, "release_band_mm", None)
    return release is None or not bool(np.any(e[inside[0]:] > release))


def rerun_segments(measured: pd.DataFrame, *, simulate: Callable, rig, controller,
                   reference: tuple[np.ndarray, np.ndarray],
                   load: tuple[np.ndarray, np.ndarray], valve, effects: Sequence = (),
                   seed: int = 0, run_id: str = "segment",
                   lead_s: float = DEFAULT_LEAD_S, ticks: np.ndarray | None = None
                   ) -> SegmentRerun:
    """Re-run each segment of a position-control run closed loop on the twin.

    Parameters
    ----------
    measured : the run's derived samples (:func:`~seanv_analysis.signals.derive.derive_samples`):
        t_s [s], position_mm [mm], p_head_mpag [MPaG], cam_deg (or cam_cmd_deg) [deg]
    simulate : :func:`~seanv_analysis.sim.run.simulate_position_control` (it
        takes the initial state: ``x0_mm``, ``cam0_deg``, ``p0_mpag``, ``hold_deg``)
    rig, controller, valve, effects, seed : the twin, as the free re-run has them
    reference, load : the run's (t [s], x_ref [mm]) and (t [s], load set
        point [MPaG]) step sequences, on the measured clock
    lead_s : a segment starts this long before the change it follows [s]
    ticks : the controller's logged instants [s]: each segment starts on
        one (the twin's controller ticks from the segment's start, so its
        steps fall where the rig's did, not up to a period later)
    """
    from ..signals.derive import derive_columns

    t = measured["t_s"].to_numpy(float)
    x = measured["position_mm"].to_numpy(float)
    ph = measured["p_head_mpag"].to_numpy(float) if "p_head_mpag" in measured \
        else np.full(t.size, np.nan)
    cam_col = "cam_deg" if "cam_deg" in measured else "cam_cmd_deg"
    cam = measured[cam_col].to_numpy(float) if cam_col in measured else np.full(t.size, np.nan)
    cmd = measured["cam_cmd_deg"].to_numpy(float) if "cam_cmd_deg" in measured else cam
    ref_t, ref_v = (np.asarray(a, float) for a in reference)
    load_t, load_v = (np.asarray(a, float) for a in load)
    q = measured["q_mm3_s"].to_numpy(float)
    starts = segment_starts(t, q, cam, np.r_[ref_t[1:], load_t[1:]], lead_s=lead_s,
                            rest_mm3_s=float(rig.analysis["leakage_flow_mm3_s"]))
    if ticks is not None and np.size(ticks):
        tk = np.sort(np.asarray(ticks, float))
        i = np.searchsorted(tk, starts[1:], side="right") - 1
        starts[1:] = np.where(i >= 0, tk[np.maximum(i, 0)], starts[1:])
        starts = np.unique(starts)
    ends = np.r_[starts[1:], t[-1]]
    x_sim, q_sim = np.full(t.size, np.nan), np.full(t.size, np.nan)
    for k, (a, b) in enumerate(zip(starts, ends)):
        i = min(int(np.searchsorted(t, a)), t.size - 1)
        w = (t >= a - _P0_WINDOW_S) & (t <= a) & np.isfinite(ph)
        p0 = float(np.median(ph[w])) if w.any() else None
        cam0 = float(cam[i]) if math.isfinite(cam[i]) else None
        hold = _holding(controller, t, x, ref_t, ref_v, a) and math.isfinite(cmd[i])
        sim = simulate(rig, controller=controller, x_ref=_from(ref_t, ref_v, a),
                       load=_from(load_t, load_v, a), duration_s=float(b - a) + 0.01,
                       seed=seed, valve=valve, effects=tuple(effects), x0_mm=float(x[i]),
                       cam0_deg=cam0, p0_mpag=p0, hold_deg=float(cmd[i]) if hold else None,
                       run_id=f"{run_id}-seg{k}")
        sim = sim[0] if isinstance(sim, tuple) else sim
        ds, _ = derive_columns(sim)         # numpy: the same numbers as derive_samples
        ts = np.asarray(ds["t_s"], float) + a
        m = (t >= a) & (t < b) if k + 1 < starts.size else (t >= a) & (t <= b)
        m &= t <= ts[-1]
        x_sim[m] = np.interp(t[m], ts, np.asarray(ds["position_mm"], float))
        q_sim[m] = np.interp(t[m], ts, np.asarray(ds["q_mm3_s"], float))
    return SegmentRerun(x_sim, q_sim, starts)
