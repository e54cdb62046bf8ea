"""Flow tracking during position control (paper Sec. III-C.2, Fig. 7).

For each position_control run:

- actual flow Q [mm^3/s] from the encoder with the same derivative as ingest
  (:func:`seanv_analysis.signals.derive.derive_samples`, Q = v A);
- target flow Q_ref [mm^3/s] from controller.csv (``q_ref_mm3_s``, held
  between controller samples). When Q_ref is empty: with the flow model,
  Q_ref = Kp (x_ref - x) at the controller instants (run.json
  ``controller.kp``); without it and with a valve ``model``, the model's net
  flow (eq. 5) at the commanded cam angle and the measured pressures;
  otherwise the run is skipped with a warning;
- the delay of Q behind Q_ref: given (``shift_s``, the paper's 0.25 s) or
  estimated by cross-correlation (:func:`seanv_analysis.analysis.lag.estimate_lag`),
  pooled over the runs, and per run;
- Q is shifted earlier by the delay: Q_shifted(t) = Q(t + lag) (linear
  interpolation, no extrapolation), and the residual Q_shifted - Q_ref
  (actual - target) is summarised over the samples whose target lies in
  ``q_range`` (inclusive; the paper's -2.5e3..8e3 mm^3/s): RMSE, bias, RMSE
  per side (target >= 0 supply, < 0 drain) and per load level.

The headline numbers (the pooled delay estimate, RMSE, bias, per side and
load) are the paper's: over the runs whose Q_ref the controller commanded
(logged, or Kp e of the flow-model controller: :data:`COMMANDED`), in the
stated Q_ref range. A run without the flow model has no commanded Q_ref (its
target is only implied by a valve model): it gets its own numbers, and is
pooled only when no run had a commanded Q_ref (``pooled`` says which).
The paper reports RMSE = 0.516e3 mm^3/s with a 0.25 s shift.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from typing import Any, Iterable, Sequence

import numpy as np
import pandas as pd

from ..errors import ConfigError, DataError
from ..estimate import Estimate, Estimates
from ..io.run import Run
from ..jsonable import JsonResult, json_num
from ..signals.derive import derive_samples
from .lag import LagEstimate, estimate_lag, estimate_lag_segments

__all__ = ["DEFAULT_Q_RANGE_MM3_S", "LOAD_LEVEL_STEP_MPA", "COMMANDED", "load_level_holds",
           "RunTracking", "Tracking", "run_flows", "tracking_runs", "load_levels_mpag"]

#: The paper's fitting range of the target flow [mm^3/s] (Sec. III-C.2).
DEFAULT_Q_RANGE_MM3_S = (-2.5e3, 8e3)
#: Target sources that are the controller's commanded Q_ref: logged, or Kp e
#: of the flow-model controller (``model``: only implied by a valve model).
COMMANDED = ("q_ref", "kp_error")
#: Load pressures are grouped into levels on this grid [MPa].
LOAD_LEVEL_STEP_MPA = 0.05


#: how the headline numbers' runs are said
POOLED_COMMANDED = "runs with a commanded Q_ref"
POOLED_ALL = ("all runs: none had a commanded Q_ref (targets implied by the valve model at "
              "the commanded cam)")


def _rmse(r: np.ndarray) -> float:
    return float(np.sqrt(np.mean(r * r))) if r.size else math.nan


def load_levels_mpag(t_s, p_load_mpag, *, step_mpa: float = LOAD_LEVEL_STEP_MPA,
                     smooth_s: float = 0.1, min_hold_s: float = 0.3) -> np.ndarray:
    """Load level of each sample [MPaG].

    The load pressure is smoothed by a running median over ``smooth_s``,
    rounded to the ``step_mpa`` grid, and holds shorter than ``min_hold_s``
    (the pressure passing through levels during a load change) take the
    previous level (the next one at the start of the record).
    """
    from scipy.ndimage import median_filter

    t = np.asarray(t_s, dtype=float)
    p = np.asarray(p_load_mpag, dtype=float)
    if p.size == 0:
        return p
    dt = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    n = max(1, int(round(smooth_s / dt)) | 1)
    fill = np.where(np.isfinite(p), p, np.nanmedian(p) if np.isfinite(p).any() else 0.0)
    ps = median_filter(fill, size=n, mode="nearest")
    lv = np.round(np.round(ps / step_mpa) * step_mpa, 6)
    starts = np.concatenate(([0], np.flatnonzero(np.diff(lv) != 0) + 1))
    ends = np.concatenate((starts[1:], [lv.size]))
    short = (t[ends - 1] - t[starts]) < min_hold_s
    if short.any() and not short.all():
        keep_val = lv[starts].copy()
        first_long = int(np.flatnonzero(~short)[0])
        for k in range(starts.size):
            if short[k]:
                keep_val[k] = keep_val[k - 1] if k > first_long else keep_val[first_long]
        lv = np.repeat(keep_val, ends - starts)
    return lv


def load_level_holds(t_s, p_load_mpag, *, step_mpa: float = LOAD_LEVEL_STEP_MPA,
                     min_hold_s: float = 0.3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The holds of :func:`load_levels_mpag`: (first sample, one past the
    last sample, level [MPaG]) of each, the level being the median of the
    raw load pressure over the hold (NaN left out)."""
    p = np.asarray(p_load_mpag, dtype=float)
    lv = load_levels_mpag(t_s, p, step_mpa=step_mpa, min_hold_s=min_hold_s)
    starts = np.concatenate(([0], np.flatnonzero(np.diff(lv) != 0) + 1))
    ends = np.concatenate((starts[1:], [lv.size]))
    levels = np.array([float(np.nanmedian(p[a:b])) for a, b in zip(starts, ends)])
    return starts, ends, levels


