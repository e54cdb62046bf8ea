"""Discovery figure: flow residual (measured - model) against the explanatory
variables, before and after adding the effects found (and with the proposed
closed-form term, when the term search proposed one)."""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from ._style import DEFAULT_FORMATS, check_formats, new_figure, paper_style, save_figure
from .registry import Figure, register_figure

__all__ = ["plot_discovery_residuals", "draw"]

#: axis label of each residual variable (also for Discovery.plot)
LABELS = {"run_index": "Run index (time order)", "dp_mpa": r"Pressure difference $\Delta p$ [MPa]",
           "opening_deg": r"Opening past threshold $\theta - \theta_d$ [deg]",
           "cam_approach": "Cam approach direction (-1 closing, +1 opening)",
           "q_mm3_s": "|Flow rate| [mm$^3$/s]", "load_mpag": "Load [MPaG]"}
_VERDICT = {"none": "nothing found", "effect_found": "the model misses",
            "unexplained": "unexplained residual"}


def plot_discovery_residuals(discovery, *, out_dir: str | Path, stem: str = "discover_residuals",
                             variables=("run_index", "dp_mpa", "opening_deg", "cam_approach"),
                             formats: str | Sequence[str] = DEFAULT_FORMATS) -> list[Path]:
    """Residual vs variable, all runs (fit set and held-out), before/after,
    as ``<out_dir>/<stem>.<format>`` for each of ``formats``.

    Returns the written paths; none when the discovery had no flow-step runs
    (position-control data only: its evidence is the lag and ``validate``).
    """
    if discovery.fit_data is None or discovery.base_fit is None:
        return []
    with paper_style():
        return _draw(discovery, out_dir, stem, variables, formats)


def residual_with_term(discovery, data):
    """Residual [mm^3/s] with the proposed closed-form term (``discovery.proposed_term``,
    :mod:`seanv_analysis.discover.terms`), None when there is none."""
    term = getattr(discovery, "proposed_term", None)
    if term is None:
        return None
    from ..discover import predict_static
    from ..discover.terms import term_spec

    spec = term_spec(term.side, term.mode, term.features)
    return data.q_mm3_s - predict_static(term.model or discovery.model, data,
                                         {spec.label: (spec, np.asarray(term.coefficients))})


def _draw(discovery, out_dir, stem, variables, formats) -> list[Path]:
    """The figure (a grid of two columns), in the house style."""
    # the variables and predictions exactly as discovery saw them
    from ..discover import predict_static, residual_variables

    ncol = 2 if len(variables) > 1 else 1
    nrow = -(-len(variables) // ncol)
    fig = new_figure(figsize=(9.0, 3.0 * nrow + 1.0))
    axes = np.atleast_1d(fig.subplots(nrow, ncol, sharey=True)).ravel()
    for ax in axes[len(variables):]:
        ax.set_visible(False)
    for part, data, marker in (("fit", discovery.fit_data, "o"), ("held-out", discovery.heldout_data, "s")):
        if data is None or len(data) == 0:
            continue
        var = residual_variables(discovery.base_model, data)
        r_before = data.q_mm3_s - predict_static(discovery.base_fit.model, data)
        r_after = data.q_mm3_s - predict_static(discovery.final_fit.model, data, discovery.final_fit.effects)
        r_term = residual_with_term(discovery, data)
        for ax, name in zip(axes, variables):
            x = var.get(name)
            if x is None:
                continue
            jitter = 0.08 * np.random.default_rng(0).standard_normal(x.size) if name == "cam_approach" else 0
            for side, colour in (("supply", "tab:red"), ("drain", "tab:blue")):
                m = data.side == side
                ax.scatter((x + jitter)[m], r_before[m], s=10, marker=marker, facecolors="none",
                           edgecolors="0.6", linewidths=0.7,
                           label=f"before ({part})" if side == "supply" else None)
                ax.scatter((x + jitter)[m], r_after[m], s=10, marker=marker, color=colour, alpha=0.8,
                           label=f"after, {side} ({part})")
                if r_term is not None:
                    ax.scatter((x + jitter)[m], r_term[m], s=12, marker="x", color="tab:green",
                               linewidths=0.8, label=f"with the proposed term ({part})"
                               if side == "supply" else None)
    for ax, name in zip(axes, variables):
        ax.axhline(0, color="k", lw=0.8)
        ax.set_xlabel(LABELS.get(name, name))
        ax.grid(alpha=0.3)
    for ax in axes[::ncol]:
        ax.set_ylabel("Residual $Q - Q_{model}$\n[mm$^3$/s]")
    names = ", ".join(f"{e.name} ({e.side})" for e in discovery.effects)
    verdict = _VERDICT.get(discovery.verdict, discovery.verdict) + (f" {names}" if names else "")
    fig.suptitle(f"Discovery: {verdict}; held-out RMSE {discovery.rmse_before_mm3_s:.0f} "
                 f"$\\rightarrow$ {discovery.rmse_after_mm3_s:.0f} mm$^3$/s")
    handles, labels = axes[0].get_legend_handles_labels()
    uniq = dict(zip(labels, handles))
    fig.legend(uniq.values(), uniq.keys(), loc="lower center", ncol=3, frameon=False,
               markerscale=1.5)
    fig.tight_layout(rect=(0, 0.1, 1, 0.95))
    return save_figure(fig, out_dir, stem, formats=formats, tight=False)


def draw(results, folder: Path, *, formats: Sequence[str] = DEFAULT_FORMATS) -> list[Path]:
    """Residuals before/after discovery as ``folder/discover_residuals.<format>``
    (:func:`plot_discovery_residuals`)."""
    return plot_discovery_residuals(results["discovery"], out_dir=folder,
                                    formats=check_formats(formats))


register_figure(Figure(
    name="discover_residuals", needs=("discovery",), draw=draw, order=50,
    title="Discovery: flow residual (measured - model) before/after the effects found"))
