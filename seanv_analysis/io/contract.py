"""The data contract as the reader uses it: tables, their columns and units.

``data_schema/contract.toml`` is read once per process (:func:`contract`);
:func:`table_specs` gives its tables as typed specs in contract order, which
is the order tables are read and columns are returned in.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any, Iterable

from ..config import load_contract

__all__ = ["contract", "ColumnSpec", "TableSpec", "table_specs", "contract_columns",
           "canonical_names", "PRESSURE_UNIT"]

#: unit of every pressure column (checked against the plausible maximum)
PRESSURE_UNIT = "MPaG"


@functools.lru_cache(maxsize=1)
def contract() -> dict[str, Any]:
    """The data contract (read once per process; do not modify the result)."""
    return load_contract()


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
    for name, t in contract()["tables"].items():
        cols = tuple(ColumnSpec(c["name"], c.get("unit", ""), bool(c.get("required", False)),
                                bool(c.get("nullable", False)), tuple(c.get("raw", ())))
                     for c in t["columns"])
        specs[name] = TableSpec(name, bool(t.get("required_file", True)), tuple(t["kinds"]), cols)
    return specs


def contract_columns(table: str) -> tuple[str, ...]:
    """Engineering column names of a contract table, ``t_s`` first
    (e.g. ``('t_s', 'position_mm')`` for 'encoder')."""
    return tuple(c.name for c in table_specs()[table].columns)


def canonical_names(names: Iterable[str], spec: TableSpec) -> list[str]:
    """Column names as the contract spells them when they differ only in case
    or surrounding blanks (' T_S ' -> 't_s'); other names without surrounding
    blanks. Units are part of the names, so nothing else is matched.

    Every table format's parser returns its columns under these names.
    """
    known = {n.lower(): n for n in spec.typed_names}
    out = []
    for name in names:
        bare = name.strip()
        out.append(known.get(bare.lower(), bare))
    return out
