"""The package in a notebook: a data set in, results out, nothing written.

    >>> import seanv_analysis as sa
    >>> ds = sa.load_dataset("data/flow")          # doctest: +SKIP
    >>> fit = sa.flowfit(ds)                       # doctest: +SKIP
    >>> fit.to_frame(); fit.plot()                 # doctest: +SKIP

Each call is the same stage the CLI runs (``seanv_analysis.stages``), on a
context with no output folder. Results print short (``repr``), render as
tables in Jupyter (``_repr_html_``), give DataFrames (``to_frame()``), the
CLI's JSON (``to_json()`` text, ``to_json_dict()`` a dict) and figures on your axes (``plot(ax=None)``).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

__all__ = ["load_dataset", "flowfit"]


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
    return res


def flowfit(ds, *, sides: Sequence[str] = ("supply", "drain"), procedure: str = "joint",
            cam: str = "measured", n_boot: int = 200, seed: int = 0):
    """Fit eq. (3)-(5) per side to a loaded data set (``flowfit`` stage):
    z0 [mm] and C [mm^3/(s deg^2 MPa^0.5)] with 95 % bootstrap intervals.

    Returns
    -------
    FlowFit
    """
    from .fit import fit_flow

    rig = getattr(ds, "rig", None)
    if rig is None:
        from .config import load_rig

        rig = load_rig()
    return fit_flow(ds.summary, rig, sides=tuple(sides), procedure=procedure, cam=cam,
                    n_boot=n_boot, seed=seed)
