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
    LOAD_LEVEL_IMPORTS,
    SIM_COLOUR,
    TARGET_COLOUR,
    align_ylabels,
    check_formats,
    legend_outside,
    new_figure,
    paper_style,
    save_figure,
    shade_loads,
    trace,
)
from .registry import Figure, register_figure

__all__ = ["plot_overlay", "plot_overlay_run", "draw", "parts"]


def plot_overlay_run(run_validation, out_dir: str | Path, *, stem: str | None = None,
                     threshold_pct: float | None = None,
                     formats: str | Sequence[str] = DEFAULT_FORMATS) -> list[Path]:
    """Three stacked panels (position, flow, cam) of one run, measured vs
    simulated, written in ``formats`` as ``<stem>.<format>`` (default stem
    ``validate_<run_id>``)."""
    from ..analysis.tracking import load_levels_mpag

    ov = run_validation.overlay   # every sample; each trace decimated to the pixels it fills
    row = run_validation.row
    t = ov["t_s"].to_numpy(float)
    with paper_style():
        fig = new_figure(figsize=(7.6, 6.0))
        axes = fig.subplots(3, 1, sharex=True)
        loads = shade_loads(axes, t, load_levels_mpag(t, ov["p_load_mpag"].to_numpy(float)))
        ax_x, ax_q, ax_c = axes
        ax_x.plot(*trace(t, ov["x_ref_mm"]), color=TARGET_COLOUR, ls="--", drawstyle="steps-post",
                  label="reference")
        ax_x.plot(*trace(t, ov["position_mm"]), color=ACTUAL_COLOUR, label="measured")
        ax_x.plot(*trace(t, ov["position_sim_mm"]), color=SIM_COLOUR, label="simulated")
        ax_x.set_ylabel("Position [mm]")
        seg = "position_seg_mm" in ov and bool(np.isfinite(ov["position_seg_mm"]).any())
        if seg:
            ax_x.plot(*trace(t, ov["position_seg_mm"]), color=SIM_COLOUR, ls=":", lw=1.0,
                      label="per segment")
        ax_x.set_title(f"{run_validation.run_id} ({row['controller']}): position fit "
                       f"{row['fit_position_pct']:.1f} %, flow fit {row['fit_flow_pct']:.1f} %, "
                       f"cam fit {row['fit_cam_pct']:.1f} %"
                       + (f"\nre-run per segment from the logged state: position fit "
                          f"{row['fit_position_segments_pct']:.1f} %, flow fit "
                          f"{row['fit_flow_segments_pct']:.1f} %" if seg else "")
                       + ("  [FLAGGED]" if row.get("flagged") else ""), fontsize=8)
        ax_q.plot(*trace(t, ov["q_mm3_s"] * 1e-3), color=ACTUAL_COLOUR, lw=0.8, label="measured")
        ax_q.plot(*trace(t, ov["q_sim_mm3_s"] * 1e-3), color=SIM_COLOUR, lw=0.8, label="simulated")
        if seg:
            ax_q.plot(*trace(t, ov["q_seg_mm3_s"] * 1e-3), color=SIM_COLOUR, ls=":", lw=0.9,
                      label="per segment")
        ax_q.set_ylabel("Flow rate [$10^3$ mm$^3$/s]")
        ax_c.plot(*trace(t, ov["cam_deg"]), color=ACTUAL_COLOUR, lw=0.8, label="measured")
        ax_c.plot(*trace(t, ov["cam_sim_deg"]), color=SIM_COLOUR, lw=0.8, label="simulated")
        ax_c.set_ylabel("Cam angle [deg]")
        ax_c.set_xlabel("Time [s]")
        ax_c.set_xlim(t[0], t[-1])
        for i, ax in enumerate(axes):   # beside the panel, never over the traces
            legend_outside(ax, extra=loads if i == 0 else ())
        align_ylabels(axes)
        fig.tight_layout(h_pad=0.4)
        return save_figure(fig, out_dir, stem or f"validate_{safe_name(run_validation.run_id)}",
                           formats=formats, tight=False)


