"""Per-run result cache of the batch runner, under ``<out>/.cache/``.

Each per-run result is stored in its own file, named by a key: the SHA-256
of the run's input file hashes (by file name), the stage and its
parameters, the rig config and the code version (package version plus a
hash of the package's sources). Change any of these (a byte of a log, an
option, a rig constant, a line of code) and the key
changes, so stale results are never reused; a removed parameter changes the
key too, because the whole option dict is hashed.

Input files are hashed as the reader parses them; the worker returns the
digests and ``index.json`` remembers them with each file's size and
modification time. The key of a later run is always made from the files'
content: size and mtime only say which files the run read, and each file is
hashed again once per process (a same-size edit with its mtime restored
changes the key). A re-run with nothing changed hashes its inputs (about
1 GB/s) but parses no log.

Every write is atomic (temp file + rename) and the index is saved every few
seconds while a stage runs, so killing a run (SIGINT, SIGKILL) leaves either
whole entries or none; temp files left by a killed run are removed when the
cache is opened again, and an unreadable entry counts as missing.

Entries are plain data (:mod:`.codec`: JSON with arrays as raw bytes),
never pickle, headed by the SHA-256 of their payload, checked on read: a
file anyone put into ``<out>/.cache`` can at worst be a miss (or, written
consistently, wrong numbers for whoever can write the output folder anyway),
never code run by the next user. Entries of older versions (``*.pkl``) are
removed unread.
"""
from __future__ import annotations

import functools
import hashlib
import hmac
import json
import os
import threading
import time
from pathlib import Path
from typing import Any, Mapping

from .. import __version__
from ..io.atomic import atomic_path, write_json_atomic
from ..io.hashing import code_version, file_sha256
from ..io.readback import load_json_back, read_back
from .codec import CodecError, decode, encode

__all__ = ["RunCache", "run_key", "code_version", "folder_listing", "own_folder", "CACHE_DIRNAME"]

CACHE_DIRNAME = ".cache"
_INDEX_SCHEMA = "seanv-batch-index/1"


#: one run folder's record in ``index.json``: its file names and, per file
#: read, [size, mtime_ns, SHA-256]
_RUN_RECORD = {"listing": [str], "files": {str: lambda v: (
    isinstance(v, list) and len(v) == 3 and all(type(n) is int for n in v[:2])
    and isinstance(v[2], str))}}


def own_folder(folder: Path) -> None:
    """Make ``folder`` (a folder of the cache) or check the one there: a
    link or anything but a folder is refused, never followed.

    Raises
    ------
    OutputError
        naming the path.
    """
    import stat

    from ..errors import OutputError

    try:
        mode = os.lstat(folder).st_mode
    except FileNotFoundError:
        folder.mkdir(parents=True, exist_ok=True)
        mode = os.lstat(folder).st_mode
    if not stat.S_ISDIR(mode):
        what = "a link" if stat.S_ISLNK(mode) else "not a folder"
        raise OutputError(f"{folder}: {what}; expected the per-run cache folder this package "
                          "makes (links are not followed): remove it or choose another --out")


def _canonical(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str)


#: what a simulated data set depends on (package-relative paths or folders)
_SIMULATOR_SOURCES = ("sim", "models", "control.py", "config.py", "io/writer.py",
                      "_data_schema/rig/default.toml")


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
        for folder in (self.root, self.entries):
            own_folder(folder)
        #: one line per entry found malformed (removed, recomputed)
        self.rejected: list[str] = []
        self.removed_partial = self.clean_partial()
        self._lock = threading.Lock()
        self._index: dict[str, Any] = self._load_index()
        self._dirty = False
        self._last_save = time.monotonic()

    # housekeeping --------------------------------------------------------
    def clean_partial(self) -> int:
        """Remove temp files a killed run left behind; return how many."""
        n = 0
        for old in self.entries.glob("*.pkl"):   # an older version's pickles: never read
            try:
                old.unlink()
            except OSError:
                pass
        for folder in (self.root, self.entries):
            for tmp in folder.glob(".*.tmp"):
                try:
                    tmp.unlink()
                    n += 1
                except OSError:
                    pass
        return n

    def _load_index(self) -> dict[str, Any]:
        doc = load_json_back(self.root / "index.json", root=self.root,
                             shape={"schema": _INDEX_SCHEMA.__eq__, "runs": {str: _RUN_RECORD}})
        return {} if doc is None else doc["runs"]

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
        """The content hashes of the files a run folder was read from last
        time, hashed now (once per process, :func:`~seanv_analysis.io.hashing.
        file_sha256`), when its file list is unchanged; else None. The
        recorded size and mtime are never trusted for the content: a same-
        size edit with the mtime put back gives another hash, so another key."""
        rec = self._index.get(str(Path(run_dir).resolve()))
        if not rec:
            return None
        listing = folder_listing(run_dir)
        if sorted(listing) != rec["listing"] or not set(rec["files"]) <= set(listing):
            return None   # only the folder's own regular files are ever hashed
        try:
            return {name: file_sha256(Path(run_dir) / name) for name in rec["files"]}
        except OSError:
            return None

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
        return read_entry(self.entries, key, rejected=self.rejected)

    def reject(self, key: str, why: str) -> None:
        """Remove the entry ``key`` (read, but not what its stage stores) and say why."""
        self.rejected.append(f"{key}.json: {why}")
        try:
            (self.entries / f"{key}.json").unlink()
        except OSError:
            pass


_ENTRY_SCHEMA = b"seanv-cache-entry/2"
#: the largest entry read back (a long run's validation overlay is a few hundred MB)
MAX_ENTRY_BYTES = 2 << 30


def read_entry(entries: str | Path, key: str, *, rejected: list[str] | None = None) -> Any | None:
    """Load one entry; None when missing, damaged (its SHA-256 does not match
    its payload), not a plain-data entry (:mod:`.codec`) or not a regular
    file of the folder (a link, a FIFO, larger than :data:`MAX_ENTRY_BYTES`):
    such a file is removed, one line saying why is appended to ``rejected``,
    and the result recomputed. Nothing in the file can run code."""
    path = Path(entries) / f"{key}.json"
    if not os.path.lexists(path):
        return None
    data = read_back(path, root=entries, max_bytes=MAX_ENTRY_BYTES)
    why = "not a regular file of the cache, or too large"
    if data is not None:
        head, _, payload = data.partition(b"\n")
        try:
            schema, digest = head.split(b" ")
            if schema != _ENTRY_SCHEMA or not hmac.compare_digest(
                    digest, hashlib.sha256(payload).hexdigest().encode()):
                raise CodecError("damaged entry (its SHA-256 does not match)")
            return decode(json.loads(payload))
        except (ValueError, RecursionError) as exc:   # CodecError, JSON, a bad split: a miss
            why = str(exc) if isinstance(exc, CodecError) else f"not an entry ({type(exc).__name__})"
    if rejected is not None:
        rejected.append(f"{path.name}: {why}")
    try:
        path.unlink()
    except OSError:
        pass
    return None


def write_entry(entries: str | Path, key: str, value: Any) -> bool:
    """Store one entry atomically (temp file in the same folder + rename) as
    plain data with the SHA-256 of its payload; False (nothing stored) when
    the value holds something :mod:`.codec` does not store."""
    try:
        payload = json.dumps(encode(value), separators=(",", ":")).encode()
    except CodecError:
        return False
    path = Path(entries) / f"{key}.json"
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(_ENTRY_SCHEMA + b" " + hashlib.sha256(payload).hexdigest().encode() + b"\n")
            fh.write(payload)
    return True
