"""Content hashes of input files, computed once per process.

The reader hashes each file from the bytes it has already read (no second
pass over the disk) and remembers the digest here; the manifest writer asks
:func:`file_sha256`, which only reads and hashes a file it has not seen (or
that changed size, modification or change time, or inode since).
"""
from __future__ import annotations

import dataclasses
import datetime
import enum
import errno
import functools
import hashlib
import math
import os
import stat
import threading
from pathlib import Path, PurePath
from typing import Any

from .run_tables import RunTables

__all__ = ["file_sha256", "remember_sha256", "code_version", "content_sha256"]

_CACHE: dict[tuple[int, int, int, int, int], str] = {}
_LOCK = threading.Lock()
_CHUNK = 1 << 22


def _key(path: Path, st: os.stat_result | None = None) -> tuple[int, int, int, int, int]:
    """(device, inode, size, mtime, ctime) of the file ``path`` leads to
    (one ``stat``, or ``st`` when given; every path of one file shares it):
    a same-size edit whose mtime was put back still changes the ctime
    (which no user can set), a file replaced by another the inode."""
    st = os.stat(path) if st is None else st
    return (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)


def remember_sha256(path: str | Path, digest: str, *, stat: os.stat_result | None = None) -> None:
    """Record the digest of ``path`` (as it is now on disk) for later look-ups.

    ``stat``: the file's ``os.stat``/``os.fstat`` result taken after the
    bytes hashed were read (saves a ``stat`` of ``path``).
    """
    try:
        key = _key(path, stat)
    except OSError:
        return
    with _LOCK:
        _CACHE[key] = digest


def file_sha256(path: str | Path) -> str:
    """Hex SHA-256 of a file's content; reuses a digest already computed in
    this process while the file's size, modification and change times and
    inode are unchanged.

    Raises
    ------
    OSError
        the file cannot be read, or is not a regular file (a FIFO or a
        device is never read: it could block or never end)."""
    path = Path(path)
    st = os.stat(path)
    if not stat.S_ISREG(st.st_mode):   # a FIFO, a device (/dev/zero): never read
        raise OSError(errno.EINVAL, "not a regular file", str(path))
    key = _key(path, st)
    with _LOCK:
        hit = _CACHE.get(key)
    if hit is not None:
        return hit
    h = hashlib.sha256()
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    with open(fd, "rb") as fh:
        if not stat.S_ISREG(os.fstat(fd).st_mode):   # replaced since the stat
            raise OSError(errno.EINVAL, "not a regular file", str(path))
        while chunk := fh.read(_CHUNK):
            h.update(chunk)
    digest = h.hexdigest()
    with _LOCK:
        _CACHE[key] = digest
    return digest


@functools.lru_cache(maxsize=1)
def code_version() -> str:
    """Package version plus a hash of every source file of the package
    (``0.1.0+1a2b3c4d5e6f``): an edited stage invalidates cached results
    even when the version number was not bumped."""
    from .. import __version__

    pkg = Path(__file__).resolve().parents[1]  # the package
    h = hashlib.sha256()
    for path in sorted(pkg.rglob("*.py")):
        h.update(path.relative_to(pkg).as_posix().encode())
        h.update(path.read_bytes())
    return f"{__version__}+{h.hexdigest()[:12]}"


def content_sha256(value: Any) -> str:
    """Hex SHA-256 of a result's content, the same in every process.

    Walks plain data (None, bool, int, float bit for bit, str, bytes, paths),
    dicts (items in their order), sets (sorted by their items' digests),
    lists and tuples, enums, numpy arrays and scalars (dtype, shape, raw
    bytes), pandas DataFrames, Series and Index (column names, dtypes,
    values), dates and times (ISO text) and dataclasses (class name and
    fields), tagging each type;
    never ``id()``, ``hash()`` or pickle. Raises TypeError for anything else.
    """
    h = hashlib.sha256()
    _feed(h, value)
    return h.hexdigest()


def _feed(h, v: Any) -> None:
    import numpy as np
    import pandas as pd

    if v is None or isinstance(v, (bool, str, bytes)):
        h.update(f"{type(v).__name__}:{len(v) if isinstance(v, (str, bytes)) else v}:".encode())
        if isinstance(v, (str, bytes)):
            h.update(v.encode() if isinstance(v, str) else v)
    elif isinstance(v, int) and not isinstance(v, enum.Enum):
        h.update(f"int:{v};".encode())
    elif isinstance(v, float):
        h.update(f"float:{v.hex() if math.isfinite(v) else repr(v)};".encode())
    elif isinstance(v, PurePath):
        _feed(h, ("path", str(v)))
    elif isinstance(v, (datetime.date, datetime.time, datetime.timedelta)):
        _feed(h, (type(v).__name__, str(v) if isinstance(v, datetime.timedelta) else v.isoformat()))
    elif isinstance(v, enum.Enum):
        _feed(h, ("enum", type(v).__qualname__, v.name))
    elif isinstance(v, np.generic):
        _feed(h, np.asarray(v))
    elif isinstance(v, np.ndarray):
        if v.dtype.kind == "O":
            _feed(h, ("objarray", v.shape, v.ravel().tolist()))
        else:
            a = np.ascontiguousarray(v)
            h.update(f"ndarray:{a.dtype.str}:{a.shape};".encode())
            h.update(memoryview(a).cast("B"))
    elif isinstance(v, pd.DataFrame):
        h.update(f"frame:{v.shape};".encode())
        _feed(h, v.index)
        for name in v.columns:
            _feed(h, name)
            _feed(h, v[name])
    elif isinstance(v, (pd.Series, pd.Index)):
        h.update(f"{type(v).__name__}:{v.dtype};".encode())
        if isinstance(v, pd.Series):
            _feed(h, v.name)
        if isinstance(v, pd.RangeIndex):
            _feed(h, (v.start, v.stop, v.step))
        elif isinstance(v.dtype, np.dtype) and v.dtype.kind != "O":
            _feed(h, v.to_numpy())
        else:
            _feed(h, [None if x is pd.NA else x for x in v.tolist()])
    elif isinstance(v, (list, tuple)):
        h.update(f"{type(v).__name__}:{len(v)};".encode())
        for x in v:
            _feed(h, x)
    elif isinstance(v, (dict, RunTables)):
        # insertion order: it orders what is drawn; a run's tables as {name: DataFrame}
        _feed(h, ("dict", list(v.items())))
    elif isinstance(v, (set, frozenset)):
        _feed(h, ("set", sorted(content_sha256(x) for x in v)))
    elif dataclasses.is_dataclass(v) and not isinstance(v, type):
        _feed(h, ("dataclass", type(v).__qualname__,
                  [(f.name, getattr(v, f.name)) for f in dataclasses.fields(v)]))
    else:
        raise TypeError(f"value: cannot hash a {type(v).__name__} by content")
