"""Small helpers shared by the CLI commands (output folders, bad-run lists,
the built-in simulated data sets)."""
from __future__ import annotations

import functools
import hashlib
import inspect
import json
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import click

__all__ = ["verbosity", "default_out_dir", "check_out_dir", "probe_writable", "echo_bad_runs", "unusable", "stage_context",
           "sim_default_dataset", "write_command_manifest", "OUTPUTS_ROOT", "OUT_FOLDER",
           "command_pipeline", "run_command", "CommandRun"]

OUTPUTS_ROOT = Path("outputs")


class OutFolder(click.Path):
    """The type of every ``--out``: a folder path, never empty (``--out ""``
    would mean the current folder, which holds the user's files)."""

    def __init__(self) -> None:
        super().__init__(file_okay=False, path_type=Path)

    def convert(self, value, param, ctx):
        if isinstance(value, str) and not value.strip():
            self.fail("empty; expected a folder to write the outputs into", param, ctx)
        return super().convert(value, param, ctx)


#: the ``type=`` of every ``--out`` option
OUT_FOLDER = OutFolder()


def verbosity(command):
    """Decorator of a command (put it right under ``@cli.command``):
    ``-q/--quiet`` and ``-v/--verbose`` (progress lines, bars and logging on
    stderr: warnings and errors only / the default / details), logging
    configured before the command runs (:func:`seanv_analysis.log.configure`).
    A command that takes a ``quiet`` argument gets it (its own ``--quiet``
    option, if any, is replaced)."""
    takes_quiet = "quiet" in inspect.signature(command).parameters
    own = [p for p in getattr(command, "__click_params__", []) if p.name != "quiet"]

    @functools.wraps(command)
    def wrapper(*args, quiet: bool = False, verbose: int = 0, **kwargs):
        from ..log import configure

        configure(quiet=quiet, verbose=verbose)
        if takes_quiet:
            kwargs["quiet"] = quiet
        return command(*args, **kwargs)

    wrapper.__click_params__ = list(own)
    wrapper = click.option("-q", "--quiet", is_flag=True,
                           help="Nothing on stderr but warnings and errors (default where "
                                "stderr is not a terminal).")(wrapper)
    wrapper = click.option("-v", "--verbose", count=True,
                           help="Each step and its details on stderr, terminal or not (-vv: "
                                "each line with its time and module).")(wrapper)
    return wrapper


def _formats(ctx, param, value: str) -> tuple[str, ...]:
    out = tuple(dict.fromkeys(v.strip().lower() for v in value.split(",") if v.strip()))
    bad = [v for v in out if v not in ("png", "svg")]
    if bad or not out:
        raise click.BadParameter(f"{value!r}: expected png, svg or png,svg")
    return out


def formats_option(command):
    """Decorator: ``--formats png,svg`` (the files each figure is written as)."""
    return click.option("--formats", "formats", default="png,svg", show_default=True,
                        callback=_formats, metavar="png|svg|png,svg",
                        help="File formats of the figures.")(command)


def figure_options(command):
    """Decorator: ``--no-figures`` (draw none; matplotlib is never imported)
    and ``--formats`` (:func:`formats_option`)."""
    command = formats_option(command)
    return click.option("--no-figures", is_flag=True,
                        help="Draw no figure (faster; matplotlib is not loaded).")(command)


def default_out_dir(data: str | Path, command: str) -> Path:
    """``outputs/<dataset-name>/<command>/`` (never inside the data folder)."""
    name = Path(data).resolve().name or "dataset"
    return OUTPUTS_ROOT / name / command


