"""Stage ``flowfit``: z0 and C of each valve side with 95 % intervals (eq. 3-5).

Q = C (theta - theta_d(p1, dp; z0))^2 sqrt(dp), eq. (5), fitted on the
flow-step runs the filters kept (:func:`seanv_analysis.fit.fit_flow`). The
fitted model is what the later stages (tracking, validate, discover) use.
Each side carries a lack-of-fit check against the repeats (``lack_of_fit``,
``lack_of_fit_ratio``, ``lack_of_fit_p`` in ``flowfit.json``; the test's
details in ``flowfit_details.json``).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

from ..errors import DataError
from ..report import ReportSection, sections
from .base import Context, Result
from .pipeline import MAX_N_BOOT, MAX_SEED, check_count

__all__ = ["NAME", "NEEDS", "WRITES", "OPTIONS", "check_option", "run", "write"]

NAME = "flowfit"
ORDER = 20
NEEDS = ("ingest",)
FOLDER = "flowfit"
RESULTS = (Result("flowfit", "FlowFit", module="seanv_analysis.fit.flowfit"),)
SECTION = ReportSection("flowfit", "Identified flow model (eq. 5)", sections.flowfit_section)
WRITES = ("flowfit/flowfit.json", "flowfit/flowfit_details.json", "flowfit/model.toml",
          "flowfit/model.json", "flowfit/per_run.parquet", "flowfit/per_load.parquet")
DESCRIPTION = "z0 and C per valve side with 95 % intervals (eq. 3-5)"
#: sides: valve sides to fit; procedure: 'joint' (eq. 5 on all runs) or the
#: paper's 'two_step'; cam: 'measured' (servo feedback) or 'commanded';
#: n_boot: bootstrap resamples of the 95 % intervals; seed: their seed
OPTIONS: dict[str, Any] = {"sides": ["supply", "drain"], "procedure": "joint", "cam": "measured",
                           "n_boot": 200, "seed": 0}


#: what its code imports only when it runs (scipy.optimize: the fits;
#: pyarrow.parquet: per_run.parquet), imported beside ingest
#: (:func:`~seanv_analysis.stages.catalogue.stage_imports`)
IMPORTS = ("scipy.optimize", "pyarrow.parquet")
def check_option(key: str, value: Any) -> Any:
    if key == "sides" and (not isinstance(value, list) or not value
                           or any(v not in ("supply", "drain") for v in value)):
        raise ValueError("a non-empty list of 'supply', 'drain'")
    if key == "procedure" and value not in ("joint", "two_step"):
        raise ValueError("'joint' or 'two_step'")
    if key == "cam" and value not in ("measured", "commanded"):
        raise ValueError("'measured' or 'commanded'")
    if key == "n_boot":
        return check_count(value, most=MAX_N_BOOT, what="a number of resamples")
    if key == "seed":
        return check_count(value, most=MAX_SEED, what="a seed")
    return value


def expected(ds) -> bool:
    """The data set has flow steps, so a flow fit was to be expected."""
    return not ds.kind("flow_step").empty


def run(ctx: Context, options: Mapping[str, Any]):
    """:func:`seanv_analysis.fit.fit_flow` on the data set's summary.

    Raises
    ------
    DataError
        no flow-step run in the data set.
    FitError
        no side could be fitted.
    """
    from ..fit import fit_flow

    opts = {**OPTIONS, **options}
    ds = ctx.result("ingest")
    if ds is None or not (ds.summary["kind"] == "flow_step").any():
        raise DataError("no flow_step runs in the data set; expected flow-step runs "
                        "(run.json kind = 'flow_step')", path=ctx.data[0])
    ctx.log(f"flowfit: eq. (3)-(5) per side ({', '.join(opts['sides'])}), "
            f"{opts['n_boot']} bootstrap resamples for the intervals")
    return fit_flow(ds.summary, ctx.rig, sides=tuple(opts["sides"]), procedure=opts["procedure"],
                    cam=opts["cam"], n_boot=opts["n_boot"], seed=opts["seed"])


def raw_inputs(ctx: Context, options: Mapping[str, Any]) -> list[str]:
    """None: the flow fit reads the per-run summary only (the data-set stage
    cache's key, :mod:`seanv_analysis.batch.stage_memo`)."""
    return []


def write(fit, folder: Path) -> list[Path]:
    """``flowfit.json`` (the contract), ``flowfit_details.json``, ``model.json``
    and ``model.toml`` (the valve model, ``--model`` of the other commands),
    ``per_run.parquet``, ``per_load.parquet``; each atomically."""
    from ..io import write_json_atomic, write_table_parquet
    from ..io.model_file import write_model_toml

    out = Path(folder)
    model_dict = fit.model.to_dict()
    return [
        write_json_atomic(out / "flowfit.json", fit.to_json_dict()),
        write_json_atomic(out / "flowfit_details.json", fit.to_dict()),
        write_json_atomic(out / "model.json", model_dict),
        write_model_toml(out / "model.toml", fit.model,
                         header="SEANV valve model fitted by seanv-analyze flowfit "
                                "(paper eq. 3-5). Units: mm, deg, MPa, mm^3/s."),
        write_table_parquet(fit.per_run, out / "per_run.parquet",
                            units={"residual_mm3_s": "mm^3/s", "z_score": ""}),
        write_table_parquet(fit.per_load, out / "per_load.parquet"),
    ]
