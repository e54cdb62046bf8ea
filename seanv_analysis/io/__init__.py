"""Data-contract I/O: reading and validating runs, writing runs and outputs.

Reading: :func:`find_runs`, :func:`read_run`, :func:`read_dataset`,
:func:`iter_dataset` (validated, calibrated :class:`Run` objects; bad runs
collected as :class:`RunError`). Checks live in :mod:`.validate`, raw-unit
conversions in :mod:`.calibrate`, the file formats of run tables in
:mod:`.formats` (:func:`register_format`). Writing: :func:`write_run`,
:func:`write_table_parquet` and the atomic helpers.
"""
from .atomic import atomic_path, write_bytes_atomic, write_json_atomic, write_text_atomic
from .calibrate import calibrate
from .contract import contract_columns
from .dataset import DatasetRead, RunError, dataset_plan, find_runs, is_run_dir
from .formats import FORMATS, TableFormat, register_format
from .hashing import file_sha256
from .reader import iter_dataset, read_dataset, read_run, read_run_tables, read_runs
from .run import SUMMARY_COLUMNS, Run, RunMeta
from .writer import TABLE_NAMES, units_from_columns, write_run, write_table_parquet

__all__ = ["atomic_path", "write_json_atomic", "write_text_atomic", "write_bytes_atomic",
           "TABLE_NAMES", "units_from_columns", "write_run", "write_table_parquet",
           "SUMMARY_COLUMNS", "Run", "RunMeta", "calibrate", "DatasetRead", "RunError",
           "contract_columns", "find_runs", "is_run_dir", "iter_dataset", "read_dataset",
           "dataset_plan", "read_run_tables", "read_runs",
           "read_run", "file_sha256", "FORMATS", "TableFormat", "register_format"]
