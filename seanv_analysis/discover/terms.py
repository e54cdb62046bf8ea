"""Propose the missing term in closed form where the named effects leave a structured residual.

Eq. (5), Q = C (theta - theta_d)^2 dp^0.5 per side (theta_d of eq. 3-4),
with the needle geometry y_c freed and the named effects discover kept
(if any), may still leave a structured residual that no effect of the
vocabulary names. This module searches a library of
physically meaningful correction terms of eq. (5) (the ``term`` effect of
:mod:`seanv_analysis.models.effects`) for the one that explains it:

1. library: per side, features g_k of the run variables (dp, p1 [MPa],
   dtheta [deg], |q| [mm^3/s], load [MPaG], run, approach [-]): v, v^2,
   sqrt(v) (v >= 0), tanh(v/s) (s at quantiles of |v|), hinges
   max(v - k, 0) (knots at the 25/50/75 % quantiles), for a three-valued
   variable (approach: +-1, 0 unknown) v, max(v, 0) and min(v, 0), and
   products of two variables; each has its expression text (:mod:`seanv_analysis.models.expr`);
2. the three modes linearised around the base fit, on all runs: residual
   r ~ J_mode sum_k a_k g_k with J_mul = Q_hat, J_add = 1,
   J_threshold = dQ/dtheta_d; 'mul' and 'threshold' act on the side's own
   runs, 'add' on every run (each run's flow is what both valves pass, and
   an added flow, a leak, passes the sealed valve too, as in the
   simulator; :func:`.static.predict_static`); the base fit's own Jacobian
   (both sides' z0, C, y_c and the named effects' parameters) is always in
   the regression, so a term that is only a change of those cannot be
   proposed; weights 1/sigma (discover's noise model);
3. forward stepwise (<= :data:`MAX_TERMS` terms) per (side, mode), kept
   only where stable over bootstrap resamples of runs, the best (side,
   mode, terms) chosen by the inner chronological validation split;
4. the closed form refitted (coefficients jointly with z0, C, y_c) by
   :func:`.static.fit_static`, Wald 95 % intervals (a feature whose
   interval holds 0 is dropped and the rest refitted);
5. false-alarm control: the whole search repeated on permuted data
   (standardised residuals permuted among each side's runs; for run-dependent terms
   the run order permuted within side and load); proposed only when the
   observed fit beats the permutation distribution at p < ``alpha`` and
   the held-out RMSE (never used before) drops by >= ``min_heldout_drop``.

Everything is linear algebra on (runs x features) matrices: the search
costs well under a second.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from itertools import combinations

import numpy as np

from ..models import ValveModel, side_pressures
from ..models import effects as fx
from ..models.expr import compile_expr, evaluate, searched_variables
from .result import ProposedTerm
from .split import chrono_split, permutation_strata, permuted_run_order
from .static import EffectSpec, FlowData, StaticFit, fit_static, predict_static

__all__ = ["propose_term", "library", "side_variables", "term_spec", "MAX_TERMS"]

#: library variable -> its expression text (|q|: the flow's size, either side)
LIBRARY_VARIABLES = {"dp": "dp", "p1": "p1", "dtheta": "dtheta", "q": "abs(q)", "load": "load",
                     "run": "run", "approach": "approach"}
#: hinge knots at these quantiles of the variable
KNOT_QUANTILES = (0.25, 0.5, 0.75)
#: tanh scales at these quantiles of |variable|
SCALE_QUANTILES = (0.5, 0.9)
#: at most this many features in a proposed term
MAX_TERMS = 2
#: bootstrap resamples of runs and the share of them a feature must be chosen in
N_BOOT = 40
STABILITY = 0.6
#: features whose (projected, weighted) columns correlate this much are one choice
SAME_FEATURE = 0.95
#: share of a feature's (weighted) sum of squares that must lie outside the
#: span of the nuisance columns and the features already chosen
OWN_SHARE = 0.05
#: features whose gain is within this share of the RSS of the best count as
#: ties, and the simplest of them is taken (:func:`complexity`)
TIE = 0.03
#: step of the finite differences of the linearisation (threshold [deg], z0 [mm], y_c [mm])
STEP_DEG, STEP_Z0_MM, STEP_YC_MM = 1e-3, 1e-4, 1e-2


def _num(x: float) -> str:
    """A constant in an expression's text (4 significant digits)."""
    return f"{float(x):.4g}"


