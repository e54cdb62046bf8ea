"""Needle geometry: how the sealing threshold moves with the pressures.

Eq. (3) gives the threshold's spring displacement z_c = z0 - F_w / k, with
F_w = pi/4 (d_n^2 p1 - d_o^2 dp) (eq. 1); eq. (4) turns it into a cam angle
through the needle-head centre (x_c, y_c), which Table II does not publish.
Near the thresholds the cam angle moves by dz_c / (dz/dtheta) per unit
height, and dz/dtheta = tan(phi) (-x_c sin theta - y_c cos theta) + O(r
tan(phi) sin(phi)): at theta = -10..-25 deg, y_c sets it ~4-6 times more
strongly than x_c, while x_c's effect on the height itself is a constant
offset that z0 absorbs. So the one-parameter form fitted here is y_c with
x_c kept at the rig file's value: with z0 it reproduces the threshold over
the tested pressures whatever the true (x_c, y_c). x_c itself the flow steps
cannot tell (with it free the fit is singular): it is reported as not
identified, confounded with z0 and y_c, and the rig file's 95 % range of it
(``valve.needle_x_c_uncertainty_mm``) is carried into the intervals of y_c,
z0 and C by what it moves them (:func:`_x_c_slopes`).

Q = C (theta - theta_d(p1, dp; z0, y_c))^2 dp^0.5 (eq. 5) plus the needles'
seat leakage g (dp_supply - dp_drain) (:func:`seanv_analysis.models.seat_leakage_mm3_s`)
is fitted to the flow steps flowfit used, both sides at once: (z0, C, y_c)
of each side and the one leakage conductance g, with the same per-run noise
scale and robust loss as flowfit's joint fit. The leakage must be in it: it
moves with the head pressure from load to load as the threshold does, and
left out it put y_c 0.27 mm (7 standard errors) off on the simulator's own
clean flow steps (supply -20.27 [-20.31, -20.23] for -20; drain 19.2 for 20).
The 95 % interval of y_c is a cluster-robust sandwich (the repeats of a
condition, load level x commanded cam, share their errors), widened to the
same sandwich clustered by load level with Student's t (load levels - 1)
where that is wider: y_c is told by the threshold's movement from load to
load only. y_c is
identified only when the runs span different fluid forces (>= 2 load levels
whose thresholds differ by more than the threshold's own scatter) and its
95 % interval is finite and narrower than +-50 % of the value; otherwise the
rig file's value stays.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any, Sequence

import numpy as np
from scipy.optimize import least_squares

from ..estimate import widen_interval
from ..fit import Eq5Residual, SideRuns, cluster_covariance, prior_sd_mm3_s_per_mpa, soft_l1_weights
from ..fit.flowfit import C_KEY
from ..models import ValveSide, fluid_force_n
from .result import Constant

__all__ = ["GeometryFit", "fit_geometry", "fit_geometry_sides", "geometry_constants",
           "threshold_span"]


@dataclass
class GeometryFit:
    """(z0, C, y_c) of one side with 95 % intervals (cluster-robust sandwich);
    ``identified`` False with ``note`` when y_c cannot be told; the seat
    leakage's conductance g [mm^3/(s MPa)] of the fit (shared by the sides
    fitted together) with its interval."""

    side: str
    z0_mm: float
    c_flow: float
    y_c_mm: float
    y_c_ci95: tuple[float, float]
    identified: bool
    note: str
    rmse_mm3_s: float
    rmse_default_mm3_s: float
    n_runs: int
    n_loads: int
    force_span_n: float
    leak_mm3_s_per_mpa: float = 0.0
    leak_ci95: tuple[float, float] = (math.nan, math.nan)
    x_c_slope: tuple[float, float, float] = (math.nan, math.nan, math.nan)


def _with(side: ValveSide, z0, c, y_c) -> ValveSide:
    geom = replace(side.geometry, needle_y_c_mm=float(y_c))
    return replace(side, z0_mm=float(z0), c_flow=float(c), geometry=geom)


def _valid(side: ValveSide, y_c) -> bool:
    """Eq. (4) with this y_c is monotonic over the model's cam range (it can
    be inverted: a geometry the valve model can use)."""
    try:
        z, _ = _with(side, side.z0_mm, side.c_flow, y_c).geometry.height_table
    except ValueError:
        return False
    return z.size > 0


def _predict(side: ValveSide, x, theta, p1, dp):
    try:
        return _with(side, *x).flow(theta, p1, dp)
    except ValueError:          # eq. (4) not monotonic for this y_c
        return np.full(theta.shape, np.nan)


def _bounds(side: ValveSide, z0: float, c: float) -> tuple[list[float], list[float]]:
    """Bounds of (z0 [mm], C, y_c [mm]): z0 +-1 mm, C within 20x of its sign,
    y_c on the rig file's side of the cam, 4-80 mm from it."""
    y0 = float(side.geometry.needle_y_c_mm)
    sgn = math.copysign(1.0, y0) if y0 != 0 else -1.0
    return ([z0 - 1.0, min(0.0, 20 * c), -80.0 if sgn < 0 else 4.0],
            [z0 + 1.0, max(0.0, 20 * c), -4.0 if sgn < 0 else 80.0])


