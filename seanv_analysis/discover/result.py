"""Result of model discovery: verdict, effects found, error before/after."""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..models import ValveModel

__all__ = ["EffectFinding", "Discovery"]

_EFFECT_TEXT = {
    "drift": "the flow coefficient C of the {side} side {direction} by {abs_step:.2%} every {every} runs "
             "(C (1 - step)^floor((i + offset)/every), step = {step:+.4f})",
    "threshold_shift": "the {side} sealing threshold creeps with use (z0 changes {rate_mm_per_run:+.2e} mm per run)",
    "backlash": "the cam has a direction-dependent dead band of {width_deg:.2f} deg (backlash)",
    "pressure_law": "the {side} flow follows dp^{exponent:.2f}, not the orifice law dp^0.5",
    "saturation": "the {side} flow saturates at about {q_max_mm3_s:.0f} mm^3/s at large openings",
    "sensor_gain": "a {sensor} sensor reads {gain:.3f} x the true value",
    "delay": "the flow lags Q_ref by an extra {delay_s:.3f} s beyond the nominal lag (transport delay)",
}


@dataclass(frozen=True)
class EffectFinding:
    """One effect kept by the selection.

    ``params``: fitted values (units in the names); ``params_ci95``: Wald
    95 % intervals from the joint fit's covariance (NaN when singular);
    ``p_value``: permutation-check p-value; ``f_p_value``: F-test p-value;
    ``inner_improvement``: relative error drop on the inner validation split.
    """

    name: str
    side: str
    params: dict[str, Any]
    params_ci95: dict[str, tuple[float, float]]
    p_value: float
    f_p_value: float = float("nan")
    inner_improvement: float = float("nan")

    def sentence(self) -> str:
        try:
            extra = {}
            if self.name == "drift":
                step = float(self.params["step"])
                extra = {"direction": "falls" if step > 0 else "rises", "abs_step": abs(step)}
            return _EFFECT_TEXT[self.name].format(side=self.side, **self.params, **extra)
        except (KeyError, ValueError):
            return f"{self.name} ({self.side}): {self.params}"

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "side": self.side,
                "params": {k: _num(v) for k, v in self.params.items()},
                "params_ci95": {k: [_num(a), _num(b)] for k, (a, b) in self.params_ci95.items()},
                "p_value": _num(self.p_value)}


def _num(v):
    if isinstance(v, (np.floating, float)):
        return None if not np.isfinite(v) else float(v)
    if isinstance(v, np.integer):
        return int(v)
    return v


