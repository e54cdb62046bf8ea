"""Flow-model identification of the SEANV (paper Sec. II-C/D, eq. 3-5, Fig. 4).

For each side, from the filtered flow-step runs of a per-run summary:

(a) per load level, Q = alpha (theta - theta_d)^2 on the open side
    (theta_d [deg], alpha [mm^3/(s deg^2)] per load: :attr:`FlowFit.per_load`);
(b) two-step (the paper's procedure): z0 [mm] so that the eq. (3)+(4)
    thresholds theta_d(p1, dp; z0) match the per-load theta_d, then C from
    alpha = C dp^0.5;
(c) joint (**default**): z0 and C fitted together on every run of the side
    with eq. (5), Q = C (theta - theta_d(p1, dp; z0))^2 sqrt(dp), residuals
    scaled by a fitted noise model sigma = a + b |Q| and a ``soft_l1`` robust
    loss (scipy.optimize.least_squares, ``f_scale`` = 1.4826 MAD of the
    scaled residuals).

Why joint is the default: it uses every run with its own p1 and dp (the
two-step fit uses one median dp per load and needs enough runs per load for
a quadratic), it weights runs by their noise, it does not throw away the
correlation between theta_d and alpha of each per-load fit, and the robust
loss bounds the pull of a bad run. Both results are reported
(:attr:`SideFit.joint`, :attr:`SideFit.two_step`).

dp changes with the opening within a load (it does on the rig and in the
simulator: the head pressure follows the flow), so each run has its own
threshold theta_d(p1, dp). The per-load fits take that movement out
(each run's cam angle less its threshold's offset, eq. 3+4, from the
threshold at the load's median p1 and dp), so each load's theta_d is the
threshold at the load's median pressures, the point of Fig. 4(b) and of the
two-step fit. (Without it, one quadratic through runs whose thresholds move
0.2-0.8 deg with their flow put each load's theta_d 0.1-0.6 deg above the
eq. 3+4 line, 5-40 standard errors, on the simulator's ``paper-flowsteps``,
and the two-step C 4-8 % off; with it, within 0.01 deg and 1 s.e., the
two-step C within 0.02 % of the joint one.)

Seat leakage: each needle leaks past its seat, open or sealed, g dp
(:func:`seanv_analysis.models.seat_leakage_mm3_s`), so a run's flow is the
open side's eq. (5) plus g (dp_supply - dp_drain). It is a few mm^3/s, but
it changes with the head pressure from load to load, the very dependence
the threshold's eq. (3) has: left in, it shifts z0 and C and (with the
needle centre free, ``identify``) the geometry. The conductance g, one for
both needles, is fitted with the sides' z0 and C on all their runs
(:mod:`._leakage`, ``leakage='fit'``, the default; 'rig' takes the rig
file's ``valve.plant.leakage_conductance_mm3_s_per_mpa``, 'none' leaves it
out), then each side is fitted to its runs' flow less the leakage
(:attr:`FlowFit.leakage`). The other needle's dp comes from the summary's
``dp_sealed_mpa`` (else the rig's supply and tank pressures).

Theta is the measured cam angle (servo feedback), the command where it is
missing. Per-load fits use each run's flow scaled to the load's median dp
(Q dp_med^n / dp^n), since dp drops as the valve opens.

Uncertainty: 95 % intervals = percentile bootstrap over conditions (seeded,
``n_boot`` resamples; a condition is a load level x commanded cam angle, its
repeats resampled together because they share systematic errors such as
the servo's quantised position), with calibration (Type B) uncertainties
added in quadrature: flow scale (``flow_scale_u95``, 0.5 %: C scales with
the piston area and the velocity estimate) and cam zero (``cam_u95_deg``,
0.05 deg: shifts every theta_d), and the seat leakage's conductance (its
95 % half-width moved through the fit: z0 and C refitted at g -+ half). The
statistical part alone is kept (``z0_ci95_stat``, ``c_ci95_stat``). When the fit's covariance is singular
(e.g. the runs do not pin down the threshold) the intervals are NaN
(``null`` in JSON) and the message says so.

Lack of fit (per side, :attr:`SideFit.lack_of_fit`): the intervals assume
eq. (5) describes the runs. A classical lack-of-fit F test checks it: the
scatter of the conditions' mean residuals about the model against the
scatter of the repeats about their condition's mean (pure error), residuals
weighted by the noise model 1/sigma^2, two parameters (z0, C)
(:func:`~._perload.lack_of_fit_test`), on the joint fit's residuals (with
``procedure='two_step'`` too: the question is the model's, not the
procedure's). ``lack_of_fit`` is true when
p < 0.01, the ratio sqrt(F) > 1.5 and the systematic misfit exceeds 1 % of
the flow (on very clean data a tiny systematic term is significant and many
times the repeats' scatter, yet immaterial); the side's message then says so
and points to ``seanv-analyze discover``. Nothing is widened: the intervals
stay what the bootstrap and the calibration terms give. Without repeated
conditions there is no pure error: ``lack_of_fit`` is None (``null``) and
``lack_of_fit_detail['reason']`` says why. A drift through time also
spreads the repeats (they are taken at different times), so it shows only
where it moves the conditions apart more than the repeats: on the paper's
protocol (three sweeps per load) it does.
Residual sign everywhere: measured - model.
"""
from __future__ import annotations

import json
import math
import warnings
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
import pandas as pd

from ..errors import ConfigError, DataError, FitError
from ..estimate import Estimate, Estimates, widen_interval
from ..jsonable import JsonResult, json_num
from ..models import SIDES, ValveModel, signed_power
from ..models.valve import MIN_DP_MPA, SEAT_LEAK_KEY
from ._joint import _cluster_members, bootstrap_joint, fit_joint, resample_indices
from ._leakage import LeakageFit, SideRuns, fit_leakage, leak_dp_mpa, prior_sd_mm3_s_per_mpa
from ._perload import (
    LOF_P_MAX,
    LOF_RATIO_MIN,
    LOF_SYSTEMATIC_MIN,
    LackOfFit,
    fit_load,
    fit_noise_model,
    group_loads,
    lack_of_fit_test,
    two_step,
)

__all__ = ["SideFit", "FlowFit", "Parameter", "fit_flow", "PROCEDURES", "LEAKAGE_MODES", "UNITS",
           "C_KEY", "PEAK_BIAS", "CAM_SOURCES", "DEFAULT_FLOW_SCALE_U95", "DEFAULT_CAM_U95_DEG"]

#: Fit procedures: 'joint' (default, eq. 5 on all runs) and the paper's 'two_step'.
PROCEDURES = ("joint", "two_step")

#: Seat leakage beside eq. (5): 'fit' (default: its conductance fitted with the
#: sides' z0 and C), 'rig' (the rig file's conductance), 'none' (eq. 5 alone).
LEAKAGE_MODES = ("fit", "rig", "none")

#: Units of the JSON contract.
#: the flow coefficient C of eq. (5) in JSON, its unit in its key
C_KEY = "C_mm3_s_deg2_sqrtMPa"
UNITS = {C_KEY: "mm^3/(s deg^2 MPa^0.5)", "z0_mm": "mm"}

#: Default calibration (Type B) uncertainties, 95 % half-widths, added in
#: quadrature to the bootstrap intervals: flow scale (relative; piston area
#: +-0.02 mm on 16 mm is 0.25 %, plus derivative / steady-window bias) and
#: cam zero [deg] (half the servo resolution, 0.088 deg).
DEFAULT_FLOW_SCALE_U95 = 0.005
DEFAULT_CAM_U95_DEG = 0.05

