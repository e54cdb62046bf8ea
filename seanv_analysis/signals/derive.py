"""Derived signals and per-run flow of a flow-step run (paper Sec. II-D.2).

Three stages, each a flat function:

- :func:`velocity_mm_s`: actuator velocity [mm/s] from encoder position with
  a Savitzky-Golay derivative (noise-robust; window from the rig config's
  ``analysis.derivative_window_s``).
- :func:`derive_samples`: a run's aligned table plus ``velocity_mm_s``,
  ``q_mm3_s`` (Q = v A), ``dp_supply_mpa`` and ``dp_drain_mpa``.
- :func:`summarize_run`: one per-run summary row (``SUMMARY_COLUMNS``) with
  two flow estimates: the paper's peak method and a steady-motion estimate
  (:func:`estimate_flow`).

:func:`derive_columns` is :func:`derive_samples` on numpy arrays (same
numbers); :func:`summarize_run` and :func:`estimate_flow` use it when no
derived table is given, so summarising a run builds no DataFrame (the
per-run work of every data set: pandas only at the data-set level).

Units: s, mm, mm/s, mm^2, mm^3/s, MPa (gauge), deg.
"""
from __future__ import annotations

import functools
import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from typing import Any, Mapping

import numpy as np
import pandas as pd

from ..errors import ConfigError, DataError
from ..io.run import Run
from ..io.run_tables import table_columns
from ..models import flow_from_velocity, side_pressures
from .align import align_run, align_run_columns, interp_sorted
from .savgol import moving_average, savgol_derivative
from .stats import median, nanmean, nanmedian

__all__ = [
    "FLOW_METHODS", "DEFAULT_MAX_JITTER", "DEFAULT_SETTLE_BAND",
    "DerivativeInfo", "velocity_mm_s", "derive_samples", "derive_columns", "derive_flow",
    "StepWindow", "step_window", "FlowEstimate", "estimate_flow", "summarize_run",
]

#: Per-run flow methods: 'steady' (default) and the paper's 'peak'.
FLOW_METHODS = ("steady", "peak")

#: Largest timestamp jitter, as a fraction of the median sample interval, for
#: which samples are taken as uniform; above it the position is resampled.
DEFAULT_MAX_JITTER = 0.01

#: Half-width of the "near-constant velocity" band of the steady method, as a
#: fraction of the steady velocity (never narrower than the leakage velocity).
#: The window starts where the smoothed velocity enters this band, so a
#: monotone approach (a flow that rises with a first-order lag, time
#: constant tau) leaves a deficit of up to band x tau / window in the mean:
#: 5 % gave -0.5..-1 % on C for a rig with tau = 0.15..0.2 s and 0.5 s
#: windows; 1 % keeps it below 0.3 %. Noisy or ringing runs that never stay
#: inside 1 % fall back to the unsettled rule (mean over the second half).
DEFAULT_SETTLE_BAND = 0.01

# Columns summarize_run fills (SUMMARY_COLUMNS minus run_index, excluded,
# excluded_detail, which the data-set stage and the filters add).
_SUMMARY_KEYS = ("run_id", "kind", "side", "started_at", "load_mpag", "cam_deg",
                 "cam_measured_deg", "cam_approach", "q_mm3_s", "q_peak_mm3_s",
                 "q_steady_mm3_s", "dp_mpa", "p1_mpa", "flow_method", "motion_steady")