def _controller_info(run: Run) -> tuple[float | None, bool]:
    c = run.meta.controller or {}
    kp = c.get("kp")
    return (None if kp is None else float(kp)), bool(c.get("flow_model", True))


def run_flows(run: Run, *, model=None) -> tuple[pd.DataFrame, str]:
    """Target and actual flow of one position_control run on the encoder time base.

    Parameters
    ----------
    run : a position_control run
    model : :class:`~seanv_analysis.models.ValveModel` used for the target
        when Q_ref is empty and the run has no flow model

    Returns
    -------
    (DataFrame, source)
        columns ``t_s`` [s], ``q_ref_mm3_s`` (target), ``q_mm3_s`` (actual,
        Q = v A), ``position_mm``, ``x_ref_mm``, ``p_load_mpag``,
        ``load_level_mpag``; ``source`` is 'q_ref' | 'kp_error' | 'model'.

    Raises
    ------
    DataError
        not a position_control run, or no way to build the target flow.
    """
    if run.meta.kind != "position_control":
        raise DataError(f"kind {run.meta.kind!r}; expected a position_control run",
                        path=run.meta.path)
    d = derive_samples(run)
    t = d["t_s"].to_numpy(np.float64)
    q_ref = d["q_ref_mm3_s"].to_numpy(np.float64) if "q_ref_mm3_s" in d else np.full(t.size, np.nan)
    source = "q_ref"
    if not np.isfinite(q_ref).any():
        kp, flow_model = _controller_info(run)
        ctrl = run.tables.get("controller")
        if flow_model and kp is not None and ctrl is not None and len(ctrl):
            tc = ctrl["t_s"].to_numpy(np.float64)
            enc = run.tables["encoder"]
            x_c = np.interp(tc, enc["t_s"].to_numpy(np.float64),
                            enc["position_mm"].to_numpy(np.float64))
            q_c = kp * (ctrl["x_ref_mm"].to_numpy(np.float64) - x_c)
            i = np.searchsorted(tc, t, side="right") - 1
            q_ref = np.where(i >= 0, q_c[np.clip(i, 0, None)], np.nan)
            source = "kp_error"
        elif model is not None and "cam_cmd_deg" in d:
            pt = d["p_tank_mpag"].to_numpy(np.float64) if "p_tank_mpag" in d else 0.0
            q_ref = np.asarray(model.net_flow(d["cam_cmd_deg"].to_numpy(np.float64),
                                              d["p_supply_mpag"].to_numpy(np.float64),
                                              d["p_head_mpag"].to_numpy(np.float64), pt),
                               dtype=np.float64)
            source = "model"
        else:
            raise DataError("q_ref_mm3_s is empty and the run has no flow model (or no kp); "
                            "expected a valve model (--model) to compute the target flow",
                            path=run.meta.path, column="q_ref_mm3_s")
    p_load = d["p_load_mpag"].to_numpy(np.float64) if "p_load_mpag" in d else np.full(t.size, np.nan)
    out = pd.DataFrame({
        "t_s": t, "q_ref_mm3_s": q_ref, "q_mm3_s": d["q_mm3_s"].to_numpy(np.float64),
        "position_mm": d["position_mm"].to_numpy(np.float64),
        "x_ref_mm": d["x_ref_mm"].to_numpy(np.float64) if "x_ref_mm" in d else np.nan,
        "p_load_mpag": p_load, "load_level_mpag": load_levels_mpag(t, p_load),
    })
    return out, source