#: Cam angle used as theta: the servo feedback, or the command.
CAM_SOURCES = ("measured", "commanded")

_PER_RUN_COLUMNS = ("run_id", "side", "run_index", "load_mpag", "load_level_mpag", "cam_deg",
                    "theta_deg",
                    "q_mm3_s", "p1_mpa", "dp_mpa", "dp_leak_mpa", "q_leak_mm3_s",
                    "excluded", "excluded_detail", "used",
                    "theta_d_model_deg", "theta_d_implied_deg", "q_model_mm3_s",
                    "residual_mm3_s", "sigma_mm3_s",
                    "z_score")


def _nan_ci() -> tuple[float, float]:
    return (math.nan, math.nan)


@dataclass
class SideFit:
    """Identified flow model of one side.

    Attributes
    ----------
    side : 'supply' or 'drain'
    z0_mm : initial disc-spring deflection z0 [mm] (of the chosen procedure)
    c_flow : C [mm^3/(s deg^2 MPa^0.5)], negative on the drain side
    z0_ci95, c_ci95 : 95 % intervals: bootstrap over conditions (percentile) with the
        calibration uncertainties added in quadrature; NaN when unavailable
    z0_ci95_stat, c_ci95_stat : the bootstrap (statistical) part alone
    rmse_mm3_s : RMSE of measured - model over the runs used [mm^3/s]
    n_runs : runs used (flow steps of this side that passed the filters)
    procedure : 'joint' or 'two_step'
    joint, two_step : both procedures' estimates (dicts with z0_mm, c_flow, standard errors;
        in :meth:`to_dict` under their estimates' keys, :meth:`procedure_estimates`)
    ci_method : how the intervals were made
    noise : noise model {floor_mm3_s, rel}: sigma = floor + rel |Q|
    lack_of_fit : True when eq. (5) does not describe the runs (lack-of-fit F
        test against the repeats: significant and material), False when it
        does, None when it cannot be tested (no repeated condition)
    lack_of_fit_ratio : sqrt(F): scatter of the conditions' mean residuals
        (per run) / scatter of the repeats [-], ~1 without lack of fit; NaN untested
    lack_of_fit_p : p-value of the F test; NaN untested
    lack_of_fit_detail : F, degrees of freedom, conditions, systematic misfit
        [% of the flow], criteria, and the reason when untested
    success, message : whether the fit worked; why not, or notes (the
        lack-of-fit sentence when flagged)

    :meth:`estimates` gives z0 and C as the package's one estimate type
    (:class:`~seanv_analysis.estimate.Estimate`); the JSON and
    ``FlowFit.to_frame()`` are made from them.
    """

    side: str
    z0_mm: float = math.nan
    c_flow: float = math.nan
    z0_ci95: tuple[float, float] = field(default_factory=_nan_ci)
    c_ci95: tuple[float, float] = field(default_factory=_nan_ci)
    z0_ci95_stat: tuple[float, float] = field(default_factory=_nan_ci)
    c_ci95_stat: tuple[float, float] = field(default_factory=_nan_ci)
    rmse_mm3_s: float = math.nan
    n_runs: int = 0
    procedure: str = "joint"
    joint: dict = field(default_factory=dict)
    two_step: dict = field(default_factory=dict)
    ci_method: str = ""
    n_boot_ok: int = 0
    noise: dict = field(default_factory=dict)
    success: bool = False
    message: str = ""
    lack_of_fit: bool | None = None
    lack_of_fit_ratio: float = math.nan
    lack_of_fit_p: float = math.nan
    lack_of_fit_detail: dict = field(default_factory=dict)

    def estimates(self) -> Estimates:
        """z0 and C of the side (names '<side>.z0', '<side>.C') as
        :class:`~seanv_analysis.estimate.Estimate`: the value of the fit's
        procedure, its standard error (the procedure's covariance; NaN when
        singular), the 95 % interval (:attr:`z0_ci95`, :attr:`c_ci95`)."""
        return self.procedure_estimates(self.procedure)

    def procedure_estimates(self, procedure: str) -> Estimates:
        """z0 and C of one procedure ('joint' or 'two_step': :attr:`joint`,
        :attr:`two_step`) as :meth:`estimates` gives them; the 95 % intervals
        are the chosen procedure's only (the other's: its standard error)."""
        est = self.joint if procedure == "joint" else self.two_step
        chosen = procedure == self.procedure
        method = (f"{procedure.replace('_', '-')} fit of eq. (5)"
                  + (f"; intervals: {self.ci_method}" if self.ci_method and chosen else ""))
        by = f"{self.n_runs} flow steps of the {self.side} side"
        nan2 = (math.nan, math.nan)
        out = []
        for q, key, se_key, ci in (("z0", "z0_mm", "z0_se_mm", self.z0_ci95),
                                   ("C", "c_flow", "c_se", self.c_ci95)):
            value, se = est.get(key, math.nan), est.get(se_key, math.nan)
            value = math.nan if value is None else float(value)
            source = "identified" if math.isfinite(value) else "not_estimated"
            out.append(Estimate(f"{self.side}.{q}", value, UNITS["z0_mm" if q == "z0" else C_KEY],
                                tuple(ci) if chosen else nan2,
                                float(se if se is not None else math.nan),
                                method=method, constrained_by=by, source=source,
                                note="" if self.success or not chosen else self.message))
        return Estimates.of(out)

    def _procedure_json(self, procedure: str) -> dict[str, Any]:
        """One procedure's numbers under its estimates' keys (``z0_mm``,
        ``z0_stderr_mm``, ``C_mm3_s_deg2_sqrtMPa``,
        ``C_stderr_mm3_s_deg2_sqrtMPa``) and the fit's own (success,
        message, f_scale, nfev or n_loads)."""
        est = self.joint if procedure == "joint" else self.two_step
        if not est:
            return {}
        out: dict[str, Any] = {}
        for e in self.procedure_estimates(procedure).values():
            out.update({e.key: json_num(e.value), e.stderr_key: json_num(e.stderr)})
        rest = {k: v for k, v in est.items() if k not in ("z0_mm", "c_flow", "z0_se_mm", "c_se")}
        return {**out, **_clean(rest)}

    def to_json_dict(self) -> dict[str, Any]:
        """The ``--json`` contract for one side (NaN -> null); z0 and C are
        :meth:`estimates`' ``key`` and ``ci95_key``."""
        z0, c = self.estimates().values()
        return {z0.key: json_num(z0.value), c.key: json_num(c.value),
                z0.ci95_key: [json_num(v) for v in z0.ci95],
                c.ci95_key: [json_num(v) for v in c.ci95],
                "rmse_mm3_s": json_num(self.rmse_mm3_s), "n_runs": int(self.n_runs),
                "lack_of_fit": None if self.lack_of_fit is None else bool(self.lack_of_fit),
                "lack_of_fit_ratio": json_num(self.lack_of_fit_ratio),
                "lack_of_fit_p": json_num(self.lack_of_fit_p)}

    def to_dict(self) -> dict[str, Any]:
        """Everything (JSON-ready)."""
        d = self.to_json_dict()
        d["z0_ci95_stat_mm"] = [json_num(v) for v in self.z0_ci95_stat]
        d["C_ci95_stat" + C_KEY[1:]] = [json_num(v) for v in self.c_ci95_stat]
        d.update(side=self.side, procedure=self.procedure, success=self.success,
                 message=self.message, ci_method=self.ci_method, n_boot_ok=self.n_boot_ok,
                 noise=self.noise, joint=self._procedure_json("joint"),
                 two_step=self._procedure_json("two_step"),
                 lack_of_fit_detail=_clean(self.lack_of_fit_detail))
        return d

    @property
    def status(self) -> str:
        """'failed', 'lack of fit' or 'ok'."""
        if not self.success:
            return "failed"
        return "lack of fit" if self.lack_of_fit else "ok"

    def lack_of_fit_line(self) -> str:
        """One line on the lack-of-fit check (empty when it was not run)."""
        d = self.lack_of_fit_detail
        if not d:
            return ""
        if self.lack_of_fit is None:
            return f"lack-of-fit check: not possible ({d.get('reason') or 'untested'})"
        verdict = "LACK OF FIT" if self.lack_of_fit else "none material"
        sys_pct = d.get("systematic_pct")
        sys_txt = (f", systematic misfit {sys_pct:.2g} % of the flow"
                   if sys_pct is not None and math.isfinite(sys_pct) else "")
        return (f"lack-of-fit check: {verdict} (residual scatter {self.lack_of_fit_ratio:.1f}x "
                f"the repeats' scatter, p = {_fmt_p(self.lack_of_fit_p)}{sys_txt}; "
                f"{d.get('n_repeated', 0)}/{d.get('n_conditions', 0)} conditions repeated)")