class _Layout:
    """Parameter vector of the joint fit: per side z0, C (and y_c when free),
    then the leakage conductance g when fitted."""

    def __init__(self, names, free_y, fit_leak):
        self.names = list(names)
        self.free = [n in free_y for n in self.names]
        self.fit_leak = fit_leak
        self.slices = {}
        i = 0
        for n, f in zip(self.names, self.free):
            self.slices[n] = slice(i, i + (3 if f else 2))
            i += 3 if f else 2
        self.size = i + (1 if fit_leak else 0)

    def side_x(self, x, name, y_fixed):
        p = x[self.slices[name]]
        return (p[0], p[1], p[2] if len(p) == 3 else y_fixed)

    def leak(self, x, fixed):
        return x[-1] if self.fit_leak else fixed


def _fit(runs: dict[str, SideRuns], x0, lo, hi, f_scale, layout: _Layout, y_fixed, g_fixed,
         g_prior_sd: float = math.inf, starts: Sequence[float] | None = None):
    """least_squares from ``x0`` (a few starts of the free y_c), with
    :func:`_jacobian`; returns (x, solution, residual function). A fitted
    leakage conductance has the prior N(``g_fixed``, ``g_prior_sd``^2): one
    more residual."""
    prior = layout.fit_leak and math.isfinite(g_prior_sd)
    last: dict[str, Any] = {}

    def resid(p):
        g = layout.leak(p, g_fixed)
        sides = [_side_resid(runs[n], layout.side_x(p, n, y_fixed[n]), g) for n in layout.names]
        last["p"], last["sides"] = np.array(p, copy=True), sides
        return np.concatenate(sides + ([np.array([(g - g_fixed) / g_prior_sd])] if prior else []))

    def jac(p):     # the sides' rows at p: scipy asks for the Jacobian where it just evaluated
        at_p = last["sides"] if "p" in last and np.array_equal(last["p"], p) else None
        return _jacobian(runs, layout, p, y_fixed, g_fixed, hi, prior, g_prior_sd, at_p)

    x_scale = []
    for n, free in zip(layout.names, layout.free):
        x_scale += [0.01, max(abs(runs[n].side.c_flow), 1e-3)] + ([1.0] if free else [])
    x_scale += [1.0] if layout.fit_leak else []
    best = None
    factors = starts or ((1.0, 0.75, 1.3) if any(layout.free) else (1.0,))
    for k in factors:   # a few starts: the threshold is piecewise in the parameters
        p0 = np.array(x0, float)
        for n, free in zip(layout.names, layout.free):
            if free:
                p0[layout.slices[n].stop - 1] *= k
        p0 = np.clip(p0, np.add(lo, 1e-9), np.subtract(hi, 1e-9))
        sol = least_squares(resid, p0, jac=jac, bounds=(lo, hi), loss="soft_l1",
                            f_scale=f_scale, x_scale=x_scale)
        if best is None or sol.cost < best.cost:
            best = sol
    return np.asarray(best.x, float), best, resid


#: relative forward step of y_c in the fit's Jacobian (its z0, C and g columns are exact)
_Y_C_REL_STEP = 1e-5
#: the fit's residual of a run whose flow cannot be computed (eq. 4 not invertible, NaN)
_NO_FLOW = 1e3


