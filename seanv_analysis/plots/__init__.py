"""Figures (matplotlib objects on an Agg canvas, written as PNG and/or SVG).

:data:`FIGURES` is the registry of every figure the pipeline, the ``plots``
command and the report know of (:mod:`.registry`); each figure module also
offers plain functions for use from a script or a notebook:

- :mod:`.fig4`: :func:`~.fig4.plot_fig4`, :func:`~.fig4.draw_fig4`, flow
  characterisation (paper Fig. 4)
- :mod:`.fig6`: :func:`~.fig6.plot_fig6`, position control per run (Fig. 6)
- :mod:`.fig7`: :func:`~.fig7.plot_fig7`, flow tracking (Fig. 7)
- :mod:`.validate`: :func:`~.validate.plot_overlay`, measured vs simulated
- :mod:`.residuals`: discovery residual plots

Importing this package does not import matplotlib; drawing a figure does.
"""
from ._style import warm_up
from .registry import FIGURES, Figure, describe_figures, load_figure_modules, register_figure

__all__ = ["FIGURES", "Figure", "describe_figures", "register_figure", "load_figure_modules",
           "warm_up"]