def _fmt_p(p: float) -> str:
    """p-value for a sentence: 0.03, 2e-9."""
    if not math.isfinite(p):
        return "n/a"
    if p >= 1e-3:
        return f"{p:.2g}"
    mant, exp = f"{p:.0e}".split("e")
    return f"{mant}e{int(exp)}"


def _lack_of_fit_sentence(lof: LackOfFit) -> str:
    """The message of a side whose runs eq. (5) does not describe."""
    sys_txt = (f", systematic misfit {100 * lof.systematic:.2g} % of the flow"
               if math.isfinite(lof.systematic) else "")
    return (f"residual scatter {lof.ratio:.1f}x the repeats' scatter (p = {_fmt_p(lof.p_value)}"
            f"{sys_txt}): eq. (5) does not describe these runs (drift, or another effect); "
            "the intervals assume it does. Run `seanv-analyze discover`.")


def _clean(d: dict) -> dict:
    return {k: (json_num(v) if isinstance(v, float) else v) for k, v in d.items()}


#: ``fit.params[name]``'s type: the package's one estimate type (kept
#: under lmfit's name)
Parameter = Estimate


@dataclass
class FlowFit(JsonResult):
    """Result of :func:`fit_flow`: per-side parameters with 95 % intervals,
    the fitted :class:`~seanv_analysis.models.ValveModel`, per-run and
    per-load tables.

    Attributes
    ----------
    sides : {'supply': SideFit, 'drain': SideFit} (the sides asked for)
    model : the rig's valve with the fitted z0 and C (sides not fitted keep the rig's)
    per_run : one row per flow-step run of the sides asked for (excluded ones too):
        cam_deg (commanded) and theta_deg (used) [deg], q_mm3_s, q_model_mm3_s (eq. 5
        plus the seat leakage), q_leak_mm3_s (the leakage, g dp_leak_mpa),
        residual_mm3_s (measured - model) [mm^3/s], dp_leak_mpa (dp_supply -
        dp_drain) [MPa], theta_d_model_deg (eq. 3+4 at the
        run's pressures) and theta_d_implied_deg (theta minus the opening that gives the
        measured flow with the fitted C, eq. 6) [deg], sigma_mm3_s (noise scale),
        z_score, used
    per_load : one row per side and load level: theta_d_deg +- theta_d_se_deg [deg],
        alpha_mm3_s_deg2 +- alpha_se_mm3_s_deg2, p1_mpa, dp_mpa (medians of the runs used),
        p1/dp_threshold_mpa (the pressures theta_d refers to: the same medians; each
        run's threshold movement about them is taken out), n_runs,
        theta_d_model_deg and alpha_model_mm3_s_deg2 (the fitted model at those pressures)
    excluded : runs excluded per reason {'leakage', 'friction', 'cam_range', 'invalid'}
    success, message : True when every side asked for was fitted
    warnings : recoverable oddities met on the way
    settings : options used
    leakage : the needles' seat-leakage conductance g [mm^3/(s MPa)] with its
        95 % interval (:class:`~._leakage.LeakageFit`; ``fitted`` False: the
        rig file's, or 0 with ``leakage='none'``)
    """

    sides: dict[str, SideFit]
    model: ValveModel
    per_run: pd.DataFrame
    per_load: pd.DataFrame
    excluded: dict[str, int]
    success: bool
    message: str = ""
    warnings: list[str] = field(default_factory=list)
    settings: dict[str, Any] = field(default_factory=dict)
    leakage: LeakageFit = field(default_factory=lambda: LeakageFit(0.0))

    def to_json_dict(self) -> dict[str, Any]:
        """The stable JSON contract of ``flowfit --json``."""
        out: dict[str, Any] = {s: f.to_json_dict() for s, f in self.sides.items()}
        out["excluded"] = {k: int(v) for k, v in self.excluded.items()}
        out["units"] = dict(UNITS)
        out["flow_method"] = self.flow_method
        return out

    @property
    def flow_method(self) -> str:
        """The per-run flow estimate fitted: 'steady', 'peak' (biased:
        :data:`PEAK_BIAS`), 'mixed' or '' (not said)."""
        return str(self.settings.get("flow_method", ""))

    @property
    def params(self) -> Estimates:
        """The fitted numbers by name, as lmfit's ``result.params``:
        ``'supply.z0'``, ``'supply.C'``, ``'drain.z0'``, ``'drain.C'`` (the
        sides fitted, :meth:`SideFit.estimates`) and the seat leakage's
        conductance ``'leakage.g'`` (unless ``leakage='none'``; in
        ``to_dict()``'s ``seat_leakage``, not in the ``--json`` contract), each an
        :class:`~seanv_analysis.estimate.Estimate` (value, stderr, ci95,
        unit, method, constrained_by, source); ``params.to_frame()`` is
        their table, ``to_frame()`` and the JSON give the same numbers under
        each estimate's ``key``."""
        out = Estimates()
        for f in self.sides.values():
            out.update(f.estimates())
        if self.settings.get("leakage", "fit") != "none":
            out["leakage.g"] = self.leakage.estimate()
        return out

    def eval(self, theta_deg, dp_mpa, side: str, *, p1_mpa=None) -> np.ndarray:
        """The fitted model's flow through the opened needle, eq. (3)-(5):
        Q = C (theta - theta_d)^2 sqrt(dp) [mm^3/s] at cam angle ``theta_deg``
        [deg] and pressure difference ``dp_mpa`` [MPa] across ``side`` (arrays
        broadcast). The seat leakage of both needles, fitted beside it, is not
        in it (it depends on both sides' pressures: ``per_run``'s
        ``q_leak_mm3_s``; ``q_model_mm3_s`` is the sum).

        ``p1_mpa`` [MPa] is the pressure on the needle, which moves the
        sealing threshold theta_d (eq. 4); default as in the runs fitted:
        the supply pressure (median of the supply runs) on the supply side,
        dp plus the tank pressure (median) on the drain side.

        Raises
        ------
        ValueError
            ``side`` is not a side of this fit.
        """
        if side not in self.sides:
            raise ValueError(f"side: expected one of {', '.join(self.sides)}, got {side!r}")
        dp = np.asarray(dp_mpa, dtype=float)
        if p1_mpa is None:
            rows = self.per_run[(self.per_run["side"] == side) & self.per_run["used"].astype(bool)] \
                if len(self.per_run) else self.per_run
            if side == "supply":
                p1_mpa = float(np.median(rows["p1_mpa"])) if len(rows) else 3.3
            else:
                p1_mpa = dp + (float(np.median(rows["p1_mpa"] - rows["dp_mpa"])) if len(rows)
                               else 0.0)
        return np.asarray(self.model.side(side).flow(np.asarray(theta_deg, dtype=float),
                                                     np.asarray(p1_mpa, dtype=float), dp),
                          dtype=float)

    def to_frame(self) -> pd.DataFrame:
        """One row per side: z0_mm, C_mm3_s_deg2_sqrtMPa (the JSON's names),
        their 95 % intervals (``z0_ci95_lo_mm``, ``z0_ci95_hi_mm``,
        ``C_ci95_lo_mm3_s_deg2_sqrtMPa``...), rmse_mm3_s, n_runs, status."""
        rows = []
        for side, f in self.sides.items():
            row: dict[str, Any] = {"side": side}
            for e in f.estimates().values():
                row.update(e.wide_items())
            rows.append({**row, "rmse_mm3_s": f.rmse_mm3_s, "n_runs": f.n_runs,
                         "status": f.status})
        return pd.DataFrame(rows).set_index("side")

    def plot(self, ax=None, *, panel: str = "a"):
        """Fig. 4 on ``ax`` (a new pyplot figure when None): panel 'a' flow vs
        cam angle with the model per load, 'b' threshold vs dp (one axes per
        side); returns the axes."""
        from ..plotting import plot

        return plot(self, ax, panel=panel)

    def __repr__(self) -> str:
        parts = [f"{s} z0={f.z0_mm:.4f} mm C={f.c_flow:.3f}"
                 + ("" if f.success else f" ({f.status})") for s, f in self.sides.items()]
        return f"<FlowFit {'; '.join(parts)}; {len(self.per_run)} runs>"

    def _repr_html_(self) -> str:
        t = self.to_frame()
        return (f"<p><b>FlowFit</b> (eq. 3-5; C in {UNITS[C_KEY]}, "
                f"95 % intervals)</p>" + t.to_html(float_format=lambda v: f"{v:.4g}"))

    def to_dict(self) -> dict[str, Any]:
        """Full result (sides with both procedures, settings, warnings)."""
        return {"sides": {s: f.to_dict() for s, f in self.sides.items()},
                "excluded": self.to_json_dict()["excluded"], "units": dict(UNITS),
                "success": self.success, "message": self.message, "warnings": self.warnings,
                "settings": self.settings,
                "seat_leakage": self.leakage.to_dict(
                    modelled=self.settings.get("leakage", "fit") != "none"),
                "per_load": json.loads(self.per_load.to_json(orient="records"))}

    def skipped_runs(self) -> dict[str, str]:
        """{run_id: why} of the runs the paper's filters kept out of the fit."""
        pr = self.per_run
        if pr.empty or "excluded" not in pr:
            return {}
        out = pr[pr["excluded"].fillna("").astype(str) != ""]
        why = out["excluded_detail"] if "excluded_detail" in out else out["excluded"]
        return dict(zip(out["run_id"].astype(str), why.astype(str)))

    def report(self) -> str:
        """Human-readable summary."""
        lines = ["Flow-model fit (paper eq. 3-5), residual = measured - model"]
        for s, f in self.sides.items():
            if f.status == "lack of fit":
                lines.append(f"{s}: lack of fit: {f.message}")
            elif f.success and self.flow_method == "peak":
                lines.append(f"{s}: fitted on the biased 'peak' flow estimate (see the warning "
                             "below; the intervals do not hold its bias)")
            else:
                lines.append(f"{s}: {'ok' if f.success else 'FAILED'}"
                             + (f" ({f.message})" if f.message else ""))
            if not math.isfinite(f.z0_mm):
                continue
            lines.append(f"  z0 = {f.z0_mm:.4f} mm  95% [{f.z0_ci95[0]:.4f}, {f.z0_ci95[1]:.4f}]")
            lines.append(f"  C  = {f.c_flow:.3f} mm^3/(s deg^2 MPa^0.5)  95% "
                         f"[{f.c_ci95[0]:.3f}, {f.c_ci95[1]:.3f}]")
            lines.append(f"  RMSE {f.rmse_mm3_s:.1f} mm^3/s over {f.n_runs} runs; "
                         f"procedure {f.procedure}")
            if f.ci_method:
                lines.append(f"  intervals: {f.ci_method}")
            t = f.two_step
            other = "two-step" if f.procedure == "joint" else "joint"
            o = t if f.procedure == "joint" else f.joint
            if o and o.get("z0_mm") is not None and math.isfinite(o.get("z0_mm", math.nan)):
                lines.append(f"  {other}: z0 = {o['z0_mm']:.4f} mm, C = {o['c_flow']:.3f}")
            if f.noise:
                lines.append(f"  noise model: sigma = {f.noise['floor_mm3_s']:.1f} + "
                             f"{f.noise['rel']:.3f} |Q| mm^3/s")
            if f.lack_of_fit_line() and not f.lack_of_fit:  # flagged: said above
                lines.append(f"  {f.lack_of_fit_line()}")
        lk = self.leakage
        if lk.fitted:
            lines.append(f"seat leakage: g = {lk.conductance_mm3_s_per_mpa:.3g} mm^3/(s MPa)  95% "
                         f"[{lk.ci95[0]:.3g}, {lk.ci95[1]:.3g}] (Q_leak = g (dp_supply - "
                         "dp_drain), taken off each run's flow before eq. (5))")
        elif lk.conductance_mm3_s_per_mpa or lk.message:
            lines.append(f"seat leakage: g = {lk.conductance_mm3_s_per_mpa:.3g} mm^3/(s MPa)"
                         + (f" ({lk.message})" if lk.message else ""))
        ex = ", ".join(f"{k} {v}" for k, v in self.excluded.items())
        lines.append(f"excluded runs: {ex}")
        for w in self.warnings:
            lines.append(f"warning: {w}")
        return "\n".join(lines)

