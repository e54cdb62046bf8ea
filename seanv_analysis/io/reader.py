"""Reading runs and data sets of the data contract (validated, calibrated).

:func:`read_run` turns one run folder into a :class:`~seanv_analysis.io.run.Run`
whose tables are in engineering units and pass every check of
:mod:`seanv_analysis.io.validate`; :func:`read_dataset` does it for every run
of a data set, collecting bad runs instead of stopping at them.

Tables are parsed by pyarrow (multi-threaded C++ CSV and Parquet readers);
checks and calibration are vectorised numpy, so a run costs little more than
parsing its files. Each file is read from disk once: the same bytes are
hashed (SHA-256, for manifests) and parsed.
"""
from __future__ import annotations

import csv as _csv_module
import functools
import hashlib
import os
import re
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.csv as pacsv
import pyarrow.parquet as pq

from ..config import RigConfig, load_rig
from ..errors import DataError, SeanvError
from .hashing import remember_sha256, sha256_bytes
from .calibrate import calibrate, raw_unit
from .run import Run, RunMeta
from .validate import (_contract, _one_line, check_finite, check_increasing, check_pressure,
                       check_rig_overrides, format_value, read_run_json)

__all__ = ["find_runs", "is_run_dir", "read_run", "read_dataset", "iter_dataset",
           "dataset_plan", "read_run_tables", "read_runs",
           "DatasetRead", "RunError", "ColumnSpec", "TableSpec", "table_specs",
           "contract_columns"]

_PRESSURE_UNIT = "MPa gauge"
_DEFAULT_MAX_PRESSURE_MPAG = 50.0
_CHUNK = 1 << 22
_PREFIX = 1 << 16
_POOL: pa.MemoryPool | None = None


#: tables from files at least this large are parsed into the purging pool
_LARGE_FILE = 16 << 20


def _pool(size_bytes: int) -> pa.MemoryPool:
    """Arrow memory pool for parsing a file of ``size_bytes``.

    Large files (>= 16 MiB, long logs): jemalloc with immediate page purging
    when pyarrow has it. Measured on a 60-minute 1 kHz run: the default
    (mimalloc) and system pools keep the CSV reader's freed buffers
    resident (~ the file's size after the parse, peak RSS 760-810 MB for
    170 MB of CSV); jemalloc with decay 0 returns them at once. Small files:
    Arrow's default pool, whose kept buffers are reused by the next parse
    (~1.5x faster than purging pages after every 1-minute run, and what it
    keeps is bounded by one file). ``jemalloc_set_decay_ms`` is
    process-wide for the jemalloc pool.
    """
    global _POOL
    if size_bytes < _LARGE_FILE:
        return pa.default_memory_pool()
    if _POOL is None:
        try:
            pool = pa.jemalloc_memory_pool()
            pa.jemalloc_set_decay_ms(0)
        except (NotImplementedError, pa.ArrowNotImplementedError, AttributeError):
            pool = pa.default_memory_pool()
        _POOL = pool
    return _POOL


# contract ------------------------------------------------------------------

@dataclass(frozen=True)
class ColumnSpec:
    """One column of a contract table (``data_schema/contract.toml``)."""

    name: str
    unit: str
    required: bool
    nullable: bool = False
    raw: tuple[str, ...] = ()


@dataclass(frozen=True)
class TableSpec:
    """One table of a run folder: its columns and the run kinds that need it."""

    name: str
    required_file: bool
    kinds: tuple[str, ...]
    columns: tuple[ColumnSpec, ...]

    @property
    def typed_names(self) -> tuple[str, ...]:
        """Every column name the reader parses as float64 (engineering + raw)."""
        out: list[str] = []
        for c in self.columns:
            out.append(c.name)
            out.extend(c.raw)
        return tuple(out)


@functools.lru_cache(maxsize=1)
def table_specs() -> dict[str, TableSpec]:
    """Table specs of the data contract, in contract order."""
    specs = {}
    for name, t in _contract()["tables"].items():
        cols = tuple(ColumnSpec(c["name"], c.get("unit", ""), bool(c.get("required", False)),
                                bool(c.get("nullable", False)), tuple(c.get("raw", ())))
                     for c in t["columns"])
        specs[name] = TableSpec(name, bool(t.get("required_file", True)), tuple(t["kinds"]), cols)
    return specs


