"""Shared look of the paper-style figures: rc settings, shading of load
periods, new Agg figures and saving them atomically in the formats asked.

matplotlib is imported inside the functions that draw, so importing the
figure modules (and the registry) costs nothing until a figure is drawn.
Figures are built with :class:`matplotlib.figure.Figure` on an Agg canvas,
not through pyplot: no backend is selected, no GUI window can open, and
figures drawn in worker threads do not share pyplot's global state.
"""
from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from ..io.atomic import atomic_path


def _forget_fonts_after_fork() -> None:
    """In a forked child: drop the parsed math-text labels, which hold the
    parent's open FreeType faces (matplotlib drops its font cache itself,
    not these, and the wider cache of :func:`_widen_mathtext_cache` kept
    them across every fork). Sibling workers drawing with one inherited
    face read its file through one shared offset: 'FT_Load_Glyph ...
    invalid outline' / 'too many hints' on a worker, in 1 to 4 of 5 runs of
    tests/test_figures_parallel.py."""
    import sys

    mathtext = sys.modules.get("matplotlib.mathtext")
    clear = getattr(getattr(mathtext, "MathTextParser", None), "_parse_cached", None)
    if clear is not None and hasattr(clear, "cache_clear"):
        clear.cache_clear()      # matplotlib's lru cache, or the wider one here


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_fonts_after_fork)

__all__ = ["paper_style", "warm_up", "trace", "TRACE_PIXELS", "align_ylabels", "shade_high_load",
           "shade_loads", "high_load_spans", "LOAD_LEVEL_IMPORTS",
           "legend_outside", "new_figure", "check_formats", "save_figure", "DEFAULT_FORMATS",
           "TARGET_COLOUR", "ACTUAL_COLOUR", "SIM_COLOUR", "SHADE_COLOUR"]

TARGET_COLOUR = "tab:red"
ACTUAL_COLOUR = "tab:blue"
SIM_COLOUR = "tab:orange"
SHADE_COLOUR = "0.88"
#: file formats written when none are asked for
DEFAULT_FORMATS: tuple[str, ...] = ("png", "svg")

_RC = {"font.size": 8.5, "axes.titlesize": 9, "axes.labelsize": 8.5, "legend.fontsize": 7.5,
       "xtick.labelsize": 8, "ytick.labelsize": 8, "axes.grid": True, "grid.alpha": 0.3,
       "grid.linewidth": 0.5, "lines.linewidth": 1.0, "axes.linewidth": 0.7,
       "xtick.direction": "in", "ytick.direction": "in", "legend.frameon": True,
       "legend.framealpha": 0.85, "legend.edgecolor": "0.8",
       "svg.fonttype": "none", "savefig.dpi": 150,
       "svg.hashsalt": "seanv-analysis"}  # fixed ids: the same figure gives the same SVG bytes
#: file metadata per format: no creation date, so equal figures are equal files
_METADATA: dict[str, dict[str, Any]] = {"svg": {"Date": None}, "pdf": {"CreationDate": None},
                                        "ps": {"CreationDate": None}}


@contextmanager
def paper_style() -> Iterator[None]:
    """Context with the figures' rc settings (compact, serif-free, inward ticks).

    Create, draw and save the figure inside it: rc settings are read when
    artists are made and when the file is written.
    """
    import matplotlib

    _widen_mathtext_cache()
    with matplotlib.rc_context(_RC):
        yield


#: parsed math labels kept (matplotlib keeps 50)
MATHTEXT_CACHE = 1024