# ---------------------------------------------------------------------------

#: what a fit on the paper's peak-velocity flows must say (docs/flow_estimate.md)
PEAK_BIAS = ("flow estimate 'peak' (the paper's peak velocity) is biased: +16 % / -14 % "
             "median on the supply / drain side against simulated truth, +28 % / -33 % below "
             "1500 mm^3/s where the actuator stick-slips (docs/flow_estimate.md); the 95 % "
             "intervals do not include that bias, so they may exclude the true z0 and C. "
             "Use the default 'steady' estimate for numbers you quote")


def _flow_method(steps: pd.DataFrame) -> str:
    """The per-run flow estimate of the flow steps ('steady', 'peak', or
    'mixed'; '' when the summary does not say)."""
    if "flow_method" not in steps or steps.empty:
        return ""
    found = {m for m in steps["flow_method"].astype(str) if m}
    return found.pop() if len(found) == 1 else ("mixed" if found else "")


def _check_summary(summary: pd.DataFrame) -> None:
    need = ("kind", "side", "load_mpag", "cam_deg", "q_mm3_s", "dp_mpa", "p1_mpa", "excluded")
    missing = [c for c in need if c not in summary.columns]
    if missing:
        raise DataError(f"summary has no column(s) {', '.join(missing)}; expected the per-run "
                        "summary (seanv_analysis.stages.dataset) with filters applied",
                        column=missing[0])


