"""What the simulator's compiled code is built from, and where it is kept.

One list for the two caches of compiled code: numba's own
(:mod:`.numba_cache`) and the ahead-of-time module (:mod:`.compiled`), both
keyed by a hash of these files, both kept in private folders
(:func:`private_cache_folder`). No numba here.
"""
from __future__ import annotations

import os
from pathlib import Path

__all__ = ["COMPILED_SOURCES", "cache_base", "hash_compiled_sources", "private_cache_folder"]

#: the package sources compiled code is built from (relative to the package):
#: the key of numba's cache folder and of the ahead-of-time module
COMPILED_SOURCES = ("models/sealing.py", "models/valve.py", "models/effects.py",
                    "models/expr.py", "sim/jit.py", "sim/packing.py", "sim/control_law.py",
                    "sim/_pp.py", "sim/kernel.py", "sim/rosenbrock.py")


def hash_compiled_sources(h) -> None:
    """Feed each compiled source's path and content to the hash ``h``
    (a missing file adds nothing)."""
    pkg = Path(__file__).resolve().parents[1]
    for rel in COMPILED_SOURCES:
        p = pkg / rel
        if p.is_file():
            h.update(rel.encode())
            h.update(p.read_bytes())


def cache_base() -> Path:
    """Folder of the compiled code's caches: ``$SEANV_NUMBA_CACHE``, else the
    package's user cache folder."""
    from ..config import user_cache_dir

    return Path(os.environ.get("SEANV_NUMBA_CACHE") or user_cache_dir())


def private_cache_folder(folder: Path) -> None:
    """Make the cache folder (:func:`cache_base`) and its sub-folder
    ``folder`` private: this user's, mode 0700
    (:func:`seanv_analysis.config.private_folder`). A ``folder`` that was
    open to others is emptied first: what it held may be someone else's.

    Raises
    ------
    ConfigError
        either is another user's (or not a folder): nothing may be loaded from it.
    """
    import shutil

    from ..config import private_folder

    private_folder(cache_base())
    if private_folder(folder):
        for entry in folder.iterdir():
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry, ignore_errors=True)
            else:
                entry.unlink(missing_ok=True)
