"""Run a pipeline's stages on a context: the one path every command, the
batch runner and the notebook's :func:`run_stages` share.
"""
from __future__ import annotations

from typing import Any, Callable, Mapping, Sequence

from ..errors import ConfigError, DataError
from .base import Context, RunMapper, serial_map

__all__ = ["execute", "run_stages"]


def execute(pipe, ctx: Context, *,
            on_error: Callable[[str, BaseException], bool] | None = None,
            done: Callable[[str, Any], None] | None = None,
            start: Callable[[str], None] | None = None,
            run: Callable[[Any, Context, Mapping[str, Any]], Any] | None = None) -> Context:
    """Run the stages of ``pipe`` (a :class:`~seanv_analysis.stages.pipeline.Pipeline`)
    in order on ``ctx``; each value that is not None is added to the context.

    Each stage is announced on ``ctx.log`` before it runs and after it
    ended (with its wall time), and a progress bar over the stages is drawn
    on a terminal where logging is configured (:func:`seanv_analysis.log.progress`).

    Parameters
    ----------
    start : called with a stage's name before it runs
    on_error : called with a stage's name and its exception; True when the
        error was handled (the pipeline goes on without the stage's result),
        False to raise it. None: every error is raised.
    done : called with a stage's name and its value (None: the stage had
        nothing to do, e.g. tracking without position-control runs) after
        it is added
    run : ``run(stage module, ctx, options) -> value``, how a stage is run
        (the batch runner's: its stored value when its inputs are unchanged,
        :class:`seanv_analysis.batch.stage_memo.StageMemo`); None: ``module.run``

    Raises
    ------
    ConfigError
        a stage needs a stage's result that neither ran before it nor is in
        the context already.
    """
    from ..log import progress
    from .catalogue import STAGES

    tag = f"[{pipe.name}] " if pipe.name else ""
    bar = progress(total=len(pipe.stages), desc=pipe.name or "stages", unit="stage")
    try:
        for i, stage in enumerate(pipe.stages):
            bar.set_postfix_str(stage.name, refresh=False)
            bar.refresh()
            _run_one(pipe, stage, ctx, STAGES[stage.name], tag,
                     start=start, on_error=on_error, done=done, run=run)
            _start_ahead(pipe.stages[i + 2:], ctx, STAGES)
            bar.update()
    finally:
        bar.close()
    return ctx


def _start_ahead(later, ctx: Context, stages) -> None:
    """Let each stage of ``later`` (the stages after the next one) start the
    work whose inputs exist now on the workers (``start_ahead``: the figures
    of the results so far, drawn beside the stages between); nothing where
    tasks cannot be started without waiting (a single process)."""
    if getattr(ctx, "start_tasks", None) is None:
        return
    for stage in later:
        begin = getattr(stages[stage.name], "start_ahead", None)
        if begin is None:
            continue
        try:
            begin(ctx, stage.options)
        except Exception as exc:   # only a head start: the stage does the work, and says why not
            ctx.log(f"{stage.name}: nothing started ahead ({' '.join(str(exc).split())[:200]})")


def _run_one(pipe, stage, ctx: Context, mod, tag: str, *, start, on_error, done,
             run=None) -> None:
    """One stage of :func:`execute`: its line before and after (``ctx.log``,
    with the time it took), its value added to the context."""
    import time

    missing = [n for n in mod.NEEDS if ctx.result(n) is None]
    ran = [s.name for s in pipe.stages[:pipe.stages.index(stage)]]
    if missing and not set(missing) <= set(ran):
        where = pipe.source or "pipeline " + pipe.name
        raise ConfigError(f"{where}: stage '{stage.name}' needs the result of "
                          f"{', '.join(repr(m) for m in missing)}; add that stage before it")
    if start is not None:
        start(stage.name)
    ctx.log(f"{tag}stage {stage.name} ...")
    t0 = time.perf_counter()
    try:
        if missing:   # in the pipeline, but it failed or gave nothing
            raise DataError(f"nothing to work on: stage {', '.join(map(repr, missing))} "
                            "gave no result")
        value = mod.run(ctx, stage.options) if run is None else run(mod, ctx, stage.options)
    except Exception as exc:
        if on_error is None or not on_error(stage.name, exc):
            raise
        first = " ".join(str(exc).split())[:200]
        ctx.log(f"{tag}stage {stage.name} FAILED ({time.perf_counter() - t0:.1f} s): {first}")
        return
    if value is not None:
        ctx.add(stage.name, value)
    if done is not None:
        done(stage.name, value)
    ctx.log(f"{tag}stage {stage.name} {'done' if value is not None else 'gave nothing'} "
            f"({time.perf_counter() - t0:.1f} s)")


def run_stages(data, names: Sequence[str] = ("ingest", "flowfit"), *, rig=None, model=None,
               options: Mapping[str, Mapping[str, Any]] | None = None,
               map_runs: RunMapper = serial_map) -> Context:
    """Run stages in this process (nothing written) and return the context
    holding their results (``ctx.result("flowfit")``, ...): the notebook form
    of a pipeline. ``options``: {stage name: {option: value}}, checked as a
    pipeline file's are (an unknown stage or option, a badly typed value: a
    ConfigError naming it); ``model``: the valve model to start from
    (default: none, the rig's where one is needed).

    Raises
    ------
    ConfigError
        an unknown stage or option, a bad option value, stages out of order,
        an option for a stage not in ``names``.
    DataError, FitError
        as the stages do; a stage that returns nothing (e.g. tracking without
        position-control runs) leaves no result.
    """
    from .base import one_blas_thread
    from .pipeline import parse_pipeline

    options = dict(options or {})
    stray = sorted(set(options) - set(names))
    if stray:
        raise ConfigError(f"run_stages: options for {', '.join(map(repr, stray))}, which "
                          f"{'is' if len(stray) == 1 else 'are'} not among the stages "
                          f"{list(names)}")
    pipe = parse_pipeline({"pipeline": {"name": "run_stages"},
                           "stages": [{"name": n, **dict(options.get(n, {}))} for n in names]},
                          source="run_stages")
    ctx = Context.for_data(data, rig=rig, model=model, map_runs=map_runs)
    with one_blas_thread():
        execute(pipe, ctx)
    return ctx
