"""Per-run (static) flow model of both valve sides with optional effects.

The base model is eq. (5) with the sealing threshold of eq. (3)+(4):
Q = C (theta - theta_d(p1, dp; z0))^2 dp^0.5 per side, plus the needles'
seat leakage g (dp_supply - dp_drain) (:func:`seanv_analysis.models.seat_leakage_mm3_s`;
g one parameter for both sides, with a prior as flowfit has it, carried in
the fitted model's ``extras['seat_leak_mm3_s_per_mpa']``). Each candidate effect
adds a few parameters and changes the terms of that equation through its
static form (:meth:`seanv_analysis.models.effects.Effect.apply_static` on
:class:`~seanv_analysis.models.effects.FlowTerms`), and the whole thing is
fitted jointly over both sides with ``scipy.optimize.least_squares``.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import least_squares

from ..models import ValveModel, fluid_force_n, seat_leakage_mm3_s, side_pressures
from ..models import effects as fx
from ..models.valve import SEAT_LEAK_KEY

__all__ = ["FlowData", "EffectSpec", "StaticFit", "fit_static", "predict_static", "geometry_sides",
           "plausible_geometry", "Y_C_RANGE_MM", "LEAK_KEY", "LEAK_PRIOR_KEY", "LeakPrior",
           "seat_leak_of", "leak_dp_mpa", "with_leak_prior"]

#: the seat leakage's conductance [mm^3/(s MPa)] in a fitted model's ``extras``
LEAK_KEY = SEAT_LEAK_KEY
#: its prior [mean, sd] [mm^3/(s MPa)] in a model's ``extras``: fit_static fits g with it
LEAK_PRIOR_KEY = "seat_leak_prior_mm3_s_per_mpa"


@dataclass(frozen=True)
class LeakPrior:
    """Prior of the seat leakage's conductance g ~ N(mean, sd^2) [mm^3/(s MPa)]
    (:func:`seanv_analysis.fit._leakage.prior_sd_mm3_s_per_mpa`)."""

    mean: float
    sd: float


def with_leak_prior(model: ValveModel, prior: LeakPrior) -> ValveModel:
    """``model`` whose fits (:func:`fit_static`) fit the seat leakage with ``prior``."""
    return replace(model, extras={**model.extras, LEAK_PRIOR_KEY: [float(prior.mean),
                                                                     float(prior.sd)]})


def seat_leak_of(model: ValveModel) -> float:
    """The seat leakage's conductance a model carries [mm^3/(s MPa)] (0 without)."""
    return float(model.extras.get(LEAK_KEY, 0.0)) if model.extras else 0.0


def leak_dp_mpa(data: "FlowData") -> np.ndarray:
    """dp_supply - dp_drain of each run [MPa] (0 where a pressure is unknown)."""
    dp_s = data.p_supply_mpag - data.p_head_mpag
    dp_d = data.p_head_mpag - data.p_tank_mpag
    return np.nan_to_num(dp_s - dp_d)