def contract_columns(table: str) -> tuple[str, ...]:
    """Engineering column names of a contract table, ``t_s`` first
    (e.g. ``('t_s', 'position_mm')`` for 'encoder')."""
    return tuple(c.name for c in table_specs()[table].columns)


# results -------------------------------------------------------------------

@dataclass(frozen=True)
class RunError:
    """A run that could not be read: its folder and a one-line reason."""

    path: Path
    message: str

    def __str__(self) -> str:
        return self.message

    def to_json(self) -> dict[str, str]:
        return {"path": str(self.path), "message": self.message}


@dataclass
class DatasetRead:
    """Result of :func:`read_dataset`.

    ``runs`` are in ``started_at`` order (ties: run_id); ``errors`` hold the
    runs that broke the contract, one line each, in folder order.
    """

    path: Path
    runs: list[Run] = field(default_factory=list)
    errors: list[RunError] = field(default_factory=list)

    @property
    def success(self) -> bool:
        """True when every run was read."""
        return not self.errors

    def file_sha256(self) -> dict[str, str]:
        """SHA-256 of every file of the good runs {path: hex digest}."""
        out: dict[str, str] = {}
        for run in self.runs:
            out.update(run.file_sha256)
        return out

    def report(self) -> str:
        lines = [f"{self.path}: {len(self.runs)} run(s) read, {len(self.errors)} bad"]
        lines += [f"  {e.message}" for e in self.errors]
        return "\n".join(lines)


# finding runs ----------------------------------------------------------------

def is_run_dir(path: str | Path) -> bool:
    """True when ``path`` is a folder holding ``run.json`` (a file, or an entry
    of that name that is not a readable file: reading the run says why)."""
    return os.path.lexists(Path(path) / "run.json")


def find_runs(dataset: str | Path) -> list[Path]:
    """Every folder at any depth under ``dataset`` (itself included) that holds
    ``run.json``, sorted by path. Hidden folders (name starting with '.') are
    skipped.

    Raises
    ------
    DataError
        ``dataset`` does not exist or is not a folder.
    """
    root = Path(dataset)
    if not root.exists():
        raise DataError("not found; expected a data set folder or a run folder", path=root)
    if not root.is_dir():
        raise DataError("is a file; expected a data set folder (sub-folders holding run.json) "
                        "or a run folder", path=root)
    found = []
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames[:] = sorted(d for d in dirnames if not d.startswith("."))
        if "run.json" in filenames or "run.json" in dirnames:  # a folder: reading says so
            found.append(Path(dirpath))
    return sorted(found)


# reading one run -------------------------------------------------------------

