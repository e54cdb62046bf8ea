"""Result of model discovery: verdict, effects found, error before/after.

Results are frozen: a later step (the closed-loop check) makes a new one
(:meth:`Discovery.with_closed_loop`). Each effect's sentence comes from its
class in :mod:`seanv_analysis.models.effects`.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from typing import Any

from ..errors import ConfigError
from ..estimate import Estimate, Estimates
from ..jsonable import JsonResult, clean_json
from ..models import ValveModel
from ..models import effects as fx

__all__ = ["EffectFinding", "Discovery", "ProposedTerm", "STATIC_EVIDENCE"]

#: how the static selection backs an effect (:mod:`.engine`): the residual
#: permutation check and the F-test against the model without it
STATIC_EVIDENCE = "permutation p = {p_value:.3f}, F-test p = {f_p_value:.2g}"


@dataclass(frozen=True)
class EffectFinding:
    """One effect kept by the selection.

    ``params``: the effect's parameters in its own names (fitted, searched
    or held; their units are the effect's ``PARAMS``); ``params_ci95``: Wald
    95 % intervals from the joint fit's covariance (NaN when singular);
    ``p_value``: the p-value of the check that kept it (the permutation
    check for the static selection); ``f_p_value``: F-test p-value;
    ``inner_improvement``: relative error drop on the inner validation split;
    ``evidence``: the report's clause on the test, ``str.format``-ed with
    ``p_value`` and ``f_p_value``. :attr:`estimates` gives the numeric
    parameters as the package's one estimate type
    (:class:`~seanv_analysis.estimate.Estimate`); the JSON's ``estimates``
    are their records.
    """

    name: str
    side: str
    params: dict[str, Any]
    params_ci95: dict[str, tuple[float, float]]
    p_value: float
    f_p_value: float = float("nan")
    inner_improvement: float = float("nan")
    evidence: str = STATIC_EVIDENCE
    #: {parameter: (lower, upper)} the fit allowed (the static form's bounds)
    params_bounds: dict[str, tuple[float, float]] = field(default_factory=dict)

    def sentence(self) -> str:
        """What the effect means, in words (its class's sentence), or its
        name and parameters when it has none."""
        cls = fx.EFFECTS.get(self.name)
        try:
            if cls is None:
                raise KeyError(self.name)
            return cls.sentence(self.side, self.params)
        except (KeyError, ValueError):
            return f"{self.name} ({self.side}): {self.params}"

    @property
    def estimates(self) -> Estimates:
        """The numeric parameters as :class:`~seanv_analysis.estimate.Estimate`,
        named '<side>.<effect>.<parameter>' ('drain.drift.step'), in the
        units the effect declares: fitted ones with their interval, grid-searched
        ones (drift's ``every``, ``offset``) without one. Text parameters
        (a sensor's name) are not estimates.

        Raises
        ------
        ValueError
            a parameter whose unit the effect does not declare.
        """
        units = _param_units(self.name, self.params)
        searched = _searched(self.name)
        closed = self.evidence != STATIC_EVIDENCE
        where = ("position-control runs replayed on the identified twin" if closed else
                 f"flow steps{'' if self.side == 'both' else ' of the ' + self.side + ' side'}")
        out = []
        for k, v in self.params.items():
            if isinstance(v, str) or v is None:
                continue
            if k not in units:
                raise ValueError(f"effect {self.name}: parameter {k!r} declares no unit "
                                 "(its PARAMS entry ends in '[unit]')")
            ci = tuple(self.params_ci95.get(k, (math.nan, math.nan)))
            se = math.nan
            if k in self.params_ci95:
                method = ("fitted on the identified twin (profile of the replayed flow error "
                          "and segment bootstrap)" if closed else
                          "joint least squares with z0, C of both sides (Wald 95 % interval)")
                if not closed:   # Wald: value +- 1.96 stderr
                    se = (ci[1] - ci[0]) / (2 * 1.96)
            else:
                method = ("grid search before each fit (no interval)" if k in searched else
                          "held during the fit (no interval)")
            out.append(Estimate(f"{self.side}.{self.name}.{k}", v, units[k], ci, se,
                                method=method, constrained_by=where,
                                bounds=tuple(self.params_bounds.get(k, (-math.inf, math.inf)))))
        return Estimates.of(out)

    def evidence_text(self) -> str:
        """The test behind the finding with its p-values."""
        return self.evidence.format(p_value=self.p_value, f_p_value=self.f_p_value)

    def to_json_dict(self) -> dict[str, Any]:
        """name, side, ``params`` (the effect's spec, {parameter: value} in
        its own parameter names: what ``from_fit``, the model file and the
        simulator read), ``estimates`` (the numeric parameters'
        :class:`~seanv_analysis.estimate.Estimate` records: ``value_<unit>``,
        ``ci95_<unit>``, unit, method...; the same numbers) and p_value."""
        est = self.estimates
        by_param = {e.quantity: e for e in est.values()}
        return {"name": self.name, "side": self.side,
                "params": {k: clean_json(by_param[k].value if k in by_param else v)
                           for k, v in self.params.items()},
                "estimates": [e.to_json_dict() for e in est.values()],
                "p_value": clean_json(self.p_value)}


def _searched(name: str) -> tuple[str, ...]:
    """The parameters of effect ``name`` its static form sets on a grid."""
    cls = fx.EFFECTS.get(name)
    form = getattr(cls, "STATIC", None) if cls is not None else None
    return form.searched if form is not None else ()


def _param_units(name: str, params: dict[str, Any]) -> dict[str, str]:
    """{parameter: unit} of a named effect's fitted parameters (the effect's
    own declaration: :meth:`~seanv_analysis.models.effects.Effect.param_units`)."""
    from ..models.effects import EFFECTS

    cls = EFFECTS.get(name)
    units = cls.param_units() if cls is not None else {}
    return {k: units[k] for k in params if k in units}


#: term variable (:mod:`seanv_analysis.models.expr`) -> residual variable name
_RESIDUAL_NAMES = {"dp": "dp_mpa", "p1": "p1_mpa", "dtheta": "opening_deg", "theta": "opening_deg",
                   "q": "q_mm3_s", "load": "load_mpag", "run": "run_index",
                   "approach": "cam_approach"}


@dataclass(frozen=True)
class ProposedTerm:
    """A closed-form correction of eq. (5) the term search proposes
    (:mod:`.terms`) where the named effects (if any) leave a structured
    residual: not a known effect, a formula to examine.

    side, mode : the valve side and the ``term`` effect's mode ('mul' Q ->
        Q (1 + f), 'add' Q -> Q + f [mm^3/s], 'threshold' theta_d -> theta_d + f [deg])
    expr : f = sum_k a_k g_k in the expression grammar (canonical text)
    features, coefficients, coefficients_ci95 : the g_k texts, the a_k and
        their Wald 95 % intervals (refit jointly with z0, C, y_c)
    p_value : of the permutation test of the whole search
    rmse_before_mm3_s, rmse_after_mm3_s : held-out flow RMSE of the base
        model (needle geometry freed, named effects kept) and with the term
        as well [mm^3/s]
    inner_improvement : relative error drop on the inner validation split [-]
    model : the valve refitted with the term (z0, C, y_c; the named effects
        refitted beside it)
    """

    side: str
    mode: str
    expr: str
    features: tuple[str, ...]
    coefficients: tuple[float, ...]
    coefficients_ci95: tuple[tuple[float, float], ...]
    p_value: float
    rmse_before_mm3_s: float
    rmse_after_mm3_s: float
    inner_improvement: float
    model: ValveModel | None = None

    @property
    def estimates(self) -> Estimates:
        """The coefficients a_k as :class:`~seanv_analysis.estimate.Estimate`,
        named '<side>.term.a<k>', each in the unit of f
        (:data:`~seanv_analysis.models.effects.TERM_MODE_UNITS`) per the unit
        of its feature g_k (:func:`~seanv_analysis.models.expr.unit_of`;
        'mm^3/(s MPa^2)' for an added flow in dp**2, the units module's
        derived unit), with its Wald 95 % interval and standard error; the
        note names the feature."""
        from ..models.expr import unit_of
        from ..units import ratio_unit

        f_unit = fx.TERM_MODE_UNITS[self.mode]
        where = ("flow steps of both sides (an added flow passes the sealed valve too)"
                 if self.mode == "add" else f"flow steps of the {self.side} side")
        out = []
        for k, (g, a, ci) in enumerate(zip(self.features, self.coefficients,
                                           self.coefficients_ci95), start=1):
            out.append(Estimate(f"{self.side}.term.a{k}", a, ratio_unit(f_unit, unit_of(g)),
                                tuple(ci), (ci[1] - ci[0]) / (2 * 1.96),
                                method="joint least squares with z0, C, y_c of both sides and "
                                       "the named effects kept (Wald 95 % interval)",
                                constrained_by=where, note=f"coefficient of {g}"))
        return Estimates.of(out)

    @property
    def spec(self) -> str:
        """The ``term`` effect spec (``--effect`` string) of the proposal."""
        return fx.Term(side=self.side, mode=self.mode, expr=self.expr).spec()

    @property
    def trend_variable(self) -> str:
        """The residual variable (:func:`.engine.residual_variables`) of the
        term's first feature."""
        from ..models.expr import compile_expr

        names = compile_expr(self.features[0]).variables if self.features else ()
        return next((_RESIDUAL_NAMES[v] for v in names if v in _RESIDUAL_NAMES), "run_index")

    @property
    def heldout_drop(self) -> float:
        """Relative held-out RMSE drop with the term (0.3 = 30 % lower)."""
        return 1.0 - self.rmse_after_mm3_s / self.rmse_before_mm3_s if self.rmse_before_mm3_s \
            else 0.0

    def to_json_dict(self) -> dict[str, Any]:
        """side, mode, expr, spec, ``coefficients`` (each the feature and its
        :attr:`estimates` record: ``value_<unit>``, ``ci95_<unit>``, unit,
        method...), the search's p_value and the held-out RMSEs."""
        return {"side": self.side, "mode": self.mode, "expr": self.expr, "spec": self.spec,
                "coefficients": [{"feature": g, **e.to_json_dict()}
                                 for g, e in zip(self.features, self.estimates.values())],
                "p_value": clean_json(self.p_value),
                "heldout_rmse_before_mm3_s": clean_json(self.rmse_before_mm3_s),
                "heldout_rmse_after_mm3_s": clean_json(self.rmse_after_mm3_s),
                "inner_improvement_ratio": clean_json(self.inner_improvement)}

    def sentence(self, beside_named: bool = False) -> str:
        """The report's paragraph on the proposal (``beside_named``: named
        effects were found and the term acts on top of them)."""
        lead = ("Beyond the named effects, the flow-step residual holds a proposed term (not a "
                "known effect): " if beside_named else
                "No named effect explains the flow-step residual; a proposed term (not a known "
                "effect): ")
        return (lead +
                f"{self.spec} lowers the held-out error from {self.rmse_before_mm3_s:.0f} to "
                f"{self.rmse_after_mm3_s:.0f} mm^3/s ({-self.heldout_drop:+.0%}; search "
                f"permutation p = {self.p_value:.3f}, inner validation "
                f"{-self.inner_improvement:+.0%}). Coefficients (95 % intervals): "
                + "; ".join(f"{a:.4g} [{lo:.4g}, {hi:.4g}] of {g}" for a, (lo, hi), g in
                            zip(self.coefficients, self.coefficients_ci95, self.features))
                + ". Check it against the physics before naming it.")


def _interval(ci) -> str:
    lo, hi = (ci or (None, None))[:2]
    return f" [{lo:.1f}, {hi:.1f}]" if lo is not None and hi is not None else ""


def _geometry_sentence(geometry: dict, with_effects: bool) -> str:
    """The report's sentence on the needle centres discover fitted (with the
    named flow-step effects: ``with_effects``), and identify's beside them
    where that stage ran: two readings, their intervals, and whether they
    agree."""
    parts, apart = [], []
    for s, g in geometry.items():
        part = (f"{s} y_c {g['needle_y_c_mm']:.1f} mm{_interval(g.get('ci95_mm'))} "
                f"(rig file {g['rig_file_mm']:.1f}")
        if "identified_mm" in g:
            part += f"; identify {g['identified_mm']:.1f}{_interval(g.get('identified_ci95_mm'))}"
            lo, hi = (g.get("identified_ci95_mm") or (None, None))[:2]
            a_lo, a_hi = (g.get("ci95_mm") or (None, None))[:2]
            if None not in (lo, hi, a_lo, a_hi) and (a_hi < lo or hi < a_lo):
                apart.append(s)
        parts.append(part + ")")
    text = ("The needle geometry (eq. 4's centre, not published) differs from the rig file's "
            "and is part of the base model" + (", fitted with the named effects" if with_effects
                                               else "") + ": " + "; ".join(parts) + ".")
    if apart:
        text += (f" On the {' and '.join(apart)} side the two readings' intervals do not "
                 "overlap: identify fits the centre before and without any effect (the twin "
                 "keeps that one); here it is chosen together with the effects. The data "
                 "give both; neither is assumed.")
    elif not any("identified_mm" in g for g in geometry.values()):
        text += (" `seanv-analyze identify` fits it alone, before any effect (the twin's "
                 "reading).")
    return text


@dataclass(frozen=True)
class Discovery(JsonResult):
    """What discovery found and how much it helps on held-out runs.

    Frozen: :meth:`with_closed_loop` (and ``dataclasses.replace``) return a
    new result.
    """

    verdict: str
    effects: list[EffectFinding]
    n_heldout_runs: int
    rmse_before_mm3_s: float
    rmse_after_mm3_s: float
    trend_variable: str | None
    base_model: ValveModel
    model: ValveModel
    heldout_data: Any = None
    fit_data: Any = None
    base_fit: Any = None
    final_fit: Any = None
    holdout: str = "chrono"
    validation: dict | None = None   # closed-loop fit % before/after (with_closed_loop)
    position_control: dict | None = None  # delay check on position-control runs (dynamic.py)
    #: where the held-out error comes from: "flow_step" (static model on held-out
    #: runs), "closed_loop_heldout" (held-out position-control runs re-run on
    #: the identified twin) or "replay_heldout" (replayed on it, open loop)
    heldout_source: str = "flow_step"
    #: sides whose needle centre y_c (eq. 4, not published) the data moved from
    #: the rig file's: part of the base model, never an effect
    geometry: dict | None = None
    #: rig keys the closed-loop search refitted with the effect found (e.g. the
    #: line's bulk modulus), applied to the twin of the closed-loop check
    twin_overrides: dict | None = None
    #: the closed-form term the search proposes where the named effects (if
    #: any) leave a structured residual (:mod:`.terms`); None: none
    proposed_term: ProposedTerm | None = None

    @property
    def params(self) -> Estimates:
        """The effects' parameters by name ('drain.drift.step', ...: each
        effect's :attr:`EffectFinding.estimates`) and a proposed term's
        coefficients ('supply.term.a1', :attr:`ProposedTerm.estimates`), as
        lmfit's ``result.params``; ``params.to_frame()`` is their table. The
        JSON's ``effects[].estimates`` and ``proposed_term.coefficients`` are
        their records (``effects[].params``: the same numbers under the
        parameters' own names, the last part of each name)."""
        out = Estimates()
        for e in self.effects:
            out.update(e.estimates)
        if self.proposed_term is not None:
            out.update(self.proposed_term.estimates)
        return out

    @property
    def improvement(self) -> float:
        """Relative held-out RMSE drop (0.3 = 30 % lower)."""
        if not self.rmse_before_mm3_s:
            return 0.0
        return 1.0 - self.rmse_after_mm3_s / self.rmse_before_mm3_s

    def to_json_dict(self) -> dict[str, Any]:
        """The stable JSON contract of ``seanv-analyze discover --json``."""
        out = {"verdict": self.verdict,
               "effects": [e.to_json_dict() for e in self.effects],
               "heldout": {"n_runs": int(self.n_heldout_runs),
                           "rmse_before_mm3_s": clean_json(self.rmse_before_mm3_s),
                           "rmse_after_mm3_s": clean_json(self.rmse_after_mm3_s)},
               "trend_variable": self.trend_variable,
               # where the held-out numbers come from
               "heldout_source": self.heldout_source}
        if self.geometry:
            out["base_geometry"] = self.geometry
        if self.position_control:
            out["position_control"] = self.position_control
        if self.validation:
            out["validation"] = self.validation
        if self.proposed_term is not None:
            out["proposed_term"] = self.proposed_term.to_json_dict()
        return out

    def augmented_model_dict(self) -> dict[str, Any]:
        """Model file content: the refitted valve plus the effects found
        (with a proposed term: the valve refitted with it, and the term as
        ``proposed_term``, its ``term:`` spec)."""
        term = self.proposed_term
        d = (term.model if term is not None and term.model is not None else self.model).to_dict()
        d["effects"] = [e.to_json_dict() for e in self.effects]
        if term is not None:
            d["proposed_term"] = term.spec
        return d

    def with_closed_loop(self, before: dict | None, after: dict | None) -> "Discovery":
        """A copy holding the closed-loop check (``validation``: mean fit per
        controller with the base model ``before`` and the augmented one
        ``after``); the held-out numbers stay as they are."""
        return replace(self, validation={"before": before, "after": after})

    def augmented_model_and_effects(self, rig=None) -> tuple[ValveModel, list[str]]:
        """The refitted valve and the effects found as ``models.effects``
        specs (what the simulator's plant and ``validate`` take); with a
        proposed term, the valve refitted with it and its ``term`` spec last.

        Raises
        ------
        ConfigError
            A fitted value outside the effect's range (the simulator cannot
            put it in).
        """
        specs = []
        for e in self.effects:
            cls = fx.EFFECTS.get(e.name)
            if cls is None:
                continue
            try:
                specs.append(cls.from_fit(e.side, e.params).spec())
            except ValueError as exc:
                raise ConfigError(str(exc)) from None
        if self.proposed_term is not None:
            # the valve refitted with the term, and the term itself
            return self.proposed_term.model or self.model, [*specs, self.proposed_term.spec]
        return self.model, specs

    def position_run_model_and_effects(self, rig=None) -> tuple[ValveModel, list[str]]:
        """:meth:`augmented_model_and_effects` for the position-control runs:
        where the dynamic search set a constant that changes with use from
        those runs (``position_control['valve_at_position_runs']``: a
        drift's C, a threshold shift's z0), the valve carries that value and
        the effect of use on that side is left out (the runs lie outside the
        flow steps' sequence: extrapolating the trend to them is what the
        refit replaces).

        Raises
        ------
        ConfigError
            As :meth:`augmented_model_and_effects`.
        """
        model, specs = self.augmented_model_and_effects(rig)
        refit = (self.position_control or {}).get("valve_at_position_runs") or []
        return at_position_runs(model, specs, refit)

    def __repr__(self) -> str:
        found = ", ".join(f"{e.name} ({e.side})" for e in self.effects) or "nothing"
        return (f"<Discovery {self.verdict}: {found}; held-out RMSE "
                f"{self.rmse_before_mm3_s:.4g} -> {self.rmse_after_mm3_s:.4g} mm^3/s "
                f"({self.heldout_source}, {self.n_heldout_runs} runs)>")

    def plot(self, ax=None, **kwargs):
        """Flow residual before and after the effects found against
        ``variable`` (default 'run_index') on ``ax`` (a new pyplot figure when None); returns the axes."""
        from ..plotting import plot

        return plot(self, ax, **kwargs)

    def to_frame(self):
        """One row per parameter of the effects found and per coefficient
        of a proposed term (effect 'term'; a long table, each row's numbers
        in its ``unit``): effect, side, then :attr:`params`' table (name
        '<side>.<effect>.<parameter>', value, 95 % interval ci95_lo/ci95_hi,
        stderr, default, unit, source, method, constrained_by, note), and
        the effect's p_value (the term's: its search's permutation p)."""
        found = [(f.name, f.side, f.p_value, f.estimates) for f in self.effects]
        if self.proposed_term is not None:
            t = self.proposed_term
            found.append(("term", t.side, t.p_value, t.estimates))
        frame = Estimates.frame_of(e for *_, est in found for e in est.values())
        per = [(name, side, p) for name, side, p, est in found for _ in est]
        frame.insert(0, "effect", [p[0] for p in per])
        frame.insert(1, "side", [p[1] for p in per])
        frame["p_value"] = [p[2] for p in per]
        return frame

    def report(self) -> str:
        """A short text a researcher can paste into a lab note."""
        lines = []
        if self.verdict == "effect_found":
            names = ", ".join(f"{e.name} ({e.side})" for e in self.effects)
            lines.append(f"Discovery: the base model misses {names}.")
            for e in self.effects:
                lines.append(f"- {e.sentence()}; {e.evidence_text()}.")
        elif self.verdict == "unexplained":
            lines.append("Discovery: the residual of the base flow model is structured "
                         f"(it trends with {self.trend_variable}), but no candidate effect "
                         "explains it materially.")
        else:
            lines.append("Discovery: nothing found. The residual of the base flow model is "
                         "consistent with noise; no candidate effect lowers the error materially.")
        if self.proposed_term is not None:
            lines.append(self.proposed_term.sentence(beside_named=bool(self.effects)))
        if self.geometry:
            lines.append(_geometry_sentence(self.geometry, any(
                e.evidence == STATIC_EVIDENCE for e in self.effects)))
        what = {"closed_loop": "closed-loop flow RMSE (validate: controller re-run on the plant)",
                "closed_loop_heldout": "closed-loop flow RMSE on held-out position-control runs "
                                       "(controller re-run on the identified twin, each "
                                       "segment from the logged state)",
                "replay_heldout": "flow RMSE on held-out position-control runs replayed on the "
                                  "identified twin (its logged cam command in, open loop)",
                }.get(self.heldout_source, "flow RMSE")
        # with a proposed term and no named effect, "after" is the named
        # effects' (none): say so, the term's own figure is above
        after = "after the named effects (none)" if self.proposed_term and not self.effects \
            else "after"
        lines.append(f"Held-out runs ({self.holdout}, n = {self.n_heldout_runs}): {what} "
                     f"{self.rmse_before_mm3_s:.0f} mm^3/s before, {self.rmse_after_mm3_s:.0f} mm^3/s "
                     f"{after} ({-self.improvement:+.0%} error, residual = measured - model).")
        if self.position_control and self.position_control.get("method"):
            pc = self.position_control
            n = int(pc["n_runs"])
            lines.append(f"Position control ({n} run{'s' if n != 1 else ''}, "
                         f"{pc.get('n_heldout_runs', 0)} held out): {pc['method']}: "
                         f"{pc.get('message', '')}; "
                         + ("an effect is added to the twin." if pc.get("found") else
                            "none kept (significant on training runs, and on held-out runs a "
                            "significant and >= 10 % lower replayed flow error, are both "
                            "needed)."))
        elif self.position_control:
            pc = self.position_control
            n = int(pc["n_runs"])
            lines.append(f"Position control ({n} run{'s' if n != 1 else ''}): "
                         f"{pc.get('message', '')}.")
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


def at_position_runs(model: ValveModel, specs: list[str],
                     refit: list[dict[str, Any]]) -> tuple[ValveModel, list[str]]:
    """``model`` with each refitted constant of ``refit`` (entries of
    ``position_control['valve_at_position_runs']``: side, key and
    ``<name>_position_runs_<unit>``) and ``specs`` without the effects of use
    that move those constants on those sides (``Effect.CHANGES_WITH_USE``)."""
    moved = set()
    for r in refit:
        value = next(v for k, v in r.items() if "_position_runs_" in k)
        model = model.with_side(r["side"], **{r["key"]: float(value)})
        moved.add((r["side"], r["key"]))
    kept = []
    for spec in specs:
        effect = fx.parse_effect(spec)
        side = getattr(effect, "side", None)
        if (side, getattr(type(effect), "CHANGES_WITH_USE", None)) not in moved:
            kept.append(spec)
    return model, kept
