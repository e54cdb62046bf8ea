"""The field data: logs from a rig nobody here wrote, with its truth (not part
of the package; for tests and benchmarks).

The archive sits beside the repository: ``../shared/field-data`` (from
``/work/main``; from a worktree deeper down, the nearest ``shared/field-data``
above it), or where ``SEANV_FIELD_DATA`` points. Its ``unpack DEST`` script
writes ``DEST/field-clean``, ``DEST/field-drift-backlash``,
``DEST/field-slow-servo`` and ``DEST/_truth/<set>.json`` (skipped when DEST
already holds them). The truth is read, never copied into code or rig files.
"""
from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

__all__ = ["FIELD_SETS", "field_archive", "unpack_field_data", "field_truth"]

#: the three data sets of the archive
FIELD_SETS = ("field-clean", "field-drift-backlash", "field-slow-servo")

REPO = Path(__file__).resolve().parents[1]


def field_archive() -> Path | None:
    """The folder holding the archive and its ``unpack`` script, or None."""
    env = os.environ.get("SEANV_FIELD_DATA")
    candidates = [Path(env)] if env else []
    candidates += [p / "shared" / "field-data" for p in REPO.parents]
    return next((c for c in candidates if (c / "unpack").is_file()), None)


def unpack_field_data(dest: Path) -> Path | None:
    """The field data unpacked into ``dest`` (its own script; a few seconds
    once), or None without the archive."""
    archive = field_archive()
    if archive is None:
        return None
    dest = Path(dest)
    subprocess.run([str(archive / "unpack"), str(dest)], check=True, capture_output=True)
    return dest


def field_truth(root: Path, name: str) -> dict:
    """``_truth/<name>.json`` of an unpacked field data set."""
    return json.loads((Path(root) / "_truth" / f"{name}.json").read_text())