def check_out_dir(data: str | Path | Sequence[str | Path] | None, out: str | Path, *,
                  files: Sequence[str | Path | None] = (), owned: Sequence[str] = ()) -> None:
    """Refuse an output folder that would write over an input
    (:func:`seanv_analysis.io.outdir.check_out_dir`: inside a data folder,
    or an ``owned`` entry that is or holds DATA or one of ``files``), or one
    that cannot be written (:func:`probe_writable`).

    Raises
    ------
    DataError
        a data folder is missing or a file; ``out`` would write over an
        input (symbolic links resolved, inodes compared).
    OutputError
        ``out`` is empty or cannot be written; with "." in ``owned`` (a
        command that replaces its folder whole), ``out`` holds files this
        package did not write.
    """
    from ..io.atomic import check_not_foreign
    from ..io.dataset import check_data_root
    from ..io.outdir import check_out_dir as check

    datas = [] if data is None else [data] if isinstance(data, (str, Path)) else list(data)
    for d in datas:     # DATA that is not there: said before any output folder is made
        check_data_root(d)
    check(out, data=datas, files=files, owned=owned)
    out = Path(out)
    if "." in owned and out.is_dir() and not out.is_symlink() and any(out.iterdir()):
        check_not_foreign(out)     # the command replaces the folder whole: ours, or refused now
    probe_writable(out)


def probe_writable(out: str | Path) -> None:
    """Create ``out`` (and its parents) and a probe file in it, then remove
    the probe: a folder that cannot take the outputs is refused before any
    work, not after it.

    Raises
    ------
    OutputError
        ``out`` lies under a file, is a file, or cannot be written (read-only,
        permissions, disk full); one line naming the path.
    """
    import os
    import tempfile

    from ..errors import OutputError, os_error_line

    out = Path(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".seanv-probe-", suffix=".tmp", dir=out)
        try:
            os.write(fd, b"probe")
        finally:
            os.close(fd)
            os.unlink(probe)
    except FileExistsError:
        raise OutputError(f"--out: {out} is a file; expected a folder to write the outputs "
                          "into") from None
    except OSError as exc:
        raise OutputError(f"--out: cannot write the outputs there ({os_error_line(exc)})") \
            from None


#: data sets with at least this many runs are read on all cores by a single
#: command (below it a process pool costs more than it saves)
AUTO_PARALLEL_MIN_RUNS = 64


@contextmanager
def stage_context(data, *, rig, out_dir, model=None, quiet: bool = True, figures: bool = False,
                  warm_modules: Sequence[str] = (), warm_imports: Sequence[str] = (),
                  main_imports: Sequence[str] = ()):
    """The :class:`~seanv_analysis.stages.Context` of a single command: per-run
    work in this process, or on all cores for large data sets (no cache)
    inside the block; in this process after it. With ``figures`` (the
    command draws some) the figures are tasks on all cores too, and the
    worker processes load matplotlib at once, while the analysis runs here,
    and import ``warm_modules`` (the modules of the results the figures will
    be sent: :func:`seanv_analysis.stages.figures.warm_figure_worker`;
    imported here first, so the workers inherit them) and ``warm_imports``
    (what the figures import when they first draw; only there). With the
    runs read on all cores, this process imports ``main_imports`` (what its
    stages will import: :func:`~seanv_analysis.stages.catalogue.stage_imports`)
    meanwhile, on a thread (:meth:`~seanv_analysis.batch.executor.Executor.import_beside`),
    which the stages after ingest wait for.

    No figure is started ahead (``ctx.start_tasks``) here, unlike in
    ``run``: a command's analysis (1-2 s) is shorter than its workers'
    warm-up, and a data-set figure drawn ahead on the low-priority worker
    beside them was starved and became the figures' last task (``tracking``
    on the paper's two position runs: Fig. 6 side by side 5.2 s instead of
    1.2 s, the figures stage 4.2-4.8 s instead of 2.9-3.9 s)."""
    import multiprocessing as mp
    import os
    from functools import partial

    from ..batch import CachedMapper, make_executor
    from ..stages import Context, serial_map, serial_tasks

    ctx = Context.for_data(data, rig=rig, out_dir=out_dir, model=model,
                           model_source="--model" if model is not None else None, quiet=quiet)
    big = len(ctx.run_dirs) >= AUTO_PARALLEL_MIN_RUNS
    if not (big or figures) or mp.parent_process() is not None or (os.cpu_count() or 1) < 2:
        yield ctx
        return
    with make_executor(workers=os.cpu_count()) as ex:
        ex.preload(warm_modules)    # the workers start with them (forked at the first task)
        warm = None
        if figures:
            from ..stages.figures import warm_figure_worker

            warm = partial(ex.warm, partial(warm_figure_worker,
                                            (*warm_modules, *warm_imports)))
            ctx.map_tasks, ctx.task_slots = partial(ex.tasks, quiet=quiet), ex.slots
        if big:
            imported = ex.import_beside(main_imports)
            ctx.map_runs = _WarmAfter(CachedMapper(ex, None, quiet=quiet), warm, imported)
        elif warm is not None:
            warm()
        try:
            yield ctx
        finally:  # the pool is gone after the block
            ctx.map_runs, ctx.map_tasks, ctx.task_slots = serial_map, serial_tasks, 1