def _after_change(t: np.ndarray, df: pd.DataFrame, window_s: float) -> np.ndarray:
    """True within ``window_s`` after a reference or load-level change."""
    changes = []
    for col in ("x_ref_mm", "load_level_mpag"):
        v = df[col].to_numpy(np.float64)
        ok = np.isfinite(v)
        idx = np.flatnonzero(ok[1:] & ok[:-1] & (np.diff(v) != 0)) + 1
        changes.append(t[idx])
    tc = np.sort(np.concatenate(changes))
    if tc.size == 0 or window_s <= 0:
        return np.zeros(t.size, dtype=bool)
    k = np.searchsorted(tc, t, side="right") - 1
    since = np.where(k >= 0, t - tc[np.clip(k, 0, None)], np.inf)
    return since <= window_s


def _shifted(t: np.ndarray, q: np.ndarray, lag_s: float) -> np.ndarray:
    """q(t + lag) by linear interpolation; NaN outside the record."""
    tq = t + lag_s
    out = np.interp(tq, t, q)
    out[(tq < t[0]) | (tq > t[-1])] = np.nan
    return out


@dataclass
class RunTracking:
    """Tracking of one run.

    Attributes
    ----------
    run_id : the run
    target_source : 'q_ref' | 'kp_error' | 'model'
    lag : this run's own delay estimate (None if it failed; ``lag_s``)
    shift_s : shift applied to this run's actual flow [s] (the data set's:
        given, or the pooled estimate)
    rmse_mm3_s, bias_mm3_s : of (shifted actual - target) inside the range [mm^3/s]
    rmse_supply_mm3_s, rmse_drain_mm3_s : same, target >= 0 / < 0 [mm^3/s]
    n_samples : samples inside the range
    rmse_by_load_mm3_s : {load level [MPaG]: RMSE [mm^3/s]}
    data : t_s, q_ref_mm3_s, q_mm3_s, q_shifted_mm3_s, in_range, position_mm,
        x_ref_mm, p_load_mpag, load_level_mpag, after_change (within the
        applied delay after a reference or load change: highlighted in Fig. 7)
    """

    run_id: str
    target_source: str
    lag: LagEstimate | None
    shift_s: float
    rmse_mm3_s: float
    bias_mm3_s: float
    rmse_supply_mm3_s: float
    rmse_drain_mm3_s: float
    n_samples: int
    rmse_by_load_mm3_s: dict[float, float]
    data: pd.DataFrame = field(repr=False)
    run: Run | None = field(default=None, repr=False)

    @property
    def lag_s(self) -> float:
        """Per-run estimated delay [s] (NaN when the estimate failed)."""
        return self.lag.lag_s if self.lag is not None else math.nan

    @property
    def lag_estimate(self) -> Estimate:
        """This run's delay as an :class:`~seanv_analysis.estimate.Estimate`
        named '<run_id>.lag' (value NaN, 'not_estimated', when it failed)."""
        if self.lag is None:
            return Estimate(f"{self.run_id}.lag", math.nan, "s", source="not_estimated",
                            note="the run's delay estimate failed")
        return self.lag.estimate(f"{self.run_id}.lag")

    def row(self) -> dict[str, Any]:
        """The run's row of ``Tracking.per_run``: its lag estimate's columns
        (``lag_s``, ``lag_ci95_lo_s``, ``lag_ci95_hi_s``), shift, RMSEs."""
        return {"run_id": self.run_id, "target_source": self.target_source,
                **self.lag_estimate.wide_items(),
                "shift_s": self.shift_s, "rmse_mm3_s": self.rmse_mm3_s,
                "bias_mm3_s": self.bias_mm3_s, "rmse_supply_mm3_s": self.rmse_supply_mm3_s,
                "rmse_drain_mm3_s": self.rmse_drain_mm3_s, "n_samples": self.n_samples}


