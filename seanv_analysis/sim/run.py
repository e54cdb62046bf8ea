"""Simulate one run of the data contract in memory: a flow step or a
closed-loop position-control test.

Both return a :class:`seanv_analysis.io.Run` whose tables are exactly what a
recorded run holds (encoder and pressure at 1 kHz, servo and controller at
100 Hz, engineering units), so every analysis stage can consume it, and
:func:`seanv_analysis.io.write_run` can write it.
"""
from __future__ import annotations

import math
from datetime import datetime, timezone
from functools import lru_cache
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from ..config import RigConfig, load_rig
from ..errors import ConfigError
from ..io.run import Run, RunMeta
from ..models import ValveModel
from ..models.effects import Effect
from . import compiled
from ._config_errors import config_errors
from ._pp import MODE_SCHEDULE, OUT_FAST, OUT_SLOW
from ._signals import Signals, contract_tables
from .control import CamController, FlowModelController
from .plant import Plant

__all__ = ["simulate_flow_step", "simulate_position_control", "simulate_cam_replay", "SimTrace"]

_EPOCH = datetime(2026, 3, 2, 9, 0, 0, tzinfo=timezone.utc)


class SimTrace(dict):
    """True plant signals of a simulated run (not part of the data contract):
    ``x_true_mm``, ``q_true_mm3_s`` at 1 kHz, ``cam_needle_deg`` at 100 Hz,
    ``t_release_s`` of a flow step."""


def _rng(seed: int, run_index: int) -> np.random.Generator:
    return np.random.default_rng([int(seed), int(run_index), 0x5EA7])


#: runs up to this many 1 kHz samples keep their noise draws (3 x 8 bytes each)
_NOISE_CACHE_SAMPLES = 200_000


@lru_cache(maxsize=4)
def _cached_draws(seed: int, run_index: int, n_fast: int) -> np.ndarray:
    draws = _rng(seed, run_index).standard_normal((n_fast, 3))
    draws.flags.writeable = False
    return draws


def _unit_noise(seed: int, run_index: int, n_fast: int) -> np.ndarray:
    """The run's (n_fast, 3) standard-normal pressure-noise draws [-]; a short
    run's are drawn once (read-only, shared): a twin replayed many times with
    one seed (identify's and discover's searches) draws the same numbers."""
    if n_fast > _NOISE_CACHE_SAMPLES:
        return _rng(seed, run_index).standard_normal((n_fast, 3))
    return _cached_draws(int(seed), int(run_index), int(n_fast))


def _steps(seq, name: str) -> tuple[np.ndarray, np.ndarray]:
    """(t, value) step sequence from a number or a pair of sequences."""
    if np.isscalar(seq):
        return np.array([0.0]), np.array([float(seq)])
    t, v = (np.asarray(a, dtype=float) for a in seq)
    if t.ndim != 1 or t.shape != v.shape or t.size == 0:
        raise ConfigError(f"{name}: expected (t_s, values) of equal length >= 1")
    if np.any(np.diff(t) <= 0):
        raise ConfigError(f"{name}: times must be strictly increasing")
    if t[0] > 0:
        t, v = np.r_[0.0, t], np.r_[v[0], v]
    return t, v


def _run(plant: Plant, *, ctrl_kind: int, cp, ctrl_tables, ref, load, cmd, duration_s: float,
         seed: int, run_index: int, x0_mm: float, cam0_deg: float, neutral_deg: float,
         x_stop_mm: tuple[float, float], p0_mpag: float = math.nan,
         hold0_deg: float = math.nan):
    rig = plant.rig
    with config_errors():  # the rig's valve geometry and the effects meet here
        pp = plant.packed_params(neutral_deg=neutral_deg, x_stop_mm=x_stop_mm)
        valve = plant.valve_at(run_index)
        tw = plant.term_at(run_index)
    rate = float(rig["sensors"]["encoder_rate_hz"])
    n_fast = int(round(duration_s * rate)) + 1
    sigma = float(rig["sensors"]["pressure_noise_mpa"])
    noise = _unit_noise(seed, run_index, n_fast) * sigma
    fast, slow, t_release = compiled.simulate_kernel()(
        pp, *valve, tw, ctrl_kind, cp, *ctrl_tables,
        ref[0], ref[1], load[0], load[1], cmd[0], cmd[1], noise, n_fast, float(x0_mm),
        float(cam0_deg), float(p0_mpag), float(hold0_deg))
    if plant.has_terms and not np.all(np.isfinite(fast)):
        specs = ", ".join(e.spec() for e in plant.effects if e.name == "term")
        raise ConfigError(f"term: the plant's state became non-finite with {specs}; the "
                          "expression must stay finite over the run's dp, p1, dtheta, theta, q "
                          "and load")
    return Signals(fast, OUT_FAST), Signals(slow, OUT_SLOW), float(t_release)


def _tables(fast: Signals, slow: Signals, *, controller: bool):
    return contract_tables(fast, slow, controller=controller)  # numpy; DataFrames on demand


