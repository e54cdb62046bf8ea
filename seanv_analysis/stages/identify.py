"""Stage ``identify``: the rig's unpublished constants from its own logs.

Needle geometry (with z0 and C refitted), servo, friction and the line's
bulk modulus (:func:`seanv_analysis.identify.identify_rig`). Later stages
of the same pipeline use the identified rig: ``validate`` and ``discover``
simulate the identified twin, and the identified valve is the model they
start from. ``rig-identified.toml`` holds only the identified keys, in the
rig file's schema, so ``--rig rig-identified.toml`` gives the same twin to
any command.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

from ..report import ReportSection, sections
from .base import Context, Result, tasks_beside
from .dataset import position_runs
from .pipeline import MAX_N_BOOT, MAX_SEED, check_count

__all__ = ["NAME", "NEEDS", "WRITES", "OPTIONS", "DESCRIPTION", "check_option", "run", "write",
           "rig_toml", "servo_flow_paths", "servo_flow_runs", "raw_inputs"]

NAME = "identify"
ORDER = 30
NEEDS = ("ingest",)
FOLDER = "identify"
RESULTS = (Result("identify", "Identification", module="seanv_analysis.identify.result"),)
SECTION = ReportSection("identify", "The rig identified from its logs", sections.identify_section)
WRITES = ("identify/rig-identified.toml", "identify/identify.json", "identify/identify.txt")
DESCRIPTION = ("identify the rig's unpublished constants (needle geometry, servo, friction, "
               "line) from its logs; later stages simulate the identified twin")
#: parts: which constants to identify (geometry, servo, friction, load, flow_path);
#: n_boot: bootstrap resamples of the z0/C refit; seed: its seed
OPTIONS: dict[str, Any] = {"parts": ["geometry", "servo", "friction", "load", "flow_path"],
                           "n_boot": 100, "seed": 0}
#: where its tasks run (the servo's fit, the geometry's flow fits: on the
#: executor's workers beside this process, :func:`identify_rig`'s ``map_tasks``)
TASK_MODULES = ("seanv_analysis.identify.engine",)


def check_option(key: str, value: Any) -> Any:
    # the default lists every part (identify.PARTS; a test keeps them equal):
    # checking a pipeline must not import the identify layer (2 s with scipy.signal)
    PARTS = OPTIONS["parts"]
    if key == "parts":
        if (not isinstance(value, list) or not value
                or not all(isinstance(v, str) and v in PARTS for v in value)):
            raise ValueError(f"a non-empty list of {', '.join(PARTS)}")
        return list(value)
    if key == "n_boot":
        return check_count(value, most=MAX_N_BOOT, what="a number of resamples")
    if key == "seed":
        return check_count(value, most=MAX_SEED, what="a seed")
    return value


def run(ctx: Context, options: Mapping[str, Any]):
    """:class:`~seanv_analysis.identify.Identification` of the data set;
    None when it has neither flow steps nor position-control runs."""
    from ..identify import identify_rig

    opts = {**OPTIONS, **options}
    ds = ctx.result("ingest")
    if ds is None or ds.summary.empty:
        return None
    pos = position_runs(ctx)
    return identify_rig(ds.summary, ctx.rig, position_runs=pos, flow_runs=servo_flow_runs(ctx, pos),
                        parts=tuple(opts["parts"]), n_boot=int(opts["n_boot"]),
                        seed=int(opts["seed"]), log=ctx.log,
                        map_tasks=tasks_beside(ctx))


def servo_flow_paths(ctx: Context, pos) -> list[str]:
    """The flow-step run folders the servo is identified from when no
    position-control run ``pos`` has cam feedback (the first 120); else none."""
    if any("servo" in r.tables and "cam_deg" in r.tables["servo"]
           and r.tables["servo"]["cam_deg"].notna().any() for r in pos):
        return []
    return ctx.result("ingest").kind("flow_step")["path"].tolist()[:120]


def servo_flow_runs(ctx: Context, pos) -> list:
    """The runs of :func:`servo_flow_paths`, read."""
    from ..io.reader import read_run

    return [ctx.loaded_runs[p] if p in ctx.loaded_runs else read_run(p, rig=ctx.rig)
            for p in servo_flow_paths(ctx, pos)]


def raw_inputs(ctx: Context, options: Mapping[str, Any]) -> list[str]:
    """The run folders whose files this stage reads itself, beyond the
    per-run summary (the data-set stage cache's key,
    :mod:`seanv_analysis.batch.stage_memo`): the position-control runs, and
    when the servo is identified and they have no cam feedback, the flow
    steps it is identified from."""
    from .validate import position_paths

    pos = [str(p) for p in position_paths(ctx)]
    parts = {**OPTIONS, **options}["parts"]
    return pos + (servo_flow_paths(ctx, position_runs(ctx)) if "servo" in parts else [])


def rig_toml(result) -> str:
    """rig-identified.toml: the identified keys only, in the rig file's schema,
    each with its 95 % interval and the rig file's value as a comment."""
    from ..io.model_file import dumps_toml

    head = ["# Identified by `seanv-analyze identify` from the data set's own logs.",
            "# Only the keys the data constrain are here; every other key comes from the",
            "# rig file the analysis was given (or the default): pass this file with --rig.",
            "# 95 % intervals and the rig file's values: identify.json / identify.txt.", ""]
    body = dumps_toml({"schema": "seanv-rig/1", "name": "identified from data",
                       **result.overrides()})
    notes = [f"# {c.key}: {c.value:.6g} {c.unit} (rig file {c.default:.6g})"
             for c in result.identified()]
    return "\n".join(head) + body + "\n" + "\n".join(notes) + "\n"


def write(result, folder: Path) -> list[Path]:
    """rig-identified.toml, identify.json and identify.txt."""
    from ..io import write_json_atomic, write_text_atomic

    out = Path(folder)
    return [write_text_atomic(out / "rig-identified.toml", rig_toml(result)),
            write_json_atomic(out / "identify.json", result.to_json_dict()),
            write_text_atomic(out / "identify.txt", result.report() + "\n")]
