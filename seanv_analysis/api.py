"""The package in a notebook: a data set in, results out, nothing written.

    >>> import seanv_analysis as sa
    >>> ds = sa.load_dataset("data/flow")          # doctest: +SKIP
    >>> fit = sa.flowfit(ds)                       # doctest: +SKIP
    >>> fit.to_frame(); fit.plot()                 # doctest: +SKIP

One function per command, with the command's option names (``--shift`` is
``shift=``, ``--n-boot`` is ``n_boot=``, ``--model FILE`` is ``model=`` a
file or a :class:`~seanv_analysis.models.ValveModel``): :func:`load_dataset`
(``ingest``), :func:`flowfit`, :func:`tracking`, :func:`validate`,
:func:`identify`, :func:`discover` and :func:`run` (a whole pipeline, which
writes its outputs as ``seanv-analyze run`` does). Each call runs the stages
the command runs (``seanv_analysis.stages``, options checked as a pipeline
file's are: an unknown or misspelt option is a ``TypeError``, a bad value a
``ConfigError`` naming it), on a context with no output folder. Results
print short (``repr``), render as tables in Jupyter (``_repr_html_``), give
DataFrames (``to_frame()``), the CLI's JSON (``to_json()`` text,
``to_json_dict()`` a dict) and figures on your axes (``plot(ax=None)``).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

__all__ = ["load_dataset", "flowfit", "tracking", "validate", "identify", "discover", "run"]


def load_dataset(data: str | Path | Sequence[str | Path], *, rig: Any = None,
                 method: str = "steady"):
    """Read, check, align and summarise every run of ``data`` (a data set
    folder, a run folder, or several): the ``ingest`` stage.

    Parameters
    ----------
    data : folder(s) in the data contract's layout
    rig : rig config file or :class:`~seanv_analysis.config.RigConfig` (default: shipped)
    method : flow estimate of a flow step: 'steady' (steady-motion window) or
        'peak' (the paper's peak velocity)

    Returns
    -------
    DatasetResult
        ``.summary`` (one row per run), ``.failed`` (bad runs, with why),
        ``.excluded`` (filter counts); ``.rig`` is the rig config used.
    """
    from .stages import Context, dataset

    ctx = Context.for_data(data, rig=rig)
    res = dataset.run(ctx, {"method": method})
    object.__setattr__(res, "rig", ctx.rig)
    object.__setattr__(res, "folders", tuple(ctx.data))
    return res


def flowfit(data, *, side: str = "both", method: str = "steady", procedure: str = "joint",
            cam: str = "measured", n_boot: int = 200, seed: int = 0, rig: Any = None):
    """Fit eq. (3)-(5) per side (``seanv-analyze flowfit``): z0 [mm] and
    C [mm^3/(s deg^2 MPa^0.5)] with 95 % bootstrap intervals.

    Parameters
    ----------
    data : a :func:`load_dataset` result, or data set folder(s) (read here
        with ``method``)
    side : 'supply', 'drain' or 'both'
    method : flow estimate of a flow step when ``data`` is a folder:
        'steady' or the paper's 'peak' (biased: docs/flow_estimate.md)
    procedure : 'joint' (eq. 5 on all runs of a side) or the paper's 'two_step'
    cam : 'measured' (servo feedback) or 'commanded'
    n_boot : bootstrap resamples of the intervals; seed : their seed
    rig : rig config or rig file, when ``data`` is a folder (default: shipped)

    Returns
    -------
    FlowFit
        ``fit.params["supply.C"].value / .stderr / .ci95``, ``fit.eval(...)``.

    Raises
    ------
    ConfigError
        a bad option value (one line naming it).
    """
    if side not in ("supply", "drain", "both"):
        from .errors import ConfigError

        raise ConfigError(f"side = {side!r}; expected 'supply', 'drain' or 'both'")
    options = {"sides": ["supply", "drain"] if side == "both" else [side],
               "procedure": procedure, "cam": cam, "n_boot": n_boot, "seed": seed}
    if not hasattr(data, "summary"):
        from .config import load_rig

        rig = load_rig(rig) if rig is None or isinstance(rig, (str, Path)) else rig
        data = load_dataset(data, rig=rig, method=method)
    from .fit import fit_flow
    from .stages.pipeline import parse_pipeline

    checked = parse_pipeline({"pipeline": {"name": "flowfit"},
                              "stages": [{"name": "flowfit", **options}]},
                             source="flowfit").stage("flowfit").options
    rig = getattr(data, "rig", None)
    if rig is None:
        from .config import load_rig

        rig = load_rig()
    return fit_flow(data.summary, rig, sides=tuple(checked["sides"]),
                    procedure=checked["procedure"], cam=checked["cam"],
                    n_boot=checked["n_boot"], seed=checked["seed"])


def _data_of(data) -> Any:
    """Folder(s) of ``data``: a path, several, or a :func:`load_dataset` result."""
    if isinstance(data, (str, Path)):
        return data
    folders = getattr(data, "folders", None)   # a DatasetResult: the folders it read
    if folders:
        return list(folders)
    if folders is not None:
        raise TypeError("data: a DatasetResult not made by seanv_analysis.load_dataset; "
                        "expected the data folder(s)")
    return list(data)


def _model_of(model, rig) -> Any:
    """A valve model (returned as is), a model file read (``--model FILE``), or None."""
    if model is None or not isinstance(model, (str, Path)):
        return model
    from .config import load_rig
    from .io.model_file import read_model

    return read_model(model, rig=rig if rig is not None and not isinstance(rig, (str, Path))
                      else load_rig(rig))


#: a stage option -> the argument (and CLI option) that sets it, where they differ
_ARGUMENTS = {"shift_s": "shift", "q_range": "range", "threshold_pct": "threshold",
              "parts": "part"}


def _one_stage(data, stage: str, options: dict[str, Any], *, rig, model=None,
               derive: bool = False, before: Sequence[str] = (), missing: str):
    """Run ingest, ``before`` and ``stage`` (:func:`~seanv_analysis.stages.run_stages`)
    and return ``stage``'s result; ``DataError(missing)`` when it gives none."""
    from .config import load_rig
    from .errors import ConfigError, DataError
    from .stages import run_stages

    rig = load_rig(rig) if rig is None or isinstance(rig, (str, Path)) else rig
    try:
        ctx = run_stages(_data_of(data), ["ingest", *before, stage], rig=rig,
                         model=_model_of(model, rig),
                         options={"ingest": {"derive": derive}, stage: options})
    except ConfigError as exc:   # an option said by its argument's name, as the CLI by its flag
        msg = str(exc)
        for option, argument in _ARGUMENTS.items():
            msg = msg.replace(f"option '{option}' =", f"option '{option}' ({argument}=) =")
        raise ConfigError(msg) from None
    value = ctx.result(stage)
    if value is None:
        raise DataError(missing, path=_data_of(data) if isinstance(data, (str, Path)) else None)
    return value


def tracking(data, *, shift: float | None = None,
             range: tuple[float, float] = (-2.5e3, 8e3),  # noqa: A002 - the CLI's --range
             model: Any = None, rig: Any = None):
    """Flow delay and tracking RMSE of the position-control runs
    (``seanv-analyze tracking``; paper Sec. III-C.2, Fig. 7).

    Parameters
    ----------
    data : data set folder(s), or a :func:`load_dataset` result
    shift : delay [s] to compensate (the paper's 0.25, within 0..2 s); None:
        estimated by cross-correlation, with a 95 % interval
    range : (lo, hi) target flow [mm^3/s] of the RMSE (inclusive)
    model : valve model or model file: the target flow of runs without a
        commanded Q_ref (default: none; such runs are skipped, as the CLI does)
    rig : rig config or rig file (default: the shipped one)

    Returns
    -------
    Tracking
        ``rmse_mm3_s`` over the runs with a commanded Q_ref (``pooled``).

    Raises
    ------
    ConfigError
        ``shift`` or ``range`` out of range (one line naming it).
    DataError
        no position-control run in ``data``.
    """
    return _one_stage(data, "tracking", {"shift_s": shift, "q_range": [*map(float, range)]},
                      rig=rig, model=model, derive=True,
                      missing="no position_control run in the data set; expected runs with "
                              "run.json kind = 'position_control'")


def validate(data, *, model: Any = None, rig: Any = None, threshold: float = 80.0,
             controller_model: str = "rig"):
    """Closed-loop validation of the position-control runs: each run's
    controller re-run on the simulated plant (``seanv-analyze validate``).

    Parameters
    ----------
    data : data set folder(s), or a :func:`load_dataset` result
    model : valve model or model file (default: the rig's)
    rig : rig config or rig file (default: the shipped one)
    threshold : position fit [%] under which a run is flagged
    controller_model : 'rig' (the rig file's valve model in the controller)
        or 'plant' (the plant's)

    Returns
    -------
    Validation

    Raises
    ------
    ConfigError
        a bad option value.
    DataError
        no position-control run could be validated.
    """
    return _one_stage(data, "validate", {"threshold_pct": threshold,
                                         "controller_model": controller_model},
                      rig=rig, model=model, derive=True,
                      missing="no position_control run could be validated")


def identify(data, *, rig: Any = None, part: Sequence[str] | None = None, n_boot: int = 100):
    """The rig's unpublished constants from its logs: needle geometry,
    servo, friction, load regulator, line (``seanv-analyze identify``).

    Parameters
    ----------
    data : data set folder(s) (flow steps and position control), or a
        :func:`load_dataset` result
    rig : rig config or rig file to start from (default: the shipped one)
    part : the parts to identify (default: all; ``--part``)
    n_boot : bootstrap resamples of the z0/C refit

    Returns
    -------
    Identification
        ``.rig`` is the identified rig config (``rig-identified.toml``'s keys).
    """
    options: dict[str, Any] = {"n_boot": n_boot, **({"parts": list(part)} if part else {})}
    return _one_stage(data, "identify", options, rig=rig,
                      missing="no flow_step or position_control run to identify from")


def discover(data, *, model: Any = None, rig: Any = None, holdout: str = "chrono",
             seed: int = 0, identify: bool = False):  # noqa: F811 - the CLI's --identify
    """What the flow model (eq. 5) misses, with the held-out error before
    and after (``seanv-analyze discover``).

    Parameters
    ----------
    data : data set folder(s), or a :func:`load_dataset` result
    model : valve model or model file to start from (default: the rig's)
    rig : rig config or rig file (default: the shipped one)
    holdout : 'chrono' (the last 30 % in time held out) or 'kfold'
    seed : seed of the permutation checks and resamples
    identify : identify the rig first and discover on its twin

    Returns
    -------
    Discovery
    """
    return _one_stage(data, "discover", {"holdout": holdout, "seed": seed}, rig=rig,
                      model=model, before=("identify",) if identify else (),
                      missing="nothing to discover")


def run(pipeline: Any, data, *, out: str | Path, workers: int | None = None,
        scheduler: str | None = None, force: bool = False, rig: Any = None,
        no_figures: bool = False, formats: Sequence[str] = ("png", "svg")):
    """A whole pipeline (``seanv-analyze run``): its outputs written under
    ``out`` (report, figures, JSON, manifest), per-run work in worker
    processes and cached.

    Parameters
    ----------
    pipeline : a pipeline file, a shipped name ('paper', 'flowfit',
        'tracking') or its document (a dict)
    data : data set folder(s), or a :func:`load_dataset` result
    out : output folder (``--out``)
    workers : local worker processes (1: serial, here); default the CPU count
    scheduler : a running dask scheduler ``tcp://host:port``
    force : recompute everything (no reuse of the last run or the cache)
    rig : rig config or rig file (default: the shipped one)
    no_figures, formats : as ``--no-figures`` and ``--formats``

    Returns
    -------
    PipelineResult
    """
    from .batch import load_pipeline, parse_pipeline, run_pipeline

    pipe = load_pipeline(pipeline)
    if no_figures or tuple(formats) != ("png", "svg"):
        doc = pipe.to_dict()
        doc["stages"] = [s for s in doc["stages"] if not (no_figures and s["name"] == "figures")]
        for s in doc["stages"]:
            if s["name"] == "figures":
                s["formats"] = list(formats)
        pipe = parse_pipeline(doc, source=pipe.source)
    return run_pipeline(pipe, _data_of(data), out_dir=out, workers=workers, scheduler=scheduler,
                        force=force, rig=rig, reuse=True)
