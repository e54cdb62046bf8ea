"""Identify the rig's unpublished constants from its own logs.

Order (each part uses what the ones before found):

0. the supply pressure the runs were made at (logged; the twin runs at it),
   and the controller's law (:mod:`.controller`: gain, hold band, hold
   angle, latch or release, cam limits, from its logs);
1. needle geometry (:mod:`.geometry`): the sealing threshold's dependence
   on the pressures, from the flow steps; then z0 and C refitted with it
   (flowfit's joint fit, bootstrap intervals);
2. servo (:mod:`.servo`): dead time, time constant, rate limit from the
   servo logs of the position-control runs (of the flow steps when there are
   none), by simulation error with the simulator's own servo step (it needs
   nothing the parts before find: it runs beside them, on a thread or, given
   the executor's task mapper, a worker process);
3. friction (:mod:`.friction`): Coulomb and viscous from the flow steps'
   steady force balance;
4. load regulator (:mod:`.load`): its time constant from the load changes
   logged in the position-control runs;
5. flow path (:mod:`.flowpath`): the lag from valve flow to actuator flow in
   position control, and the line's bulk modulus that makes the twin,
   driven by the logged cam command, move like the rig.

Runs are split into training and held-out ones (position-control runs in
time order, every other one held out; flow steps: every third); the fits
report both, with the rig file's constants and with the identified ones.
"""
from __future__ import annotations

import math
import warnings
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, Callable, Sequence

import pandas as pd

from ..discover.split import split_position_runs as split_runs
from ..estimate import widen_interval
from ..fit.flowfit import C_KEY
from ..models import SIDES
from .controller import controller_constants
from .flowpath import closed_loop_fits, flow_path_constants
from .friction import friction_constants
from .geometry import geometry_constants
from .load import load_constants
from .result import Constant, Identification, nest_constants
from .servo import servo_constants, servo_data

__all__ = ["identify_rig", "PARTS", "split_runs", "TaskMapper"]

#: ``map_tasks(func, items, *, kwargs, desc) -> [(ok, value or one-line
#: error)]``: the executor's task mapper (:class:`seanv_analysis.stages.TaskMapper`:
#: worker processes or Dask), on which identify runs its independent fits
TaskMapper = Callable[..., list]

#: the parts of the rig ``identify`` looks at, in order
PARTS = ("geometry", "servo", "friction", "load", "flow_path")

#: how each part obtains its constants (an estimate's ``method``, where the
#: part does not say more itself)
PART_METHODS = {
    "supply": "logged supply pressure: a line p1 = p_0 - k Q through the supply flow steps' "
              "steady (Q, p1) (intervals from its standard errors), else the median over "
              "runs (bootstrap interval)",
    "geometry": "the sealing threshold's dependence on the pressures in the flow steps "
                "(eq. 3-4)",
    "controller": "the controller's law read off its logged ticks",
    "servo": "simulation error of the simulator's servo step against the logged servo "
             "feedback (training runs)",
    "friction": "steady force balance of the flow steps",
    "load": "the load regulator's time constant from the load changes logged in position "
            "control",
    "flow_path": "the twin driven by the logged cam command: lag from valve to actuator "
                 "flow and the line's constants by simulation error",
    "mass": "not fitted: m a against the friction in the logged accelerations",
}