@dataclass(frozen=True)
class FlowData:
    """Per-run inputs of the static model (one row per run).

    side: 'supply'/'drain'; theta_deg: cam angle; p_supply/p_head/p_tank in
    MPaG; run_index: 0-based time order; approach: +1/-1/0 cam approach
    direction; q: measured flow [mm^3/s].
    """

    side: np.ndarray
    theta_deg: np.ndarray
    p_supply_mpag: np.ndarray
    p_head_mpag: np.ndarray
    p_tank_mpag: np.ndarray
    run_index: np.ndarray
    approach: np.ndarray
    q_mm3_s: np.ndarray
    #: the pneumatic load of each run [MPaG] (NaN: not logged); it names the
    #: operating condition a run-order effect may be confounded with
    load_mpag: np.ndarray | None = None

    def __post_init__(self):
        if self.load_mpag is None:
            object.__setattr__(self, "load_mpag", np.full(self.q_mm3_s.shape, np.nan))
        object.__setattr__(self, "_side_masks", {})

    def on_side(self, side: str) -> np.ndarray:
        """The runs of ``side`` ('supply'/'drain'): ``self.side == side``, made
        once per data set and side (a fit evaluates the model tens of
        thousands of times on the same runs); read-only: copy it to change it."""
        mask = self._side_masks.get(side)
        if mask is None:
            mask = np.asarray(self.side == side)
            mask.flags.writeable = False
            self._side_masks[side] = mask
        return mask

    def __len__(self) -> int:
        return int(self.q_mm3_s.size)

    def subset(self, mask: np.ndarray) -> "FlowData":
        return FlowData(*(getattr(self, f)[mask] for f in self.__dataclass_fields__))

    @classmethod
    def from_summary(cls, summary) -> "FlowData":
        """Build from a per-run summary table (``SUMMARY_COLUMNS``) of flow_step runs.

        Head and tank pressures are recovered from (p1, dp) per side:
        supply p_h = p1 - dp, p_s = p1; drain p_h = p1, p_t = p1 - dp; the
        sealed valve's side from ``dp_sealed_mpa`` when the summary has it
        (supply runs p_t = p_h - dp_sealed, drain runs p_s = p_h + dp_sealed;
        else p_t = 0 and p_s unknown, NaN).
        """
        side = summary["side"].to_numpy(dtype=object).astype(str)
        p1 = summary["p1_mpa"].to_numpy(float)
        dp = summary["dp_mpa"].to_numpy(float)
        sealed = (summary["dp_sealed_mpa"].to_numpy(float) if "dp_sealed_mpa" in summary
                  else np.full(len(summary), np.nan))
        sup = side == "supply"
        p_head = np.where(sup, p1 - dp, p1)
        p_supply = np.where(sup, p1, p_head + sealed)
        p_tank = np.where(sup, np.nan_to_num(p_head - sealed), p1 - dp)
        theta = summary["cam_measured_deg"].to_numpy(float) if "cam_measured_deg" in summary else \
            np.full(len(summary), np.nan)
        theta = np.where(np.isfinite(theta), theta, summary["cam_deg"].to_numpy(float))
        approach = (summary["cam_approach"].to_numpy(float) if "cam_approach" in summary
                    else np.zeros(len(summary)))
        load = (summary["load_mpag"].to_numpy(float) if "load_mpag" in summary
                else np.full(len(summary), np.nan))
        return cls(side, theta, p_supply, p_head, p_tank,
                   summary["run_index"].to_numpy(float), np.nan_to_num(approach),
                   summary["q_mm3_s"].to_numpy(float), load)


@dataclass(frozen=True)
class EffectSpec:
    """One candidate effect instance: name, side ('supply'/'drain'/'both'),
    continuous parameter names with start values and bounds, fixed
    parameters, and which fixed ones are grid-searched (value None until
    :meth:`~seanv_analysis.models.effects.Effect.static_search` sets them)."""

    name: str
    side: str
    params: tuple[str, ...]
    x0: tuple[float, ...]
    lower: tuple[float, ...]
    upper: tuple[float, ...]
    fixed: dict = field(default_factory=dict)
    searched: tuple[str, ...] = ()

    @classmethod
    def from_form(cls, name: str, side: str, form: fx.StaticForm) -> "EffectSpec":
        """The candidate of effect ``name`` on ``side`` with its static ``form``."""
        return cls(name, side, tuple(form.params), tuple(form.x0), tuple(form.lower),
                   tuple(form.upper), dict(form.fixed), form.searched)

    @property
    def label(self) -> str:
        return f"{self.name}[{self.side}]"

    @property
    def effect(self) -> type[fx.Effect]:
        """The registered effect class (:data:`seanv_analysis.models.effects.EFFECTS`)."""
        try:
            return fx.EFFECTS[self.name]
        except KeyError:
            raise ValueError(f"effect {self.name!r} is not registered") from None

    @property
    def needs_search(self) -> bool:
        """True while a grid-searched parameter has no value yet."""
        return any(self.fixed.get(k) is None for k in self.searched)

    def unsearched(self) -> "EffectSpec":
        """The same candidate with its grid-searched parameters cleared, so
        the next fit searches them again."""
        if not self.searched:
            return self
        return replace(self, fixed={**self.fixed, **{k: None for k in self.searched}})