def _side_resid(r: SideRuns, x, g: float) -> np.ndarray:
    """One side's rows of :func:`_fit`'s residual at its (z0, C, y_c) ``x``
    and the leakage conductance ``g``: (q - Q - g dp_leak) / sigma, :data:`_NO_FLOW`
    where no flow is computed (eq. 4 not invertible, or no number)."""
    z = (r.q_mm3_s - _predict(r.side, x, r.theta_deg, r.p1_mpa, r.dp_mpa)
         - g * r.dp_leak_mpa) / r.sigma_mm3_s
    return np.where(np.isfinite(z), z, _NO_FLOW)


def _jacobian(runs: dict[str, SideRuns], layout: _Layout, p: np.ndarray, y_fixed, g_fixed,
              hi, prior: bool, g_prior_sd: float,
              at_p: Sequence[np.ndarray] | None = None) -> np.ndarray:
    """Jacobian of :func:`_fit`'s residual: a side's rows move with its own
    z0 and C (eq. 5's analytic derivatives, :class:`~seanv_analysis.fit.Eq5Residual`,
    at its y_c) and y_c (a forward difference of that side's rows alone,
    :data:`_Y_C_REL_STEP` of |y_c|, backward at its upper bound), every
    flow row with g (-dp_leak / sigma), the prior's row with g alone; rows
    at the residual's sentinel (no flow computed) move with nothing.
    ``at_p``: each side's rows of the residual at ``p`` where known."""
    n_rows = sum(runs[n].q_mm3_s.size for n in layout.names) + (1 if prior else 0)
    out = np.zeros((n_rows, layout.size))
    g = layout.leak(p, g_fixed)
    row = 0
    for k, (n, free) in enumerate(zip(layout.names, layout.free)):
        r, sl = runs[n], layout.slices[n]
        rows = slice(row, row + r.q_mm3_s.size)
        row += r.q_mm3_s.size
        x = layout.side_x(p, n, y_fixed[n])
        f0 = at_p[k] if at_p is not None else _side_resid(r, x, g)
        moving = f0 != _NO_FLOW
        try:
            eq5 = Eq5Residual(_with(r.side, *x), r.theta_deg, r.p1_mpa, r.dp_mpa, r.q_mm3_s,
                              r.sigma_mm3_s)
        except ValueError:      # eq. (4) not monotonic for this y_c: no flow, no slope
            continue
        xs = np.array([[x[0], x[1]]])
        o, z = eq5.opening(xs)
        d_z0, d_c = eq5.jacobian(xs, o, z)
        out[rows, sl.start] = np.where(moving, d_z0[0], 0.0)
        out[rows, sl.start + 1] = np.where(moving, d_c[0], 0.0)
        if free:
            y = float(x[2])
            h = _Y_C_REL_STEP * max(abs(y), 1.0)
            h = -h if y + h > hi[sl.stop - 1] else h
            f1 = _side_resid(r, (x[0], x[1], y + h), g)
            out[rows, sl.stop - 1] = np.where(moving, (f1 - f0) / ((y + h) - y), 0.0)
        if layout.fit_leak:
            out[rows, -1] = np.where(moving, -r.dp_leak_mpa / r.sigma_mm3_s, 0.0)
    if prior:
        out[-1, -1] = 1.0 / g_prior_sd
    return out


def _raw_jacobian(fun, x, lo, hi) -> np.ndarray:
    """Central-difference Jacobian of ``fun`` at ``x`` (one-sided at a bound)."""
    f0 = fun(x)
    jac = np.empty((f0.size, x.size))
    for j in range(x.size):
        h = 1e-5 * max(abs(x[j]), 1e-2)
        xp, xm = x.copy(), x.copy()
        xp[j] = min(x[j] + h, hi[j])
        xm[j] = max(x[j] - h, lo[j])
        jac[:, j] = (fun(xp) - fun(xm)) / (xp[j] - xm[j])
    return jac


@dataclass
class JointGeometry:
    """Result of :func:`fit_geometry_sides`: per side (z0, C, y_c) with y_c's
    95 % interval (NaN when not free or singular), the fit with the rig
    file's y_c (``default``), the leakage conductance g with its interval."""

    sides: dict[str, tuple[float, float, float]]
    y_ci95: dict[str, tuple[float, float]]
    default: dict[str, tuple[float, float, float]]
    leak_mm3_s_per_mpa: float
    leak_ci95: tuple[float, float]
    leak_default_mm3_s_per_mpa: float
    x_c_slope: dict[str, tuple[float, float, float]] = field(default_factory=dict)
    x_c_slope_default: dict[str, tuple[float, float, float]] = field(default_factory=dict)