def _cam_angle(rows: pd.DataFrame, cam: str) -> np.ndarray:
    """theta [deg] per run: ``cam_measured_deg`` where finite (cam='measured'),
    else the commanded ``cam_deg``."""
    theta = rows["cam_deg"].to_numpy(float)
    if cam == "measured" and "cam_measured_deg" in rows:
        measured = rows["cam_measured_deg"].to_numpy(float)
        theta = np.where(np.isfinite(measured), measured, theta)
    return theta


def _load_shift(side, theta_d_fn, p1, dp, groups) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each run's threshold relative to its load's median pressures, eq. (3)+(4)
    [deg], and the load's median (p1, dp) [MPa] per run: dp falls as the valve
    opens (the head pressure follows the flow), so within one load every run
    has its own theta_d(p1, dp); taking that movement out of theta lets one
    quadratic per load give the threshold at the load's median pressures."""
    shift = np.zeros(p1.shape)
    p1_ref, dp_ref = np.full(p1.shape, np.nan), np.full(p1.shape, np.nan)
    for g in groups:
        p1_ref[g], dp_ref[g] = np.median(p1[g]), np.median(dp[g])
    ok = np.isfinite(p1_ref)
    with np.errstate(invalid="ignore"):
        shift[ok] = theta_d_fn(p1[ok], dp[ok]) - theta_d_fn(p1_ref[ok], dp_ref[ok])
    return shift, p1_ref, dp_ref


def _fit_side(side_name: str, rows: pd.DataFrame, base: ValveModel, *, procedure: str,
              n_boot: int, seed: int, load_tol_mpag: float, cam: str,
              flow_scale_u95: float, cam_u95_deg: float, q_leak: np.ndarray | None = None,
              dp_leak: np.ndarray | None = None, leak_half95: float = math.nan,
              ) -> tuple[SideFit, pd.DataFrame, np.ndarray, list[str]]:
    """Fit one side to its runs' flow less the seat leakage ``q_leak`` [mm^3/s]
    (eq. 5 is the valve's own flow). ``dp_leak`` [MPa] and ``leak_half95``
    [mm^3/(s MPa)]: the leakage's pressure term and its conductance's 95 %
    half-width, whose effect on z0 and C is added to their intervals.
    Returns (SideFit, per-load table, sigma per used row, warnings)."""
    side = base.side(side_name)
    up = side.opens_upward
    warns: list[str] = []
    result = SideFit(side_name, procedure=procedure, n_runs=len(rows))
    theta = _cam_angle(rows, cam)
    q = rows["q_mm3_s"].to_numpy(float)
    if q_leak is not None:
        q = q - q_leak
    p1 = rows["p1_mpa"].to_numpy(float)
    dp = rows["dp_mpa"].to_numpy(float)
    level = group_loads(rows["load_mpag"].to_numpy(float), tol_mpag=load_tol_mpag)
    sigma = np.full(q.shape, np.nan)
    if len(rows) < 3 or np.unique(theta).size < 2:
        result.message = (f"{len(rows)} usable run(s) at {np.unique(theta).size} cam angle(s); "
                          "need >= 3 runs at >= 2 angles")
        return result, pd.DataFrame(), sigma, [f"{side_name}: {result.message}"]

    # (a) per load, pass 1 unweighted -> noise model -> pass 2 weighted
    levels = np.unique(level[np.isfinite(level)])
    groups = [np.flatnonzero(level == lv) for lv in levels]
    # each run's flow brought to its load's median dp (eq. 5: Q ~ dp^n), so the
    # per-load quadratic is not bent by dp changing with the opening
    dp_pow = signed_power(dp, side.dp_exponent)
    q_load = q.copy()
    for g in groups:
        q_load[g] = q[g] * signed_power(np.median(dp[g]), side.dp_exponent) / dp_pow[g]
    # ... and its cam angle moved by its threshold's offset from the one at the
    # load's median pressures (eq. 3+4 with the side's geometry), so theta_d
    # of each load is the threshold at the load's median pressures
    shift, p1_ref, dp_ref = _load_shift(side, side.threshold_deg, p1, dp, groups)
    q_hat = np.abs(q).copy()
    resid1 = np.full(q.shape, np.nan)
    for g in groups:
        lf = fit_load(theta[g], q_load[g], opens_upward=up, theta_shift_deg=shift[g])
        if lf.success and math.isfinite(lf.theta_d_deg):
            pred = lf.predict(theta[g] - shift[g], opens_upward=up)
            q_hat[g], resid1[g] = np.abs(pred), q_load[g] - pred
    noise = fit_noise_model(resid1, q_hat)
    sigma = noise.sigma(q_hat)
    result.noise = {"floor_mm3_s": noise.floor_mm3_s, "rel": noise.rel}
    load_rows = []
    for lv, g in zip(levels, groups):
        lf = fit_load(theta[g], q_load[g], opens_upward=up, sigma_mm3_s=sigma[g],
                      theta_shift_deg=shift[g])
        p1_med, dp_med = float(np.median(p1[g])), float(np.median(dp[g]))
        load_rows.append({"side": side_name, "load_level_mpag": float(lv), "n_runs": int(g.size),
                          "p1_mpa": p1_med, "dp_mpa": dp_med,
                          "p1_threshold_mpa": p1_med, "dp_threshold_mpa": dp_med,
                          "theta_d_deg": lf.theta_d_deg, "theta_d_se_deg": lf.theta_d_se_deg,
                          "alpha_mm3_s_deg2": lf.alpha, "alpha_se_mm3_s_deg2": lf.alpha_se,
                          "rmse_mm3_s": lf.rmse_mm3_s, "success": lf.success,
                          "message": lf.message})
    per_load = pd.DataFrame(load_rows)
    ok = per_load["success"].to_numpy(bool) if len(per_load) else np.zeros(0, bool)
    if len(per_load) and not ok.all():
        warns.append(f"{side_name}: quadratic fit failed at load(s) "
                     f"{per_load.loc[~ok, 'load_level_mpag'].tolist()} MPaG")

    # (b)+(c) two-step
    pl = per_load[ok] if len(per_load) else per_load
    ts = two_step(side, pl["theta_d_deg"], pl["theta_d_se_deg"], pl["alpha_mm3_s_deg2"],
                  pl["alpha_se_mm3_s_deg2"],
                  pl["p1_mpa"], pl["dp_mpa"]) if len(pl) else {
        "z0_mm": math.nan, "c_flow": math.nan, "success": False, "message": "no per-load fit"}
    result.two_step = ts

    # joint fit, eq. (5) on every run
    z_start = ts["z0_mm"] if math.isfinite(ts.get("z0_mm", math.nan)) else side.z0_mm
    jf = fit_joint(side, theta, p1, dp, q, sigma, z0_start_mm=z_start)
    if math.isfinite(jf.z0_mm):  # noise model again, from the joint residuals
        noise = fit_noise_model(jf.residual_mm3_s, jf.q_model_mm3_s)
        sigma = noise.sigma(jf.q_model_mm3_s)
        result.noise = {"floor_mm3_s": noise.floor_mm3_s, "rel": noise.rel}
        jf = fit_joint(side, theta, p1, dp, q, sigma, z0_start_mm=jf.z0_mm)
    result.joint = {"z0_mm": jf.z0_mm, "c_flow": jf.c_flow, "z0_se_mm": jf.z0_se_mm,
                    "c_se": jf.c_se, "f_scale": jf.f_scale, "nfev": jf.nfev,
                    "success": jf.success, "message": jf.message}
    if procedure == "joint":
        result.z0_mm, result.c_flow, result.success = jf.z0_mm, jf.c_flow, jf.success
        result.message = jf.message
    else:
        result.z0_mm, result.c_flow = ts["z0_mm"], ts["c_flow"]
        result.success = bool(ts["success"]) and math.isfinite(ts["c_flow"])
        result.message = ts.get("message", "")
    if not (math.isfinite(result.z0_mm) and math.isfinite(result.c_flow)):
        result.success = False
        result.message = result.message or "fit gave no finite parameters"
        return result, per_load, sigma, warns + [f"{side_name}: {result.message}"]

    q_model = base.with_side(side_name, z0_mm=result.z0_mm, c_flow=result.c_flow) \
        .side(side_name).flow(theta, p1, dp)
    result.rmse_mm3_s = float(np.sqrt(np.mean((q - q_model) ** 2)))
    # a condition = load level x commanded cam; its runs are repeats (lack of
    # fit: their scatter is the pure error; bootstrap: resampled together)
    clusters = [f"{lv:.4g}|{c:.3f}" for lv, c in zip(level, rows["cam_deg"].to_numpy(float))]
    # the test asks whether eq. (5) describes the runs, so it takes the best
    # eq. (5) fit: the joint one (two-step parameters are biased when dp
    # changes with the opening, a misfit of the procedure, not of the model)
    joint_ok = math.isfinite(jf.z0_mm) and math.isfinite(jf.c_flow)
    lof = lack_of_fit_test(jf.residual_mm3_s if joint_ok else q - q_model, clusters,
                           sigma_mm3_s=sigma, flow_mm3_s=jf.q_model_mm3_s if joint_ok else q_model)
    _set_lack_of_fit(result, lof)

    # uncertainty: bootstrap over runs, unless the covariance is singular
    singular = not (math.isfinite(jf.z0_se_mm) and math.isfinite(jf.c_se))
    if procedure == "joint" and singular:
        result.message = "covariance singular: no confidence intervals"
        warns.append(f"{side_name}: {result.message}")
    elif n_boot > 0:
        boot = _bootstrap(side, theta, p1, dp, q_load, q, sigma, level, procedure=procedure,
                          x_hat=(result.z0_mm, result.c_flow), f_scale=jf.f_scale,
                          n_boot=n_boot, seed=seed, clusters=clusters,
                          per_load=(shift, p1_ref, dp_ref))
        result.n_boot_ok = len(boot)
        result.ci_method = (f"bootstrap over conditions (load level x commanded cam; repeats "
                            f"resampled together), percentile, {len(boot)}/{n_boot} "
                            f"resamples, seed {seed}")
        if len(boot) >= max(20, 0.8 * n_boot):
            lo, hi = np.percentile(boot, [2.5, 97.5], axis=0)
            result.z0_ci95_stat = (float(lo[0]), float(hi[0]))
            result.c_ci95_stat = (float(lo[1]), float(hi[1]))
            # calibration (Type B) half-widths: cam zero -> z0, flow scale -> C
            dz0 = cam_u95_deg / _threshold_slope(side, result.z0_mm, p1, dp)
            dc = flow_scale_u95 * abs(result.c_flow)
            # the seat leakage's conductance, fitted beside: its 95 % half-width
            # moved through the fit (z0, C refitted at g -+ half)
            dz0_leak, dc_leak = _leak_sensitivity(
                side, theta, p1, dp, q, sigma, dp_leak, leak_half95, procedure=procedure,
                x_hat=(result.z0_mm, result.c_flow))
            result.z0_ci95 = widen_interval(result.z0_mm, result.z0_ci95_stat, math.hypot(dz0, dz0_leak))
            result.c_ci95 = widen_interval(result.c_flow, result.c_ci95_stat, math.hypot(dc, dc_leak))
            if cam_u95_deg or flow_scale_u95:
                result.ci_method += (f" (+) calibration: cam zero {cam_u95_deg:g} deg, flow "
                                     f"scale {flow_scale_u95:.2%} (95 %, in quadrature)")
            if dz0_leak or dc_leak:
                result.ci_method += (f" (+) seat leakage: its conductance's 95 % half-width "
                                     f"{leak_half95:.3g} mm^3/(s MPa) through the fit (z0 "
                                     f"{dz0_leak:.2g} mm, C {dc_leak:.2g}, in quadrature)")
        else:
            msg = f"only {len(boot)}/{n_boot} bootstrap fits converged: no intervals"
            result.message = (result.message + "; " if result.message else "") + msg
            warns.append(f"{side_name}: {msg}")
    else:
        result.ci_method = "none (n_boot = 0)"
    if lof.flagged:
        result.message = "; ".join(m for m in (result.message, _lack_of_fit_sentence(lof)) if m)
    return result, per_load, sigma, warns