class _WarmAfter:
    """A run mapper that, once its first batch (ingest) has ended, waits for
    ``imported()`` (this process's imports beside it) and calls ``warm()``:
    the workers are idle from then on, while the analysis runs in the main
    process, and load matplotlib then rather than delaying the runs'
    reading. Not after a batch that raised (Ctrl-C: the command ends at
    once, not after the imports)."""

    def __init__(self, mapper, warm, imported=None):
        self.mapper, self.after = mapper, [f for f in (imported, warm) if f is not None]

    def __call__(self, *args, **kwargs):
        out = self.mapper(*args, **kwargs)
        after, self.after = self.after, []
        for then in after:
            then()
        return out


def command_pipeline(command: str, stages: Sequence[dict], *, ingest: dict | None = None,
                     figures: bool = True, formats: Sequence[str] = ("png", "svg"),
                     flags: dict[str, str] | None = None):
    """The pipeline a command runs: ingest (with ``ingest``'s options), its
    ``stages`` (each ``{"name": ..., option: value}``), and, unless
    ``figures`` is False, the figures its last stage's results feed (the
    catalogue's :func:`~seanv_analysis.stages.figures_reading`), written flat
    into the output folder. Checked as a pipeline file is; a bad value is
    said with its command-line option (``flags``: {option: "--flag"}).

    Raises
    ------
    ConfigError
        an option's value is not what its stage expects (one line naming it).
    """
    from ..errors import ConfigError
    from ..stages import STAGES, figures_reading
    from ..stages.pipeline import parse_pipeline

    doc = [{"name": "ingest", **(ingest or {})}, *stages]
    for item in doc:
        for key, value in item.items():
            try:
                if key != "name":
                    STAGES[item["name"]].check_option(key, value)
            except ValueError as exc:
                flag = (flags or {}).get(key)
                raise ConfigError(f"{key} = {value!r}{f' ({flag})' if flag else ''}; "
                                  f"expected {exc}") from None
    figs = figures_reading(stages[-1]["name"]) if figures else []
    if figs:
        doc.append({"name": "figures", "figs": figs, "formats": list(formats), "layout": "flat"})
    return parse_pipeline({"pipeline": {"name": command, "description": f"seanv-analyze {command}"},
                           "stages": doc}, source=f"seanv-analyze {command}")


@dataclass
class CommandRun:
    """What a command's pipeline gave: the context (every stage's value),
    the data set read, the last analysis stage's value and the files written."""

    ctx: Any
    ds: Any
    value: Any
    written: list[Path]


class _Unusable(Exception):
    """Nothing usable in the data: the command's exit code after listing the
    bad runs (raised inside the output folder's swap, so nothing is swapped in)."""

    def __init__(self, code: int):
        super().__init__(code)
        self.code = code