def _side_mask(data: FlowData, side: str) -> np.ndarray:
    return np.ones(len(data), bool) if side == "both" else data.on_side(side)


def predict_static(model: ValveModel, data: FlowData, effects: dict[str, tuple[EffectSpec, np.ndarray]]
                   | None = None) -> np.ndarray:
    """Predicted flow per run [mm^3/s] of ``model`` with ``effects`` applied.

    ``effects`` maps a label to (spec, parameter values).
    """
    effects = effects or {}
    n = len(data)
    exponent = {s: model.side(s).dp_exponent for s in ("supply", "drain")}
    terms = fx.FlowTerms(
        theta_deg=data.theta_deg.astype(float),       # (copies: effects edit the terms)
        p_head_mpag=data.p_head_mpag.astype(float),
        z0_offset_mm=np.zeros(n),
        c_multiplier=np.ones(n),
        dp_exponent=np.where(data.on_side("supply"), exponent["supply"], exponent["drain"]),
        q_max_mm3_s=np.full(n, np.inf))
    for spec, values in effects.values():
        p = dict(zip(spec.params, values), **spec.fixed)
        known = len(terms.corrections)
        spec.effect.apply_static(terms, data, _side_mask(data, spec.side), p)
        terms.corrections[known:] = [replace(c, side=spec.side) for c in terms.corrections[known:]]
    q = np.zeros(n)
    for s in ("supply", "drain"):
        m = data.on_side(s)
        if not m.any():
            continue
        vs = model.side(s)
        p1, dp = side_pressures(s, data.p_supply_mpag[m], terms.p_head_mpag[m], data.p_tank_mpag[m])
        theta_d = vs.threshold_deg(p1, dp, z0_mm=vs.z0_mm + terms.z0_offset_mm[m])

        def flow_at(theta_d, m=m, vs=vs, dp=dp):
            d = terms.theta_deg[m] - theta_d
            opening = np.maximum(d if vs.opens_upward else -d, 0.0)
            qs = (vs.c_flow * terms.c_multiplier[m] * opening ** 2 * np.sign(dp)
                  * np.abs(dp) ** terms.dp_exponent[m])
            return fx.saturate_flow(qs, terms.q_max_mm3_s[m])

        if terms.corrections:       # closed-form terms (the ``term`` effect)
            q[m] = fx.apply_corrections(
                terms.corrections, m, flow_at=flow_at, theta_deg=terms.theta_deg[m],
                theta_d_deg=theta_d, p1_mpa=p1, dp_mpa=dp, opens_upward=vs.opens_upward,
                load_mpag=data.load_mpag[m], run_index=data.run_index[m],
                approach=data.approach[m])
        else:
            q[m] = flow_at(theta_d)
    if any(c.mode == "add" for c in terms.corrections):
        q += _sealed_valve_flow(model, data, terms)
    g = seat_leak_of(model)
    if g:
        q = q + seat_leakage_mm3_s(leak_dp_mpa(data), 0.0, conductance_mm3_s_per_mpa=g)
    return q