def _set_lack_of_fit(result: SideFit, lof: LackOfFit) -> None:
    result.lack_of_fit = lof.flagged
    result.lack_of_fit_ratio, result.lack_of_fit_p = lof.ratio, lof.p_value
    result.lack_of_fit_detail = {
        "test": "lack-of-fit F test: conditions' mean residuals vs repeats (pure error), "
                "weights 1/sigma^2, 2 parameters",
        "f_stat": lof.f_stat, "df_lof": lof.df_lof, "df_pe": lof.df_pe,
        "n_conditions": lof.n_conditions, "n_repeated": lof.n_repeated,
        "systematic_pct": 100.0 * lof.systematic,
        "criteria": f"p < {LOF_P_MAX:g}, ratio > {LOF_RATIO_MIN:g}, systematic misfit > "
                    f"{100 * LOF_SYSTEMATIC_MIN:g} % of the flow",
        "reason": lof.reason}


def _threshold_slope(side, z0_mm: float, p1, dp) -> float:
    """|d theta_d / d z0| [deg/mm] at the side's median pressures (eq. 3+4)."""
    p1m, dpm, h = float(np.median(p1)), float(np.median(dp)), 1e-3
    d = side.threshold_deg(p1m, dpm, z0_mm=z0_mm + h) - side.threshold_deg(p1m, dpm,
                                                                          z0_mm=z0_mm - h)
    return max(abs(float(d)) / (2 * h), 1e-9)


def _leak_sensitivity(side, theta, p1, dp, q, sigma, dp_leak, half, *, procedure,
                      x_hat) -> tuple[float, float]:
    """(|dz0| [mm], |dC|) of the joint fit when the seat leakage's conductance
    moves by its 95 % half-width ``half`` [mm^3/(s MPa)] either way (half the
    difference of the two refits); (0, 0) without a fitted leakage or for the
    two-step procedure (whose per-load fits see the same flows)."""
    if dp_leak is None or not (math.isfinite(half) and half > 0) or procedure != "joint":
        return 0.0, 0.0
    fits = [fit_joint(side, theta, p1, dp, q - sgn * half * dp_leak, sigma,
                      z0_start_mm=x_hat[0]) for sgn in (1.0, -1.0)]
    if not all(math.isfinite(f.z0_mm) and math.isfinite(f.c_flow) for f in fits):
        return 0.0, 0.0
    return 0.5 * abs(fits[0].z0_mm - fits[1].z0_mm), 0.5 * abs(fits[0].c_flow - fits[1].c_flow)


