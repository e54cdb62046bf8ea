"""Close the loop on flow-step data: residual -> missing effect -> refit.

Procedure:

1. chronological split of runs into fit / held-out, per valve side (the
   last ``fraction`` of each side's runs; never used for fitting or
   selection);
2. base fit of eq. (5) on the fit set (both sides, robust loss, weights
   from a flow-noise model sigma = a + b |Q|);
3. residual diagnostics on the fit set against run order, dp, opening,
   load, cam approach direction, flow; Ljung-Box whiteness in run order;
4. forward selection over the candidate effects (every registered effect
   with a static form, :mod:`seanv_analysis.models.effects`, that the data
   can identify; :func:`.candidates.candidate_specs`). A candidate is kept only when
   (a) its F-test against the current model has p < alpha / m (m candidates),
   (b) it lowers the error on an inner chronological validation split of
   the fit set by at least ``min_improvement``, and (c) a residual
   permutation check (refits on data resampled under the current model)
   gives p < ``alpha_perm``;
5. closed-form term search (:mod:`.terms`) on what the kept effects (if
   any) leave: a proposed term, never a named effect;
6. verdict: ``effect_found``; ``unexplained`` when nothing is kept but the
   residual still trends with a variable or a term is proposed; ``none``
   otherwise;
7. held-out RMSE before (base) and after (base + selected effects).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import pandas as pd
from scipy import special

from ..errors import FitError
from ..models import ValveModel, side_pressures
from .candidates import candidate_specs, fit_candidate
from .diagnostics import ljung_box, robust_scale, trend_tests
from .result import Discovery, EffectFinding
from .split import (  # noqa: F401 (permutation_strata re-exported)
    chrono_split,
    kfold_splits,
    permutation_strata,
    permuted_run_order,
)
from .static import (
    FlowData,
    LeakPrior,
    StaticFit,
    fit_static,
    geometry_sides,
    plausible_geometry,
    predict_static,
    seat_leak_of,
    with_leak_prior,
)
from .terms import propose_term

__all__ = ["discover_flow_steps", "noise_model", "residual_variables", "trend_amplitude",
           "practical_floor_mm3_s"]


def noise_model(q_hat: np.ndarray, residual: np.ndarray, *, floor_mm3_s: float = 10.0) -> np.ndarray:
    """Flow noise sigma_i = a + b |Q_i| [mm^3/s] fitted to |residual| (robust).

    Flow-step noise grows with flow (pump ripple, friction), so equal
    weights would let the largest flows decide everything.
    """
    x = np.abs(np.asarray(q_hat, float))
    y = np.abs(np.asarray(residual, float))
    ok = np.isfinite(x) & np.isfinite(y)
    if ok.sum() < 6:
        return np.full(x.shape, max(robust_scale(residual), floor_mm3_s))
    # median regression of |r| on |Q| via iteratively reweighted least squares
    a, b = float(np.median(y[ok])), 0.0
    for _ in range(30):
        r = y[ok] - (a + b * x[ok])
        w = 1.0 / np.maximum(np.abs(r), 1e-6 * (1 + np.median(y[ok])))
        A = np.column_stack([np.ones(ok.sum()), x[ok]]) * np.sqrt(w)[:, None]
        coef, *_ = np.linalg.lstsq(A, y[ok] * np.sqrt(w), rcond=None)
        a, b = float(coef[0]), float(max(coef[1], 0.0))
    sigma = 1.4826 * (np.maximum(a, 0.0) + b * x)
    return np.maximum(sigma, floor_mm3_s)


def _leak_prior(model: ValveModel, data: FlowData, leakage_mm3_s: float) -> LeakPrior:
    """The seat leakage's prior: mean the model's g (flowfit's fitted one) or
    0, sd from the leakage band at the runs' median supply pressure
    (:func:`seanv_analysis.fit._leakage.prior_sd_mm3_s_per_mpa`)."""
    from ..fit import prior_sd_mm3_s_per_mpa

    ps = data.p_supply_mpag[np.isfinite(data.p_supply_mpag)]
    if not ps.size:     # no supply pressure logged: the highest head pressure seen
        ps = data.p_head_mpag[np.isfinite(data.p_head_mpag)]
    p_supply = float(np.median(ps) if ps.size and np.isfinite(data.p_supply_mpag).any()
                     else np.max(ps) if ps.size else 1.0)
    return LeakPrior(seat_leak_of(model), prior_sd_mm3_s_per_mpa(leakage_mm3_s, p_supply))


#: the leakage is fitted when the runs alone tell g to better than this
#: fraction of its prior's standard deviation
LEAK_TOLD_FRACTION = 0.5


def _with_leakage(model: ValveModel, data: FlowData, leakage_mm3_s: float) -> ValveModel:
    """``model`` with the seat leakage's prior (:func:`with_leak_prior`)
    when the runs ``data`` alone (a flat prior) give g a standard error below
    :data:`LEAK_TOLD_FRACTION` of the prior's; else ``model`` (g stays what
    it carries, 0 without). Measured: the simulator's 345 flow steps 0.19
    mm^3/(s MPa) (prior 3.3): fitted; 48 foreign-rig steps with the rig
    file's needle centres unlike the rig's 12.9: not (the leakage took the
    geometry's mismatch, g = 63, and the centre then failed its test)."""
    prior = _leak_prior(model, data, leakage_mm3_s)
    probe = fit_static(with_leak_prior(model, LeakPrior(prior.mean, 1e6)), data,
                       np.full(len(data), max(robust_scale(data.q_mm3_s), 1.0)))
    if "seat_leak.g" not in probe.param_names or probe.covariance is None:
        return model
    k = list(probe.param_names).index("seat_leak.g")
    se = float(np.sqrt(max(probe.covariance[k, k], 0.0)))
    return with_leak_prior(model, prior) if se < LEAK_TOLD_FRACTION * prior.sd else model


def _fit_base(model: ValveModel, data: FlowData) -> tuple[StaticFit, np.ndarray]:
    """Two-pass base fit: unweighted-robust, then with the fitted noise model."""
    first = fit_static(model, data, np.full(len(data), max(robust_scale(data.q_mm3_s), 1.0)))
    q_hat = predict_static(first.model, data)
    sigma = noise_model(q_hat, data.q_mm3_s - q_hat)
    return fit_static(first.model, data, sigma), sigma


def _f_test(rss0: float, p0: int, rss1: float, p1: int, n: int) -> tuple[float, float]:
    df1, df2 = max(p1 - p0, 1), max(n - p1, 1)
    if rss1 <= 0:
        return np.inf, 0.0
    f = ((rss0 - rss1) / df1) / (rss1 / df2)
    return float(f), float(special.fdtrc(df1, df2, f)) if f > 0 else 1.0   # F survival


def _rmse(x: np.ndarray) -> float:
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x ** 2))) if x.size else float("nan")


