"""Data-contract I/O: reading and validating runs, writing runs and outputs."""
from .atomic import atomic_path, write_json_atomic, write_text_atomic, write_bytes_atomic
from .writer import TABLE_NAMES, units_from_columns, write_run, write_table_parquet

__all__ = ["atomic_path", "write_json_atomic", "write_text_atomic", "write_bytes_atomic",
           "TABLE_NAMES", "units_from_columns", "write_run", "write_table_parquet"]