#: x_c step [mm] of :func:`_x_c_slopes` (z0, C, y_c move linearly with x_c
#: over several mm: field-clean, supply y_c 0.146, 0.148, 0.146 mm/mm for
#: steps of +1, -1, +2 mm)
X_C_STEP_MM = 1.0


def _x_c_slopes(runs: dict[str, SideRuns], x: np.ndarray, lo, hi, f_scale, layout: _Layout,
                y_fixed, g_fixed, g_prior_sd) -> dict[str, tuple[float, float, float]]:
    """How far each side's fitted (z0 [mm], C, y_c [mm]) moves per mm of the
    needle centres' x_c (which the fit holds at the rig file's): the same fit
    from its solution with one side's x_c moved by :data:`X_C_STEP_MM`, for
    each side (the sides share the leakage, so one side's x_c moves the
    other's too a little); per side and parameter the sum in quadrature over
    the moved sides. y_c's is 0 where y_c is held."""
    sq: dict[str, np.ndarray] = {n: np.zeros(3) for n in layout.names}
    for m in layout.names:
        moved = dict(runs)
        r = runs[m]
        moved[m] = replace(r, side=replace(r.side, geometry=replace(
            r.side.geometry, needle_x_c_mm=r.side.geometry.needle_x_c_mm + X_C_STEP_MM)))
        try:
            x1, _, _ = _fit(moved, x, lo, hi, f_scale, layout, y_fixed, g_fixed, g_prior_sd,
                            starts=(1.0,))
        except ValueError:      # eq. (4) not invertible with the moved centre
            return {}
        for n in layout.names:
            a, b = layout.side_x(x, n, y_fixed[n]), layout.side_x(x1, n, y_fixed[n])
            sq[n] += ((np.asarray(b, float) - np.asarray(a, float)) / X_C_STEP_MM) ** 2
    return {n: tuple(float(v) for v in np.sqrt(sq[n])) for n in layout.names}