# ---------------------------------------------------------------------------
# velocity
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class DerivativeInfo:
    """How :func:`velocity_mm_s` differentiated a position record.

    Attributes
    ----------
    window_samples : Savitzky-Golay window length [samples] (odd)
    window_s : that window in time, ``window_samples * dt_s`` [s]
    requested_window_s : the ``window_s`` asked for [s]
    polyorder : polynomial order of the local fit
    dt_s : uniform sample interval used (median of the timestamps' steps) [s]
    sample_rate_hz : ``1 / dt_s`` [Hz]
    jitter : largest ``|t[i+1] - t[i] - dt_s| / dt_s`` of the input
    resampled : True when the jitter exceeded the tolerance and the position
        was linearly resampled onto a uniform grid (velocity interpolated
        back to the input timestamps)
    edge_s : half window ``(window_samples // 2) * dt_s`` [s]; velocities
        closer than this to either end come from an off-centre fit
    valid_start_s, valid_end_s : first and last instant [s] whose velocity
        comes from a centred window (outside: edge samples)
    edge_mode : how edges are handled ('interp': polynomial fitted to the
        first/last full window and differentiated there)
    """

    window_samples: int
    window_s: float
    requested_window_s: float
    polyorder: int
    dt_s: float
    sample_rate_hz: float
    jitter: float
    resampled: bool
    edge_s: float
    valid_start_s: float
    valid_end_s: float
    edge_mode: str = "interp"

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (JSON-ready)."""
        return {k: (v.item() if isinstance(v, np.generic) else v)
                for k, v in asdict(self).items()}

    def report(self) -> str:
        """One-line description of the derivative used."""
        how = "resampled to uniform" if self.resampled else "uniform"
        return (f"Savitzky-Golay derivative: {self.window_samples} samples = "
                f"{self.window_s * 1e3:.1f} ms (asked {self.requested_window_s * 1e3:.1f} ms), "
                f"order {self.polyorder}, {self.sample_rate_hz:.1f} Hz ({how}, jitter "
                f"{self.jitter:.2%}); edges ({self.edge_s * 1e3:.1f} ms each end) from an "
                f"off-centre fit")


def _window_samples(window_s: float, dt_s: float, polyorder: int) -> int:
    """Nearest odd sample count to ``window_s / dt_s``, at least polyorder + 2."""
    # ties (an even window_s / dt) round up; 1e-6 absorbs float noise in dt
    n = 2 * math.floor((window_s / dt_s - 1.0) / 2.0 + 0.5 + 1e-6) + 1
    n_min = polyorder + 2
    n_min += 1 - n_min % 2
    return max(n, n_min)


def velocity_mm_s(t_s, position_mm, *, window_s: float, polyorder: int,
                  max_jitter: float = DEFAULT_MAX_JITTER) -> tuple[np.ndarray, DerivativeInfo]:
    """Actuator velocity from encoder position, Savitzky-Golay derivative.

    v(t_i) = d/dt of the least-squares polynomial of order ``polyorder``
    fitted to the ``window_samples`` positions centred on t_i
    (:func:`.savgol.savgol_derivative`, scipy's ``savgol_filter(deriv=1,
    mode='interp')`` without importing scipy.signal).

    Parameters
    ----------
    t_s : array [s], strictly increasing
    position_mm : array [mm], same length, finite
    window_s : derivative window [s] (rig config ``analysis.derivative_window_s``).
        The sample count is the odd integer nearest to ``window_s / dt``, and
        at least ``polyorder + 2``.
    polyorder : order of the local polynomial (``analysis.derivative_polyorder``), >= 1
    max_jitter : largest timestamp jitter (fraction of the median step) for
        which the samples are taken as uniform.

    Returns
    -------
    v : ndarray [mm/s], one value per input sample
    info : :class:`DerivativeInfo` with the window used, the sample rate and
        the edge span

    Raises
    ------
    ConfigError
        ``window_s`` not a positive number, ``polyorder`` below 1.
    DataError
        Arrays of different lengths, non-finite values, timestamps not
        strictly increasing, or fewer samples than the window.

    Notes
    -----
    *Sampling.* dt is the median timestamp step. When every step is within
    ``max_jitter * dt`` of it the samples are taken as uniform. Otherwise
    (jitter, dropped samples) the position is linearly interpolated onto a
    uniform grid of step dt, differentiated there and the velocity linearly
    interpolated back to the input timestamps (``info.resampled``). Across a
    gap this gives the mean velocity over the gap.

    *Edges.* as ``savgol_filter(mode='interp')``: the first and last
    ``window_samples // 2`` samples take the derivative of the polynomial
    fitted to the first/last full window, evaluated off-centre. Exact for
    polynomial motion up to ``polyorder``, but noisier and (for curved
    motion) biased; ``info.valid_start_s``/``valid_end_s`` bound the
    centred part, and the flow estimates of this module use only that part.

    *Response.* For order 1 or 2 the derivative filter is the slope of a
    centred least-squares line: constant and linear-in-time velocities are
    exact, a sine of frequency f is attenuated by about
    ``(2 pi f T)^2 / 10`` with T = half window (0.25 % at 1 Hz, 1 % at 2 Hz
    for the default 51 ms). Position noise sigma gives velocity noise
    ``sigma / (dt sqrt(sum k^2))``, ~9.5 sigma/mm per mm/s at 51 samples, 1 kHz.

    Examples
    --------
    >>> t = np.arange(0, 1, 0.001)
    >>> v, info = velocity_mm_s(t, 10 + 5.0 * t, window_s=0.051, polyorder=2)
    >>> round(float(v[500]), 6), info.window_samples
    (5.0, 51)
    """
    if not (isinstance(window_s, (int, float, np.floating)) and math.isfinite(window_s)
            and window_s > 0):
        raise ConfigError(f"window_s: expected a positive number of seconds, got {window_s!r}")
    if int(polyorder) != polyorder or polyorder < 1:
        raise ConfigError(f"polyorder: expected an integer >= 1, got {polyorder!r}")
    polyorder = int(polyorder)
    t = np.asarray(t_s, dtype=np.float64).ravel()
    x = np.asarray(position_mm, dtype=np.float64).ravel()
    if t.size != x.size:
        raise DataError(f"t_s has {t.size} samples but position_mm {x.size}; expected equal "
                        "lengths")
    for name, a in (("t_s", t), ("position_mm", x)):
        with np.errstate(over="ignore", invalid="ignore"):
            total = np.add.reduce(a)
        if np.isfinite(total):
            continue  # one pass, no temporary: a NaN or inf would make the sum non-finite
        bad = np.flatnonzero(~np.isfinite(a))
        if bad.size:
            raise DataError(f"value {a[bad[0]]!r} at index {bad[0]}; expected a finite number",
                            column=name)
    if t.size < 2:
        raise DataError(f"{t.size} sample(s); expected at least two", column="position_mm")
    steps = np.diff(t)
    lo, hi = float(steps.min()), float(steps.max())
    if lo <= 0:
        i = int(np.flatnonzero(steps <= 0)[0]) + 1
        raise DataError(f"t_s[{i}] = {t[i]!r} after {t[i - 1]!r}; expected strictly increasing "
                        "timestamps", column="t_s")
    dt = median(steps)
    jitter = max(hi - dt, dt - lo) / dt                   # = max |step - dt| / dt
    del steps
    n = _window_samples(float(window_s), dt, polyorder)
    resampled = jitter > max_jitter
    if resampled:
        m = int(math.floor((t[-1] - t[0]) / dt + 1e-9)) + 1
        t_u = t[0] + dt * np.arange(m)
        x_u = np.interp(t_u, t, x)
    else:
        t_u, x_u = t, x
    if x_u.size < n:
        raise DataError(f"{x_u.size} samples, fewer than the {n}-sample derivative window "
                        f"({window_s} s at {1 / dt:.4g} Hz); expected a longer record",
                        column="position_mm")
    v_u = savgol_derivative(x_u, n, polyorder, deriv=1, delta=dt)   # scipy mode="interp"
    v = np.interp(t, t_u, v_u) if resampled else v_u
    half = n // 2
    info = DerivativeInfo(window_samples=n, window_s=n * dt, requested_window_s=float(window_s),
                          polyorder=polyorder, dt_s=dt, sample_rate_hz=1.0 / dt, jitter=jitter,
                          resampled=bool(resampled), edge_s=half * dt,
                          valid_start_s=float(t_u[half]), valid_end_s=float(t_u[-1 - half]))
    return v, info


# ---------------------------------------------------------------------------
# derived samples
# ---------------------------------------------------------------------------

def _n_rows(cols: Mapping[str, np.ndarray]) -> int:
    """Rows of a {column: array} table (0 without columns)."""
    return len(next(iter(cols.values()))) if cols else 0


def _col(table, name: str) -> np.ndarray:
    """Column ``name`` of a DataFrame or a {column: array} table as float64 numpy."""
    return np.asarray(table[name], dtype=np.float64)


def _tank_pressure(df, rig) -> np.ndarray | float:
    if "p_tank_mpag" in df:
        return _col(df, "p_tank_mpag")
    return float(rig["supply"]["tank_pressure_mpag"])


#: encoder records at least this long (200 s at 1 kHz) get their derivative
#: computed on a helper thread while the streams are aligned (~0.1 s saved
#: per hour of 1 kHz; a thread per call, so nothing survives a fork)
_OVERLAP_MIN_SAMPLES = 200_000


def _add_column(df: pd.DataFrame, name: str, values: np.ndarray) -> None:
    """``df[name] = values`` for an array this module made, without the copy
    ``df[name] = ndarray`` takes (29 MB per column on an hour of 1 kHz)."""
    df[name] = pd.Series(values, index=df.index, copy=False)


def _derive(run: Run, align, *, window_s: float | None, polyorder: int | None, overlap: bool):
    """(aligned table, {velocity_mm_s, q_mm3_s, dp_supply_mpa, dp_drain_mpa},
    DerivativeInfo) of :func:`derive_samples`; ``align(run)`` gives the
    aligned table (a DataFrame or {column: array}); ``overlap``: a long
    record's derivative may run on a helper thread beside it."""
    analysis = run.rig.analysis
    window_s = float(analysis["derivative_window_s"]) if window_s is None else window_s
    polyorder = int(analysis["derivative_polyorder"]) if polyorder is None else polyorder
    enc = table_columns(run.tables, "encoder") if "encoder" in run.tables else None
    if enc is not None and not _n_rows(enc):
        enc = None
    derivative = helper = pending = None
    if enc is not None:
        derivative = functools.partial(velocity_mm_s, enc["t_s"], enc["position_mm"],
                                       window_s=window_s, polyorder=polyorder)
        if overlap and enc["t_s"].size >= _OVERLAP_MIN_SAMPLES:
            # a long record: the derivative (np.correlate) and the alignment
            # (np.interp) both release the GIL, so they run side by side
            helper = ThreadPoolExecutor(max_workers=1, thread_name_prefix="seanv-derive")
            pending = helper.submit(derivative)
    try:
        df = align(run)
        for col in ("t_s", "p_supply_mpag", "p_head_mpag"):
            if col not in df:
                raise DataError(f"aligned table has no '{col}' column; expected the contract's "
                                "columns", path=run.meta.path, column=col)
    finally:
        if helper is not None:
            helper.shutdown(wait=True)   # the derivative is done (or its error kept)
    if enc is not None:
        v_enc, info = pending.result() if pending is not None else derivative()
        v = interp_sorted(_col(df, "t_s"), np.asarray(enc["t_s"], dtype=np.float64), v_enc,
                          copy=False)  # v_enc is ours: on the encoder's clock, a view of it
    else:
        if "position_mm" not in df:
            raise DataError("no encoder table and no 'position_mm' column; expected one",
                            path=run.meta.path, column="position_mm")
        v, info = velocity_mm_s(np.asarray(df["t_s"]), np.asarray(df["position_mm"]),
                                window_s=window_s, polyorder=polyorder)
    ps = _col(df, "p_supply_mpag")
    ph = _col(df, "p_head_mpag")
    pt = _tank_pressure(df, run.rig)
    return df, {"velocity_mm_s": v,
                "q_mm3_s": flow_from_velocity(v, run.rig.piston_area_mm2),
                "dp_supply_mpa": side_pressures("supply", ps, ph, pt)[1],
                "dp_drain_mpa": side_pressures("drain", ps, ph, pt)[1]}, info


