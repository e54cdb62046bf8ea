"""seanv-analysis: rig logs of the SEANV water-hydraulic needle valve turned
into identified valve models, tracking figures and honest error numbers.

Paper: "Series Elastic Actuated Needle Valve (SEANV)" flow and sealing
characteristics (see README). Units follow the paper: mm, MPa gauge, deg, s,
mm^3/s, N.
"""
from importlib.metadata import PackageNotFoundError
from importlib.metadata import version as _version

try:
    __version__ = _version("seanv-analysis")
except PackageNotFoundError:  # running from a source tree without install
    __version__ = "0.0.0+unknown"

from .config import RigConfig, load_rig
from .errors import ConfigError, DataError, FitError, SeanvError
from .models import NeedleGeometry, ValveModel, ValveSide

__all__ = ["__version__", "SeanvError", "DataError", "ConfigError", "FitError",
           "RigConfig", "load_rig", "ValveModel", "ValveSide", "NeedleGeometry",
           "load_dataset", "flowfit"]


def __getattr__(name):
    """The notebook API (:mod:`seanv_analysis.api`), imported on first use so
    ``import seanv_analysis`` stays light."""
    if name in ("load_dataset", "flowfit"):
        import importlib  # by name: the root package stays below every layer

        return getattr(importlib.import_module("seanv_analysis.api"), name)
    raise AttributeError(f"module 'seanv_analysis' has no attribute {name!r}")