def fit_geometry_sides(runs: dict[str, SideRuns], *, free_y: Sequence[str],
                       leak_mm3_s_per_mpa: float = 0.0, fit_leak: bool = True,
                       leak_upper_mm3_s_per_mpa: float = 15.0,
                       leak_prior_sd_mm3_s_per_mpa: float = math.inf) -> JointGeometry:
    """Fit (z0, C, y_c) of each side in ``runs`` (y_c only for ``free_y``)
    and the seat leakage's conductance g (``fit_leak``, with the prior
    N(``leak_mm3_s_per_mpa``, ``leak_prior_sd_mm3_s_per_mpa``^2) as flowfit
    has it; else held at ``leak_mm3_s_per_mpa``) to the flow steps, eq.
    (3)-(5) + leakage, all at once.

    First with the rig file's y_c (the ``default`` fit), then from it with
    y_c free (a few starts). 95 % intervals of y_c and g: cluster-robust
    sandwich over ``SideRuns.clusters``, normal quantile.
    """
    names = [n for n in runs]
    y_fixed = {n: float(runs[n].side.geometry.needle_y_c_mm) for n in names}
    z = np.concatenate([(runs[n].q_mm3_s - _predict(runs[n].side, (runs[n].side.z0_mm,
                                                                    runs[n].side.c_flow,
                                                                    y_fixed[n]),
                                                     runs[n].theta_deg, runs[n].p1_mpa,
                                                     runs[n].dp_mpa)
                         - leak_mm3_s_per_mpa * runs[n].dp_leak_mpa) / runs[n].sigma_mm3_s
                        for n in names])
    f_scale = max(1.4826 * float(np.nanmedian(np.abs(z))), 1e-6)
    fit_leak = bool(fit_leak and np.ptp(np.concatenate([runs[n].dp_leak_mpa for n in names]))
                    >= 0.2)
    g0 = min(max(float(leak_mm3_s_per_mpa), 0.0), leak_upper_mm3_s_per_mpa)

    def setup(free):
        layout = _Layout(names, free, fit_leak)
        x0, lo, hi = [], [], []
        for n in names:
            s = runs[n].side
            b_lo, b_hi = _bounds(s, s.z0_mm, s.c_flow)
            k = 3 if n in free else 2
            x0 += [s.z0_mm, s.c_flow, y_fixed[n]][:k]
            lo += b_lo[:k]
            hi += b_hi[:k]
        if fit_leak:
            x0.append(g0)
            lo.append(0.0)
            hi.append(float(leak_upper_mm3_s_per_mpa))
        return layout, np.array(x0, float), np.array(lo, float), np.array(hi, float)

    lay_d, x0_d, lo_d, hi_d = setup(())
    sd = float(leak_prior_sd_mm3_s_per_mpa)
    x_def, _, _ = _fit(runs, x0_d, lo_d, hi_d, f_scale, lay_d, y_fixed, g0, sd)
    slopes_def = _x_c_slopes(runs, x_def, lo_d, hi_d, f_scale, lay_d, y_fixed, g0, sd)
    default = {n: lay_d.side_x(x_def, n, y_fixed[n]) for n in names}
    g_def = float(lay_d.leak(x_def, g0))
    lay, x0, lo, hi = setup(tuple(free_y))
    for n in names:     # start from the default fit
        sl = lay.slices[n]
        x0[sl.start:sl.start + 2] = default[n][:2]
    if fit_leak:
        x0[-1] = g_def
    x, best, resid = _fit(runs, x0, lo, hi, f_scale, lay, y_fixed, g0, sd)
    ci = {n: (math.nan, math.nan) for n in names}
    g_ci = (math.nan, math.nan)
    r = resid(x)
    clusters = np.concatenate([np.asarray([f"{n}|{c}" for c in runs[n].clusters], object)
                               for n in names]
                              + ([np.asarray(["prior"], object)]
                                 if fit_leak and math.isfinite(sd) else []))
    jac, w = _raw_jacobian(resid, x, lo, hi), soft_l1_weights(r, f_scale)
    cov = cluster_covariance(jac, r, w, clusters)
    if cov is not None:
        by_load = _load_covariance(runs, names, jac, r, w, fit_leak and math.isfinite(sd))
        for n, free in zip(names, lay.free):
            j = lay.slices[n].stop - 1
            if free and np.isfinite(cov[j, j]) and cov[j, j] >= 0:
                half = max(1.96 * math.sqrt(cov[j, j]), _load_half_width(by_load, runs[n], j))
                ci[n] = (float(x[j] - half), float(x[j] + half))
        if fit_leak and np.isfinite(cov[-1, -1]) and cov[-1, -1] >= 0:
            half = 1.96 * math.sqrt(cov[-1, -1])
            g_ci = (max(float(x[-1]) - half, 0.0), float(x[-1]) + half)
    slopes = _x_c_slopes(runs, x, lo, hi, f_scale, lay, y_fixed, g0, sd)
    return JointGeometry({n: tuple(float(v) for v in lay.side_x(x, n, y_fixed[n]))
                          for n in names}, ci,
                         {n: tuple(float(v) for v in default[n]) for n in names},
                         float(lay.leak(x, g0)), g_ci, g_def, slopes, slopes_def)


def _load_covariance(runs: dict[str, SideRuns], names: Sequence[str], jac: np.ndarray,
                     r: np.ndarray, w: np.ndarray, prior: bool) -> np.ndarray | None:
    """The fit's sandwich covariance with the runs clustered by side and load
    level (None where a run's load level is not given)."""
    levels = [runs[n].load_level for n in names]
    if not all(np.isfinite(lv).all() for lv in levels):
        return None
    labels = np.concatenate([np.asarray([f"{n}|{v:.6g}" for v in lv], object)
                             for n, lv in zip(names, levels)]
                            + ([np.asarray(["prior"], object)] if prior else []))
    return cluster_covariance(jac, r, w, labels)


def _load_half_width(cov: np.ndarray | None, runs: SideRuns, j: int) -> float:
    """Half-width of parameter ``j``'s 95 % interval from the covariance
    clustered by load level, Student's t with (load levels - 1) degrees of
    freedom (0 when not available).

    y_c is told by how the threshold moves from load to load only, so an
    error a load level's runs share (the threshold's law a little off the
    model's at that load's pressures) is shared by every cam angle of it: on
    field-clean the per-load thresholds sat 0.006-0.017 deg off the true
    eq. (3)+(4) line with standard errors of 0.002-0.004 deg, and the
    interval clustered by condition (load x cam) missed the true y_c by
    1.5 half-widths. With five or so clusters the sandwich is itself
    uncertain: t(G - 1) quantile (Cameron, Gelbach & Miller 2008).
    """
    from scipy import stats

    if cov is None or not (np.isfinite(cov[j, j]) and cov[j, j] >= 0):
        return 0.0
    g = int(np.unique(runs.load_level).size)
    if g < 3:
        return 0.0
    return float(stats.t.ppf(0.975, g - 1)) * math.sqrt(cov[j, j])


