"""The CSV table format: comma-separated text with a header line.

Parsed by pyarrow's multi-threaded CSV reader with the contract's columns
typed float64. The header is sniffed first from the file's first 64 KiB, so
a ';'- or tab-separated or non-UTF-8 header is named as such; when pyarrow
refuses the file, the row and value at fault are looked up (a slow path,
only taken on bad input).
"""
from __future__ import annotations

import csv as _csv_module
import io
import re
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping

import numpy as np
import pyarrow as pa
import pyarrow.csv as pacsv

from ..errors import DataError
from .atomic import atomic_path
from .calibrate import raw_unit
from .columns import first_invalid_utf8, first_non_number, number_hint
from .contract import TableSpec, canonical_names, contract_columns
from .scan import HEAD_BYTES
from .validate import format_value, one_line

if TYPE_CHECKING:
    import pandas as pd

__all__ = ["parse_csv", "write_csv", "round_significant", "CSV_DIGITS"]


#: significant digits of the floats :func:`write_csv` writes
CSV_DIGITS = 9


#: 10**k for k = 0..22: exact doubles
_POW10 = 10.0 ** np.arange(23)


def round_significant(x: np.ndarray, digits: int = CSV_DIGITS) -> np.ndarray:
    """``x`` rounded to ``digits`` significant digits, each value the double
    nearest its decimal (so the shortest repr prints at most ``digits``
    digits); NaN, inf and 0 unchanged. Vectorised (no per-value formatting);
    the same values as printf's ``%.9g`` but where the scaled binary value
    falls on a tie, which may round to the other neighbour.

    A value needing 0..22 decimals (1e-14 <= |x| < 1e9 at 9 digits: every
    value of a rig's log) is ``rint(x 10^k) / 10^k``, 10^k exact, all in one
    pass; the others (|x| >= 1e9, or tiny) are done apart."""
    x = np.asarray(x, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        decimals = (digits - 1) - np.floor(np.log10(np.abs(x)))   # NaN, +-inf for 0, inf, NaN
    up = (decimals >= 0) & (decimals <= 22)  # 10**k exact: rint(x 10^k) / 10^k correctly rounded
    p = _POW10[np.where(up, decimals, 0).astype(np.intp)]
    out = np.rint(x * p) / p
    if up.all():
        return out
    np.copyto(out, x, where=~up)   # NaN, inf, 0 as they are; the rest below
    rest = np.flatnonzero(~up & np.isfinite(decimals))
    if rest.size:
        v, k = x[rest], decimals[rest].astype(np.int64)
        down = (k < 0) & (k >= -22)
        r = np.empty_like(v)
        q = 10.0 ** (-k[down])
        r[down] = np.rint(v[down] / q) * q
        tiny = ~down  # |v| >= 1e31 or < 1e-14 at 9 digits: rare, formatted one by one
        r[tiny] = [float(f"{t:.{digits}g}") for t in v[tiny]]
        out[rest] = r
    return out


def write_csv(df: pd.DataFrame | Mapping[str, Any], path: Path) -> None:
    """Write ``df`` (a DataFrame, or {column: numpy array}) as CSV atomically
    through pyarrow's writer: floats rounded to :data:`CSV_DIGITS`
    significant digits (deterministic, so a seed reproduces a data set bit
    for bit), empty cells for NaN, no index. Both forms of the same table
    give the same bytes."""
    cols = {}
    items = df.items() if isinstance(df, Mapping) else ((c, df[c]) for c in df.columns)
    names = []
    for name, column in items:
        names.append(name)
        values = np.asarray(column) if isinstance(df, Mapping) else column.to_numpy()
        if values.dtype.kind == "f":
            cols[str(name)] = _float_array(round_significant(values))
        else:
            cols[str(name)] = pa.array(values, from_pandas=True)
    table = pa.table(cols)
    header = io.StringIO()
    _csv_module.writer(header, lineterminator="\n").writerow([str(c) for c in names])
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(header.getvalue().encode())
        if table.num_rows:
            pacsv.write_csv(table, fh, pacsv.WriteOptions(include_header=False,
                                                          quoting_style="needed"))


def _float_array(values: np.ndarray) -> pa.Array:
    """float64 Arrow array of ``values`` (a float64 array this module made), NaN
    as null: ``pa.array(values, mask=np.isnan(values))`` without pyarrow's
    pandas checks, which import pandas (~0.3 s of a cold ``simulate``)."""
    values = np.ascontiguousarray(values, dtype=np.float64)
    nan = np.isnan(values)
    valid = pa.py_buffer(np.packbits(~nan, bitorder="little")) if nan.any() else None
    return pa.Array.from_buffers(pa.float64(), values.size, [valid, pa.py_buffer(values)])


def parse_csv(path: Path, spec: TableSpec, head: bytes, pool: pa.MemoryPool, *,
              data: bytes | None = None) -> pa.Table:
    """Parse a CSV table into Arrow, the contract's columns as float64 under
    the contract's names; ``head``: the file's first 64 KiB (already read by
    :func:`~seanv_analysis.io.scan.scan_file`), where the header is sniffed.
    ``pool``: the Arrow memory pool to parse into. ``data``: the file's
    whole content when already read (parsed from memory, the file is not
    opened again), None to read ``path``.

    Raises
    ------
    DataError
        naming the file and, where found, the column, row and value at fault.
    """
    header = _csv_header_names(head, path, spec)
    names = canonical_names(header, spec) if header is not None else None
    typed = set(spec.typed_names)
    if names is None:
        types = {name: pa.float64() for name in typed}
    else:  # keyed by the names as written (" T_S" is parsed as t_s)
        types = {raw: pa.float64() for raw, name in zip(header, names) if name in typed}
    try:
        # the file's read buffers come from the reader's pool too (else from
        # Arrow's default pool, which keeps ~ the file's size resident after)
        with (pa.BufferReader(data) if data is not None
              else pa.OSFile(str(path), "r", memory_pool=pool)) as source:
            table = pacsv.read_csv(source, convert_options=pacsv.ConvertOptions(
                column_types=types), memory_pool=pool)
    except UnicodeDecodeError:
        raise DataError("header line is not UTF-8 text (binary data?); expected column "
                        f"names like {','.join(contract_columns(spec.name))}", path=path) from None
    except (pa.ArrowInvalid, pa.ArrowException) as exc:
        raise _diagnose_csv(path.read_bytes(), path, spec, str(exc), header=header) from None
    if names is not None and names != header and table.num_columns == len(names):
        table = table.rename_columns(names)
    return table


def _csv_header_names(head: bytes, path: Path, spec: TableSpec) -> list[str] | None:
    """Names of the CSV's header line as the CSV reader takes them, from the
    file's first 64 KiB ``head`` (None when the first line is not found in
    it: the parse then decides).

    Raises DataError for a header that is not UTF-8, a file holding only a
    byte-order mark and blanks, and a header separated by ';' or tabs.
    """
    expected = ",".join(contract_columns(spec.name))
    pos = 3 if head.startswith(b"\xef\xbb\xbf") else 0
    while True:  # the first non-empty line (the CSV reader skips empty ones)
        ends = [i for i in (head.find(b"\n", pos), head.find(b"\r", pos)) if i >= 0]
        if not ends and len(head) == HEAD_BYTES:
            return None
        end = min(ends) if ends else len(head)
        if end > pos or not ends:
            break
        pos = end + 1
    line = head[pos:end]
    try:
        text = line.decode("utf-8")
    except UnicodeDecodeError as exc:
        bad = format_value(line[exc.start:exc.start + 1])
        raise DataError(f"header line is not UTF-8 text (byte {bad} at offset {exc.start}; "
                        f"another encoding such as Latin-1?); expected UTF-8 column names like "
                        f"{expected}", path=path) from None
    if not text.strip():
        if not head.decode("utf-8-sig", errors="replace").strip():
            raise DataError(f"empty file; expected a header line "
                            f"({', '.join(contract_columns(spec.name))}) and data rows", path=path)
        return None  # blank first line: the CSV reader skips it
    try:  # same quoting rules as pyarrow's reader for a header line
        names = next(_csv_module.reader([text]))
    except (_csv_module.Error, StopIteration):
        return None
    if len(names) == 1:
        for sep, what in ((";", "semicolon"), ("\t", "tab")):
            if sep in names[0]:
                raise DataError(f"header {format_value(text)} is {what}-separated; expected "
                                f"comma-separated columns ({expected}) with '.' as the decimal "
                                "point", path=path)
    return names


_CONVERSION = re.compile(r"In CSV column #(\d+): .*conversion error")
_NCOLS = re.compile(r"Expected (\d+) columns, got (\d+)")


def _diagnose_csv(data: bytes, path: Path, spec: TableSpec, message: str, *,
                  header: list[str] | None = None) -> DataError:
    """Slow path after pyarrow refused a CSV: find the row and value at fault.
    ``header``: the header names as written (else split from ``data``)."""
    nul = data.find(b"\x00")
    if nul >= 0:
        line = data.count(b"\n", 0, nul)
        where = "in the header line" if line == 0 else f"in row {line}"
        return DataError(f"binary data (NUL byte at byte offset {nul}, {where}); expected a "
                         "UTF-8 CSV text table", path=path)
    m = _CONVERSION.search(message)
    if m:
        header = header if header is not None else _csv_header(data)
        idx = int(m.group(1))
        if idx < len(header):
            written = header[idx]
            name = canonical_names([written], spec)[0]
            unit = ""
            for c in spec.columns:
                if name == c.name:
                    unit = c.unit
                elif name in c.raw:
                    unit = raw_unit(name)
            row, value = _locate_bad_number(data, written)
            return DataError(f"value {format_value(value)} is not a number"
                             f"{number_hint(value)}; expected a decimal number [{unit}]",
                             path=path, column=name, row=row)
    m = _NCOLS.search(message)
    if m:
        expected = int(m.group(1))
        row, got = _locate_bad_field_count(data, expected)
        return DataError(f"row has {got if got is not None else m.group(2)} fields, the header has "
                         f"{expected}; expected one value per header column", path=path, row=row)
    first = one_line(message)[:200]
    return DataError(f"not a readable CSV table ({first}); expected comma-separated text with "
                     "a header line", path=path)


def _csv_header(data: bytes) -> list[str]:
    pos = 3 if data.startswith(b"\xef\xbb\xbf") else 0
    while True:  # the first non-empty line (the CSV reader skips empty ones)
        end = data.find(b"\n", pos)
        line = (data[pos:] if end < 0 else data[pos:end]).rstrip(b"\r")
        if line or end < 0:
            break
        pos = end + 1
    first = line.decode("utf-8", errors="replace")
    return [h.strip().strip('"') for h in first.split(",")]


def _locate_bad_number(data: bytes, name: str) -> tuple[int | None, object]:
    try:
        return _locate_bad_number_in(data, name)
    except (pa.ArrowException, KeyError, UnicodeDecodeError):  # the error still names the column
        return None, "?"


def _locate_bad_number_in(data: bytes, name: str) -> tuple[int | None, object]:
    try:
        table = pacsv.read_csv(
            pa.BufferReader(data),
            convert_options=pacsv.ConvertOptions(include_columns=[name],
                                                 column_types={name: pa.string()},
                                                 strings_can_be_null=True))
    except (pa.ArrowInvalid, pa.ArrowException):
        table = pacsv.read_csv(
            pa.BufferReader(data),
            convert_options=pacsv.ConvertOptions(include_columns=[name],
                                                 column_types={name: pa.binary()},
                                                 strings_can_be_null=True))
        row = first_invalid_utf8(table.column(0))
        if row is not None:
            return row, table.column(0)[row - 1].as_py()
        return None, "?"
    row, value = first_non_number(table.column(0))
    return row, value if row is not None else "?"


def _locate_bad_field_count(data: bytes, expected: int) -> tuple[int | None, int | None]:
    row = 0
    for line in data.split(b"\n")[1:]:
        line = line.rstrip(b"\r")
        if not line:
            continue
        row += 1
        got = line.count(b",") + 1
        if got != expected:
            return row, got
    return None, None


from .formats import TableFormat, register_format  # noqa: E402  (the registry imports this module)

register_format(TableFormat("csv", "CSV", (".csv",), parse_csv, write_csv, text=True,
                            writes_columns=True, parses_bytes=True))