def identify_rig(summary: pd.DataFrame, rig, *, position_runs: Sequence[Any] = (),
                 flow_runs: Sequence[Any] = (), parts: Sequence[str] = PARTS,
                 n_boot: int = 100, seed: int = 0, log=lambda msg: None,
                 map_tasks: TaskMapper | None = None) -> Identification:
    """Identify the rig constants the paper does not publish.

    Parameters
    ----------
    summary : the data set's per-run summary with the filters applied
        (``stages.dataset.run(...).summary``)
    rig : the rig config the data were read with (its values are the
        starting point and stay for what the data cannot tell)
    position_runs : position-control runs (:class:`~seanv_analysis.io.run.Run`)
    flow_runs : flow-step runs, used for the servo only when no
        position-control run has servo feedback
    parts : which of :data:`PARTS` to identify
    n_boot : bootstrap resamples of the z0/C refit
    map_tasks : the executor's task mapper (worker processes or Dask): the
        servo's fit and the flow fits of the geometry part (the refit and
        y_c's interval edges) run there as tasks, beside this process; the
        same numbers as without (None: all here, the servo on a thread)

    Returns
    -------
    Identification
    """
    unknown = set(parts) - set(PARTS)
    if unknown:
        raise ValueError(f"parts: unknown {sorted(unknown)}; expected some of {list(PARTS)}")
    train_pos, held_pos = split_runs(position_runs)
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="seanv-servo") as pool:
        # the servo's fit reads its logs and the rig file's servo section
        # only: it runs beside the geometry's, its result taken in its place
        servo = pool.submit(_servo_part, train_pos, held_pos, flow_runs, rig, map_tasks) \
            if "servo" in parts else None
        return _identify(summary, rig, position_runs, train_pos, held_pos, parts, n_boot, seed,
                         log, servo, map_tasks)


def _on_tasks(map_tasks: TaskMapper | None, func: Callable, items: Sequence[Any],
              kwargs: dict[str, Any], desc: str) -> list:
    """``[func(x, **kwargs) for x in items]``, as tasks on ``map_tasks``
    where given (None: here). The warnings a task gave are given again here
    (a command or the batch records them, as those of the work done here).
    A task that failed there is run again here, so its error is the
    exception this process raises, as without tasks."""
    if map_tasks is None:
        return [func(x, **kwargs) for x in items]
    done = map_tasks(_warned, list(items), kwargs={"task": func, **kwargs}, desc=desc)
    out = []
    for x, (ok, v) in zip(items, done):
        if not ok:
            out.append(func(x, **kwargs))
            continue
        value, caught = v
        for category, message in caught:
            warnings.warn(message, category, stacklevel=2)
        out.append(value)
    return out


