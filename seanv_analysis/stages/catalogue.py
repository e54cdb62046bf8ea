"""The catalogue of stages: every stage module of this package, found once.

A stage is one module of :mod:`seanv_analysis.stages` that declares itself
(``NAME``, ``ORDER``, ``FOLDER``, ``RESULTS``... see :mod:`.base`). This module
imports every module of the package and keeps those with a ``NAME`` and a
``run``, in increasing ``ORDER``: :data:`STAGES`. The pipeline files, the
batch runner, the figures stage, ``plots``, the report and the CLI read the
stages, their results, folders, report sections and figures from here;
nothing else lists them. Adding a stage is adding its module.
"""
from __future__ import annotations

import importlib
import pkgutil
from types import ModuleType
from typing import Any

__all__ = ["STAGES", "refresh", "has_role", "stage_names", "result_names", "results_of", "producers_of",
           "report_sections", "figures_reading", "describe_stages", "check_catalogue",
           "task_modules", "stage_imports"]

#: the roles a stage may declare (``ROLE``; see :mod:`.base`), each one
#: stage's at most: what the batch runner treats apart
ROLES = ("reads_runs", "draws_figures", "report")

#: the declarations every stage module must have
REQUIRED = ("NAME", "ORDER", "DESCRIPTION", "NEEDS", "WRITES", "FOLDER", "RESULTS", "OPTIONS",
            "check_option", "run", "write")


def _scan() -> dict[str, ModuleType]:
    """{name: stage module} of every module of this package that declares a
    stage, in run order."""
    from .. import stages as package

    found = []
    for info in pkgutil.iter_modules(package.__path__):
        if info.name.startswith("_") or info.name in ("base", "catalogue", "pipeline"):
            continue
        mod = importlib.import_module(f"{package.__name__}.{info.name}")
        if hasattr(mod, "NAME") and hasattr(mod, "run"):
            found.append(mod)
    return {m.NAME: m for m in sorted(found, key=lambda m: (m.ORDER, m.NAME))}


def check_catalogue(stages: dict[str, ModuleType]) -> None:
    """Every stage declares what the catalogue reads, under a unique name and
    order; each result name is given by stages of one type.

    Raises
    ------
    TypeError
        a declaration is missing or malformed (the module and what is expected).
    """
    orders: dict[Any, str] = {}
    types: dict[str, str] = {}
    roles: dict[str, str] = {}
    for name, mod in stages.items():
        missing = [k for k in REQUIRED if not hasattr(mod, k)]
        if missing:
            raise TypeError(f"stage module {mod.__name__}: missing {', '.join(missing)} "
                            "(docs/architecture.md, 'How to add a stage')")
        if mod.ORDER in orders:
            raise TypeError(f"stage module {mod.__name__}: ORDER {mod.ORDER} is also stage "
                            f"'{orders[mod.ORDER]}''s")
        orders[mod.ORDER] = name
        for need in mod.NEEDS:
            if need not in stages or stages[need].ORDER >= mod.ORDER:
                raise TypeError(f"stage '{name}': needs '{need}', which is no stage running "
                                "before it")
        role = getattr(mod, "ROLE", None)
        if role is not None:
            if role not in ROLES:
                raise TypeError(f"stage module {mod.__name__}: ROLE {role!r} is none of "
                                f"{', '.join(ROLES)}")
            if roles.setdefault(role, name) != name:
                raise TypeError(f"stage '{name}': ROLE {role!r} is also stage "
                                f"'{roles[role]}''s")
        for res in mod.RESULTS:
            if types.setdefault(res.name, res.type) != res.type:
                raise TypeError(f"stage '{name}': result '{res.name}' is a {res.type}, "
                                f"elsewhere a {types[res.name]}")


STAGES: dict[str, ModuleType] = _scan()
check_catalogue(STAGES)


def refresh() -> dict[str, ModuleType]:
    """Scan the package again (a stage module added to its path since) and
    update :data:`STAGES` in place; returns it."""
    found = _scan()
    check_catalogue(found)
    STAGES.clear()
    STAGES.update(found)
    return STAGES