def read_run(run_dir: str | Path, *, rig: RigConfig | None = None,
             hash_files: bool = True) -> Run:
    """Read, validate and calibrate one run folder.

    Parameters
    ----------
    run_dir : folder holding run.json and the tables (CSV or Parquet)
    rig : rig config (default: the shipped one); the run's own run.json
        "rig" overrides are applied on top of it and the result is ``run.rig``
    hash_files : compute each file's SHA-256 from the bytes read
        (``run.file_sha256``, used by manifests)

    Returns
    -------
    Run
        ``tables`` hold ``t_s`` [s] first, then the contract's engineering
        columns in contract order (position_mm; p_supply/head/load/tank_mpag;
        cam_cmd_deg, cam_deg; x_ref_mm, q_ref_mm3_s), then any extra columns
        of the file as they were read (kept, ignored by the analysis).
        Raw columns (encoder_counts, p_*_v, p_*_kpag, cam_cmd_pulse,
        cam_pulse) are converted with the rig's [calibration] when the
        engineering column is absent and replaced by it; ``p_tank_mpag`` is added from the rig's
        ``supply.tank_pressure_mpag`` (0 MPaG, atmospheric) when absent (a
        read-only constant column: a zero-stride view, no memory).
        A ``started_at`` without time zone is taken as UTC. Column names
        that differ from the contract's only in case or surrounding blanks
        (" T_S") are taken as the contract's; a UTF-8 BOM and CRLF line ends
        are fine.

    Raises
    ------
    DataError
        Any break of the contract; the message names the file, the column,
        the row (1-based data row: the header is not counted, nor blank
        lines), the bad value and what was expected. Cases: run.json missing,
        not JSON, wrong schema version, unknown kind, missing side/cam_deg
        (flow_step) or controller (position_control), bad started_at, unknown
        rig override keys; a required table file missing, or both its .csv
        and .parquet present; an empty file, a header without data rows,
        binary data, a missing column, a non-numeric cell, NaN/inf/empty in
        a required column (nullable cam_deg and q_ref_mm3_s may be empty),
        repeated or decreasing timestamps, a pressure above the rig's
        ``analysis.max_plausible_pressure_mpag`` (kPa or Pa written as MPa);
        a ';'- or tab-separated or non-UTF-8 header, a table entry that is a
        folder, link loop or FIFO, a Parquet integer float64 cannot hold.

    Examples
    --------
    >>> run = read_run("data/flow/supply-load0.35-cam-8.0-r2")  # doctest: +SKIP
    >>> run.tables["pressure"].columns.tolist()                  # doctest: +SKIP
    ['t_s', 'p_supply_mpag', 'p_head_mpag', 'p_load_mpag', 'p_tank_mpag']
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise DataError("not a folder; expected a run folder holding run.json", path=run_dir)
    base = rig if rig is not None else load_rig()
    meta = read_run_json(run_dir, max_pressure_mpag=_max_pressure(base))
    return _read_tables(meta, base, hash_files=hash_files)


def _max_pressure(rig: RigConfig) -> float:
    try:
        return float(rig.analysis.get("max_plausible_pressure_mpag", _DEFAULT_MAX_PRESSURE_MPAG))
    except (KeyError, TypeError, ValueError):
        return _DEFAULT_MAX_PRESSURE_MPAG


def _read_tables(meta: RunMeta, base: RigConfig, *, hash_files: bool) -> Run:
    run_json = meta.path / "run.json"
    rig = base
    if meta.rig_overrides:
        check_rig_overrides(meta.rig_overrides, base.data, path=run_json)
        rig = base.with_overrides(meta.rig_overrides, where=f"{run_json} rig")
    files: dict[str, Path] = {"run.json": run_json}
    hashes: dict[str, str] = {}
    if hash_files:
        data = run_json.read_bytes()
        hashes[str(run_json)] = digest = sha256_bytes(data)
        remember_sha256(run_json, digest)
    todo: list[tuple[TableSpec, Path]] = []
    for spec in table_specs().values():
        if meta.kind not in spec.kinds:
            continue
        path = _locate(meta.path, spec, meta.kind)
        if path is not None:
            files[spec.name] = path
            todo.append((spec, path))
    per_table = [{} if hash_files else None for _ in todo]
    sizes = [_file_size(path) for _, path in todo]
    jobs = [functools.partial(_read_table, path, spec, rig, h, size)
            for (spec, path), h, size in zip(todo, per_table, sizes)]
    tables = dict(zip((spec.name for spec, _ in todo), _run_in_order(jobs, sum(sizes))))
    for h in per_table:
        hashes.update(h or {})
    return Run(meta=meta, tables=tables, rig=rig, files=files, file_sha256=hashes)


#: a run's tables are read side by side on threads when they hold at least
#: this many bytes together (one post-processes while another parses)
_CONCURRENT_MIN_BYTES = 8 << 20


def _run_in_order(jobs: list, size: int) -> list:
    """Results of ``jobs`` in order; on threads for large runs. The first
    job (in order) that fails raises, as reading one table after the other
    would."""
    if len(jobs) < 2 or size < _CONCURRENT_MIN_BYTES:
        return [job() for job in jobs]
    with ThreadPoolExecutor(max_workers=len(jobs), thread_name_prefix="seanv-table") as pool:
        futures = [pool.submit(job) for job in jobs]
    return [f.result() for f in futures]


def _locate(run_dir: Path, spec: TableSpec, kind: str) -> Path | None:
    csv, parquet = run_dir / f"{spec.name}.csv", run_dir / f"{spec.name}.parquet"
    has_csv, has_pq = csv.is_file(), parquet.is_file()
    if has_csv and has_pq:
        raise DataError(f"both {csv.name} and {parquet.name} exist; expected exactly one "
                        "(which one to use is not guessed: remove the other)", path=csv)
    if has_csv:
        return csv
    if has_pq:
        return parquet
    for p in (csv, parquet):  # there, but not a regular file: never opened (a FIFO would block)
        if os.path.lexists(p):
            what = ("a folder" if p.is_dir() else
                    "a broken or looping symbolic link" if not p.exists() else
                    "not a regular file (pipe, socket or device)")
            raise DataError(f"is {what}; expected the {spec.name} table as a CSV or Parquet file",
                            path=p)
    if spec.required_file:
        needed = [s.name for s in table_specs().values() if kind in s.kinds]
        raise DataError(f"missing required file (no {csv.name} or {parquet.name}); a "
                        f"{kind} run needs {', '.join(needed)} tables", path=csv)
    return None


@dataclass(frozen=True)
class _Scan:
    size: int            # bytes looked at (the whole file only when hashed)
    sha256: str | None
    nul_offset: int      # first NUL byte, -1 if none
    blank: bool          # only whitespace (or nothing)
    head: bytes = b""    # the first 64 KiB (the CSV header is read from it)


def _scan(path: Path, *, want_hash: bool, find_nul: bool) -> _Scan:
    """One streaming pass over a file: SHA-256, first NUL byte, blankness.

    Streams in 4 MiB chunks, so the raw bytes are never held in memory at
    once; the parse that follows reads the file again from the page cache.
    Without ``want_hash`` only the first 64 KiB are looked at (a NUL byte
    further down in a numeric column still fails the parse, and the error
    path then reports it as binary data).
    """
    h = hashlib.sha256() if want_hash else None
    size, nul, blank, head = 0, -1, True, b""
    with open(path, "rb") as fh:
        while chunk := fh.read(_CHUNK if want_hash else _PREFIX):
            if not size:
                head = chunk[:_PREFIX]
            if h is not None:
                h.update(chunk)
            if find_nul and nul < 0:
                i = chunk.find(b"\x00")
                if i >= 0:
                    nul = size + i
            if blank and not chunk.isspace():
                blank = False
            size += len(chunk)
            if not want_hash:
                if len(chunk) == _PREFIX:
                    blank = False  # more follows: not known to be blank
                break
    return _Scan(size, h.hexdigest() if h is not None else None, nul, blank, head)


def _file_size(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError:
        return 0  # reading it says why


def _read_table(path: Path, spec: TableSpec, rig: RigConfig,
                hashes: dict[str, str] | None, size: int) -> pd.DataFrame:
    """One table file (``size`` bytes), validated and calibrated."""
    is_csv = path.suffix == ".csv"
    try:
        scan = _scan(path, want_hash=hashes is not None, find_nul=is_csv)
    except OSError as exc:
        raise DataError(f"cannot read file ({exc.strerror}); expected a readable "
                        f"{spec.name} table", path=path) from None
    if hashes is not None:
        hashes[str(path)] = scan.sha256
        remember_sha256(path, scan.sha256)
    if scan.blank:
        raise DataError(f"empty file; expected a header line ({', '.join(contract_columns(spec.name))}) "
                        "and data rows", path=path)
    if scan.nul_offset >= 0:
        with open(path, "rb") as fh:
            line = fh.read(scan.nul_offset).count(b"\n")
        where = "in the header line" if line == 0 else f"in row {line}"
        raise DataError(f"binary data (NUL byte at byte offset {scan.nul_offset}, {where}); "
                        "expected a UTF-8 CSV text table", path=path)
    # ``table`` is this frame's only reference: each column is dropped from it
    # once converted, so Arrow's copy of a column is released as numpy's is
    # made (peak: one table in Arrow + numpy, not two).
    pool = _pool(size)
    table = _parse_csv(path, spec, scan.head, pool) if is_csv else _parse_parquet(path, spec)
    names = table.column_names
    if len(set(names)) != len(names):
        dup = next(n for n in names if names.count(n) > 1)
        raise DataError("appears twice in the header; expected unique column names",
                        path=path, column=dup)
    present = set(names)
    chosen: list[tuple[ColumnSpec, str | None]] = []
    used: set[str] = set()
    for col in spec.columns:  # header checks first, then values
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
    n = table.num_rows
    if n == 0:
        raise DataError("header only, no data rows; expected at least one row of numbers",
                        path=path)
    for name in names:  # garbage in an extra column is still garbage
        if name not in used:
            t = table.schema.field(name).type
            if pa.types.is_binary(t) or pa.types.is_large_binary(t):
                row = _first_invalid_utf8(table.column(name))
                raise DataError("binary data (not UTF-8 text); expected a text table",
                                path=path, column=name, row=row)
    limit = _max_pressure(rig)
    out: dict[str, object] = {}
    for col, source in chosen:
        if source is None:
            if col.unit != _PRESSURE_UNIT:
                continue  # an optional non-pressure column: nothing to default to
            tank = float(rig["supply"].get("tank_pressure_mpag", 0.0))
            out[col.name] = np.broadcast_to(np.float64(tank), n)  # constant: a view, no memory
            continue
        values = _float_column(table, source, path, col, pool)
        table = table.drop_columns([source])
        check_finite(values, path=path, column=source, nullable=col.nullable)
        raw = source if source != col.name else None
        if raw is not None:
            values = calibrate(raw, values, rig)
        if col.name == "t_s":
            check_increasing(values, path=path, column=source)
        if col.unit == _PRESSURE_UNIT:
            check_pressure(values, limit_mpag=limit, path=path, column=col.name, source=raw)
        out[col.name] = values
    for name in table.column_names:  # extra columns, kept as read
        out[name] = table.column(name).to_pandas()
    del table
    return pd.DataFrame(out, copy=False)


def _float_column(table: pa.Table, name: str, path: Path, col: ColumnSpec,
                  pool: pa.MemoryPool) -> np.ndarray:
    column = table.column(name)
    t = column.type
    if not pa.types.is_float64(t):
        if pa.types.is_integer(t) or pa.types.is_floating(t) or pa.types.is_null(t) \
                or pa.types.is_decimal(t):
            try:
                column = column.cast(pa.float64())
            except (pa.ArrowInvalid, pa.ArrowException):
                row, value = _first_inexact(column)
                raise DataError(f"value {format_value(value)} ({t}) does not convert exactly to "
                                f"float64; expected a float [{col.unit}] (an integer beyond 2^53, "
                                "e.g. epoch nanoseconds, is not one)",
                                path=path, column=name, row=row) from None
        elif pa.types.is_string(t) or pa.types.is_large_string(t):
            row, value = _first_non_number(column)
            if row is None:
                column = pc.cast(pc.utf8_trim_whitespace(column), pa.float64())
            else:
                raise DataError(f"value {format_value(value)} is not a number"
                                f"{_number_hint(value)}; expected a decimal number [{col.unit}]",
                                path=path, column=name, row=row)
        else:
            raise DataError(f"has type {t}; expected float64 [{col.unit}]", path=path, column=name)
    return _to_numpy(column, pool)


def _first_inexact(column: pa.ChunkedArray) -> tuple[int | None, object]:
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


def _number_hint(value: object) -> str:
    """A hint for a non-number that looks like a decimal-comma number ("0,35")."""
    if isinstance(value, str) and _DECIMAL_COMMA.match(value):
        return " (decimal comma? write '.' as the decimal point)"
    return ""


def _to_numpy(column: pa.ChunkedArray, pool: pa.MemoryPool) -> np.ndarray:
    """float64 column -> contiguous numpy array (nulls -> NaN), concatenating
    chunks in the reader's pool so the memory comes from (and returns to) it."""
    chunks = column.chunks
    if len(chunks) == 1:
        return chunks[0].to_numpy(zero_copy_only=False)
    if not chunks:
        return np.empty(0)
    return pa.concat_arrays(chunks, memory_pool=pool).to_numpy(zero_copy_only=False)


