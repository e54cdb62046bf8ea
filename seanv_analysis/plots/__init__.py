"""Figures (matplotlib, Agg-safe, PNG + SVG). Import the submodule you need;
nothing is imported eagerly, so ``import seanv_analysis.plots`` stays light.

- :mod:`.fig4`: :func:`~.fig4.plot_fig4`, flow characterisation (paper Fig. 4)
- :mod:`.residuals`: discovery residual plots
"""

__all__: list[str] = []
