"""Closed-loop validation: re-run each measured position-control test on the
simulated plant and compare (paper Sec. III-C).

For every position_control run the same controller is rebuilt from run.json
(``controller.kp``, ``controller.flow_model``: :class:`~seanv_analysis.sim.control.FlowModelController`
with the identified valve model, or :class:`~seanv_analysis.sim.control.CamController`),
driven by the run's own reference sequence (controller.csv ``x_ref_mm``,
as steps) and load sequence (pressure.csv ``p_load_mpag`` reduced to
steps), and simulated with :func:`seanv_analysis.sim.simulate_position_control`
on the plant with the identified valve. Simulated and measured position
[mm], flow [mm^3/s] (same derivative, :func:`seanv_analysis.signals.derive.derive_samples`)
and cam angle [deg] are compared on the measured time base:

- fit % = 100 (1 - ||y - y_sim|| / ||y - mean(y)||) (100: perfect; 0: no
  better than the mean; negative: worse);
- RMSE of y - y_sim (measured - simulated);
- per reference step (measured and simulated): convergence within the
  rig's band (+-0.5 mm), overshoot past the reference [mm], settling time
  [s] (from the step until |e| stays inside the band to the step's end).

Each run is also re-run segment by segment (:mod:`.rerun`): from the
logged state just before each reference step and load change, so that no
hold's end is carried into the next step (``*_segments_*`` metrics; with
stick-slip these, not the whole run's, measure the twin's response to the
inputs).

A sustained oscillation (limit cycle, :mod:`.limitcycle`) is compared by
its statistics, measured and simulated: amplitude [mm], period [s], mean
error [mm] (``limit_cycle_*``; ``limit_cycle``: 'none', 'agrees' (amplitude
and period within 20 %, mean error within 20 % of the amplitude),
'differs', 'measured only', 'simulated only'). Its phase depends on where
the first swing began, so a twin that hunts like the rig still scores a low
fit %.

Runs whose position fit % is below ``threshold_pct`` (default 80) are
flagged: the plant disagrees with the data (what discovery looks at);
unless both records hold a limit cycle that agrees. A run where only one
record oscillates, or whose oscillations differ, is flagged whatever its fit.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Sequence

import numpy as np
import pandas as pd

from ..errors import ConfigError, DataError
from ..io.run import Run
from ..jsonable import JsonResult, clean_json
from ..signals.derive import derive_columns, derive_samples
from .limitcycle import LIMIT_CYCLE_RTOL, compare_limit_cycles, limit_cycle
from .tracking import load_level_holds

__all__ = ["DEFAULT_THRESHOLD_PCT", "fit_percent", "pooled_rmse", "reference_steps", "load_steps",
           "step_metrics", "build_controller", "RunValidation", "Validation", "validate_runs"]

#: Position fit % below which a run is flagged.
DEFAULT_THRESHOLD_PCT = 80.0


def fit_percent(y, y_sim) -> float:
    """Normalised fit [%]: 100 (1 - ||y - y_sim||_2 / ||y - mean(y)||_2).

    NaN pairs are ignored; NaN when y is constant or no pair is valid.

    Examples
    --------
    >>> fit_percent([0.0, 1.0, 2.0], [0.0, 1.0, 2.0])
    100.0
    """
    y = np.asarray(y, dtype=float)
    s = np.asarray(y_sim, dtype=float)
    ok = np.isfinite(y) & np.isfinite(s)
    if ok.sum() < 2:
        return math.nan
    y, s = y[ok], s[ok]
    den = float(np.linalg.norm(y - y.mean()))
    if den == 0:
        return math.nan
    return float(100.0 * (1.0 - np.linalg.norm(y - s) / den))


def _rmse(y, s) -> float:
    ok = np.isfinite(y) & np.isfinite(s)
    return float(np.sqrt(np.mean((y[ok] - s[ok]) ** 2))) if ok.any() else math.nan


def pooled_rmse(rmse, n_samples) -> float:
    """The RMSE of several runs pooled [their unit]: sqrt(sum n_i rmse_i^2 /
    sum n_i), each run's RMSE weighted by its samples (the RMSE of all their
    samples together; the package's one pooling of RMSEs: not a mean of
    them). Runs with a NaN RMSE are left out; NaN when none is left."""
    r = np.asarray(rmse, dtype=float)
    n = np.broadcast_to(np.asarray(n_samples, dtype=float), r.shape)
    ok = np.isfinite(r) & np.isfinite(n) & (n > 0)
    return float(np.sqrt(np.sum(n[ok] * r[ok] ** 2) / np.sum(n[ok]))) if ok.any() else math.nan


def _steps(t: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    ok = np.isfinite(v)
    t, v = t[ok], v[ok]
    if t.size == 0:
        return t, v
    idx = np.concatenate(([0], np.flatnonzero(np.diff(v) != 0) + 1))
    ts = t[idx].copy()
    ts[0] = min(ts[0], 0.0)
    return ts, v[idx]


def reference_steps(run: Run) -> tuple[np.ndarray, np.ndarray]:
    """(t [s], x_ref [mm]) step sequence of controller.csv ``x_ref_mm``
    (first step starts at t = 0 or earlier)."""
    ctrl = run.tables.get("controller")
    if ctrl is None or "x_ref_mm" not in ctrl or not len(ctrl):
        raise DataError("no controller table with x_ref_mm; expected a position_control run",
                        path=run.meta.path, column="x_ref_mm")
    return _steps(ctrl["t_s"].to_numpy(float), ctrl["x_ref_mm"].to_numpy(float))


#: a load change's onset is found where the pressure has covered this share of it
_ONSET_SHARE = 0.2
#: centred moving mean of the load pressure for the onset search [s]
_ONSET_SMOOTH_S = 0.02


def load_steps(run: Run, *, step_mpa: float = 0.05, min_hold_s: float = 0.3,
               regulator_tau_s: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(t [s], load set point [MPaG]) step sequence of pressure.csv ``p_load_mpag``.

    Levels from :func:`seanv_analysis.analysis.tracking.load_levels_mpag`
    (running median, ``step_mpa`` grid, holds shorter than ``min_hold_s``
    merged into the previous level); each level's value is the median of the
    raw load pressure over its hold. Each change of set point is placed at
    its onset, so that the simulator's first-order regulator (time constant
    ``regulator_tau_s``, default the run's rig ``load.regulator_time_constant_s``)
    reproduces the logged pressure: where the pressure (20 ms centred mean)
    has covered 20 % of the change, less tau ln(1/0.8). run.json
    ``load_mpag`` (when not null) gives a single step.
    """
    if run.meta.load_mpag is not None:
        return np.array([0.0]), np.array([float(run.meta.load_mpag)])
    p = run.tables["pressure"]
    t = p["t_s"].to_numpy(float)
    raw = p["p_load_mpag"].to_numpy(float)
    starts, _, vals = load_level_holds(t, raw, step_mpa=step_mpa, min_hold_s=min_hold_s)
    ts = t[starts].copy()
    ts[0] = min(ts[0], 0.0)
    if starts.size > 1:
        tau = float(run.rig["load"]["regulator_time_constant_s"]) if regulator_tau_s is None \
            else float(regulator_tau_s)
        ts[1:] = _onsets(t, raw, starts, vals, tau)
        for k in range(1, ts.size):        # the simulator wants increasing instants
            ts[k] = max(ts[k], ts[k - 1] + 1e-3)
    return ts, vals