@dataclass
class Discovery:
    """What discovery found and how much it helps on held-out runs."""

    verdict: str
    effects: list[EffectFinding]
    n_heldout_runs: int
    rmse_before_mm3_s: float
    rmse_after_mm3_s: float
    trend_variable: str | None
    base_model: ValveModel
    model: ValveModel
    effect_fits: dict = field(default_factory=dict)
    trends: list = field(default_factory=list)
    ljung_box: tuple[float, float] = (0.0, 1.0)
    residual_before: np.ndarray | None = None
    residual_after: np.ndarray | None = None
    heldout_data: Any = None
    fit_data: Any = None
    base_fit: Any = None
    final_fit: Any = None
    holdout: str = "chrono"
    validation: dict | None = None   # closed-loop fit % before/after, filled by the CLI/pipeline
    position_control: dict | None = None  # delay check on position-control runs (dynamic.py)
    #: where the held-out error comes from: "flow_step" (static model on held-out
    #: runs), "position_control_shift" (shifted-flow RMSE on held-out run tails,
    #: position-only data) or "closed_loop" (validate's flow RMSE, base vs augmented)
    heldout_source: str = "flow_step"

    @property
    def improvement(self) -> float:
        """Relative held-out RMSE drop (0.3 = 30 % lower)."""
        if not self.rmse_before_mm3_s:
            return 0.0
        return 1.0 - self.rmse_after_mm3_s / self.rmse_before_mm3_s

    def to_json(self) -> dict[str, Any]:
        """The stable JSON contract of ``seanv-analyze discover --json``."""
        out = {"verdict": self.verdict,
               "effects": [e.to_json() for e in self.effects],
               "heldout": {"n_runs": int(self.n_heldout_runs),
                           "rmse_before_mm3_s": _num(self.rmse_before_mm3_s),
                           "rmse_after_mm3_s": _num(self.rmse_after_mm3_s)},
               "trend_variable": self.trend_variable,
               # additive to the issue-8 contract: where the held-out numbers come from
               "heldout_source": self.heldout_source}
        if self.position_control:
            out["position_control"] = self.position_control
        if self.validation:
            out["validation"] = self.validation
        return out

    def augmented_model_dict(self) -> dict[str, Any]:
        """Model file content: the refitted valve plus the effects found."""
        d = self.model.to_dict()
        d["effects"] = [e.to_json() for e in self.effects]
        return d

    def use_closed_loop_heldout(self) -> None:
        """Position-control-only data: take the before/after error from the
        closed-loop check (``validation``, flow-model controller runs, else
        all) instead of the shifted-flow RMSE, which a delay in the loop makes
        a poor predictor (see :mod:`.dynamic`). Nothing changes when the
        held-out error comes from flow-step runs."""
        if self.heldout_source == "flow_step":
            return
        val = self.validation or {}
        before, after = val.get("before") or {}, val.get("after") or {}
        ctrl = "flow_model" if "flow_model" in before else next(iter(before), None)
        try:
            b = float(before[ctrl]["rmse_flow_mm3_s"])
            a = float(after[ctrl]["rmse_flow_mm3_s"])
        except (KeyError, TypeError, ValueError):
            return
        self.rmse_before_mm3_s, self.rmse_after_mm3_s = b, a
        self.heldout_source = "closed_loop"

    def augmented_model_and_effects(self, rig=None) -> tuple[ValveModel, list[str]]:
        """The refitted valve and the effects found as ``models.effects``
        specs (what the simulator's plant and ``validate`` take)."""
        from dataclasses import fields

        from ..models.effects import EFFECTS, parse_effect

        specs = []
        for e in self.effects:
            cls = EFFECTS.get(e.name)
            if cls is None:
                continue
            known = {f.name for f in fields(cls)}
            raw = {"side": e.side, **{k: v for k, v in e.params.items() if v is not None}}
            specs.append(parse_effect({"name": e.name,
                                       **{k: v for k, v in raw.items() if k in known}}).spec())
        return self.model, specs

    def report(self) -> str:
        """A short text a researcher can paste into a lab note."""
        lines = []
        if self.verdict == "effect_found":
            names = ", ".join(f"{e.name} ({e.side})" for e in self.effects)
            lines.append(f"Discovery: the base model misses {names}.")
            for e in self.effects:
                if e.name == "delay":
                    lines.append(f"- {e.sentence()}; p = {e.p_value:.2g} (lag vs nominal, "
                                 "from the block-bootstrap interval).")
                else:
                    lines.append(f"- {e.sentence()}; permutation p = {e.p_value:.3f}, "
                                 f"F-test p = {e.f_p_value:.2g}.")
        elif self.verdict == "unexplained":
            lines.append("Discovery: the residual of the base flow model is structured "
                         f"(it trends with {self.trend_variable}), but no candidate effect "
                         "explains it materially.")
        else:
            lines.append("Discovery: nothing found. The residual of the base flow model is "
                         "consistent with noise; no candidate effect lowers the error materially.")
        what = {"closed_loop": "closed-loop flow RMSE (validate: controller re-run on the plant)",
                "position_control_shift": "flow RMSE of actual flow shifted by the nominal "
                                          "vs the estimated lag"}.get(self.heldout_source,
                                                                     "flow RMSE")
        lines.append(f"Held-out runs ({self.holdout}, n = {self.n_heldout_runs}): {what} "
                     f"{self.rmse_before_mm3_s:.0f} mm^3/s before, {self.rmse_after_mm3_s:.0f} mm^3/s "
                     f"after ({-self.improvement:+.0%} error, residual = measured - model).")
        if self.position_control:
            pc = self.position_control
            lines.append(f"Position control (n = {pc['n_runs']} runs; lag from the first 70 % of "
                         f"each run, confirmed on the last 30 %): {pc.get('message', '')}; "
                         + ("an extra delay is added to the model." if pc.get("found") else
                            "no extra delay.")
                         + " The closed-loop error before/after comes from validate.")
        if self.validation:
            before, after = self.validation.get("before") or {}, self.validation.get("after") or {}
            for ctrl, b in before.items():
                a = after.get(ctrl) or {}
                try:
                    lines.append(f"Closed loop (validate, {ctrl} controller): position fit "
                                 f"{b['fit_position_pct']:.1f} % -> {a['fit_position_pct']:.1f} %, flow "
                                 f"RMSE {b['rmse_flow_mm3_s']:.0f} -> {a['rmse_flow_mm3_s']:.0f} mm^3/s "
                                 "(base -> augmented model).")
                except (KeyError, TypeError):
                    lines.append(f"Closed loop (validate, {ctrl}): {json.dumps(b)} -> {json.dumps(a)}")
        return "\n".join(lines)