def _bootstrap(side, theta, p1, dp, q_load, q, sigma, level, *, procedure, x_hat, f_scale, n_boot,
               seed, clusters, per_load) -> np.ndarray:
    if procedure == "joint":
        return bootstrap_joint(side, theta, p1, dp, q, sigma, x_hat=x_hat, f_scale=f_scale,
                               n_boot=n_boot, seed=seed, clusters=clusters)
    rng = np.random.default_rng(seed)
    members = _cluster_members(q.size, clusters)
    shift, p1_ref, dp_ref = per_load
    out = []
    up = side.opens_upward
    for _ in range(n_boot):
        idx = resample_indices(rng, members)
        rows = []
        for lv in np.unique(level[idx]):
            g = idx[level[idx] == lv]
            lf = fit_load(theta[g], q_load[g], opens_upward=up, sigma_mm3_s=sigma[g],
                          theta_shift_deg=shift[g])
            if lf.success:
                rows.append((lf.theta_d_deg, lf.theta_d_se_deg, lf.alpha, lf.alpha_se,
                             np.median(p1_ref[g]), np.median(dp_ref[g])))
        if not rows:
            continue
        a = np.array(rows, dtype=float)
        ts = two_step(side, *a.T)
        if ts["success"] and math.isfinite(ts["c_flow"]):
            out.append((ts["z0_mm"], ts["c_flow"]))
    return np.asarray(out, dtype=float).reshape(-1, 2)


def fit_flow(summary: pd.DataFrame, rig: Any, *, sides: Sequence[str] = SIDES,
             procedure: str = "joint", n_boot: int = 200, seed: int = 0,
             load_tol_mpag: float = 0.02, cam: str = "measured",
             flow_scale_u95: float = DEFAULT_FLOW_SCALE_U95,
             cam_u95_deg: float = DEFAULT_CAM_U95_DEG,
             model: ValveModel | None = None, leakage: str = "fit") -> FlowFit:
    """Identify z0 and C of each side from a per-run summary (paper Sec. II-D.2).

    Q = C (theta - theta_d(p1, dp; z0))^2 dp^0.5, eq. (5), with theta_d from
    eq. (3)+(4) inverted by interpolation (:meth:`ValveSide.threshold_deg`).

    Parameters
    ----------
    summary : per-run summary with filters applied (``stages.dataset.run(...).summary``);
        only ``kind == 'flow_step'`` rows with ``excluded == ''`` are fitted.
        Columns used: side, load_mpag [MPaG], cam_deg [deg], q_mm3_s [mm^3/s],
        p1_mpa and dp_mpa [MPa] (supply: p1 = p_supply, dp = p_supply - p_head;
        drain: p1 = p_head, dp = p_head - p_tank).
    rig : rig config (needle geometry, cam range); :class:`~seanv_analysis.config.RigConfig`
    sides : sides to fit ('supply', 'drain')
    procedure : 'joint' (default; z0 and C together on all runs, robust) or
        'two_step' (the paper's: per-load quadratics, then z0, then C)
    n_boot : bootstrap resamples for the 95 % intervals (0: no intervals)
    seed : bootstrap seed
    load_tol_mpag : runs whose loads differ by less than this [MPa] share a load level
    cam : theta of each run: 'measured' (default; the servo feedback
        ``cam_measured_deg``, the commanded angle where it is NaN) or 'commanded'
        (``cam_deg``). The valve sees the actual angle; the servo's resolution
        (0.088 deg) and backlash make the command differ from it by a
        repeatable amount that no averaging removes.
    flow_scale_u95 : calibration uncertainty (95 % half-width, relative) of the
        flow scale Q = v A (piston area, encoder scale, derivative bias); it
        scales C and is added in quadrature to the bootstrap interval of C
    cam_u95_deg : calibration uncertainty (95 % half-width) of the cam zero [deg];
        it shifts every theta_d, so it is added in quadrature to z0's interval
        as cam_u95_deg / |d theta_d / d z0|
    model : valve whose geometry is used (default ``ValveModel.from_rig(rig)``)
    leakage : the needles' seat leakage beside eq. (5): 'fit' (default; its
        conductance fitted with both sides' z0 and C, the rig file's where the
        runs cannot tell it), 'rig' (the rig file's
        ``valve.plant.leakage_conductance_mm3_s_per_mpa``) or 'none'

    Returns
    -------
    FlowFit

    Raises
    ------
    ConfigError
        ``sides``, ``procedure`` or ``leakage`` not known.
    DataError
        ``summary`` lacks a needed column.
    FitError
        no side asked for could be fitted (too few usable runs).

    Examples
    --------
    >>> from seanv_analysis.config import load_rig
    >>> from synthetic_flow import synthetic_flow_summary  # tests/synthetic_flow.py
    >>> rig = load_rig(); truth = ValveModel.from_rig(rig)
    >>> fit = fit_flow(synthetic_flow_summary(truth, rig, seed=1), rig, n_boot=0)
    >>> round(fit.sides["supply"].c_flow, 0), round(fit.sides["drain"].z0_mm, 2)
    (17.0, -0.03)
    """
    sides = tuple(sides)
    bad = [s for s in sides if s not in SIDES]
    if bad or not sides:
        raise ConfigError(f"sides: expected a non-empty subset of {SIDES}, got {sides!r}")
    if cam not in CAM_SOURCES:
        raise ConfigError(f"cam: expected one of {CAM_SOURCES}, got {cam!r}")
    if procedure not in PROCEDURES:
        raise ConfigError(f"procedure: expected one of {PROCEDURES}, got {procedure!r}")
    if leakage not in LEAKAGE_MODES:
        raise ConfigError(f"leakage: expected one of {LEAKAGE_MODES}, got {leakage!r}")
    _check_summary(summary)
    from ..signals.filters import exclusion_counts

    base = model or ValveModel.from_rig(rig)
    steps = summary[summary["kind"] == "flow_step"]
    asked = steps if set(sides) == set(SIDES) else steps[steps["side"].isin(sides)]
    excluded = exclusion_counts(asked)
    fitted = base
    results: dict[str, SideFit] = {}
    per_runs, per_loads, warns = [], [], []
    method = _flow_method(asked)
    if method == "peak":
        warns.append(PEAK_BIAS)
    opts = dict(procedure=procedure, seed=seed, load_tol_mpag=load_tol_mpag, cam=cam,
                flow_scale_u95=flow_scale_u95, cam_u95_deg=cam_u95_deg)
    rows_of = {}
    for s in sides:
        rows_all = asked[asked["side"] == s]
        use = (rows_all["excluded"].fillna("").astype(str) == "").to_numpy()
        rows_of[s] = (rows_all, use)
    leak, dp_leak = _fit_leakage(rows_of, base, rig, leakage=leakage, opts=opts)
    for s in sides:
        rows_all, use = rows_of[s]
        rows = rows_all[use]
        g = leak.conductance_mm3_s_per_mpa
        res, pl, sigma, w = _fit_side(s, rows, base, n_boot=n_boot, q_leak=g * dp_leak[s][use],
                                      dp_leak=dp_leak[s][use],
                                      leak_half95=leak.half_width95, **opts)
        results[s], warns = res, warns + w
        if math.isfinite(res.z0_mm) and math.isfinite(res.c_flow):
            fitted = fitted.with_side(s, z0_mm=res.z0_mm, c_flow=res.c_flow)
        side_model = fitted.side(s) if res.success else None
        per_runs.append(_per_run(rows_all, use, sigma, side_model, load_tol_mpag, cam,
                                 dp_leak=dp_leak[s], conductance=g))
        if len(pl):
            if side_model is not None:
                pl["theta_d_model_deg"] = side_model.threshold_deg(pl["p1_mpa"].to_numpy(),
                                                                   pl["dp_mpa"].to_numpy())
                pl["alpha_model_mm3_s_deg2"] = side_model.c_flow * signed_power(pl["dp_mpa"].to_numpy(),
                                                                     side_model.dp_exponent)
            per_loads.append(pl)
    if leak.message and leakage == "fit":
        warns.append(f"seat leakage: {leak.message}")
    if not any(r.success for r in results.values()):
        raise FitError("no side could be fitted: " + "; ".join(
            f"{s}: {r.message}" for s, r in results.items()))
    for w in warns:
        warnings.warn(w, stacklevel=2)
    ok = all(r.success for r in results.values())
    fitted = type(fitted)(fitted.supply, fitted.drain, fitted.cam_min_deg, fitted.cam_max_deg,
                          {**fitted.extras, SEAT_LEAK_KEY: leak.conductance_mm3_s_per_mpa,
                           "flowfit": {
                              "procedure": procedure, "sides": list(sides),
                              "ci95": {s: {"z0_mm": [json_num(v) for v in r.z0_ci95],
                                           "c_flow": [json_num(v) for v in r.c_ci95]}
                                       for s, r in results.items()}}})
    per_run = (pd.concat(per_runs, ignore_index=True) if per_runs
               else pd.DataFrame(columns=list(_PER_RUN_COLUMNS)))
    per_load = pd.concat(per_loads, ignore_index=True) if per_loads else pd.DataFrame()
    return FlowFit(results, fitted, per_run, per_load, excluded, ok,
                   "" if ok else "; ".join(f"{s}: {r.message}" for s, r in results.items()
                                           if not r.success),
                   warns, {"procedure": procedure, "n_boot": n_boot, "seed": seed,
                           "sides": list(sides), "load_tol_mpag": load_tol_mpag, "cam": cam,
                           "flow_scale_u95": flow_scale_u95, "cam_u95_deg": cam_u95_deg,
                           "loss": "soft_l1", "ci": "bootstrap percentile 95 %",
                           "leakage": leakage, "flow_method": method},
                   leak)


