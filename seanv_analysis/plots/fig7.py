"""Fig. 7 of the paper: flow control performance during position control.

(a) target Q_ref and actual Q flow against time [mm^3/s] (the higher
load's periods shaded, both loads named); (b) actual flow shifted earlier by the delay against the
target, with the identity line (solid inside the fitting range, dashed
outside), the range bounds and the RMSE in the title. One figure for the
data set (``fig7``) and one per run (``fig7_<run_id>``).
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..io.names import safe_name
from ._style import (
    ACTUAL_COLOUR,
    DEFAULT_FORMATS,
    TARGET_COLOUR,
    legend_outside,
    new_figure,
    paper_style,
    save_figure,
    shade_loads,
    trace,
)
from .registry import Figure, register_figure

__all__ = ["plot_fig7", "plot_fig7_run", "draw_flow_time", "draw_flow_scatter", "draw", "parts",
           "scatter_runs"]

_K = 1e-3  # axes in 10^3 mm^3/s, as the paper


#: how each target source is labelled: only a logged Q_ref is the controller's own
TARGET_LABELS = {"q_ref": "target $Q_{ref}$ (logged)",
                 "kp_error": "target $Q_{ref} = K_p e$ (from the logged error)",
                 "model": "$Q_{ref}$ implied by the flow model (not commanded)"}


def scatter_runs(tracking) -> tuple[list, str]:
    """The runs of panel (b) and how to say it: the runs the tracking
    headline pools (``tracking.pooled_runs``: those with a commanded Q_ref,
    as the paper's Fig. 7(b); all runs when none had one), so the panel's
    RMSE is the headline's."""
    pooled = set(tracking.pooled_runs)
    return [r for r in tracking.runs if r.run_id in pooled], tracking.pooled


def draw_flow_time(ax, run_tracking, *, shifted: bool = False, legend: bool = True) -> None:
    """Panel (a): target and actual flow [10^3 mm^3/s] against time [s]."""
    d = run_tracking.data   # every sample; each trace decimated to the pixels it fills
    t = d["t_s"].to_numpy(float)
    loads = shade_loads(ax, t, d["load_level_mpag"].to_numpy(float))
    ax.plot(*trace(t, d["q_ref_mm3_s"].to_numpy(float) * _K), color=TARGET_COLOUR, lw=0.9,
            drawstyle="steps-post",
            label=TARGET_LABELS.get(run_tracking.target_source, "target $Q_{ref}$"),
            ls="-" if run_tracking.target_source == "q_ref" else "--")
    ax.plot(*trace(t, d["q_mm3_s"].to_numpy(float) * _K), color=ACTUAL_COLOUR, lw=0.8,
            label="actual $Q$")
    if shifted:
        ax.plot(*trace(t, d["q_shifted_mm3_s"].to_numpy(float) * _K), color="tab:cyan", lw=0.7,
                label=f"actual shifted by -{run_tracking.shift_s:.3g} s")
    ax.set_xlabel("Time [s]")
    ax.set_ylabel("Flow rate [$10^3$ mm$^3$/s]")
    ax.set_xlim(t[0], t[-1])
    if legend:
        legend_outside(ax, extra=loads)


def draw_flow_scatter(ax, datas, *, q_range, lag_s: float, rmse_mm3_s: float) -> None:
    """Panel (b): shifted actual against target [10^3 mm^3/s] for the data
    frames ``datas`` (RunTracking.data), coloured by side and range."""
    lo, hi = q_range
    q = np.concatenate([d["q_ref_mm3_s"].to_numpy(float) for d in datas]) * _K
    a = np.concatenate([d["q_shifted_mm3_s"].to_numpy(float) for d in datas]) * _K
    ok = np.isfinite(q) & np.isfinite(a)
    q, a = q[ok], a[ok]
    inside = (q >= lo * _K) & (q <= hi * _K)
    step = max(1, q.size // 20000)  # keep the SVG light
    ax.scatter(q[~inside][::step], a[~inside][::step], s=2, color="0.65", lw=0, alpha=0.5,
               label="outside range", rasterized=True)
    sup = inside & (q >= 0)
    ax.scatter(q[sup][::step], a[sup][::step], s=2, color="tab:red", lw=0, alpha=0.35,
               label="supply ($Q_{ref} \\geq 0$)", rasterized=True)
    dr = inside & (q < 0)
    ax.scatter(q[dr][::step], a[dr][::step], s=2, color="tab:blue", lw=0, alpha=0.35,
               label="drain ($Q_{ref} < 0$)", rasterized=True)
    if all("after_change" in d for d in datas):
        ac = np.concatenate([d["after_change"].to_numpy(bool) for d in datas])[ok]
        ax.scatter(q[ac][::step], a[ac][::step], s=3, color="tab:orange", lw=0, alpha=0.6,
                   label=f"$\\leq${lag_s:.3g} s after a reference/load change",
                   rasterized=True)
    span = [min(np.min(q, initial=lo * _K), lo * _K), max(np.max(q, initial=hi * _K), hi * _K)]
    ax.plot(span, span, color="k", lw=0.8, ls="--")
    ax.plot([lo * _K, hi * _K], [lo * _K, hi * _K], color="k", lw=1.4,
            label="$Q = Q_{ref}$ (fitting range)")
    for b in (lo, hi):
        ax.axvline(b * _K, color="k", lw=0.6, ls=":")
    ax.set_xlabel("Target flow rate $Q_{ref}$ [$10^3$ mm$^3$/s]")
    ax.set_ylabel(f"Actual flow rate $Q(t + {lag_s:.3g}$ s) [$10^3$ mm$^3$/s]")
    ax.set_title(f"RMSE {rmse_mm3_s * _K:.3f} $\\times 10^3$ mm$^3$/s in "
                 f"[{lo * _K:g}, {hi * _K:g}] $\\times 10^3$")
    legend_outside(ax, markerscale=4)


def plot_fig7_run(tracking, run_tracking, out_dir: str | Path, *, stem: str | None = None,
                  formats: str | Sequence[str] = DEFAULT_FORMATS) -> list[Path]:
    """Fig. 7 of one run: (a) flows against time, (b) shifted actual vs target,
    written in ``formats`` as ``<stem>.<format>`` (default stem ``fig7_<run_id>``)."""
    with paper_style():
        fig = new_figure(figsize=(12.5, 3.8))
        ax_a, ax_b = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1.6, 1]})
        draw_flow_time(ax_a, run_tracking)
        ax_a.set_title(f"(a) {run_tracking.run_id}: target and actual flow rate")
        draw_flow_scatter(ax_b, [run_tracking.data], q_range=tracking.range_mm3_s,
                          lag_s=run_tracking.shift_s, rmse_mm3_s=run_tracking.rmse_mm3_s)
        ax_b.set_title(f"(b) shifted {run_tracking.shift_s:.3g} s; " + ax_b.get_title())
        fig.tight_layout()
        return save_figure(fig, out_dir, stem or f"fig7_{safe_name(run_tracking.run_id)}",
                           tight=False,
                           formats=formats)