def _onsets(t, raw, starts, vals, tau: float) -> np.ndarray:
    """Onset [s] of each level change k >= 1 (see :func:`load_steps`)."""
    from scipy.ndimage import uniform_filter1d

    dt = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    fill = np.where(np.isfinite(raw), raw, np.nanmedian(raw))
    ps = uniform_filter1d(fill, max(1, int(round(_ONSET_SMOOTH_S / dt))), mode="nearest")
    out = np.empty(starts.size - 1)
    lead = tau * math.log(1.0 / (1.0 - _ONSET_SHARE))
    for k in range(1, starts.size):
        a, b, i = vals[k - 1], vals[k], int(starts[k])
        lo = int(starts[k - 1])
        share = (ps[lo:i + 1] - a) / (b - a) if b != a else np.zeros(i + 1 - lo)
        below = np.flatnonzero(share < _ONSET_SHARE)
        if below.size == 0:
            out[k - 1] = t[i]
            continue
        m = int(below[-1])                  # last sample short of the share
        if m + 1 < share.size and share[m + 1] != share[m]:
            frac = (_ONSET_SHARE - share[m]) / (share[m + 1] - share[m])
            t_cross = t[lo + m] + min(max(frac, 0.0), 1.0) * (t[lo + m + 1] - t[lo + m])
        else:
            t_cross = t[lo + m]
        out[k - 1] = max(t_cross - lead, t[lo])
    return out