def derive_samples(run: Run, *, aligned: pd.DataFrame | None = None,
                   window_s: float | None = None, polyorder: int | None = None) -> pd.DataFrame:
    """A run's aligned table with velocity, flow and the two sides' dp.

    Parameters
    ----------
    run : the run (its ``rig`` gives the piston area and the derivative settings)
    aligned : the run's streams on one time base (default ``align_run(run)``)
    window_s : derivative window [s] (default ``rig.analysis['derivative_window_s']``)
    polyorder : Savitzky-Golay order (default ``rig.analysis['derivative_polyorder']``)

    Returns
    -------
    DataFrame
        ``aligned`` plus ``velocity_mm_s`` [mm/s], ``q_mm3_s`` = v A [mm^3/s]
        (A = ``run.rig.piston_area_mm2``, 201.06 mm^2), ``dp_supply_mpa`` =
        p_supply - p_head [MPa] and ``dp_drain_mpa`` = p_head - p_tank [MPa]
        (p_tank from ``p_tank_mpag`` or the rig's ``supply.tank_pressure_mpag``).
        ``attrs['velocity']`` holds :meth:`DerivativeInfo.to_dict` (window used,
        edge span).

    Raises
    ------
    DataError
        a required column is missing, or the position record is unusable
        (see :func:`velocity_mm_s`).

    Notes
    -----
    The velocity is computed on the full encoder table (``run.tables['encoder']``,
    its own timestamps) and linearly interpolated onto ``aligned['t_s']``
    (exact when the aligned base is the encoder's), so the derivative's edge
    samples sit at the encoder record's ends, not at the overlap's.
    :func:`derive_columns` gives the same numbers as numpy arrays, without pandas.
    """
    # align_run(run) is a fresh frame we own; a caller's frame gets a shallow
    # copy (new columns do not touch it). A deep copy here consolidated the
    # blocks and cost more than the derivative itself on an hour of 1 kHz logs.
    df, derived, info = _derive(
        run, align_run if aligned is None else (lambda _run: aligned.copy(deep=False)),
        window_s=window_s, polyorder=polyorder, overlap=aligned is None)
    for name, values in derived.items():
        _add_column(df, name, values)
    df.attrs["velocity"] = info.to_dict()
    return df


