"""Content hashes of input files, computed once per process.

The reader hashes each file from the bytes it has already read (no second
pass over the disk) and remembers the digest here; the manifest writer asks
:func:`file_sha256`, which only reads and hashes a file it has not seen (or
that changed size, modification or change time, or inode since).
"""
from __future__ import annotations

import functools
import hashlib
import os
import threading
from pathlib import Path

from .. import __version__

__all__ = ["file_sha256", "remember_sha256", "sha256_bytes", "code_version"]

_CACHE: dict[tuple[str, int, int, int, int], str] = {}
_LOCK = threading.Lock()
_CHUNK = 1 << 22


def _key(path: Path) -> tuple[str, int, int, int, int]:
    """(path, size, mtime, ctime, inode): a same-size edit whose mtime was
    put back still changes the ctime (which no user can set), a file
    replaced by another the inode."""
    st = os.stat(path)
    return (str(Path(path).resolve()), st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino)


def sha256_bytes(data: bytes | memoryview) -> str:
    """Hex SHA-256 of ``data``."""
    return hashlib.sha256(data).hexdigest()


def remember_sha256(path: str | Path, digest: str) -> None:
    """Record the digest of ``path`` (as it is now on disk) for later look-ups."""
    try:
        key = _key(Path(path))
    except OSError:
        return
    with _LOCK:
        _CACHE[key] = digest


def file_sha256(path: str | Path) -> str:
    """Hex SHA-256 of a file's content; reuses a digest already computed in
    this process while the file's size, modification and change times and
    inode are unchanged."""
    path = Path(path)
    key = _key(path)
    with _LOCK:
        hit = _CACHE.get(key)
    if hit is not None:
        return hit
    h = hashlib.sha256()
    with open(path, "rb") as fh:
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
    pkg = Path(__file__).resolve().parents[1]  # the package
    h = hashlib.sha256()
    for path in sorted(pkg.rglob("*.py")):
        h.update(path.relative_to(pkg).as_posix().encode())
        h.update(path.read_bytes())
    return f"{__version__}+{h.hexdigest()[:12]}"
