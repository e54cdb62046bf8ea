"""seanv-analysis: rig logs of the SEANV water-hydraulic needle valve turned
into identified valve models, tracking figures and honest error numbers.

Paper: "Series Elastic Actuated Needle Valve (SEANV)" flow and sealing
characteristics (see README). Units follow the paper: mm, MPa gauge, deg, s,
mm^3/s, N.
"""
import sys
import types

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
                                                   "validate", "run")}}

#: commands whose name is also a subpackage's (``seanv_analysis.identify``,
#: ``seanv_analysis.discover``): the import system sets the package's attribute
#: to the subpackage when it is imported, so ``sa.identify`` is that module,
#: made callable: ``sa.identify(data, ...)`` runs :func:`seanv_analysis.api.identify`,
#: ``sa.identify.identify_rig`` is the module's (:class:`_CommandModule`).
_COMMAND_MODULES = ("identify", "discover")


class _CommandModule(types.ModuleType):
    """A subpackage that is also a command: calling it runs the notebook
    function of the same name (:mod:`seanv_analysis.api`), whose signature
    and docstring ``help()`` and ``inspect.signature`` show."""

    def _command(self):
        import importlib

        return getattr(importlib.import_module("seanv_analysis.api"),
                       self.__name__.rsplit(".", 1)[1])

    def __call__(self, *args, **kwargs):
        return self._command()(*args, **kwargs)

    @property
    def __signature__(self):
        import inspect

        return inspect.signature(self._command())


class _Package(types.ModuleType):
    """This package's module: a command subpackage set on it (by the import
    system) becomes callable (:class:`_CommandModule`)."""

    def __setattr__(self, name: str, value) -> None:
        if name in _COMMAND_MODULES and type(value) is types.ModuleType:
            value.__class__ = _CommandModule
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package


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
    if name in _COMMAND_MODULES:   # importing it sets it here, callable (_Package)
        import importlib

        return importlib.import_module(f"{__name__}.{name}")
    if name in _LAZY:
        import importlib  # by name: the root package stays below every layer

        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'seanv_analysis' has no attribute {name!r}")


def __dir__():
    return sorted({*globals(), *__all__})