def derive_columns(run: Run, *, aligned: Mapping[str, np.ndarray] | None = None,
                   window_s: float | None = None, polyorder: int | None = None
                   ) -> tuple[dict[str, np.ndarray], DerivativeInfo]:
    """:func:`derive_samples` on numpy arrays, without pandas: ({column:
    array}, the derivative used).

    Same parameters (``aligned``: {column: array}, default
    :func:`~seanv_analysis.signals.align.align_run_columns`), columns, units,
    errors and numbers as :func:`derive_samples`; the
    :class:`DerivativeInfo` is what that puts in ``attrs['velocity']``.
    Aligned columns may be views of the run's arrays: read them, do not write.
    """
    cols, derived, info = _derive(
        run, align_run_columns if aligned is None else (lambda _run: dict(aligned)),
        window_s=window_s, polyorder=polyorder, overlap=aligned is None)
    cols.update(derived)
    return cols, info


#: the aligned columns :func:`_derive` reads (beside ``t_s``)
_DERIVE_READS = ("position_mm", "p_supply_mpag", "p_head_mpag", "p_tank_mpag")


def derive_flow(run: Run, *, window_s: float | None = None,
                polyorder: int | None = None) -> dict[str, np.ndarray]:
    """``t_s`` [s], ``position_mm`` [mm] and ``q_mm3_s`` [mm^3/s] of
    :func:`derive_columns` (the same numbers, on the same time base), with
    only the columns the derivation reads aligned: what a comparison of
    actuator flows needs (identify's and discover's replays, one per twin
    they try)."""
    cols, derived, _ = _derive(run, lambda r: align_run_columns(r, columns=_DERIVE_READS),
                               window_s=window_s, polyorder=polyorder, overlap=False)
    return {"t_s": cols["t_s"], "position_mm": cols["position_mm"],
            "q_mm3_s": derived["q_mm3_s"]}


