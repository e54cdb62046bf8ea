"""Dataset-level entry point of discovery: read, summarise, filter, discover."""
from __future__ import annotations

from pathlib import Path

from ..config import RigConfig, load_rig
from ..summary import DatasetSummary, summarize_dataset
from ..models import ValveModel
from .engine import discover_flow_steps
from .result import Discovery

__all__ = ["summarize_dataset", "discover_dataset", "DatasetSummary"]


def discover_dataset(path: str | Path, *, model: ValveModel | None = None,
                     rig: RigConfig | None = None, holdout: str = "chrono",
                     seed: int = 0) -> tuple[Discovery, DatasetSummary]:
    """Discovery on a data set folder: flow-step runs drive the static model."""
    rig = rig or load_rig()
    ds = summarize_dataset(path, rig=rig)
    model = model or ValveModel.from_rig(rig)
    leak = float(rig.analysis.get("leakage_flow_mm3_s", 50.0))
    return discover_flow_steps(ds.summary, model=model, holdout=holdout, seed=seed,
                               leakage_mm3_s=leak), ds
