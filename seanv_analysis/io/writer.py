"""Writers of the data contract (runs, data sets) and of analysis tables.

The simulator writes runs through :func:`write_run`, so simulated data sets
follow exactly the layout the reader validates.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Mapping

import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from .atomic import atomic_path, write_json_atomic

__all__ = ["write_run", "write_table_parquet", "units_from_columns", "TABLE_NAMES"]

TABLE_NAMES = ("encoder", "pressure", "servo", "controller")

# Unit of a column from its name suffix (data contract: units in names).
_SUFFIX_UNITS = (
    ("_mm3_s", "mm^3/s"), ("_mm_s", "mm/s"), ("_mpag", "MPa gauge"), ("_mpa", "MPa"),
    ("_deg", "deg"), ("_mm", "mm"), ("_s", "s"), ("_n", "N"), ("_hz", "Hz"),
    ("_pct", "%"),
)


def units_from_columns(columns) -> dict[str, str]:
    """Map each column to the unit its name carries ('' when none)."""
    out = {}
    for c in columns:
        out[c] = next((u for suf, u in _SUFFIX_UNITS if str(c).endswith(suf)), "")
    return out


def write_table_parquet(df: pd.DataFrame, path: str | Path, *,
                        units: Mapping[str, str] | None = None,
                        metadata: Mapping[str, Any] | None = None) -> Path:
    """Write ``df`` as Parquet atomically, units in the schema metadata.

    Each field carries ``unit`` metadata and the file carries a JSON
    ``seanv.units`` map (plus ``metadata`` under ``seanv.meta``).
    """
    units = dict(units_from_columns(df.columns), **(units or {}))
    table = pa.Table.from_pandas(df, preserve_index=False)
    fields = [f.with_metadata({b"unit": units.get(f.name, "").encode()}) for f in table.schema]
    meta = dict(table.schema.metadata or {})
    meta[b"seanv.units"] = json.dumps(units).encode()
    if metadata:
        meta[b"seanv.meta"] = json.dumps(metadata, default=str).encode()
    table = table.cast(pa.schema(fields, metadata=meta))
    with atomic_path(path) as tmp:
        pq.write_table(table, tmp)
    return Path(path)


def write_run(run_dir: str | Path, meta: Mapping[str, Any],
              tables: Mapping[str, pd.DataFrame], *, fmt: str = "csv") -> Path:
    """Write one run folder in the data-contract layout.

    Parameters
    ----------
    run_dir : folder to create (parents too)
    meta : run.json content (``schema`` defaults to ``seanv-run/1``)
    tables : {"encoder": df, "pressure": df, "servo": df[, "controller": df]}
    fmt : 'csv' or 'parquet'

    Every file is written atomically; floats in CSV with 9 significant digits
    (deterministic, so a seed reproduces a data set bit for bit).
    """
    if fmt not in ("csv", "parquet"):
        raise ValueError(f"fmt: expected 'csv' or 'parquet', got {fmt!r}")
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    for name, df in tables.items():
        if name not in TABLE_NAMES:
            raise ValueError(f"tables: unknown table {name!r}; expected one of {TABLE_NAMES}")
        target = run_dir / f"{name}.{fmt}"
        if fmt == "csv":
            with atomic_path(target) as tmp:
                df.to_csv(tmp, index=False, float_format="%.9g", na_rep="")
        else:
            write_table_parquet(df, target)
    meta = {"schema": "seanv-run/1", **dict(meta)}
    write_json_atomic(run_dir / "run.json", meta)
    return run_dir