@dataclass
class Tracking(JsonResult):
    """Flow tracking of a set of position_control runs (``tracking --json`` contract).

    Names: a *lag* is an estimate (of the data set pooled, ``lag_s``, or of
    a run, ``runs[].lag_s``); the *shift* is the delay compensated (``shift_s``).

    Attributes
    ----------
    shift_s : delay compensated [s]: given, or the pooled estimate
    shift_source : 'given' | 'estimated'
    lag : pooled :class:`LagEstimate` of the runs with a commanded Q_ref
        (also computed when the shift is given, for reference; None if it
        failed); ``lag_s`` and ``lag_ci95_s`` read it
    rmse_mm3_s, bias_mm3_s : pooled over the in-range samples of the
        ``pooled_runs`` (the runs with a commanded Q_ref, as the paper's
        Fig. 7(b)), residual = shifted actual - target [mm^3/s]
    rmse_supply_mm3_s, rmse_drain_mm3_s : target >= 0 / < 0 [mm^3/s]
    rmse_by_load_mm3_s : {load level [MPaG]: RMSE}
    range_mm3_s : (lo, hi) target range, inclusive [mm^3/s]
    n_samples : in-range samples
    runs : per-run :class:`RunTracking`
    skipped : {run_id: reason}
    warnings : messages worth reading
    pooled_runs : run_ids the headline numbers pool
    pooled : what they are, in words ("runs with a commanded Q_ref", or
        "all runs: none had a commanded Q_ref ...")
    """

    shift_s: float
    shift_source: str
    lag: LagEstimate | None
    rmse_mm3_s: float
    bias_mm3_s: float
    rmse_supply_mm3_s: float
    rmse_drain_mm3_s: float
    rmse_by_load_mm3_s: dict[float, float]
    range_mm3_s: tuple[float, float]
    n_samples: int
    runs: list[RunTracking]
    skipped: dict[str, str] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    pooled_runs: list[str] = field(default_factory=list)
    pooled: str = POOLED_COMMANDED

    @property
    def success(self) -> bool:
        return self.n_samples > 0 and math.isfinite(self.rmse_mm3_s)

    @property
    def lag_s(self) -> float:
        """The pooled delay estimate [s] (NaN when it failed)."""
        return self.lag.lag_s if self.lag is not None else math.nan

    @property
    def lag_ci95_s(self) -> tuple[float, float] | None:
        """95 % interval of the pooled delay estimate [s]; None without one."""
        return None if self.lag is None else self.lag.ci95_s

    @property
    def params(self) -> Estimates:
        """The delay estimates as :class:`~seanv_analysis.estimate.Estimate`
        [s], as lmfit's ``result.params``: ``'lag'`` (pooled over the runs
        with a commanded Q_ref; the JSON's ``lag_s``, ``lag_ci95_s``) and
        ``'<run_id>.lag'`` per run (``runs[].lag_s``, ``per_run``'s
        ``lag_s``, ``lag_ci95_lo_s``, ``lag_ci95_hi_s``)."""
        return Estimates((e.name, e) for e in (self._pooled_lag(),
                                               *(r.lag_estimate for r in self.runs)))

    def _pooled_lag(self) -> Estimate:
        """The pooled delay estimate (``params['lag']``)."""
        if self.lag is None:
            return Estimate("lag", math.nan, "s", source="not_estimated",
                            note="the pooled delay estimate failed")
        return self.lag.estimate("lag", constrained_by=f"{len(self.pooled_runs)} runs: "
                                                       f"{self.pooled}")

    @property
    def per_run(self) -> pd.DataFrame:
        """One row per run (lag estimate, applied shift, RMSE, bias, per side;
        ``pooled``: in the headline numbers)."""
        return pd.DataFrame([{**r.row(), "pooled": r.run_id in self.pooled_runs}
                             for r in self.runs])

    def to_json_dict(self) -> dict[str, Any]:
        """The ``tracking --json`` document: ``shift_s`` the delay compensated,
        ``lag_s`` the pooled estimate, ``runs[].lag_s`` each run's own estimate."""
        lag = self._pooled_lag()
        return {"shift_s": json_num(self.shift_s), "shift_source": self.shift_source,
                lag.key: json_num(lag.value),
                lag.ci95_key: None if self.lag_ci95_s is None else [json_num(v) for v in lag.ci95],
                "rmse_mm3_s": json_num(self.rmse_mm3_s), "bias_mm3_s": json_num(self.bias_mm3_s),
                "range_mm3_s": [float(self.range_mm3_s[0]), float(self.range_mm3_s[1])],
                "n_samples": int(self.n_samples),
                "pooled": self.pooled, "pooled_runs": list(self.pooled_runs),
                "runs": [{"run_id": r.run_id, "target_source": r.target_source,
                          "pooled": r.run_id in self.pooled_runs, "lag_s": json_num(r.lag_s),
                          "rmse_mm3_s": json_num(r.rmse_mm3_s)} for r in self.runs]}

    def details(self) -> dict[str, Any]:
        """More than :meth:`to_json_dict`: per side/load RMSE, lag estimates, skipped runs."""
        return {**self.to_json_dict(),
                "rmse_supply_mm3_s": json_num(self.rmse_supply_mm3_s),
                "rmse_drain_mm3_s": json_num(self.rmse_drain_mm3_s),
                "rmse_by_load_mm3_s": {f"{k:g}": json_num(v) for k, v in self.rmse_by_load_mm3_s.items()},
                "lag_estimate": None if self.lag is None else self.lag.to_json_dict(),
                "runs_detail": [{k: (json_num(v) if isinstance(v, float) else v)
                                 for k, v in r.row().items()} for r in self.runs],
                "skipped": dict(self.skipped), "warnings": list(self.warnings),
                "residual_sign": "actual (shifted) - target"}

    def __repr__(self) -> str:
        lo, hi = self.range_mm3_s
        return (f"<Tracking shift {self.shift_s:.3f} s ({self.shift_source}), RMSE "
                f"{self.rmse_mm3_s:.4g} mm^3/s over Q_ref in [{lo:g}, {hi:g}] mm^3/s; "
                f"{len(self.runs)} runs" + (f", {len(self.skipped)} skipped" if self.skipped
                                             else "") + ">")

    def plot(self, ax=None, **kwargs):
        """Fig. 7 on ``ax`` (a new pyplot figure when None): ``panel='b'`` actual
        vs target flow (the logged-Q_ref runs), ``'a'`` flows against time of ``run``; returns the axes."""
        from ..plotting import plot

        return plot(self, ax, **kwargs)

    def to_frame(self) -> pd.DataFrame:
        """One row per tracked run: lag_s (its estimate), shift_s, rmse_mm3_s... (``per_run``)."""
        return self.per_run

    def skipped_runs(self) -> dict[str, str]:
        """{run_id: why} of the runs that could not be used."""
        return dict(self.skipped)

    def report(self) -> str:
        """Plain-text summary."""
        lo, hi = self.range_mm3_s
        lines = ["Flow tracking during position control (paper Sec. III-C.2, Fig. 7)"]
        if self.shift_source == "given":
            est = f" (estimated: {self.lag.report()})" if self.lag is not None else ""
            lines.append(f"  delay: {self.shift_s:.3f} s given{est}")
        else:
            lines.append(f"  delay: estimated, {self.lag.report() if self.lag else 'failed'}")
        lines.append(f"  actual shifted earlier by {self.shift_s:.4f} s; target range "
                     f"[{lo:g}, {hi:g}] mm^3/s, {self.n_samples} samples of the "
                     f"{self.pooled} ({', '.join(self.pooled_runs)})")
        lines.append(f"  RMSE {self.rmse_mm3_s:.1f} mm^3/s (paper: 516, its run with a "
                     f"commanded Q_ref), bias {self.bias_mm3_s:+.1f} mm^3/s (actual - target)")
        lines.append(f"  per side: supply {self.rmse_supply_mm3_s:.1f}, drain "
                     f"{self.rmse_drain_mm3_s:.1f} mm^3/s")
        if self.rmse_by_load_mm3_s:
            lines.append("  per load level: " + ", ".join(
                f"{k:g} MPaG {v:.1f}" for k, v in sorted(self.rmse_by_load_mm3_s.items())))
        lines.append(f"  {'run':<32} {'lag est [s]':>11} {'RMSE':>8} {'bias':>8} {'n':>7}  target")
        for r in self.runs:
            lines.append(f"  {r.run_id:<32} {r.lag_s:>11.4f} {r.rmse_mm3_s:>8.1f} "
                         f"{r.bias_mm3_s:>+8.1f} {r.n_samples:>7d}  {_SOURCE_WORDS[r.target_source]}")
        for rid, why in self.skipped.items():
            lines.append(f"  skipped {rid}: {why}")
        for w in self.warnings:
            lines.append(f"  warning: {w}")
        return "\n".join(lines)