# ---------------------------------------------------------------------------
# step window (servo log)
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class StepWindow:
    """Where a flow-step run holds its cam angle (from the servo log).

    Attributes
    ----------
    t_start_s : first servo sample commanding the run's ``cam_deg`` [s]
    t_end_s : end of that hold: the next command change, or the run's last
        sample [s]
    t_settled_s : instant the cam feedback settled at its hold value [s]
        (from ``cam_deg``; without feedback, from the rig's servo model)
    cam_cmd_deg : commanded angle (run.json ``cam_deg``) [deg]
    cam_measured_deg : median feedback ``cam_deg`` over the hold [deg] (NaN
        without feedback)
    cam_approach : +1 the command reached the angle moving up, -1 moving
        down, 0 unknown (the log starts at the angle)
    settled_from_feedback : True when ``t_settled_s`` comes from feedback
    """

    t_start_s: float
    t_end_s: float
    t_settled_s: float
    cam_cmd_deg: float
    cam_measured_deg: float
    cam_approach: float
    settled_from_feedback: bool

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (JSON-ready)."""
        return asdict(self)


def _longest_true_run(mask: np.ndarray) -> tuple[int, int] | None:
    """(first, last) index of the longest run of True, None if no True."""
    if not mask.any():
        return None
    padded = np.concatenate(([False], mask, [False])).astype(np.int8)
    d = np.diff(padded)
    starts, ends = np.flatnonzero(d == 1), np.flatnonzero(d == -1) - 1
    k = int(np.argmax(ends - starts))
    return int(starts[k]), int(ends[k])


def step_window(run: Run) -> StepWindow:
    """The cam hold of a flow-step run, from ``run.tables['servo']``.

    The hold is the longest stretch of servo samples whose command is within
    the servo resolution (rig ``servo.resolution_deg``) of run.json
    ``cam_deg``. The cam has settled at the first hold sample from which
    three consecutive feedback samples lie within two servo resolutions of
    the hold's median feedback; without feedback, at
    ``t_start + dead_time + |step| / max_rate + 5 time_constant`` (rig
    ``[servo]``).

    Raises
    ------
    DataError
        ``cam_deg`` missing from run.json, no servo table, or no command
        near ``cam_deg`` (the message names the range commanded).
    """
    meta = run.meta
    path = run.files.get("servo", meta.path)
    if meta.cam_deg is None:
        raise DataError("flow_step run has no cam_deg; expected the commanded cam angle",
                        path=run.files.get("run.json", meta.path))
    servo = table_columns(run.tables, "servo") if "servo" in run.tables else None
    if servo is None or not _n_rows(servo):
        raise DataError("no servo table; expected t_s, cam_cmd_deg, cam_deg", path=path)
    cam = float(meta.cam_deg)
    srv = run.rig["servo"]
    res = float(srv["resolution_deg"])
    t = _col(servo, "t_s")
    cmd = _col(servo, "cam_cmd_deg")
    fb = _col(servo, "cam_deg") if "cam_deg" in servo else np.full(t.size, np.nan)
    at_step = np.abs(cmd - cam) <= res
    span = _longest_true_run(at_step)
    if span is None:
        raise DataError(f"no command within {res} deg of run.json cam_deg {cam}; commands span "
                        f"{np.nanmin(cmd):g}..{np.nanmax(cmd):g} deg", path=path,
                        column="cam_cmd_deg")
    i0, i1 = span
    t_start = float(t[i0])
    last_t = max(float(ts[-1]) for ts in (table_columns(run.tables, name)["t_s"]
                                          for name in run.tables) if ts.size)
    t_end = float(t[i1 + 1]) if i1 + 1 < t.size else last_t

    before = cmd[:i0][~at_step[:i0] & np.isfinite(cmd[:i0])]
    prior = float(before[-1]) if before.size else math.nan
    approach = 0.0 if math.isnan(prior) else float(np.sign(cam - prior))

    hold_fb = fb[i0:i1 + 1]
    if np.isfinite(hold_fb).any():
        measured = nanmedian(hold_fb)
        ok = np.abs(hold_fb - measured) <= 2.0 * res
        ok3 = ok.copy()
        ok3[:-2] &= ok[1:-1] & ok[2:]
        j = np.flatnonzero(ok3)
        t_settled = float(t[i0 + j[0]]) if j.size else t_end
        from_fb = True
    else:
        measured = math.nan
        travel = 0.0 if math.isnan(prior) else abs(cam - prior)
        t_settled = (t_start + float(srv["dead_time_s"]) + travel / float(srv["max_rate_deg_s"])
                     + 5.0 * float(srv["time_constant_s"]))
        from_fb = False
    return StepWindow(t_start_s=t_start, t_end_s=t_end, t_settled_s=min(t_settled, t_end),
                      cam_cmd_deg=cam, cam_measured_deg=measured, cam_approach=approach,
                      settled_from_feedback=from_fb)


# ---------------------------------------------------------------------------
# per-run flow
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class FlowEstimate:
    """Per-run flow of a flow-step run by one method.

    Attributes
    ----------
    method : 'steady' or 'peak'
    q_mm3_s : flow [mm^3/s] = velocity x piston area (negative: drain)
    velocity_mm_s : the velocity it comes from [mm/s]
    dp_mpa : side's pressure difference over the window [MPa] (median for
        'peak', mean for 'steady')
    p1_mpa : side's upstream pressure over the window [MPa]
    t_start_s, t_end_s : the window [s]
    n_samples : samples in the window
    moving : False when the actuator did not move (flow is then the mean
        leakage over the settled hold)
    steady : True when the window passed the near-constant-velocity test
        (always False for 'peak')
    success : False when no estimate could be made (values NaN)
    message : how the window was chosen, or why it failed
    """

    method: str
    q_mm3_s: float
    velocity_mm_s: float
    dp_mpa: float
    p1_mpa: float
    t_start_s: float
    t_end_s: float
    n_samples: int
    moving: bool
    steady: bool
    success: bool
    message: str

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (JSON-ready; NaN as None)."""
        return {k: (None if isinstance(v, float) and math.isnan(v) else v)
                for k, v in asdict(self).items()}

    def report(self) -> str:
        """One-line summary."""
        if not self.success:
            return f"{self.method}: no estimate ({self.message})"
        return (f"{self.method}: Q = {self.q_mm3_s:.1f} mm^3/s (v = {self.velocity_mm_s:.4f} mm/s),"
                f" dp = {self.dp_mpa:.3f} MPa, p1 = {self.p1_mpa:.3f} MPa over "
                f"{self.t_start_s:.3f}..{self.t_end_s:.3f} s; {self.message}")