def valve_variables(model: ValveModel, data: FlowData, side: str) -> dict[str, np.ndarray]:
    """The term variables of :mod:`seanv_analysis.models.expr` of valve
    ``side`` on every run of ``data`` under ``model``: on its own runs eq. (5)
    flow q [mm^3/s] signed and dtheta the opening past eq. 3-4's threshold
    [deg]; on the other side's runs the valve is sealed (q = 0, dtheta < 0,
    its own pressures: NaN where the summary does not give them)."""
    m = data.side == side
    vs = model.side(side)
    p1, dp = side_pressures(side, data.p_supply_mpag, data.p_head_mpag, data.p_tank_mpag)
    with np.errstate(invalid="ignore"):
        d = data.theta_deg - vs.threshold_deg(p1, dp)
    q = np.where(m, predict_static(model, data), 0.0)
    return fx.term_variables(dp_mpa=dp, p1_mpa=p1, dtheta_deg=d if vs.opens_upward else -d,
                             theta_deg=data.theta_deg, q_mm3_s=q, load_mpag=data.load_mpag,
                             run_index=data.run_index, approach=data.approach)


def side_variables(model: ValveModel, data: FlowData, side: str) -> dict[str, np.ndarray]:
    """:func:`valve_variables` on ``side``'s own runs (where the library's
    knots and scales come from)."""
    m = data.side == side
    return {k: v[m] for k, v in valve_variables(model, data, side).items()}


def library(variables: dict[str, np.ndarray]) -> list[str]:
    """Feature texts of the library on one side's runs (module doc, item 1):
    only finite, non-constant ones, each once."""
    first, texts = [], []
    for v_text in dict.fromkeys([*LIBRARY_VARIABLES.values(), *searched_variables().values()]):
        v = np.asarray(evaluate(v_text, variables), float)
        if not np.all(np.isfinite(v)) or np.ptp(v) <= 1e-9 * (1.0 + np.max(np.abs(v))):
            continue
        first.append(v_text)
        texts.append(v_text)
        if np.unique(v).size <= 3:          # approach: +-1, 0 (unknown)
            # one direction against the rest: a run whose direction is
            # unknown (its log starts at the angle) may belong to either
            if v.min() < 0 < v.max():
                texts += [f"max({v_text}, 0)", f"min({v_text}, 0)"]
            continue
        texts.append(f"{v_text}**2")
        if v.min() >= 0:
            texts.append(f"sqrt({v_text})")
        for s in np.unique(np.quantile(np.abs(v), SCALE_QUANTILES)):
            if s > 0:
                texts.append(f"tanh({v_text}/{_num(s)})")
        for k in np.unique(np.quantile(v, KNOT_QUANTILES)):
            if v.min() < k < v.max():
                texts.append(f"max({v_text} - {_num(k)}, 0)" if k >= 0 else
                             f"max({v_text} + {_num(-k)}, 0)")
    texts += [f"{a}*{b}" for a, b in combinations(first, 2)]
    out, seen = [], set()
    for t in texts:
        prog = compile_expr(t)
        g = np.asarray(evaluate(prog, variables), float)
        if prog.text in seen or not np.all(np.isfinite(g)) or np.ptp(g) <= 1e-12:
            continue
        seen.add(prog.text)
        out.append(prog.text)
    return out


def complexity(text: str) -> int:
    """How complex a feature is: the steps of its compiled program (a
    variable 1, v**2 3, tanh(v/s) 4, a hinge 5)."""
    return int(compile_expr(text).code.size)


def term_spec(side: str, mode: str, features: tuple[str, ...],
              x0: tuple[float, ...] | None = None) -> EffectSpec:
    """The ``term`` effect with coefficients a1.. of ``features`` as its
    fitted parameters (expression sum_k a_k g_k; :meth:`Term.linear_expr`)."""
    n = len(features)
    return EffectSpec("term", side, tuple(f"a{k + 1}" for k in range(n)),
                      tuple(x0) if x0 is not None else (0.0,) * n,
                      (-np.inf,) * n, (np.inf,) * n, {"mode": mode, "features": tuple(features)})


