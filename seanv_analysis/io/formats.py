"""Table formats of a run folder: the one place the reader and writer learn a file type.

Each table of a run (encoder, pressure, servo, controller) is one file
``<table><suffix>``. :data:`FORMATS` maps every suffix to its
:class:`TableFormat`; the reader looks for a table under each suffix of
:func:`table_suffixes` and parses what it finds with that suffix's
``parse``; :func:`~seanv_analysis.io.writer.write_run` writes with a
format's ``write``.

``data_schema/contract.toml`` ``table_formats`` names the formats the data
contract guarantees (it is shared with the rig software), in the order they
are looked for; this registry says how each is read. :func:`table_formats`
checks them when reading starts: a format named in the contract without a
parser is a :class:`~seanv_analysis.errors.ConfigError` rather than a format
silently ignored. A registered format the contract does not name is an
extension of this package, looked for after the contract's.

Adding a format is one module ``io/format_<name>.py``: a parse function (see
:data:`ParseFn`), optionally a writer, and one :func:`register_format` call
at its end; this module imports every ``format_*`` module of the package.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Iterable

import pyarrow as pa

from ..config import schema_dir
from ..errors import ConfigError
from .contract import TableSpec, contract

if TYPE_CHECKING:
    import pandas as pd

__all__ = ["TableFormat", "ParseFn", "WriteFn", "FORMATS", "register_format",
           "registered_formats", "table_formats", "table_suffixes", "format_named", "either",
           "load_format_modules"]

#: ``parse(path, spec, head, pool) -> pyarrow.Table``: the table file at
#: ``path`` as an Arrow table whose columns carry the contract's names
#: (:func:`~seanv_analysis.io.contract.canonical_names`), any column types
#: (the reader converts the contract's columns to float64 and checks them).
#: ``head`` is the file's first 64 KiB (already read: for sniffing a text
#: header), ``pool`` the Arrow memory pool to parse into. Raise
#: :class:`~seanv_analysis.errors.DataError` naming the file for a file that
#: cannot be parsed. A format with ``parses_bytes`` also takes ``data=``: the
#: file's whole content when the reader already holds it (a small file,
#: read in one piece for its hash), else None (read the file at ``path``).
ParseFn = Callable[[Path, TableSpec, bytes, pa.MemoryPool], pa.Table]

#: ``write(df, path)``: write one run table atomically
#: (:func:`~seanv_analysis.io.atomic.atomic_path`).
WriteFn = Callable[["pd.DataFrame", Path], object]


@dataclass(frozen=True)
class TableFormat:
    """One file format a run's tables may be stored in.

    Attributes
    ----------
    name : as contract.toml ``table_formats`` and ``write_run(fmt=...)`` name it
    title : as messages name it ("CSV")
    suffixes : file name endings, with the dot (".csv")
    parse : see :data:`ParseFn`
    write : see :data:`WriteFn`; None when runs are never written in it
    text : a text format: a NUL byte in the file is reported as binary data
        (with its row) before parsing
    writes_columns : ``write`` also takes the table as {column: numpy array}
        (what a run read or simulated holds, so it is written without
        building a DataFrame)
    parses_bytes : ``parse`` also takes ``data=`` (see :data:`ParseFn`), so
        a small file is parsed from the bytes already read, not opened again
    """

    name: str
    title: str
    suffixes: tuple[str, ...]
    parse: ParseFn
    write: WriteFn | None = None
    text: bool = False
    writes_columns: bool = False
    parses_bytes: bool = False


#: every registered format by suffix, in registration order
FORMATS: dict[str, TableFormat] = {}


def register_format(fmt: TableFormat) -> TableFormat:
    """Add ``fmt`` to :data:`FORMATS` under each of its suffixes (replacing a
    format of the same name); returns ``fmt``.

    Raises
    ------
    ValueError
        no suffix, a suffix without its leading dot, or a suffix another
        format already has.
    """
    if not fmt.suffixes or any(not s.startswith(".") or len(s) < 2 for s in fmt.suffixes):
        raise ValueError(f"format {fmt.name!r}: suffixes {fmt.suffixes!r}; expected file name "
                         "endings with their dot, like ('.csv',)")
    for suffix in fmt.suffixes:
        other = FORMATS.get(suffix)
        if other is not None and other.name != fmt.name:
            raise ValueError(f"format {fmt.name!r}: suffix {suffix!r} is already read by format "
                             f"{other.name!r}; expected a suffix of its own")
    for suffix in [s for s, f in FORMATS.items() if f.name == fmt.name]:
        del FORMATS[suffix]
    for suffix in fmt.suffixes:
        FORMATS[suffix] = fmt
    return fmt


def registered_formats() -> list[TableFormat]:
    """Every registered format once, in registration order."""
    out: dict[str, TableFormat] = {}
    for fmt in FORMATS.values():
        out.setdefault(fmt.name, fmt)
    return list(out.values())


def table_formats() -> tuple[TableFormat, ...]:
    """The formats a run's tables may use: the contract's, in contract.toml
    ``table_formats`` order (the first is the one named when a table is
    missing), then the package's extensions in registration order.

    Raises
    ------
    ConfigError
        the contract names a format no module registers.
    """
    named = contract().get("table_formats", ())
    known = {fmt.name: fmt for fmt in registered_formats()}
    if len(named) == len(known) and set(named) == known.keys():
        return tuple(known[n] for n in named)  # the usual case (checked for every table read)
    where = f"{schema_dir() / 'contract.toml'}: table_formats"
    missing = [n for n in named if n not in known]
    if missing:
        raise ConfigError(f"{where} names {either(repr(n) for n in missing)} but no parser is "
                          f"registered for it; expected formats of seanv_analysis.io "
                          f"({', '.join(known)}), or a module io/format_<name>.py registering it")
    order = [*dict.fromkeys(named), *(n for n in known if n not in named)]
    return tuple(known[n] for n in order)  # a name listed twice counts once


def table_suffixes() -> tuple[str, ...]:
    """File name endings the reader looks for, in :func:`table_formats` order."""
    return tuple(s for fmt in table_formats() for s in fmt.suffixes)


def format_named(name: str) -> TableFormat:
    """The format ``name`` (as contract.toml names it) that runs can be written in.

    Raises
    ------
    ValueError
        no such format, or it has no ``write``.
    """
    writable = {fmt.name: fmt for fmt in table_formats() if fmt.write is not None}
    if name not in writable:
        raise ValueError(f"fmt: expected {either(repr(n) for n in writable)}, got {name!r}")
    return writable[name]


def either(words: Iterable[str]) -> str:
    """'a', 'a or b', 'a, b or c': alternatives in a message."""
    words = list(words)
    if not words:
        return "nothing"
    return words[0] if len(words) == 1 else f"{', '.join(words[:-1])} or {words[-1]}"


def load_format_modules() -> None:
    """Import every ``format_*`` module of :mod:`seanv_analysis.io`: each
    registers its format at its end (:func:`register_format`)."""
    import importlib
    import pkgutil

    from .. import io as package

    for info in pkgutil.iter_modules(package.__path__):
        if info.name.startswith("format_"):
            importlib.import_module(f"{package.__name__}.{info.name}")


load_format_modules()