def _failed(method: str, message: str) -> FlowEstimate:
    nan = math.nan
    return FlowEstimate(method, nan, nan, nan, nan, nan, nan, 0, False, False, False, message)


def _side_arrays(derived, side: str, rig) -> tuple[np.ndarray, np.ndarray]:
    """(p1, dp) of a side [MPa]: views of :func:`derive_samples`' columns
    (a DataFrame or {column: array}) when there (the same arithmetic), else
    computed."""
    p1_col = "p_supply_mpag" if side == "supply" else "p_head_mpag"
    if f"dp_{side}_mpa" in derived and p1_col in derived:
        return _col(derived, p1_col), _col(derived, f"dp_{side}_mpa")
    p1, dp = side_pressures(side, _col(derived, "p_supply_mpag"), _col(derived, "p_head_mpag"),
                            _tank_pressure(derived, rig))
    return np.asarray(p1, dtype=np.float64), np.asarray(dp, dtype=np.float64)


def _peak(t, v, p1, dp, *, side, lo, hi, half, area) -> FlowEstimate:
    idx = np.flatnonzero((t >= lo) & (t <= hi))
    if idx.size == 0:
        return _failed("peak", f"no samples in the step window {lo:.3f}..{hi:.3f} s")
    k = int(idx[np.argmax(v[idx])] if side == "supply" else idx[np.argmin(v[idx])])
    a, b = max(k - half, 0), min(k + half + 1, t.size)
    vk = float(v[k])
    which = "maximum" if side == "supply" else "minimum"
    return FlowEstimate("peak", float(flow_from_velocity(vk, area)), vk,
                        nanmedian(dp[a:b]), nanmedian(p1[a:b]),
                        float(t[a]), float(t[b - 1]), b - a, True, False, True,
                        f"{which} velocity at {t[k]:.3f} s; dp, p1 medians over the "
                        f"{b - a}-sample derivative window around it")


def _steady(t, v, p1, dp, *, lo, hi, window_s, dt, v_stall, area, band,
            smooth_s) -> FlowEstimate:
    def est(i0, i1, moving, steady, message):
        sl = slice(i0, i1 + 1)
        vm = float(np.mean(v[sl]))
        return FlowEstimate("steady", float(flow_from_velocity(vm, area)), vm,
                            nanmean(dp[sl]), nanmean(p1[sl]),
                            float(t[i0]), float(t[i1]), i1 - i0 + 1, moving, steady, True,
                            message)

    idx = np.flatnonzero((t >= lo) & (t <= hi))
    if idx.size < 3:
        return _failed("steady", f"fewer than 3 samples in the settled hold {lo:.3f}..{hi:.3f} s")
    i0, i1 = int(idx[0]), int(idx[-1])
    seg_v = v[i0:i1 + 1]
    fast = np.flatnonzero(np.abs(seg_v) > v_stall)
    if fast.size == 0:
        return est(i0, i1, False, True, "actuator did not move (|v| <= leakage velocity "
                   f"{v_stall:.3g} mm/s): mean over the settled hold (leakage)")
    notes = []
    # A stall at the end (end stop, or motion stopped) lasting at least one
    # derivative window: cut it, plus one window for the filter's smear.
    last_fast = i0 + int(fast[-1])
    if t[i1] - t[last_fast] >= window_s:
        cut = int(np.searchsorted(t, t[last_fast] - window_s, side="right")) - 1
        notes.append(f"stall from {t[last_fast]:.3f} s (end stop?) cut")
        if cut - i0 < 2:
            return est(i0, i1, True, False, "motion too short before the stall; mean over "
                       "the settled hold")
        i1 = cut
    n_smooth = max(1, int(round(smooth_s / dt)))
    vs = moving_average(v[i0:i1 + 1], n_smooth)
    mid = (i1 - i0) // 2
    v_ref = float(np.mean(v[i0 + mid:i1 + 1]))
    width = max(band * abs(v_ref), v_stall)
    out = np.flatnonzero(np.abs(vs - v_ref) > width)
    if out.size == 0:
        notes.append(f"velocity within +-{width:.3g} mm/s throughout")
        return est(i0, i1, True, True, "; ".join(notes))
    start = int(out[-1]) + 1
    if start <= mid:
        notes.append(f"settled within +-{width:.3g} mm/s from {t[i0 + start]:.3f} s")
        return est(i0 + start, i1, True, True, "; ".join(notes))
    # Not settled (stick-slip, sustained oscillation, drift): mean over whole
    # stop-to-stop cycles if the actuator stops repeatedly, else over all.
    slow = np.abs(v[i0:i1 + 1]) <= v_stall
    stops = np.flatnonzero(slow[1:] & ~slow[:-1]) + 1
    if stops.size >= 2:
        a, b = i0 + int(stops[0]), i0 + int(stops[-1])
        notes.append(f"unsteady motion (stick-slip?): mean over {stops.size - 1} whole "
                     "stop-to-stop cycle(s)")
        return est(a, b, True, False, "; ".join(notes))
    notes.append(f"velocity did not settle within +-{width:.3g} mm/s: mean over the second "
                 "half of the moving interval")
    return est(i0 + mid, i1, True, False, "; ".join(notes))


