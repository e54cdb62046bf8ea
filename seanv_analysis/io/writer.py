"""Writers of the data contract (runs, data sets) and of analysis tables.

The simulator writes runs through :func:`write_run`, so simulated data sets
follow exactly the layout the reader validates; tables are written by the
format's own writer (:mod:`.formats`). Analysis tables are Parquet with
units in the schema (:func:`write_table_parquet`).
"""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping

from .atomic import write_json_atomic
from .format_parquet import units_from_columns, write_table_parquet
from .formats import format_named
from .run_tables import RunTables

if TYPE_CHECKING:
    import pandas as pd

__all__ = ["write_run", "write_table_parquet", "units_from_columns", "TABLE_NAMES"]

TABLE_NAMES = ("encoder", "pressure", "servo", "controller")


def write_run(run_dir: str | Path, meta: Mapping[str, Any],
              tables: Mapping[str, pd.DataFrame], *, fmt: str = "csv") -> Path:
    """Write one run folder in the data-contract layout.

    Parameters
    ----------
    run_dir : folder to create (parents too)
    meta : run.json content (``schema`` defaults to ``seanv-run/1``)
    tables : {"encoder": df, "pressure": df, "servo": df[, "controller": df]}
        (a run's :class:`~seanv_analysis.io.run_tables.RunTables` is written
        from its numpy columns when the format can: CSV, without pandas)
    fmt : a table format's name: 'csv' or 'parquet' (any format of
        :mod:`.formats` with a writer)

    Every file is written atomically; floats in CSV with 9 significant digits
    (deterministic, so a seed reproduces a data set bit for bit).
    """
    table_format = format_named(fmt)
    suffix = table_format.suffixes[0]
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    by_columns = table_format.writes_columns and isinstance(tables, RunTables)
    for name in tables:
        if name not in TABLE_NAMES:
            raise ValueError(f"tables: unknown table {name!r}; expected one of {TABLE_NAMES}")
        table = tables.columns(name) if by_columns else tables[name]
        table_format.write(table, run_dir / f"{name}{suffix}")
    meta = {"schema": "seanv-run/1", **dict(meta)}
    write_json_atomic(run_dir / "run.json", meta)
    return run_dir
