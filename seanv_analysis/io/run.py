"""Typed in-memory form of one run of the data contract."""
from __future__ import annotations

from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping

from ..config import RigConfig
from .run_tables import RunTables, table_columns

if TYPE_CHECKING:  # pandas loads when a table's DataFrame is first asked for
    import pandas as pd

__all__ = ["RunMeta", "Run", "SUMMARY_COLUMNS"]

# Columns of the per-run summary table (one row per run) that ingest/derive
# produce and flowfit, discover and the report consume. Units in the names.
SUMMARY_COLUMNS = {
    "run_id": "str",
    "kind": "str",                  # flow_step | position_control
    "side": "str",                  # supply | drain | '' (position_control)
    "started_at": "datetime64[ns, UTC]",
    "run_index": "int64",           # 0-based order of the run in the data set (started_at order)
    "load_mpag": "float64",         # run.json load, or median p_load when null
    "cam_deg": "float64",           # commanded cam angle of a flow_step (NaN otherwise)
    "cam_measured_deg": "float64",  # median servo feedback during the step window (NaN if none)
    "cam_approach": "float64",      # +1 cam reached its angle moving up, -1 moving down, 0 unknown
    "q_mm3_s": "float64",           # per-run flow of the default method
    "q_peak_mm3_s": "float64",      # paper's method: max (supply) / min (drain) velocity x area
    "q_steady_mm3_s": "float64",    # steady-motion estimate
    "dp_mpa": "float64",            # side's pressure difference over the same window as q_mm3_s
    "p1_mpa": "float64",            # side's upstream pressure over that window
    "dp_sealed_mpa": "float64",     # the other (sealed) valve's pressure difference over that
                                    # window (supply run: p_head - p_tank; drain: p_supply - p_head)
    "flow_method": "str",           # 'steady' | 'peak'
    "motion_steady": "bool",        # the actuator moved at a steady speed in the steady window
                                    # (False: stick-slip, not settled, did not move, not a flow step)
    "excluded": "str",              # '' or one of: leakage, friction, cam_range, invalid
    "excluded_detail": "str",       # human-readable reason
}


@dataclass(frozen=True)
class RunMeta:
    """run.json of one run, validated.

    ``load_mpag`` None means it varies (read p_load_mpag); ``side`` and
    ``cam_deg`` are set for flow_step runs; ``controller`` for
    position_control runs. ``extra`` keeps unknown fields.
    """

    run_id: str
    kind: str
    started_at: datetime
    path: Path
    load_mpag: float | None = None
    side: str | None = None
    cam_deg: float | None = None
    controller: dict[str, Any] | None = None
    rig_overrides: dict[str, Any] = field(default_factory=dict)
    extra: dict[str, Any] = field(default_factory=dict)

    def to_json_dict(self) -> dict[str, Any]:
        """run.json content (data contract ``seanv-run/1``)."""
        started = self.started_at
        text = started.isoformat().replace("+00:00", "Z") if hasattr(started, "isoformat") else str(started)
        out: dict[str, Any] = {"schema": "seanv-run/1", "run_id": self.run_id, "kind": self.kind,
                               "started_at": text, "load_mpag": self.load_mpag}
        if self.kind == "flow_step":
            out.update(side=self.side, cam_deg=self.cam_deg)
        if self.controller is not None:
            out["controller"] = dict(self.controller)
        out["rig"] = dict(self.rig_overrides)
        out.update(self.extra)
        return out


@dataclass
class Run:
    """One validated run: metadata, calibrated tables in engineering units,
    and the rig config with this run's overrides applied.

    ``tables`` maps 'encoder', 'pressure', 'servo' (and 'controller' for
    position_control) to DataFrames whose first column is ``t_s``
    (strictly increasing) and whose other columns are the contract's names
    (position_mm, p_*_mpag, cam_cmd_deg, cam_deg, x_ref_mm, q_ref_mm3_s).
    It is a :class:`~seanv_analysis.io.run_tables.RunTables` (a plain dict
    given here is wrapped in one): each DataFrame is built on first use,
    and ``run.tables.columns(name)`` gives a table's numpy columns without
    building it.
    All streams on one time base: :func:`seanv_analysis.signals.align.align_run`.
    """

    meta: RunMeta
    tables: Mapping[str, pd.DataFrame]
    rig: RigConfig
    #: files the run was read from: {'run.json' | table name: path}
    files: dict[str, Path] = field(default_factory=dict)
    #: SHA-256 of each file read {str(path): hex digest} (empty if not hashed)
    file_sha256: dict[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.tables, RunTables):
            self.tables = RunTables(self.tables)

    @property
    def run_id(self) -> str:
        return self.meta.run_id

    @property
    def kind(self) -> str:
        return self.meta.kind

    @property
    def span_s(self) -> tuple[float, float]:
        """Time span [s] covered by every table (the alignment overlap)."""
        ts = [table_columns(self.tables, name)["t_s"] for name in self.tables]
        return max(float(t[0]) for t in ts if t.size), min(float(t[-1]) for t in ts if t.size)
