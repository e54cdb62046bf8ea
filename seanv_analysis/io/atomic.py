"""Atomic file writes: write to a temp file in the target folder, then rename.

A reader (or a resumed run) never sees a half-written output. Files and
folders written here follow the process umask (like ``open`` and ``mkdir``),
not the private 0600 / 0700 of :mod:`tempfile`. :func:`atomic_folder` swaps a
whole folder in; :func:`remove_stale_temps` removes what a killed run left.

Only a folder this package made is ever replaced or deleted: every folder it
makes carries the marker file :data:`OWNER_MARKER`, and :func:`swap_in`,
:func:`retire_folder` and :func:`remove_stale_temps` refuse (or skip) a folder
without it (:class:`~seanv_analysis.errors.OutputError` naming the folder).
"""
from __future__ import annotations

import json
import os
import re
import secrets
import shutil
import stat
import tempfile
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterable, Iterator

__all__ = ["atomic_path", "atomic_folder", "write_text_atomic", "write_json_atomic",
           "write_bytes_atomic", "current_umask", "swap_in", "retire_folder",
           "remove_stale_temps", "TEMP_FILE", "TEMP_FOLDER", "OWNER_MARKER", "is_owned",
           "claim_folder", "check_not_foreign"]

#: a temp file of :func:`atomic_path`: ``.<name>.<random>.tmp``
TEMP_FILE = re.compile(r"\..+\.[a-z0-9_]+\.tmp")
#: a temp or retired folder of :func:`atomic_folder`: ``.<name>.tmp-<random>`` / ``.<name>.old-<random>``
TEMP_FOLDER = re.compile(r"\.(?P<name>[^/]+)\.(?:tmp|old)-[A-Za-z0-9_]+")

#: the file in every folder this package made (stage folders, their temp and
#: retired copies): a folder without it is the user's and is never replaced
OWNER_MARKER = ".seanv-output"
_MARKER_TEXT = ("This folder was written by seanv-analysis; a later run may replace "
                "or delete it whole.\n")

_UMASK_LOCK = threading.Lock()


def is_owned(path: str | Path) -> bool:
    """``path`` is a folder (not a link) that this package made: it holds
    :data:`OWNER_MARKER` as a regular file."""
    try:
        return (stat.S_ISDIR(os.lstat(path).st_mode)
                and stat.S_ISREG(os.lstat(Path(path) / OWNER_MARKER).st_mode))
    except OSError:
        return False


def _mark_owned(folder: Path) -> None:
    (folder / OWNER_MARKER).write_text(_MARKER_TEXT)


def check_not_foreign(path: str | Path) -> None:
    """Raise unless ``path`` is absent or a folder this package made.

    Raises
    ------
    OutputError
        something else stands at ``path`` (a data folder, a file, a link, a
        folder of an older version): it is never replaced or deleted.
    """
    path = Path(path)
    if os.path.lexists(path) and not is_owned(path):
        from ..errors import OutputError

        what = ("a link" if path.is_symlink() else "a folder" if path.is_dir()
                else "a file")
        raise OutputError(f"{path}: {what} this package did not write (no {OWNER_MARKER} "
                          "marker) stands where an output folder goes; it is never replaced "
                          "or deleted: move it away or choose another --out")


def claim_folder(path: str | Path) -> Path:
    """Make ``path`` a folder this package owns (created with its marker),
    or check that the one there is (:func:`check_not_foreign`)."""
    path = Path(path)
    check_not_foreign(path)
    if not os.path.lexists(path):
        path.mkdir(parents=True, exist_ok=True)
        _follow_umask(path, folder=True)
        _mark_owned(path)
    return path


def current_umask() -> int:
    """The process umask, read without changing it where the system tells it
    (Linux ``/proc/self/status``); elsewhere set and restored under a lock,
    with the strict 077 in the instant between (never a looser mode)."""
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    with _UMASK_LOCK:
        old = os.umask(0o077)
        os.umask(old)
    return old


def _follow_umask(path: Path, *, folder: bool = False) -> None:
    """Give ``path`` the mode a plain ``open`` / ``mkdir`` would have given it
    (best effort: a file system without modes keeps its own)."""
    try:
        os.chmod(path, (0o777 if folder else 0o666) & ~current_umask())
    except PermissionError:
        pass


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temp path next to ``path``; on success rename it over ``path``.

    On an exception the temp file is removed and ``path`` is untouched. The
    file gets the mode the umask gives new files (e.g. 0644 with umask 022).

    Raises
    ------
    OutputError
        an operating-system error that names no file or the temp file (disk
        full, file too large, while writing): the message names ``path``
        and why.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        _follow_umask(tmp_path)
        os.replace(tmp_path, path)
    except BaseException as exc:
        tmp_path.unlink(missing_ok=True)
        if isinstance(exc, OSError) and exc.filename in (None, tmp, tmp_path):
            from ..errors import OutputError

            why = " ".join((exc.strerror or str(exc) or type(exc).__name__).split())
            raise OutputError(f"{path}: {why}") from None
        raise