def plot_overlay(validation, out_dir: str | Path, *, summary: bool = True,
                 formats: str | Sequence[str] = DEFAULT_FORMATS, runs: bool = True
                 ) -> list[Path]:
    """Overlay figure per run (``runs``), plus (``summary``) a bar chart of the
    position/flow/cam fit [%] per run with the flag threshold
    (``validate_fit.<format>``), in ``formats`` (default PNG and SVG)."""
    paths: list[Path] = []
    for r in (validation.runs if runs else ()):
        paths += plot_overlay_run(r, out_dir, formats=formats)
    if summary and not validation.table.empty:
        tab = validation.table
        with paper_style():
            fig = new_figure(figsize=(max(4.5, 1.6 * len(tab) + 2.0), 3.2))
            ax = fig.subplots()
            x = np.arange(len(tab))
            bars = [("fit_position_pct", "position", "tab:blue", None),
                    ("fit_flow_pct", "flow", "tab:green", None),
                    ("fit_cam_pct", "cam angle", "tab:purple", None)]
            if "fit_flow_segments_pct" in tab and np.isfinite(
                    tab["fit_flow_segments_pct"].to_numpy(float)).any():
                bars += [("fit_position_segments_pct", "position, per segment", "tab:blue", "//"),
                         ("fit_flow_segments_pct", "flow, per segment", "tab:green", "//")]
            w = 0.8 / len(bars)
            for k, (col, label, colour, hatch) in enumerate(bars):
                ax.bar(x + (k - (len(bars) - 1) / 2) * w, np.clip(tab[col].to_numpy(float), -50, 100),
                       w, color=colour, label=label, hatch=hatch,
                       alpha=0.55 if hatch else 1.0, edgecolor="white" if hatch else None)
            ax.axhline(validation.threshold_pct, color="tab:red", ls="--", lw=0.9,
                       label=f"flag threshold {validation.threshold_pct:g} %")
            ax.set_xticks(x, [f"{a}\n({c})" for a, c in zip(tab.run_id, tab.controller)],
                          fontsize=7)
            ax.set_ylabel("Fit [%]")
            ax.set_ylim(min(0.0, float(np.nanmin(np.clip(tab[[b[0] for b in bars]].to_numpy(float),
                                                           -50, 100), initial=0.0)) - 5), 105)
            legend_outside(ax)
            ax.set_title("Measured vs simulated: fit % = 100 (1 - ||y - y_sim|| / ||y - mean y||)")
            fig.tight_layout()
            paths += save_figure(fig, out_dir, "validate_fit", formats=formats)
    return paths


def parts(results) -> list:
    """The figure's independent parts: each run's overlay (its index), then
    the fit % chart ("summary")."""
    v = results["validation"]
    return list(range(len(v.runs))) + ([] if v.table.empty else ["summary"])


def draw(results, folder: Path, *, formats: Sequence[str] = DEFAULT_FORMATS,
         part=None) -> list[Path]:
    """Closed-loop validation: the fit % per run (``validate_fit.<format>``)
    and measured vs simulated overlays, one per run (:func:`plot_overlay`);
    ``part`` (:func:`parts`): only that run's overlay or only the chart."""
    v, formats = results["validation"], check_formats(formats)
    if part is None:
        return plot_overlay(v, folder, formats=formats)
    if part == "summary":
        return plot_overlay(v, folder, formats=formats, runs=False)
    return plot_overlay_run(v.runs[int(part)], folder, formats=formats)


register_figure(Figure(
    name="validate_fit", needs=("validation",), draw=draw, parts=parts, order=40,
    imports=LOAD_LEVEL_IMPORTS,
    title="Closed-loop validation: measured vs simulated position control, fit % per run "
          "and overlays"))
