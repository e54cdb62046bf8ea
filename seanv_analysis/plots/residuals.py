"""Discovery figure: flow residual (measured - model) against the explanatory
variables, before and after adding the effects found."""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from ._style import DEFAULT_FORMATS, new_figure, save_figure

__all__ = ["plot_discovery_residuals"]

_LABELS = {"run_index": "Run index (time order) [-]", "dp_mpa": "Pressure difference [MPa]",
           "opening_deg": "Opening past threshold [deg]", "cam_approach": "Cam approach direction [-]",
           "q_mm3_s": "|Flow rate| [mm^3/s]", "load_mpag": "Load [MPaG]"}


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
    # the variables and predictions exactly as discovery saw them
    from ..discover import predict_static, residual_variables

    fig = new_figure(figsize=(4.2 * len(variables), 3.6))
    axes = np.atleast_1d(fig.subplots(1, len(variables), sharey=True))
    for part, data, marker in (("fit", discovery.fit_data, "o"), ("held-out", discovery.heldout_data, "s")):
        if data is None or len(data) == 0:
            continue
        var = residual_variables(discovery.base_model, data)
        r_before = data.q_mm3_s - predict_static(discovery.base_fit.model, data)
        r_after = data.q_mm3_s - predict_static(discovery.final_fit.model, data, discovery.final_fit.effects)
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
    for ax, name in zip(axes, variables):
        ax.axhline(0, color="k", lw=0.8)
        ax.set_xlabel(_LABELS.get(name, name))
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("Flow residual (measured - model) [mm^3/s]")
    names = ", ".join(f"{e.name} ({e.side})" for e in discovery.effects) or "no effect"
    fig.suptitle(f"Discovery: {discovery.verdict} - {names}; held-out RMSE "
                 f"{discovery.rmse_before_mm3_s:.0f} -> {discovery.rmse_after_mm3_s:.0f} mm^3/s")
    handles, labels = axes[0].get_legend_handles_labels()
    uniq = dict(zip(labels, handles))
    fig.legend(uniq.values(), uniq.keys(), loc="lower center", ncol=min(len(uniq), 6), fontsize=8,
               frameon=False)
    fig.tight_layout(rect=(0, 0.08, 1, 0.95))
    return save_figure(fig, out_dir, stem, formats=formats, dpi=130, tight=False)
