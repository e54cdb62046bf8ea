"""Per-run result cache of the batch runner, under ``<out>/.cache/``.

Each per-run result is stored in its own file, named by a key: the SHA-256
of the run's input file hashes (by file name), the stage and its
parameters, the rig config and the code version (package version plus a
hash of the package's sources). Change any of these (a byte of a log, an
option, a rig constant, a line of code) and the key
changes, so stale results are never reused; a removed parameter changes the
key too, because the whole option dict is hashed.

Input files are hashed once: the reader hashes the bytes it parses, the
worker returns the digests, and ``index.json`` remembers them together with
each file's size and modification time. A later run re-uses a digest while
the file's size and mtime (and the folder's file list) are unchanged, so a
re-run with nothing changed reads no log at all.

Every write is atomic (temp file + rename) and the index is saved every few
seconds while a stage runs, so killing a run (SIGINT, SIGKILL) leaves either
whole entries or none; temp files left by a killed run are removed when the
cache is opened again, and an unreadable entry counts as missing.

Entries are pickles signed with a per-user key (HMAC-SHA256; the key lives
in ``$SEANV_CACHE_KEY_DIR`` or ``~/.cache/seanv-analysis/cache-key``, mode
0600): only an entry this user's processes wrote is ever unpickled. A file
another user (or anything else) put into ``<out>/.cache`` is a miss.
"""
from __future__ import annotations

import functools
import hashlib
import hmac
import json
import os
import pickle
import threading
import time
from pathlib import Path
from typing import Any, Mapping

from .. import __version__
from ..io.atomic import atomic_path, write_json_atomic

__all__ = ["RunCache", "run_key", "code_version", "folder_listing", "CACHE_DIRNAME"]

CACHE_DIRNAME = ".cache"
_INDEX_SCHEMA = "seanv-batch-index/1"


def _canonical(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str)


@functools.lru_cache(maxsize=1)
def code_version() -> str:
    """Package version plus a hash of every source file of the package
    (``0.1.0+1a2b3c4d5e6f``): an edited stage invalidates cached results
    even when the version number was not bumped."""
    pkg = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for path in sorted(pkg.rglob("*.py")):
        h.update(path.relative_to(pkg).as_posix().encode())
        h.update(path.read_bytes())
    return f"{__version__}+{h.hexdigest()[:12]}"


#: what a simulated data set depends on (package-relative paths or folders)
_SIMULATOR_SOURCES = ("sim", "models", "control.py", "config.py", "io/writer.py",
                      "../data_schema/rig/default.toml")


@functools.lru_cache(maxsize=1)
def simulator_version() -> str:
    """Package version plus a hash of the simulator's sources and the default
    rig (``0.1.0+sim1a2b3c4d5e6f``): the key of cached built-in simulated data
    sets, so a changed plant or integrator re-simulates them while an edited
    plot or report does not."""
    pkg = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for rel in _SIMULATOR_SOURCES:
        base = (pkg / rel).resolve()
        files = sorted(base.rglob("*.py")) if base.is_dir() else [base]
        for path in files:
            if path.is_file():
                h.update(rel.encode() + b"/" + path.name.encode())
                h.update(path.read_bytes())
    return f"{__version__}+sim{h.hexdigest()[:12]}"


def run_key(file_hashes: Mapping[str, str], *, stage: str, params: Mapping[str, Any],
            rig: Mapping[str, Any], version: str | None = None) -> str:
    """Cache key of one run's result of one stage (hex SHA-256).

    Parameters
    ----------
    file_hashes : {file name inside the run folder: SHA-256} of the inputs read
    stage : stage name ('ingest', 'fig6', ...)
    params : every parameter the stage uses (hashed whole)
    rig : the rig config dict
    version : code version (default: :func:`code_version`, the package
        version plus a hash of its sources)
    """
    doc = {"files": dict(sorted(file_hashes.items())), "stage": stage, "params": params,
           "rig": rig, "version": code_version() if version is None else version}
    return hashlib.sha256(_canonical(doc).encode()).hexdigest()


def folder_listing(run_dir: str | Path) -> dict[str, tuple[int, int]]:
    """{file name: (size, mtime_ns)} of the non-hidden files of a run folder."""
    out: dict[str, tuple[int, int]] = {}
    try:
        with os.scandir(run_dir) as it:
            for entry in it:
                if entry.name.startswith(".") or not entry.is_file():
                    continue
                st = entry.stat()
                out[entry.name] = (st.st_size, st.st_mtime_ns)
    except OSError:
        return {}
    return out


