"""``.plot(ax=None)`` of the result objects, without the lower layers
importing the figures.

A result (``FlowFit``, ``DatasetResult``, ...) lives below the plotting
layer, so its ``plot`` method asks this module, which loads the drawing code
(``seanv_analysis.plots.notebook``) by name on first use, as pandas does for
its plotting back end. Nothing is imported, and no matplotlib back end is
chosen, until a figure is drawn; without ``ax`` the figure comes from
``matplotlib.pyplot`` (the notebook's or the user's back end).
"""
from __future__ import annotations

import importlib
from typing import Any

__all__ = ["plot"]

_BACKEND = "seanv_analysis.plots.notebook"


def plot(obj: Any, ax: Any = None, **kwargs: Any) -> Any:
    """Draw ``obj`` on ``ax`` (a new pyplot figure when None); returns the axes."""
    return importlib.import_module(_BACKEND).plot(obj, ax=ax, **kwargs)
