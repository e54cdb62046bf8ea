"""One table file of a run: finding it, and reading it validated and calibrated.

:func:`locate_table` finds ``<table><suffix>`` in a run folder for the
suffixes of the registered formats (:mod:`.formats`); :func:`read_table`
scans the file once (hash, binary data, blankness), parses it with its
format's parser into Arrow and turns the contract's columns into checked,
calibrated float64 numpy columns (:func:`read_table_columns`; the reader keeps
them so, and a DataFrame is only built when one is asked for).
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import pyarrow as pa

from ..config import RigConfig
from ..errors import DataError
from .calibrate import calibrate
from .columns import first_invalid_utf8, float_column
from .contract import PRESSURE_UNIT, ColumnSpec, TableSpec, contract_columns, table_specs
from .formats import TableFormat, either, table_formats
from .hashing import remember_sha256
from .scan import memory_pool, scan_file
from .validate import (
    check_finite,
    check_folder_link,
    check_increasing,
    check_link,
    check_pressure,
    check_time_plausible,
    format_value,
    max_pressure_mpag,
    time_limits_s,
)

__all__ = ["folder_listing", "locate_table", "read_table", "read_table_columns"]

#: a folder's entries by lower-cased name (:func:`folder_listing`)
Listing = Mapping[str, Sequence[os.DirEntry]]


def folder_listing(folder: Path) -> Listing | None:
    """The entries of run folder ``folder`` by lower-cased name (one
    directory read for every table of a run), None when it cannot be listed.

    Raises
    ------
    DataError
        ``folder`` is a symbolic link (:func:`~.validate.check_folder_link`).
    """
    check_folder_link(folder)
    out: dict[str, list[os.DirEntry]] = {}
    try:
        with os.scandir(folder) as entries:
            for entry in entries:
                out.setdefault(entry.name.lower(), []).append(entry)
    except OSError:
        return None
    return out


def locate_table(run_dir: Path, spec: TableSpec, kind: str, *,
                 listing: Listing | None = None) -> tuple[Path, TableFormat] | None:
    """The file of table ``spec`` in ``run_dir`` and its format; None when an
    optional table is absent.

    ``listing``: :func:`folder_listing` of ``run_dir`` (which refused a
    linked folder). When it shows the table as exactly one regular file (no
    link, no other entry of a candidate's name in any case) that file is
    taken without a ``stat`` per candidate; anything else is looked at file
    by file, as without it.

    Raises
    ------
    DataError
        a required table missing, the table present in two formats, or an
        entry of its name that is not a regular file.
    """
    formats = table_formats()
    if listing is not None:
        by_name = {f"{spec.name}{suffix}": fmt for fmt in formats for suffix in fmt.suffixes}
        listed = [e for name in by_name for e in listing.get(name.lower(), ())]
        if len(listed) == 1 and listed[0].name in by_name \
                and listed[0].is_file(follow_symlinks=False):
            return run_dir / listed[0].name, by_name[listed[0].name]
    by_path = {run_dir / f"{spec.name}{suffix}": fmt for fmt in formats for suffix in fmt.suffixes}
    candidates = list(by_path)
    found = [p for p in candidates if p.is_file()]
    if len(found) > 1:
        names = [p.name for p in found]
        what = (f"both {names[0]} and {names[1]} exist" if len(found) == 2
                else f"{', '.join(names[:-1])} and {names[-1]} all exist")
        raise DataError(f"{what}; expected exactly one (which one to use is not guessed: "
                        f"remove the other{'s' if len(found) > 2 else ''})", path=found[0])
    if found:
        check_link(run_dir, found[0])
        return found[0], by_path[found[0]]
    for p in candidates:  # there, but not a regular file: never opened (a FIFO would block)
        if os.path.lexists(p):
            what = ("a folder" if p.is_dir() else
                    "a broken or looping symbolic link" if not p.exists() else
                    "not a regular file (pipe, socket or device)")
            titles = either(fmt.title for fmt in formats)
            raise DataError(f"is {what}; expected the {spec.name} table as a {titles} file",
                            path=p)
    if spec.required_file:
        needed = [s.name for s in table_specs().values() if kind in s.kinds]
        raise DataError(f"missing required file (no {either(p.name for p in candidates)}); a "
                        f"{kind} run needs {', '.join(needed)} tables", path=candidates[0])
    return None


def read_table(path: Path, fmt: TableFormat, spec: TableSpec, rig: RigConfig,
               hashes: dict[str, str] | None, size: int):
    """:func:`read_table_columns` as a DataFrame (the same arrays, no copy)."""
    import pandas as pd

    return pd.DataFrame(read_table_columns(path, fmt, spec, rig, hashes, size), copy=False)


def read_table_columns(path: Path, fmt: TableFormat, spec: TableSpec, rig: RigConfig,
                       hashes: dict[str, str] | None, size: int) -> dict[str, Any]:
    """One table file (``size`` bytes, format ``fmt``), validated and calibrated,
    as {column: array}.

    ``hashes``: where to record the file's SHA-256 ({str(path): hex}), None
    to skip hashing. Columns: the contract's engineering columns in contract
    order (float64 numpy arrays), then the file's extra columns as read
    (pandas Series, as ``pyarrow``'s ``to_pandas`` gives them; see
    :func:`seanv_analysis.io.read_run`).
    """
    try:
        scan = scan_file(path, want_hash=hashes is not None, find_nul=fmt.text)
    except OSError as exc:
        raise DataError(f"cannot read file ({exc.strerror}); expected a readable "
                        f"{spec.name} table", path=path) from None
    if hashes is not None:
        hashes[str(path)] = scan.sha256
        remember_sha256(path, scan.sha256, stat=scan.stat)
    if scan.blank:
        raise DataError(f"empty file; expected a header line ({', '.join(contract_columns(spec.name))}) "
                        "and data rows", path=path)
    if scan.nul_offset >= 0:
        with open(path, "rb") as fh:
            line = fh.read(scan.nul_offset).count(b"\n")
        where = "in the header line" if line == 0 else f"in row {line}"
        raise DataError(f"binary data (NUL byte at byte offset {scan.nul_offset}, {where}); "
                        f"expected a UTF-8 {fmt.title} text table", path=path)
    # ``table`` is this frame's only reference: each column is dropped from it
    # once converted, so Arrow's copy of a column is released as numpy's is
    # made (peak: one table in Arrow + numpy, not two).
    pool = memory_pool(size)
    if fmt.parses_bytes:
        table = fmt.parse(path, spec, scan.head, pool, data=scan.data)
    else:
        table = fmt.parse(path, spec, scan.head, pool)
    names = table.column_names
    chosen, used = _choose_columns(names, spec, path)
    n = table.num_rows
    if n == 0:
        raise DataError("header only, no data rows; expected at least one row of numbers",
                        path=path)
    for name in names:  # garbage in an extra column is still garbage
        if name not in used:
            t = table.schema.field(name).type
            if pa.types.is_binary(t) or pa.types.is_large_binary(t):
                row = first_invalid_utf8(table.column(name))
                raise DataError("binary data (not UTF-8 text); expected a text table",
                                path=path, column=name, row=row)
    limit = max_pressure_mpag(rig)
    out: dict[str, object] = {}
    for col, source in chosen:
        if source is None:
            if col.unit != PRESSURE_UNIT:
                continue  # an optional non-pressure column: nothing to default to
            tank = float(rig["supply"].get("tank_pressure_mpag", 0.0))
            out[col.name] = np.broadcast_to(np.float64(tank), n)  # constant: a view, no memory
            continue
        values = float_column(table, source, path, col, pool)
        table = table.drop_columns([source])
        check_finite(values, path=path, column=source, nullable=col.nullable)
        raw = source if source != col.name else None
        if raw is not None:
            values = calibrate(raw, values, rig)
        if col.name == "t_s":
            check_increasing(values, path=path, column=source)
            check_time_plausible(values, path=path, column=source, limits_s=time_limits_s(rig))
        if col.unit == PRESSURE_UNIT:
            check_pressure(values, limit_mpag=limit, path=path, column=col.name, source=raw)
        out[col.name] = values
    for name in table.column_names:  # extra columns, kept as read
        out[name] = table.column(name).to_pandas()
    del table
    return out


def _choose_columns(names: list[str], spec: TableSpec, path: Path
                    ) -> tuple[list[tuple[ColumnSpec, str | None]], set[str]]:
    """Header checks: for each contract column, the file column it is read
    from (itself, a raw alternative, or None when optional and absent), and
    the set of file columns so used.

    Raises
    ------
    DataError
        a repeated column name, two raw alternatives of one column, or a
        required column missing.
    """
    if len(set(names)) != len(names):
        dup = next(n for n in names if names.count(n) > 1)
        raise DataError("appears twice in the header; expected unique column names",
                        path=path, column=dup)
    present = set(names)
    chosen: list[tuple[ColumnSpec, str | None]] = []
    used: set[str] = set()
    for col in spec.columns:
        if col.name in present:
            chosen.append((col, col.name))
            used.add(col.name)
            continue
        raws = [r for r in col.raw if r in present]
        if len(raws) > 1:
            raise DataError(f"raw columns {', '.join(raws)} both given; expected one "
                            "(which to convert is not guessed)", path=path, column=col.name)
        if raws:
            chosen.append((col, raws[0]))
            used.add(raws[0])
        elif col.required:
            alt = f" or a raw column ({', '.join(col.raw)})" if col.raw else ""
            raise DataError(f"missing (header has {format_value(','.join(names))}); expected "
                            f"'{col.name}' [{col.unit}]{alt}", path=path, column=col.name)
        else:
            chosen.append((col, None))
    return chosen, used