def _sealed_valve_flow(model: ValveModel, data: FlowData, terms: fx.FlowTerms) -> np.ndarray:
    """Each run's flow through the valve of the other side, sealed in the run
    [mm^3/s]: only its 'add' terms (:func:`~seanv_analysis.models.effects.sealed_valve_terms`);
    0 where that valve's pressures are unknown (a summary without ``dp_sealed_mpa``)."""
    q = np.zeros(len(data))
    for s, other in (("supply", "drain"), ("drain", "supply")):
        m = data.side == other
        if not m.any() or not any(c.mode == "add" and c.side == s for c in terms.corrections):
            continue
        vs = model.side(s)
        p1, dp = side_pressures(s, data.p_supply_mpag, terms.p_head_mpag, data.p_tank_mpag)
        m &= np.isfinite(p1) & np.isfinite(dp)
        p1, dp = p1[m], dp[m]
        q[m] = fx.sealed_valve_terms(
            terms.corrections, side=s, theta_deg=terms.theta_deg[m],
            theta_d_deg=vs.threshold_deg(p1, dp), p1_mpa=p1, dp_mpa=dp,
            opens_upward=vs.opens_upward, load_mpag=data.load_mpag[m],
            run_index=data.run_index[m], approach=data.approach[m])
    return q


@dataclass
class StaticFit:
    """Result of a joint fit: the valve model, effect parameter values, the
    weighted residuals (measured - model) / sigma, and the cost."""

    model: ValveModel
    effects: dict[str, tuple[EffectSpec, np.ndarray]]
    residual: np.ndarray
    weighted_residual: np.ndarray
    rss_weighted: float
    n_params: int
    success: bool
    message: str
    covariance: np.ndarray | None = None
    param_names: tuple[str, ...] = ()
    geometry: tuple[str, ...] = ()          # sides whose needle centre y_c was fitted

    def param_ci95(self) -> dict[str, tuple[float, float]]:
        """Wald 95 % intervals from the scaled Jacobian covariance (NaN if singular)."""
        out = {}
        values = self._values()
        for i, name in enumerate(self.param_names):
            if self.covariance is None or not np.isfinite(self.covariance[i, i]):
                out[name] = (float("nan"), float("nan"))
            else:
                half = 1.96 * float(np.sqrt(max(self.covariance[i, i], 0.0)))
                out[name] = (values[i] - half, values[i] + half)
        return out

    def _values(self) -> list[float]:
        base = {}
        for s in ("supply", "drain"):
            side = self.model.side(s)
            base.update({f"{s}.z0_mm": side.z0_mm, f"{s}.C": side.c_flow,
                         f"{s}.y_c_mm": side.geometry.needle_y_c_mm})
        base["seat_leak.g"] = seat_leak_of(self.model)
        vals = [float(base[n]) for n in self.param_names if n in base]
        for _spec, v in self.effects.values():
            vals.extend(float(x) for x in v)
        return vals


#: the range of |y_c| [mm] the needle centre is searched in, on the side of
#: the cam axis the rig file puts it: from 4 mm (below it eq. (4) turns over
#: inside the cam range for any x_c of the paper's scale) to 80 mm (4 x the
#: head radius r of Table II: a centre that far from the cam axis is no
#: valve of the paper's dimensions). A fit that ends at either edge has not
#: found a centre: the residual it absorbs is an effect's (:func:`plausible_geometry`).
Y_C_RANGE_MM = (4.0, 80.0)


def plausible_geometry(fit: "StaticFit", *, tol_mm: float = 0.05) -> tuple[str, ...]:
    """The sides of ``fit.geometry`` whose fitted needle centre is a centre:
    inside :data:`Y_C_RANGE_MM` (not within ``tol_mm`` of an edge) with eq. (4)
    invertible over the cam range."""
    out = []
    for s in fit.geometry:
        geom = fit.model.side(s).geometry
        y = abs(float(geom.needle_y_c_mm))
        if not Y_C_RANGE_MM[0] + tol_mm < y < Y_C_RANGE_MM[1] - tol_mm:
            continue
        try:
            z, _ = geom.height_table
        except ValueError:
            continue
        if z.size:
            out.append(s)
    return tuple(out)