#: a run's target, in words (the report's run table)
_SOURCE_WORDS = {"q_ref": "commanded Q_ref (logged)",
                 "kp_error": "commanded Q_ref = Kp e (from the logged error)",
                 "model": "implied by the valve model (not pooled)"}


def _summary(resid: np.ndarray, target: np.ndarray, load: np.ndarray):
    sup = target >= 0
    by_load = {}
    for lvl in np.unique(load[np.isfinite(load)]):
        m = load == lvl
        by_load[float(lvl)] = _rmse(resid[m])
    return (_rmse(resid), float(np.mean(resid)) if resid.size else math.nan,
            _rmse(resid[sup]), _rmse(resid[~sup]), by_load)


def tracking_runs(runs: Iterable[Run], *, shift_s: float | None = None,
                  q_range: Sequence[float] = DEFAULT_Q_RANGE_MM3_S, model=None,
                  max_lag_s: float = 1.0, seed: int = 0) -> Tracking:
    """Flow tracking of position_control runs (paper Fig. 7).

    Parameters
    ----------
    runs : runs of any kind (only position_control runs are used)
    shift_s : delay [s] to compensate (the paper's 0.25); None: estimate it
        (pooled over the runs)
    q_range : (lo, hi) target-flow range [mm^3/s], inclusive
    model : valve model for runs without Q_ref and without flow model
    max_lag_s : lag search range [s]
    seed : bootstrap seed of the lag interval

    Returns
    -------
    Tracking

    Raises
    ------
    ConfigError
        ``q_range`` not (lo, hi) with lo < hi, or ``shift_s`` not finite.
    DataError
        no usable position_control run.

    Notes
    -----
    RMSE = sqrt(mean((Q(t + lag) - Q_ref(t))^2)) over the samples with
    lo <= Q_ref(t) <= hi and Q(t + lag) inside the record; the per-run RMSE
    uses the same (pooled or given) lag. The pooled lag estimate and the
    headline numbers are over the runs with a commanded Q_ref
    (:data:`COMMANDED`; all runs when none has one): the paper's Fig. 7(b).
    """
    if len(q_range) != 2 or not float(q_range[0]) < float(q_range[1]):
        raise ConfigError(f"q_range: expected (lo, hi) with lo < hi, got {tuple(q_range)}")
    lo, hi = float(q_range[0]), float(q_range[1])
    if shift_s is not None and not math.isfinite(float(shift_s)):
        raise ConfigError(f"shift_s: expected a finite number of seconds, got {shift_s!r}")
    flows: list[tuple[Run, pd.DataFrame, str]] = []
    skipped: dict[str, str] = {}
    notes: list[str] = []
    for run in runs:
        if run.meta.kind != "position_control":
            continue
        try:
            df, source = run_flows(run, model=model)
        except DataError as exc:
            skipped[run.run_id] = str(exc)
            warnings.warn(f"tracking: skipped run {run.run_id}: {exc}", stacklevel=2)
            continue
        flows.append((run, df, source))
    if not flows:
        why = (f" ({len(skipped)} skipped; first: {' '.join(next(iter(skipped.values())).split())})"
               if skipped else "")
        raise DataError(f"no usable position_control run{why}; expected at least one with a "
                        "target flow (q_ref_mm3_s, flow-model kp, or --model)")
    segs = [(df.t_s.to_numpy(), df.q_ref_mm3_s.to_numpy(), df.q_mm3_s.to_numpy())
            for _, df, _ in flows]
    # the headline pools the runs with a commanded Q_ref (all, if none has one)
    pool = [i for i, (_, _, src) in enumerate(flows) if src in COMMANDED] or list(range(len(flows)))
    pooled_what = POOLED_COMMANDED if flows[pool[0]][2] in COMMANDED else POOLED_ALL
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        pooled = estimate_lag_segments([segs[i] for i in pool], max_lag_s=max_lag_s, seed=seed)
        per_run = []
        for seg in segs:
            try:
                per_run.append(estimate_lag(*seg, max_lag_s=max_lag_s, seed=seed))
            except DataError as exc:
                notes.append(f"per-run lag failed: {exc}")
                per_run.append(None)
    notes.extend(str(w.message) for w in caught)
    if shift_s is not None:
        lag_s, source = float(shift_s), "given"
    else:
        if not pooled.success:
            raise DataError(f"the delay could not be estimated ({pooled.message}); "
                            "give it with shift_s")
        lag_s, source = pooled.lag_s, "estimated"
    results = []
    all_r, all_q, all_l = [], [], []
    for i, ((run, df, tsrc), lag) in enumerate(zip(flows, per_run)):
        t = df.t_s.to_numpy()
        q = df.q_ref_mm3_s.to_numpy()
        qs = _shifted(t, df.q_mm3_s.to_numpy(), lag_s)
        inside = np.isfinite(q) & np.isfinite(qs) & (q >= lo) & (q <= hi)
        data = df.assign(q_shifted_mm3_s=qs, in_range=inside,
                         after_change=_after_change(t, df, abs(lag_s)))
        resid = (qs - q)[inside]
        rmse, bias, rs, rd, by_load = _summary(resid, q[inside],
                                               df.load_level_mpag.to_numpy()[inside])
        results.append(RunTracking(run.run_id, tsrc, lag, lag_s,
                                   rmse, bias, rs, rd, int(inside.sum()), by_load, data, run))
        if i not in pool:
            continue
        all_r.append(resid)
        all_q.append(q[inside])
        all_l.append(df.load_level_mpag.to_numpy()[inside])
    resid = np.concatenate(all_r)
    rmse, bias, rs, rd, by_load = _summary(resid, np.concatenate(all_q), np.concatenate(all_l))
    if resid.size == 0:
        notes.append(f"no sample has its target inside [{lo:g}, {hi:g}] mm^3/s")
    return Tracking(lag_s, source, pooled if pooled.success else None, rmse, bias, rs, rd,
                    by_load, (lo, hi), int(resid.size), results, skipped, notes,
                    pooled_runs=[flows[i][0].run_id for i in pool], pooled=pooled_what)