def _opening(model: ValveModel, data: FlowData) -> np.ndarray:
    out = np.full(len(data), np.nan)
    for s in ("supply", "drain"):
        m = data.side == s
        if m.any():
            p1, dp = side_pressures(s, data.p_supply_mpag[m], data.p_head_mpag[m], data.p_tank_mpag[m])
            d = data.theta_deg[m] - model.side(s).threshold_deg(p1, dp)
            out[m] = d if model.side(s).opens_upward else -d
    return out


def residual_variables(model: ValveModel, data: FlowData,
                       summary: pd.DataFrame | None = None) -> dict[str, np.ndarray]:
    """The variables discovery tests the flow residual against, per run:
    run_index (time order) [-], dp_mpa [MPa], opening_deg (cam angle past the
    threshold theta_d of eq. 3+4 under ``model``) [deg], cam_approach [-],
    q_mm3_s (|Q|) [mm^3/s], and load_mpag [MPaG] when ``summary`` (the rows
    of ``data``) has it."""
    summary = pd.DataFrame() if summary is None else summary
    dp = np.where(data.side == "supply", data.p_supply_mpag - data.p_head_mpag,
                  data.p_head_mpag - data.p_tank_mpag)
    v = {"run_index": data.run_index, "dp_mpa": dp, "opening_deg": _opening(model, data),
         "cam_approach": data.approach, "q_mm3_s": np.abs(data.q_mm3_s)}
    if "load_mpag" in summary:
        v["load_mpag"] = summary["load_mpag"].to_numpy(float)
    return v