@dataclass(frozen=True)
class _Side:
    """One valve side's linearised problem (weighted) on all runs of the fit
    data: residual r and nuisance columns N (both sides' z0, C, y_c and the
    kept named effects' parameters), the side's features on every run
    (``g``; the other side's runs with the valve sealed) and the mode
    Jacobians, its own runs ``rows``."""

    side: str
    rows: np.ndarray          # boolean mask of the side's own runs
    r: np.ndarray
    nuisance: np.ndarray
    features: tuple[str, ...]
    g: np.ndarray
    jac: dict[str, np.ndarray]
    run_dep: np.ndarray       # feature reads run
    variables: dict           # the valve's term variables on every run
    complexity: np.ndarray    # of each feature (:func:`complexity`)


def _nuisance(fit: StaticFit, data: FlowData, q0: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted columns d(prediction)/d(parameter) of what the base fit
    already has (``q0``: its prediction [mm^3/s]): each side's z0, C (and
    y_c where it was fitted) and every kept named effect's parameters
    (forward differences)."""
    cols = []
    for side in ("supply", "drain"):
        if not np.any(data.side == side):
            continue
        vs = fit.model.side(side)
        h_c = 1e-6 * abs(vs.c_flow)
        changes = [(fit.model.with_side(side, z0_mm=vs.z0_mm + STEP_Z0_MM), STEP_Z0_MM),
                   (fit.model.with_side(side, c_flow=vs.c_flow + h_c), h_c)]
        if side in fit.geometry:
            geom = replace(vs.geometry, needle_y_c_mm=vs.geometry.needle_y_c_mm + STEP_YC_MM)
            try:
                changes.append((fit.model.with_side(side, geometry=geom), STEP_YC_MM))
            except ValueError:
                pass
        cols += [(predict_static(moved, data, fit.effects) - q0) / h for moved, h in changes]
    for label, (spec, values) in fit.effects.items():
        for k, v in enumerate(np.asarray(values, float)):
            h = 1e-6 * max(abs(v), 1.0)
            moved = np.array(values, float)
            moved[k] = v + h
            cols.append((predict_static(fit.model, data, {**fit.effects, label: (spec, moved)})
                         - q0) / h)
    return np.column_stack(cols) * w[:, None]


def _jacobians(fit: StaticFit, data: FlowData, side: str, q0: np.ndarray,
               w: np.ndarray) -> dict[str, np.ndarray]:
    """{mode: weighted J} of ``side``'s valve on every run (``q0``: the fit's
    prediction [mm^3/s]): 'mul' its flow (0 where sealed), 'add' 1,
    'threshold' dQ/dtheta_d (0 where sealed)."""
    own = data.side == side
    shifted = term_spec(side, "threshold", ("1",))
    q_th = predict_static(fit.model, data, {**fit.effects, "t": (shifted, np.array([STEP_DEG]))})
    jac = {"mul": np.where(own, q0, 0.0), "add": np.ones_like(q0),
           "threshold": np.where(own, (q_th - q0) / STEP_DEG, 0.0)}
    return {k: v * w for k, v in jac.items()}


def _prepare(fit: StaticFit, data: FlowData, sigma: np.ndarray) -> list[_Side]:
    """Each side's linearised problem (:class:`_Side`) around ``fit`` on
    ``data`` (sides with >= 8 runs)."""
    out = []
    w = 1.0 / sigma
    q0 = predict_static(fit.model, data, fit.effects)
    r = (data.q_mm3_s - q0) * w
    nuis = None
    for side in ("supply", "drain"):
        m = data.side == side
        if m.sum() < 8:
            continue
        variables = valve_variables(fit.model, data, side)
        feats = tuple(library({k: v[m] for k, v in variables.items()}))
        if not feats:
            continue
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            g = np.column_stack([evaluate(t, variables) for t in feats]).astype(float)
        nuis = _nuisance(fit, data, q0, w) if nuis is None else nuis
        run_dep = np.array(["run" in compile_expr(t).variables for t in feats])
        out.append(_Side(side, m, r, nuis, feats, g, _jacobians(fit, data, side, q0, w),
                         run_dep, variables, np.array([complexity(t) for t in feats])))
    return out


def _orth(n: np.ndarray) -> np.ndarray:
    """Orthonormal basis of the columns of ``n``."""
    if n.size == 0:
        return np.zeros((n.shape[0], 0))
    u, s, _ = np.linalg.svd(n, full_matrices=False)
    return u[:, s > 1e-10 * s.max()] if s.size and s.max() > 0 else np.zeros((n.shape[0], 0))


def _stepwise(r: np.ndarray, nuisance: np.ndarray, x: np.ndarray, k: int,
              allowed: np.ndarray | None = None, complexity: np.ndarray | None = None
              ) -> tuple[list[int], float]:
    """Forward stepwise least squares: up to ``k`` columns of ``x`` (the
    ``allowed`` ones) with ``nuisance`` always in; (chosen, fraction of the
    residual sum of squares they remove beyond the nuisance)."""
    u = _orth(nuisance)
    r0 = r - u @ (u.T @ r)
    x0 = x - u @ (u.T @ x)
    rss0 = float(r0 @ r0)
    if rss0 <= 0:
        return [], 0.0
    chosen: list[int] = []
    scale = np.sum(x ** 2, axis=0)
    for _ in range(k):
        nx = np.sum(x0 ** 2, axis=0)
        # a feature (nearly) in the span of the nuisance and the chosen ones is
        # only a change of z0, C, y_c or of them: not a term of its own
        ok = nx > OWN_SHARE * np.maximum(scale, 1e-300)
        if allowed is not None:
            ok &= allowed
        ok[chosen] = False
        if not ok.any():
            break
        gain = np.where(ok, (x0.T @ r0) ** 2 / np.where(ok, nx, 1.0), -1.0)
        # the simplest of the features that do (nearly) as well as the best
        near = ok & (gain >= gain.max() - TIE * rss0)
        j = int(np.flatnonzero(near)[np.argmin(complexity[near])]) if complexity is not None \
            else int(np.argmax(gain))
        chosen.append(j)
        e = x0[:, j] / np.sqrt(nx[j])
        r0 = r0 - e * (e @ r0)
        x0 = x0 - np.outer(e, e @ x0)
    return chosen, 1.0 - float(r0 @ r0) / rss0


def _design(s: _Side, mode: str, g: np.ndarray | None = None) -> np.ndarray:
    """The side's weighted feature columns in ``mode``: J_mode g_k (``g``:
    the features on every run, default the side's). 'mul' and 'threshold'
    act on the side's own runs only; an 'add' feature acts on every run (a
    leak past the sealed valve) and is left out (a zero column) where it is
    not finite on some run (sqrt of a negative opening, pressures unknown)."""
    g = s.g if g is None else g
    if mode != "add":
        return s.jac[mode][:, None] * np.where(s.rows[:, None], g, 0.0)
    x = s.jac[mode][:, None] * g
    return np.where(np.all(np.isfinite(x), axis=0), x, 0.0)


def _stepwise_many(r: np.ndarray, nuisance: np.ndarray, x: np.ndarray, k: int,
                   complexity: np.ndarray) -> np.ndarray:
    """:func:`_stepwise`'s fraction of the RSS removed for each column of the
    residuals ``r`` (n x B) at once (k = 1 or 2; the same choices, ties and
    admissibility), for the permutation replicates."""
    u = _orth(nuisance)
    r0 = r - u @ (u.T @ r)
    x0 = x - u @ (u.T @ x)
    rss0 = np.sum(r0 ** 2, axis=0)
    scale = np.maximum(np.sum(x ** 2, axis=0), 1e-300)
    nx = np.sum(x0 ** 2, axis=0)
    cols = np.arange(r.shape[1])

    def pick(num, den, ok, rss):
        gain = np.where(ok, num / np.where(ok, den, 1.0), -1.0)
        near = ok & (gain >= gain.max(axis=0) - TIE * rss)
        j = np.argmin(np.where(near, complexity[:, None], np.inf), axis=0)
        return j, np.maximum(gain[j, cols], 0.0), ok.any(axis=0)

    ok1 = np.repeat((nx > OWN_SHARE * scale)[:, None], r.shape[1], axis=1)
    j1, g1, any1 = pick((x0.T @ r0) ** 2, nx[:, None], ok1, rss0)
    rss = rss0 - np.where(any1, g1, 0.0)
    if k >= 2:
        e = x0[:, j1] / np.sqrt(np.where(any1, nx[j1], 1.0))          # n x B
        r1 = r0 - e * np.sum(e * r0, axis=0)
        den = nx[:, None] - (x0.T @ e) ** 2                              # p x B
        ok2 = (den > OWN_SHARE * scale[:, None]) & any1
        ok2[j1, cols] = False
        _, g2, any2 = pick((x0.T @ r1) ** 2, den, ok2, rss0)
        rss = rss - np.where(any2, g2, 0.0)
    return np.where(rss0 > 0, 1.0 - rss / np.where(rss0 > 0, rss0, 1.0), 0.0)


def _stats(sides: list[_Side], k: int, rng: np.random.Generator | None = None,
           n: int = 1, groups: np.ndarray | None = None) -> np.ndarray:
    """Fraction of the weighted RSS that ``k`` stepwise features remove, per
    (side, mode) in the order of ``sides`` x ``TERM_MODES`` (the search's
    statistic): (1 x combos) on the data, or with ``rng`` (n x combos) on
    ``n`` replicates whose residuals are permuted among each side's runs
    (``groups``: each run's side)."""
    out = []
    r = sides[0].r[:, None] if rng is None else _permuted_within_sides(sides[0].r, groups, rng, n)
    for s in sides:
        for mode in fx.TERM_MODES:
            out.append(_stepwise_many(r, s.nuisance, _design(s, mode), k, s.complexity))
    return np.column_stack(out)


def _permuted_within_sides(r: np.ndarray, groups: np.ndarray, rng: np.random.Generator,
                           n: int) -> np.ndarray:
    """``n`` replicates (columns) of the standardised residual ``r``, each
    permuted among the runs of each valve side (``groups``); one replicate
    serves every (side, mode) search (the family-wise null of :func:`_p_value`)."""
    out = np.repeat(r[:, None], n, axis=1)
    for g in np.unique(groups):
        idx = np.flatnonzero(groups == g)
        out[idx] = np.column_stack([r[rng.permutation(idx)] for _ in range(n)])
    return out


def _stability(s: _Side, mode: str, chosen: list[int], rng: np.random.Generator) -> np.ndarray:
    """Share of bootstrap resamples of runs whose stepwise choice holds each
    of ``chosen`` (or a feature whose column correlates >= SAME_FEATURE)."""
    x = _design(s, mode)
    u = _orth(s.nuisance)
    xp = x - u @ (u.T @ x)
    norm = np.linalg.norm(xp, axis=0)
    norm[norm == 0] = 1.0
    corr = np.abs((xp / norm).T @ (xp / norm))
    n = s.r.size
    hits = np.zeros(len(chosen))
    for _ in range(N_BOOT):
        idx = rng.integers(0, n, n)
        got, _ = _stepwise(s.r[idx], s.nuisance[idx], x[idx], len(chosen),
                           complexity=s.complexity)
        for i, c in enumerate(chosen):
            hits[i] += bool(got) and corr[c, got].max() >= SAME_FEATURE
    return hits / N_BOOT


def _inner_improvement(s: _Side, mode: str, cols: list[int], inner_fit: np.ndarray) -> float:
    """Relative weighted RMSE drop on the side's inner validation runs of the
    linearised term fitted on its inner fit runs, against the nuisance-only
    refit (both from the side's base residual): how much of the side's
    error the term removes on runs it was not fitted to."""
    fit_rows, val_rows = inner_fit, ~inner_fit
    if fit_rows.sum() < 4 or not val_rows.any():
        return 0.0
    x = _design(s, mode)[:, cols]

    def val_rmse(cols_mat):
        coef, *_ = np.linalg.lstsq(cols_mat[fit_rows], s.r[fit_rows], rcond=None)
        return float(np.sqrt(np.mean((s.r[val_rows] - cols_mat[val_rows] @ coef) ** 2)))

    before = val_rmse(s.nuisance)
    after = val_rmse(np.column_stack([s.nuisance, x]))
    return 1.0 - after / before if before > 0 else 0.0


@dataclass(frozen=True)
class _Choice:
    side: str
    mode: str
    features: tuple[str, ...]
    coef: tuple[float, ...]
    inner_improvement: float
    run_dep: bool


def _search(sides: list[_Side], data: FlowData, rng) -> _Choice | None:
    """Steps 1-3 on the fit data: the best stable (side, mode, terms)."""
    inner_fit, _ = chrono_split(data.run_index, fraction=0.25, groups=data.side)
    best: _Choice | None = None
    for s in sides:
        for mode in fx.TERM_MODES:
            x = _design(s, mode)
            chosen, _ = _stepwise(s.r, s.nuisance, x, MAX_TERMS, complexity=s.complexity)
            if not chosen:
                continue
            share = _stability(s, mode, chosen, rng)
            stable = []
            for c, sh in zip(chosen, share):
                if sh < STABILITY:
                    break
                stable.append(c)
            for k in range(1, len(stable) + 1):
                cols = stable[:k]
                imp = _inner_improvement(s, mode, cols, inner_fit)
                if best is not None and imp <= best.inner_improvement:
                    continue
                design = np.column_stack([s.nuisance, x[:, cols]])
                coef, *_ = np.linalg.lstsq(design, s.r, rcond=None)
                best = _Choice(s.side, mode, tuple(s.features[c] for c in cols),
                               tuple(float(a) for a in coef[s.nuisance.shape[1]:]), imp,
                               bool(s.run_dep[cols].any()))
    return best


def _p_value(sides: list[_Side], choice: _Choice, data: FlowData, n_perm: int, rng) -> float:
    """p of the choice's statistic against the search repeated on permuted data.

    Residual permutation: each side's standardised residuals permuted among
    its runs (data that obey the base model with the same noise), the
    statistic the fraction of the RSS the k-feature stepwise fit removes, per
    (side, mode) against its own null, family-wise by the smallest p of all
    (side, mode) searches on each replicate (Westfall-Young min-p). A
    term reading the run order is also tested by permuting the run order
    within side and load (:func:`.split.permutation_strata`), the data as
    measured, the search restricted to run-dependent features; the larger
    p counts.
    """
    k = len(choice.features)
    combos = [(x.side, mode) for x in sides for mode in fx.TERM_MODES]
    observed = _stats(sides, k)[0, combos.index((choice.side, choice.mode))]
    null = _stats(sides, k, rng, n_perm, groups=data.side)
    # Westfall-Young min-p over the (side, mode) searches: each against its own
    # null (ranks), so a side whose residual is heavy-tailed does not set the
    # bar of the other
    c = combos.index((choice.side, choice.mode))
    p_obs = (1 + np.sum(null[:, c] >= observed)) / (1 + n_perm)
    p_null = ((1 + np.sum(null[None, :, :] >= null[:, None, :], axis=1)) / (1 + n_perm)).min(axis=1)
    p = float((1 + np.sum(p_null < p_obs)) / (1 + n_perm))
    if not choice.run_dep:
        return p
    strata = permutation_strata(data)
    me = next(s for s in sides if s.side == choice.side)
    fixed = [f for f in choice.features if "run" not in compile_expr(f).variables]
    n_run = k - len(fixed)
    idx_fixed = [me.features.index(f) for f in fixed]
    nuis = np.column_stack([me.nuisance, _design(me, choice.mode)[:, idx_fixed]])

    # only the run-dependent features change with the run order: compiled
    # once, evaluated per replicate into a copy of the side's features
    run_cols = np.flatnonzero(me.run_dep)
    run_progs = [compile_expr(me.features[j]) for j in run_cols]

    def stat(run_index):
        variables = {**me.variables, "run": run_index}
        g = me.g.copy()
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            for j, prog in zip(run_cols, run_progs):
                g[:, j] = evaluate(prog, variables)
        x = _design(me, choice.mode, g)
        return _stepwise(me.r, nuis, x, n_run, allowed=me.run_dep, complexity=me.complexity)[1]

    observed = stat(data.run_index)
    exceed = 0
    for _ in range(n_perm):
        exceed += stat(permuted_run_order(data.run_index, strata, rng)) >= observed
    return max(p, (1 + exceed) / (1 + n_perm))


def _refit(final: StaticFit, data: FlowData, sigma: np.ndarray, choice: _Choice
           ) -> tuple[EffectSpec, StaticFit]:
    """The chosen term refitted jointly with z0, C, y_c (step 4); a feature
    whose coefficient's 95 % interval holds 0 is dropped (the first kept
    when all do) and the rest refitted."""
    named = [sp for sp, _ in final.effects.values()]
    spec = term_spec(choice.side, choice.mode, choice.features, choice.coef)
    fitted = fit_static(final.model, data, sigma, effects=[*named, spec], geometry=final.geometry)
    if len(choice.features) == 1:
        return spec, fitted
    ci = fitted.param_ci95()
    keep = [k for k, name in enumerate(spec.params)
            if not ci[f"{spec.label}.{name}"][0] <= 0.0 <= ci[f"{spec.label}.{name}"][1]] or [0]
    if len(keep) == len(choice.features):
        return spec, fitted
    values = fitted.effects[spec.label][1]
    spec = term_spec(choice.side, choice.mode, tuple(choice.features[k] for k in keep),
                     tuple(float(values[k]) for k in keep))
    return spec, fit_static(final.model, data, sigma, effects=[*named, spec],
                            geometry=final.geometry)


def propose_term(final: StaticFit, data: FlowData, sigma: np.ndarray, *, splits, fit_mask,
                 refit_sigma=None, floor_mm3_s: float = 0.0, alpha: float = 0.01, min_heldout_drop: float = 0.10,
                 n_perm: int = 999, seed: int = 0) -> ProposedTerm | None:
    """The missing term of eq. (5) in closed form, or None (module doc).

    Parameters
    ----------
    final : the fit on the fit runs (needle geometry freed where the data
        identify it) with the named effects discover kept, if any (the
        term is searched, refitted and judged on top of them)
    data : all flow-step runs; ``fit_mask`` the fit runs (``final``'s data);
        ``splits``: the engine's (fit, held-out) masks over ``data``
    sigma : flow noise sigma of the fit runs [mm^3/s] (:func:`.engine.noise_model`)
    refit_sigma : fit mask -> sigma for the other folds' refits (k-fold)
    floor_mm3_s : smallest RMS change of the fitted flows the term must make
        [mm^3/s] (the rig's flow resolution; a smaller term is not proposed)
    alpha : level of the permutation test; ``min_heldout_drop``: relative
        held-out RMSE drop required
    """
    rng = np.random.default_rng(seed)
    fit_data = data.subset(fit_mask)
    sides = _prepare(final, fit_data, sigma)
    if not sides:
        return None
    choice = _search(sides, fit_data, rng)
    if choice is None or choice.inner_improvement <= 0:
        return None
    p = _p_value(sides, choice, fit_data, n_perm, rng)
    if p >= alpha:
        return None
    spec, fitted = _refit(final, fit_data, sigma, choice)
    # material, as a named effect must be: the term moves the prediction by
    # more than the rig's flow resolution (.engine.practical_floor_mm3_s)
    size = float(np.sqrt(np.mean((predict_static(fitted.model, fit_data, fitted.effects)
                                  - predict_static(final.model, fit_data, final.effects)) ** 2)))
    if size <= floor_mm3_s:
        return None
    named = [sp for sp, _ in final.effects.values()]
    before, after = [], []
    for f_m, h_m in splits:
        fd, hd = data.subset(f_m), data.subset(h_m)
        if f_m is fit_mask:
            b_fit, t_fit = final, fitted
        else:
            s_f = refit_sigma(f_m)
            b_fit = fit_static(final.model, fd, s_f, effects=named, geometry=final.geometry)
            t_fit = fit_static(final.model, fd, s_f, effects=[*named, spec], geometry=final.geometry)
        before.append(hd.q_mm3_s - predict_static(b_fit.model, hd, b_fit.effects))
        after.append(hd.q_mm3_s - predict_static(t_fit.model, hd, t_fit.effects))
    rmse_b = float(np.sqrt(np.mean(np.concatenate(before) ** 2)))
    rmse_a = float(np.sqrt(np.mean(np.concatenate(after) ** 2)))
    if not rmse_b > 0 or 1.0 - rmse_a / rmse_b < min_heldout_drop:
        return None
    coef = tuple(float(a) for a in fitted.effects[spec.label][1])
    ci_all = fitted.param_ci95()
    ci = tuple(ci_all[f"{spec.label}.{name}"] for name in spec.params)
    return ProposedTerm(side=choice.side, mode=choice.mode,
                        expr=fx.Term.linear_expr(coef, spec.fixed["features"]),
                        features=spec.fixed["features"], coefficients=coef, coefficients_ci95=ci,
                        p_value=p, rmse_before_mm3_s=rmse_b, rmse_after_mm3_s=rmse_a,
                        inner_improvement=choice.inner_improvement, model=fitted.model)