def step_metrics(t_s, x_mm, ref_t_s, ref_mm, *, x0_mm: float | None = None,
                 band_mm: float = 0.5) -> pd.DataFrame:
    """Per reference step: converged, overshoot [mm], settling time [s].

    Parameters
    ----------
    t_s, x_mm : position record [s], [mm]
    ref_t_s, ref_mm : reference steps (value holds from each t until the next)
    x0_mm : position before the first step (default the first sample)
    band_mm : convergence band half-width [mm]

    Returns
    -------
    DataFrame with t_start_s, t_end_s, x_ref_mm, step_mm, converged (|e| <=
    band at some instant of the step), convergence_time_s (first instant
    inside the band, from the step; NaN if never), overshoot_mm (largest
    excursion past the reference in the step's direction, >= 0),
    settling_time_s (from the step until |e| stays inside the band to the
    step's end; NaN if it is outside at the step's end).
    """
    t = np.asarray(t_s, float)
    x = np.asarray(x_mm, float)
    rt = np.asarray(ref_t_s, float)
    rv = np.asarray(ref_mm, float)
    prev = float(x[0] if x0_mm is None else x0_mm)
    rows = []
    for k in range(rt.size):
        a = rt[k]
        b = rt[k + 1] if k + 1 < rt.size else t[-1] + 1e-12
        m = (t >= a) & (t < b)
        step = rv[k] - prev
        prev_ref = rv[k]
        prev = prev_ref
        if m.sum() < 2:
            continue
        e = rv[k] - x[m]
        inside = np.abs(e) <= band_mm
        sign = 1.0 if step >= 0 else -1.0
        over = float(max(0.0, np.max(-sign * e))) if step != 0 else float(np.max(np.abs(e)))
        if inside[-1]:
            out = np.flatnonzero(~inside)
            j = 0 if out.size == 0 else int(out[-1]) + 1
            settle = float(t[m][j] - a) if j > 0 else 0.0
        else:
            settle = math.nan
        first_in = np.flatnonzero(inside)
        t_conv = float(t[m][first_in[0]] - a) if first_in.size else math.nan
        rows.append({"t_start_s": float(a), "t_end_s": float(min(b, t[-1])), "x_ref_mm": float(rv[k]),
                     "step_mm": float(step), "converged": bool(inside.any()),
                     "convergence_time_s": t_conv,
                     "overshoot_mm": over, "settling_time_s": settle})
    return pd.DataFrame(rows, columns=["t_start_s", "t_end_s", "x_ref_mm", "step_mm",
                                       "converged", "convergence_time_s", "overshoot_mm",
                                       "settling_time_s"])


def build_controller(run: Run, model, rig=None):
    """The run's controller (run.json ``controller``) rebuilt with ``model``.

    flow_model true (default): ``FlowModelController.from_rig(rig, model,
    kp_mm3_s_per_mm=kp)``; false: ``CamController.from_rig(rig, kp_deg_per_mm=kp)``;
    the band, release, hold angle and cam limits are the rig's
    ([controller], ``servo.neutral_deg``, ``valve.cam_min_deg``/``cam_max_deg``:
    what ``identify`` reads from the logs). Missing ``kp`` takes the rig's
    value, and so does every run when the rig says ``controller.kp_from_logs``
    (the logged gain contradicts run.json's); ``rate_hz`` is kept.
    """
    from ..sim.control import CamController, FlowModelController

    rig = run.rig if rig is None else rig
    c = dict(run.meta.controller or {})
    extra = {"rate_hz": float(c["rate_hz"])} if c.get("rate_hz") else {}
    declared = c.get("kp") is not None and not rig["controller"].get("kp_from_logs", False)
    if c.get("flow_model", True):
        if declared:
            extra["kp_mm3_s_per_mm"] = float(c["kp"])
        lo, hi = rig.cam_range_deg
        return FlowModelController.from_rig(rig, model, cam_min_deg=lo, cam_max_deg=hi, **extra)
    if declared:
        extra["kp_deg_per_mm"] = float(c["kp"])
    return CamController.from_rig(rig, **extra)


def _cam_column(d) -> str:
    """'cam_deg' where the derived table ``d`` (DataFrame or {column: array})
    has cam feedback in most samples, else 'cam_cmd_deg'."""
    if "cam_deg" in d and np.isfinite(np.asarray(d["cam_deg"], dtype=float)).mean() > 0.5:
        return "cam_deg"
    return "cam_cmd_deg"


