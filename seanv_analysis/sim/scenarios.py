"""Built-in scenarios: whole data sets written in the data-contract layout.

========================  ==================================================
scenario                  what it writes
========================  ==================================================
``paper-flowsteps``       flow-step runs over the paper's grid (Sec. II-D.2):
                          both sides, cam -42.5..12.5 deg every 2.5 deg,
                          loads 0.1..0.5 MPaG, three sweeps per load (the
                          second approaching each angle from the far side),
                          in time order: 345 runs
``paper-flowsteps-small`` the same every 5 deg, loads 0.2..0.5: 144 runs
``paper-position``        position control (Sec. III-C): reference 0 mm for
                          5 s, then 30, 15, 30, 33, 30, 0 mm every 15 s, load
                          0.35 / 0.45 MPaG alternating every 15 s; one run
                          with the flow model, one without
``paper-position-model``  only the run with the flow model
========================  ==================================================

Effects (``--effect``) act on the plant of every run; the truth goes to
``<out>/_truth.json`` only when asked for.
"""
from __future__ import annotations

from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone
from pathlib import Path
from typing import Callable, Iterable, Iterator

import numpy as np

from ..config import RigConfig, load_rig
from ..errors import ConfigError
from ..io import Run, write_json_atomic, write_run
from ..models import ValveModel
from ..models.effects import Effect
from ._config_errors import config_errors
from .control import CamController, FlowModelController
from .plant import Plant
from .run import simulate_flow_step, simulate_position_control

__all__ = ["PAPER_DRAIN_DRIFT", "SCENARIOS", "simulate_scenario", "iter_scenario_runs", "scenario_size", "flowstep_grid",
           "paper_position_profile"]

_START = datetime(2026, 3, 2, 9, 0, 0, tzinfo=timezone.utc)

#: The drift the paper saw on the drain side (Sec. II-D.2, Fig. 4(a): "the
#: drain-side flow rate decreased slightly every three measurements"): C
#: falls 0.5 % every three runs, to 56 % of its first value over the 345
#: runs of ``paper-flowsteps``. (The effect's default 5 % step would leave
#: the drain side without flow after ~100 runs.)
PAPER_DRAIN_DRIFT = "drift:side=drain,step=0.005,every=3"


@dataclass(frozen=True)
class FlowStep:
    side: str
    cam_deg: float
    load_mpag: float
    approach: int


def flowstep_grid(*, small: bool = False) -> list[FlowStep]:
    """The paper-style flow-step protocol in time order.

    For each load: three sweeps over both sides' cam angles (supply -15..12.5,
    drain -42.5..-17.5 deg, 2.5 deg apart; 5 deg when ``small``); the second
    sweep reaches each angle from the far side. Cam angles just outside the
    model's range (-42.5, 12.5) and loads <= 0.2 MPaG give the filters work.
    """
    step = 5.0 if small else 2.5
    supply = np.arange(-15.0, 12.5 + 1e-9, step)
    drain = np.arange(-42.5, -17.5 + 1e-9, step)
    loads = (0.2, 0.3, 0.4, 0.5) if small else (0.1, 0.2, 0.3, 0.4, 0.5)
    out = []
    for load in loads:
        for rep in range(3):
            approach = -1 if rep == 1 else +1
            out += [FlowStep("supply", float(c), load, approach) for c in supply]
            out += [FlowStep("drain", float(c), load, approach) for c in drain]
    return out


def paper_position_profile() -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray], float]:
    """Reference and load steps of the paper's position-control test (Sec. III-C)
    and its duration [s]: x_ref 0 mm for 5 s, then 30, 15, 30, 33, 30, 0 mm
    every 15 s; load 0.35 / 0.45 MPaG alternating every 15 s."""
    refs = [0.0, 30.0, 15.0, 30.0, 33.0, 30.0, 0.0]
    t_ref = np.array([0.0] + [5.0 + 15.0 * k for k in range(6)])
    loads = [0.35 if k % 2 == 0 else 0.45 for k in range(7)]
    t_load = np.array([0.0] + [5.0 + 15.0 * k for k in range(1, 7)])
    return (t_ref, np.array(refs)), (t_load, np.array(loads[:7])), 5.0 + 15.0 * 6


def _flowstep_runs(plant: Plant, *, seed: int, small: bool) -> Iterator[Run]:
    t = _START
    last_load = None
    for i, step in enumerate(flowstep_grid(small=small)):
        if last_load is not None and step.load_mpag != last_load:
            t += timedelta(seconds=60)   # the operator sets a new load
        last_load = step.load_mpag
        rid = f"{i:04d}-{step.side}-load{step.load_mpag:.2f}-cam{step.cam_deg:+.1f}"
        run, _ = simulate_flow_step(plant.rig, side=step.side, cam_deg=step.cam_deg,
                                    load_mpag=step.load_mpag, seed=seed, run_index=i, plant=plant,
                                    approach=step.approach, run_id=rid, started_at=t)
        yield run
        t += timedelta(seconds=float(run.tables.columns("encoder")["t_s"][-1]) + 8.0)