def _fit_leakage(rows_of: dict, base: ValveModel, rig: Any, *, leakage: str,
                 opts: dict) -> tuple[LeakageFit, dict[str, np.ndarray]]:
    """The seat leakage's conductance (:func:`._leakage.fit_leakage`: fitted
    with the sides' z0 and C, each side's noise scale and start from its fit
    without leakage; 'rig': the rig file's; 'none': 0) and each side's
    leakage pressure term dp_supply - dp_drain per row [MPa]."""
    plant = rig["valve"]["plant"]
    default = float(plant["leakage_conductance_mm3_s_per_mpa"])
    p_supply = float(rig["supply"]["pressure_mpag"])
    p_tank = float(rig["supply"]["tank_pressure_mpag"])
    dp_leak = {}
    for s, (rows_all, _) in rows_of.items():
        sealed = (rows_all["dp_sealed_mpa"].to_numpy(float) if "dp_sealed_mpa" in rows_all
                  else np.full(len(rows_all), np.nan))
        dp_leak[s] = leak_dp_mpa(np.full(len(rows_all), s), rows_all["p1_mpa"].to_numpy(float),
                                 rows_all["dp_mpa"].to_numpy(float), sealed,
                                 p_supply_mpag=p_supply, p_tank_mpag=p_tank)
    if leakage == "none":
        return LeakageFit(0.0, message="not modelled (leakage='none')"), dp_leak
    if leakage == "rig":
        return LeakageFit(default, message="the rig file's (leakage='rig')"), dp_leak
    parts = []
    for s, (rows_all, use) in rows_of.items():
        rows = rows_all[use]
        ok = np.isfinite(dp_leak[s][use])
        if len(rows) < 3:
            continue
        res, _, sigma, _ = _fit_side(s, rows, base, n_boot=0, **opts)
        if not (math.isfinite(res.joint.get("z0_mm", math.nan))
                and math.isfinite(res.joint.get("c_flow", math.nan))) or not ok.all():
            continue
        theta = _cam_angle(rows, opts["cam"])
        level = group_loads(rows["load_mpag"].to_numpy(float), tol_mpag=opts["load_tol_mpag"])
        clusters = np.asarray([f"{lv:.4g}|{c:.3f}" for lv, c in
                               zip(level, rows["cam_deg"].to_numpy(float))], dtype=object)
        start = base.with_side(s, z0_mm=res.joint["z0_mm"], c_flow=res.joint["c_flow"]).side(s)
        parts.append(SideRuns(start, theta, rows["p1_mpa"].to_numpy(float),
                              rows["dp_mpa"].to_numpy(float), rows["q_mm3_s"].to_numpy(float),
                              sigma, dp_leak[s][use], clusters=clusters))
    # the paper's leakage band: a sealed valve's flow stays within +-leakage_flow
    # at the supply pressure, which bounds the conductance
    band = float(rig.analysis["leakage_flow_mm3_s"])
    upper = band / max(p_supply, 0.1)
    return fit_leakage(parts, upper_mm3_s_per_mpa=upper, default_mm3_s_per_mpa=default,
                       prior_sd_mm3_s_per_mpa=prior_sd_mm3_s_per_mpa(band, p_supply)), dp_leak


def _per_run(rows_all: pd.DataFrame, use: np.ndarray, sigma_used: np.ndarray, side_model,
             load_tol_mpag: float, cam: str, *, dp_leak: np.ndarray,
             conductance: float) -> pd.DataFrame:
    cols = [c for c in ("run_id", "side", "run_index", "load_mpag", "cam_deg", "q_mm3_s",
                        "p1_mpa", "dp_mpa", "excluded", "excluded_detail") if c in rows_all]
    df = rows_all[cols].reset_index(drop=True).copy()
    if "excluded_detail" not in df:
        df["excluded_detail"] = ""
    df["excluded"] = df["excluded"].fillna("").astype(str)
    df["excluded_detail"] = df["excluded_detail"].fillna("").astype(str)
    df.insert(4, "load_level_mpag", group_loads(df["load_mpag"].to_numpy(float),
                                                tol_mpag=load_tol_mpag))
    df["used"] = use
    df.insert(6, "theta_deg", _cam_angle(rows_all, cam))
    theta, p1, dp = (df[c].to_numpy(float) for c in ("theta_deg", "p1_mpa", "dp_mpa"))
    df["dp_leak_mpa"] = dp_leak
    q_leak = conductance * dp_leak
    df["q_leak_mm3_s"] = q_leak
    if side_model is not None:
        with np.errstate(invalid="ignore"):
            df["theta_d_model_deg"] = side_model.threshold_deg(p1, dp)
            # the model's flow: eq. (5) of the side and the seat leakage
            df["q_model_mm3_s"] = side_model.flow(theta, p1, dp) + np.nan_to_num(q_leak)
            # threshold implied by each run's flow less the leakage with the
            # fitted C (eq. 6 inverted): theta_i - opening_i, opening from the
            # model's cam_for_flow
            opening = side_model.cam_for_flow(df["q_mm3_s"].to_numpy(float)
                                              - np.nan_to_num(q_leak), p1, dp) \
                - side_model.threshold_deg(p1, np.maximum(dp, MIN_DP_MPA))
            df["theta_d_implied_deg"] = theta - opening
    else:
        df["theta_d_model_deg"] = np.nan
        df["q_model_mm3_s"] = np.nan
        df["theta_d_implied_deg"] = np.nan
    df["residual_mm3_s"] = df["q_mm3_s"] - df["q_model_mm3_s"]
    sig = np.full(len(df), np.nan)
    sig[use] = sigma_used
    df["sigma_mm3_s"] = sig
    df["z_score"] = df["residual_mm3_s"] / df["sigma_mm3_s"]
    return df[[c for c in _PER_RUN_COLUMNS if c in df]]

