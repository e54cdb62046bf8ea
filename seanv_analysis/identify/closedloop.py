"""Re-running position-control runs on a twin, and their flow error.

Two ways to put a logged position-control run on the twin:

- closed loop (:func:`validate_on_twin`): the run's own controller,
  references and loads re-simulated
  (:func:`seanv_analysis.analysis.validate.validate_run`); what ``validate``
  reports. With stick-slip, a hold that ends a few tenths of a millimetre
  elsewhere changes every later command, so this error is a rough function
  of the twin's constants (on the foreign rig: held-out flow fit 62 %, 54 %,
  68 %, 62 %, 66 % for B = 35, 45, 55, 70, 88 MPa);
- open loop (:func:`replay_on_twin`): the twin driven by the cam command
  the rig's controller logged (output error with a measured input, the
  direct approach to closed-loop identification). The same twin's flow fit
  is then a smooth function of its constants (60, 68, 75, 74, 69 %), which
  is what the line's bulk modulus and the dynamic effects are fitted on.

:func:`flow_sse` gives the measured vs simulated actuator flow error of
either, with the residuals' effective sample size.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
import pandas as pd

from ..analysis.validate import pooled_rmse
from .noise import integrated_autocorrelation

__all__ = ["validate_on_twin", "replay_on_twin", "replay_targets", "replay_target", "Replay",
           "ReplayTarget", "flow_sse", "with_bulk", "fit_summary"]


def fit_summary(results, suffix: str = "") -> dict[str, Any]:
    """Pooled numbers of re-runs or replays (each with a ``row`` of
    ``validate_run``'s metrics): ``rmse_flow_mm3_s`` (over the runs' samples:
    :func:`~seanv_analysis.analysis.validate.pooled_rmse`),
    mean ``fit_flow_pct`` and, where every row has it, ``fit_position_pct``,
    and ``runs`` {run_id: {those fits}}. ``suffix`` picks a variant of the
    metrics ('_segments': the per-segment re-runs); {} when there are no
    results or a row lacks a finite flow metric."""
    rows = [r.row for r in results]
    keys = {"fit_flow_pct": f"fit_flow{suffix}_pct", "rmse_flow_mm3_s": f"rmse_flow{suffix}_mm3_s"}
    if not rows or not all(np.isfinite(r.get(k, np.nan)) for r in rows for k in keys.values()):
        return {}
    if all(np.isfinite(r.get(f"fit_position{suffix}_pct", np.nan)) for r in rows):
        keys["fit_position_pct"] = f"fit_position{suffix}_pct"
    out: dict[str, Any] = {
        "rmse_flow_mm3_s": pooled_rmse([r[keys["rmse_flow_mm3_s"]] for r in rows],
                                       [r["n_samples"] for r in rows]),
        **{k: float(np.mean([r[v] for r in rows])) for k, v in keys.items()
           if k.startswith("fit_")}}
    out["runs"] = {r["run_id"]: {k: r[v] for k, v in keys.items() if k.startswith("fit_")}
                   for r in rows}
    return out


def with_bulk(rig, bulk_mpa: float, *, where: str = "identify"):
    """``rig`` with the line's effective bulk modulus ``bulk_mpa`` [MPa]."""
    return rig.with_overrides({"tube": {"effective_bulk_modulus_mpa": float(bulk_mpa)}},
                              where=where)


def validate_on_twin(runs: Sequence[Any], valve, rig, effects: Sequence[str] = ()) -> list[Any]:
    """:func:`~seanv_analysis.analysis.validate.validate_run` of each run on the
    twin ``rig`` with the simulator's ``effects``; runs it cannot re-run are left out."""
    from ..analysis.validate import validate_run
    from ..errors import DataError

    out = []
    for run in runs:
        try:
            out.append(validate_run(run, valve, rig=rig, effects=tuple(effects)))
        except DataError:
            continue
    return out


@dataclass
class Replay:
    """One run replayed open loop on the twin, on the measured time base:
    ``t`` [s], measured and simulated flow ``q``, ``q_sim`` [mm^3/s] (NaN
    outside the simulated span) and position ``x``, ``x_sim`` [mm], each
    sample's segment (the reference step it follows). ``overlay`` (the same
    columns as a table: t_s, q_mm3_s / q_sim_mm3_s, position_mm /
    position_sim_mm) and ``row`` (fit_flow_pct [%], rmse_flow_mm3_s) are
    made when first read: a search that replays a run per twin it tries
    reads neither."""

    run_id: str
    t: np.ndarray = field(repr=False)
    q: np.ndarray = field(repr=False)
    q_sim: np.ndarray = field(repr=False)
    x: np.ndarray = field(repr=False)
    x_sim: np.ndarray = field(repr=False)
    segment: np.ndarray | None = field(default=None, repr=False)

    @property
    def flow_error(self) -> np.ndarray:
        """Measured minus simulated flow [mm^3/s] per sample (NaN where either is)."""
        return self.q - self.q_sim

    @functools.cached_property
    def overlay(self) -> pd.DataFrame:
        return pd.DataFrame({"t_s": self.t, "q_mm3_s": self.q, "q_sim_mm3_s": self.q_sim,
                             "position_mm": self.x, "position_sim_mm": self.x_sim})

    @functools.cached_property
    def row(self) -> dict[str, Any]:
        from ..analysis.validate import fit_percent

        r = self.flow_error
        return {"run_id": self.run_id, "fit_flow_pct": fit_percent(self.q, self.q_sim),
                "rmse_flow_mm3_s": float(np.sqrt(np.nanmean(r * r))),
                "n_samples": int(r.size)}

    def segment_sse(self) -> np.ndarray:
        """Sum of squared flow errors [(mm^3/s)^2] per segment."""
        r = self.flow_error
        ok = np.isfinite(r)
        seg = self.segment if self.segment is not None else np.zeros(r.size, int)
        return np.bincount(seg[ok], weights=r[ok] ** 2, minlength=int(seg.max()) + 1)