def _position_runs(plant: Plant, *, seed: int, which: Iterable[str]) -> Iterator[Run]:
    """The position-control runs, simulated side by side on threads (the
    kernel runs without the GIL; each run is computed alone), in order."""
    rig = plant.rig
    ref, load, duration = paper_position_profile()

    def one(i: int, name: str) -> Run:
        ctrl = FlowModelController.from_rig(rig) if name == "model" else CamController.from_rig(rig)
        rid = f"position-{'with' if name == 'model' else 'without'}-flow-model"
        run, _ = simulate_position_control(
            rig, controller=ctrl, x_ref=ref, load=load, duration_s=duration, seed=seed,
            plant=plant, run_index=i, run_id=rid,
            started_at=_START + i * timedelta(seconds=duration + 120.0))
        return run

    which = list(which)
    with ThreadPoolExecutor(max_workers=max(len(which), 1),
                            thread_name_prefix="seanv-sim") as pool:
        futures = [pool.submit(one, i, name) for i, name in enumerate(which)]
        for f in futures:
            yield f.result()


def scenario_size(name: str) -> int:
    """Number of runs a scenario writes."""
    if name.startswith("paper-flowsteps"):
        return len(flowstep_grid(small=name.endswith("small")))
    return 1 if name == "paper-position-model" else 2


def iter_scenario_runs(name: str, *, seed: int = 0, effects: Iterable[str | Effect | dict] = (),
                       rig: RigConfig | None = None, valve: ValveModel | None = None,
                       plant: Plant | None = None) -> Iterator[Run]:
    """The runs of a scenario in time order, in memory (nothing written).

    Same runs, bit for bit, as :func:`simulate_scenario` writes.
    """
    if name not in SCENARIOS:
        raise ConfigError(f"scenario: unknown {name!r}; expected one of {', '.join(SCENARIOS)}")
    with config_errors():
        plant = plant or Plant.from_rig(rig or load_rig(), valve=valve, effects=effects)
    if name.startswith("paper-flowsteps"):
        return _flowstep_runs(plant, seed=seed, small=name.endswith("small"))
    which = ("model",) if name == "paper-position-model" else ("model", "cam")
    return _position_runs(plant, seed=seed, which=which)


#: runs written at once on helper threads by :func:`simulate_scenario`
_WRITERS = 2

SCENARIOS: dict[str, str] = {
    "paper-flowsteps": "flow steps over the paper's grid, both sides, 5 loads, 3 sweeps (345 runs)",
    "paper-flowsteps-small": "flow steps on a coarser grid (5 deg, 4 loads, 3 sweeps; 144 runs)",
    "paper-position": "position control, paper's reference and loads, with and without flow model",
    "paper-position-model": "position control with the flow model only",
}


def simulate_scenario(name: str, out_dir: str | Path, *, seed: int = 0,
                      effects: Iterable[str | Effect | dict] = (), rig: RigConfig | None = None,
                      valve: ValveModel | None = None, write_truth: bool = False,
                      fmt: str = "csv", progress: Callable[[int, int], None] | None = None) -> Path:
    """Simulate a built-in scenario and write it as a data set.

    Parameters
    ----------
    name : one of :data:`SCENARIOS`
    out_dir : data set folder to create (must not hold runs already)
    seed : noise seed; the same seed gives the same files bit for bit
    effects : injected plant effects (``"drift:side=drain,step=0.05,every=3"``)
    rig, valve : rig config and true valve (defaults: shipped rig, paper's fit)
    write_truth : also write ``_truth.json`` (plant parameters and effects)
    fmt : 'csv' or 'parquet'
    progress : callback(done, total) after each run

    Returns
    -------
    Path of the data set.

    Raises
    ------
    ConfigError
        unknown scenario, bad effect, or ``out_dir`` already holds run folders.
    """
    if name not in SCENARIOS:
        raise ConfigError(f"scenario: unknown {name!r}; expected one of {', '.join(SCENARIOS)}")
    rig = rig or load_rig()
    with config_errors():
        plant = Plant.from_rig(rig, valve=valve, effects=effects)
    out = Path(out_dir)
    if out.exists() and any(out.rglob("run.json")):
        raise ConfigError(f"out: {out} already holds runs; choose an empty folder")
    out.mkdir(parents=True, exist_ok=True)
    ids = []
    total = scenario_size(name)
    # each run is written on a helper thread while the next one is simulated
    # (the kernel, the rounding and Arrow's CSV writer run without the GIL);
    # at most _WRITERS runs wait to be written, and write errors are raised
    # in run order
    with ThreadPoolExecutor(max_workers=_WRITERS, thread_name_prefix="seanv-write") as pool:
        pending: deque[Future] = deque()
        written = 0

        def finish_one() -> None:
            nonlocal written
            pending.popleft().result()
            written += 1
            if progress:
                progress(written, total)

        for run in iter_scenario_runs(name, seed=seed, plant=plant):
            pending.append(pool.submit(write_run, out / run.run_id, run.meta.to_json_dict(),
                                       run.tables, fmt=fmt))
            ids.append(run.run_id)
            while len(pending) > _WRITERS or (pending and pending[0].done()):
                finish_one()
        while pending:
            finish_one()
    if write_truth:
        write_json_atomic(out / "_truth.json", {
            "scenario": name, "seed": seed, "runs": ids, **plant.truth()})
    return out