@dataclass
class RunValidation:
    """One run re-simulated: metrics row, step metrics and the overlay data.

    ``overlay``: t_s, position_mm / _sim, q_mm3_s / _sim, cam_deg / _sim,
    x_ref_mm (the measured time base).
    """

    run_id: str
    row: dict[str, Any]
    steps_measured: pd.DataFrame = field(repr=False)
    steps_simulated: pd.DataFrame = field(repr=False)
    overlay: pd.DataFrame = field(repr=False)
    simulated: Run | None = field(default=None, repr=False)
    #: starts [s] of the per-segment re-runs (``*_seg_*`` overlay columns;
    #: empty when none was made)
    segment_starts_s: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)

    @property
    def flow_error(self) -> np.ndarray:
        """Measured minus re-simulated (whole run) flow [mm^3/s] per sample
        (NaN where either is)."""
        return (self.overlay["q_mm3_s"] - self.overlay["q_sim_mm3_s"]).to_numpy(float)


def _applicable(rec: dict[str, Any]) -> dict[str, Any]:
    """``rec`` without the gain key of the other controller (kp_* null)."""
    return {k: v for k, v in rec.items() if not (k.startswith("kp_") and v is None)}


@dataclass
class Validation(JsonResult):
    """Closed-loop validation of a data set.

    Attributes
    ----------
    table : one row per run: run_id, controller ('flow_model' | 'cam'),
        kp_mm3_s_per_mm (flow-model controller) or kp_deg_per_mm (cam
        controller), fit_position_pct, rmse_position_mm, fit_flow_pct,
        rmse_flow_mm3_s, fit_cam_pct, rmse_cam_deg, steps,
        converged_measured_frac / converged_simulated_frac (fraction of steps), convergence_time_measured_s /
        convergence_time_simulated_s (mean time to first enter the band),
        overshoot_measured_mm /
        overshoot_simulated_mm (largest), settling_measured_s /
        settling_simulated_s (mean over settled steps), limit_cycle ('none',
        'agrees', 'differs', 'measured only', 'simulated only') and
        limit_cycle_{amplitude,mean_error}_{measured,simulated}_mm,
        limit_cycle_{period,duration}_{measured,simulated}_s, flagged
    flagged : run ids with position fit % < ``threshold_pct`` (unless their
        limit cycles agree), or whose limit cycles do not agree
    threshold_pct : the flag threshold [%]
    runs : per-run :class:`RunValidation` (overlay data for the figure)
    skipped : {run_id: reason}
    warnings : messages worth reading
    controller_model : which valve model the flow-model controller used
        ('rig', 'plant' or 'given')
    """

    table: pd.DataFrame
    flagged: list[str]
    threshold_pct: float
    runs: list[RunValidation] = field(default_factory=list, repr=False)
    skipped: dict[str, str] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    controller_model: str = "rig"

    @property
    def success(self) -> bool:
        return len(self.table) > 0

    def by_controller(self) -> pd.DataFrame:
        """Per controller ('flow_model' | 'cam'): n_runs, steps (total), the
        RMSEs pooled over its runs' samples (:func:`pooled_rmse`) and the
        mean of every other numeric metric over its runs."""
        if self.table.empty:
            return pd.DataFrame()
        g = self.table.drop(columns=["run_id", "flagged"]).groupby("controller")
        out = g.mean(numeric_only=True)
        if "n_samples" in self.table:
            for col in (c for c in out.columns if c.startswith("rmse_")):
                out[col] = g.apply(lambda d, col=col: pooled_rmse(d[col], d["n_samples"]),
                                   include_groups=False)
            out["n_samples"] = g["n_samples"].sum().astype(int)
        out["steps"] = g["steps"].sum().astype(int)  # a count stays a count
        if "n_segments" in self.table:
            out["n_segments"] = g["n_segments"].sum().astype(int)
        out.insert(0, "n_runs", g.size().astype(int))
        return out

    def steps(self) -> pd.DataFrame:
        """Per reference step of every run, measured and simulated
        (:func:`step_metrics` columns plus run_id and source)."""
        parts = []
        for r in self.runs:
            for source, df in (("measured", r.steps_measured), ("simulated", r.steps_simulated)):
                if not df.empty:
                    parts.append(df.assign(run_id=r.run_id, source=source))
        return pd.concat(parts, ignore_index=True) if parts else pd.DataFrame()

    def to_json_dict(self) -> dict[str, Any]:
        """JSON document: threshold, flagged runs, per-run table, per-controller means."""
        by = self.by_controller()
        return {"threshold_pct": self.threshold_pct, "flagged": list(self.flagged),
                "controller_model": self.controller_model,
                "metric": "fit % = 100 (1 - ||y - y_sim|| / ||y - mean(y)||); RMSE of "
                          "measured - simulated; limit cycle: amplitude (half peak-to-peak "
                          "error per cycle, median), period (median), mean error",
                "limit_cycle_tolerance_pct": 100.0 * LIMIT_CYCLE_RTOL,
                "runs": [_applicable({k: clean_json(v) for k, v in rec.items()})
                         for rec in self.table.to_dict(orient="records")],
                "by_controller": {str(c): _applicable({k: clean_json(v) for k, v in row.items()})
                                  for c, row in by.to_dict(orient="index").items()},
                "skipped": dict(self.skipped), "warnings": list(self.warnings)}

    def __repr__(self) -> str:
        fits = ", ".join(f"{r.run_id} {r.row['fit_position_pct']:.1f} %"
                         for r in self.runs) or "none"
        return (f"<Validation position fit: {fits}; flagged (< {self.threshold_pct:g} %): "
                f"{', '.join(self.flagged) or 'none'}>")

    def plot(self, ax=None, **kwargs):
        """Measured and simulated ``quantity`` ('position', 'flow', 'cam') of
        every run against time on ``ax`` (a new pyplot figure when None); returns the axes."""
        from ..plotting import plot

        return plot(self, ax, **kwargs)

    def to_frame(self) -> pd.DataFrame:
        """The per-run table indexed by run_id (fits, RMSEs, step metrics)."""
        return self.table.set_index("run_id") if "run_id" in self.table else self.table

    def skipped_runs(self) -> dict[str, str]:
        """{run_id: why} of the runs that could not be used."""
        return dict(self.skipped)

    def report(self) -> str:
        """Plain-text table."""
        lines = ["Closed-loop validation: measured vs simulated position control "
                 f"(flag: position fit < {self.threshold_pct:g} % unless both hold the same "
                 "limit cycle; a limit cycle in one only)"]
        head = (f"  {'run':<28} {'ctrl':<10} {'fit x %':>8} {'RMSE x':>7} {'fit Q %':>8} "
                f"{'fit cam %':>9} {'conv':>9} {'t_conv s':>13} {'OS mm':>11} {'settle s':>13}")
        lines.append(head)
        lines.append("  (pairs are measured/simulated; conv = fraction of steps reaching +-band; OS = "
                 "largest overshoot; settle = mean time to stay in band)")
        for r in self.table.to_dict(orient="records"):
            lines.append(
                f"  {r['run_id']:<28} {r['controller']:<10} {r['fit_position_pct']:>8.1f} "
                f"{r['rmse_position_mm']:>7.3f} {r['fit_flow_pct']:>8.1f} {r['fit_cam_pct']:>9.1f} "
                f"{r['converged_measured_frac']:>4.2f}/{r['converged_simulated_frac']:<4.2f} "
                f"{r['convergence_time_measured_s']:>6.2f}/{r['convergence_time_simulated_s']:<6.2f} "
                f"{r['overshoot_measured_mm']:>5.2f}/{r['overshoot_simulated_mm']:<5.2f} "
                f"{r['settling_measured_s']:>6.2f}/{r['settling_simulated_s']:<6.2f}"
                + ("  FLAGGED" if r["flagged"] else ""))
            if r.get("limit_cycle", "none") != "none":
                lines.append(
                    f"    limit cycle ({r['limit_cycle']}): amplitude "
                    f"{r['limit_cycle_amplitude_measured_mm']:.3g}/"
                    f"{r['limit_cycle_amplitude_simulated_mm']:.3g} mm, period "
                    f"{r['limit_cycle_period_measured_s']:.3g}/"
                    f"{r['limit_cycle_period_simulated_s']:.3g} s, mean error "
                    f"{r['limit_cycle_mean_error_measured_mm']:.3g}/"
                    f"{r['limit_cycle_mean_error_simulated_mm']:.3g} mm, for "
                    f"{r['limit_cycle_duration_measured_s']:.3g}/"
                    f"{r['limit_cycle_duration_simulated_s']:.3g} s (measured/simulated; "
                    f"agrees: within {100 * LIMIT_CYCLE_RTOL:g} %)")
        by = self.by_controller()
        for c, row in by.iterrows():
            lines.append(f"  mean {c}: position fit {row['fit_position_pct']:.1f} %, flow fit "
                         f"{row['fit_flow_pct']:.1f} %, cam fit {row['fit_cam_pct']:.1f} %")
            if math.isfinite(row.get("fit_flow_segments_pct", math.nan)):
                lines.append(f"  mean {c}, each segment re-run from the logged state: position "
                             f"fit {row['fit_position_segments_pct']:.1f} %, flow fit "
                             f"{row['fit_flow_segments_pct']:.1f} %")
        lines.append(f"  flagged: {', '.join(self.flagged) if self.flagged else 'none'}")
        for rid, why in self.skipped.items():
            lines.append(f"  skipped {rid}: {why}")
        for w in self.warnings:
            lines.append(f"  warning: {w}")
        return "\n".join(lines)

