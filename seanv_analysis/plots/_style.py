"""Shared look of the paper-style figures: rc settings, shading of load
periods, saving as PNG + SVG atomically."""
from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from ..io.atomic import atomic_path  # noqa: E402

__all__ = ["paper_style", "thin", "shade_high_load", "high_load_spans", "save_figure", "safe_name",
           "TARGET_COLOUR", "ACTUAL_COLOUR", "SIM_COLOUR", "SHADE_COLOUR"]

TARGET_COLOUR = "tab:red"
ACTUAL_COLOUR = "tab:blue"
SIM_COLOUR = "tab:orange"
SHADE_COLOUR = "0.88"

_RC = {"font.size": 8.5, "axes.titlesize": 9, "axes.labelsize": 8.5, "legend.fontsize": 7.5,
       "xtick.labelsize": 8, "ytick.labelsize": 8, "axes.grid": True, "grid.alpha": 0.3,
       "grid.linewidth": 0.5, "lines.linewidth": 1.0, "axes.linewidth": 0.7,
       "xtick.direction": "in", "ytick.direction": "in", "legend.frameon": True, "legend.framealpha": 0.85, "legend.edgecolor": "0.8",
       "svg.fonttype": "none", "savefig.dpi": 150}


@contextmanager
def paper_style() -> Iterator[None]:
    """Context with the figures' rc settings (compact, serif-free, inward ticks)."""
    with plt.rc_context(_RC):
        yield


def thin(n: int, *, max_points: int = 6000) -> slice:
    """Stride slice keeping at most ~``max_points`` of ``n`` samples (light figures)."""
    return slice(None, None, max(1, int(np.ceil(n / max_points))))


def high_load_spans(t_s, level_mpag, *, level: float | None = None) -> list[tuple[float, float]]:
    """Time spans [s] where ``level_mpag`` equals ``level`` (default: the
    highest level, when there are at least two levels)."""
    t = np.asarray(t_s, dtype=float)
    lv = np.asarray(level_mpag, dtype=float)
    finite = np.isfinite(lv)
    levels = np.unique(lv[finite])
    if level is None:
        if levels.size < 2:
            return []
        level = float(levels.max())
    m = finite & np.isclose(lv, level)
    if not m.any():
        return []
    edges = np.diff(np.concatenate(([0], m.astype(np.int8), [0])))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1
    return [(float(t[a]), float(t[b])) for a, b in zip(starts, ends)]


def shade_high_load(axes, spans, *, label: str | None = None) -> None:
    """Grey bands over ``spans`` on every axis (label on the first only)."""
    for i, ax in enumerate(np.atleast_1d(axes).ravel()):
        for j, (a, b) in enumerate(spans):
            ax.axvspan(a, b, color=SHADE_COLOUR, lw=0, zorder=0,
                       label=label if (i == 0 and j == 0) else None)


def safe_name(text: str) -> str:
    """``text`` reduced to characters safe in a file name."""
    return "".join(c if (c.isalnum() or c in "-_.") else "_" for c in str(text))


def save_figure(fig, out_dir: str | Path, stem: str, *, close: bool = True) -> list[Path]:
    """Save ``fig`` as ``<out_dir>/<stem>.png`` and ``.svg`` atomically."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for ext in ("png", "svg"):
        path = out / f"{stem}.{ext}"
        with atomic_path(path) as tmp:
            fig.savefig(tmp, format=ext, dpi=150, bbox_inches="tight")
        paths.append(path)
    if close:
        plt.close(fig)
    return paths