def _judge(side: ValveSide, y, ci, levels: int, span: float) -> tuple[bool, str]:
    """(identified, why not) of a fitted y_c [mm]."""
    lo, hi = _bounds(side, side.z0_mm, side.c_flow)
    if not _valid(side, y):
        # the fit ended where eq. (4) cannot be inverted (every residual at
        # its sentinel, a flat cost): no centre of a valve
        return False, (f"the fit ended at y_c = {y:.1f} mm, where eq. (4) is not "
                       "monotonic over the cam range")
    if levels < 2:
        return False, (f"{levels} load level(s): the threshold's dependence on the "
                       "pressures needs >= 2")
    if not all(math.isfinite(v) for v in ci) or (ci[1] - ci[0]) / 2 > 0.5 * abs(y):
        return False, (f"the fluid force spans {span:.1f} N only; y_c's 95 % interval "
                       f"{_fmt_ci(ci)} mm is too wide")
    if abs(y - lo[2]) < 1e-6 or abs(y - hi[2]) < 1e-6:
        return False, f"y_c ran into its bound ({y:.1f} mm)"
    return True, ""


def _rmse(side: ValveSide, x, g, held) -> float:
    th, p1, dp, q, dpl = (np.asarray(a, float) for a in held)
    r = q - _predict(side, x, th, p1, dp) - g * dpl
    return float(np.sqrt(np.nanmean(r ** 2))) if np.isfinite(r).any() else math.nan


def fit_geometry(side: ValveSide, theta_deg, p1_mpa, dp_mpa, q_mm3_s, sigma_mm3_s, load_level,
                 *, z0_start_mm: float, c_start: float, heldout=None, dp_leak_mpa=None,
                 leak_mm3_s_per_mpa: float = 0.0, fit_leak: bool = False) -> GeometryFit:
    """Fit (z0, C, y_c) of one side to its flow steps (eq. 3-5); see the module notes.

    ``heldout``: optional (theta, p1, dp, q[, dp_leak]) of runs kept out of
    the fit; the RMSEs reported are then on them, for this fit and for (z0,
    C) fitted with the rig file's y_c (``rmse_default_mm3_s``).
    ``dp_leak_mpa`` [MPa] per run (dp_supply - dp_drain) with the seat
    leakage's conductance ``leak_mm3_s_per_mpa`` (held, or fitted with
    ``fit_leak``); default: no leakage. Both sides at once, sharing the
    leakage: :func:`fit_geometry_sides`.
    """
    q = np.asarray(q_mm3_s, float)
    dpl = np.zeros(q.shape) if dp_leak_mpa is None else np.asarray(dp_leak_mpa, float)
    runs = SideRuns(replace(side, z0_mm=float(z0_start_mm), c_flow=float(c_start)), theta_deg,
                    p1_mpa, dp_mpa, q, sigma_mm3_s, dpl, load_level)
    if heldout is not None:
        held = list(heldout) + ([np.zeros(np.shape(heldout[3]))] if len(heldout) == 4 else [])
        runs.heldout = tuple(held)
    return _side_results({side.side: runs}, leak_mm3_s_per_mpa=leak_mm3_s_per_mpa,
                         fit_leak=fit_leak)[side.side]


