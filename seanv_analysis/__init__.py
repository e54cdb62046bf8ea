"""seanv-analysis: rig logs of the SEANV water-hydraulic needle valve turned
into identified valve models, tracking figures and honest error numbers.

Paper: "Series Elastic Actuated Needle Valve (SEANV)" flow and sealing
characteristics (see README). Units follow the paper: mm, MPa gauge, deg, s,
mm^3/s, N.
"""
from .config import RigConfig, load_rig
from .errors import ConfigError, DataError, FitError, SeanvError

__all__ = ["__version__", "SeanvError", "DataError", "ConfigError", "FitError",
           "RigConfig", "load_rig", "ValveModel", "ValveSide", "NeedleGeometry",
           "load_dataset", "flowfit", "tracking", "validate", "identify", "discover", "run"]

#: names imported on first use (numpy and the rest stay out of
#: ``import seanv_analysis`` and ``seanv-analyze --help``): name -> module
_LAZY = {"ValveModel": "seanv_analysis.models", "ValveSide": "seanv_analysis.models",
         "NeedleGeometry": "seanv_analysis.models",
         **{name: "seanv_analysis.api" for name in ("load_dataset", "flowfit", "tracking",
                                                   "validate", "identify", "discover", "run")}}


def __getattr__(name):
    """The valve model classes, the notebook API (:mod:`seanv_analysis.api`)
    and ``__version__``, made on first use so ``import seanv_analysis`` stays
    light."""
    if name == "__version__":  # importlib.metadata costs ~40 ms: only when asked
        from importlib.metadata import PackageNotFoundError, version

        try:
            value = version("seanv-analysis")
        except PackageNotFoundError:  # running from a source tree without install
            value = "0.0.0+unknown"
        globals()[name] = value
        return value
    if name in _LAZY:
        import importlib  # by name: the root package stays below every layer

        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'seanv_analysis' has no attribute {name!r}")


def __dir__():
    return sorted({*globals(), *__all__})