def geometry_sides(model: ValveModel, data: FlowData, *, min_force_span_n: float = 1.5
                   ) -> tuple[str, ...]:
    """Sides whose runs span enough fluid force (eq. 1, > ``min_force_span_n``
    [N]) for the threshold's pressure dependence, i.e. the needle centre y_c
    of eq. (4), to be fitted with z0 and C (the unpublished geometry is part
    of the base model, so it cannot pass for an effect)."""
    out = []
    for s in ("supply", "drain"):
        m = data.on_side(s)
        if m.sum() < 8:
            continue
        p1, dp = side_pressures(s, data.p_supply_mpag[m], data.p_head_mpag[m], data.p_tank_mpag[m])
        f = fluid_force_n(p1, dp, model.side(s).geometry)
        f = f[np.isfinite(f)]
        if f.size and float(np.ptp(f)) > min_force_span_n:
            out.append(s)
    return tuple(out)


def fit_static(model: ValveModel, data: FlowData, sigma: np.ndarray, *,
               effects: list[EffectSpec] = (), loss: str = "soft_l1",
               fit_sides: tuple[str, ...] = ("supply", "drain"),
               geometry: tuple[str, ...] = (), leak: LeakPrior | None = None) -> StaticFit:
    """Fit z0 and C of both sides (and the effects' parameters) to ``data``;
    with them the needle centre y_c (eq. 4) of the ``geometry`` sides (the
    rig's unpublished geometry; :func:`geometry_sides` tells which sides the
    data can say it for) and, with ``leak`` (default: the prior the model
    carries, ``extras[LEAK_PRIOR_KEY]``, :func:`with_leak_prior`), the seat
    leakage's conductance g (one more residual (g - mean) / sd; g >= 0; the
    fitted model carries it, ``extras[LEAK_KEY]``; without a prior the
    model's own g stays).

    Residuals are weighted by ``sigma`` (flow noise model [mm^3/s]); the loss
    is robust (``soft_l1`` with f_scale = 2, i.e. residuals beyond ~2 sigma
    count less) so a few bad runs cannot drag C.
    """
    present = [s for s in fit_sides if data.on_side(s).any()]
    geometry = tuple(geometry)
    with_geom = [s for s in present if s in geometry]
    names = []
    x0, lo, hi = [], [], []
    for s in present:
        vs = model.side(s)
        c_abs = max(abs(vs.c_flow), 1.0)
        names += [f"{s}.z0_mm", f"{s}.C"]
        x0 += [vs.z0_mm, vs.c_flow]
        lo += [vs.z0_mm - 1.0, -50 * c_abs if vs.c_flow < 0 else 0.0]
        hi += [vs.z0_mm + 1.0, 0.0 if vs.c_flow < 0 else 50 * c_abs]
        if s in with_geom:
            y = vs.geometry.needle_y_c_mm
            names.append(f"{s}.y_c_mm")
            x0.append(y)
            lo.append(-Y_C_RANGE_MM[1] if y < 0 else Y_C_RANGE_MM[0])
            hi.append(-Y_C_RANGE_MM[0] if y < 0 else Y_C_RANGE_MM[1])
    if leak is None and model.extras and LEAK_PRIOR_KEY in model.extras:
        leak = LeakPrior(*(float(v) for v in model.extras[LEAK_PRIOR_KEY]))
    fit_leak = leak is not None and len(data) > 0 and bool(np.ptp(leak_dp_mpa(data)) >= 0.2)
    if fit_leak:
        names.append("seat_leak.g")
        x0.append(seat_leak_of(model) or leak.mean)
        lo.append(0.0)
        hi.append(max(leak.mean + 5.0 * leak.sd, 1e-9))
    for spec in effects:
        names += [f"{spec.label}.{p}" for p in spec.params]
        x0 += list(spec.x0)
        lo += list(spec.lower)
        hi += list(spec.upper)
    x0 = np.clip(np.array(x0, float), np.array(lo) + 1e-12, np.array(hi) - 1e-12)

    def unpack(x):
        sides = {}
        k = 0
        for s in present:
            change = {"z0_mm": float(x[k]), "c_flow": float(x[k + 1])}
            k += 2
            if s in with_geom:
                change["geometry"] = replace(model.side(s).geometry, needle_y_c_mm=float(x[k]))
                k += 1
            sides[s] = replace(model.side(s), **change)
        if fit_leak:
            sides["extras"] = {**model.extras, LEAK_KEY: float(x[k])}
            k += 1
        m = replace(model, **sides)      # one copy per call (the residual is called often)
        eff = {}
        for spec in effects:
            npar = len(spec.params)
            eff[spec.label] = (spec, np.asarray(x[k:k + npar], float))
            k += npar
        return m, eff

    far_off = []

    def resid(x):
        m, eff = unpack(x)
        try:
            return (data.q_mm3_s - predict_static(m, data, eff)) / sigma
        except ValueError:      # eq. (4) not monotonic for this y_c: far off
            far_off.append(True)
            return np.full(len(data), 1e3)

    objective = resid
    structure = _jacobian_structure(data, present, with_geom, effects, fit_leak)
    known = {}
    if fit_leak:       # the prior: one more residual, moved by g alone
        k_g = names.index("seat_leak.g")

        def objective(x):
            return np.append(resid(x), (x[k_g] - leak.mean) / leak.sd)

        if structure is not None:
            prior_row = np.zeros((1, structure.shape[1]), bool)
            prior_row[0, k_g] = True
            structure = np.vstack([structure, prior_row])
            # the flow is linear in g: its column is known, no evaluation for it
            known[k_g] = np.append(-leak_dp_mpa(data) / sigma, 1.0 / leak.sd)
    fun, jac = _grouped_jacobian(objective, structure, (lo, hi), far_off, known=known)
    sol = least_squares(fun, x0, jac=jac, bounds=(lo, hi), loss=loss, f_scale=2.0,
                        x_scale="jac", max_nfev=400)
    m, eff = unpack(sol.x)
    wr = resid(sol.x)
    cov = None
    try:
        jac = sol.jac
        dof = max(len(data) - len(sol.x), 1)
        s2 = float(np.sum(wr ** 2)) / dof
        cov = np.linalg.inv(jac.T @ jac) * s2
        if not np.all(np.isfinite(cov)):
            cov = None
    except np.linalg.LinAlgError:
        cov = None
    return StaticFit(m, eff, wr * sigma, wr, float(np.sum(wr ** 2)), len(sol.x),
                     bool(sol.success), str(sol.message), cov, tuple(names), tuple(with_geom))