def has_role(name: str, role: str) -> bool:
    """Whether stage ``name`` declares ``ROLE`` = ``role`` (:data:`ROLES`)."""
    return name in STAGES and getattr(STAGES[name], "ROLE", None) == role


def stage_names() -> tuple[str, ...]:
    """The stages in the order a pipeline runs them."""
    return tuple(STAGES)


def result_names() -> tuple[str, ...]:
    """Every result a stage gives, in run order (first appearance)."""
    return tuple(dict.fromkeys(res.name for mod in STAGES.values() for res in mod.RESULTS))


def results_of(stage: str, value: Any, ctx: Any = None, *, json_only: bool = False
               ) -> dict[str, Any]:
    """{result name: result} a stage's return ``value`` gives (absent ones left out)."""
    out = {}
    for res in STAGES[stage].RESULTS:
        if json_only and not res.json:
            continue
        got = res.of(value, ctx)
        if got is not None:
            out[res.name] = got
    return out


def producers_of(result: str) -> list[str]:
    """The stages giving ``result``, in run order."""
    return [name for name, mod in STAGES.items() if any(r.name == result for r in mod.RESULTS)]


def report_sections() -> list:
    """The report sections of the stages (``SECTION``), in run order."""
    return [mod.SECTION for mod in STAGES.values() if getattr(mod, "SECTION", None) is not None]


def figures_reading(stage: str) -> list[str]:
    """Names of the figures a command running ``stage`` draws, in registry
    order: the data-set figures whose needs are all results of ``stage``, the
    first of them one that ``stage`` is the first to give (discover's
    closed-loop validation does not make it draw validate's figure), and
    those that name it in ``shown_with``."""
    from ..plots import FIGURES

    mine = {r.name for r in STAGES[stage].RESULTS}
    return [f.name for f in FIGURES.values()
            if stage in f.shown_with or (not f.per_run and set(f.needs) <= mine
                                         and producers_of(f.needs[0])[:1] == [stage])]


def task_modules(pipe: Any) -> tuple[str, ...]:
    """The modules in which the stages of pipeline ``pipe`` run tasks on the
    executor's workers (a stage's ``TASK_MODULES``, e.g. identify's fits), in
    stage order, each once: imported here before a forked pool starts
    (:meth:`seanv_analysis.batch.executor.Executor.preload`), so the workers
    start with them and a task does not pay the import (identify's: 0.7 s);
    also imported by :func:`seanv_analysis.stages.figures.warm_figure_worker`
    where a pipeline draws figures (for workers that were not forked)."""
    mods = [m for s in pipe.stages if s.name in STAGES
            for m in getattr(STAGES[s.name], "TASK_MODULES", ())]
    return tuple(dict.fromkeys(mods))


def stage_imports(pipe: Any) -> tuple[str, ...]:
    """What the stages of pipeline ``pipe`` import in this process when they
    run (a stage's ``IMPORTS``: the libraries its code loads only then, such
    as scipy.optimize for the flow fit), in stage order, each once: imported
    on a thread while the workers read the runs
    (:meth:`seanv_analysis.batch.executor.Executor.import_beside`) instead
    of after them (``flowfit`` on 345 runs: 0.5-0.8 s)."""
    mods = [m for s in pipe.stages if s.name in STAGES
            for m in getattr(STAGES[s.name], "IMPORTS", ())]
    return tuple(dict.fromkeys(mods))


def describe_stages() -> str:
    """One paragraph per stage: name, what it does, needs, results, options, writes."""
    lines = []
    for name, mod in STAGES.items():
        lines.append(f"{name}: {mod.DESCRIPTION}")
        lines.append(f"  needs:   {', '.join(mod.NEEDS) or '(the run folders)'}")
        res = ", ".join(f"{r.name} ({r.type})" for r in mod.RESULTS)
        lines.append(f"  gives:   {res or '(files only)'}")
        opts = ", ".join(f"{k}={v!r}" for k, v in mod.OPTIONS.items())
        lines.append(f"  options: {opts or '(none)'}")
        lines.append(f"  writes:  {', '.join(mod.WRITES)}")
    return "\n".join(lines)
