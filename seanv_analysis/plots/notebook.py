"""Drawing a result on a user's axes: what ``result.plot(ax=None)`` calls
(through :mod:`seanv_analysis.plotting`).

The same panels as the saved figures, on an axes the caller owns; without
one, a new figure from ``matplotlib.pyplot`` (so a notebook shows it inline).
"""
from __future__ import annotations

from typing import Any

from ._style import legend_outside

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
        legend_outside(ax, fontsize=7, frameon=False)
    ax.grid(True, lw=0.3, alpha=0.5)
    return ax


def _tracking(tr, ax, panel: str = "b", run: str | None = None):
    from .fig7 import draw_flow_scatter, draw_flow_time, scatter_runs

    if panel == "a":
        r = next((r for r in tr.runs if run in (None, r.run_id)), None)
        if r is None:
            raise ValueError(f"run: {run!r} is not a tracked run; expected one of "
                             + ", ".join(x.run_id for x in tr.runs))
        ax = _axes(ax, figsize=(8.0, 3.2))
        draw_flow_time(ax, r)
        ax.set_title(f"(a) {r.run_id}", loc="left", fontsize=10)
        return ax
    if panel == "b":
        ax = _axes(ax, figsize=(5.0, 4.6))
        runs, which = scatter_runs(tr)
        draw_flow_scatter(ax, [r.data for r in runs], q_range=tr.range_mm3_s, lag_s=tr.shift_s,
                          rmse_mm3_s=tr.rmse_mm3_s)
        ax.set_title(f"(b) {which}\n" + ax.get_title(), fontsize=9)
        return ax
    raise ValueError(f"panel: expected 'a' (flows against time) or 'b' (actual vs target), "
                     f"got {panel!r}")


def _validation(val, ax, quantity: str = "position"):
    cols = {"position": ("position_mm", "position_sim_mm", "Position [mm]"),
            "flow": ("q_mm3_s", "q_sim_mm3_s", "Flow rate [mm$^3$/s]"),
            "cam": ("cam_deg", "cam_sim_deg", "Cam angle [deg]")}
    if quantity not in cols:
        raise ValueError(f"quantity: expected one of {', '.join(cols)}, got {quantity!r}")
    measured, simulated, label = cols[quantity]
    ax = _axes(ax, figsize=(8.0, 3.2 * max(1, len(val.runs))) if ax is None else ax)
    for r in val.runs:
        ov = r.overlay
        line, = ax.plot(ov["t_s"], ov[measured], lw=0.9, label=f"{r.run_id}: measured")
        ax.plot(ov["t_s"], ov[simulated], lw=0.9, ls="--", color=line.get_color(),
                label=f"{r.run_id}: simulated")
    ax.set_xlabel("Time [s]")
    ax.set_ylabel(label)
    legend_outside(ax, fontsize=7, frameon=False)
    ax.grid(True, lw=0.3, alpha=0.5)
    return ax


def _discovery(d, ax, variable: str = "run_index"):
    from ..discover import predict_static, residual_variables
    from .residuals import LABELS, residual_with_term

    if d.fit_data is None or d.base_fit is None:
        raise ValueError("this discovery had no flow-step runs: nothing to plot (its evidence "
                         "is the position-control check)")
    ax = _axes(ax)
    for part, data, marker in (("fit", d.fit_data, "o"), ("held-out", d.heldout_data, "s")):
        if data is None or len(data) == 0:
            continue
        x = residual_variables(d.base_model, data).get(variable)
        if x is None:
            raise ValueError(f"variable: {variable!r} is not a residual variable")
        before = data.q_mm3_s - predict_static(d.base_fit.model, data)
        after = data.q_mm3_s - predict_static(d.final_fit.model, data, d.final_fit.effects)
        ax.scatter(x, before, s=10, marker=marker, facecolors="none", edgecolors="0.6",
                   label=f"before ({part})")
        ax.scatter(x, after, s=10, marker=marker, label=f"after ({part})")
        with_term = residual_with_term(d, data)
        if with_term is not None:
            ax.scatter(x, with_term, s=12, marker="x", label=f"with the proposed term ({part})")
    ax.axhline(0.0, color="k", lw=0.8)
    ax.set_xlabel(LABELS.get(variable, variable.replace("_", " ")))
    ax.set_ylabel("Residual $Q - Q_{model}$ [mm$^3$/s]")
    legend_outside(ax, fontsize=7, frameon=False)
    ax.grid(True, lw=0.3, alpha=0.5)
    return ax


_PLOTS = {"FlowFit": _flowfit, "DatasetResult": _dataset, "Tracking": _tracking,
          "Validation": _validation, "Discovery": _discovery}


def plot(obj: Any, ax: Any = None, **kwargs: Any) -> Any:
    """Draw ``obj`` on ``ax``: a ``FlowFit`` (``panel='a'`` flow vs cam angle,
    ``'b'`` threshold vs dp), a ``DatasetResult`` (steady flow per run), a
    ``Tracking`` (``panel='b'`` actual vs target as Fig. 7(b), ``'a'`` flows
    against time of ``run``), a ``Validation`` (measured and simulated
    ``quantity``: position, flow or cam) or a ``Discovery`` (residual before
    and after against ``variable``)."""
    kind = type(obj).__name__
    if kind not in _PLOTS:
        raise TypeError(f"no plot for {kind}; expected one of {', '.join(_PLOTS)}")
    return _PLOTS[kind](obj, ax, **kwargs)
