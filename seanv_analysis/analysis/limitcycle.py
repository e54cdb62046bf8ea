"""Sustained oscillation (limit cycle) of a position-control record.

A P controller that releases its hold as soon as |e| leaves the convergence
band, on a valve whose sealed dead zone and servo lag make the loop hunt,
swings the cam between its limits for as long as the reference stays: a
limit cycle. Its phase depends on where the first swing started, so no twin
reproduces it sample for sample (the fit % of such a run is low even for a
perfect twin); its statistics can be compared:

- amplitude [mm]: half the peak-to-peak error of each cycle (median over cycles);
- period [s]: time between successive upward crossings of the error through
  its mean (median over cycles);
- mean error [mm]: mean of e = x_ref - x over the oscillating windows;
- duration [s]: how long the record oscillates.

A reference segment (x_ref constant) oscillates when, from the first time
the position reaches the reference, its error crosses its median with
hysteresis (:data:`HYSTERESIS_SHARE` of the band, at least
:data:`MIN_HYSTERESIS_MM`) in at least :data:`MIN_CYCLES` full cycles and
keeps doing so to the segment's end (the last crossing within two periods
of it): one overshoot after a step, or a load change kicking a held piston,
is not a limit cycle.

Examples
--------
>>> import numpy as np
>>> t = np.arange(0.0, 20.0, 0.001)
>>> x = 30.0 + 2.0 * np.sin(2 * np.pi * t / 0.8)
>>> lc = limit_cycle(t, x, [0.0], [30.0], band_mm=0.5)
>>> round(lc.amplitude_mm, 2), round(lc.period_s, 2)
(2.0, 0.8)
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["LimitCycle", "limit_cycle", "compare_limit_cycles", "LIMIT_CYCLE_RTOL",
           "MIN_CYCLES", "HYSTERESIS_SHARE", "MIN_HYSTERESIS_MM"]

#: relative tolerance within which a twin's amplitude and period agree with the rig's
LIMIT_CYCLE_RTOL = 0.2
#: full cycles a segment needs to count as oscillating
MIN_CYCLES = 3
#: crossing hysteresis as a share of the convergence band ...
HYSTERESIS_SHARE = 0.25
#: ... and at least this [mm] (encoder noise and stick-slip creep are not cycles)
MIN_HYSTERESIS_MM = 0.05


@dataclass(frozen=True)
class LimitCycle:
    """Statistics of the sustained oscillation of one record (NaN, and
    ``present`` False, when it has none).

    Attributes
    ----------
    present : the record oscillates in at least one reference segment
    amplitude_mm : median half peak-to-peak error of the cycles [mm]
    period_s : median cycle period [s]
    mean_error_mm : mean error x_ref - x over the oscillating windows [mm]
    duration_s : total time in sustained oscillation [s]
    n_cycles : full cycles counted
    windows_s : (start, end) [s] of each oscillating window
    """

    present: bool
    amplitude_mm: float = math.nan
    period_s: float = math.nan
    mean_error_mm: float = math.nan
    duration_s: float = 0.0
    n_cycles: int = 0
    windows_s: tuple[tuple[float, float], ...] = ()


def _segment_cycles(t: np.ndarray, e: np.ndarray, h: float):
    """(up-crossing instants, window mean) of one segment's error, or None."""
    crossed = np.flatnonzero(np.diff(np.signbit(e).astype(np.int8)) != 0)
    if crossed.size == 0:
        return None
    i0 = int(crossed[0]) + 1            # the position reaches the reference
    tt, ee = t[i0:], e[i0:]
    if tt.size < 4:
        return None
    c = ee - float(np.median(ee))
    state = 0
    ups = []
    for i in np.flatnonzero((c > h) | (c < -h)):   # Schmitt trigger
        s = 1 if c[i] > h else -1
        if s != state:
            if s == 1 and state == -1:
                ups.append(i)
            state = s
    return tt, ee, np.asarray(ups, dtype=int)


def limit_cycle(t_s, x_mm, ref_t_s, ref_mm, *, band_mm: float,
                min_cycles: int = MIN_CYCLES) -> LimitCycle:
    """The sustained oscillation of a position record (see the module docstring).

    Parameters
    ----------
    t_s, x_mm : position record [s], [mm] (NaN samples are left out)
    ref_t_s, ref_mm : reference steps [s], [mm] (each holds until the next)
    band_mm : the controller's convergence band [mm] (sets the hysteresis)
    min_cycles : full cycles a segment needs

    Returns
    -------
    LimitCycle
    """
    t = np.asarray(t_s, float)
    x = np.asarray(x_mm, float)
    ok = np.isfinite(t) & np.isfinite(x)
    t, x = t[ok], x[ok]
    rt, rv = np.asarray(ref_t_s, float), np.asarray(ref_mm, float)
    h = max(HYSTERESIS_SHARE * float(band_mm), MIN_HYSTERESIS_MM)
    amps, periods, windows, sums = [], [], [], [0.0, 0.0]
    for k in range(rt.size):
        a = rt[k]
        b = rt[k + 1] if k + 1 < rt.size else (t[-1] + 1e-9 if t.size else a)
        m = (t >= a) & (t < b)
        if m.sum() < 10:
            continue
        found = _segment_cycles(t[m], rv[k] - x[m], h)
        if found is None:
            continue
        tt, ee, ups = found
        if ups.size < min_cycles + 1:
            continue
        per = np.diff(tt[ups])
        if tt[-1] - tt[ups[-1]] > 2.0 * float(np.median(per)):
            continue                    # died out before the segment's end
        for i, j in zip(ups[:-1], ups[1:]):
            seg = ee[i:j]
            amps.append(0.5 * float(seg.max() - seg.min()))
        periods.extend(per.tolist())
        w = slice(int(ups[0]), int(ups[-1]))
        sums[0] += float(np.sum(ee[w]))
        sums[1] += float(ee[w].size)
        windows.append((float(tt[ups[0]]), float(tt[ups[-1]])))
    if not amps:
        return LimitCycle(False)
    return LimitCycle(True, float(np.median(amps)), float(np.median(periods)),
                      sums[0] / sums[1], float(sum(b - a for a, b in windows)), len(amps),
                      tuple(windows))


def compare_limit_cycles(measured: LimitCycle, simulated: LimitCycle, *,
                         rtol: float = LIMIT_CYCLE_RTOL) -> str:
    """How a twin's oscillation compares with the rig's: 'none' (neither
    oscillates), 'agrees' (both do, amplitude and period within ``rtol`` of
    the measured, mean error within ``rtol`` of the measured amplitude), 'differs', 'measured only' or 'simulated only'."""
    if not measured.present and not simulated.present:
        return "none"
    if not simulated.present:
        return "measured only"
    if not measured.present:
        return "simulated only"
    close = all(abs(s / m - 1.0) <= rtol for m, s in
                ((measured.amplitude_mm, simulated.amplitude_mm),
                 (measured.period_s, simulated.period_s)))
    close = close and (abs(simulated.mean_error_mm - measured.mean_error_mm)
                       <= rtol * measured.amplitude_mm)
    return "agrees" if close else "differs"