# CSV ---------------------------------------------------------------------------

def _parse_csv(path: Path, spec: TableSpec, head: bytes, pool: pa.MemoryPool) -> pa.Table:
    """Parse a CSV table; ``head``: its first 64 KiB (already read by :func:`_scan`)."""
    header = _csv_header_names(head, path, spec)
    names = _canonical_names(header, spec) if header is not None else None
    typed = set(spec.typed_names)
    if names is None:
        types = {name: pa.float64() for name in typed}
    else:  # keyed by the names as written (" T_S" is parsed as t_s)
        types = {raw: pa.float64() for raw, name in zip(header, names) if name in typed}
    try:
        # the file's read buffers come from the reader's pool too (else from
        # Arrow's default pool, which keeps ~ the file's size resident after)
        with pa.OSFile(str(path), "r", memory_pool=pool) as source:
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


def _canonical_names(names: list[str], spec: TableSpec) -> list[str]:
    """Column names as the contract spells them when they differ only in case
    or surrounding blanks (' T_S ' -> 't_s'); other names without surrounding
    blanks. Units are part of the names, so nothing else is matched."""
    known = {n.lower(): n for n in spec.typed_names}
    out = []
    for name in names:
        bare = name.strip()
        out.append(known.get(bare.lower(), bare))
    return out


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
        if not ends and len(head) == _PREFIX:
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
            name = _canonical_names([written], spec)[0]
            unit = ""
            for c in spec.columns:
                if name == c.name:
                    unit = c.unit
                elif name in c.raw:
                    unit = raw_unit(name)
            row, value = _locate_bad_number(data, written)
            return DataError(f"value {format_value(value)} is not a number"
                             f"{_number_hint(value)}; expected a decimal number [{unit}]",
                             path=path, column=name, row=row)
    m = _NCOLS.search(message)
    if m:
        expected = int(m.group(1))
        row, got = _locate_bad_field_count(data, expected)
        return DataError(f"row has {got if got is not None else m.group(2)} fields, the header has "
                         f"{expected}; expected one value per header column", path=path, row=row)
    first = _one_line(message)[:200]
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
        row = _first_invalid_utf8(table.column(0))
        if row is not None:
            return row, table.column(0)[row - 1].as_py()
        return None, "?"
    row, value = _first_non_number(table.column(0))
    return row, value if row is not None else "?"