def _meta(run_id: str, kind: str, started_at, **fields: Any) -> RunMeta:
    started = started_at or _EPOCH
    return RunMeta(run_id=run_id, kind=kind, started_at=started, path=Path("<sim>") / run_id,
                   **fields)


def simulate_flow_step(rig: RigConfig | None = None, *, side: str, cam_deg: float,
                       load_mpag: float, seed: int = 0, run_index: int = 0,
                       valve: ValveModel | None = None,
                       effects: Iterable[str | Effect | dict] = (), plant: Plant | None = None,
                       approach: int = +1, overshoot_deg: float = 3.0, overshoot_s: float = 0.4,
                       pre_s: float = 0.5, hold_max_s: float = 3.0, post_s: float = 0.3,
                       run_id: str | None = None, started_at: datetime | None = None
                       ) -> tuple[Run, SimTrace]:
    """One flow-step run (paper Sec. II-D.2): the cam steps from the neutral
    angle to ``cam_deg`` and is held while the actuator moves, until it nears
    the end of its stroke or ``hold_max_s`` has passed, then back to neutral.

    Parameters
    ----------
    rig : rig config (default: the shipped one)
    side : 'supply' (actuator starts retracted, extends) or 'drain' (starts
        extended, retracts)
    cam_deg : commanded cam angle [deg]
    load_mpag : pneumatic load pressure [MPaG]
    seed, run_index : noise seed; ``run_index`` is also the "use" count of
        drift-like effects
    valve, effects, plant : the true valve and injected effects (or a ready
        :class:`Plant`)
    approach : +1 the cam reaches ``cam_deg`` from the neutral side; -1 from
        the far side (it overshoots by ``overshoot_deg`` for ``overshoot_s`` first),
        which makes a backlash visible
    pre_s, hold_max_s, post_s : timing of the step [s]

    Returns
    -------
    (Run, SimTrace)
    """
    rig = rig or load_rig()
    if side not in ("supply", "drain"):
        raise ConfigError(f"side: expected 'supply' or 'drain', got {side!r}")
    with config_errors():
        plant = plant or Plant.from_rig(rig, valve=valve, effects=effects)
    neutral = float(rig["servo"]["neutral_deg"])
    stroke = float(rig["actuator"]["stroke_mm"])
    x0, stops = (5.0, (-math.inf, stroke - 5.0)) if side == "supply" else \
        (stroke - 5.0, (5.0, math.inf))
    toward = math.copysign(1.0, cam_deg - neutral) if cam_deg != neutral else 1.0
    if approach < 0:
        over = cam_deg + toward * overshoot_deg
        cmd = (np.array([0.0, pre_s, pre_s + overshoot_s]), np.array([neutral, over, cam_deg]))
    else:
        cmd = (np.array([0.0, pre_s]), np.array([neutral, cam_deg]))
    dummy = CamController.from_rig(rig).jit_spec()
    fast, slow, t_rel = _run(plant, ctrl_kind=MODE_SCHEDULE, cp=dummy[1], ctrl_tables=dummy[2],
                             ref=(np.array([0.0]), np.array([0.0])),
                             load=(np.array([0.0]), np.array([float(load_mpag)])), cmd=cmd,
                             duration_s=pre_s + hold_max_s + post_s, seed=seed,
                             run_index=run_index, x0_mm=x0, cam0_deg=neutral,
                             neutral_deg=neutral, x_stop_mm=stops)
    if math.isfinite(t_rel):
        end = t_rel + post_s
        fast, slow = fast[fast["t_s"] <= end + 1e-9], slow[slow["t_s"] <= end + 1e-9]
    rid = run_id or f"{side}-load{load_mpag:g}-cam{cam_deg:g}-i{run_index}"
    meta = _meta(rid, "flow_step", started_at, load_mpag=float(load_mpag), side=side,
                 cam_deg=float(cam_deg))
    trace = SimTrace(x_true_mm=fast["x_true_mm"], q_true_mm3_s=fast["q_true_mm3_s"],
                     cam_needle_deg=slow["cam_needle_deg"], t_release_s=t_rel)
    return Run(meta=meta, tables=_tables(fast, slow, controller=False), rig=rig), trace