def _warned(item: Any, *, task: Callable, **kwargs) -> tuple[Any, list[tuple[type, str]]]:
    """Task wrapper: (``task(item, **kwargs)``, the warnings it gave as
    (category, message))."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        value = task(item, **kwargs)
    return value, [(w.category, str(w.message)) for w in caught]


def _servo_task(data: tuple[list, list], *, rig) -> tuple:
    """Task: :func:`.servo.servo_constants` of (training, held-out) servo data."""
    return servo_constants(data[0], data[1], rig)


def _flow_fit_task(item: tuple[Any, int, int], *, summary: pd.DataFrame):
    """Task: flowfit of ``summary`` with item = (rig, n_boot, seed)."""
    from ..fit import fit_flow

    rig, n_boot, seed = item
    return fit_flow(summary, rig, n_boot=n_boot, seed=seed)


def _servo_part(train_pos: Sequence[Any], held_pos: Sequence[Any], flow_runs: Sequence[Any],
                rig, map_tasks: TaskMapper | None = None) -> tuple[tuple, list[str]]:
    """The servo's (constants, fits, notes) and the notes said before them;
    its fit a task on ``map_tasks`` where given."""
    tr = [d for d in (servo_data(r) for r in train_pos) if d is not None]
    he = [d for d in (servo_data(r) for r in held_pos) if d is not None]
    before = []
    if not tr:
        steps = [d for d in (servo_data(r) for r in flow_runs) if d is not None]
        tr, he = steps[0::2][:40], steps[1::2][:20]
        if tr:
            before.append("servo: from the flow steps' logs (no position-control run with "
                          "cam feedback); the command instant is known to half a servo "
                          "sample only")
    (found,) = _on_tasks(map_tasks, _servo_task, [(tr, he)], {"rig": rig}, "identify: servo")
    return found, before


def _identify(summary: pd.DataFrame, rig, position_runs: Sequence[Any],
              train_pos: Sequence[Any], held_pos: Sequence[Any], parts: Sequence[str],
              n_boot: int, seed: int, log, servo: Future | None,
              map_tasks: TaskMapper | None = None) -> Identification:
    """:func:`identify_rig`'s parts in order; ``servo``: the servo's part,
    running; ``map_tasks``: where the geometry part's flow fits run."""
    from ..errors import FitError
    from ..fit import fit_flow
    from ..models import ValveModel

    constants: list[Constant] = []
    fits: dict[str, Any] = {}
    notes: list[str] = []
    current = rig
    model = None

    def take(part: str, found) -> Any:
        """Keep a part's (constants, fits, notes); the twin with its identified keys."""
        c, f, n = found
        _say_how(c, part)
        constants.extend(c)
        fits[part] = f
        notes.extend(n)
        return current.with_overrides(nest_constants(c), where="identify")

    supply = _say_how(_supply_pressure(summary, position_runs, rig), "supply")
    if supply:
        constants.extend(supply)
        current = current.with_overrides(nest_constants(supply), where="identify")
    has_steps = bool((summary["kind"] == "flow_step").any())
    base_fit = None
    if "geometry" in parts and has_steps:
        log("identify: needle geometry from the flow steps")
        try:
            base_fit = fit_flow(summary, rig, n_boot=0)
        except FitError as exc:
            notes.append(f"geometry: no flow fit to start from ({exc})")
    if base_fit is not None:
        current = take("geometry", geometry_constants(base_fit.per_run, base_fit.model, rig))
        # z0, C and the seat leakage are refitted with y_c held at its value:
        # its own 95 % interval moves them too (z0 most: it absorbs the
        # threshold's offset), added in quadrature to theirs. The refit and
        # the fits at y_c's interval edges are independent: tasks side by side
        edges = _y_c_edges(current, constants)
        items = [(current, n_boot, seed)] + [(r, 0, 0) for _, pair in edges for r in pair]
        refit, *edge_fits = _on_tasks(map_tasks, _flow_fit_task, items, {"summary": summary},
                                      "identify: flow fits")
        spread = _geometry_spread(edges, edge_fits, refit)
        added = []
        for side in SIDES:
            sf = refit.sides.get(side)
            if sf is not None and sf.success:
                dz0, dc = spread.get(side, {}).get("z0", 0.0), spread.get(side, {}).get("c", 0.0)
                xz0, xc = _x_c_spread(fits["geometry"].get(side))
                by = [who for who, moved in (("y_c's", dz0 or dc), ("x_c's", xz0 or xc)) if moved]
                how = "flowfit with the identified geometry" + (
                    ", interval widened by " + " and ".join(by) if by else "")
                dz0, dc = math.hypot(dz0, xz0), math.hypot(dc, xc)
                fitted = sf.estimates()
                added += [
                    Constant(f"valve.{side}.z0_mm", f"{side} z0", sf.z0_mm,
                             float(rig["valve"][side]["z0_mm"]), "mm", True,
                             how, widen_interval(sf.z0_mm, sf.z0_ci95, dz0),
                             method=fitted[f"{side}.z0"].method),
                    Constant(f"valve.{side}.c_flow", f"{side} C", sf.c_flow,
                             float(rig["valve"][side]["c_flow"]), "mm^3/(s deg^2 MPa^0.5)", True,
                             how, widen_interval(sf.c_flow, sf.c_ci95, dc),
                             method=fitted[f"{side}.C"].method)]
                continue
            # no z0 to go with a new centre: the rig file's centre stays
            for k in constants:
                if k.key == f"valve.{side}.needle_y_c_mm" and k.identified:
                    k.identified, k.value, k.ci95 = False, k.default, (float("nan"), float("nan"))
                    k.note = "flowfit with it failed on this side"
            notes.append(f"geometry ({side}): flowfit with the identified geometry failed"
                         + (f": {sf.message}" if sf is not None else ""))
        if added:
            added.append(_leak_constant(refit.leakage, rig, spread.get("leak", 0.0)))
        constants += added
        valve_keys = [k for k in constants if k.key and k.key.startswith(("valve.", "supply."))]
        current = rig.with_overrides(nest_constants(valve_keys), where="identify")
        model = ValveModel.from_rig(current) if added else None
    elif "geometry" in parts and not has_steps:
        notes.append("geometry: no flow-step runs")
    valve = model if model is not None else ValveModel.from_rig(current)

    if position_runs:
        current = take("controller", controller_constants(position_runs, valve, current))
    if servo is not None:
        log("identify: servo from its logs")
        found, before = servo.result()
        notes.extend(before)
        current = take("servo", found)
    if "friction" in parts:
        log("identify: friction from the flow steps' force balance")
        current = take("friction", friction_constants(summary, current, runs=position_runs))
    if "load" in parts and position_runs:
        log("identify: load regulator from the logged load pressure")
        current = take("load", load_constants(train_pos, held_pos, current))
    if "flow_path" in parts:
        log("identify: flow-path lag from the position-control runs")
        spread = {c.key: tuple(c.ci95) for c in constants if c.key and c.identified}
        current = take("flow_path", flow_path_constants(train_pos, held_pos, current, valve,
                                                        spread=spread))
    if position_runs and {"servo", "flow_path", "friction", "load"} & set(parts):
        log("identify: closed-loop check on the training and held-out runs")
        fits.update(closed_loop_fits(train_pos, held_pos, valve, rig, current))
    constants += _say_how([_mass(position_runs, rig, current)], "mass")
    return Identification(constants, current, model, fits, notes)