def _side_results(runs: dict[str, SideRuns], *, leak_mm3_s_per_mpa: float, fit_leak: bool,
                  leak_upper_mm3_s_per_mpa: float = 15.0,
                  leak_prior_sd_mm3_s_per_mpa: float = math.inf) -> dict[str, GeometryFit]:
    """:func:`fit_geometry_sides` with y_c free where the runs span >= 2 load
    levels, judged per side (:func:`_judge`)."""
    levels = {n: np.unique(r.load_level[np.isfinite(r.load_level)]).size for n, r in runs.items()}
    free = [n for n in runs if levels[n] >= 2]
    jg = fit_geometry_sides(runs, free_y=free, leak_mm3_s_per_mpa=leak_mm3_s_per_mpa,
                            fit_leak=fit_leak, leak_upper_mm3_s_per_mpa=leak_upper_mm3_s_per_mpa,
                            leak_prior_sd_mm3_s_per_mpa=leak_prior_sd_mm3_s_per_mpa)
    out = {}
    for n, r in runs.items():
        side = r.side
        x = jg.sides[n]
        force = fluid_force_n(r.p1_mpa, r.dp_mpa, side.geometry)
        span = float(np.ptp(force)) if force.size else 0.0
        ok, note = _judge(side, x[2], jg.y_ci95[n], levels[n], span)
        # what x_c moves: in the fit whose centre is kept (y_c's, or the rig
        # file's where y_c is not identified)
        slope = (jg.x_c_slope if ok else jg.x_c_slope_default).get(n, (math.nan,) * 3)
        held = r.heldout if r.heldout is not None else \
            (r.theta_deg, r.p1_mpa, r.dp_mpa, r.q_mm3_s, r.dp_leak_mpa)
        out[n] = GeometryFit(n, x[0], x[1], x[2], jg.y_ci95[n], ok, note,
                             _rmse(side, x, jg.leak_mm3_s_per_mpa, held),
                             _rmse(side, jg.default[n], jg.leak_default_mm3_s_per_mpa, held),
                             int(r.q_mm3_s.size), int(levels[n]), span,
                             jg.leak_mm3_s_per_mpa, jg.leak_ci95, slope)
    return out


def x_c_uncertainty_mm(rig) -> float:
    """The rig file's 95 % half-range of the needle centres' x_c [mm]
    (``valve.needle_x_c_uncertainty_mm``; 0 where not given)."""
    return float(rig["valve"].get("needle_x_c_uncertainty_mm", 0.0))


def _x_c_constant(name: str, rig, g: GeometryFit, u: float) -> Constant:
    """x_c of one side: not told by the flow steps (see the module notes);
    the rig file's value stays, with what its range moves."""
    default = float(rig["valve"][name]["needle_x_c_mm"])
    dz0, _, dy = g.x_c_slope
    moves = (f"; 1 mm of the sides' x_c moves z0 by {dz0:.4f} mm" if math.isfinite(dz0)
             else "") + (f" and y_c by {dy:.3f} mm" if math.isfinite(dy) and g.identified else "")
    which = "z0's, C's and y_c's" if g.identified else "z0's and C's"
    note = ("the flow steps cannot tell it: to first order x_c moves eq. (4) by a constant, "
            "which z0 takes" + moves
            + (f"; {which} intervals carry the rig file's +-{u:g} mm "
               "(valve.needle_x_c_uncertainty_mm)" if u else ""))
    return Constant(f"valve.{name}.needle_x_c_mm", f"{name} needle centre x_c", default, default,
                    "mm", False, "flow steps (eq. 3-5)", note=note,
                    confounded_with=(f"valve.{name}.z0_mm", f"valve.{name}.needle_y_c_mm"))


def _fmt_ci(ci) -> str:
    return "[" + ", ".join("n/a" if not math.isfinite(v) else f"{v:.3g}" for v in ci) + "]"


def threshold_span(side: ValveSide, p1_mpa, dp_mpa) -> np.ndarray:
    """Sealing threshold [deg] (eq. 3+4) at each (p1, dp)."""
    return np.asarray(side.threshold_deg(np.asarray(p1_mpa, float), np.asarray(dp_mpa, float)))