def _default_simulate():
    from ..sim.run import simulate_position_control
    return simulate_position_control


def _controller_model(spec, model, rig):
    from ..models import ValveModel

    if isinstance(spec, ValveModel):
        return spec
    if spec == "rig":
        return ValveModel.from_rig(rig)
    if spec == "plant":
        return model
    raise ConfigError(f"controller_model: expected 'rig', 'plant' or a ValveModel, got {spec!r}")


#: a log whose encoder clock starts further than this from 0 [s] (epoch
#: seconds, negative times) is validated on a clock starting at its first sample
_CLOCK_OFFSET_MAX_S = 1.0
#: longest run [s] the plant is simulated for (a longer t_s span is taken as wrong units)
_SIM_SPAN_MAX_S = 86400.0


def _on_run_clock(run: Run) -> Run:
    """``run`` with every table's ``t_s`` shifted so the encoder starts at 0
    when it starts before 0 or after :data:`_CLOCK_OFFSET_MAX_S` (the plant
    is simulated from t = 0 to the last encoder sample); else ``run``."""
    enc = run.tables.get("encoder")
    if enc is None or not len(enc):
        return run
    t0 = float(enc["t_s"].iloc[0])
    if 0.0 <= t0 <= _CLOCK_OFFSET_MAX_S:
        return run
    import dataclasses

    tables = {name: df.assign(t_s=df["t_s"].to_numpy(float) - t0)
              for name, df in run.tables.items()}
    return dataclasses.replace(run, tables=tables)