def _first_non_number(column: pa.ChunkedArray) -> tuple[int | None, object]:
    """First (1-based row, value) of a string column that does not parse as float."""
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


def _first_invalid_utf8(column: pa.ChunkedArray) -> int | None:
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


# Parquet -------------------------------------------------------------------

def _parse_parquet(path: Path, spec: TableSpec) -> pa.Table:
    try:
        table = pq.read_table(path)  # (no pool argument: Arrow's default pool)
    except (pa.ArrowException, OSError, ValueError) as exc:
        raise DataError(f"not a readable Parquet file ({_one_line(str(exc))[:160]}); expected a "
                        f"Parquet table with columns {', '.join(contract_columns(spec.name))}",
                        path=path) from None
    names = _canonical_names(table.column_names, spec)
    return table if names == table.column_names else table.rename_columns(names)


# data sets -----------------------------------------------------------------

def dataset_plan(path: str | Path, *, rig: RigConfig | None = None
                 ) -> tuple[list[RunMeta], list[RunError], RigConfig]:
    """The metadata phase of reading a data set, without touching any table.

    Every run's run.json is read and checked; returns the good runs'
    :class:`RunMeta` in ``started_at`` order (repeated run ids refused), the
    :class:`RunError` items of bad metadata (sorted by path) and the base rig.
    :func:`read_run_tables` then reads one run's tables (also in a worker
    process: a ``RunMeta`` and a ``RigConfig`` pickle).

    Raises
    ------
    DataError
        ``path`` missing, or no run.json at any depth.
    """
    root = Path(path)
    dirs = find_runs(root)
    if not dirs:
        raise DataError("no run.json found at any depth; expected a data set folder (sub-folders "
                        "holding run.json) or a run folder", path=root)
    base = rig if rig is not None else load_rig()
    limit = _max_pressure(base)
    metas: list[RunMeta] = []
    bad: list[RunError] = []
    for d in dirs:
        try:
            metas.append(read_run_json(d, max_pressure_mpag=limit))
        except (SeanvError, OSError) as exc:
            bad.append(RunError(d, _one_line(exc)))
    metas.sort(key=lambda m: (m.started_at, m.run_id, str(m.path)))
    seen: dict[str, Path] = {}
    good: list[RunMeta] = []
    for m in metas:
        if m.run_id in seen:
            bad.append(RunError(m.path, _one_line(DataError(
                f"field 'run_id': '{m.run_id}' is also the run id of {seen[m.run_id]}; expected "
                "run ids unique in the data set", path=m.path / "run.json"))))
            continue
        seen[m.run_id] = m.path
        good.append(m)
    bad.sort(key=lambda e: str(e.path))
    return good, bad, base