def _say_how(constants: list[Constant], part: str) -> list[Constant]:
    """``constants`` with :data:`PART_METHODS`' ``method`` of ``part`` where
    they do not say their own (in place; returned)."""
    for c in constants:
        if not c.method:
            c.method = PART_METHODS[part]
    return constants


def _x_c_spread(geometry_fit: dict[str, Any] | None) -> tuple[float, float]:
    """(|dz0| [mm], |dC|) that the rig file's 95 % range of x_c moves a
    side's z0 and C (the geometry fit's slopes x its range; 0 without)."""
    x = (geometry_fit or {}).get("x_c") or {}
    u, per = float(x.get("uncertainty_mm", 0.0)), x.get("per_mm", {})
    out = tuple(abs(float(per.get(k, math.nan))) * u for k in ("z0_mm", C_KEY))
    return tuple(v if math.isfinite(v) else 0.0 for v in out)


def _y_c_edges(current, constants) -> list[tuple[str, tuple[Any, Any]]]:
    """(side, (rig at y_c's lower 95 % edge, rig at its upper edge)) of each
    side whose identified y_c has a finite interval."""
    out = []
    for c in constants:
        if not (c.identified and c.key and c.key.endswith(".needle_y_c_mm")):
            continue
        side = c.key.split(".")[1]
        lo, hi = c.ci95
        if math.isfinite(lo) and math.isfinite(hi):
            out.append((side, tuple(current.with_overrides(
                {"valve": {side: {"needle_y_c_mm": float(v)}}}, where="identify")
                for v in (lo, hi))))
    return out


def _geometry_spread(edges, edge_fits, refit) -> dict[str, Any]:
    """How far y_c's 95 % half-width moves each side's z0 [mm] and C and the
    seat leakage's conductance [mm^3/(s MPa)]: flowfit refitted (no
    bootstrap) with each identified y_c at its interval's two edges
    (``edges``: :func:`_y_c_edges`; ``edge_fits``: their fits, lower and
    upper edge in turn), half the difference; summed in quadrature over the
    sides' y_c. {side: {'z0', 'c'}, 'leak'}."""
    out: dict[str, Any] = {"leak": 0.0}
    for k in range(len(edges)):
        edge = edge_fits[2 * k:2 * k + 2]
        for s in refit.sides:
            a, b = edge[0].sides.get(s), edge[1].sides.get(s)
            if a is None or b is None or not (a.success and b.success):
                continue
            d = out.setdefault(s, {"z0": 0.0, "c": 0.0})
            d["z0"] = math.hypot(d["z0"], 0.5 * abs(b.z0_mm - a.z0_mm))
            d["c"] = math.hypot(d["c"], 0.5 * abs(b.c_flow - a.c_flow))
        if edge[0].leakage.fitted and edge[1].leakage.fitted:
            out["leak"] = math.hypot(out["leak"], 0.5 * abs(
                edge[1].leakage.conductance_mm3_s_per_mpa
                - edge[0].leakage.conductance_mm3_s_per_mpa))
    return out