@contextmanager
def atomic_folder(path: str | Path) -> Iterator[Path]:
    """Yield a fresh folder beside ``path`` (``.<name>.tmp-<random>``, holding
    only :data:`OWNER_MARKER`); on success swap it in whole: the old ``path``
    is renamed away, the new one renamed in, the old one deleted. Nothing of
    the old folder remains.

    On an exception the temp folder is removed and ``path`` is untouched.

    Raises
    ------
    OutputError
        a folder this package did not make stands at ``path`` (checked
        before anything is written).
    """
    path = Path(path)
    check_not_foreign(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.tmp-", dir=path.parent))
    try:
        _follow_umask(tmp, folder=True)
        _mark_owned(tmp)
        yield tmp
        swap_in(tmp, path)
    except BaseException:
        _remove(tmp)
        raise


def swap_in(new: Path, path: Path) -> None:
    """Put folder ``new`` at ``path``, replacing the folder of this package
    there (:func:`check_not_foreign`: anything else is refused)."""
    check_not_foreign(path)
    old = _rename_away(path)
    os.rename(new, path)
    if old is not None:
        _remove(old)


def retire_folder(path: str | Path) -> None:
    """Remove the folder ``path`` of this package if it exists: renamed away
    first (``.<name>.old-<random>``, which :func:`remove_stale_temps` removes
    should a kill come between), then deleted. Anything else at ``path`` is
    refused (:func:`check_not_foreign`)."""
    check_not_foreign(path)
    old = _rename_away(Path(path))
    if old is not None:
        _remove(old)


def _rename_away(path: Path) -> Path | None:
    """Rename ``path`` to a hidden ``.old-`` name beside it; None if absent."""
    if not os.path.lexists(path):
        return None
    old = path.with_name(f".{path.name}.old-{secrets.token_hex(4)}")
    os.rename(path, old)
    return old


def _remove(path: Path) -> None:
    """Delete a file, link or folder tree (links not followed)."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def remove_stale_temps(out: str | Path, folders: Iterable[str]) -> int:
    """Remove what a killed run left in ``out``: temp files of
    :func:`atomic_path` (``.<name>.<random>.tmp``) directly in ``out`` and
    anywhere under its ``folders``, and temp / retired folders of
    :func:`atomic_folder` (``.<folder>.tmp-*``, ``.<folder>.old-*``) of those
    ``folders``. Only folders with :data:`OWNER_MARKER` are touched; nothing
    else is; links are not followed.
    Returns how many entries were removed."""
    out = Path(out)
    names = {f for f in folders if f not in (".", "")}
    if not out.is_dir():
        return 0
    n = 0
    for entry in list(out.iterdir()):
        m = TEMP_FOLDER.fullmatch(entry.name)
        if m and m["name"] in names and is_owned(entry):
            _remove(entry)
            n += 1
    n += _remove_temp_files(out, recurse=False)
    for name in sorted(names):
        sub = out / name
        if is_owned(sub):
            n += _remove_temp_files(sub, recurse=True)
    return n


def _remove_temp_files(folder: Path, *, recurse: bool) -> int:
    """Remove the regular files named like :data:`TEMP_FILE` in ``folder``."""
    n = 0
    for dirpath, dirnames, filenames in os.walk(folder):
        if not recurse:
            dirnames.clear()
        for f in filenames:
            p = Path(dirpath) / f
            try:
                if TEMP_FILE.fullmatch(f) and stat.S_ISREG(os.lstat(p).st_mode):
                    p.unlink()
                    n += 1
            except FileNotFoundError:
                continue
    return n


def write_bytes_atomic(path: str | Path, data: bytes) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def write_text_atomic(path: str | Path, text: str) -> Path:
    return write_bytes_atomic(path, text.encode("utf-8"))


def write_json_atomic(path: str | Path, obj: Any, *, indent: int = 2) -> Path:
    """``obj`` as strict JSON (:func:`~seanv_analysis.jsonable.clean_json`:
    NaN and infinities as null, numpy values as numbers and lists), atomically."""
    from ..jsonable import clean_json

    text = json.dumps(clean_json(obj), indent=indent, sort_keys=False, default=_jsonable,
                      allow_nan=False)
    return write_text_atomic(path, text + "\n")


def _jsonable(o: Any):
    import numpy as np
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