def run_command(pipe, data, *, rig, out: Path, model=None, quiet: bool = True,
                folders: dict[str, str] | None = None, missing: str = "nothing to analyse",
                manifest: dict | None = None) -> CommandRun | int:
    """Run a command's pipeline (:func:`command_pipeline`) through the one
    path of the stages (:func:`seanv_analysis.stages.execute`), each stage's
    files written as it ends, then ``manifest.json`` (``manifest``: the
    command's options); per-run work on all cores for large data sets
    (:func:`stage_context`).

    The output folder is written whole and swapped in (as ``run`` does with
    a stage's folder): a new one beside ``out``, renamed in when the command
    has written everything, so no file of an earlier run into ``out`` stays
    beside this one's; one command at a time per folder (a lock beside it).
    ``out`` must be new, empty, or a folder this package wrote.

    Returns the :class:`CommandRun` (its files at their final paths), or the
    exit code after listing the bad runs when the data held nothing usable
    (:func:`unusable`; ``out`` is then left as it was); a last stage that
    gives nothing raises ``DataError(missing)`` (listed the same way).
    """

    from ..errors import DataError, FitError
    from ..io.atomic import OWNER_MARKER, atomic_folder
    from ..io.outdir import out_lock
    from ..stages import STAGES, execute
    from ..stages.dataset import NoRunsRead

    folders = folders or {}
    main = [s.name for s in pipe.stages if s.name not in ("ingest", "figures")][-1]
    first = data if isinstance(data, (str, Path)) else data[0]
    out = Path(out)
    try:
        with out_lock(out, beside=True):
            if out.is_dir() and not out.is_symlink() and not any(out.iterdir()):
                (out / OWNER_MARKER).touch()      # an empty folder given as --out: taken
            with atomic_folder(out) as tmp:
                ctx, written = _run_in(pipe, data, first, tmp, rig=rig, model=model, quiet=quiet,
                                       folders=folders, main=main, missing=missing,
                                       execute=execute, stages=STAGES, no_runs=NoRunsRead,
                                       errors=(DataError, FitError))
                write_command_manifest(tmp, ctx, outputs=written, extra=manifest or {})
    except _Unusable as exc:
        return exc.code
    final = [out / p.relative_to(tmp) if p.is_relative_to(tmp) else p for p in written]
    return CommandRun(ctx, ctx.result("ingest"), ctx.result(main), final)


def _run_in(pipe, data, first, folder: Path, *, rig, model, quiet, folders, main, missing,
            execute, stages, no_runs, errors):
    """:func:`run_command`'s stages, writing into ``folder``: (context, files)."""
    import warnings

    from ..errors import DataError

    written: list[Path] = []

    def done(name: str, value) -> None:
        if value is None and name == main:
            raise DataError(missing, path=first)
        if value is not None and name != "ingest":
            written.extend(Path(p) for p in stages[name].write(value, folder / folders.get(name, ".")))

    from ..stages.catalogue import stage_imports, task_modules
    from ..stages.figures import figure_imports, figure_input_modules

    figures = any(s.name == "figures" for s in pipe.stages)
    with stage_context(data, rig=rig, out_dir=folder, model=model, quiet=quiet, figures=figures,
                       warm_modules=figure_input_modules(pipe) + task_modules(pipe),
                       warm_imports=figure_imports(pipe),
                       main_imports=stage_imports(pipe)) as ctx, \
            warnings.catch_warnings(record=True):
        warnings.simplefilter("always")   # a result keeps what matters (skipped runs, notes)
        try:
            execute(pipe, ctx, done=done)
        except no_runs as exc:
            raise _Unusable(unusable(first, exc.result.failed)) from None
        except errors as exc:  # nothing usable: say which runs were bad and why
            ds = ctx.result("ingest")
            if ds is None:
                raise
            raise _Unusable(unusable(first, ds.failed, exc)) from None
    return ctx, written


def unusable(data, failed, exc: Exception | None = None) -> int:
    """After a command found nothing usable in DATA (``exc``, e.g. "no valid
    runs"), say which runs were bad and why.

    A single run folder that is bad: its own one-line DataError is raised
    (exit 2). A data set with bad runs: ``exc``'s line, then the bad runs
    listed; returns 1. Otherwise ``exc`` is raised again.
    """
    from ..errors import DataError
    from ..io.reader import is_run_dir
    from ..io.validate import one_line

    errors = [getattr(f, "message", str(f)) for f in failed]
    single = data is not None and is_run_dir(data)
    if not errors:
        if exc is None:
            raise DataError("no valid runs in the data set", path=data)
        msg = one_line(exc)
        if single and isinstance(exc, DataError) and str(data) not in msg:
            raise DataError(msg, path=data) from None  # name the run folder at least
        raise exc
    if single:
        raise DataError(errors[0]) from None
    line = one_line(exc) if exc is not None else f"{data}: no valid runs in the data set"
    click.echo(f"error: {line}", err=True)
    return echo_bad_runs(errors)


