"""Arrow columns -> float64 numpy arrays, naming the first bad row when they do not convert.

Every table format parses into an Arrow table; :func:`float_column` turns one
of its columns into the contiguous float64 array the checks and the analysis
use, whatever type the format gave it (float, integer, decimal, text). The
search helpers find the 1-based data row of the first value at fault, for
the one-line error.
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pyarrow as pa

from ..errors import DataError
from .contract import ColumnSpec
from .validate import format_value

__all__ = ["float_column", "to_numpy", "first_non_number", "first_inexact",
           "first_invalid_utf8", "number_hint"]


def float_column(table: pa.Table, name: str, path: Path, col: ColumnSpec,
                 pool: pa.MemoryPool) -> np.ndarray:
    """Column ``name`` of ``table`` as float64 numpy (nulls -> NaN).

    Raises
    ------
    DataError
        a value float64 cannot hold exactly, a text cell that is not a
        number, or a column type that is not numeric.
    """
    column = table.column(name)
    t = column.type
    if not pa.types.is_float64(t):
        if pa.types.is_integer(t) or pa.types.is_floating(t) or pa.types.is_null(t) \
                or pa.types.is_decimal(t):
            try:
                column = column.cast(pa.float64())
            except (pa.ArrowInvalid, pa.ArrowException):
                row, value = first_inexact(column)
                raise DataError(f"value {format_value(value)} ({t}) does not convert exactly to "
                                f"float64; expected a float [{col.unit}] (an integer beyond 2^53, "
                                "e.g. epoch nanoseconds, is not one)",
                                path=path, column=name, row=row) from None
        elif pa.types.is_string(t) or pa.types.is_large_string(t):
            row, value = first_non_number(column)
            if row is None:
                import pyarrow.compute as pc  # text columns only (~40 ms to import)

                column = pc.cast(pc.utf8_trim_whitespace(column), pa.float64())
            else:
                raise DataError(f"value {format_value(value)} is not a number"
                                f"{number_hint(value)}; expected a decimal number [{col.unit}]",
                                path=path, column=name, row=row)
        else:
            raise DataError(f"has type {t}; expected float64 [{col.unit}]", path=path, column=name)
    return to_numpy(column, pool)


def to_numpy(column: pa.ChunkedArray, pool: pa.MemoryPool) -> np.ndarray:
    """float64 column -> contiguous numpy array (nulls -> NaN), concatenating
    chunks in the reader's pool so the memory comes from (and returns to) it."""
    chunks = column.chunks
    if len(chunks) == 1:
        return chunks[0].to_numpy(zero_copy_only=False)
    if not chunks:
        return np.empty(0)
    return pa.concat_arrays(chunks, memory_pool=pool).to_numpy(zero_copy_only=False)


def first_inexact(column: pa.ChunkedArray) -> tuple[int | None, object]:
    """First (1-based row, value) of a numeric column that float64 cannot hold exactly."""
    row = 0
    for chunk in column.chunks:
        for i in range(len(chunk)):
            value = chunk[i].as_py()
            if value is not None:
                try:
                    if float(value) != value:
                        return row + i + 1, value
                except (OverflowError, ValueError, TypeError):
                    return row + i + 1, value
        row += len(chunk)
    return None, "?"


_DECIMAL_COMMA = re.compile(r"^\s*[-+]?\d*,\d+\s*$")


def number_hint(value: object) -> str:
    """A hint for a non-number that looks like a decimal-comma number ("0,35")."""
    if isinstance(value, str) and _DECIMAL_COMMA.match(value):
        return " (decimal comma? write '.' as the decimal point)"
    return ""


def first_non_number(column: pa.ChunkedArray) -> tuple[int | None, object]:
    """First (1-based row, value) of a string column that does not parse as float."""
    import pyarrow.compute as pc

    arr = column.combine_chunks() if isinstance(column, pa.ChunkedArray) else column
    trimmed = pc.utf8_trim_whitespace(arr)

    def ok(a: pa.Array) -> bool:
        try:
            pc.cast(a, pa.float64())
            return True
        except (pa.ArrowInvalid, pa.ArrowException):
            return False

    step = 1 << 16
    for start in range(0, len(trimmed), step):
        chunk = trimmed.slice(start, step)
        if ok(chunk):
            continue
        lo, hi = 0, len(chunk)  # smallest prefix length that fails
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if ok(chunk.slice(0, mid)):
                lo = mid
            else:
                hi = mid
        i = start + hi - 1
        return i + 1, arr[i].as_py()
    return None, None


def first_invalid_utf8(column: pa.ChunkedArray) -> int | None:
    """1-based row of the first value of a binary column that is not UTF-8 text."""
    row = 0
    for chunk in column.chunks:
        for value in chunk.to_pylist():
            row += 1
            if value is not None:
                try:
                    value.decode("utf-8")
                except UnicodeDecodeError:
                    return row
    return None
