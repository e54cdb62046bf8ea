"""The figures registry: every figure the pipeline, the ``plots`` command and
the report know of, in the order the report shows them.

Each :class:`Figure` names the results it draws from (``needs``) and one
drawing function that writes its files and returns their paths:

- a data-set figure has ``draw(results, folder, *, formats) -> [paths]``,
  where ``results`` maps each of its ``needs`` to a result of the stages by
  name (the catalogue's ``RESULTS``, :mod:`seanv_analysis.stages.catalogue`:
  ``seanv-analyze run --list-stages`` lists them with their types);
  a data-set figure with independent files (one per run beside a summary)
  may also declare ``parts(results) -> [part, ...]``, its ``draw`` then
  taking ``part=`` to write one part (each part is then a task of its own);
- a per-run figure (``per_run=True``, ``needs=("runs",)``) has
  ``draw_run(run, folder, *, formats, rig) -> [paths]``, called once per run
  of kind ``run_kind`` (the batch runner runs these as parallel, cached
  per-run tasks).

Both write exactly the file formats asked (``("png", "svg")``, ...) into
``folder``. Adding a figure is one module of this package with such a
function and a :func:`register_figure` call at its end: the registry imports
every module of the package; nothing else changes.

The figure modules import matplotlib only when they draw, so reading this
registry (``--help``, pipeline validation) does not load it.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Protocol

from ..io.names import safe_name

__all__ = ["Figure", "FIGURES", "register_figure", "describe_figures", "DrawDataset",
           "DrawRun", "load_figure_modules"]


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
    needs : result names it draws from (a stage's ``RESULTS``; "runs" for a
        per-run figure); a figure needing a result no stage gives is never drawn
    number : the paper's figure number (4, 6, 7), which ``figs`` may use
        instead of the name; None for figures not in the paper
    draw : data-set figure: ``draw(results, folder, *, formats) -> [paths]``
    draw_run : per-run figure: ``draw_run(run, folder, *, formats, rig) -> [paths]``
    per_run : drawn once per run (``draw_run``) instead of once per data set
    run_kind : per-run figures: the run kind drawn ("position_control")
    shown_with : stages whose command draws this figure although it reads
        none of their results (Fig. 6 beside ``tracking``'s Fig. 7); a
        command draws the figures its stage's results feed and these
    order : where the report shows it (lower first; equal orders in the
        order registered)
    parts : data-set figures whose files are independent of each other (one
        per run beside a summary): ``parts(results) -> [part, ...]`` (small,
        picklable keys); ``draw(results, folder, *, formats, part=key)`` then
        writes one part's files, and without ``part`` all of them. The
        figures stage draws each part as a task of its own, side by side on
        the workers (None: the figure is one task)
    imports : modules its drawing imports the first time it draws, beyond
        matplotlib and the modules of its inputs (e.g. ``scipy.ndimage`` for
        the load levels Fig. 6 shades): a worker process warming up for the
        figures imports them then, while the analysis runs, rather than in
        the first figure it draws (:func:`~seanv_analysis.stages.figures.warm_figure_worker`)
    """

    name: str
    title: str
    needs: tuple[str, ...]
    number: int | None = None
    draw: DrawDataset | None = None
    draw_run: DrawRun | None = None
    per_run: bool = False
    run_kind: str | None = None
    shown_with: tuple[str, ...] = ()
    order: float = float("inf")
    parts: Callable[[Mapping[str, Any]], Sequence[Any]] | None = None
    imports: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        where = f"figure {self.name!r}"
        if not isinstance(self.name, str) or not self.name or safe_name(self.name) != self.name:
            raise ValueError(f"name: {self.name!r} must be a non-empty file-name-safe string "
                             "(letters, digits, '-', '_', '.')")
        if not isinstance(self.title, str) or not self.title.strip() or "\n" in self.title:
            raise ValueError(f"{where}: title must be one non-empty line, got {self.title!r}")
        needs = (self.needs,) if isinstance(self.needs, str) else tuple(self.needs)
        object.__setattr__(self, "needs", needs)
        if not needs or not all(isinstance(n, str) and n for n in needs):
            raise ValueError(f"{where}: needs {list(needs)!r}; expected one or more result "
                             "names")
        imports = (self.imports,) if isinstance(self.imports, str) else tuple(self.imports)
        object.__setattr__(self, "imports", imports)
        if not all(isinstance(m, str) and m for m in imports):
            raise ValueError(f"{where}: imports {list(imports)!r}; expected module names")
        if self.number is not None and (isinstance(self.number, bool) or not isinstance(self.number, int)):
            raise ValueError(f"{where}: number must be an int or None, got {self.number!r}")
        if self.per_run:
            if self.draw_run is None or self.draw is not None:
                raise ValueError(f"{where}: a per-run figure has draw_run and no draw")
            if needs != ("runs",) or not self.run_kind:
                raise ValueError(f"{where}: a per-run figure needs ('runs',) and a run_kind "
                                 "such as 'position_control'")
            if self.parts is not None:
                raise ValueError(f"{where}: a per-run figure has no parts (each run is one)")
        else:
            if self.draw is None or self.draw_run is not None:
                raise ValueError(f"{where}: a data-set figure has draw and no draw_run "
                                 "(set per_run=True for a figure drawn once per run)")
            if self.parts is not None and not callable(self.parts):
                raise ValueError(f"{where}: parts must be a function of the results")
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
    ordered = sorted(FIGURES.values(), key=lambda f: f.order)   # stable: equal orders as registered
    FIGURES.clear()
    FIGURES.update((f.name, f) for f in ordered)
    return figure


def describe_figures() -> str:
    """One line per registered figure: name, number, what it needs, title."""
    lines = []
    for f in FIGURES.values():
        num = f" ({f.number})" if f.number is not None else ""
        lines.append(f"{f.name}{num}: {f.title} [needs {', '.join(f.needs)}]")
    return "\n".join(lines)


def load_figure_modules() -> None:
    """Import every module of this package but the registry's own helpers:
    each figure module registers its figures (:func:`register_figure` at its
    end), so a new figure is one new module and nothing else. Called when
    the registry loads; again to pick up a module added to the package's
    path since (modules already imported are not run twice)."""
    import importlib
    import pkgutil

    from .. import plots as package

    for info in pkgutil.iter_modules(package.__path__):
        if not info.name.startswith("_") and info.name not in ("registry", "notebook"):
            importlib.import_module(f"{package.__name__}.{info.name}")


load_figure_modules()