def trend_amplitude(residual: np.ndarray, variable: np.ndarray, *, bins: int = 8) -> float:
    """Size of a residual trend [mm^3/s]: RMS over quantile bins of the
    variable of the bin medians of the residual (count-weighted)."""
    ok = np.isfinite(residual) & np.isfinite(variable)
    r, v = residual[ok], variable[ok]
    if r.size < 2 * bins:
        return 0.0
    edges = np.unique(np.quantile(v, np.linspace(0, 1, bins + 1)))
    if edges.size < 2:
        return 0.0
    which = np.clip(np.searchsorted(edges, v, side="right") - 1, 0, edges.size - 2)
    meds, counts = [], []
    for b in range(edges.size - 1):
        m = which == b
        if m.any():
            meds.append(np.median(r[m]))
            counts.append(m.sum())
    meds, counts = np.asarray(meds), np.asarray(counts)
    centre = np.median(r)
    return float(np.sqrt(np.sum(counts * (meds - centre) ** 2) / counts.sum()))


def practical_size(change_mm3_s: np.ndarray) -> float:
    """How much an effect moves the prediction where it acts [mm^3/s]: the
    90th percentile of |change| over the runs. Not the RMS over all runs: a
    drift is zero until its first step, and small at small openings, so an
    RMS would average a material change away."""
    change = np.abs(np.asarray(change_mm3_s, float))
    change = change[np.isfinite(change)]
    return float(np.percentile(change, 90)) if change.size else 0.0


def practical_floor_mm3_s(data: FlowData, leakage_mm3_s: float = 50.0) -> float:
    """Smallest residual trend that matters [mm^3/s]: max(leakage, 2 % of median |Q|)."""
    return max(float(leakage_mm3_s), 0.02 * float(np.median(np.abs(data.q_mm3_s))))


