"""A run's tables: numpy columns inside, pandas DataFrames when asked for.

The reader and the simulator hold each table of a run as its columns
(``{column: ndarray}``, ``t_s`` first); ``run.tables["encoder"]`` builds the
DataFrame on first use (from the same arrays, no copy) and keeps it. The
per-run analysis reads :meth:`RunTables.columns` instead and never builds a
frame: per run that saves the frames' construction and pandas' column
look-ups (pandas 3 keys columns by an Arrow-string index, rebuilt per new
frame), about half of what summarising a short run cost.

Once a table's DataFrame exists it is the table: :meth:`RunTables.columns`
then reads the frame, so a frame changed in place is what the analysis sees.
"""
from __future__ import annotations

from collections.abc import Mapping, MutableMapping
from typing import Any, Iterator

import numpy as np

__all__ = ["RunTables", "table_columns"]


class RunTables(MutableMapping):
    """{table name: DataFrame} of one run, stored as numpy columns until a
    DataFrame is asked for.

    Parameters
    ----------
    tables : {name: DataFrame or {column: array}} (a DataFrame is kept as it
        is; a column mapping is kept as its arrays, in its order)

    Examples
    --------
    >>> t = RunTables({"encoder": {"t_s": np.array([0.0, 0.001]),
    ...                            "position_mm": np.array([5.0, 5.1])}})
    >>> t.columns("encoder")["position_mm"].tolist()    # numpy, no DataFrame built
    [5.0, 5.1]
    >>> t["encoder"].columns.tolist()                   # the DataFrame, built now
    ['t_s', 'position_mm']
    """

    def __init__(self, tables: Mapping[str, Any] | None = None):
        self._order: dict[str, None] = {}
        self._columns: dict[str, dict[str, Any]] = {}
        self._frames: dict[str, Any] = {}
        for name, table in (tables or {}).items():
            self[name] = table

    # -- the numpy side -----------------------------------------------------
    def columns(self, name: str) -> dict[str, np.ndarray]:
        """Table ``name`` as {column: numpy array}, in column order, without
        building a DataFrame (when it has one, its columns).

        The arrays are the table's own (not copies): read them, do not write.

        Raises
        ------
        KeyError
            no table ``name``.
        """
        frame = self._frames.get(name)
        if frame is not None:
            return {str(col): series.to_numpy() for col, series in frame.items()}
        cols = self._columns[name]
        return {col: (v if isinstance(v, np.ndarray) else np.asarray(v)) for col, v in cols.items()}

    def n_rows(self, name: str) -> int:
        """Number of rows of table ``name`` (KeyError when absent)."""
        frame = self._frames.get(name)
        if frame is not None:
            return len(frame)
        cols = self._columns[name]
        return len(next(iter(cols.values()))) if cols else 0

    # -- the mapping (pandas) side -------------------------------------------
    def __getitem__(self, name: str):
        frame = self._frames.get(name)
        if frame is None:
            cols = self._columns[name]  # KeyError when absent
            import pandas as pd

            frame = pd.DataFrame(cols, copy=False)
            self._frames[name] = frame
            del self._columns[name]  # the frame holds the arrays now, and is the table
        return frame

    def __setitem__(self, name: str, table: Any) -> None:
        self._frames.pop(name, None)
        self._columns.pop(name, None)
        if isinstance(table, Mapping):
            self._columns[name] = dict(table)
        else:
            self._frames[name] = table
        self._order[name] = None

    def __delitem__(self, name: str) -> None:
        del self._order[name]
        self._frames.pop(name, None)
        self._columns.pop(name, None)

    def __contains__(self, name: object) -> bool:
        return name in self._order

    def __iter__(self) -> Iterator[str]:
        return iter(list(self._order))

    def __len__(self) -> int:
        return len(self._order)

    def __repr__(self) -> str:
        parts = [f"{n}: {self.n_rows(n)} rows" for n in self._order]
        return f"RunTables({', '.join(parts)})"


def table_columns(tables: Mapping[str, Any], name: str) -> dict[str, np.ndarray]:
    """{column: numpy array} of table ``name`` of ``tables`` (a
    :class:`RunTables`, or a plain {name: DataFrame})."""
    if isinstance(tables, RunTables):
        return tables.columns(name)
    return {str(col): series.to_numpy() for col, series in tables[name].items()}