def _no_segments(n: int):
    """The per-segment re-run's stand-in when none is made (all NaN: the
    whole run's numbers stand)."""
    from .rerun import SegmentRerun

    return SegmentRerun(np.full(n, np.nan), np.full(n, np.nan), np.zeros(0))


def validate_run(run: Run, model, *, rig=None, seed: int = 0, effects: Sequence[str] = (),
                 threshold_pct: float = DEFAULT_THRESHOLD_PCT, controller_model="rig",
                 simulate: Callable | None = None, segments: bool | None = None
                 ) -> RunValidation:
    """Re-simulate one position_control run and compare (see module docstring).

    ``segments``: also re-run it per segment from the logged state
    (:mod:`.rerun`; the ``*_segments_*`` metrics); default: with the
    built-in simulator (a ``simulate`` given may not take an initial state).
    """
    if segments is None:
        segments = simulate is None
    if run.meta.kind != "position_control":
        raise DataError(f"kind {run.meta.kind!r}; expected position_control", path=run.meta.path)
    sim_fn = simulate or _default_simulate()
    run = _on_run_clock(run)
    plant_rig = run.rig if rig is None else rig.with_overrides(run.meta.rig_overrides or None)
    ctrl = build_controller(run, _controller_model(controller_model, model, plant_rig), plant_rig)
    ref_t, ref_v = reference_steps(run)
    load_t, load_v = load_steps(
        run, regulator_tau_s=float(plant_rig["load"]["regulator_time_constant_s"]))
    enc = run.tables["encoder"]
    t_enc = enc["t_s"].to_numpy(float)
    if not t_enc[-1] <= _SIM_SPAN_MAX_S:
        raise DataError(f"last timestamp {t_enc[-1]:.6g} s; expected a run of at most "
                        f"{_SIM_SPAN_MAX_S:g} s to simulate (t_s in ms or ns instead of s?)",
                        path=run.files.get("encoder", run.meta.path), column="t_s")
    x0 = float(enc["position_mm"].iloc[0])
    sim = sim_fn(plant_rig, controller=ctrl, x_ref=(ref_t, ref_v), load=(load_t, load_v),
                 duration_s=float(t_enc[-1]), seed=seed, valve=model, effects=tuple(effects),
                 x0_mm=x0, run_id=f"{run.run_id}-sim", started_at=run.meta.started_at)
    if isinstance(sim, tuple):  # (Run, SimTrace)
        sim = sim[0]
    dm = derive_samples(run)
    if len(dm) < 2:
        raise DataError(f"{len(dm)} sample(s) where all streams overlap in time; expected a "
                        "longer common span to validate", path=run.meta.path)
    ds, _ = derive_columns(sim)    # numpy, the numbers of derive_samples
    t = dm["t_s"].to_numpy(float)
    ts = np.asarray(ds["t_s"], dtype=float)

    def on_t(col):      # NaN outside the simulated span
        return np.interp(t, ts, np.asarray(ds[col], dtype=float), left=np.nan, right=np.nan)

    cam_m, cam_s = _cam_column(dm), _cam_column(ds)
    ov = pd.DataFrame({"t_s": t, "x_ref_mm": dm["x_ref_mm"].to_numpy(float),
                       "position_mm": dm["position_mm"].to_numpy(float),
                       "position_sim_mm": on_t("position_mm"),
                       "q_mm3_s": dm["q_mm3_s"].to_numpy(float), "q_sim_mm3_s": on_t("q_mm3_s"),
                       "cam_deg": dm[cam_m].to_numpy(float), "cam_sim_deg": on_t(cam_s),
                       "p_load_mpag": dm["p_load_mpag"].to_numpy(float)})
    band = float(plant_rig["controller"]["convergence_band_mm"])
    sm = step_metrics(t, ov.position_mm.to_numpy(), ref_t, ref_v, x0_mm=x0, band_mm=band)
    ss = step_metrics(ts, np.asarray(ds["position_mm"], dtype=float), ref_t, ref_v, x0_mm=x0,
                      band_mm=band)
    c = run.meta.controller or {}

    def agg(df, col, how):
        df = df[df.step_mm.abs() > band] if not df.empty else df  # real steps only
        if df.empty:
            return math.nan
        v = df[col].to_numpy(float)
        v = v[np.isfinite(v)]
        return float(how(v)) if v.size else math.nan

    fit_x = fit_percent(ov.position_mm, ov.position_sim_mm)
    lc_m = limit_cycle(t, ov.position_mm.to_numpy(), ref_t, ref_v, band_mm=band)
    lc_s = limit_cycle(t, ov.position_sim_mm.to_numpy(), ref_t, ref_v, band_mm=band)
    lc = compare_limit_cycles(lc_m, lc_s)
    seg = _no_segments(len(dm))
    if segments:            # unless the logs cannot start one (then the whole run's stand)
        from .rerun import rerun_segments

        try:
            seg = rerun_segments(dm, simulate=sim_fn, rig=plant_rig, controller=ctrl,
                                 reference=(ref_t, ref_v), load=(load_t, load_v), valve=model,
                                 effects=effects, seed=seed, run_id=run.run_id,
                                 ticks=run.tables["controller"]["t_s"].to_numpy(float))
        except DataError:
            pass
    ov["position_seg_mm"], ov["q_seg_mm3_s"] = seg.position_mm, seg.q_mm3_s
    kp = float(c["kp"]) if c.get("kp") is not None else math.nan
    row = {"run_id": run.run_id,
           "controller": "flow_model" if c.get("flow_model", True) else "cam",
           # the gain's unit depends on the controller (eq. 6 or the cam law)
           "kp_mm3_s_per_mm": kp if c.get("flow_model", True) else math.nan,
           "kp_deg_per_mm": math.nan if c.get("flow_model", True) else kp,
           "fit_position_pct": fit_x,
           "rmse_position_mm": _rmse(ov.position_mm.to_numpy(), ov.position_sim_mm.to_numpy()),
           "fit_flow_pct": fit_percent(ov.q_mm3_s, ov.q_sim_mm3_s),
           "rmse_flow_mm3_s": _rmse(ov.q_mm3_s.to_numpy(), ov.q_sim_mm3_s.to_numpy()),
           "fit_cam_pct": fit_percent(ov.cam_deg, ov.cam_sim_deg),
           "rmse_cam_deg": _rmse(ov.cam_deg.to_numpy(), ov.cam_sim_deg.to_numpy()),
           # re-run per segment from the logged state (NaN when not asked)
           "fit_position_segments_pct": fit_percent(ov.position_mm, ov.position_seg_mm),
           "rmse_position_segments_mm": _rmse(ov.position_mm.to_numpy(),
                                              ov.position_seg_mm.to_numpy()),
           "fit_flow_segments_pct": fit_percent(ov.q_mm3_s, ov.q_seg_mm3_s),
           "rmse_flow_segments_mm3_s": _rmse(ov.q_mm3_s.to_numpy(), ov.q_seg_mm3_s.to_numpy()),
           "n_segments": seg.n_segments,
           "n_samples": int(len(ov)),
           "steps": int((sm.step_mm.abs() > band).sum()) if not sm.empty else 0,
           "converged_measured_frac": agg(sm, "converged", np.mean),
           "converged_simulated_frac": agg(ss, "converged", np.mean),
           "convergence_time_measured_s": agg(sm, "convergence_time_s", np.mean),
           "convergence_time_simulated_s": agg(ss, "convergence_time_s", np.mean),
           "overshoot_measured_mm": agg(sm, "overshoot_mm", np.max),
           "overshoot_simulated_mm": agg(ss, "overshoot_mm", np.max),
           "settling_measured_s": agg(sm, "settling_time_s", np.mean),
           "settling_simulated_s": agg(ss, "settling_time_s", np.mean),
           # a sustained oscillation, compared by its statistics (its phase is not reproducible)
           "limit_cycle": lc,
           "limit_cycle_amplitude_measured_mm": lc_m.amplitude_mm,
           "limit_cycle_amplitude_simulated_mm": lc_s.amplitude_mm,
           "limit_cycle_period_measured_s": lc_m.period_s,
           "limit_cycle_period_simulated_s": lc_s.period_s,
           "limit_cycle_mean_error_measured_mm": lc_m.mean_error_mm,
           "limit_cycle_mean_error_simulated_mm": lc_s.mean_error_mm,
           "limit_cycle_duration_measured_s": lc_m.duration_s,
           "limit_cycle_duration_simulated_s": lc_s.duration_s,
           "flagged": _flagged(fit_x, threshold_pct, lc)}
    return RunValidation(run.run_id, row, sm, ss, ov, sim, seg.starts_s)


