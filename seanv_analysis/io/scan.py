"""One pass over a table file before it is parsed, and the memory it is parsed into.

:func:`scan_file` reads a file once for its SHA-256 (manifests), its first
NUL byte (binary data in a text table), whether it is blank, its first
64 KiB (where a text format's header is sniffed) and, for a file read in
one piece, its whole content (which a format may parse from memory instead
of reading the file again); :func:`memory_pool` picks the Arrow memory pool
a file of that size is parsed into.
"""
from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

import pyarrow as pa

__all__ = ["FileScan", "scan_file", "file_size", "memory_pool", "HEAD_BYTES"]

#: bytes of a file's beginning kept by :func:`scan_file` (``FileScan.head``)
HEAD_BYTES = 1 << 16
_CHUNK = 1 << 22

#: tables from files at least this large are parsed into the purging pool
_LARGE_FILE = 16 << 20
_POOL: pa.MemoryPool | None = None


@dataclass(frozen=True)
class FileScan:
    """What one pass over a file found."""

    size: int            # bytes looked at (the whole file only when hashed)
    sha256: str | None
    nul_offset: int      # first NUL byte, -1 if none
    blank: bool          # only whitespace (or nothing)
    head: bytes = b""    # the first 64 KiB (a CSV header is read from it)
    data: bytes | None = None   # the whole file when one read held it (<= 4 MiB hashed, < 64 KiB not)
    stat: os.stat_result | None = None   # the open file's, after reading (the hash cache's key)


def scan_file(path: Path, *, want_hash: bool, find_nul: bool) -> FileScan:
    """One streaming pass over a file: SHA-256, first NUL byte, blankness.

    Streams in 4 MiB chunks, so a large file's raw bytes are never held in
    memory at once; the parse that follows reads it again from the page
    cache. A file that one chunk held whole is kept (``FileScan.data``), so
    its parse need not open it again. Without ``want_hash`` only the first
    64 KiB are looked at (a NUL byte further down in a numeric column still
    fails the parse, and the error path then reports it as binary data).
    ``FileScan.stat`` is the open file's ``fstat`` after the reads.
    """
    h = hashlib.sha256() if want_hash else None
    size, nul, blank, head, first = 0, -1, True, b"", b""
    with open(path, "rb") as fh:
        # reads of a small file ask for little more than its size: a 4 MiB
        # request allocates (and faults in) 4 MiB for every file, ~4x the
        # cost of reading a 20 KiB table
        step = min(_CHUNK, max(os.fstat(fh.fileno()).st_size + 1, HEAD_BYTES)) if want_hash \
            else HEAD_BYTES
        while chunk := fh.read(step):
            if not size:
                first = chunk
                head = chunk[:HEAD_BYTES]
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
                if len(chunk) == HEAD_BYTES:
                    blank = False  # more follows: not known to be blank
                break
        st = os.fstat(fh.fileno())
    # hashed: read to the end, whole when the first chunk was all; else
    # whole when the one read of HEAD_BYTES came back short
    whole = len(first) == size if want_hash else len(first) < HEAD_BYTES
    return FileScan(size, h.hexdigest() if h is not None else None, nul, blank, head,
                    first if whole else None, st)


def file_size(path: Path) -> int:
    """Size of ``path`` in bytes; 0 when it cannot be stat'ed (reading it says why)."""
    try:
        return path.stat().st_size
    except OSError:
        return 0


def memory_pool(size_bytes: int) -> pa.MemoryPool:
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