def _jacobian_structure(data: FlowData, present: list[str], with_geom: list[str],
                        effects, leak: bool = False) -> np.ndarray | None:
    """Which runs each fitted parameter moves (runs x parameters, bool), where
    the model's form says so: a side's z0, C and y_c and a one-sided effect's
    parameters move that side's runs only (the effects' static forms change
    their ``rows`` only), the seat leakage every run. None when every
    parameter may move every run: with a closed-form term (an 'add' term
    moves the other side's sealed valve)."""
    if any(spec.effect.name == "term" for spec in effects):
        return None
    cols = []
    for s in present:
        rows = data.on_side(s)
        cols += [rows] * (3 if s in with_geom else 2)
    if leak:
        cols.append(np.ones(len(data), bool))
    for spec in effects:
        cols += [np.asarray(_side_mask(data, spec.side))] * len(spec.params)
    return np.column_stack(cols)


def _forward_steps(x: np.ndarray, bounds) -> np.ndarray:
    """The forward-difference steps of ``least_squares(jac='2-point')``
    (scipy's rule, written out here: scipy keeps it private): sqrt(eps) x
    max(1, |x|), positive at x = 0, turned backward where the forward step
    would leave the bounds and the backward one fits, shortened to the
    farther bound where neither fits."""
    lb, ub = (np.resize(np.asarray(b, dtype=float), x.shape) for b in bounds)
    sign = (x >= 0).astype(float) * 2 - 1
    h = np.finfo(np.float64).eps ** 0.5 * sign * np.maximum(1.0, np.abs(x))
    if np.all((lb == -np.inf) & (ub == np.inf)):
        return h
    lower, upper = x - lb, ub - x
    out = h.copy()
    ahead = x + h
    fitting = np.abs(h) <= np.maximum(lower, upper)
    out[((ahead < lb) | (ahead > ub)) & fitting] *= -1
    forward = (upper >= lower) & ~fitting
    out[forward] = upper[forward]
    backward = (upper < lower) & ~fitting
    out[backward] = -lower[backward]
    return out


