"""Where numba keeps the compiled simulator and controllers.

numba's on-disk cache (``cache=True``) is keyed by the source file of each
compiled function only: when a function it calls (e.g. a valve equation in
``models``) changes, a stale machine-code cache of the caller is reused. To
make that impossible, the cache lives in a folder named after a hash of every
source file that compiled code is built from (and the numba version), under
``$SEANV_NUMBA_CACHE`` or the package's user cache folder
(:func:`seanv_analysis.config.user_cache_dir`, default ``~/.cache/seanv-analysis``). A changed equation gets a new folder and is
compiled afresh; the package tree itself is never written to.

Inside that folder numba would file each module's cache under a hash of its
folder's absolute path, so a moved checkout or the same sources installed
from a wheel would compile everything again (20-30 s). The package's own
functions are located by :class:`PackageCacheLocator` instead: under their
folder inside the package (``sim/``, ``models/``); numba stamps entries by
the source's content hash, so any copy of the same sources reuses them.

numba's index files are pickles, loaded with the cache: the cache lives
only in a folder no one else can write to (this user's, mode 0700:
:func:`seanv_analysis.config.private_folder`; one that was open to others
is emptied first). Where the cache folder is another user's, a warning says
so and numba caches into a fresh private temporary folder for this process
instead (it compiles again, 10-30 s).
"""
from __future__ import annotations

import atexit
import hashlib
import logging
import os
import shutil
import tempfile
from pathlib import Path

from ..errors import ConfigError
from ._sources import cache_base, hash_compiled_sources, private_cache_folder

__all__ = ["configure_numba_cache", "PackageCacheLocator"]

_PKG = Path(__file__).resolve().parents[1]
#: numba's own locators, tried after ours (other libraries' cached functions)
_NUMBA_LOCATORS = ("UserProvidedCacheLocator", "InTreeCacheLocator", "UserWideCacheLocator",
                   "IPythonCacheLocator", "ZipCacheLocator")

_DONE = False


def configure_numba_cache() -> Path | None:
    """Point numba's cache at a folder keyed by the compiled sources; returns it.

    Call before the first ``@njit(cache=True)`` decoration (``sim.jit``
    does). Does nothing when ``NUMBA_CACHE_DIR`` is set by the user.
    """
    global _DONE
    import numba
    from numba.core import config

    if _DONE or os.environ.get("NUMBA_CACHE_DIR"):
        _DONE = True
        return Path(config.CACHE_DIR) if config.CACHE_DIR else None
    h = hashlib.sha256(numba.__version__.encode())
    hash_compiled_sources(h)
    folder = cache_base() / f"numba-{h.hexdigest()[:16]}"
    try:
        private_cache_folder(folder)
    except ConfigError as exc:
        folder = Path(tempfile.mkdtemp(prefix="seanv-numba-"))   # 0700, this process's own
        atexit.register(shutil.rmtree, folder, ignore_errors=True)
        logging.getLogger(__name__).warning(
            "%s; numba's cache for this process: %s (compiled again)", exc, folder)
    config.CACHE_DIR = str(folder)
    if not os.environ.get("NUMBA_CACHE_LOCATOR_CLASSES"):  # a user's choice wins
        config.CACHE_LOCATOR_CLASSES = ",".join((f"{__name__}.PackageCacheLocator",
                                                 *_NUMBA_LOCATORS))
    _DONE = True
    return folder


def _locator_base():
    from numba.core.caching import UserProvidedCacheLocator

    return UserProvidedCacheLocator


class PackageCacheLocator(_locator_base()):
    """numba cache locator of the package's compiled functions: the cache
    path is ``CACHE_DIR/pkg/<folder inside the package>``, not a hash of the
    absolute path (module doc); None for any other file (numba's locators
    take it)."""

    def __init__(self, py_func, py_file):
        super().__init__(py_func, py_file)
        from numba.core import config

        rel = Path(py_file).resolve().parent.relative_to(_PKG)
        self._cache_path = os.path.join(config.CACHE_DIR, "pkg", *rel.parts)

    @classmethod
    def from_function(cls, py_func, py_file):
        try:
            Path(py_file).resolve().relative_to(_PKG)
        except ValueError:
            return None
        return super().from_function(py_func, py_file)
