"""Data sets: finding the run folders and reading their metadata.

A data set is any folder whose sub-folders, at any depth, hold ``run.json``.
:func:`dataset_plan` is the metadata phase of reading one: every run.json is
read and checked before any table is touched, so bad metadata and repeated
run ids are reported up front and the good runs come in ``started_at``
order. Reading the tables is :mod:`.reader`'s.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from ..config import RigConfig, load_rig
from ..errors import DataError, SeanvError
from .formats import table_formats
from .run import Run, RunMeta
from .validate import max_pressure_mpag, one_line, read_run_json

__all__ = ["is_run_dir", "find_runs", "dataset_plan", "RunError", "DatasetRead"]


@dataclass(frozen=True)
class RunError:
    """A run that could not be read: its folder and a one-line reason."""

    path: Path
    message: str

    def __str__(self) -> str:
        return self.message

    def to_json_dict(self) -> dict[str, str]:
        return {"path": str(self.path), "message": self.message}


@dataclass
class DatasetRead:
    """Result of :func:`~seanv_analysis.io.reader.read_dataset`.

    ``runs`` are in ``started_at`` order (ties: run_id); ``errors`` hold the
    runs that broke the contract, one line each, in folder order.
    """

    path: Path
    runs: list[Run] = field(default_factory=list)
    errors: list[RunError] = field(default_factory=list)

    @property
    def success(self) -> bool:
        """True when every run was read."""
        return not self.errors

    def file_sha256(self) -> dict[str, str]:
        """SHA-256 of every file of the good runs {path: hex digest}."""
        out: dict[str, str] = {}
        for run in self.runs:
            out.update(run.file_sha256)
        return out

    def report(self) -> str:
        """A header line (runs read, runs bad), then one line per bad run."""
        lines = [f"{self.path}: {len(self.runs)} run(s) read, {len(self.errors)} bad"]
        lines += [f"  {e.message}" for e in self.errors]
        return "\n".join(lines)


def is_run_dir(path: str | Path) -> bool:
    """True when ``path`` is a folder holding ``run.json`` (a file, or an entry
    of that name that is not a readable file: reading the run says why)."""
    return os.path.lexists(Path(path) / "run.json")


def check_data_root(dataset: str | Path) -> Path:
    """``dataset`` as a path, when it is a folder (a data set or a run).

    Raises
    ------
    DataError
        it does not exist, or is a file (one line naming it).
    """
    root = Path(dataset)
    if not root.exists():
        raise DataError("not found; expected a data set folder or a run folder", path=root)
    if not root.is_dir():
        raise DataError("is a file; expected a data set folder (sub-folders holding run.json) "
                        "or a run folder", path=root)
    return root


def find_runs(dataset: str | Path) -> list[Path]:
    """Every folder at any depth under ``dataset`` (itself included) that holds
    ``run.json``, sorted by path. Hidden folders (name starting with '.') are
    skipped. A folder below ``dataset`` that is a symbolic link is not walked;
    outside run folders it is listed (a run folder or a folder of runs alike), and reading it
    refuses it (:func:`~seanv_analysis.io.validate.check_link`), so it shows
    as a bad run naming the link. ``dataset`` itself may be a link.

    Raises
    ------
    DataError
        ``dataset`` does not exist or is not a folder.
    """
    root = check_data_root(dataset)
    if root.is_symlink():  # DATA given as a link: the user chose it, follow it
        root = root.resolve()
    found = []
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames[:] = sorted(d for d in dirnames if not d.startswith("."))
        if "run.json" in filenames or "run.json" in dirnames:  # a folder: reading says so
            found.append(Path(dirpath))
        # a linked folder of the data set (a run, or a folder of runs) is listed,
        # not walked: reading it says it is a link (never skipped without a
        # word); inside a run folder, only a link to a run
        found += [Path(dirpath) / d for d in dirnames
                  if os.path.islink(os.path.join(dirpath, d))
                  and ("run.json" not in filenames
                       or os.path.lexists(os.path.join(dirpath, d, "run.json")))]
    return sorted(found)


def dataset_plan(path: str | Path, *, rig: RigConfig | None = None
                 ) -> tuple[list[RunMeta], list[RunError], RigConfig]:
    """The metadata phase of reading a data set, without touching any table.

    Every run's run.json is read and checked; returns the good runs'
    :class:`RunMeta` in ``started_at`` order (repeated run ids refused), the
    :class:`RunError` items of bad metadata (sorted by path) and the base rig.
    :func:`~seanv_analysis.io.reader.read_run_tables` then reads one run's
    tables (also in a worker process: a ``RunMeta`` and a ``RigConfig``
    pickle).

    Raises
    ------
    DataError
        ``path`` missing, or no run.json at any depth.
    ConfigError
        contract.toml ``table_formats`` and the format registry disagree.
    """
    root = Path(path)
    dirs = find_runs(root)
    if not dirs:
        raise DataError("no run.json found at any depth; expected a data set folder (sub-folders "
                        "holding run.json) or a run folder", path=root)
    base = rig if rig is not None else load_rig()
    table_formats()  # the contract and the format registry agree (else one error, not one per run)
    limit = max_pressure_mpag(base)
    metas: list[RunMeta] = []
    bad: list[RunError] = []
    for d in dirs:
        try:
            metas.append(read_run_json(d, max_pressure_mpag=limit))
        except (SeanvError, OSError) as exc:
            bad.append(RunError(d, one_line(exc)))
    metas.sort(key=lambda m: (m.started_at, m.run_id, str(m.path)))
    seen: dict[str, Path] = {}
    good: list[RunMeta] = []
    for m in metas:
        if m.run_id in seen:
            bad.append(RunError(m.path, one_line(DataError(
                f"field 'run_id': '{m.run_id}' is also the run id of {seen[m.run_id]}; expected "
                "run ids unique in the data set", path=m.path / "run.json"))))
            continue
        seen[m.run_id] = m.path
        good.append(m)
    bad.sort(key=lambda e: str(e.path))
    return good, bad, base