def read_run_tables(meta: RunMeta, rig: RigConfig, *, hash_files: bool = True) -> Run | RunError:
    """The tables of one run of :func:`dataset_plan` (validated and
    calibrated), or its :class:`RunError` when they break the contract."""
    try:
        return _read_tables(meta, rig, hash_files=hash_files)
    except (SeanvError, OSError) as exc:
        return RunError(meta.path, _one_line(exc))


def iter_dataset(path: str | Path, *, rig: RigConfig | None = None,
                 hash_files: bool = True) -> Iterator[Run | RunError]:
    """Yield each run of a data set (or the one run of a run folder), one at a
    time, so a caller can process and drop runs as it goes.

    First every run's run.json is read (:func:`dataset_plan`);
    :class:`RunError` items for bad metadata (and repeated run ids) come
    first, then the good runs in ``started_at`` order, each a :class:`Run` or
    a :class:`RunError` when its tables break the contract.

    Raises
    ------
    DataError
        ``path`` missing, or no run.json at any depth.
    """
    good, bad, base = dataset_plan(path, rig=rig)
    yield from bad
    yield from read_runs(good, base, hash_files=hash_files)


def read_runs(metas: list[RunMeta], rig: RigConfig, *,
              hash_files: bool = True) -> Iterator[Run | RunError]:
    """:func:`read_run_tables` of each run, in order, reading one run ahead.

    The next run's files are parsed on a helper thread (Arrow's CSV/Parquet
    readers and the checks on numpy arrays run without the GIL) while the
    caller works on the current one; at most two runs are in memory.
    """
    if len(metas) < 2:
        for m in metas:
            yield read_run_tables(m, rig, hash_files=hash_files)
        return
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="seanv-read") as pool:
        ahead = pool.submit(read_run_tables, metas[0], rig, hash_files=hash_files)
        for i in range(len(metas)):
            current = ahead
            if i + 1 < len(metas):
                ahead = pool.submit(read_run_tables, metas[i + 1], rig, hash_files=hash_files)
            yield current.result()


def read_dataset(path: str | Path, *, rig: RigConfig | None = None,
                 hash_files: bool = True) -> DatasetRead:
    """Read every run of a data set; a bad run never stops the others.

    Parameters
    ----------
    path : a data set folder (any folder whose sub-folders, at any depth,
        hold run.json) or a single run folder
    rig : rig config (default: the shipped one); each run's run.json "rig"
        overrides are applied on top of it
    hash_files : see :func:`read_run`

    Returns
    -------
    DatasetRead
        ``runs`` in started_at order, ``errors`` (path + one-line message).

    Raises
    ------
    DataError
        ``path`` missing or holding no run.json at all.

    Examples
    --------
    >>> ds = read_dataset("data/flow")   # doctest: +SKIP
    >>> [r.run_id for r in ds.runs][:2], len(ds.errors)  # doctest: +SKIP
    """
    result = DatasetRead(Path(path))
    for item in iter_dataset(path, rig=rig, hash_files=hash_files):
        (result.errors if isinstance(item, RunError) else result.runs).append(item)
    result.errors.sort(key=lambda e: str(e.path))
    return result