def result_json(result, ds, *, failed=(), filtered: bool = False) -> str:
    """A command's ``--json`` document: the result's contract plus the
    ``inputs`` block (runs found, read, failed with why, skipped with why;
    :meth:`~seanv_analysis.stages.dataset.DatasetResult.runs_json`);
    ``filtered``: the command works on the flow steps the paper's filters
    keep, so the runs they exclude are listed as skipped, with the filter."""
    from ..jsonable import dumps

    skipped = getattr(result, "skipped_runs", None)
    left_out = {**(ds.excluded_runs() if filtered else {}),
                **(skipped() if callable(skipped) else {})}
    doc = result.to_json_dict()
    doc["inputs"] = ds.runs_json(failed=failed, skipped=left_out)
    return dumps(doc)


def echo_bad_runs(errors) -> int:
    """List bad runs on stderr, one line each; return the exit code (1 if any)."""
    if not errors:
        return 0
    click.echo(f"{len(errors)} bad run(s) skipped:", err=True)
    for err in errors:
        click.echo(f"  {getattr(err, 'message', err)}", err=True)
    return 1


def builtin_data_dir() -> Path:
    """Folder of the built-in simulated data sets: ``builtin/`` in the user
    cache folder (:func:`seanv_analysis.config.user_cache_dir`), so they are
    shared by every folder a user works in and never mixed with results;
    a temporary folder when the cache cannot be written."""
    import tempfile

    from ..config import user_cache_dir
    from ..errors import OutputError

    folder = user_cache_dir() / "builtin"
    try:
        probe_writable(folder)          # creates it
    except OutputError:                 # a read-only home must not stop the command
        folder = Path(tempfile.gettempdir()) / "seanv-analysis" / "builtin"
        folder.mkdir(parents=True, exist_ok=True)
    return folder


def sim_default_dataset(scenario: str, *, seed: int = 0, effects: tuple[str, ...] = ()) -> Path:
    """Path of a built-in simulated data set, generated on first use and cached
    in :func:`builtin_data_dir` (keyed by scenario, seed, effects and the
    simulator's version: package version + hash of its sources and rig)."""
    import os
    import shutil
    import tempfile

    from ..batch.cache import simulator_version
    from ..sim import simulate_scenario

    key = hashlib.sha256(json.dumps([scenario, seed, list(effects),
                                     simulator_version()]).encode()).hexdigest()[:10]
    path = builtin_data_dir() / f"{scenario}-{key}"
    if (path / ".complete").exists():
        return path
    import logging

    logging.getLogger("seanv_analysis.cli").info(
        f"simulating the built-in data set '{scenario}' into {path} (first use only; "
        "kept for later commands)")
    # made beside it and renamed in whole: two commands starting at once both
    # simulate, the first rename wins, the other's copy is dropped
    from ..io.atomic import current_umask

    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.tmp-", dir=path.parent))
    try:
        os.chmod(tmp, 0o777 & ~current_umask())
        simulate_scenario(scenario, tmp, seed=seed, effects=list(effects))
        (tmp / ".complete").write_text("ok\n")
        if path.exists() and not (path / ".complete").exists():
            shutil.rmtree(path, ignore_errors=True)     # a copy left incomplete
        try:
            os.rename(tmp, path)
        except OSError:
            if not (path / ".complete").exists():
                raise
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return path


def write_command_manifest(out: Path, ctx, *, extra: dict,
                           outputs: list[Path] | tuple[Path, ...] = ()) -> Path:
    """manifest.json of a command's output folder: version, rig, the SHA-256
    of every input file read, the command line, the command's options and
    ``outputs``, the files it wrote (each with its SHA-256 and size: a file
    of ``out`` not listed is not from this command)."""
    import sys

    from ..io.manifest import write_manifest

    ds = ctx.result("ingest")
    inputs = dict(ds.input_hashes) if ds is not None else [str(d) for d in ctx.data]
    bad = [f.message for f in ds.failed] if ds is not None else []
    return write_manifest(out, config=ctx.rig, inputs=inputs, command=sys.argv,
                          extra={**extra, "bad_runs": bad}, outputs=outputs)
