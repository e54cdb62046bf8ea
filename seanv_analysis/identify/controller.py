"""The position controller's law, read from its own logs (paper Sec. III-A/B).

Both of the paper's P controllers (:mod:`seanv_analysis.sim.control`) act on
e = x_ref - x [mm] at every control tick:

- without the flow model (Fig. 5(b)): theta_cmd = theta_n + Kp e [deg]
  (Kp in deg/mm around the neutral theta_n);
- with it (Fig. 5(a)): Q_ref = Kp e [mm^3/s], theta_cmd from eq. (6),
  theta_d(p) +- sqrt(Q_ref / (C dp^n));

both clipped to the cam range, and both hold a fixed cam once |e| is
inside the convergence band: the neutral, or ``h`` degrees below the supply
sealing threshold. The paper says the valve was "held"; when the hold ends
(the next reference change, or |e| leaving a release band) it does not say.
Which one a rig's controller does decides whether a run converges or
hunts, so it is read from the logs, not assumed.

Per position-control run (:func:`controller_law`), on the controller's
ticks (controller.csv), with the encoder position and the servo command of
the same tick (a logging offset of the controller's clock is searched on a
1 ms grid):

- the P law: a straight line through (e, cam command) (cam controller:
  Kp and the law's neutral), or Kp from (e, Q_ref) and, for the command, a
  line through (opening, theta_cmd - theta_d) per side (flow-model
  controller: the identified valve's eq. (6) up to a threshold offset and a
  gain on the opening, i.e. the rig's own controller model, which may not be
  the identified valve), fitted on the unsaturated ticks outside the rig
  file's band (less a cluster of one command: a latched hold), robustly
  (residuals beyond 6 MADs left out), then refitted on the ticks it explains;
- saturation: the cam limits where the law asks for more than the logged
  command gives (at least 3 ticks at the extreme);
- the hold: the ticks the law does not explain; their command (cam
  controller) or threshold - command (flow model) clusters at the hold
  angle (densest 0.1 deg bin);
- each tick is then labelled law or hold, and within each reference the
  switches give the bands: a hold is entered at |e| <= band and the law
  applies only at |e| > band (the band: the threshold that the fewest ticks
  contradict; interval: all thresholds that few); a hold that ends before
  the reference changes ends at |e| > release, and a held tick has |e| <=
  release. A release interval overlapping the band's is a controller that
  releases as soon as |e| leaves the band (``release_band_mm`` = band); no
  release while the held error went past the band is a latch (``inf``).

:func:`controller_constants` pools the runs into the rig keys the twin's
controller reads (:meth:`~seanv_analysis.sim.control.CamController.from_rig`,
:meth:`~seanv_analysis.sim.control.FlowModelController.from_rig`) and
replays every run's logged error through the rig file's and the identified
law (the compiled step law itself) to compare their commands with the
logged one. Where the rig file's value lies in a constant's interval (the
logs cannot tell them apart) it is kept, as the supply's droop is.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from ..models.valve import MIN_DP_MPA
from .result import Constant

__all__ = ["ControllerLaw", "controller_law", "controller_constants", "controller_valve",
           "replay_commands"]

#: logging offsets of the controller's clock tried [s] (below one tick)
_OFFSET_STEP_S = 0.001
#: the P law is first fitted on ticks with |e| beyond this multiple of the rig file's band ...
_SEED_BAND_FACTOR = 1.2
#: ... and at least this [mm]
_SEED_MIN_MM = 0.1
#: seed ticks needed for a fit
_MIN_SEED = 10
#: a hold's cluster in the seed: within this of its densest bin [deg] ...
_CLUSTER_DEG = 1.0
#: ... holding at least this share of the seed
_CLUSTER_SHARE = 0.05
#: residual tolerance: this many robust standard deviations, at least _TOL_MIN_DEG
_TOL_SIGMAS = 6.0
_TOL_MIN_DEG = 0.02
#: ticks at an extreme command, past which the law asks, that show a cam limit
_MIN_SATURATED = 3
#: ticks needed for a hold angle, a gain
_MIN_HOLD = 10
_MIN_LAW = 20
#: a logged gain differs from run.json's beyond this share (and its interval)
_KP_RTOL = 0.02


@dataclass
class ControllerLaw:
    """The controller law of one position-control run, read from its logs.

    Angles in deg, errors in mm; NaN where the logs do not tell.

    Attributes
    ----------
    run_id, kind : the run and its controller ('flow_model' | 'cam', run.json)
    n_ticks : controller ticks used
    offset_s : the controller's clock offset (the tick at logged t - offset)
    kp, kp_ci95 : the gain (deg/mm or mm^3/s per mm) and its 95 % interval
    kp_declared : run.json's ``kp``
    neutral_deg : cam controller: the P law's angle at e = 0
    threshold_offset_deg : flow model: the command's eq. (6) threshold minus
        the given valve's, per side (0: the controller's model is that valve)
    opening_gain : flow model: the command's opening over the valve's, per side
    law_rmse_deg : RMS of the command about the law on the law's ticks
    hold : True (holds), False (follows the law down to e = 0), None (cannot tell)
    hold_deg, hold_ci95 : cam controller: the hold angle
    hold_below_deg, hold_below_ci95 : flow model: the hold angle below the
        (controller's) supply threshold
    band_mm, band_interval_mm : the convergence band and the thresholds the
        switches allow
    release : 'latch' (until the next reference), 'band' (as soon as |e|
        leaves the band), 'threshold' (at |e| > release_mm), 'unknown', or
        'none' (no hold)
    release_mm, release_interval_mm : the release threshold (inf: latch)
    max_held_error_mm : largest |e| while held
    cam_min_deg, cam_max_deg : the command's limits (NaN: never reached)
    n_law, n_hold, n_entries, n_releases, n_saturated : tick and event counts
    messages : what a user should know about this run's controller
    """

    run_id: str
    kind: str
    n_ticks: int
    offset_s: float = 0.0
    kp: float = math.nan
    kp_ci95: tuple[float, float] = (math.nan, math.nan)
    kp_declared: float = math.nan
    neutral_deg: float = math.nan
    threshold_offset_deg: dict[str, float] = field(default_factory=dict)
    opening_gain: dict[str, float] = field(default_factory=dict)
    law_rmse_deg: float = math.nan
    hold: bool | None = None
    hold_deg: float = math.nan
    hold_ci95: tuple[float, float] = (math.nan, math.nan)
    hold_below_deg: float = math.nan
    hold_below_ci95: tuple[float, float] = (math.nan, math.nan)
    band_mm: float = math.nan
    band_interval_mm: tuple[float, float] = (math.nan, math.nan)
    release: str = "unknown"
    release_mm: float = math.nan
    release_interval_mm: tuple[float, float] = (math.nan, math.nan)
    max_held_error_mm: float = math.nan
    cam_min_deg: float = math.nan
    cam_max_deg: float = math.nan
    n_law: int = 0
    n_hold: int = 0
    n_entries: int = 0
    n_releases: int = 0
    n_saturated: int = 0
    messages: list[str] = field(default_factory=list)
    # the events behind the bands (pooled over runs by controller_constants)
    _entries: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    _law_e: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    _held: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    _releases: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    _hold_episodes: list = field(default_factory=list, repr=False)
    _pressures: dict = field(default_factory=dict, repr=False)

    def to_json_dict(self) -> dict[str, Any]:
        """The numbers, each key ending in its unit."""
        ku = "mm3_s_per_mm" if self.kind == "flow_model" else "deg_per_mm"
        out: dict[str, Any] = {
            "controller": self.kind, "n_ticks": self.n_ticks, "offset_s": self.offset_s,
            f"kp_{ku}": self.kp, f"kp_ci95_{ku}": list(self.kp_ci95),
            f"kp_declared_{ku}": self.kp_declared, "law_rmse_deg": self.law_rmse_deg,
            "hold": self.hold, "band_mm": self.band_mm,
            "band_interval_mm": list(self.band_interval_mm), "release": self.release,
            "release_mm": self.release_mm, "release_interval_mm": list(self.release_interval_mm),
            "max_held_error_mm": self.max_held_error_mm, "cam_min_deg": self.cam_min_deg,
            "cam_max_deg": self.cam_max_deg, "n_law_ticks": self.n_law,
            "n_hold_ticks": self.n_hold, "n_entries": self.n_entries,
            "n_releases": self.n_releases, "n_saturated_ticks": self.n_saturated,
            "messages": list(self.messages)}
        if self.kind == "cam":
            out.update(neutral_deg=self.neutral_deg, hold_deg=self.hold_deg,
                       hold_ci95_deg=list(self.hold_ci95))
        else:
            out.update(threshold_offset_deg=dict(self.threshold_offset_deg),
                       **{f"opening_gain_{k}_ratio": v for k, v in self.opening_gain.items()},
                       hold_below_deg=self.hold_below_deg,
                       hold_below_ci95_deg=list(self.hold_below_ci95))
        return out


# ---------------------------------------------------------------- the ticks

def _col(cols: dict, name: str, n: int) -> np.ndarray:
    v = cols.get(name)
    return np.full(n, np.nan) if v is None else np.asarray(v, dtype=float)


def _latest(t_src: np.ndarray, t_at: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index of the latest sample at or before each instant, and whether one is."""
    i = np.searchsorted(t_src, t_at + 1e-7, side="right") - 1
    return np.maximum(i, 0), i >= 0


@dataclass
class _Log:
    """One run's logs on the controller's ticks (before the offset is applied)."""

    run_id: str
    kind: str
    kp_declared: float
    rate_declared_hz: float
    t: np.ndarray
    x_ref: np.ndarray
    q_ref: np.ndarray
    te: np.ndarray
    xe: np.ndarray
    ts: np.ndarray
    cmd_s: np.ndarray
    tp: np.ndarray
    ps_s: np.ndarray
    ph_s: np.ndarray
    pt_s: np.ndarray

    @property
    def period_s(self) -> float:
        return float(np.median(np.diff(self.t))) if self.t.size > 1 else math.nan

    def at(self, offset_s: float) -> dict[str, np.ndarray]:
        """e, command and pressures of each tick, its instant taken ``offset_s`` early."""
        ta = self.t - offset_s
        ie, oke = _latest(self.te, ta)
        e = np.where(oke, self.x_ref - self.xe[ie], np.nan)
        # the command sent at the tick: the first servo sample from it on, within a tick
        js = np.searchsorted(self.ts, ta - 1e-7, side="left")
        oks = js < self.ts.size
        js = np.minimum(js, self.ts.size - 1)
        oks &= self.ts[js] - ta < self.period_s
        cmd = np.where(oks, self.cmd_s[js], np.nan)
        ip, okp = _latest(self.tp, ta)
        p = {k: np.where(okp, v[ip], np.nan) for k, v in
             (("ps", self.ps_s), ("ph", self.ph_s), ("pt", self.pt_s))}
        p["pt"] = np.where(np.isfinite(p["pt"]), p["pt"], 0.0)
        return {"e": e, "cmd": cmd, **p}


def _log(run, rig) -> _Log | None:
    tables = run.tables
    if not all(k in tables for k in ("controller", "servo", "encoder")):
        return None
    c = run.meta.controller or {}
    kind = "flow_model" if c.get("flow_model", True) else "cam"
    ctl, srv, enc = (tables.columns(k) for k in ("controller", "servo", "encoder"))
    t = np.asarray(ctl["t_s"], float)
    if t.size < _MIN_LAW or "x_ref_mm" not in ctl or "cam_cmd_deg" not in srv:
        return None
    n = t.size
    pres = tables.columns("pressure") if "pressure" in tables else {"t_s": np.zeros(0)}
    npres = np.asarray(pres["t_s"]).size
    kp_default = rig["controller"]["kp_flow_mm3_s_per_mm" if kind == "flow_model"
                                   else "kp_cam_deg_per_mm"]
    return _Log(run.run_id, kind, float(c["kp"]) if c.get("kp") is not None else float(kp_default),
                float(c["rate_hz"]) if c.get("rate_hz") else math.nan, t,
                _col(ctl, "x_ref_mm", n), _col(ctl, "q_ref_mm3_s", n),
                np.asarray(enc["t_s"], float), _col(enc, "position_mm", len(enc["t_s"])),
                np.asarray(srv["t_s"], float), _col(srv, "cam_cmd_deg", len(srv["t_s"])),
                np.asarray(pres["t_s"], float), _col(pres, "p_supply_mpag", npres),
                _col(pres, "p_head_mpag", npres), _col(pres, "p_tank_mpag", npres))


# ------------------------------------------------------------ robust pieces

def _line(x: np.ndarray, y: np.ndarray, *, through_origin: bool = False, iters: int = 4):
    """Least-squares line y = a + b x with residuals beyond :data:`_TOL_SIGMAS`
    robust standard deviations left out (repeated): (a, b, se_a, se_b,
    inliers, robust sigma)."""
    keep = np.isfinite(x) & np.isfinite(y)
    a = b = se_a = se_b = sigma = math.nan
    for _ in range(iters):
        if keep.sum() < 3:
            return math.nan, math.nan, math.nan, math.nan, keep, math.nan
        X = x[keep][:, None] if through_origin else np.c_[np.ones(keep.sum()), x[keep]]
        coef, *_ = np.linalg.lstsq(X, y[keep], rcond=None)
        a, b = (0.0, float(coef[0])) if through_origin else (float(coef[0]), float(coef[1]))
        r = y - a - b * x
        sigma = 1.4826 * float(np.median(np.abs(r[keep])))
        new = np.isfinite(r) & (np.abs(r) <= max(_TOL_SIGMAS * sigma, 1e-9))
        if np.array_equal(new, keep):
            break
        keep = new
    rk = (y - a - b * x)[keep]
    dof = max(int(keep.sum()) - (1 if through_origin else 2), 1)
    s2 = float(rk @ rk) / dof
    X = x[keep][:, None] if through_origin else np.c_[np.ones(keep.sum()), x[keep]]
    try:
        cov = s2 * np.linalg.inv(X.T @ X)
        se = np.sqrt(np.diag(cov))
        se_a, se_b = (0.0, float(se[0])) if through_origin else (float(se[0]), float(se[1]))
    except np.linalg.LinAlgError:
        pass
    return a, b, se_a, se_b, keep, sigma


def _mode_centre(v: np.ndarray, *, bin_deg: float = 0.1, half_deg: float = 0.5) -> float:
    """Median of the values within ``half_deg`` of the densest ``bin_deg`` bin."""
    v = v[np.isfinite(v)]
    if v.size == 0:
        return math.nan
    lo = math.floor(v.min() / bin_deg)
    idx = np.floor(v / bin_deg).astype(np.int64) - lo
    peak = (int(np.argmax(np.bincount(idx))) + lo + 0.5) * bin_deg
    near = v[np.abs(v - peak) <= half_deg]
    return float(np.median(near))


def _threshold_interval(below: np.ndarray, above: np.ndarray) -> tuple[float, float, int]:
    """The thresholds b with the fewest of ``below`` > b and ``above`` <= b:
    (lowest, highest, number contradicting). ``below`` must be non-empty."""
    vals = np.unique(np.r_[below, above])
    cand = np.r_[vals, np.inf]
    b_sorted, a_sorted = np.sort(below), np.sort(above)
    cost = (b_sorted.size - np.searchsorted(b_sorted, cand, side="right")
            + np.searchsorted(a_sorted, cand, side="right"))
    best = int(cost.min())
    ok = np.flatnonzero(cost == best)
    lo = float(cand[ok[0]])
    nxt = cand[ok[-1] + 1] if ok[-1] + 1 < cand.size else np.inf
    return lo, float(nxt), best


def _episodes(labels: np.ndarray) -> list[np.ndarray]:
    """Index arrays of the consecutive runs of hold ticks."""
    idx = np.flatnonzero(labels == 2)
    if idx.size == 0:
        return []
    cut = np.flatnonzero(np.diff(idx) > 1) + 1
    return np.split(idx, cut)


def _boot_median(values: list[float], seed: int = 0) -> tuple[float, float]:
    """95 % percentile-bootstrap interval of the median of per-episode values."""
    v = np.asarray([x for x in values if math.isfinite(x)])
    if v.size < 2:
        return (float(v[0]), float(v[0])) if v.size else (math.nan, math.nan)
    rng = np.random.default_rng(seed)
    boot = np.median(rng.choice(v, (400, v.size)), axis=1)
    return float(np.percentile(boot, 2.5)), float(np.percentile(boot, 97.5))


# ---------------------------------------------------------- the law per run

class _Law:
    """The P law's command (unclipped) on the ticks, for one kind."""

    def __init__(self, log: _Log, d: dict[str, np.ndarray], valve, q: np.ndarray):
        self.kind = log.kind
        self.e, self.cmd, self.q = d["e"], d["cmd"], q
        if self.kind == "flow_model":
            from ..models import side_pressures

            self.thr, self.open = {}, {}
            for side in ("supply", "drain"):
                sd = valve.side(side)
                p1, dp = side_pressures(side, d["ps"], d["ph"], d["pt"])
                self.thr[side] = sd.threshold_deg(p1, dp)
                dpn = np.maximum(dp, MIN_DP_MPA) ** sd.dp_exponent
                flow = np.maximum(q, 0.0) if side == "supply" else np.maximum(-q, 0.0)
                self.open[side] = np.sqrt(flow / (abs(sd.c_flow) * dpn))
        self.neutral, self.kp = math.nan, math.nan
        self.offset = {"supply": 0.0, "drain": 0.0}
        self.gain = {"supply": 1.0, "drain": 1.0}

    def predict(self) -> np.ndarray:
        if self.kind == "cam":
            return self.neutral + self.kp * self.e
        s, r = "supply", "drain"
        up = self.thr[s] + self.offset[s] + self.gain[s] * self.open[s]
        down = self.thr[r] + self.offset[r] - self.gain[r] * self.open[r]
        return np.where(self.q >= 0, up, down)

    def hold_value(self) -> np.ndarray:
        """Cam: the command; flow model: the controller's supply threshold - command."""
        if self.kind == "cam":
            return self.cmd
        return self.thr["supply"] + self.offset["supply"] - self.cmd

    def fit(self, seed: np.ndarray) -> tuple[np.ndarray, float]:
        """Fit on the ``seed`` ticks: (the ticks it explains, robust sigma [deg])."""
        if self.kind == "cam":
            a, b, _, _, keep, sigma = _line(np.where(seed, self.e, np.nan), self.cmd)
            self.neutral, self.kp = a, b
            return keep, sigma
        keep = np.zeros(self.e.size, bool)
        sig = []
        for side, sel in (("supply", self.q > 0), ("drain", self.q < 0)):
            m = seed & sel & np.isfinite(self.thr[side])
            if m.sum() < _MIN_SEED:
                continue
            sign = 1.0 if side == "supply" else -1.0
            x = np.where(m, sign * self.open[side], np.nan)
            if np.ptp(x[m]) > 0.5:
                a, b, _, _, k, s = _line(x, self.cmd - self.thr[side])
            else:               # too little spread for a gain: the offset alone
                r = (self.cmd - self.thr[side])[m] - sign * self.open[side][m]
                a, b = float(np.median(r)), 1.0
                full = self.cmd - self.thr[side] - sign * self.open[side] - a
                s = 1.4826 * float(np.median(np.abs(full[m])))
                k = m & (np.abs(full) <= max(_TOL_SIGMAS * s, 1e-9))
            if math.isfinite(a) and 0.25 < b < 4.0:
                self.offset[side], self.gain[side] = a, b
                keep |= k & m
                sig.append(s)
        return keep, float(np.max(sig)) if sig else math.nan


def _seed(e: np.ndarray, cmd: np.ndarray, hv: np.ndarray, band0: float) -> np.ndarray:
    """Ticks to fit the P law on first: unsaturated, |e| outside the rig
    file's band, and not in the densest cluster (+-:data:`_CLUSTER_DEG`) of
    the hold value ``hv`` (command, or threshold - command) when it holds
    :data:`_CLUSTER_SHARE` of them (a latched hold whose error drifted out of
    the band; there, the P law's command is at least Kp x band from the hold)."""
    lo, hi = np.nanmin(cmd), np.nanmax(cmd)
    seed = (cmd > lo + 1e-6) & (cmd < hi - 1e-6)
    seed &= np.abs(e) > max(_SEED_BAND_FACTOR * band0, _SEED_MIN_MM)
    if seed.sum() >= _MIN_SEED:
        centre = _mode_centre(hv[seed], half_deg=_CLUSTER_DEG)
        cluster = seed & (np.abs(hv - centre) <= _CLUSTER_DEG)
        if cluster.sum() >= max(_MIN_SEED, _CLUSTER_SHARE * seed.sum()):
            seed &= ~cluster
    return seed


#: a logging offset's score: mean |e| misfit [mm], each tick's capped at this
_OFFSET_CAP_MM = 0.1
#: the smallest offset within this share of the best score is taken
_OFFSET_SHARE = 1.05


def _offset_score(log: _Log, offset: float, band0: float) -> float:
    """How well the logged command (Q_ref, or the cam command of the cam
    controller) follows the position ``offset`` s before the logged tick:
    the mean misfit in mm of e, each tick's capped at :data:`_OFFSET_CAP_MM`."""
    d = log.at(offset)
    e, cmd = d["e"], d["cmd"]
    if log.kind == "flow_model" and np.isfinite(log.q_ref).mean() > 0.5:
        _, b, *_ = _line(e, log.q_ref, through_origin=True)
        r = (log.q_ref - b * e) / max(abs(b), 1e-9)
    elif log.kind == "cam":
        seed = _seed(e, cmd, cmd, band0)
        if seed.sum() < _MIN_SEED:
            return math.inf
        a, b, *_ = _line(np.where(seed, e, np.nan), cmd)
        r = np.where(seed, (cmd - a - b * e) / max(abs(b), 1e-9), np.nan)
    else:
        return math.inf
    r = np.abs(r[np.isfinite(r)])
    return float(np.mean(np.minimum(r, _OFFSET_CAP_MM))) if r.size else math.inf


def controller_law(run, valve, rig) -> ControllerLaw | None:
    """The controller law of one position-control run from its logs (see the
    module docstring); None when the run has no controller, servo or encoder log.

    Parameters
    ----------
    run : a position-control :class:`~seanv_analysis.io.run.Run`
    valve : the valve model the flow-model controller's eq. (6) is compared
        with (its thresholds and C; the identified one)
    rig : the rig config (its ``controller.convergence_band_mm`` only seeds
        the search: the law is first fitted outside 1.2 times that band)
    """
    log = _log(run, rig)
    if log is None:
        return None
    band0 = float(rig["controller"]["convergence_band_mm"])
    out = ControllerLaw(log.run_id, log.kind, int(log.t.size), kp_declared=log.kp_declared)
    period = log.period_s
    if math.isfinite(log.rate_declared_hz) and abs(1.0 / period / log.rate_declared_hz - 1) > 0.05:
        out.messages.append(f"ticks every {period * 1e3:.1f} ms: {1.0 / period:.1f} Hz, run.json "
                            f"says rate_hz {log.rate_declared_hz:g}")
    offsets = np.arange(0.0, max(period - 1e-9, 0.0), _OFFSET_STEP_S)
    scores = np.array([_offset_score(log, float(o), band0) for o in offsets])
    if np.isfinite(scores).any():
        out.offset_s = float(offsets[np.flatnonzero(scores <= _OFFSET_SHARE * scores.min())[0]])
    d = log.at(out.offset_s)
    e, cmd = d["e"], d["cmd"]
    use = np.isfinite(e) & np.isfinite(cmd)
    if use.sum() < _MIN_LAW:
        out.messages.append("fewer than 20 ticks with both a position and a command")
        return out
    # the gain
    q_logged = np.isfinite(log.q_ref).mean() > 0.5
    if log.kind == "flow_model":
        if q_logged:
            a, b, _, se_b, _, _ = _line(e, log.q_ref)
            out.kp, out.kp_ci95 = b, (b - 1.96 * se_b, b + 1.96 * se_b)
            q = np.where(np.isfinite(log.q_ref), log.q_ref, b * e)
        else:
            q = log.kp_declared * e
            out.messages.append("no Q_ref logged: the gain is not identified (only Kp/C of "
                                "the controller's own eq. (6) shows in its command); run.json's kp")
    else:
        q = np.full(e.size, np.nan)
    law = _Law(log, d, valve, q)
    seed = _seed(e, cmd, law.hold_value(), band0) & use
    labels = np.zeros(e.size, np.int8)      # 0 unknown, 1 law, 2 hold
    for _ in range(2):                      # fit, label, refit on the law's ticks
        keep, sigma = law.fit(seed)
        if keep.sum() < _MIN_SEED or not math.isfinite(sigma):
            out.messages.append("the commanded cam follows no P law on this run's ticks")
            return out
        tol = max(_TOL_SIGMAS * sigma, _TOL_MIN_DEG)
        pred = law.predict()
        lo_obs, hi_obs = float(np.nanmin(cmd[use])), float(np.nanmax(cmd[use]))
        at_lo = np.abs(cmd - lo_obs) <= 1e-6
        at_hi = np.abs(cmd - hi_obs) <= 1e-6
        sat_lo = at_lo & (pred < lo_obs - tol)
        sat_hi = at_hi & (pred > hi_obs + tol)
        cam_lo = lo_obs if sat_lo.sum() >= _MIN_SATURATED else -np.inf
        cam_hi = hi_obs if sat_hi.sum() >= _MIN_SATURATED else np.inf
        r_law = cmd - np.clip(pred, cam_lo, cam_hi)
        # the hold: ticks the law leaves unexplained, clustered
        hv = law.hold_value()
        cand = use & (np.abs(r_law) > tol) & ~sat_lo & ~sat_hi
        hold_c = _mode_centre(hv[cand]) if cand.sum() >= _MIN_HOLD else math.nan
        if math.isfinite(hold_c):
            near = cand & (np.abs(hv - hold_c) <= 0.5)
            s_h = 1.4826 * float(np.median(np.abs(hv[near] - hold_c)))
            tol_h = max(_TOL_SIGMAS * s_h, _TOL_MIN_DEG)
            r_hold = hv - hold_c
        else:
            tol_h, r_hold = 0.0, np.full(e.size, np.inf)
        is_law = use & (np.abs(r_law) <= tol) & ~(np.abs(r_hold) < np.abs(r_law))
        is_hold = use & (np.abs(r_hold) <= tol_h) & ~(np.abs(r_law) <= np.abs(r_hold))
        labels[:] = 0
        labels[is_law] = 1
        labels[is_hold] = 2
        if (labels == 2).sum() < _MIN_HOLD:
            labels[labels == 2] = 0
        seed = (labels == 1) & ~sat_lo & ~sat_hi
    out.n_law, out.n_hold = int((labels == 1).sum()), int((labels == 2).sum())
    out.law_rmse_deg = float(np.sqrt(np.mean(r_law[labels == 1] ** 2)))
    out.n_saturated = int((sat_lo | sat_hi).sum())
    out.cam_min_deg = cam_lo if math.isfinite(cam_lo) else math.nan
    out.cam_max_deg = cam_hi if math.isfinite(cam_hi) else math.nan
    if log.kind == "cam":
        out.kp, out.neutral_deg = law.kp, law.neutral
        *_, se_b, _, _ = _line(np.where(labels == 1, e, np.nan), cmd)
        out.kp_ci95 = (law.kp - 1.96 * se_b, law.kp + 1.96 * se_b)
    else:
        out.threshold_offset_deg = {k: float(v) for k, v in law.offset.items()}
        out.opening_gain = {k: float(v) for k, v in law.gain.items()}
        from ..models import side_pressures

        for side in ("supply", "drain"):
            p1, dp = side_pressures(side, d["ps"], d["ph"], d["pt"])
            ok = use & np.isfinite(p1) & np.isfinite(dp)
            if ok.any():
                out._pressures[side] = (float(np.median(p1[ok])), float(np.median(dp[ok])))
    _events(out, log, e, labels, hv)
    return out


def _runs(labels: np.ndarray, x_ref: np.ndarray) -> list[list[tuple[int, np.ndarray]]]:
    """Per reference (x_ref constant), the runs of equal labels among the
    labelled ticks: [(label, tick indices), ...]."""
    idx = np.flatnonzero(labels > 0)
    out: list[list[tuple[int, np.ndarray]]] = []
    if idx.size == 0:
        return out
    new_ref = np.r_[True, x_ref[idx[1:]] != x_ref[idx[:-1]]]
    new_run = new_ref | np.r_[True, labels[idx[1:]] != labels[idx[:-1]]]
    starts = np.flatnonzero(new_run)
    for a, b in zip(starts, np.r_[starts[1:], idx.size]):
        if new_ref[a]:
            out.append([])
        out[-1].append((int(labels[idx[a]]), idx[a:b]))
    return out


#: ticks a run of hold or law ticks needs for its start to count as a switch
_MIN_RUN = 2


def _events(out: ControllerLaw, log: _Log, e: np.ndarray, labels: np.ndarray,
            hv: np.ndarray) -> None:
    """Entries, releases, held errors and the bands of one run (in place).

    Within each reference: a hold run entered from the law (or at the
    reference's start, which ends any hold) is an entry at its first tick's
    |e|; a law run after a hold run is a release at its first tick's |e|;
    the other ticks of a hold run are held. Only runs of at least
    :data:`_MIN_RUN` ticks count as switches (one mislabelled tick is not a
    release)."""
    ae = np.abs(e)
    entries, held, releases = [], [], []
    for runs in _runs(labels, log.x_ref):
        for k, (lab, ix) in enumerate(runs):
            if lab != 2 or ix.size < _MIN_RUN:
                continue
            before = runs[k - 1] if k else None
            if before is None or before[1].size >= _MIN_RUN:
                entries.append(ae[ix[0]])
                held.extend(ae[ix[1:]].tolist())
            after = runs[k + 1] if k + 1 < len(runs) else None
            if after is not None and after[1].size >= _MIN_RUN:
                releases.append(ae[after[1][0]])
    out._entries, out._law_e = np.asarray(entries, float), ae[labels == 1]
    out._held, out._releases = np.asarray(held, float), np.asarray(releases, float)
    eps = [k for k in _episodes(labels) if k.size >= _MIN_RUN]
    out._hold_episodes = [float(np.median(hv[k])) for k in eps]
    out.n_entries, out.n_releases = len(entries), len(releases)
    _bands(out, log.kind, out._entries, out._law_e, out._held, out._releases,
           out._hold_episodes, seed=0)


def _bands(out, kind: str, entries, law_e, held, releases, episodes, *, seed: int) -> None:
    """Hold, band, release and hold angle from the events (in place)."""
    if entries.size == 0:
        out.hold = (False if law_e.size and float(np.min(law_e)) < 0.05 else None)
        if out.hold is False:
            out.band_mm, out.band_interval_mm = 0.0, (0.0, float(np.min(law_e)))
            out.release = "none"
        return
    out.hold = True
    lo, hi, _ = _threshold_interval(entries, law_e)
    hi = min(hi, float(np.max(law_e)) if law_e.size else hi)
    out.band_interval_mm = (lo, hi)
    out.band_mm = 0.5 * (lo + hi) if math.isfinite(hi) else lo
    allh = np.r_[entries, held]
    out.max_held_error_mm = float(np.max(allh))
    if releases.size:
        rlo, rhi, _ = _threshold_interval(allh, releases)
        out.release_interval_mm = (rlo, rhi)
        if rlo <= hi:   # released as soon as |e| left the band
            out.release, out.release_mm = "band", out.band_mm
        else:
            out.release = "threshold"
            out.release_mm = 0.5 * (rlo + rhi) if math.isfinite(rhi) else rlo
    elif out.max_held_error_mm > hi + 0.02:
        out.release, out.release_mm = "latch", math.inf
        out.release_interval_mm = (out.max_held_error_mm, math.inf)
    else:
        out.release = "unknown"
    centre = float(np.median(episodes)) if episodes else math.nan
    ci = _boot_median(episodes, seed)
    if kind == "cam":
        out.hold_deg, out.hold_ci95 = centre, ci
    else:
        out.hold_below_deg, out.hold_below_ci95 = centre, ci


# ------------------------------------------------------ replay and pooling

def replay_commands(run, controller, *, offset_s: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(logged, replayed) cam command [deg] of each controller tick: the
    controller's own step law (:meth:`~seanv_analysis.sim.control.CamController.step`)
    driven by the logged reference, position and pressures of each tick."""
    log = _log(run, run.rig)
    if log is None:
        return np.zeros(0), np.zeros(0)
    d = log.at(offset_s)
    x = log.x_ref - d["e"]
    pt = np.broadcast_to(np.asarray(d["pt"], dtype=float), log.t.shape)
    return d["cmd"], controller.replay(log.x_ref, x, d["ps"], d["ph"], pt)


def _pooled(laws: list[ControllerLaw], kind: str | None = None) -> ControllerLaw:
    """The events of ``laws`` (of ``kind``, or all) as one law's bands."""
    sel = [w for w in laws if kind is None or w.kind == kind]
    cat = (lambda name: np.concatenate([getattr(w, name) for w in sel])
           if sel else np.zeros(0))
    p = ControllerLaw("pooled", kind or "any", sum(w.n_ticks for w in sel))
    eps = [v for w in sel for v in w._hold_episodes]
    _bands(p, kind or "cam", cat("_entries"), cat("_law_e"), cat("_held"), cat("_releases"),
           eps, seed=0)
    return p


def _or_default(value: float, default: float, interval: tuple[float, float]) -> tuple[float, str]:
    """``default`` when it lies in ``interval`` (the logs cannot tell them
    apart: the rig file's value stays), else ``value``; and a note saying so."""
    lo, hi = interval
    if lo <= default <= hi:
        return default, "; the rig file's value lies in the interval and is kept"
    return value, ""


def controller_constants(runs: Sequence[Any], valve, rig) -> tuple[list[Constant], dict, list[str]]:
    """The controller's law as rig constants, from every position-control run.

    Returns (constants, fits, notes): ``controller.convergence_band_mm``,
    ``controller.release_band_mm`` (inf: latch), per controller its gain
    (``controller.kp_cam_deg_per_mm``, ``controller.kp_flow_mm3_s_per_mm``)
    and hold angle (``servo.neutral_deg``,
    ``controller.hold_below_supply_threshold_deg``), the command limits
    (``valve.cam_min_deg``, ``valve.cam_max_deg``) and, when a logged gain
    is not run.json's, ``controller.kp_from_logs``; fits: per run
    (:meth:`ControllerLaw.to_json_dict`) and the logged command replayed
    through the rig file's and the identified law (RMSE [deg]).
    """
    laws = [w for w in (controller_law(r, valve, rig) for r in runs) if w is not None]
    c0 = rig["controller"]
    band0, rel0 = float(c0["convergence_band_mm"]), float(c0.get("release_band_mm", math.inf))
    src = "controller, servo and encoder logs"
    notes: list[str] = []
    if not laws:
        return ([Constant("controller.convergence_band_mm", "controller hold band", band0, band0,
                          "mm", False, src, note="no position-control run with controller, "
                          "servo and encoder logs")], {}, [])
    consts: list[Constant] = []
    n_runs = f"{len(laws)} run(s)"
    pool = _pooled(laws)
    # the band and the release
    if pool.hold is None:
        consts.append(Constant("controller.convergence_band_mm", "controller hold band", band0,
                               band0, "mm", False, src,
                               note="no hold seen and the law never reached |e| < 0.05 mm"))
    elif pool.hold is False:
        consts.append(Constant("controller.convergence_band_mm", "controller hold band", 0.0,
                               band0, "mm", True, f"{src} of {n_runs}",
                               pool.band_interval_mm,
                               note="the controller does not hold: its P law applies down "
                                    f"to |e| = {pool.band_interval_mm[1]:.3g} mm"))
    else:
        lo, hi = pool.band_interval_mm
        band, kept = _or_default(pool.band_mm, band0, (lo, hi))
        consts.append(Constant("controller.convergence_band_mm", "controller hold band",
                               band, band0, "mm", True,
                               f"{pool.n_ticks} controller ticks of {n_runs}: holds entered at "
                               f"|e| <= {lo:.4g} mm, P law at |e| >= {hi:.4g} mm",
                               (lo, hi), note="interval: the bands the logged switches allow"
                               + kept))
        rname = "controller hold release band"
        if pool.release == "latch":
            consts.append(Constant("controller.release_band_mm", rname, math.inf, rel0, "mm",
                                   True, src, (pool.max_held_error_mm, math.inf),
                                   note="the hold latches until the next reference: held up "
                                        f"to |e| = {pool.max_held_error_mm:.3g} mm without "
                                        "release"))
        elif pool.release in ("band", "threshold"):
            rlo, rhi = pool.release_interval_mm
            how = ("released as soon as |e| leaves the band" if pool.release == "band" else
                   f"released at |e| > {pool.release_mm:.3g} mm")
            if pool.release == "band":
                release, ci, kept = band, (band, band), ""
            else:
                release, kept = _or_default(pool.release_mm, rel0, (rlo, rhi))
                ci = (rlo, rhi)
            consts.append(Constant("controller.release_band_mm", rname, release, rel0,
                                   "mm", True,
                                   f"{int(sum(w.n_releases for w in laws))} holds that ended "
                                   f"before the reference changed (at |e| >= {rhi:.4g} mm), "
                                   f"held up to |e| = {rlo:.4g} mm", ci, note=how + kept))
        else:
            consts.append(Constant("controller.release_band_mm", rname, rel0, rel0, "mm", False,
                                   src, note="no hold ended before its reference, but the held "
                                   f"error never left the band (at most {pool.max_held_error_mm:.3g}"
                                   " mm): latch or release cannot be told"))
    # per controller: gain and hold angle
    disagree = False
    for kind, key, name, unit in (("cam", "controller.kp_cam_deg_per_mm", "cam controller gain",
                                   "deg/mm"),
                                  ("flow_model", "controller.kp_flow_mm3_s_per_mm",
                                   "flow-model controller gain", "mm^3/s per mm")):
        ws = [w for w in laws if w.kind == kind and math.isfinite(w.kp)]
        if not ws:
            continue
        k0 = float(c0[key.split(".")[1]])
        se = np.array([(w.kp_ci95[1] - w.kp_ci95[0]) / 3.92 for w in ws])
        wt = 1.0 / np.maximum(se, 1e-12) ** 2
        kp = float(np.sum(wt * [w.kp for w in ws]) / np.sum(wt))
        half = 1.96 / math.sqrt(float(np.sum(wt)))
        bad = [w for w in ws if abs(w.kp - w.kp_declared) > max(_KP_RTOL * abs(w.kp_declared),
                                                                 (w.kp_ci95[1] - w.kp_ci95[0]) / 2)]
        for w in bad:
            msg = (f"{w.run_id}: the logs show Kp = {w.kp:.4g} {unit}, run.json says "
                   f"{w.kp_declared:.4g}: the twin uses the logged gain")
            notes.append(msg)
            w.messages.append(msg)
        disagree |= bool(bad)
        agree = "" if bad else "; agrees with run.json's kp"
        value, kept = _or_default(kp, k0, (kp - half, kp + half))
        consts.append(Constant(key, name, value, k0, unit, True,
                               f"{sum(w.n_law for w in ws)} ticks of the P law "
                               + ("(Q_ref vs e)" if kind == "flow_model" else "(cam command vs e)"),
                               (kp - half, kp + half), note=f"least squares{agree}{kept}"))
    for kind, key, name in (("cam", "servo.neutral_deg", "cam controller hold angle"),
                            ("flow_model", "controller.hold_below_supply_threshold_deg",
                             "flow-model hold below threshold")):
        ws = [w for w in laws if w.kind == kind]
        if not ws:
            continue
        section, leaf = key.split(".")
        d0 = float(rig[section][leaf])
        p = _pooled(laws, kind)
        centre = p.hold_deg if kind == "cam" else p.hold_below_deg
        ci = p.hold_ci95 if kind == "cam" else p.hold_below_ci95
        if not math.isfinite(centre):
            consts.append(Constant(key, name, d0, d0, "deg", False, src,
                                   note="no hold in these runs"))
            continue
        n_ep = len([v for w in ws for v in w._hold_episodes])
        extra = ""
        if kind == "cam":
            neutral = float(np.median([w.neutral_deg for w in ws]))
            if abs(neutral - centre) > 0.5:
                extra = (f"; the P law's own neutral is {neutral:.4g} deg (the twin's law has "
                         "one angle for both)")
        else:
            off = float(np.median([w.threshold_offset_deg.get("supply", 0.0) for w in ws]))
            if abs(off) > 0.2:
                extra = (f"; the controller's own eq. (6) puts the supply threshold {off:+.3g} "
                         "deg from the identified valve's: its flow model is not that valve, "
                         "and the hold is counted from its threshold")
        value, kept = _or_default(centre, d0, ci)
        consts.append(Constant(key, name, value, d0, "deg", True,
                               f"{n_ep} holds of {len(ws)} run(s) (median of each hold's angle)",
                               ci, note=f"interval: bootstrap over the holds{kept}{extra}"))
    # the command's limits
    for key, name, attr in (("valve.cam_min_deg", "cam command lower limit", "cam_min_deg"),
                            ("valve.cam_max_deg", "cam command upper limit", "cam_max_deg")):
        d0 = float(rig["valve"][key.split(".")[1]])
        vals = [getattr(w, attr) for w in laws if math.isfinite(getattr(w, attr))]
        if not vals:
            consts.append(Constant(key, name, d0, d0, "deg", False, src,
                                   note="the law never asked past the logged commands"))
            continue
        if np.ptp(vals) > 0.1:
            notes.append(f"controller: {name} differs between runs ({min(vals):.4g}.."
                         f"{max(vals):.4g} deg); the median is kept")
        v = float(np.median(vals))
        consts.append(Constant(key, name, v, d0, "deg", True,
                               f"{sum(w.n_saturated for w in laws)} saturated ticks of "
                               f"{len(vals)} run(s)", (min(vals), max(vals))))
    if disagree:
        consts.append(Constant("controller.kp_from_logs", "controller gain from the logs", True,
                               False, "", True, "the logged gain is not run.json's kp",
                               note="validate's twin uses the identified gains, not run.json's"))
    fits = {"runs": {w.run_id: w.to_json_dict() for w in laws}}
    fits.update(_replay_fit(runs, laws, rig, consts, valve))
    worse = fits.get("train", math.nan) > 1.05 * fits.get("train_default", math.inf)
    if worse:
        # the law read off the runs one by one replays the logged commands
        # worse than the rig file's (runs that disagree, pooled): not a law of
        # this controller; the rig file's stays
        notes.append(f"controller: the law read from the logs replays the logged commands worse "
                     f"than the rig file's ({fits['train']:.3g} vs {fits['train_default']:.3g} "
                     "deg RMSE): the rig file's law is kept")
        for c in consts:
            if c.identified and c.key != "controller.kp_from_logs":
                c.identified, c.value, c.ci95 = False, c.default, (math.nan, math.nan)
                c.note = "kept: the identified law replays the logs worse than the rig file's"
        consts = [c for c in consts if c.key != "controller.kp_from_logs"]
    for w in laws:
        notes += [f"controller ({w.run_id}): {m}" for m in w.messages
                  if not m.startswith(w.run_id)]
    return consts, fits, notes


def controller_valve(valve, laws: Sequence[ControllerLaw]):
    """The flow-model controller's own eq. (6) model as its commands show it:
    ``valve`` with each side's z0 moved so that its threshold, at the runs'
    median pressures, shifts by the median threshold offset of the
    flow-model runs, and C divided by the square of their opening gain."""
    from scipy.optimize import brentq

    ws = [w for w in laws if w.kind == "flow_model" and w.threshold_offset_deg]
    for side in ("supply", "drain"):
        offs = [w.threshold_offset_deg.get(side, 0.0) for w in ws if side in w._pressures]
        if not offs:
            continue
        off = float(np.median(offs))
        gain = float(np.median([w.opening_gain.get(side, 1.0) for w in ws]))
        p1, dp = np.median([w._pressures[side] for w in ws if side in w._pressures], axis=0)
        sd = valve.side(side)
        goal = float(sd.threshold_deg(p1, dp)) + off
        def miss(z, sd=sd, p1=p1, dp=dp, goal=goal):
            return float(sd.threshold_deg(p1, dp, z0_mm=z)) - goal

        try:
            z0 = brentq(miss, sd.z0_mm - 1.0, sd.z0_mm + 1.0, xtol=1e-7)
        except ValueError:      # no such z0 within 1 mm: keep the valve's
            continue
        valve = valve.with_side(side, z0_mm=float(z0), c_flow=sd.c_flow / gain ** 2)
    return valve


def _replay_fit(runs, laws, rig, consts, valve) -> dict[str, Any]:
    """The logged command against the rig file's and the identified law, each
    replayed on the logged error (RMSE [deg] over all runs' ticks), the
    flow-model controller with its own eq. (6) model (:func:`controller_valve`)."""
    from ..analysis.validate import build_controller
    from ..errors import ConfigError
    from .result import nest_constants

    ident = rig.with_overrides(nest_constants(consts), where="identify")
    valve = controller_valve(valve, laws)
    by_id = {w.run_id: w for w in laws}
    sq = {"train_default": [], "train": []}
    per_run = {}
    for run in runs:
        w = by_id.get(run.run_id)
        if w is None:
            continue
        row = {}
        for label, r in (("train_default", rig), ("train", ident)):
            try:
                ctrl = build_controller(run, valve, r)
            except ConfigError:
                continue
            logged, replay = replay_commands(run, ctrl, offset_s=w.offset_s)
            ok = np.isfinite(logged) & np.isfinite(replay)
            if ok.any():
                sq[label].append((logged[ok] - replay[ok]) ** 2)
                row[f"{'rig_file' if label == 'train_default' else 'identified'}_rmse_deg"] = \
                    float(np.sqrt(np.mean((logged[ok] - replay[ok]) ** 2)))
        per_run[run.run_id] = row
    out: dict[str, Any] = {"metric": "logged cam command vs the law replayed on the logged "
                                     "error, RMSE [deg] (all position runs; eq. (6) with the "
                                     "controller's own thresholds)",
                           "replay_runs": per_run}
    for k, v in sq.items():
        out[k] = float(np.sqrt(np.mean(np.concatenate(v)))) if v else math.nan
    return out
