"""Drawing a result on a user's axes: what ``result.plot(ax=None)`` calls
(through :mod:`seanv_analysis.plotting`).

The same panels as the saved figures, on an axes the caller owns; without
one, a new figure from ``matplotlib.pyplot`` (so a notebook shows it inline).
"""
from __future__ import annotations

from typing import Any

__all__ = ["plot"]


def _axes(ax, figsize=(6.4, 4.2)):
    if ax is not None:
        return ax
    import matplotlib.pyplot as plt

    return plt.subplots(figsize=figsize, layout="constrained")[1]


def _flowfit(fit, ax, panel: str = "a"):
    from .fig4 import _panel_a, _panel_b

    if panel == "a":
        ax = _axes(ax)
        _panel_a(ax, fit)
        return ax
    if panel == "b":
        if ax is None:
            import matplotlib.pyplot as plt

            _, axes = plt.subplots(len(fit.sides), 1, figsize=(6.4, 3.0 * len(fit.sides)),
                                   sharex=True, layout="constrained", squeeze=False)
            axes = list(axes[:, 0])
        else:
            axes = list(ax) if isinstance(ax, (list, tuple)) else [ax] * len(fit.sides)
        _panel_b(axes, fit)
        return axes if len(axes) > 1 else axes[0]
    raise ValueError(f"panel: expected 'a' (flow vs cam angle) or 'b' (threshold vs dp), "
                     f"got {panel!r}")


def _dataset(ds, ax):
    ax = _axes(ax)
    s = ds.summary
    steps = s[s["kind"] == "flow_step"]
    for side, marker, color in (("supply", "o", "tab:red"), ("drain", "s", "tab:blue")):
        g = steps[steps["side"] == side]
        if g.empty:
            continue
        used = (g["excluded"].fillna("") == "").to_numpy(bool)
        ax.scatter(g["cam_deg"][used], g["q_mm3_s"][used], s=12, marker=marker, color=color,
                   label=f"{side} ({int(used.sum())} used)")
        if (~used).any():
            ax.scatter(g["cam_deg"][~used], g["q_mm3_s"][~used], s=12, marker=marker,
                       facecolor="none", edgecolor="0.5",
                       label=f"{side} excluded ({int((~used).sum())})")
    ax.axhline(0.0, color="0.3", lw=0.6)
    ax.set_xlabel("Commanded cam angle [deg]")
    ax.set_ylabel("Steady flow rate [mm$^3$/s]")
    ax.set_title(f"{ds.runs_read} runs read"
                 + (f", {len(ds.failed)} bad" if ds.failed else ""), loc="left", fontsize=10)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=7, frameon=False)
    ax.grid(True, lw=0.3, alpha=0.5)
    return ax


def plot(obj: Any, ax: Any = None, **kwargs: Any) -> Any:
    """Draw ``obj`` (a ``FlowFit``: ``panel='a'`` flow vs cam angle, ``'b'``
    threshold vs dp; a ``DatasetResult``: steady flow per run) on ``ax``."""
    kind = type(obj).__name__
    if kind == "FlowFit":
        return _flowfit(obj, ax, **kwargs)
    if kind == "DatasetResult":
        return _dataset(obj, ax, **kwargs)
    raise TypeError(f"no plot for {kind}; expected a FlowFit or a DatasetResult")