def estimate_flow(run: Run, *, method: str = "steady", derived: pd.DataFrame | None = None,
                  step: StepWindow | None = None, settle_band: float = DEFAULT_SETTLE_BAND,
                  smoothing_s: float | None = None) -> FlowEstimate:
    """Per-run flow of a flow-step run [mm^3/s] by the peak or the steady method.

    Parameters
    ----------
    run : a flow_step run
    method : 'steady' (default) or 'peak'
    derived : :func:`derive_samples` of the run (computed when None)
    step : :func:`step_window` of the run (computed when None)
    settle_band : steady method: half-width of the constant-velocity band as
        a fraction of the steady velocity
    smoothing_s : steady method: moving-average length [s] applied to the
        velocity before the band test (default two derivative windows,
        ~0.1 s, which also averages out pump ripple)

    Returns
    -------
    FlowEstimate

    Notes
    -----
    Both methods use only samples inside the hold (:func:`step_window`) and
    outside the derivative's edge spans. Q = v A (A = piston area,
    ``models.flow_from_velocity``); (p1, dp) from ``models.side_pressures``.

    *peak* (paper Sec. II-D.2): v = max velocity (supply) / min velocity
    (drain) from the step command on; dp and p1 are medians over the
    derivative window centred on that sample.

    *steady*: from the instant the cam has settled (``step.t_settled_s``):

    1. If |v| never exceeds the leakage velocity
       ``analysis.leakage_flow_mm3_s / A``, the actuator did not move: Q is
       the mean velocity over the settled hold x A (mean leakage).
    2. A terminal stall (|v| at most the leakage velocity for at least one
       derivative window: end stop, or motion stopped) is cut, together
       with one derivative window before it (the filter's smear of the impact).
    3. v_ref = mean velocity over the second half of what remains. The
       window starts after the last instant the smoothed velocity leaves
       ``v_ref +- max(settle_band |v_ref|, leakage velocity)`` (ringing,
       acceleration), provided that instant lies in the first half.
    4. Otherwise the motion is unsteady: if the actuator comes to rest
       repeatedly (stick-slip) the window runs from the first to the last
       instant it comes to rest (whole stick-slip cycles); else (sustained
       oscillation, slow drift) it is the second half of the moving interval.
       ``steady`` is then False.

    Q = mean velocity over the window x A, dp and p1 = means over it. The
    mean (not the median) is the mean flow also for stick-slip, where the
    median velocity would be 0.

    Raises
    ------
    ConfigError
        unknown ``method``.
    DataError
        as :func:`step_window`, :func:`derive_samples`; the run is not a flow_step.
    """
    if method not in FLOW_METHODS:
        raise ConfigError(f"method: expected one of {', '.join(FLOW_METHODS)}, got {method!r}")
    _check_flow_step(run)
    if derived is None:
        table, info = derive_columns(run)
        return _estimate(run, method, table, vars(info), step, settle_band, smoothing_s)
    return _estimate(run, method, derived, derived.attrs.get("velocity"), step, settle_band,
                     smoothing_s)


def _check_flow_step(run: Run) -> None:
    meta = run.meta
    if meta.kind != "flow_step" or meta.side not in ("supply", "drain"):
        raise DataError(f"kind {meta.kind!r}, side {meta.side!r}; expected a flow_step run "
                        "with side 'supply' or 'drain'", path=meta.path)


def _estimate(run: Run, method: str, derived, info: Mapping[str, Any] | None,
              step: StepWindow | None, settle_band: float,
              smoothing_s: float | None) -> FlowEstimate:
    """:func:`estimate_flow` on derived samples (a DataFrame or {column:
    array}) and their derivative's info (:class:`DerivativeInfo` fields, None
    when unknown)."""
    _check_flow_step(run)
    meta = run.meta
    step = step_window(run) if step is None else step
    analysis = run.rig.analysis
    window_s = float(info["window_s"]) if info else float(analysis["derivative_window_s"])
    t = _col(derived, "t_s")
    v = _col(derived, "velocity_mm_s")
    dt = float(info["dt_s"]) if info else median(np.diff(t))
    edge_lo = float(info["valid_start_s"]) if info else t[0] + window_s / 2
    edge_hi = float(info["valid_end_s"]) if info else t[-1] - window_s / 2
    p1, dp = _side_arrays(derived, meta.side, run.rig)
    area = run.rig.piston_area_mm2
    hi = min(step.t_end_s, edge_hi)
    if method == "peak":
        half = int(info["window_samples"]) // 2 if info else int(round(window_s / dt)) // 2
        return _peak(t, v, p1, dp, side=meta.side, lo=max(step.t_start_s, edge_lo), hi=hi,
                     half=half, area=area)
    v_stall = float(analysis["leakage_flow_mm3_s"]) / area
    smooth = 2.0 * window_s if smoothing_s is None else float(smoothing_s)
    return _steady(t, v, p1, dp, lo=max(step.t_settled_s, edge_lo), hi=hi, window_s=window_s,
                   dt=dt, v_stall=v_stall, area=area, band=settle_band, smooth_s=smooth)