def _widen_mathtext_cache() -> None:
    """Keep more parsed math labels (``$\\theta_d$``, ``mm$^3$/s``) than
    matplotlib's 50 (pyparsing, ~12 ms a parse), shared by all renderers.

    matplotlib caches a parse per parser instance (``self`` is part of its
    lru key), and every renderer makes its own parser: each file saved and
    each tight box measured parsed every label again (the golden data set's
    Fig. 4, 6 and 7: 338 parses of 116 distinct labels). The parse depends
    on the instance only through its output type (vector or raster), so the
    cache here is keyed on that, and holds ``MATHTEXT_CACHE`` labels (a
    label is still parsed per size and resolution). ``_parse_cached`` is
    matplotlib's private lru cache; where a release has none, or its parser
    has no ``_output_type``, nothing changes.
    """
    import functools

    from matplotlib import mathtext

    cached = getattr(mathtext.MathTextParser, "_parse_cached", None)
    parse = getattr(cached, "__wrapped__", None)
    if parse is None:       # no lru cache in this release, or replaced here already
        return
    parsers = {"vector": mathtext.MathTextParser("path"), "raster": mathtext.MathTextParser("agg")}
    if not all(hasattr(p, "_output_type") for p in parsers.values()):
        return

    @functools.lru_cache(MATHTEXT_CACHE)
    def by_output_type(output_type, s, dpi, prop, antialiased, load_glyph_flags):
        return parse(parsers[output_type], s, dpi, prop, antialiased, load_glyph_flags)

    def shared(self, s, dpi, prop, antialiased, load_glyph_flags):
        return by_output_type(self._output_type, s, dpi, prop, antialiased, load_glyph_flags)

    shared.cache_info = by_output_type.cache_info
    shared.cache_clear = by_output_type.cache_clear    # (a forked child: see below)
    mathtext.MathTextParser._parse_cached = shared


