"""Fig. 4 of the paper: flow characterisation of the SEANV.

(a) flow rate vs cam angle per load level, both sides, with the fitted
eq. (5) curves; runs excluded by the filters drawn as grey markers, one
marker per reason. (b) sealing threshold angle vs pressure difference:
per-load theta_d (each load's own quadratic Q = alpha (theta - theta_d)^2,
at the load's median dp, +-1 standard error: the evidence, independent of
the joint fit's C) and the fitted eq. (3)+(4) interpolant, both sides. (A
threshold per run computed back from eq. 6 with the fitted C would lie on
the line by construction, so none is drawn.) Written in the formats asked
(PNG and SVG by default).
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ._style import DEFAULT_FORMATS, legend_outside, new_figure, save_figure
from .registry import Figure, register_figure

__all__ = ["plot_fig4", "draw_fig4", "draw"]

_EXCLUDED_STYLE = {  # reason -> (marker, label)
    "leakage": ("x", "excluded: leakage"),
    "friction": ("v", "excluded: friction"),
    "cam_range": ("s", "excluded: cam range"),
    "invalid": ("d", "excluded: invalid"),
}
_SIDE_STYLE = {"supply": ("o", "tab:red"), "drain": ("s", "tab:blue")}


def _load_colors(levels: np.ndarray):
    import matplotlib as mpl

    cmap = mpl.colormaps["viridis"]
    if levels.size <= 1:
        return {float(lv): cmap(0.2) for lv in levels}
    lo, hi = float(levels.min()), float(levels.max())
    return {float(lv): cmap(0.05 + 0.85 * (lv - lo) / (hi - lo)) for lv in levels}


def _pressure_path(rows, theta: np.ndarray):
    """(theta, p1, dp) along a load level's model curve: the runs' pressures
    (median per cam angle) interpolated in theta, since dp falls as the valve
    opens; the curve spans the runs' angles."""
    ok = np.isfinite(rows["p1_mpa"].to_numpy(float)) & np.isfinite(rows["dp_mpa"].to_numpy(float))
    r = rows[ok]
    med = r.assign(t=np.round(r["theta_deg"].to_numpy(float), 3)).groupby("t")[
        ["p1_mpa", "dp_mpa"]].median()
    t = med.index.to_numpy(float)
    th = theta[(theta >= t.min()) & (theta <= t.max())] if t.size > 1 else theta
    return (th, np.interp(th, t, med["p1_mpa"].to_numpy()),
            np.interp(th, t, med["dp_mpa"].to_numpy()))


def _panel_a(ax, fit) -> None:
    pr = fit.per_run
    if pr.empty:
        ax.text(0.5, 0.5, "no flow-step runs", ha="center", transform=ax.transAxes)
        return
    levels = np.unique(pr["load_level_mpag"].dropna().to_numpy(float))
    colors = _load_colors(levels)
    used = pr["used"].to_numpy(bool)
    lo, hi = fit.model.cam_min_deg, fit.model.cam_max_deg
    theta = np.linspace(lo, hi, 401)
    for side in fit.sides:
        marker, _ = _SIDE_STYLE[side]
        s_all = pr[pr["side"] == side]
        s_rows = s_all[used[(pr["side"] == side).to_numpy()]]
        for lv in levels:
            g = s_rows[s_rows["load_level_mpag"] == lv]
            if g.empty:
                continue
            ax.scatter(g["theta_deg"], g["q_mm3_s"], s=14, marker=marker, color=colors[lv],
                       edgecolor="none", alpha=0.85, zorder=3)
            if fit.sides[side].success:
                th, p1, dp = _pressure_path(s_all[s_all["load_level_mpag"] == lv], theta)
                ax.plot(th, fit.model.side(side).flow(th, p1, dp), color=colors[lv],
                        lw=1.2, zorder=2)
    excl = pr[~used]
    for reason, (marker, label) in _EXCLUDED_STYLE.items():
        g = excl[excl["excluded"] == reason]
        if g.empty:
            continue
        ax.scatter(g["theta_deg"], g["q_mm3_s"], s=14, marker=marker, color="0.55",
                   facecolor="none" if marker not in "x+" else "0.55", lw=0.8, zorder=1,
                   label=f"{label} ({len(g)})")
    ax.axhline(0.0, color="0.3", lw=0.6)
    ax.set_xlabel("Cam rotation angle [deg]")
    ax.set_ylabel("Flow rate [mm$^3$/s]")
    ax.set_title("(a) Flow rate vs cam angle", loc="left", fontsize=10)
    # legend: loads (colours), sides (markers), exclusions (grey)
    from matplotlib.lines import Line2D
    handles = [Line2D([], [], color=colors[lv], marker="o", lw=1.2, ms=4,
                      label=f"{lv:g} MPaG") for lv in levels]
    handles += [Line2D([], [], color="0.2", marker=_SIDE_STYLE[s][0], lw=0, ms=4,
                       label=f"{s} side") for s in fit.sides]
    h_ex, _ = ax.get_legend_handles_labels()
    ax.legend(handles=handles + h_ex, fontsize=7, ncol=1, loc="upper left",
              bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0, frameon=False,
              title="Load (model: lines)", title_fontsize=7)   # beside the axes, off the data
    ax.grid(True, lw=0.3, alpha=0.5)


