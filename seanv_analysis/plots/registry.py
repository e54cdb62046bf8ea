"""The figures registry: every figure the pipeline, the ``plots`` command and
the report know of, in the order the report shows them.

Each :class:`Figure` names the results it draws from (``needs``) and one
drawing function that writes its files and returns their paths:

- a data-set figure has ``draw(results, folder, *, formats) -> [paths]``,
  where ``results`` maps each of its ``needs`` to the stage's result
  (``"flowfit"``: FlowFit, ``"tracking"``: Tracking, ``"validation"``:
  Validation, ``"discovery"``: Discovery, ``"position_runs"``: the data
  set's position-control runs);
- a per-run figure (``per_run=True``, ``needs=("runs",)``) has
  ``draw_run(run, folder, *, formats, rig) -> [paths]``, called once per run
  of kind ``run_kind`` (the batch runner runs these as parallel, cached
  per-run tasks).

Both write exactly the file formats asked (``("png", "svg")``, ...) into
``folder``. Adding a figure is one module with such a function and one
:func:`register_figure` call (or one entry below); nothing else changes.

The figure modules import matplotlib only when they draw, so reading this
registry (``--help``, pipeline validation) does not load it.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from ..io.names import safe_name
from . import fig4, fig6, fig7
from ._style import DEFAULT_FORMATS, check_formats

__all__ = ["Figure", "FIGURES", "RESULT_NAMES", "register_figure", "describe_figures",
           "DrawDataset", "DrawRun"]

#: names a figure's ``needs`` may use: the stage results a figure draws from,
#: the position-control runs of the data set, and "runs" for a per-run figure
#: (it draws from one run at a time)
RESULT_NAMES: tuple[str, ...] = ("flowfit", "tracking", "validation", "discovery",
                                  "position_runs", "runs")


class DrawDataset(Protocol):
    """``draw(results, folder, *, formats) -> written paths`` of a data-set figure."""

    def __call__(self, results: Mapping[str, Any], folder: Path, *,
                 formats: Sequence[str]) -> list[Path]: ...


class DrawRun(Protocol):
    """``draw_run(run, folder, *, formats, rig) -> written paths`` of a per-run figure."""

    def __call__(self, run: Any, folder: Path, *, formats: Sequence[str],
                 rig: Any) -> list[Path]: ...


@dataclass(frozen=True, kw_only=True)
class Figure:
    """One registered figure.

    Attributes
    ----------
    name : key in :data:`FIGURES`, the pipeline's ``figs`` option and the
        pipeline result's ``figures``; also the per-run figures' sub-folder
        ("fig4", "fig6", "fig7", "discover_residuals")
    title : one line, the report's caption and the ``--help`` text
    needs : result names it draws from, among :data:`RESULT_NAMES`
    number : the paper's figure number (4, 6, 7), which ``figs`` may use
        instead of the name; None for figures not in the paper
    draw : data-set figure: ``draw(results, folder, *, formats) -> [paths]``
    draw_run : per-run figure: ``draw_run(run, folder, *, formats, rig) -> [paths]``
    per_run : drawn once per run (``draw_run``) instead of once per data set
    run_kind : per-run figures: the run kind drawn ("position_control")
    """

    name: str
    title: str
    needs: tuple[str, ...]
    number: int | None = None
    draw: DrawDataset | None = None
    draw_run: DrawRun | None = None
    per_run: bool = False
    run_kind: str | None = None

    def __post_init__(self) -> None:
        where = f"figure {self.name!r}"
        if not isinstance(self.name, str) or not self.name or safe_name(self.name) != self.name:
            raise ValueError(f"name: {self.name!r} must be a non-empty file-name-safe string "
                             "(letters, digits, '-', '_', '.')")
        if not isinstance(self.title, str) or not self.title.strip() or "\n" in self.title:
            raise ValueError(f"{where}: title must be one non-empty line, got {self.title!r}")
        needs = (self.needs,) if isinstance(self.needs, str) else tuple(self.needs)
        object.__setattr__(self, "needs", needs)
        unknown = [n for n in needs if n not in RESULT_NAMES]
        if not needs or unknown:
            raise ValueError(f"{where}: needs {list(needs)!r}; expected one or more of "
                             f"{', '.join(RESULT_NAMES)}")
        if self.number is not None and (isinstance(self.number, bool) or not isinstance(self.number, int)):
            raise ValueError(f"{where}: number must be an int or None, got {self.number!r}")
        if self.per_run:
            if self.draw_run is None or self.draw is not None:
                raise ValueError(f"{where}: a per-run figure has draw_run and no draw")
            if needs != ("runs",) or not self.run_kind:
                raise ValueError(f"{where}: a per-run figure needs ('runs',) and a run_kind "
                                 "such as 'position_control'")
        else:
            if self.draw is None or self.draw_run is not None:
                raise ValueError(f"{where}: a data-set figure has draw and no draw_run "
                                 "(set per_run=True for a figure drawn once per run)")
            if "runs" in needs or self.run_kind is not None:
                raise ValueError(f"{where}: needs 'runs' and run_kind belong to per-run figures "
                                 "(per_run=True)")


#: {name: Figure}, in the order the report shows them
FIGURES: dict[str, Figure] = {}


def register_figure(figure: Figure, *, replace: bool = False) -> Figure:
    """Add ``figure`` to :data:`FIGURES` (at the end) and return it.

    Raises ValueError when its name is taken (unless ``replace``) or its
    number is another figure's.
    """
    if not isinstance(figure, Figure):
        raise TypeError(f"figure: expected a Figure, got {type(figure).__name__}")
    if figure.name in FIGURES and not replace:
        raise ValueError(f"figure: name {figure.name!r} is already registered "
                         "(pass replace=True to replace it)")
    if figure.number is not None:
        taken = [f.name for f in FIGURES.values()
                 if f.number == figure.number and f.name != figure.name]
        if taken:
            raise ValueError(f"figure {figure.name!r}: number {figure.number} is already "
                             f"figure {taken[0]!r}'s")
    FIGURES[figure.name] = figure
    return figure


def describe_figures() -> str:
    """One line per registered figure: name, number, what it needs, title."""
    lines = []
    for f in FIGURES.values():
        num = f" ({f.number})" if f.number is not None else ""
        lines.append(f"{f.name}{num}: {f.title} [needs {', '.join(f.needs)}]")
    return "\n".join(lines)


def _draw_discovery_residuals(results: Mapping[str, Any], folder: Path, *,
                              formats: Sequence[str] = DEFAULT_FORMATS) -> list[Path]:
    """Residuals before/after discovery as ``folder/discover_residuals.<format>``
    (:func:`~seanv_analysis.plots.residuals.plot_discovery_residuals`)."""
    from .residuals import plot_discovery_residuals

    return plot_discovery_residuals(results["discovery"], out_dir=folder,
                                    formats=check_formats(formats))


def _draw_validation(results: Mapping[str, Any], folder: Path, *,
                     formats: Sequence[str] = DEFAULT_FORMATS) -> list[Path]:
    """Closed-loop validation: the fit % per run (``validate_fit.<format>``)
    and measured vs simulated overlays, one per run
    (:func:`~seanv_analysis.plots.validate.plot_overlay`)."""
    from .validate import plot_overlay

    return plot_overlay(results["validation"], folder, formats=check_formats(formats))


register_figure(Figure(
    name="fig4", number=4, needs=("flowfit",), draw=fig4.draw,
    title="Fig. 4: flow characterisation, flow rate vs cam angle and sealing threshold vs "
          "pressure difference"))
register_figure(Figure(
    name="fig6", number=6, needs=("runs",), per_run=True, run_kind="position_control",
    draw_run=fig6.draw_run,
    title="Fig. 6: position control under load variation, one figure per run"))
register_figure(Figure(
    name="fig6_runs", needs=("position_runs",), draw=fig6.draw_runs,
    title="Fig. 6: the position-control runs side by side, (a) without and (b) with the flow "
          "model"))
register_figure(Figure(
    name="fig7", number=7, needs=("tracking",), draw=fig7.draw,
    title="Fig. 7: flow tracking, target vs actual flow (delay-shifted), all runs and per run"))
register_figure(Figure(
    name="validate_fit", needs=("validation",), draw=_draw_validation,
    title="Closed-loop validation: measured vs simulated position control, fit % per run "
          "and overlays"))
register_figure(Figure(
    name="discover_residuals", needs=("discovery",), draw=_draw_discovery_residuals,
    title="Discovery: flow residual (measured - model) before/after the effects found"))