@dataclass(frozen=True)
class ReplayTarget:
    """What a replay of one run needs and is compared with, prepared once
    (:func:`replay_target`): the cam command steps and load set-point steps
    [s, deg / MPaG] on a clock starting at the first encoder sample, the
    initial position and duration, and the measured flow and position on
    the measured time base."""

    run_id: str
    cmd: tuple[np.ndarray, np.ndarray]
    load: tuple[np.ndarray, np.ndarray]
    x0_mm: float
    duration_s: float
    t: np.ndarray
    q: np.ndarray
    x: np.ndarray
    #: segment of each sample of ``t``: the reference step it follows (0 before the first)
    segment: np.ndarray | None = None


def replay_target(run, rig) -> ReplayTarget | None:
    """The :class:`ReplayTarget` of a position-control run: its logged cam
    command (the servo identification's command timing,
    :func:`.servo.command_schedule`), its load steps placed for the regulator
    of ``rig``, its measured flow; None when it has no cam command or no
    usable encoder record."""
    from ..analysis.validate import load_steps, reference_steps
    from ..errors import DataError
    from ..signals.derive import derive_samples
    from .servo import command_schedule

    enc = run.tables.get("encoder")
    sched = command_schedule(run)
    if sched is None or enc is None or len(enc) < 10:
        return None
    t0 = float(enc["t_s"].iloc[0])
    ts, cmd = sched[0] - t0, sched[1]
    keep = np.r_[True, np.diff(ts) > 0]
    ts, cmd = ts[keep], cmd[keep]
    try:
        lt, lv = load_steps(run, regulator_tau_s=float(rig["load"]["regulator_time_constant_s"]))
        dm = derive_samples(run)
    except DataError:
        return None
    # on the encoder's clock; changes before its start collapse to t = 0,
    # where the last of them holds
    lt = np.maximum(np.asarray(lt, float) - t0, 0.0)
    lv = np.asarray(lv, float)
    last = np.r_[lt[1:] > lt[:-1], True]
    lt, lv = lt[last], lv[last]
    if ts[0] > 0:
        ts, cmd = np.r_[0.0, ts], np.r_[cmd[0], cmd]
    t = dm["t_s"].to_numpy(float) - t0
    try:
        breaks = np.asarray(reference_steps(run)[0], float)[1:] - t0
    except DataError:
        breaks = np.arange(5.0, t[-1], 5.0)        # no reference log: 5 s blocks
    return ReplayTarget(run.run_id, (ts, cmd), (lt, lv), float(enc["position_mm"].iloc[0]),
                        float(enc["t_s"].iloc[-1]) - t0, t, dm["q_mm3_s"].to_numpy(float),
                        dm["position_mm"].to_numpy(float),
                        np.searchsorted(breaks, t, side="right"))


def replay_run(run, valve, rig, effects: Sequence[str] = ()) -> Replay | None:
    """``run`` (position control, or its prepared :class:`ReplayTarget`)
    replayed on the twin ``rig`` from its logged cam command and load steps,
    from its first logged position; None when it cannot be replayed."""
    from ..signals.derive import derive_flow
    from ..sim.run import simulate_cam_replay

    tg = run if isinstance(run, ReplayTarget) else replay_target(run, rig)
    if tg is None:
        return None
    sim, _ = simulate_cam_replay(rig, cam_cmd=tg.cmd, load=tg.load, duration_s=tg.duration_s,
                                 x0_mm=tg.x0_mm, valve=valve, effects=tuple(effects),
                                 run_id=f"{tg.run_id}-replay")
    ds = derive_flow(sim)    # the numbers of derive_samples
    tsim = np.asarray(ds["t_s"], dtype=float)

    def on_t(col):      # NaN outside the simulated span
        return np.interp(tg.t, tsim, np.asarray(ds[col], dtype=float), left=np.nan, right=np.nan)

    return Replay(tg.run_id, tg.t, np.asarray(tg.q, dtype=float), on_t("q_mm3_s"), tg.x,
                  on_t("position_mm"), tg.segment)


def replay_targets(runs: Sequence[Any], rig) -> list[ReplayTarget]:
    """:func:`replay_target` of each run, those that can be replayed."""
    return [t for t in (replay_target(r, rig) for r in runs) if t is not None]


def replay_on_twin(runs: Sequence[Any], valve, rig, effects: Sequence[str] = ()) -> list[Replay]:
    """:func:`replay_run` of each run (or prepared target); runs it cannot
    replay are left out."""
    out = []
    for run in runs:
        r = replay_run(run, valve, rig, effects)
        if r is not None:
            out.append(r)
    return out


def flow_sse(validations, *, effective: bool = True) -> tuple[float, float, int]:
    """(sum of squared flow errors [(mm^3/s)^2], effective sample count
    (NaN unless ``effective``), samples) of measured vs simulated actuator
    flow, NaN samples left out."""
    sse, n_eff, n = 0.0, 0.0 if effective else float("nan"), 0
    for v in validations:
        r = v.flow_error
        r = r[np.isfinite(r)]
        if r.size < 10:
            continue
        sse += float(np.sum(r * r))
        if effective:
            n_eff += r.size / integrated_autocorrelation(r)
        n += r.size
    return sse, n_eff, n
