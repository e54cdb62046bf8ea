"""Candidate effects for the static (flow-step) model and their fitting.

The candidates are the named effects with a static form
(:func:`seanv_analysis.models.effects.vocabulary_effects`; the generic
``term`` effect, which only carries a given formula, is not one): each is a small
extension of eq. (5) with one or a few continuous parameters (drift also has
a grid-searched period and phase). Their functional forms, start values and
bounds live in :mod:`seanv_analysis.models.effects`, shared with the
simulator; this module only asks each effect class.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..models import effects as fx
from .static import EffectSpec, FlowData, StaticFit, _side_mask, fit_static, predict_static

__all__ = ["candidate_specs", "fit_candidate"]


def candidate_specs(data: FlowData, base: StaticFit) -> list[EffectSpec]:
    """All candidate effects that the data can identify, in registry order:
    the sided effects once per valve side present (supply first), then the
    effects that act on both sides.

    A candidate with grid-searched parameters (drift's ``every``/``offset``)
    carries them as None; :func:`fit_candidate` fills them.

    Raises
    ------
    ValueError
        An effect's static form reads a variable flow-step data does not carry.
    """
    sides = [s for s in ("supply", "drain") if np.any(data.side == s)]
    # the vocabulary only: the generic ``term`` (VOCABULARY False) has a
    # static form too, but it is a given formula, not an effect to name
    static = fx.vocabulary_effects()
    for cls in static:
        missing = [v for v in cls.STATIC.needs if not hasattr(data, v)]
        if missing:
            raise ValueError(f"effect {cls.name!r}: its static form needs {', '.join(missing)}, "
                             "which flow-step data does not carry")
    specs = []
    for side in sides:
        for cls in static:
            if cls.sided():
                form = cls.static_form(data, side)
                if form is not None:
                    specs.append(EffectSpec.from_form(cls.name, side, form))
    for cls in static:
        if not cls.sided():
            form = cls.static_form(data, "both")
            if form is not None:
                specs.append(EffectSpec.from_form(cls.name, "both", form))
    return specs


def fit_candidate(model_base: StaticFit, data: FlowData, sigma: np.ndarray, spec: EffectSpec,
                  selected: list[EffectSpec]) -> tuple[StaticFit, EffectSpec]:
    """Fit base + ``selected`` + ``spec`` jointly; returns the fit and the
    concrete spec (grid-searched parameters, e.g. drift's period and phase,
    filled in against ``model_base``'s model without effects)."""
    if spec.needs_search:
        q_base = predict_static(model_base.model, data)
        x0, fixed = spec.effect.static_search(data, _side_mask(data, spec.side), q_base, sigma)
        spec = replace(spec, x0=tuple(x0), fixed={**spec.fixed, **fixed})
    fit = fit_static(model_base.model, data, sigma, effects=[*selected, spec],
                     geometry=model_base.geometry)
    return fit, spec