def geometry_constants(per_run, model, rig, *, leak_mm3_s_per_mpa: float | None = None
                       ) -> tuple[list[Constant], dict[str, Any], list[str]]:
    """Needle centre y_c per side from flowfit's per-run table (runs used),
    both sides fitted together with the seat leakage's conductance (started
    at ``leak_mm3_s_per_mpa``, default the rig file's; the table's
    ``dp_leak_mpa``, none without it); constants, fit summary and notes."""
    consts, fits, notes = [], {}, []
    runs: dict[str, SideRuns] = {}
    meta = {}
    g0 = float(rig["valve"]["plant"]["leakage_conductance_mm3_s_per_mpa"]) \
        if leak_mm3_s_per_mpa is None else float(leak_mm3_s_per_mpa)
    for name in ("supply", "drain"):
        key = f"valve.{name}.needle_y_c_mm"
        default = float(rig["valve"][name]["needle_y_c_mm"])
        rows = per_run[(per_run["side"] == name) & per_run["used"].astype(bool)]
        if len(rows) < 8:
            why = f"{len(rows)} usable flow step(s) on this side (need >= 8)"
            consts.append(Constant(key, f"{name} needle centre y_c", default, default, "mm", False,
                                   "flow steps", note=why))
            continue
        side = model.side(name)
        rows = rows.sort_values("run_index")
        if "dp_leak_mpa" not in rows:
            rows = rows.assign(dp_leak_mpa=0.0)
        # held out: every third run in time order (all loads and angles stay in
        # both parts: the constants are static, the split tests prediction)
        pick = (np.arange(len(rows)) % 3 == 2) if len(rows) >= 12 else np.zeros(len(rows), bool)
        train, held = rows[~pick], rows[pick]
        n_held = int(pick.sum())
        cols = ["theta_deg", "p1_mpa", "dp_mpa", "q_mm3_s", "dp_leak_mpa"]
        cond = (train["cam_deg"].to_numpy(float) if "cam_deg" in train
                else train["theta_deg"].to_numpy(float))
        clusters = np.asarray([f"{lv:.4g}|{c:.3f}" for lv, c in
                               zip(train["load_level_mpag"].to_numpy(float), cond)], object)
        runs[name] = SideRuns(side, train["theta_deg"], train["p1_mpa"], train["dp_mpa"],
                              train["q_mm3_s"],
                              train["sigma_mm3_s"].fillna(1.0).clip(lower=1e-3),
                              train["dp_leak_mpa"].fillna(0.0), train["load_level_mpag"],
                              clusters,
                              tuple(held[c].fillna(0.0) if c == "dp_leak_mpa" else held[c]
                                    for c in cols) if n_held else None)
        meta[name] = (key, default, rows, train, n_held)
    if not runs:
        return consts, fits, notes
    band, p_supply = float(rig.analysis["leakage_flow_mm3_s"]), float(rig["supply"]["pressure_mpag"])
    found = _side_results(runs, leak_mm3_s_per_mpa=g0, fit_leak=True,
                          leak_upper_mm3_s_per_mpa=band / max(p_supply, 0.1),
                          leak_prior_sd_mm3_s_per_mpa=prior_sd_mm3_s_per_mpa(band, p_supply))
    u = x_c_uncertainty_mm(rig)
    for name, g in found.items():
        key, default, rows, train, n_held = meta[name]
        side = runs[name].side
        by = (f"threshold vs fluid force over {g.n_loads} load levels ({g.n_runs} flow steps, "
              f"F_w span {g.force_span_n:.1f} N)")
        dy = abs(g.x_c_slope[2]) * u if math.isfinite(g.x_c_slope[2]) else 0.0
        ci = widen_interval(g.y_c_mm, g.y_c_ci95, dy) if g.identified else (math.nan, math.nan)
        note = g.note or (f"interval with x_c's +-{u:g} mm ({dy:.2g} mm of it)" if dy else "")
        consts.append(Constant(key, f"{name} needle centre y_c", g.y_c_mm if g.identified else
                               default, default, "mm", g.identified, by, ci, note=note))
        consts.append(_x_c_constant(name, rig, g, u))
        thr_default = threshold_span(side, rows["p1_mpa"], rows["dp_mpa"])
        thr_new = threshold_span(_with(side, g.z0_mm, g.c_flow, g.y_c_mm), rows["p1_mpa"],
                                 rows["dp_mpa"]) if _valid(side, g.y_c_mm) else thr_default
        part = "heldout" if n_held else "train"
        fits[name] = {"metric": "flow-step RMSE [mm^3/s], y_c of the rig file vs identified "
                                "(z0, C refitted for each)",
                      f"{part}_default": g.rmse_default_mm3_s, part: g.rmse_mm3_s,
                      "n_train_runs": len(train), "n_heldout_runs": n_held,
                      "z0_mm": g.z0_mm, C_KEY: g.c_flow,
                      "seat_leak": {"conductance_mm3_s_per_mpa": g.leak_mm3_s_per_mpa,
                                    "ci95_mm3_s_per_mpa": list(g.leak_ci95)},
                      "x_c": {"uncertainty_mm": u,
                              "per_mm": dict(zip(("z0_mm", C_KEY, "needle_y_c_mm"),
                                                 g.x_c_slope))},
                      "threshold_range_deg": [float(np.min(thr_new)), float(np.max(thr_new))],
                      "threshold_range_default_deg": [float(np.min(thr_default)),
                                                      float(np.max(thr_default))]}
        if not g.identified:
            notes.append(f"geometry ({name}): {g.note}; y_c stays {default:g} mm")
    return consts, fits, notes