class RunCache:
    """The cache folder of one output folder (``<out>/.cache``).

    Parameters
    ----------
    root : the cache folder (created when missing)
    enabled : False makes every look-up a miss (``--force``); results are
        still written, so the next run can use them
    """

    def __init__(self, root: str | Path, *, enabled: bool = True):
        self.root = Path(root)
        self.enabled = enabled
        self.entries = self.root / "runs"
        self.entries.mkdir(parents=True, exist_ok=True)
        self.removed_partial = self.clean_partial()
        self._lock = threading.Lock()
        self._index: dict[str, Any] = self._load_index()
        self._dirty = False
        self._last_save = time.monotonic()

    # housekeeping --------------------------------------------------------
    def clean_partial(self) -> int:
        """Remove temp files a killed run left behind; return how many."""
        n = 0
        for folder in (self.root, self.entries):
            for tmp in folder.glob(".*.tmp"):
                try:
                    tmp.unlink()
                    n += 1
                except OSError:
                    pass
        return n

    def _load_index(self) -> dict[str, Any]:
        path = self.root / "index.json"
        try:
            doc = json.loads(path.read_text())
            if doc.get("schema") == _INDEX_SCHEMA and isinstance(doc.get("runs"), dict):
                return doc["runs"]
        except (OSError, ValueError, AttributeError):
            pass
        return {}

    def save_index(self, *, force: bool = False, every_s: float = 2.0) -> None:
        """Write ``index.json`` atomically (at most every ``every_s`` unless ``force``)."""
        with self._lock:
            if not self._dirty or (not force and time.monotonic() - self._last_save < every_s):
                return
            doc = {"schema": _INDEX_SCHEMA, "version": __version__, "runs": self._index}
            write_json_atomic(self.root / "index.json", doc, indent=0)
            self._dirty = False
            self._last_save = time.monotonic()

    # input hashes --------------------------------------------------------
    def known_hashes(self, run_dir: str | Path) -> dict[str, str] | None:
        """The recorded input hashes of a run folder, when none of its files
        changed (same file list, sizes and modification times); else None."""
        rec = self._index.get(str(Path(run_dir).resolve()))
        if not rec:
            return None
        listing = folder_listing(run_dir)
        if sorted(listing) != rec.get("listing"):
            return None
        for name, (size, mtime_ns, _sha) in rec["files"].items():
            if tuple(listing.get(name, ())) != (size, mtime_ns):
                return None
        return {name: v[2] for name, v in rec["files"].items()}

    def remember(self, run_dir: str | Path, hashes: Mapping[str, str],
                 stats: Mapping[str, tuple[int, int]]) -> None:
        """Record a run folder's input hashes with the stat they were taken at."""
        listing = folder_listing(run_dir)
        files = {name: [int(stats[name][0]), int(stats[name][1]), sha]
                 for name, sha in hashes.items() if name in stats}
        with self._lock:
            self._index[str(Path(run_dir).resolve())] = {"listing": sorted(listing), "files": files}
            self._dirty = True

    # entries -------------------------------------------------------------
    def get(self, key: str) -> Any | None:
        """The stored result for ``key``, or None (missing, unreadable or disabled)."""
        if not self.enabled:
            return None
        return read_entry(self.entries, key)

    def put(self, key: str, value: Any) -> None:
        write_entry(self.entries, key, value)


#: per-user secret that signs cache entries (HMAC-SHA256): an entry is only
#: unpickled when this user's process wrote it, so a file someone else put in
#: a shared output folder is a cache miss, never code run by the next user
_KEY_NAME = "cache-key"
_MAC_SIZE = 32


def _key_dir() -> Path:
    base = os.environ.get("SEANV_CACHE_KEY_DIR") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"),
        "seanv-analysis")
    return Path(base)


@functools.lru_cache(maxsize=1)
def _signing_key() -> bytes:
    """This user's signing key (32 random bytes, created once, readable by the
    user only)."""
    folder = _key_dir()
    path = folder / _KEY_NAME
    folder.mkdir(parents=True, exist_ok=True)
    try:  # O_EXCL: of processes starting together, the first one writes the key
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        return _read_key(path)
    key = os.urandom(_MAC_SIZE)
    with os.fdopen(fd, "wb") as fh:
        fh.write(key)
    return key


def _read_key(path: Path, *, wait_s: float = 2.0) -> bytes:
    """The key in ``path``, waiting while another process is still writing it
    (a short or empty key is never used)."""
    deadline = time.monotonic() + wait_s
    while True:
        key = path.read_bytes()
        if len(key) == _MAC_SIZE:
            return key
        if time.monotonic() > deadline:
            raise OSError(f"{path}: cache signing key is {len(key)} bytes, expected {_MAC_SIZE}; "
                          "delete it to make a new one")
        time.sleep(0.01)


def _mac(payload: bytes) -> bytes:
    return hmac.new(_signing_key(), payload, hashlib.sha256).digest()


def read_entry(entries: str | Path, key: str) -> Any | None:
    """Load one entry; None when missing, damaged or not signed with this
    user's key (such a file is removed and the result recomputed)."""
    path = Path(entries) / f"{key}.pkl"
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return None
    except OSError:
        return None
    mac, payload = data[:_MAC_SIZE], data[_MAC_SIZE:]
    if len(data) > _MAC_SIZE and hmac.compare_digest(mac, _mac(payload)):
        try:
            return pickle.loads(payload)  # signed by this user: written by this package
        except Exception:  # noqa: BLE001 - a stale class layout: treat as missing
            pass
    try:
        path.unlink()
    except OSError:
        pass
    return None


def write_entry(entries: str | Path, key: str, value: Any) -> None:
    """Store one entry atomically (temp file in the same folder + rename),
    signed with this user's key."""
    path = Path(entries) / f"{key}.pkl"
    payload = pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(_mac(payload) + payload)
