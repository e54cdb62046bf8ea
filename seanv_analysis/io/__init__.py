"""Data-contract I/O: reading and validating runs, writing runs and outputs.

Reading: :func:`find_runs`, :func:`read_run`, :func:`read_dataset`,
:func:`iter_dataset` (validated, calibrated :class:`Run` objects; bad runs
collected as :class:`RunError`). Checks live in :mod:`.validate`, raw-unit
conversions in :mod:`.calibrate`. Writing: :func:`write_run`,
:func:`write_table_parquet` and the atomic helpers.
"""
from .atomic import atomic_path, write_json_atomic, write_text_atomic, write_bytes_atomic
from .writer import TABLE_NAMES, units_from_columns, write_run, write_table_parquet
from .run import SUMMARY_COLUMNS, Run, RunMeta
from .calibrate import calibrate
from .reader import (DatasetRead, RunError, contract_columns, dataset_plan, find_runs,
                     is_run_dir, iter_dataset, read_dataset, read_run, read_run_tables,
                     read_runs)
from .hashing import file_sha256

__all__ = ["atomic_path", "write_json_atomic", "write_text_atomic", "write_bytes_atomic",
           "TABLE_NAMES", "units_from_columns", "write_run", "write_table_parquet",
           "SUMMARY_COLUMNS", "Run", "RunMeta", "calibrate", "DatasetRead", "RunError",
           "contract_columns", "find_runs", "is_run_dir", "iter_dataset", "read_dataset",
           "dataset_plan", "read_run_tables", "read_runs",
           "read_run", "file_sha256"]