def discover_flow_steps(summary: pd.DataFrame, *, model: ValveModel, holdout: str = "chrono",
                        fraction: float = 0.3, alpha: float = 0.01, alpha_perm: float = 0.05,
                        min_improvement: float = 0.10, n_perm: int = 39, max_effects: int = 3,
                        leakage_mm3_s: float = 50.0, seed: int = 0) -> Discovery:
    """Find effects missing from eq. (5) in a per-run flow-step summary.

    Parameters
    ----------
    summary : per-run summary (``SUMMARY_COLUMNS``); excluded runs are dropped.
    model : starting valve model (geometry + initial z0, C).
    holdout : 'chrono' (last ``fraction`` of runs held out) or 'kfold'
        (held-out numbers pooled over 5 folds by run; selection on the first
        fold's fit set).
    leakage_mm3_s : the rig's flow resolution (the leakage filter's
        threshold, rig ``analysis.leakage_flow_mm3_s``): a residual trend
        smaller than max(this, 2 % of the median |Q|) is not "structured".
    alpha : family-wise level of the F-test screen; ``alpha_perm`` of the
        permutation check; ``min_improvement``: relative error drop required
        on the inner validation split ("materially").
    """
    df = summary[(summary["kind"] == "flow_step") & (summary["excluded"].fillna("") == "")]
    df = df[np.isfinite(df["q_mm3_s"]) & np.isfinite(df["dp_mpa"])].sort_values("run_index")
    if len(df) < 12:
        raise FitError(f"discover: {len(df)} usable flow_step runs, need >= 12")
    data = FlowData.from_summary(df)
    if holdout == "chrono":
        fit_m, held_m = chrono_split(data.run_index, fraction=fraction, groups=data.side)
        splits = [(fit_m, held_m)]
    elif holdout == "kfold":
        splits = list(kfold_splits(data.run_index, k=5, seed=seed))
    else:
        raise ValueError(f"holdout: expected 'chrono' or 'kfold', got {holdout!r}")

    fit_m, held_m = splits[0]
    fit_data = data.subset(fit_m)
    # the needles' seat leakage is part of the base model where the runs tell
    # it (it moves with the head pressure from load to load, as the threshold
    # does: left out, it passed for a needle geometry unlike the rig file's on
    # our own clean simulated data); its conductance g, one for both needles,
    # is then fitted in every fit, with the prior flowfit has (mean: the
    # model's g if it carries one, flowfit's, else 0)
    model = _with_leakage(model, fit_data, leakage_mm3_s)
    floor = practical_floor_mm3_s(fit_data, leakage_mm3_s)
    selection = _select(model, fit_data, df[fit_m], alpha=alpha, alpha_perm=alpha_perm,
                        min_improvement=min_improvement, n_perm=n_perm,
                        max_effects=max_effects, seed=seed, floor_mm3_s=floor)
    base, final, findings, trends, lb, sigma = selection

    # what the named effects (if any) leave may still hold a closed-form term (.terms)
    proposed = propose_term(final, data, sigma, splits=splits, fit_mask=fit_m,
                            refit_sigma=lambda m: _fit_base(model, data.subset(m))[1],
                            floor_mm3_s=floor, seed=seed)

    # Held-out error, before and after, with fits on the fit part only.
    before, after, n_held = [], [], 0
    for f_m, h_m in splits:
        fd, hd = data.subset(f_m), data.subset(h_m)
        b_fit = base if f_m is fit_m else _fit_base(model, fd)[0]
        specs = [spec for spec, _ in final.effects.values()]
        a_fit = final if f_m is fit_m else fit_static(b_fit.model, fd, _fit_base(model, fd)[1],
                                                      effects=specs, geometry=final.geometry)
        before.append(hd.q_mm3_s - predict_static(b_fit.model, hd))
        after.append(hd.q_mm3_s - predict_static(a_fit.model, hd, a_fit.effects))
        n_held += int(np.unique(hd.run_index).size)
    rmse_before = _rmse(np.concatenate(before))
    rmse_after = _rmse(np.concatenate(after))

    if findings:
        verdict, trend_var = "effect_found", None
    else:
        # Structured = statistically clear (Spearman p, Ljung-Box) AND
        # material: the trend's size in mm^3/s beats the rig's flow
        # resolution, so tiny systematic terms (leakage) on very clean data
        # are not called "unexplained".
        if final.geometry:      # the base model with the rig's needle geometry identified
            trends = trend_tests(final.weighted_residual,
                                 residual_variables(final.model, fit_data, df[fit_m]))
            order = np.argsort(fit_data.run_index, kind="stable")
            lb = ljung_box(final.weighted_residual[order])
        raw = fit_data.q_mm3_s - predict_static(final.model, fit_data)
        variables = residual_variables(final.model, fit_data, df[fit_m])
        alpha_trend = 1e-3 / max(len(trends), 1)
        structured = [t for t in trends if t.p_value < alpha_trend and abs(t.rho) > 0.2
                      and trend_amplitude(raw, variables[t.variable]) > floor]
        # run order: bins of ~4 consecutive runs, so a trend that comes and
        # goes (temperature, a periodic wear pattern) is not averaged away
        fine = max(8, len(raw) // 4)
        drifting = lb[1] < 1e-4 and trend_amplitude(raw, fit_data.run_index, bins=fine) > floor
        if structured or drifting:
            verdict = "unexplained"
            trend_var = structured[0].variable if structured else "run_index"
        else:
            verdict, trend_var = "none", None
        # nothing named: a proposal of the closed-form term search makes the
        # residual 'unexplained' (never a known effect)
        if proposed is not None and verdict == "none":
            verdict, trend_var = "unexplained", proposed.trend_variable
    ci = final.param_ci95() if final.geometry else {}
    geometry = {s: {"needle_y_c_mm": float(final.model.side(s).geometry.needle_y_c_mm),
                    "ci95_mm": [float(v) if math.isfinite(v) else None
                                for v in ci.get(f"{s}.y_c_mm", (math.nan, math.nan))],
                    "rig_file_mm": float(model.side(s).geometry.needle_y_c_mm)}
                for s in final.geometry} or None
    return Discovery(verdict=verdict, effects=findings, n_heldout_runs=n_held, geometry=geometry,
                     rmse_before_mm3_s=rmse_before, rmse_after_mm3_s=rmse_after,
                     trend_variable=trend_var, base_model=base.model, model=final.model,
                     heldout_data=data.subset(held_m), fit_data=fit_data,
                     base_fit=base, final_fit=final, holdout=holdout, proposed_term=proposed)


def _select(model, data: FlowData, summary_fit, *, alpha, alpha_perm, min_improvement, n_perm,
            max_effects, seed, floor_mm3_s=0.0):
    base, sigma = _fit_base(model, data)
    trends = trend_tests(base.weighted_residual, residual_variables(base.model, data, summary_fit))
    order = np.argsort(data.run_index, kind="stable")
    lb = ljung_box(base.weighted_residual[order])

    inner_fit, inner_val = chrono_split(data.run_index, fraction=0.25, groups=data.side)
    d_in, d_val = data.subset(inner_fit), data.subset(inner_val)
    s_in, s_val = sigma[inner_fit], sigma[inner_val]
    rng = np.random.default_rng(seed)

    current = base
    selected = []
    findings: list[EffectFinding] = []
    geom_sides = geometry_sides(base.model, data)
    while len(selected) < max_effects:
        specs = [s for s in candidate_specs(data, base)
                 if (s.name, s.side) not in {(x.name, x.side) for x in selected}]
        if not specs:
            break
        cur_in = fit_static(current.model, d_in, s_in, effects=selected, geometry=current.geometry)
        q_cur = predict_static(current.model, data, current.effects)
        rmse_cur_w = _rmse((d_val.q_mm3_s - predict_static(cur_in.model, d_val, cur_in.effects)) / s_val)
        scored = []
        for spec in specs:
            fit, spec_c = fit_candidate(current, data, sigma, spec, selected)
            f, p = _f_test(current.rss_weighted, current.n_params, fit.rss_weighted, fit.n_params, len(data))
            new_in, _ = fit_candidate(cur_in, d_in, s_in, spec_c, selected)
            rmse_new_w = _rmse((d_val.q_mm3_s - predict_static(new_in.model, d_val, new_in.effects)) / s_val)
            improvement = 1.0 - rmse_new_w / rmse_cur_w if rmse_cur_w > 0 else 0.0
            # practical size: how much the effect moves the prediction [mm^3/s]
            size = practical_size(predict_static(fit.model, data, fit.effects) - q_cur)
            if size <= floor_mm3_s:
                improvement = min(improvement, 0.0)
            scored.append((f, p, improvement, spec_c, fit))
        geo = None
        if geom_sides and not current.geometry:
            # the rig's unpublished needle geometry competes with the effects,
            # and is decided with them: alone (what it explains is a constant
            # of the rig, not an effect) and together with each effect (an
            # effect may hide the geometry's signal as much as the geometry
            # may absorb an effect's); a geometry at its bound is no fit
            geo = _geometry_candidate(current, cur_in, data, d_in, d_val, sigma, s_in, s_val,
                                      selected, geom_sides, rmse_cur_w)
            if geo is not None:
                scored.append(geo)
                scored += _joint_candidates(current, cur_in, data, d_in, d_val, sigma, s_in, s_val,
                                            selected, geo, specs, rmse_cur_w, floor_mm3_s, q_cur)
        m = len(scored)
        # an effect is one of many candidates (Bonferroni) and must lower the
        # inner validation error materially; the geometry is one constant of
        # the rig, asked once (is it the rig file's?), and must lower it at all
        passing = [s for s in scored
                   if (s[1] < alpha and s[2] > 0.0 if s[3] is GEOMETRY
                       else s[1] < alpha / m and s[2] >= min_improvement)]
        if not passing:
            break
        f, p, improvement, spec_c, fit = max(passing, key=lambda s: s[0])
        if spec_c is GEOMETRY:
            current = fit
            continue
        against = current
        if isinstance(spec_c, _Joint):
            # the effect is checked against the model with the geometry
            # identified: the constant is the rig's, the effect what is left
            against, spec_c = geo[4], spec_c.spec
            f, _ = _f_test(against.rss_weighted, against.n_params, fit.rss_weighted,
                           fit.n_params, len(data))
        p_perm = _permutation_check(against, data, sigma, spec_c, selected, f, n_perm=n_perm,
                                    rng=rng)
        if p_perm >= alpha_perm:
            break
        selected.append(spec_c)
        current = fit
        values = dict(zip(spec_c.params, map(float, fit.effects[spec_c.label][1])))
        values.update({k: v for k, v in spec_c.fixed.items() if v is not None})
        ci_all = fit.param_ci95()
        ci = {name: ci_all[f"{spec_c.label}.{name}"] for name in spec_c.params}
        findings.append(EffectFinding(spec_c.name, spec_c.side, values, ci, p_value=p_perm,
                                      f_p_value=p, inner_improvement=improvement,
                                      params_bounds={k: (float(lo), float(hi)) for k, lo, hi in
                                                     zip(spec_c.params, spec_c.lower,
                                                         spec_c.upper)}))
    if selected and geom_sides and not current.geometry:
        current, selected, findings = _prune_geometry(
            base, current, selected, findings, data, d_in, d_val, sigma, s_in, s_val, geom_sides,
            alpha=alpha, min_improvement=min_improvement)
    return base, current, findings, trends, lb, sigma


#: marks the geometry pseudo-candidate in the selection
GEOMETRY = "needle_geometry"


@dataclass(frozen=True)
class _Joint:
    """A candidate effect fitted together with the needle geometry."""

    spec: Any


def _geometry_candidate(current, cur_in, data, d_in, d_val, sigma, s_in, s_val, selected,
                        sides, rmse_cur_w):
    """(F, p, inner improvement, GEOMETRY, fit) of freeing the needle centre y_c
    of the ``sides`` whose fitted centre is plausible (:func:`plausible_geometry`);
    None when none is."""
    fit = fit_static(current.model, data, sigma, effects=selected, geometry=sides)
    ok = plausible_geometry(fit)
    if not ok:
        return None
    if ok != fit.geometry:
        fit = fit_static(current.model, data, sigma, effects=selected, geometry=ok)
    f, p = _f_test(current.rss_weighted, current.n_params, fit.rss_weighted, fit.n_params, len(data))
    new_in = fit_static(cur_in.model, d_in, s_in, effects=selected, geometry=ok)
    rmse_new_w = _rmse((d_val.q_mm3_s - predict_static(new_in.model, d_val, new_in.effects)) / s_val)
    improvement = 1.0 - rmse_new_w / rmse_cur_w if rmse_cur_w > 0 else 0.0
    return f, p, improvement, GEOMETRY, fit


def _joint_candidates(current, cur_in, data, d_in, d_val, sigma, s_in, s_val, selected, geo,
                      specs, rmse_cur_w, floor_mm3_s, q_cur):
    """(F, p, inner improvement, _Joint(spec), fit) of each effect fitted with
    the needle geometry of ``geo`` free, scored against ``current`` (the
    geometry as the rig file has it); a fit whose geometry leaves the
    plausible range is left out."""
    out = []
    sides = geo[4].geometry
    with_geo = replace(current, geometry=sides)
    with_geo_in = replace(cur_in, geometry=sides)
    for spec in specs:
        fit, spec_c = fit_candidate(with_geo, data, sigma, spec, selected)
        if plausible_geometry(fit) != sides:
            continue
        f, p = _f_test(current.rss_weighted, current.n_params, fit.rss_weighted, fit.n_params,
                       len(data))
        new_in, _ = fit_candidate(with_geo_in, d_in, s_in, spec_c, selected)
        rmse_new_w = _rmse((d_val.q_mm3_s - predict_static(new_in.model, d_val, new_in.effects))
                           / s_val)
        improvement = 1.0 - rmse_new_w / rmse_cur_w if rmse_cur_w > 0 else 0.0
        size = practical_size(predict_static(fit.model, data, fit.effects)
                              - predict_static(geo[4].model, data, geo[4].effects))
        if size <= floor_mm3_s:     # the effect itself moves the prediction too little
            improvement = min(improvement, 0.0)
        out.append((f, p, improvement, _Joint(spec_c), fit))
    return out


def _prune_geometry(base, current, selected, findings, data, d_in, d_val, sigma, s_in, s_val,
                    sides, *, alpha, min_improvement):
    """Keep an effect only if it still beats the base model with the needle
    geometry identified (with the other effects kept): F-test and the inner
    validation improvement, as in the selection. What it does not beat is
    the unpublished geometry, not an effect."""
    kept = list(selected)
    for spec in list(selected):
        others = [x for x in kept if x is not spec]
        with_e = fit_static(base.model, data, sigma, effects=kept, geometry=sides)
        without = fit_static(base.model, data, sigma, effects=others, geometry=sides)
        _, p = _f_test(without.rss_weighted, without.n_params, with_e.rss_weighted,
                       with_e.n_params, len(data))
        w_in = fit_static(base.model, d_in, s_in, effects=kept, geometry=sides)
        wo_in = fit_static(base.model, d_in, s_in, effects=others, geometry=sides)
        r_with = _rmse((d_val.q_mm3_s - predict_static(w_in.model, d_val, w_in.effects)) / s_val)
        r_wo = _rmse((d_val.q_mm3_s - predict_static(wo_in.model, d_val, wo_in.effects)) / s_val)
        improvement = 1.0 - r_with / r_wo if r_wo > 0 else 0.0
        if p >= alpha or improvement < min_improvement:
            kept = others
    if len(kept) == len(selected):
        return current, selected, findings
    final = fit_static(base.model, data, sigma, effects=kept, geometry=sides)
    names = {(x.name, x.side) for x in kept}
    return final, kept, [f for f in findings if (f.name, f.side) in names]


def _permutation_check(current: StaticFit, data: FlowData, sigma, spec, selected, f_obs, *, n_perm, rng):
    """p-value of the candidate's F statistic under the current model.

    Standardised residuals of the current fit are permuted among runs and
    added back to its prediction (data that obey the current model with the
    same noise); base and candidate are refitted on each replicate.

    A candidate that is a function of run order (drift, threshold shift) is
    tested by permuting the run order instead, only among runs of the same
    side and load (:func:`permutation_strata`), the data left as measured:
    when a protocol steps the load up with time, anything the model misses
    that depends on the load (or on the flow at that load) is also a trend
    in run order, and scattered residuals would pass it off as wear. The
    question asked is whether the order *within* a load explains the data.
    """
    by_order = "run_index" in spec.effect.STATIC.needs
    strata = permutation_strata(data) if by_order else []
    q_hat = predict_static(current.model, data, current.effects)
    z = (data.q_mm3_s - q_hat) / sigma
    # a current model that does not read the run order has the same refit on
    # every replicate that only permutes it: fitted once
    same_cur = (fit_static(current.model, data, sigma, effects=selected,
                           geometry=current.geometry)
                if by_order and not _reads_run_order(selected) else None)
    exceed = 0
    for _ in range(n_perm):
        if by_order:
            d_star = replace(data, run_index=permuted_run_order(data.run_index, strata, rng))
        else:
            d_star = replace(data, q_mm3_s=q_hat + sigma * rng.permutation(z))
        cur = same_cur if same_cur is not None else fit_static(
            current.model, d_star, sigma, effects=selected, geometry=current.geometry)
        # grid-searched parameters (drift's period and phase) are searched
        # again on each replicate, as they were on the data
        new, _ = fit_candidate(cur, d_star, sigma, spec.unsearched(), selected)
        f, _ = _f_test(cur.rss_weighted, cur.n_params, new.rss_weighted, new.n_params, len(data))
        exceed += f >= f_obs
    return (1 + exceed) / (1 + n_perm)


def _reads_run_order(specs) -> bool:
    """True when a static prediction with the effects ``specs`` may read the
    run order: an effect that needs it, or a closed-form term (its
    expression may)."""
    return any("run_index" in s.effect.STATIC.needs or s.name == "term" for s in specs)
