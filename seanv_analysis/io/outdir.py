"""The output folder's first rule: an input is never written over.

A run writes its outputs into an output folder ``out``: files directly in it
(``result.json``, ``manifest.json``...) and folders it owns whole (a stage's
folder, swapped in anew at every run; the per-run cache). Before any work,
:func:`check_out_dir` refuses an ``out`` for which one of those would be, or
would contain, an input (a data folder, the rig, pipeline or model file), or
that lies inside a data folder. Paths are compared resolved (links followed)
and by device and inode (bind mounts, hard links), so no second name of an
input slips through. The marker of :mod:`.atomic` is the second line of
defence: a folder this package did not make is never replaced or deleted.
"""
from __future__ import annotations

import os
from contextlib import contextmanager
from pathlib import Path
from typing import Iterable, Iterator

from ..errors import DataError, OutputError

__all__ = ["check_out_dir", "out_lock", "LOCK_NAME"]

#: the lock file of a run in its output folder (:func:`out_lock`)
LOCK_NAME = ".seanv-lock"


@contextmanager
def out_lock(out: str | Path, *, beside: bool = False) -> Iterator[Path]:
    """Hold the output folder ``out`` for one run: an exclusive lock on
    ``out/.seanv-lock`` (``beside``: ``<parent>/.<out>.lock``, for a folder
    the run swaps in whole), so two runs into one folder cannot delete each
    other's temp files or swap each other's folders. Yields the lock file.

    Raises
    ------
    OutputError
        another run holds it (one line: which folder, what to do).
    """
    out = Path(out)
    lock = out.parent / f".{out.name}.lock" if beside else out / LOCK_NAME
    lock.parent.mkdir(parents=True, exist_ok=True)
    try:
        import fcntl
    except ImportError:        # no POSIX locks here: nothing to hold
        yield lock
        return
    fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            raise OutputError(f"{out}: another seanv-analyze run is writing there (it holds "
                              f"{lock}); wait for it to end or choose another --out") from None
        yield lock
    finally:
        os.close(fd)


def _identity(path: Path) -> tuple[int, int] | None:
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino


def _chain(path: Path) -> list[Path]:
    """``path`` resolved and each of its parents, nearest first."""
    p = path.resolve()
    return [p, *p.parents]


def _is_within(inner: Path, outer: Path) -> bool:
    """``inner`` is ``outer`` or lies under it: by resolved path, or by
    (device, inode) of ``outer`` among ``inner`` and its existing parents."""
    inner_chain = _chain(inner)
    outer_res = outer.resolve()
    if outer_res in inner_chain:
        return True
    ident = _identity(outer_res)
    return ident is not None and any(_identity(p) == ident for p in inner_chain)


def check_out_dir(out: str | Path, *, data: Iterable[str | Path] = (),
                  files: Iterable[str | Path | None] = (),
                  owned: Iterable[str] = (), label: str = "--out") -> None:
    """Refuse an output folder that would write over an input.

    Parameters
    ----------
    out : the output folder (need not exist)
    data : data folders (or run folders) read by the run
    files : other input files read by the run (rig, pipeline, model; None is skipped)
    owned : names under ``out`` the run replaces or deletes whole (stage
        folders, the cache folder) or writes over (its top-level files);
        "." stands for ``out`` itself
    label : how the messages name ``out`` ("--out" on the command line,
        "out_dir" in the library)

    Raises
    ------
    OutputError
        ``out`` is empty (``--out ""``).
    DataError
        ``out`` is a data folder or lies inside one; ``out`` itself, or one of
        the ``owned`` entries, is or contains an input; the message names
        both paths.
    """
    if str(out).strip() == "":
        raise OutputError(f"{label}: empty; expected a folder to write the outputs into")
    out = Path(out)
    inputs = [Path(p) for p in data] + [Path(p) for p in files if p is not None]
    for d in (Path(p) for p in data):
        if _is_within(out, d):
            raise DataError(f"{label}: {out} is inside the data folder; outputs never go into "
                            f"raw data: choose another {label} (default: "
                            "outputs/<dataset>/<command>/ under the current folder)", path=d)
    for name in owned:
        target = out if name in (".", "") else out / name
        for src in inputs:
            if os.path.lexists(src) and _is_within(src, target):
                what = "the output folder" if target == out else f"the output folder {target}"
                raise DataError(f"{label}: {what} would be written over, and it is or holds "
                                f"the input {src}; inputs are never written over: choose "
                                f"another {label}")