def _panel_b(axes, fit) -> None:
    pl = fit.per_load
    pr = fit.per_run
    for (side, sf), ax in zip(fit.sides.items(), axes):
        marker, color = _SIDE_STYLE[side]
        g = pl[pl["side"] == side] if len(pl) else pl
        if len(g):
            ok = g["success"].to_numpy(bool)
            g = g[ok]
            yerr = g["theta_d_se_deg"].to_numpy(float)
            ax.errorbar(g["dp_mpa"], g["theta_d_deg"], yerr=np.where(np.isfinite(yerr), yerr, 0),
                        fmt=marker, color=color, ms=5, mfc="white", capsize=2, lw=0.8,
                        label=f"{side}: $\\theta_d$ of each load's own quadratic "
                              "($\\pm$1 s.e.)", zorder=3)
        rows = pr[(pr["side"] == side) & pr["used"].to_numpy(bool)]
        if not sf.success or rows.empty:
            continue
        dp_all = rows["dp_mpa"].to_numpy(float)
        dp = np.linspace(max(0.0, dp_all.min() - 0.2), dp_all.max() + 0.2, 200)
        if side == "supply":  # p1 = p_supply, held at its median
            p1 = np.full_like(dp, float(np.median(rows["p1_mpa"])))
        else:  # p1 = p_head = dp + p_tank
            p1 = dp + float(np.median(rows["p1_mpa"] - rows["dp_mpa"]))
        th = fit.model.side(side).threshold_deg(p1, dp)
        ax.plot(dp, th, color=color, lw=1.4, zorder=2,
                label=f"{side}: eq. (3)+(4), $z_0$ = {sf.z0_mm:.3f} mm")
    for side, ax in zip(fit.sides, axes):
        ax.set_ylabel(f"{side.capitalize()} threshold $\\theta_d$ [deg]")
        legend_outside(ax, fontsize=7, frameon=False)
        ax.grid(True, lw=0.3, alpha=0.5)
    axes[-1].set_xlabel("Pressure difference $\\Delta p$ [MPa]")
    axes[0].set_title("(b) Sealing threshold angle vs pressure difference", loc="left",
                      fontsize=10)


def draw_fig4(fit: Any, fig=None):
    """Draw Fig. 4 (a) and (b) of a :class:`~seanv_analysis.fit.FlowFit` into ``fig``.

    Parameters
    ----------
    fit : result of :func:`seanv_analysis.fit.fit_flow`
    fig : matplotlib Figure to draw into (empty, with constrained layout);
        default: a new 12.5 x 4.4 inch Agg figure

    Returns
    -------
    the matplotlib Figure, for showing in a notebook or saving
    """
    if fig is None:
        fig = new_figure(figsize=(12.5, 4.4), layout="constrained")
    grid = fig.add_gridspec(len(fit.sides), 2, width_ratios=[1.35, 1.0])
    ax_a = fig.add_subplot(grid[:, 0])
    axes_b = [fig.add_subplot(grid[i, 1]) for i in range(len(fit.sides))]
    for ax in axes_b[1:]:
        ax.sharex(axes_b[0])
    _panel_a(ax_a, fit)
    _panel_b(axes_b, fit)
    fig.suptitle("Flow characterisation of the SEANV (cf. paper Fig. 4)", fontsize=10)
    return fig


def plot_fig4(fit: Any, out_dir: str | Path, *, stem: str = "fig4", dpi: int = 200,
              formats: str | Sequence[str] = DEFAULT_FORMATS) -> list[Path]:
    """Draw Fig. 4 (a) and (b) of a :class:`~seanv_analysis.fit.FlowFit` and write it.

    Parameters
    ----------
    fit : result of :func:`seanv_analysis.fit.fit_flow`
    out_dir : folder for ``<stem>.<format>``
    stem : file name without suffix
    dpi : PNG resolution [dots/inch]
    formats : file formats to write, exactly these (default PNG and SVG)

    Returns
    -------
    list of the written paths, in the order of ``formats``. Uses matplotlib's
    object API with the Agg canvas (no display needed); files are written
    atomically.
    """
    return save_figure(draw_fig4(fit), out_dir, stem, formats=formats, dpi=dpi, tight=False)


def draw(results: Mapping[str, Any], folder: Path, *,
         formats: Sequence[str] = DEFAULT_FORMATS) -> list[Path]:
    """Registry entry: Fig. 4 of ``results["flowfit"]`` as ``folder/fig4.<format>``."""
    return plot_fig4(results["flowfit"], folder, formats=formats)


register_figure(Figure(
    name="fig4", number=4, needs=("flowfit",), draw=draw, order=10,
    title="Fig. 4: flow characterisation, flow rate vs cam angle and sealing threshold vs "
          "pressure difference"))
