"""Overlay of measured and simulated position-control runs (``validate``):
position [mm], flow [mm^3/s] and cam angle [deg] against time, and a bar
chart of the fit % per run."""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..io.names import safe_name
from ._style import (
    ACTUAL_COLOUR,
    DEFAULT_FORMATS,
    SIM_COLOUR,
    TARGET_COLOUR,
    high_load_spans,
    new_figure,
    paper_style,
    save_figure,
    shade_high_load,
    thin,
)

__all__ = ["plot_overlay", "plot_overlay_run"]


def plot_overlay_run(run_validation, out_dir: str | Path, *, stem: str | None = None,
                     threshold_pct: float | None = None,
                     formats: str | Sequence[str] = DEFAULT_FORMATS) -> list[Path]:
    """Three stacked panels (position, flow, cam) of one run, measured vs
    simulated, written in ``formats`` as ``<stem>.<format>`` (default stem
    ``validate_<run_id>``)."""
    from ..analysis.tracking import load_levels_mpag

    ov = run_validation.overlay
    ov = ov.iloc[thin(len(ov))]
    row = run_validation.row
    t = ov["t_s"].to_numpy(float)
    spans = high_load_spans(t, load_levels_mpag(t, ov["p_load_mpag"].to_numpy(float)))
    with paper_style():
        fig = new_figure(figsize=(6.4, 6.0))
        axes = fig.subplots(3, 1, sharex=True)
        shade_high_load(axes, spans, label="higher load")
        ax_x, ax_q, ax_c = axes
        ax_x.plot(t, ov["x_ref_mm"], color=TARGET_COLOUR, ls="--", drawstyle="steps-post",
                  label="reference")
        ax_x.plot(t, ov["position_mm"], color=ACTUAL_COLOUR, label="measured")
        ax_x.plot(t, ov["position_sim_mm"], color=SIM_COLOUR, label="simulated")
        ax_x.set_ylabel("Position [mm]")
        ax_x.set_title(f"{run_validation.run_id} ({row['controller']}): position fit "
                       f"{row['fit_position_pct']:.1f} %, flow fit {row['fit_flow_pct']:.1f} %, "
                       f"cam fit {row['fit_cam_pct']:.1f} %"
                       + ("  [FLAGGED]" if row.get("flagged") else ""))
        ax_q.plot(t, ov["q_mm3_s"] * 1e-3, color=ACTUAL_COLOUR, lw=0.8, label="measured")
        ax_q.plot(t, ov["q_sim_mm3_s"] * 1e-3, color=SIM_COLOUR, lw=0.8, label="simulated")
        ax_q.set_ylabel("Flow rate [$10^3$ mm$^3$/s]")
        ax_c.plot(t, ov["cam_deg"], color=ACTUAL_COLOUR, lw=0.8, label="measured")
        ax_c.plot(t, ov["cam_sim_deg"], color=SIM_COLOUR, lw=0.8, label="simulated")
        ax_c.set_ylabel("Cam angle [deg]")
        ax_c.set_xlabel("Time [s]")
        ax_c.set_xlim(t[0], t[-1])
        for ax in axes:
            ax.legend(loc="upper right", ncol=4)
        fig.align_ylabels(axes)
        fig.tight_layout(h_pad=0.4)
        return save_figure(fig, out_dir, stem or f"validate_{safe_name(run_validation.run_id)}",
                           formats=formats)


def plot_overlay(validation, out_dir: str | Path, *, summary: bool = True,
                 formats: str | Sequence[str] = DEFAULT_FORMATS) -> list[Path]:
    """Overlay figure per run, plus (``summary``) a bar chart of the
    position/flow/cam fit [%] per run with the flag threshold
    (``validate_fit.<format>``), in ``formats`` (default PNG and SVG)."""
    paths: list[Path] = []
    for r in validation.runs:
        paths += plot_overlay_run(r, out_dir, formats=formats)
    if summary and not validation.table.empty:
        tab = validation.table
        with paper_style():
            fig = new_figure(figsize=(max(4.5, 1.6 * len(tab) + 2.0), 3.2))
            ax = fig.subplots()
            x = np.arange(len(tab))
            for k, (col, label, colour) in enumerate(
                    (("fit_position_pct", "position", "tab:blue"),
                     ("fit_flow_pct", "flow", "tab:green"),
                     ("fit_cam_pct", "cam angle", "tab:purple"))):
                ax.bar(x + (k - 1) * 0.27, np.clip(tab[col].to_numpy(float), -50, 100), 0.27,
                       color=colour, label=label)
            ax.axhline(validation.threshold_pct, color="tab:red", ls="--", lw=0.9,
                       label=f"flag threshold {validation.threshold_pct:g} %")
            ax.set_xticks(x, [f"{a}\n({c})" for a, c in zip(tab.run_id, tab.controller)],
                          fontsize=7)
            ax.set_ylabel("Fit [%]")
            ax.set_ylim(min(0.0, float(np.nanmin(np.clip(tab[["fit_position_pct", "fit_flow_pct",
                                                                   "fit_cam_pct"]].to_numpy(float),
                                                           -50, 100), initial=0.0)) - 5), 105)
            ax.legend(loc="center left", bbox_to_anchor=(1.01, 0.5), ncol=1)
            ax.set_title("Measured vs simulated: fit % = 100 (1 - ||y - y_sim|| / ||y - mean y||)")
            fig.tight_layout()
            paths += save_figure(fig, out_dir, "validate_fit", formats=formats)
    return paths