def new_figure(**kwargs: Any):
    """A :class:`matplotlib.figure.Figure` attached to an Agg canvas.

    ``kwargs`` go to ``Figure`` (``figsize`` [inch], ``layout``, ...).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(**kwargs)
    FigureCanvasAgg(fig)
    return fig


def warm_up() -> None:
    """Pay a process's first-figure costs now (import matplotlib, load the
    fonts, build the math-text parser, lay out and render a small figure
    with the paper's style in both formats, in memory): what a worker
    process runs while the analysis goes on (:meth:`Executor.warm
    <seanv_analysis.batch.executor.Executor.warm>`), so the figures it
    draws later cost only themselves. Writes nothing."""
    import io

    with paper_style():
        fig = new_figure(figsize=(3.0, 2.0), layout="constrained")
        ax = fig.add_subplot()
        ax.plot([0.0, 1.0], [0.0, 1.0], label="$Q_{ref}$ [mm$^3$/s]")
        ax.set_xlabel(r"$\theta$ [deg]")
        legend_outside(ax)
        for ext in DEFAULT_FORMATS:
            fig.savefig(io.BytesIO(), format=ext, metadata=_METADATA.get(ext))


#: pixel columns a time trace is decimated to (:func:`trace`): a little more
#: than the widest time axis fills (13 inch x 150 dpi x ~0.6 of the width)
TRACE_PIXELS = 1500


def trace(t_s, y, *, pixels: int = TRACE_PIXELS) -> tuple[np.ndarray, np.ndarray]:
    """``(t_s, y)`` decimated to about the ``pixels`` columns a time axis
    fills: per column (equal spans of time), the first and last sample and
    the lowest and highest value of ``y``, in time order, so every peak,
    step edge and gap (NaN) a full line would show still shows, and a
    figure's cost does not grow with the samples. Traces of up to 4
    samples per column are returned whole.

    Parameters
    ----------
    t_s : time [s], non-decreasing
    y : values of any unit, one per time
    pixels : pixel columns of the time axis

    Returns
    -------
    (t_s, y) at the kept samples, at most ``4 pixels`` of them
    """
    t = np.asarray(t_s, dtype=float)
    v = np.asarray(y, dtype=float)
    n = t.size
    if n <= 4 * pixels or not (np.isfinite(t[0]) and np.isfinite(t[-1]) and t[-1] > t[0]):
        return t, v
    col = np.minimum(((t - t[0]) * (pixels / (t[-1] - t[0]))).astype(np.int64), pixels - 1)
    starts = np.flatnonzero(np.diff(col, prepend=-1))     # first sample of each column
    ends = np.append(starts[1:], n) - 1
    keep = [starts, ends]
    finite = np.isfinite(v)
    if finite.any():
        for reduce, fill in ((np.fmin, np.inf), (np.fmax, -np.inf)):
            extreme = reduce.reduceat(np.where(finite, v, fill), starts)
            hit = finite & (v == np.repeat(extreme, ends - starts + 1))
            where = np.flatnonzero(hit)
            keep.append(where[np.unique(col[where], return_index=True)[1]])   # first per column
    # a gap (NaN) between finite samples stays a gap: its first sample is kept
    gaps = np.flatnonzero(~finite[1:] & finite[:-1]) + 1
    idx = np.unique(np.concatenate([*keep, gaps]))
    return t[idx], v[idx]


def high_load_spans(t_s, level_mpag, *, level: float | None = None) -> list[tuple[float, float]]:
    """Time spans [s] where ``level_mpag`` [MPaG] equals ``level`` (default:
    the highest level, when there are at least two levels)."""
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
    """Grey bands over ``spans`` (time [s]) on every axis (label on the first only)."""
    for i, ax in enumerate(np.atleast_1d(axes).ravel()):
        for j, (a, b) in enumerate(spans):
            ax.axvspan(a, b, color=SHADE_COLOUR, lw=0, zorder=0,
                       label=label if (i == 0 and j == 0) else None)


#: what the figures that shade load levels import when they first draw
#: (:func:`seanv_analysis.analysis.tracking.load_levels_mpag` and its running
#: median): their registry entries' ``imports``, paid while a worker warms up
LOAD_LEVEL_IMPORTS = ("seanv_analysis.analysis.tracking", "scipy.ndimage")


def shade_loads(axes, t_s, level_mpag) -> list:
    """Shade the periods at the highest load level on every axis and name
    each level once (the paper's Fig. 7: "shaded regions correspond to a
    0.45 MPaG load"): the band is labelled ``load 0.45 MPaG (shaded)`` on
    the first axis, and a legend entry ``load 0.35 MPaG`` (unshaded) is
    returned for the other levels, to pass to :func:`legend_outside` as
    ``extra``. Nothing is shaded with fewer than two levels.

    Parameters
    ----------
    axes : an axis or several sharing the time axis
    t_s : time [s]; level_mpag : load level of each sample [MPaG]
        (:func:`seanv_analysis.analysis.tracking.load_levels_mpag`)
    """
    from matplotlib.patches import Patch

    lv = np.asarray(level_mpag, dtype=float)
    levels = np.unique(lv[np.isfinite(lv)])
    if levels.size < 2:
        return []
    hi = float(levels.max())
    shade_high_load(axes, high_load_spans(t_s, lv, level=hi), label=f"load {hi:g} MPaG (shaded)")
    others = ", ".join(f"{v:g}" for v in levels[:-1])
    return [Patch(facecolor="white", edgecolor="0.6", lw=0.6, label=f"load {others} MPaG")]


def legend_outside(ax, *, extra: Sequence = (), **kwargs):
    """The axis' legend beside it, right of the axes and never over the data
    (its handles and labels, then ``extra`` handles such as the unshaded load
    of :func:`shade_loads`); the figure's layout (tight or constrained)
    makes room for it. Returns the legend, or None when there is nothing to list."""
    handles, labels = ax.get_legend_handles_labels()
    # the extra entries (the unshaded load) right after the shaded load's, if any
    at = next((i + 1 for i, lab in enumerate(labels) if lab.startswith("load ")), len(labels))
    handles = [*handles[:at], *extra, *handles[at:]]
    labels = [*labels[:at], *(h.get_label() for h in extra), *labels[at:]]
    if not handles:
        return None
    opts = {"loc": "upper left", "bbox_to_anchor": (1.01, 1.0), "borderaxespad": 0.0, **kwargs}
    return ax.legend(handles, labels, **opts)


#: where :func:`align_ylabels` puts the y labels: left of the axes [axes fraction]
YLABEL_X = -0.075


def align_ylabels(axes, *, x: float = YLABEL_X) -> None:
    """The y labels of stacked axes at one distance ``x`` [axes fraction]
    left of their axes, in line: what ``Figure.align_ylabels`` does, without
    its cost (it measures every sibling's tick labels at each draw: 1.9 s
    of Fig. 6's 6.4 s). The distance leaves room for tick labels such as
    "-40" at the figures' sizes."""
    for ax in np.atleast_1d(axes).ravel():
        ax.yaxis.set_label_coords(x, 0.5)


def check_formats(formats: str | Sequence[str]) -> tuple[str, ...]:
    """``formats`` as a tuple of file suffixes without dot ('png', 'svg', ...).

    A single string is one format. Raises ValueError when none is given or
    one is not a plain suffix.
    """
    out = (formats,) if isinstance(formats, str) else tuple(formats)
    if not out:
        raise ValueError("formats: expected at least one file format such as 'png' or 'svg', got none")
    bad = [f for f in out if not isinstance(f, str) or not f.isalnum()]
    if bad:
        raise ValueError(f"formats: {bad[0]!r} is not a file format; expected e.g. 'png' or 'svg'")
    return tuple(f.lower() for f in out)


def _fix_svg_ids() -> None:
    """Fixed SVG ids (``svg.hashsalt``), also for figures saved outside
    :func:`paper_style`. Set once for the process when nobody chose a salt
    (ids stay unique within a file; only their randomness across files goes),
    so threads saving figures never race on a temporary rc setting."""
    import matplotlib

    if matplotlib.rcParams["svg.hashsalt"] is None:
        matplotlib.rcParams["svg.hashsalt"] = _RC["svg.hashsalt"]


def save_figure(fig, out_dir: str | Path, stem: str, *, formats: str | Sequence[str] = DEFAULT_FORMATS,
                dpi: float = 150, tight: bool = True) -> list[Path]:
    """Write ``fig`` as ``<out_dir>/<stem>.<format>`` for each of ``formats``, atomically.

    Parameters
    ----------
    fig : matplotlib Figure
    out_dir : folder, created when missing
    stem : file name without suffix
    formats : file formats, exactly those are written (default PNG and SVG)
    dpi : raster resolution [dots/inch] (PNG)
    tight : crop to the drawn content (``bbox_inches="tight"``); off for
        figures laid out by matplotlib's constrained layout

    Returns
    -------
    the written paths, in the order of ``formats``; the same figure gives
    the same bytes (SVG: fixed ids, no date; PNG holds no date)
    """
    formats = check_formats(formats)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    engine, drawn = _solve_layout_once(fig)
    bbox = _tight_bbox(fig, drawn=drawn) if tight else None
    paths = []
    try:
        for ext in formats:
            path = out / f"{stem}.{ext}"
            if ext == "svg":
                _fix_svg_ids()
            with atomic_path(path) as tmp:
                fig.savefig(tmp, format=ext, dpi=dpi, bbox_inches=bbox,
                            metadata=_METADATA.get(ext))
            paths.append(path)
    finally:
        if engine is not None:
            fig.set_layout_engine(engine)
    return paths


def _solve_layout_once(fig):
    """Lay ``fig`` out once and hold that layout while it is saved; returns
    the layout engine to put back afterwards (None: the figure had none)
    and whether the figure was drawn for it.

    While a figure has a layout engine, every ``savefig`` draws it once more
    before the real draw, to solve the layout again. ``Figure.tight_layout``
    leaves a placeholder engine behind (nothing to solve, yet it counted as
    an engine): each Fig. 6 file was drawn twice, and a third time for a
    box. A constrained layout is solved here once (a second solve starts
    from where the first left the axes: an SVG saved after a PNG had axes
    off by 1e-13); then the figure has no engine until its files are written.
    """
    import matplotlib
    from matplotlib.layout_engine import PlaceHolderLayoutEngine

    engine = fig.get_layout_engine()
    if engine is None:
        return None, False
    drawn = not isinstance(engine, PlaceHolderLayoutEngine)
    if drawn:
        fig.draw_without_rendering()
    with matplotlib.rc_context({"figure.autolayout": False,
                                "figure.constrained_layout.use": False}):
        fig.set_layout_engine(None)     # None, whatever a user's matplotlibrc says
    return engine, drawn


def _tight_bbox(fig, *, drawn: bool = False):
    """The drawn content's box [inch] padded by ``savefig.pad_inches``: what
    ``bbox_inches="tight"`` crops to, measured once for every format
    (``"tight"`` draws the whole figure once more per file to measure it);
    ``drawn``: the figure was just drawn as it will be saved (not again)."""
    import matplotlib

    if not drawn:
        fig.draw_without_rendering()
    box = fig.get_tightbbox(fig.canvas.get_renderer())
    return box.padded(matplotlib.rcParams["savefig.pad_inches"])