def _leak_constant(leak, rig, spread: float) -> Constant:
    """The needles' seat-leakage conductance as a rig constant (the twin's
    plant leaks with it); not identified when flowfit kept the rig file's."""
    key = "valve.plant.leakage_conductance_mm3_s_per_mpa"
    default = float(rig["valve"]["plant"]["leakage_conductance_mm3_s_per_mpa"])
    name, unit = "seat leakage conductance (per needle)", "mm^3/(s MPa)"
    if not leak.fitted:
        return Constant(key, name, default, default, unit, False, "flow steps",
                        note=leak.message or "not fitted")
    how = ("flow steps: Q_leak = g (dp_supply - dp_drain) beside eq. (5), fitted with both "
           "sides' z0 and C" + (", interval widened by y_c's" if spread else ""))
    lo, hi = widen_interval(leak.conductance_mm3_s_per_mpa, leak.ci95, spread)
    return Constant(key, name, leak.conductance_mm3_s_per_mpa, default, unit, True, how,
                    (max(lo, 0.0), hi), method=leak.method)


def _mass(runs, rig, current) -> Constant:
    """The moving mass is not identified; the note says how small m a is
    next to the friction in these runs (95th percentile of |a|)."""
    import numpy as np

    from ..errors import DataError
    from ..signals.derive import derive_samples

    mass = float(rig["actuator"]["moving_mass_kg"])
    acc = []
    for r in runs:
        try:
            d = derive_samples(r)
        except DataError:
            continue
        t, v = d["t_s"].to_numpy(float), d["velocity_mm_s"].to_numpy(float)
        ok = np.isfinite(v)
        if ok.sum() > 10:
            acc.append(np.abs(np.gradient(v[ok], t[ok])))
    coulomb = float(current["actuator"]["coulomb_friction_n"])
    if acc:
        a95 = float(np.percentile(np.concatenate(acc), 95))
        force = mass * a95 * 1e-3
        verdict = ("too small to tell the mass" if force < 0.2 * coulomb else
                   "large enough to matter, but identify does not fit the mass yet")
        note = (f"m a reaches {force:.2g} N (95th percentile |a| {a95:.3g} mm/s^2 x {mass:g} kg) "
                f"against {coulomb:.3g} N of Coulomb friction: {verdict}")
    else:
        note = "no position-control run to see accelerations in"
    return Constant("actuator.moving_mass_kg", "moving mass", mass, mass, "kg", False,
                    "acceleration transients", note=note)


#: a supply droop smaller than this fraction of the supply pressure at the
#: largest flow tested is not taken (a pressure transducer's accuracy class)
DROOP_MATERIAL = 1e-3