def _flagged(fit_position_pct: float, threshold_pct: float, limit_cycle: str) -> bool:
    """A run is flagged when its position fit is below the threshold, unless
    both records hold the same limit cycle ('agrees': a hunting loop's phase
    cannot be reproduced, its statistics can), or when one record oscillates
    and the other does not, or their oscillations differ."""
    if limit_cycle in ("differs", "measured only", "simulated only"):
        return True
    return bool(not (fit_position_pct >= threshold_pct) and limit_cycle != "agrees")


def validate_runs(runs: Iterable[Run], model=None, *, rig=None,
                  threshold_pct: float = DEFAULT_THRESHOLD_PCT, seed: int = 0,
                  effects: Sequence[str] = (), controller_model="rig",
                  simulate: Callable | None = None) -> Validation:
    """Validate every position_control run against the simulated plant.

    Parameters
    ----------
    runs : runs (only position_control runs are used)
    model : identified :class:`~seanv_analysis.models.ValveModel` (plant
        valve and flow-model controller's model); default the rig's valve
    rig : rig config of the plant (default each run's ``run.rig``)
    threshold_pct : flag runs whose position fit % is below this [%]
    seed : simulator noise seed
    effects : extra plant effects for the simulator (``models.effects`` specs)
    controller_model : valve model inside the flow-model controller (eq. 6):
        'rig' (default: the rig config's valve, i.e. what the rig's controller
        ran, since run.json does not record it), 'plant' (``model``), or a
        :class:`~seanv_analysis.models.ValveModel`
    simulate : replacement for :func:`seanv_analysis.sim.simulate_position_control`
        (same signature; for tests)

    Returns
    -------
    Validation

    Raises
    ------
    ConfigError
        ``threshold_pct`` not finite.
    DataError
        no position_control run could be validated.
    """
    if not math.isfinite(float(threshold_pct)):
        raise ConfigError(f"threshold_pct: expected a finite percentage, got {threshold_pct!r}")
    results, skipped, notes = [], {}, []
    for run in runs:
        if run.meta.kind != "position_control":
            continue
        mdl = model
        if mdl is None:
            from ..models import ValveModel
            mdl = ValveModel.from_rig(run.rig if rig is None else rig)
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                results.append(validate_run(run, mdl, rig=rig, seed=seed, effects=effects,
                                            threshold_pct=threshold_pct,
                                            controller_model=controller_model,
                                            simulate=simulate))
            notes.extend(f"{run.run_id}: {w.message}" for w in caught)
        except DataError as exc:
            skipped[run.run_id] = str(exc)
    if not results:
        why = next(iter(skipped.values()), "")
        raise DataError("no position_control run could be validated"
                        + (f" ({len(skipped)} skipped; first: {' '.join(why.split())})"
                           if skipped else ""))
    table = pd.DataFrame([r.row for r in results])
    flagged = [r.run_id for r in results if r.row["flagged"]]
    return Validation(table, flagged, float(threshold_pct), results, skipped, notes,
                      controller_model if isinstance(controller_model, str) else "given")

