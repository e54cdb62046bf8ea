"""Candidate effects for the static (flow-step) model and their fitting.

Each candidate is a small extension of eq. (5) with one continuous parameter
(drift also has a grid-searched period and phase). Functional forms live in
:mod:`seanv_analysis.models.effects`, shared with the simulator.
"""
from __future__ import annotations

import numpy as np

from .static import EffectSpec, FlowData, StaticFit, fit_static, predict_static

__all__ = ["candidate_specs", "fit_candidate", "DRIFT_MAX_EVERY"]

DRIFT_MAX_EVERY = 12  # longest drift period searched [runs]


def candidate_specs(data: FlowData, base: StaticFit) -> list[EffectSpec]:
    """All candidate effects that the data can identify.

    Drift needs a grid search over its period; its spec here carries
    ``every``/``offset`` = None and :func:`fit_candidate` fills them.
    """
    sides = [s for s in ("supply", "drain") if np.any(data.side == s)]
    specs = []
    for s in sides:
        specs.append(EffectSpec("drift", s, ("step",), (0.02,), (-0.5,), (0.5,),
                                {"every": None, "offset": None}))
        specs.append(EffectSpec("threshold_shift", s, ("rate_mm_per_run",), (0.0,), (-0.01,), (0.01,)))
        specs.append(EffectSpec("pressure_law", s, ("exponent",), (0.5,), (0.05,), (1.5,)))
        qmax = float(np.nanmax(np.abs(data.q_mm3_s[data.side == s]))) if np.any(data.side == s) else 1e4
        specs.append(EffectSpec("saturation", s, ("q_max_mm3_s",), (1.2 * qmax,), (0.1 * qmax,), (10 * qmax,)))
    if np.unique(data.approach[data.approach != 0]).size == 2:
        specs.append(EffectSpec("backlash", "both", ("width_deg",), (0.5,), (0.0,), (10.0,)))
    specs.append(EffectSpec("sensor_gain", "both", ("gain",), (1.0,), (0.5,), (2.0,),
                            {"sensor": "pressure"}))
    return specs


def _best_drift_grid(data: FlowData, base: StaticFit, sigma: np.ndarray, side: str):
    """Profile the stepwise drift: best (every, offset, step) with z0, C at the
    base fit and a free scale, by a vectorised grid over the step size."""
    m = data.side == side
    q = data.q_mm3_s[m]
    q0 = predict_static(base.model, data)[m]
    w = 1.0 / sigma[m]
    idx = data.run_index[m]
    steps = np.linspace(-0.3, 0.3, 241)
    results = []
    for every in range(1, DRIFT_MAX_EVERY + 1):
        for offset in range(every):
            k = np.floor((idx + offset) / every)
            mult = (1.0 - steps[:, None]) ** k[None, :]          # (steps, runs)
            g = mult * q0[None, :] * w[None, :]
            y = q * w
            a = (g @ y) / np.maximum(np.sum(g * g, axis=1), 1e-300)  # best scale per step
            rss = np.sum((y[None, :] - a[:, None] * g) ** 2, axis=1)
            j = int(np.argmin(rss))
            results.append((float(rss[j]), every, offset, float(steps[j])))
    # Periods alias (4 % every 3 runs ~ 7.8 % every 6): among fits within
    # 2 units of weighted RSS of the best (indistinguishable), take the
    # shortest period.
    best_rss = min(r[0] for r in results)
    close = [r for r in results if r[0] <= best_rss + 2.0]
    return min(close, key=lambda r: (r[1], r[0]))


def fit_candidate(model_base: StaticFit, data: FlowData, sigma: np.ndarray, spec: EffectSpec,
                  selected: list[EffectSpec]) -> tuple[StaticFit, EffectSpec]:
    """Fit base + ``selected`` + ``spec`` jointly; returns the fit and the
    concrete spec (drift with its period and phase filled in)."""
    if spec.name == "drift" and spec.fixed.get("every") is None:
        _, every, offset, step = _best_drift_grid(data, model_base, sigma, spec.side)
        spec = EffectSpec("drift", spec.side, ("step",), (step,), (-0.5,), (0.5,),
                          {"every": every, "offset": offset})
    fit = fit_static(model_base.model, data, sigma, effects=[*selected, spec])
    return fit, spec