def _supply_pressure(summary, runs, rig) -> list[Constant]:
    """The supply the runs were made at: its pressure at no flow [MPaG] and
    its droop with the flow drawn [MPa s/mm^3] (the twin runs with both).

    With supply-side flow steps over a range of flows, a straight line
    p1 = p_0 - k Q through their steady (Q, p1) (the steps whose motion was
    steady, where >= 5 of them span the range; least squares, 95 %
    intervals from the slope's and intercept's standard errors); the droop k
    is taken when the slope is negative beyond 3.3 standard errors (p <
    0.001) and k Q_max exceeds :data:`DROOP_MATERIAL` of p_0, else the rig
    file's stays and p_0 is the median below. Without
    them, p_0 is the median of the logged p_supply over the position-control
    runs and the supply flow steps (95 % interval: bootstrap over runs,
    spanned with the position-control records' mean over their whole
    seconds: a flow step's short window keeps part of a pump-ripple period)."""
    import numpy as np
    from scipy import stats

    default = float(rig["supply"]["pressure_mpag"])
    droop0 = float(rig["supply"]["droop_mpa_s_per_mm3"])
    if {"p1_mpa", "q_mm3_s"} <= set(summary.columns):
        sup = summary[(summary["kind"] == "flow_step") & (summary["side"] == "supply")]
        q, p1 = sup["q_mm3_s"].to_numpy(float), sup["p1_mpa"].to_numpy(float)
        ok = np.isfinite(q) & np.isfinite(p1) & (q > 0)
        if "motion_steady" in sup:
            # a stick-slipping step's mean speed is not the flow the supply
            # gives (its valve passes more while the piston sticks): the
            # foreign rig's cam -5 deg steps sat 1-5 kPa below the true line
            # and put p_0 0.7-0.9 kPa low, outside its interval, in 4 of 4 seeds
            steady = ok & sup["motion_steady"].fillna(False).astype(bool).to_numpy()
            if steady.sum() >= 5 and np.ptp(q[steady]) > 500.0:
                ok = steady
        if ok.sum() >= 5 and np.ptp(q[ok]) > 500.0:
            fit = stats.linregress(q[ok], p1[ok])
            # a droop is taken where it is significant (p < 0.001) and
            # material: more than a pressure transducer's accuracy (0.1 % of
            # the supply) at the largest flow tested (our stiff simulated
            # supply: a slope of 1e-8 MPa s/mm^3, 80 Pa at 7000 mm^3/s, whose
            # line moved p_0 by the pump ripple's phase-locked 4e-5 MPa)
            material = -fit.slope * float(np.max(q[ok])) > DROOP_MATERIAL * abs(fit.intercept)
            if fit.slope < 0 and -fit.slope > 3.3 * fit.stderr and material:
                z = 1.96
                by = f"steady supply pressure vs flow of {int(ok.sum())} supply flow steps"
                return [
                    Constant("supply.pressure_mpag", "supply pressure (no flow)",
                             float(fit.intercept), default, "MPaG", True, by,
                             (float(fit.intercept - z * fit.intercept_stderr),
                              float(fit.intercept + z * fit.intercept_stderr))),
                    Constant("supply.droop_mpa_s_per_mm3", "supply droop with flow",
                             float(-fit.slope), droop0, "MPa s/mm^3", True, by,
                             (float(-fit.slope - z * fit.stderr),
                              float(-fit.slope + z * fit.stderr)),
                             note=f"{-fit.slope * 5000.0:.3f} MPa less at 5000 mm^3/s")]
    per_run, blocks = [], []
    for r in runs:
        p = r.tables.get("pressure")
        if p is not None and "p_supply_mpag" in p:
            v = p["p_supply_mpag"].to_numpy(float)
            t = p["t_s"].to_numpy(float) if "t_s" in p else np.arange(v.size, dtype=float)
            ok = np.isfinite(v) & np.isfinite(t)
            v, t = v[ok], t[ok]
            if v.size:
                per_run.append(float(np.median(v)))
                # whole seconds of the record: their means carry the pump ripple's
                # few leftover periods and the sensor noise
                sec = np.floor((t - t[0]) / 1.0).astype(int)
                blocks += [float(np.mean(v[sec == k])) for k in np.unique(sec)
                           if np.sum(sec == k) >= 10]
    if "p1_mpa" in summary:
        sup = summary[(summary["kind"] == "flow_step") & (summary["side"] == "supply")]
        per_run += [float(v) for v in sup["p1_mpa"].to_numpy(float) if np.isfinite(v)]
    if len(per_run) < 2:
        return []
    x = np.asarray(per_run)
    rng = np.random.default_rng(0)
    boot = [float(np.median(rng.choice(x, x.size))) for _ in range(400)]
    lo, hi = float(np.percentile(boot, 2.5)), float(np.percentile(boot, 97.5))
    by = f"logged p_supply of {x.size} runs"
    if len(blocks) >= 10:
        # the span of both estimators: each flow step's window (a few tenths of
        # a second) keeps part of a ripple period, with the same sign where the
        # ripple's phase is locked to the run's start (our simulator: +4e-5 MPa
        # over 180 steps, interval +-2e-5), the long records' seconds do not
        b = np.asarray(blocks)
        half = 1.96 * float(np.std(b, ddof=1)) / math.sqrt(b.size)
        lo, hi = min(lo, float(np.mean(b)) - half), max(hi, float(np.mean(b)) + half)
        by += " (interval: also the position-control records' mean)"
    return [Constant("supply.pressure_mpag", "supply pressure", float(np.median(x)), default,
                     "MPaG", True, by, (lo, hi))]