def plot_fig7(tracking, out_dir: str | Path, *, stem: str = "fig7", per_run: bool = True,
              max_runs: int = 4, formats: str | Sequence[str] = DEFAULT_FORMATS) -> list[Path]:
    """Fig. 7 for a data set, and per run when ``per_run``.

    The data-set figure has (a) one time panel per run (up to ``max_runs``;
    the run with a logged Q_ref first; a target only implied by the flow
    model is dashed and labelled so) and (b) the scatter of the runs the
    tracking headline pools (those with a commanded Q_ref, the paper's
    Fig. 7(b); :func:`scatter_runs`), titled with the headline RMSE.

    Parameters
    ----------
    tracking : :class:`~seanv_analysis.analysis.tracking.Tracking`
    out_dir : output folder
    stem : data-set figure's file name without extension
    per_run : also write ``fig7_<run_id>.<format>`` per run
    max_runs : time panels in the data-set figure
    formats : file formats to write, exactly these (default PNG and SVG)

    Returns
    -------
    list of the written paths
    """
    paths: list[Path] = []
    if not tracking.runs:
        return paths
    # the paper's run (logged Q_ref) first: panel (a); the others (a2), (a3), ...
    ordered = sorted(tracking.runs, key=lambda r: r.target_source != "q_ref")
    shown = ordered[:max_runs]
    in_b, which = scatter_runs(tracking)
    with paper_style():
        fig = new_figure(figsize=(13.0, max(3.8, 2.6 * len(shown))))
        gs = fig.add_gridspec(len(shown), 2, width_ratios=[1.6, 1])
        for i, r in enumerate(shown):
            ax = fig.add_subplot(gs[i, 0])
            draw_flow_time(ax, r, legend=(i == 0))  # one legend: it would cover the others' data
            label = "(a)" if i == 0 else f"(a{i + 1})"
            target = "" if i == 0 and r.target_source == "q_ref" else \
                f"\nred dashed: {TARGET_LABELS.get(r.target_source, 'target')}"
            ax.set_title(f"{label} {r.run_id}{target}", loc="left")
            if i < len(shown) - 1:
                ax.set_xlabel("")
        ax_b = fig.add_subplot(gs[:, 1])
        draw_flow_scatter(ax_b, [r.data for r in in_b], q_range=tracking.range_mm3_s,
                          lag_s=tracking.shift_s, rmse_mm3_s=tracking.rmse_mm3_s)
        ax_b.set_title(f"(b) {which}, shift {tracking.shift_s:.3g} s ({tracking.shift_source})\n"
                       + ax_b.get_title())
        fig.tight_layout()
        paths += save_figure(fig, out_dir, stem, formats=formats, tight=False)
    if per_run:
        for r in tracking.runs:
            paths += plot_fig7_run(tracking, r, out_dir, formats=formats)
    return paths


def parts(results: Mapping[str, Any]) -> list:
    """The figure's independent parts: the data set's ("dataset"), then each
    run's (its index in the tracking's runs)."""
    return ["dataset"] + list(range(len(results["tracking"].runs)))


def draw(results: Mapping[str, Any], folder: Path, *,
         formats: Sequence[str] = DEFAULT_FORMATS, part=None) -> list[Path]:
    """Registry entry: Fig. 7 of ``results["tracking"]``, the data set
    (``folder/fig7.<format>``) and each run (``folder/fig7_<run_id>.<format>``);
    ``part`` (:func:`parts`): only the data set's or only that run's."""
    tracking = results["tracking"]
    if part is None:
        return plot_fig7(tracking, folder, formats=formats)
    if part == "dataset":
        return plot_fig7(tracking, folder, formats=formats, per_run=False)
    return plot_fig7_run(tracking, tracking.runs[int(part)], folder, formats=formats)


register_figure(Figure(
    name="fig7", number=7, needs=("tracking",), draw=draw, parts=parts, order=30,
    title="Fig. 7: flow tracking, target vs actual flow (delay-shifted), all runs and per run"))
