"""Stage ``figures``: the paper-style figures of the registry in :mod:`seanv_analysis.plots`.

Every registered :class:`~seanv_analysis.plots.Figure` the pipeline asks for
(``figs``: numbers such as 4, 6, 7 or names; "all" by default) whose inputs
exist is drawn: data-set figures from the results of earlier stages, per-run
figures (Fig. 6, one per position-control run) as per-run tasks through the
context's mapper. A figure that cannot be drawn is noted; it never sinks the run;
a figure file that cannot be written (disk full, file too large) ends the
run like any output error (:class:`~seanv_analysis.errors.OutputError`
naming the file).

A data-set figure whose inputs are unchanged is not drawn again: its key
(:func:`figure_key`: the SHA-256 of the figure's name, the formats, the code
and matplotlib versions, the rig and the content of its input results) is
kept with its files' sizes and modification times in
``<folder>/.figure-keys.json`` (written atomically); the same key with the
files untouched reuses them (inputs that cannot be hashed are simply drawn).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any, Mapping, Sequence

from ..errors import OutputError
from .base import Context, one_line, with_path
from .validate import position_paths

__all__ = ["NAME", "NEEDS", "WRITES", "OPTIONS", "FiguresResult", "check_option", "run", "write",
           "draw_figures", "draw_figure_task", "results_for_figures", "selected_figures",
           "draw_run_figure", "warm_figure_worker", "figure_input_modules", "figure_imports",
           "start_ahead"]

NAME = "figures"
ORDER = 90
NEEDS = ("ingest",)
FOLDER = "figures"
ROLE = "draws_figures"
RESULTS = ()
#: the pipeline record's {figure name: files}
RECORD = {"figures": "paths"}
WRITES = ("figures/<figure>.png|.svg", "figures/fig6/<run>.png|.svg")
DESCRIPTION = "paper-style figures (Fig. 4, 6, 7, discovery residuals, ...) as PNG and SVG"
#: figs: figure numbers or names of :data:`seanv_analysis.plots.FIGURES`, or
#: "all"; formats: file formats to write; layout: 'folders' (the stage's own
#: folder ``figures/``, per-run figures in ``figures/<figure>/``) or 'flat'
#: (every file directly in the output folder, as a single command writes them)
OPTIONS: dict[str, Any] = {"figs": "all", "formats": ["png", "svg"], "layout": "folders"}


def check_option(key: str, value: Any) -> Any:
    from ..plots import FIGURES

    if key == "figs":
        if value == "all":
            return value
        known = {f.number for f in FIGURES.values() if f.number is not None} | set(FIGURES)
        if (not isinstance(value, list) or any(isinstance(v, bool) or v not in known
                                               for v in value)):
            raise ValueError("\"all\" or a list of figures among "
                             + ", ".join(str(k) for k in sorted(known, key=str)))
    if key == "formats":
        if not isinstance(value, list) or not value or any(v not in ("png", "svg") for v in value):
            raise ValueError("a non-empty list among 'png', 'svg'")
    if key == "layout" and value not in ("folders", "flat"):
        raise ValueError("'folders' or 'flat'")
    return value


@dataclass(frozen=True)
class FiguresResult:
    """{figure name: files written} and one line per figure that could not be drawn."""

    paths: Mapping[str, tuple[Path, ...]] = field(default_factory=dict)
    problems: tuple[str, ...] = ()
    #: the figure keys file written beside the figures (None: none)
    keys_file: Path | None = None

    @property
    def note(self) -> str:
        """The figures that could not be drawn, one clause each (the stage's note)."""
        return "; ".join(self.problems)

    def all_paths(self) -> list[Path]:
        """Every file written: the figures and the figure keys beside them."""
        return [p for ps in self.paths.values() for p in ps] + (
            [self.keys_file] if self.keys_file is not None else [])

    def to_json_dict(self) -> dict[str, Any]:
        return {"figures": {k: [str(p) for p in v] for k, v in self.paths.items()},
                "problems": list(self.problems)}


def results_for_figures(ctx: Context, names=None) -> dict[str, Any]:
    """The results a figure may need, by name (:meth:`Context.result_named`:
    the catalogue's results of the stages that ran); ``names``: only these
    (default: every result of the catalogue)."""
    from .catalogue import result_names

    wanted = result_names() if names is None else names
    out = {n: ctx.result_named(n) for n in wanted}
    return {k: v for k, v in out.items() if v is not None}


def figure_input_modules(pipe: Any) -> tuple[str, ...]:
    """The modules defining the results the figures of pipeline ``pipe``
    read (:attr:`Result.module <seanv_analysis.stages.base.Result.module>`
    of its stages' results that a selected figure needs), in stage order,
    each once; () without a figures stage. Only those: a worker importing
    ``identify``'s (1.6 s), which no figure reads, would spend it for
    nothing (unless identify's own tasks run there:
    :func:`~seanv_analysis.stages.catalogue.task_modules`)."""
    from .catalogue import STAGES

    stage = pipe.stage(NAME)
    if stage is None:
        return ()
    needed = {n for f in selected_figures({**OPTIONS, **stage.options}["figs"]) for n in f.needs}
    mods = [r.module for s in pipe.stages if s.name in STAGES
            for r in getattr(STAGES[s.name], "RESULTS", ()) if r.module and r.name in needed]
    return tuple(dict.fromkeys(mods))


def figure_imports(pipe: Any) -> tuple[str, ...]:
    """What the figures of pipeline ``pipe`` import the first time they draw
    (:attr:`Figure.imports <seanv_analysis.plots.Figure>` of each selected
    figure), each once; () without a figures stage. Imported by the workers
    while they warm up (:func:`warm_figure_worker`), not by this process
    before their fork (unlike :func:`figure_input_modules`): it never draws."""
    stage = pipe.stage(NAME)
    if stage is None:
        return ()
    figs = selected_figures({**OPTIONS, **stage.options}["figs"])
    return tuple(dict.fromkeys(m for f in figs for m in f.imports))


def warm_figure_worker(modules: Sequence[str] = ()) -> None:
    """What a figure worker runs while the analysis goes on: import
    ``modules`` (:func:`figure_input_modules`: the results the figures will
    be sent are then read without their imports; :func:`figure_imports`:
    what the figures import when they first draw; and
    :func:`~seanv_analysis.stages.catalogue.task_modules`: the data-set
    stages' tasks run without theirs) and pay the first figure's costs
    (:func:`seanv_analysis.plots.warm_up`)."""
    import importlib

    from ..plots import warm_up

    for name in modules:
        importlib.import_module(name)
    warm_up()


def figure_files_exist(value: Mapping[str, Any], folder: str | None = None) -> bool:
    """A cached per-run figure is still valid: it names the files it wrote,
    each a regular file (not a link) inside ``folder`` where given, and they
    all exist (module level, so the mapper can send it to worker processes)."""
    from ..io.readback import conforms, regular_file_inside

    if not conforms(value, {"paths": [str], "run_id": str}):
        return False
    if folder is None:
        return all(Path(p).is_file() for p in value["paths"])
    return all(regular_file_inside(p, folder) for p in value["paths"])


def selected_figures(figs: Any) -> list:
    """The registered figures a ``figs`` option selects, in registry order."""
    from ..plots import FIGURES

    if figs == "all":
        return list(FIGURES.values())
    return [f for f in FIGURES.values() if f.name in figs or (f.number is not None and f.number in figs)]


def draw_run_figure(run, *, name: str, folder: str, formats: tuple[str, ...], rig) -> dict[str, Any]:
    """Per-run function: the per-run figure ``name`` of one run."""
    from ..errors import os_error_line
    from ..plots import FIGURES

    try:
        paths = FIGURES[name].draw_run(run, Path(folder), formats=formats, rig=rig)
    except OutputError as exc:   # ends the run (draw_figures raises it), never cached
        return {"output_error": str(exc), "run_id": run.meta.run_id}
    except OSError as exc:
        return {"output_error": os_error_line(exc), "run_id": run.meta.run_id}
    return {"paths": [str(p) for p in paths], "run_id": run.meta.run_id}


def run(ctx: Context, options: Mapping[str, Any]) -> FiguresResult:
    """Draw the selected figures into ``ctx.out_dir / 'figures'``.

    Figures are files by nature: this stage writes while it runs, and
    :func:`write` has nothing left to do.
    """
    opts = {**OPTIONS, **options}
    return draw_figures(ctx, opts["figs"], _folder(ctx, opts), formats=tuple(opts["formats"]),
                        per_run_folders=opts["layout"] != "flat")


def _folder(ctx: Context, opts: Mapping[str, Any]) -> Path:
    """Where the figures go: the output folder itself ('flat'), else the
    pipeline's ``figures/`` (claimed: swapped in whole after the stage)."""
    from ..io.atomic import claim_folder

    if opts["layout"] == "flat":
        return Path(ctx.out_dir)
    return claim_folder(Path(ctx.out_dir) / FOLDER)


def start_ahead(ctx: Context, options: Mapping[str, Any]) -> None:
    """Start drawing, on the executor's background worker (one process at a
    lower CPU priority: ``ctx.start_tasks``) and without waiting, each
    selected data-set figure whose inputs exist now and that is not started
    already, while the stages between run here (they leave a core idle part
    of the time: single-threaded steps of identify and discover). The
    figures stage takes a figure drawn here when its key
    (:func:`figure_key`: the content of its inputs) is still the same, and
    draws those not begun by then itself; the files are the same bytes.
    Nothing where no task can be started so (``ctx.start_tasks`` None) or a
    figure would be reused."""
    start = getattr(ctx, "start_tasks", None)
    if start is None or ctx.out_dir is None:
        return
    opts = {**OPTIONS, **options}
    formats = tuple(opts["formats"])
    ahead = ctx.ahead.setdefault(NAME, {})
    chosen = [f for f in selected_figures(opts["figs"]) if not f.per_run and f.name not in ahead]
    have = results_for_figures(ctx, {n for f in chosen for n in f.needs})
    ready = [f for f in chosen if all(n in have for n in f.needs)]
    if not ready:
        return
    folder = _folder(ctx, opts)
    keys = _FigureKeys(folder)
    for fig in ready:
        inputs = {n: have[n] for n in fig.needs}
        key = figure_key(fig.name, inputs, formats, getattr(ctx, "rig", None))
        if key is None or keys.reuse(fig.name, key, formats) is not None:
            continue
        tasks = [(*job, formats) for job in _jobs_of(fig, inputs, folder)]
        ahead[fig.name] = (key, str(folder), tasks,
                           start(draw_figure_task, tasks, kwargs={"formats": formats,
                                                                  "rig": ctx.rig}))


def _jobs_of(fig, inputs: Mapping[str, Any], folder: Path) -> list[tuple]:
    """A data-set figure's drawing jobs: one, or one per part (:func:`_parts_of`)."""
    split = _parts_of(fig, inputs)
    if split is None:
        return [("dataset", fig.name, inputs, str(folder))]
    return [("part", fig.name, (inputs, part), str(folder)) for part in split]


def draw_figures(ctx: Context, figs: Any, folder: Path, *, formats: tuple[str, ...] = ("png", "svg"),
                 per_run_folders: bool = True) -> FiguresResult:
    """Draw the figures ``figs`` selects ("all", or numbers/names) from the
    context's results into ``folder`` (per-run figures into ``folder/<name>/``
    when ``per_run_folders``).

    Each figure is an independent task on the context's task mapper
    (:attr:`Context.map_tasks`: the run's worker processes or Dask; here in
    a notebook): the data-set figures and, where per-run work runs in this
    process, the per-run figures too, all at once; the batch's per-run
    figures go through its cached per-run mapper (:attr:`Context.map_runs`)
    after them. A figure's files are the same bytes whichever process drew
    them. The first file that cannot be written ends the run
    (:class:`~seanv_analysis.errors.OutputError` naming it), once every
    task has ended.
    """
    from .base import serial_map, serial_tasks

    folder = Path(folder)
    ctx.log(f"figures: drawing {figs if isinstance(figs, str) else ', '.join(map(str, figs))} "
            f"into {folder}")
    # the figures started ahead (start_ahead): those not begun yet are drawn
    # here; those begun are waited for after the rest (or, their inputs
    # changed since, before the same files are drawn again); of a figure in
    # parts, the parts begun are taken and the others drawn here
    ahead = getattr(ctx, "ahead", {}).pop(NAME, {})
    for *_, started in ahead.values():
        started.cancel_waiting()
    taken: list[tuple[list, Any]] = []     # (tasks, started) of the figures drawn ahead
    keys = _FigureKeys(folder)
    chosen = selected_figures(figs)
    have = results_for_figures(ctx, {n for f in chosen if not f.per_run for n in f.needs})
    explicit = figs != "all"
    drawn: dict[str, tuple[Path, ...]] = {}
    problems: list[str] = []
    jobs: list[tuple[str, str, Any, str]] = []   # (kind, figure, inputs or run folder, folder)
    mapped: list[tuple[Any, list[Path], Path]] = []   # per-run figures on the cached mapper
    fig_keys: dict[str, str | None] = {}
    in_process = getattr(ctx, "map_runs", serial_map) is serial_map
    for fig in chosen:
        if fig.per_run:
            runs = position_paths(ctx) if fig.run_kind == "position_control" else []
            out = folder / fig.name if per_run_folders else folder
            if runs and in_process:
                jobs += [("run", fig.name, str(d), str(out)) for d in runs]
            elif runs:
                mapped.append((fig, runs, out))
            continue
        missing = [n for n in fig.needs if n not in have]
        if missing:
            if explicit or _expected(ctx, missing):
                problems.append(f"{fig.name}: no {', '.join(missing)} result "
                                "(stage absent or failed)")
            continue
        inputs = {n: have[n] for n in fig.needs}
        key = figure_key(fig.name, inputs, formats, getattr(ctx, "rig", None))
        reused = keys.reuse(fig.name, key, formats)
        if reused is not None:
            drawn[fig.name] = reused
            continue
        fig_keys[fig.name] = key
        early = ahead.pop(fig.name, None)
        if early is not None and early[:2] == (key, str(folder)):
            taken.append((early[2], early[3]))     # drawn ahead from the same inputs
            # the tasks (parts) not begun there, here (a task: (*job, formats))
            jobs += [task[:4] for task, begun in zip(early[2], early[3].begun()) if not begun]
            continue
        if early is not None:
            early[3].results()      # its files are drawn again below: not while it writes them
        jobs += _jobs_of(fig, inputs, folder)   # parts of one figure: a task each, side by side
    for *_, started in ahead.values():      # started, but reused or not drawn here after all
        started.results()                   # (ended before the stage ends, never after)
    map_tasks = getattr(ctx, "map_tasks", serial_tasks)
    tasks = _split_formats(jobs, tuple(formats), getattr(ctx, "task_slots", 1))
    outcomes = map_tasks(draw_figure_task, tasks, kwargs={"formats": tuple(formats),
                                                          "rig": ctx.rig}, desc="figures")
    done_ahead = [(task, res) for early_tasks, started in taken
                  for task, res in zip(early_tasks, started.results()) if res is not None]
    output_errors: list[str] = []
    per_run: dict[str, list[Path]] = {}
    parts: dict[str, list[Path]] = {}      # a data-set figure's files, over its tasks
    failed: set[str] = set()
    for (kind, name, what, *_), (ok, value) in [*done_ahead, *zip(tasks, outcomes)]:
        if ok and "output_error" in value:
            output_errors.append(value["output_error"])
        elif not ok or "problem" in value:
            why = value if not ok else value["problem"]
            line = f"{name}: {with_path(what, why) if kind == 'run' else why}"
            if line not in problems:    # a figure split by format fails once per format
                problems.append(line)
            failed.add(name)
        elif kind == "run":
            per_run.setdefault(name, []).extend(Path(p) for p in value["paths"])
        else:
            parts.setdefault(name, []).extend(Path(p) for p in value["paths"])
    for name, files in parts.items():
        drawn[name] = tuple(files)
        if name not in failed:          # a figure missing a format is drawn again next time
            keys.remember(name, fig_keys[name], drawn[name])
    if output_errors:      # a file that cannot be written (disk full): the run ends, the file named
        raise OutputError(output_errors[0])
    for fig, runs, out in mapped:
        res = ctx.map_runs(fig.name, draw_run_figure, runs, rig=ctx.rig,
                           params={"out_dir": str(out), "formats": list(formats)},
                           kwargs={"name": fig.name, "folder": str(out), "formats": formats,
                                   "rig": ctx.rig},
                           valid=partial(figure_files_exist, folder=str(out)))
        for d in runs:
            r = res[str(d)]
            if r.ok and "output_error" in r.value:
                raise OutputError(r.value["output_error"])
            if r.ok:
                per_run.setdefault(fig.name, []).extend(Path(p) for p in r.value["paths"])
            else:
                problems.append(f"{fig.name}: {with_path(d, r.error)}")
    paths = {f.name: (drawn[f.name] if f.name in drawn else tuple(per_run[f.name]))
             for f in chosen if f.name in drawn or per_run.get(f.name)}
    return FiguresResult(paths, tuple(problems), keys.save())


def _parts_of(fig, inputs: Mapping[str, Any]) -> list | None:
    """The parts a data-set figure is drawn in (:attr:`Figure.parts
    <seanv_analysis.plots.registry.Figure.parts>`), or None: one task (no
    parts, a single part, or parts that cannot be listed: the figure then
    draws, or fails, whole)."""
    if fig.parts is None:
        return None
    try:
        split = list(fig.parts(inputs))
    except Exception:
        return None
    return split if len(split) > 1 else None


def _split_formats(jobs: list[tuple], formats: tuple[str, ...], slots: int) -> list[tuple]:
    """The figure tasks: each job with the formats it writes. With fewer jobs
    than ``slots`` (tasks running at once), each data-set figure becomes one
    task per format, so that the idle workers draw the other formats (a lone
    Fig. 4 in PNG and SVG: about 0.8 s each instead of 1.5 s in one task;
    each task lays the figure out itself, the same bytes as together)."""
    split = len(formats) > 1 and len(jobs) < slots
    return [(*job, fmts) for job in jobs
            for fmts in ([(f,) for f in formats] if split and job[0] == "dataset" else [formats])]


def draw_figure_task(job: tuple, *, formats: tuple[str, ...], rig: Any) -> dict[str, Any]:
    """Task of :func:`draw_figures` (module level: it runs in worker
    processes): ``job`` is ("dataset", figure name, {result name: result},
    folder[, formats]), ("part", figure name, ({result name: result}, part),
    folder[, formats]) (one part of a figure drawn in parts) or ("run",
    figure name, run folder, folder[, formats]); the job's formats, where
    given, replace ``formats``. Returns
    ``{"paths": [...]}``, ``{"output_error": line}`` (a file that cannot be
    written: the run ends) or ``{"problem": line}`` (the figure cannot be
    drawn: a note); it never raises."""
    from ..errors import os_error_line
    from ..plots import FIGURES

    kind, name, what, folder, *own = job
    formats = tuple(own[0]) if own else formats
    try:
        if kind == "run":
            from ..io.reader import read_run

            paths = FIGURES[name].draw_run(read_run(what, rig=rig), Path(folder),
                                           formats=formats, rig=rig)
        elif kind == "part":
            paths = FIGURES[name].draw(what[0], Path(folder), formats=formats, part=what[1])
        else:
            paths = FIGURES[name].draw(what, Path(folder), formats=formats)
    except OutputError as exc:
        return {"output_error": str(exc)}
    except OSError as exc:
        return {"output_error": os_error_line(exc)}
    except Exception as exc:  # a figure that cannot be drawn must not sink the run
        return {"problem": one_line(exc)}
    return {"paths": [str(p) for p in paths]}


def figure_key(name: str, inputs: Mapping[str, Any], formats: tuple[str, ...],
               rig: Any = None) -> str | None:
    """SHA-256 of what a data-set figure shows: its name, the formats, the
    code version (package version + hash of its sources: the plotting code),
    the matplotlib version, the rig's constants and the content of its input
    results (:func:`~seanv_analysis.io.hashing.content_sha256`: the same in
    every process). None when an input cannot be hashed by content (the
    figure is then simply drawn)."""
    from importlib.metadata import version  # not matplotlib itself: a reused figure loads none

    from ..io.hashing import code_version, content_sha256

    try:
        return content_sha256({"figure": name, "formats": list(formats),
                               "code": code_version(), "matplotlib": version("matplotlib"),
                               "rig": getattr(rig, "data", rig), "inputs": dict(inputs)})
    except TypeError:  # an input of a type not hashed by content: no key, the figure is drawn
        return None


class _FigureKeys:
    """``<folder>/.figure-keys.json``: {figure: {key, files: {path: [size, mtime_ns]}}}.

    Read back as untrusted input (:mod:`seanv_analysis.io.readback`): a
    malformed file counts as empty, and a figure is reused only when every
    file it names is a regular file (not a link) directly in ``folder``, of
    one of the formats asked for, unchanged; anything else is drawn again."""

    NAME = ".figure-keys.json"

    def __init__(self, folder: Path):
        from ..io.readback import load_json_back

        self.folder = Path(folder)
        self.path = self.folder / self.NAME
        self.doc = load_json_back(self.path, root=self.folder, shape={str: {
            "key": str, "files": {str: lambda st: (isinstance(st, list) and len(st) == 2
                                                    and all(type(n) is int for n in st))}}}) or {}
        self.changed = False

    def reuse(self, name: str, key: str | None, formats: tuple[str, ...] = ("png", "svg")
              ) -> tuple[Path, ...] | None:
        from ..io.readback import regular_file_inside

        rec = self.doc.get(name)
        if key is None or not isinstance(rec, dict) or rec.get("key") != key:
            return None
        files = rec.get("files") or {}
        for p, st in files.items():
            f = Path(p)
            if (f.suffix[1:] not in formats or f.name.startswith(".")
                    or not regular_file_inside(f, self.folder)
                    or f.resolve().parent != self.folder.resolve()):
                return None   # only this folder's own figure files are ever reused
            s = f.lstat()
            if [s.st_size, s.st_mtime_ns] != st:
                return None
        return tuple(Path(p) for p in files) or None

    def remember(self, name: str, key: str | None, files: tuple[Path, ...]) -> None:
        if key is None:
            self.doc.pop(name, None)
        else:
            self.doc[name] = {"key": key, "files": {
                str(p): [p.stat().st_size, p.stat().st_mtime_ns] for p in files if p.is_file()}}
        self.changed = True

    def save(self) -> Path | None:
        """Write the keys when they changed; the file's path if it exists."""
        if self.changed and self.path.parent.is_dir():
            from ..io.atomic import write_json_atomic

            write_json_atomic(self.path, self.doc, indent=0)
        return self.path if self.path.is_file() else None


def _expected(ctx: Context, missing: list[str]) -> bool:
    """Whether the data would have given one of the missing results: a stage
    giving it declares ``expected(ds)`` (the flow fit: the data set has flow
    steps; tracking: position-control runs) and says so."""
    from .catalogue import STAGES, producers_of

    ds = ctx.result("ingest")
    if ds is None:
        return False
    return any(getattr(STAGES[stage], "expected", lambda ds: False)(ds)
               for name in missing for stage in producers_of(name))


def write(result: FiguresResult, folder: Path) -> list[Path]:
    """Nothing more: the figure files were written as they were drawn (and
    the figure keys beside them, kept for the next run)."""
    return result.all_paths()
