"""Dynamic effects in closed loop, fitted on the identified twin.

An extra transport delay between servo and needle, or a play (backlash)
between servo and cam, shows in position control as a different loop
behaviour, not as a flow-step residual. Each candidate is fitted by
simulation error: the training position-control runs are re-run on the
identified twin (:func:`seanv_analysis.analysis.validate.validate_run`:
the run's own controller, references and loads) with the effect at each
value of a grid, and the measured vs simulated actuator flow error is
minimised. An effect is named when

The line's bulk modulus was identified without the effect and may have
taken part of it (a longer lag mimics a delay), so it is refitted with each
candidate (coordinate descent: the effect's value, then the bulk modulus,
up to three times): the candidate must beat the base twin with its constants free.

- on the training runs it lowers the error significantly: the drop of the
  sum of squares over the residual variance (with the residuals' effective
  sample size) beats the chi-square(1) 99.9 % quantile with a Bonferroni
  factor for the candidates, and
- on the held-out runs (never used to fit) the closed-loop flow RMSE drops
  by at least ``min_improvement`` (20 %: a twin whose line is not the
  rig's gains ~10 % from a spurious delay on clean data).

The grid only brackets the value: the best grid point is refined by a
bounded scalar search between its neighbours (at the refitted bulk
modulus), and the kept candidate's 95 % interval is the profile of the
training SSE (the values whose SSE stays within the chi-square(1) 95 %
quantile of the residual variance above the minimum, bulk modulus held),
found by root finding on each side.

The headline numbers are the held-out closed-loop errors (flow RMSE and
position fit) before and after.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
from scipy import optimize, stats

from .closedloop import flow_sse, validate_on_twin, with_bulk

__all__ = ["DYNAMIC_CANDIDATES", "DynamicFinding", "closed_loop_effects"]

#: candidate: (parameter, grid of values) [s / deg]
DYNAMIC_CANDIDATES: dict[str, tuple[str, tuple[float, ...]]] = {
    "delay": ("delay_s", (0.03, 0.06, 0.1, 0.15, 0.2, 0.3)),
    "backlash": ("width_deg", (0.5, 1.0, 1.5, 2.0, 3.0)),
}

#: the line's bulk modulus is refitted with each candidate over these factors
#: of the identified value (the base model keeps its unknown constants free)
_BULK_FACTORS = (0.5, 0.7, 1.0, 1.4, 2.0)


@dataclass
class DynamicFinding:
    """The best value of one candidate and its evidence."""

    name: str
    param: str
    value: float
    ci95: tuple[float, float]
    p_value: float
    train_sse_drop: float
    heldout_before: dict[str, float] = field(default_factory=dict)
    heldout_after: dict[str, float] = field(default_factory=dict)
    named: bool = False
    bulk_mpa: float = math.nan       # the line's bulk modulus refitted with the effect

    @property
    def spec(self) -> str:
        return f"{self.name}:{self.param}={self.value:g}"

    @property
    def heldout_improvement(self) -> float:
        b, a = self.heldout_before.get("rmse_flow_mm3_s"), self.heldout_after.get("rmse_flow_mm3_s")
        return 1.0 - a / b if b and a is not None and math.isfinite(b) and b > 0 else math.nan

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "param": self.param, "value": self.value,
                "ci95": list(self.ci95), "p_value": self.p_value, "named": self.named,
                "bulk_mpa_with_effect": self.bulk_mpa,
                "heldout_before": self.heldout_before, "heldout_after": self.heldout_after}


def _summary(validations) -> dict[str, float]:
    if not validations:
        return {}
    rows = [v.row for v in validations]
    return {"rmse_flow_mm3_s": float(np.sqrt(np.mean([r["rmse_flow_mm3_s"] ** 2 for r in rows]))),
            "fit_position_pct": float(np.mean([r["fit_position_pct"] for r in rows])),
            "fit_flow_pct": float(np.mean([r["fit_flow_pct"] for r in rows]))}


def closed_loop_effects(train: Sequence[Any], held: Sequence[Any], valve, rig, *,
                        candidates: Sequence[str] = tuple(DYNAMIC_CANDIDATES),
                        alpha: float = 1e-3, min_improvement: float = 0.20
                        ) -> tuple[list[DynamicFinding], dict[str, float]]:
    """Fit each dynamic candidate on ``train`` (the twin ``rig`` with the
    valve ``valve``) and check it on ``held``; returns every candidate's
    finding (``named`` True for the kept one, at most one) and the held-out
    closed-loop numbers of the twin without effects."""
    base_train = flow_sse(validate_on_twin(train, valve, rig))
    base_held_v = validate_on_twin(held, valve, rig)
    base_held = _summary(base_held_v)
    if base_train[2] == 0:
        return [], base_held
    sse0, n_eff, _ = base_train
    findings = []
    m = len(candidates)
    b0 = float(rig["tube"]["effective_bulk_modulus_mpa"])

    seen: dict[tuple[str, float], float] = {}
    profiles: dict[str, tuple[Any, float, Sequence[float]]] = {}

    def cost(spec: str, bulk: float) -> float:
        """Training flow SSE with the effect ``spec`` at bulk modulus ``bulk``
        (each pair simulated once: the descent revisits its current point)."""
        if (spec, bulk) not in seen:
            twin = with_bulk(rig, bulk, where="discover")
            seen[(spec, bulk)] = flow_sse(validate_on_twin(train, valve, twin, [spec]))[0]
        return seen[(spec, bulk)]

    for name in candidates:
        param, grid = DYNAMIC_CANDIDATES[name]
        # coordinate descent: the effect's value on its grid, then the line's
        # bulk modulus with it (it was identified without the effect and may
        # have taken part of it), up to three times
        bulk = b0
        for _ in range(3):
            costs = [(cost(f"{name}:{param}={v:g}", bulk), v) for v in grid]
            sse1, best = min(costs)
            sse_b, bulk_new = min((cost(f"{name}:{param}={best:g}", bulk * k), bulk * k)
                                  for k in _BULK_FACTORS)
            if bulk_new == bulk:
                break
            bulk, sse1 = bulk_new, sse_b
        def at(v: float, name=name, param=param, bulk=bulk) -> float:
            return cost(f"{name}:{param}={v:.4g}", bulk)

        lo, hi = _bracket(grid, best)
        r = optimize.minimize_scalar(at, bounds=(lo, hi), method="bounded",
                                     options={"xatol": 0.01 * (hi - lo)})
        if r.fun < sse1:
            best, sse1 = float(f"{r.x:.4g}"), float(r.fun)
        s2 = sse1 / max(n_eff - 1.0, 1.0)
        stat = (sse0 - sse1) / s2 if s2 > 0 else 0.0
        p = float(stats.chi2.sf(max(stat, 0.0), 1))
        lim = sse1 + stats.chi2.ppf(0.95, 1) * s2
        inside = [v for c, v in costs if c <= lim] + [best]
        f = DynamicFinding(name, param, float(best), (min(inside), max(inside)), p,
                           (sse0 - sse1) / sse0 if sse0 > 0 else 0.0)
        f.bulk_mpa = float(bulk)
        profiles[name] = (at, lim, grid)
        findings.append(f)
    findings.sort(key=lambda f: f.p_value)
    for f in findings[:1]:
        if f.p_value >= alpha / m:
            break
        f.ci95 = _profile_interval(*profiles[f.name], f.value)
        f.heldout_before = base_held
        twin = with_bulk(rig, f.bulk_mpa, where="discover")
        f.heldout_after = _summary(validate_on_twin(held, valve, twin, [f.spec])) if held else {}
        imp = f.heldout_improvement
        f.named = bool(held) and math.isfinite(imp) and imp >= min_improvement
    return findings, base_held


def _bracket(grid: Sequence[float], best: float) -> tuple[float, float]:
    """The interval between the grid neighbours of ``best`` (0 below the
    first point, 1.5x the last above it)."""
    i = list(grid).index(best)
    lo = grid[i - 1] if i > 0 else 0.0
    hi = grid[i + 1] if i + 1 < len(grid) else 1.5 * grid[-1]
    return float(lo), float(hi)


def _profile_interval(cost, lim: float, grid: Sequence[float], best: float
                      ) -> tuple[float, float]:
    """Where ``cost`` (the training SSE at a value) crosses ``lim`` on each
    side of ``best``, searched over [0, 1.5 x the grid's last point]; an edge
    where it never crosses is the interval's end (the data cannot exclude it)."""
    def side(edge: float) -> float:
        if edge == best or cost(edge) <= lim:
            return edge
        return float(optimize.brentq(lambda v: cost(v) - lim, min(edge, best), max(edge, best),
                                     xtol=0.002 * grid[-1]))
    return side(0.0), side(1.5 * float(grid[-1]))
