"""Reading runs and data sets of the data contract (validated, calibrated).

:func:`read_run` turns one run folder into a :class:`~seanv_analysis.io.run.Run`
whose tables are in engineering units and pass every check of
:mod:`seanv_analysis.io.validate`; :func:`read_dataset` does it for every run
of a data set, collecting bad runs instead of stopping at them.

Tables are parsed by pyarrow (multi-threaded C++ CSV and Parquet readers);
checks and calibration are vectorised numpy, so a run costs little more than
parsing its files. Each file is read from disk once for its hash; a file
of up to 4 MiB is parsed from those bytes, a larger one read once more,
from the page cache, by the parser. A run folder is listed once to find its
tables. Finding runs and the metadata phase live in :mod:`.dataset`, one
table file in :mod:`.table_file`, file formats in :mod:`.formats`; their
public names are re-exported here.
"""
from __future__ import annotations

import functools
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Callable, Iterator, TypeVar

from ..config import RigConfig, check_rig, load_rig
from ..errors import ConfigError, DataError, SeanvError
from .contract import ColumnSpec, TableSpec, contract_columns, table_specs
from .dataset import DatasetRead, RunError, dataset_plan, find_runs, is_run_dir
from .formats import TableFormat
from .hashing import remember_sha256
from .run import Run, RunMeta
from .run_tables import RunTables
from .scan import file_size, scan_file
from .table_file import folder_listing, locate_table, read_table_columns
from .validate import check_rig_overrides, max_pressure_mpag, one_line, read_run_json

__all__ = ["find_runs", "is_run_dir", "read_run", "read_dataset", "iter_dataset",
           "dataset_plan", "read_run_tables", "read_runs",
           "DatasetRead", "RunError", "ColumnSpec", "TableSpec", "table_specs",
           "contract_columns"]

_T = TypeVar("_T")

#: a run's tables are read side by side on threads when they hold at least
#: this many bytes together (one post-processes while another parses)
_CONCURRENT_MIN_BYTES = 8 << 20


def read_run(run_dir: str | Path, *, rig: RigConfig | None = None,
             hash_files: bool = True) -> Run:
    """Read, validate and calibrate one run folder.

    Parameters
    ----------
    run_dir : folder holding run.json and the tables (each in one format of
        :mod:`.formats`: CSV or Parquet)
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
        rig override keys; a required table file missing, or present in two
        formats (.csv and .parquet); an empty file, a header without data rows,
        binary data, a missing column, a non-numeric cell, NaN/inf/empty in
        a required column (nullable cam_deg and q_ref_mm3_s may be empty),
        repeated or decreasing timestamps, a pressure above the rig's
        ``analysis.max_plausible_pressure_mpag`` (kPa or Pa written as MPa);
        a ';'- or tab-separated or non-UTF-8 header, a table entry that is a
        folder, link loop or FIFO, a Parquet integer float64 cannot hold.
    ConfigError
        contract.toml ``table_formats`` and the format registry disagree.

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
    meta = read_run_json(run_dir, max_pressure_mpag=max_pressure_mpag(base))
    return _read_tables(meta, base, hash_files=hash_files)


def _read_tables(meta: RunMeta, base: RigConfig, *, hash_files: bool) -> Run:
    """The tables of the run of ``meta`` (its rig overrides applied to ``base``)."""
    run_json = meta.path / "run.json"
    rig = base
    if meta.rig_overrides:
        check_rig_overrides(meta.rig_overrides, base.data, path=run_json)
        rig = base.with_overrides(meta.rig_overrides, where=f"{run_json} rig")
        try:
            check_rig(rig.data, where="field 'rig'")   # the keys that bound each other
        except ConfigError as exc:
            raise DataError(str(exc), path=run_json) from None
    files: dict[str, Path] = {"run.json": run_json}
    hashes: dict[str, str] = {}
    if hash_files:
        scan = scan_file(run_json, want_hash=True, find_nul=False)
        hashes[str(run_json)] = scan.sha256
        remember_sha256(run_json, scan.sha256, stat=scan.stat)
    todo: list[tuple[TableSpec, Path, TableFormat]] = []
    listing = folder_listing(meta.path)
    for spec in table_specs().values():
        if meta.kind not in spec.kinds:
            continue
        found = locate_table(meta.path, spec, meta.kind, listing=listing)
        if found is not None:
            files[spec.name] = found[0]
            todo.append((spec, *found))
    per_table = [{} if hash_files else None for _ in todo]
    sizes = [file_size(path) for _, path, _ in todo]
    jobs = [functools.partial(read_table_columns, path, fmt, spec, rig, h, size)
            for (spec, path, fmt), h, size in zip(todo, per_table, sizes)]
    # numpy columns; each table's DataFrame is built when first asked for
    tables = RunTables(dict(zip((spec.name for spec, _, _ in todo),
                                _run_in_order(jobs, sum(sizes)))))
    for h in per_table:
        hashes.update(h or {})
    return Run(meta=meta, tables=tables, rig=rig, files=files, file_sha256=hashes)


def _run_in_order(jobs: list[Callable[[], _T]], size: int) -> list[_T]:
    """Results of ``jobs`` in order; on threads for large runs. The first
    job (in order) that fails raises, as reading one table after the other
    would."""
    if len(jobs) < 2 or size < _CONCURRENT_MIN_BYTES:
        return [job() for job in jobs]
    with ThreadPoolExecutor(max_workers=len(jobs), thread_name_prefix="seanv-table") as pool:
        futures = [pool.submit(job) for job in jobs]
    return [f.result() for f in futures]


def read_run_tables(meta: RunMeta, rig: RigConfig, *, hash_files: bool = True) -> Run | RunError:
    """The tables of one run of :func:`dataset_plan` (validated and
    calibrated), or its :class:`RunError` when they break the contract."""
    try:
        return _read_tables(meta, rig, hash_files=hash_files)
    except (SeanvError, OSError) as exc:
        return RunError(meta.path, one_line(exc))


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
