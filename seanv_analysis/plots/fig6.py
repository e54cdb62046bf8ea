"""Fig. 6 of the paper: position control under load variation.

Stacked panels sharing the time axis: target and actual position [mm];
measured pressures (supply, head, load) [MPaG]; cam angle (command and
feedback, dashed black: servo neutral) [deg]; position error x_ref - x [mm]
(with the +-0.5 mm convergence band). Periods at the higher load level
(0.45 MPaG in the paper) are shaded and both loads named in the legend,
which sits beside the panels. The pipeline draws one figure per
position-control run (:func:`draw_run`); :func:`plot_fig6_dataset` puts
several runs side by side.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..io.names import safe_name
from ..signals.align import align_run
from ._style import (
    ACTUAL_COLOUR,
    DEFAULT_FORMATS,
    LOAD_LEVEL_IMPORTS,
    TARGET_COLOUR,
    align_ylabels,
    legend_outside,
    new_figure,
    paper_style,
    save_figure,
    shade_loads,
    trace,
)
from .registry import Figure, register_figure

__all__ = ["plot_fig6", "plot_fig6_dataset", "draw_fig6_column", "draw_run"]

_PANELS = 4


def _controller_label(run) -> str:
    c = run.meta.controller or {}
    if c.get("flow_model", True):
        return f"with flow model (Kp = {c.get('kp', '?')} mm$^3$/s/mm)"
    return f"without flow model (Kp = {c.get('kp', '?')} deg/mm)"


def draw_fig6_column(axes: Sequence, run, *, legend: bool = True) -> None:
    """Draw the four Fig. 6 panels of ``run`` on ``axes`` (4 axes, top to bottom)."""
    from ..analysis.tracking import load_levels_mpag

    a = align_run(run)   # every sample; each trace decimated to the pixels it fills
    t = a["t_s"].to_numpy(float)
    x = a["position_mm"].to_numpy(float)
    x_ref = a["x_ref_mm"].to_numpy(float) if "x_ref_mm" in a else np.full(t.size, np.nan)
    ax_x, ax_p, ax_c, ax_e = axes
    loads = (shade_loads(axes, t, load_levels_mpag(t, a["p_load_mpag"].to_numpy(float)))
             if "p_load_mpag" in a else [])
    ax_x.plot(*trace(t, x_ref), color=TARGET_COLOUR, ls="--", label="target $x_{ref}$",
              drawstyle="steps-post")
    ax_x.plot(*trace(t, x), color=ACTUAL_COLOUR, label="actual $x$")
    ax_x.set_ylabel("Position [mm]")
    for col, colour, label in (("p_supply_mpag", "tab:green", "supply $p_s$"),
                               ("p_head_mpag", "tab:purple", "head $p_h$"),
                               ("p_load_mpag", "tab:brown", "load $p_l$")):
        if col in a:
            ax_p.plot(*trace(t, a[col].to_numpy(float)), color=colour, lw=0.7, label=label)
    ax_p.set_ylabel("Pressure [MPaG]")
    if "cam_cmd_deg" in a:
        ax_c.plot(*trace(t, a["cam_cmd_deg"].to_numpy(float)), color=TARGET_COLOUR, lw=0.8,
                  label=r"command $\theta_{cmd}$", drawstyle="steps-post")
    if "cam_deg" in a and np.isfinite(a["cam_deg"].to_numpy(float)).any():
        ax_c.plot(*trace(t, a["cam_deg"].to_numpy(float)), color=ACTUAL_COLOUR, lw=0.8,
                  label=r"measured $\theta$")
    neutral = float(run.rig["servo"]["neutral_deg"])
    ax_c.axhline(neutral, color="k", ls="--", lw=0.9, label=f"neutral ({neutral:g} deg)")
    ax_c.set_ylabel("Cam angle [deg]")
    band = float(run.rig["controller"]["convergence_band_mm"])
    ax_e.plot(*trace(t, x_ref - x), color="k", lw=0.8, label="error $e = x_{ref} - x$")
    ax_e.axhspan(-band, band, color="tab:green", alpha=0.15, lw=0, label=f"$\\pm${band:g} mm")
    ax_e.set_ylabel("Error [mm]")
    ax_e.set_xlabel("Time [s]")
    ax_e.set_xlim(t[0], t[-1])
    if legend:
        for i, ax in enumerate(axes):   # beside the panel, never over the traces
            legend_outside(ax, extra=loads if i == 0 else ())


def plot_fig6(run, out_dir: str | Path, *, stem: str | None = None,
              formats: str | Sequence[str] = DEFAULT_FORMATS) -> list[Path]:
    """Fig. 6 style figure of one position_control run.

    Parameters
    ----------
    run : a position_control :class:`~seanv_analysis.io.Run`; the servo
        neutral [deg] and convergence band [mm] come from its ``run.rig``
    out_dir : output folder
    stem : file name without extension (default ``fig6_<run_id>``)
    formats : file formats to write, exactly these (default PNG and SVG)

    Returns
    -------
    list of the written paths
    """
    with paper_style():
        fig = new_figure(figsize=(8.4, 7.2))
        axes = fig.subplots(_PANELS, 1, sharex=True)
        draw_fig6_column(axes, run)
        axes[0].set_title(f"{run.run_id}: position control {_controller_label(run)}")
        align_ylabels(axes)
        fig.tight_layout(h_pad=0.4)   # room for the legends beside: no tight crop needed
        return save_figure(fig, out_dir, stem or f"fig6_{safe_name(run.run_id)}", formats=formats,
                           tight=False)


def plot_fig6_dataset(runs: Sequence, out_dir: str | Path, *, stem: str = "fig6",
                      max_runs: int = 4, formats: str | Sequence[str] = DEFAULT_FORMATS
                      ) -> list[Path]:
    """Fig. 6 style figure of several runs side by side (one column per run,
    e.g. (a) without and (b) with the flow model), in ``formats``; at most
    ``max_runs`` position_control runs. None written when there is none."""
    runs = [r for r in runs if r.meta.kind == "position_control"][:max_runs]
    if not runs:
        return []
    with paper_style():
        fig = new_figure(figsize=(4.6 * len(runs) + 2.0, 7.2))
        axes = fig.subplots(_PANELS, len(runs), sharex="col", squeeze=False)
        for j, run in enumerate(runs):
            draw_fig6_column(axes[:, j], run, legend=(j == len(runs) - 1))
            axes[0, j].set_title(f"({chr(97 + j)}) {run.run_id}\n{_controller_label(run)}")
        align_ylabels(axes)
        fig.tight_layout(h_pad=0.4)
        return save_figure(fig, out_dir, stem, formats=formats, tight=False)


def draw_runs(results: Mapping[str, Any], folder: Path, *,
              formats: Sequence[str] = DEFAULT_FORMATS) -> list[Path]:
    """Registry entry: the position-control runs side by side as
    ``folder/fig6.<format>``, the paper's order: (a) without, (b) with the flow model."""
    runs = sorted(results["position_runs"],
                  key=lambda r: bool((r.meta.controller or {}).get("flow_model", True)))
    return plot_fig6_dataset(runs, folder, formats=formats)


def draw_run(run, folder: Path, *, formats: Sequence[str] = DEFAULT_FORMATS,
             rig: Any = None) -> list[Path]:
    """Registry entry: Fig. 6 of one position-control run as
    ``folder/fig6_<run_id>.<format>``.

    ``rig`` (the pipeline's rig config) is not needed: the run carries its
    own, with the run's overrides applied, which is what the rig ran with.
    """
    return plot_fig6(run, folder, formats=formats)


register_figure(Figure(
    name="fig6", number=6, needs=("runs",), per_run=True, run_kind="position_control",
    draw_run=draw_run, shown_with=("tracking",), order=20, imports=LOAD_LEVEL_IMPORTS,
    title="Fig. 6: position control under load variation, one figure per run"))
register_figure(Figure(
    name="fig6_runs", needs=("position_runs",), draw=draw_runs, shown_with=("tracking",), order=21,
    imports=LOAD_LEVEL_IMPORTS,
    title="Fig. 6: the position-control runs side by side, (a) without and (b) with the flow "
          "model"))