def _column_groups(structure: np.ndarray) -> list[np.ndarray]:
    """Columns that touch disjoint rows, grouped greedily in column order
    (each joins the first group it shares no row with)."""
    groups: list[list[int]] = []
    rows: list[np.ndarray] = []
    for j in range(structure.shape[1]):
        for g, used in enumerate(rows):
            if not np.any(used & structure[:, j]):
                groups[g].append(j)
                rows[g] = used | structure[:, j]
                break
        else:
            groups.append([j])
            rows.append(structure[:, j].copy())
    return [np.asarray(g) for g in groups]


def _dense_forward(fun, x: np.ndarray, f0: np.ndarray, h: np.ndarray) -> np.ndarray:
    """The forward-difference Jacobian column by column, as ``'2-point'``
    makes it (each column from x with that parameter stepped)."""
    jt = np.empty((x.size, f0.size))
    for j in range(x.size):
        x1 = np.copy(x)
        x1[j] = x[j] + h[j]
        jt[j] = (fun(x1) - f0) / ((x[j] + h[j]) - x[j])
    return jt.T


def _grouped_jacobian(resid, structure: np.ndarray | None, bounds, far_off: list, *,
                      known: dict[int, np.ndarray] | None = None):
    """(residual, jac) for ``least_squares``: the forward-difference Jacobian
    that ``jac='2-point'`` makes (the same steps, bounds handling, quotients
    and memory layout), with parameters that move disjoint runs perturbed in
    one evaluation: a fit of both sides costs
    about half the evaluations, for the same matrix bit for bit. ``known``
    {column: values}: columns of parameters the residual is linear in (the
    seat leakage's g), given, not differenced. A step that lands where eq.
    (4) fails (``far_off``: the residual is the sentinel) is redone column
    by column, as the dense difference does it. Without a ``structure``, or
    nothing to group: ``(resid, '2-point')``."""
    known = known or {}
    if structure is None:
        return resid, "2-point"
    free = np.array([j for j in range(structure.shape[1]) if j not in known], int)
    members = [free[g] for g in _column_groups(np.asarray(structure, bool)[:, free])]
    if len(members) == structure.shape[1]:
        return resid, "2-point"
    last: dict[str, np.ndarray] = {}

    def fun(x):
        f = resid(x)
        last["x"], last["f"] = np.array(x, copy=True), f.copy()  # least_squares scales f in place
        return f

    def jac(x):
        x = np.asarray(x, dtype=float)
        f0 = last["f"] if "x" in last and np.array_equal(last["x"], x) else fun(x).copy()
        h = _forward_steps(x, bounds)
        del far_off[:]
        jt = np.empty((x.size, f0.size))
        for cols in members:
            x1 = x.copy()
            x1[cols] = x[cols] + h[cols]
            df = fun(x1) - f0
            for j in cols:   # runs a column does not move: exactly 0 in the dense difference too
                jt[j] = np.where(structure[:, j], df, 0.0) / ((x[j] + h[j]) - x[j])
        for j, col in known.items():
            jt[j] = col
        if far_off:
            return _dense_forward(fun, x, f0, h)
        return jt.T

    return fun, jac