def _sealed_dp(derived, est: FlowEstimate, side: str, rig) -> float:
    """The other (sealed) valve's pressure difference over ``est``'s window
    [MPa], averaged as ``est``'s dp is (mean for 'steady', median for
    'peak'): a leak past the sealed needle feeds the head too."""
    if not est.success:
        return math.nan
    t = _col(derived, "t_s")
    _, dp = _side_arrays(derived, "drain" if side == "supply" else "supply", rig)
    inside = (t >= est.t_start_s) & (t <= est.t_end_s)
    if not inside.any():
        return math.nan
    return nanmean(dp[inside]) if est.method == "steady" else nanmedian(dp[inside])


def _started_at(meta) -> pd.Timestamp:
    ts = pd.Timestamp(meta.started_at)
    return ts.tz_localize("UTC") if ts.tzinfo is None else ts.tz_convert("UTC")


def summarize_run(run: Run, *, method: str = "steady",
                  derived: pd.DataFrame | None = None) -> dict[str, Any]:
    """One per-run summary row (``io.run.SUMMARY_COLUMNS``) of a run.

    Parameters
    ----------
    run : a flow_step or position_control run
    method : flow method of ``q_mm3_s``, ``dp_mpa``, ``p1_mpa``: 'steady'
        (default) or 'peak' (the paper's)
    derived : :func:`derive_samples` of the run, to avoid computing it twice

    Returns
    -------
    dict
        Every ``SUMMARY_COLUMNS`` key except ``run_index``, ``excluded`` and
        ``excluded_detail`` (set by the data-set stage and
        :func:`seanv_analysis.signals.filters.apply_filters`). Flow-step runs get
        ``q_peak_mm3_s`` and ``q_steady_mm3_s`` (:func:`estimate_flow`),
        ``q_mm3_s`` = the chosen one, ``dp_mpa``/``p1_mpa`` over the chosen
        method's window, ``dp_sealed_mpa`` the other (sealed) valve's
        pressure difference over it, ``motion_steady`` (the steady method's window passed
        its constant-velocity test while moving, whichever method is
        chosen), ``cam_measured_deg`` and ``cam_approach``
        (:func:`step_window`), ``load_mpag`` from run.json or, when null, the
        median ``p_load_mpag`` over the hold. Position-control runs get the
        metadata, ``load_mpag`` (run.json or median over the run), NaN flows,
        ``cam_approach`` 0, ``flow_method`` '' and ``motion_steady`` False.

    Raises
    ------
    ConfigError
        unknown ``method``.
    DataError
        see :func:`step_window` and :func:`derive_samples`.
    """
    if method not in FLOW_METHODS:
        raise ConfigError(f"method: expected one of {', '.join(FLOW_METHODS)}, got {method!r}")
    meta = run.meta
    nan = math.nan
    row: dict[str, Any] = {
        "run_id": meta.run_id, "kind": meta.kind, "side": meta.side or "",
        "started_at": _started_at(meta), "load_mpag": nan,
        "cam_deg": nan if meta.cam_deg is None else float(meta.cam_deg),
        "cam_measured_deg": nan, "cam_approach": 0.0, "q_mm3_s": nan, "q_peak_mm3_s": nan,
        "q_steady_mm3_s": nan, "dp_mpa": nan, "p1_mpa": nan, "dp_sealed_mpa": nan,
        "flow_method": "", "motion_steady": False,
    }
    if meta.kind != "flow_step":
        if meta.load_mpag is not None:
            row["load_mpag"] = float(meta.load_mpag)
        elif "pressure" in run.tables:
            pressure = table_columns(run.tables, "pressure")
            if "p_load_mpag" in pressure:
                row["load_mpag"] = nanmedian(_col(pressure, "p_load_mpag"))
        return row
    if derived is None:  # numpy arrays throughout: no DataFrame is built
        table, derivative = derive_columns(run)
        info: Mapping[str, Any] | None = vars(derivative)
    else:
        table, info = derived, derived.attrs.get("velocity")
    step = step_window(run)
    peak = _estimate(run, "peak", table, info, step, DEFAULT_SETTLE_BAND, None)
    steady = _estimate(run, "steady", table, info, step, DEFAULT_SETTLE_BAND, None)
    chosen = steady if method == "steady" else peak
    if meta.load_mpag is not None:
        load = float(meta.load_mpag)
    else:
        t = _col(table, "t_s")
        inside = (t >= step.t_start_s) & (t <= step.t_end_s)
        p_load = _col(table, "p_load_mpag")
        load = nanmedian(p_load[inside] if inside.any() else p_load)
    row.update(load_mpag=load, cam_measured_deg=step.cam_measured_deg,
               cam_approach=step.cam_approach, q_mm3_s=chosen.q_mm3_s,
               q_peak_mm3_s=peak.q_mm3_s, q_steady_mm3_s=steady.q_mm3_s,
               dp_mpa=chosen.dp_mpa, p1_mpa=chosen.p1_mpa,
               dp_sealed_mpa=_sealed_dp(table, chosen, meta.side, run.rig), flow_method=method,
               motion_steady=bool(steady.success and steady.moving and steady.steady))
    return row