def simulate_position_control(rig: RigConfig | None = None, *,
                              controller: FlowModelController | CamController,
                              x_ref, load, duration_s: float, seed: int = 0,
                              valve: ValveModel | None = None,
                              effects: Iterable[str | Effect | dict] = (),
                              plant: Plant | None = None, x0_mm: float = 0.0,
                              run_index: int = 0, run_id: str = "sim",
                              started_at: datetime | None = None,
                              cam0_deg: float | None = None,
                              p0_mpag: float | None = None,
                              hold_deg: float | None = None) -> tuple[Run, SimTrace]:
    """One closed-loop position-control run (paper Sec. III) on the plant.

    Parameters
    ----------
    rig : rig config (default: the shipped one)
    controller : the paper's controller with its valve model
        (:class:`~seanv_analysis.sim.control.FlowModelController`) or without
        (:class:`~seanv_analysis.sim.control.CamController`)
    x_ref : position reference, a number or (t_s, x_ref_mm) steps
    load : load pressure set point, a number or (t_s, p_mpag) steps
    duration_s : length of the run [s]
    seed : noise seed
    valve, effects, plant : the true valve and injected effects
    x0_mm : initial position [mm]
    cam0_deg : initial servo angle (and command) [deg]; default the servo's neutral
    p0_mpag : initial line and head pressure [MPaG]; default the pressure
        that balances the initial load (a run re-started from a logged state
        gives both)
    hold_deg : the controller starts holding this cam angle [deg] (it had
        converged on the initial reference); default: it starts free

    Returns
    -------
    (Run, SimTrace)
    """
    rig = rig or load_rig()
    with config_errors():
        plant = plant or Plant.from_rig(rig, valve=valve, effects=effects)
    kind, cp, tables = controller.jit_spec()
    ref, ld = _steps(x_ref, "x_ref"), _steps(load, "load")
    neutral = float(rig["servo"]["neutral_deg"])
    fast, slow, _ = _run(plant, ctrl_kind=kind, cp=cp, ctrl_tables=tables, ref=ref, load=ld,
                         cmd=(np.array([0.0]), np.array([neutral])), duration_s=duration_s,
                         seed=seed, run_index=run_index, x0_mm=x0_mm,
                         cam0_deg=neutral if cam0_deg is None else float(cam0_deg),
                         neutral_deg=neutral, x_stop_mm=(-math.inf, math.inf),
                         p0_mpag=math.nan if p0_mpag is None else float(p0_mpag),
                         hold0_deg=math.nan if hold_deg is None else float(hold_deg))
    load_meta = float(ld[1][0]) if ld[1].size == 1 else None
    meta = _meta(run_id, "position_control", started_at, load_mpag=load_meta,
                 controller=controller.run_json())
    trace = SimTrace(x_true_mm=fast["x_true_mm"], q_true_mm3_s=fast["q_true_mm3_s"],
                     cam_needle_deg=slow["cam_needle_deg"], t_release_s=math.nan)
    return Run(meta=meta, tables=_tables(fast, slow, controller=True), rig=rig), trace


def simulate_cam_replay(rig: RigConfig | None = None, *, cam_cmd, load, duration_s: float,
                        x0_mm: float, seed: int = 0, valve: ValveModel | None = None,
                        effects: Iterable[str | Effect | dict] = (), plant: Plant | None = None,
                        run_id: str = "replay", started_at: datetime | None = None
                        ) -> tuple[Run, SimTrace]:
    """The plant driven open loop by a logged cam command (no controller).

    Output-error identification of closed-loop data: the servo, needle, line
    and actuator of the twin see the command the rig's controller actually
    sent, so the simulated flow does not inherit the closed loop's sensitivity
    to small differences (a hold that ends a few tenths of a millimetre
    elsewhere changes every later command of a re-run controller).

    Parameters
    ----------
    rig : rig config (default: the shipped one)
    cam_cmd : (t_s, cam command [deg]) steps, e.g. the servo log's ``cam_cmd_deg``
    load : load pressure set point, a number or (t_s, p_mpag) steps
    duration_s : length of the run [s]
    x0_mm : initial position [mm] (no end stops, as in position control)
    seed, valve, effects, plant : as :func:`simulate_position_control`

    Returns
    -------
    (Run, SimTrace): a ``position_control`` run without controller table
    """
    rig = rig or load_rig()
    with config_errors():
        plant = plant or Plant.from_rig(rig, valve=valve, effects=effects)
    cmd, ld = _steps(cam_cmd, "cam_cmd"), _steps(load, "load")
    neutral = float(rig["servo"]["neutral_deg"])
    dummy = CamController.from_rig(rig).jit_spec()
    fast, slow, _ = _run(plant, ctrl_kind=MODE_SCHEDULE, cp=dummy[1], ctrl_tables=dummy[2],
                         ref=(np.array([0.0]), np.array([0.0])), load=ld, cmd=cmd,
                         duration_s=duration_s, seed=seed, run_index=0, x0_mm=x0_mm,
                         cam0_deg=float(cmd[1][0]), neutral_deg=neutral,
                         x_stop_mm=(-math.inf, math.inf))
    load_meta = float(ld[1][0]) if ld[1].size == 1 else None
    meta = _meta(run_id, "position_control", started_at, load_mpag=load_meta,
                 controller={"replay": True})
    trace = SimTrace(x_true_mm=fast["x_true_mm"],
                     q_true_mm3_s=fast["q_true_mm3_s"],
                     cam_needle_deg=slow["cam_needle_deg"], t_release_s=math.nan)
    return Run(meta=meta, tables=_tables(fast, slow, controller=False), rig=rig), trace
