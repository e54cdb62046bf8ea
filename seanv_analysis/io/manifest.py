"""Provenance of an output folder: ``manifest.json``.

Every command writes one manifest per output folder with the package
version, the git commit of the source (when run from a checkout), the rig
config, the SHA-256 of every input file, the command line and every output
file it wrote (path under the folder, SHA-256, size), so a result can be
traced to exactly what produced it and outputs of different runs in one
folder can be told apart. Input hashes are computed once
per process (the reader hashes the bytes it reads; see
:func:`seanv_analysis.io.file_sha256`).
"""
from __future__ import annotations

import functools
import hashlib
import os
import platform
import shlex
import sys
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterable, Mapping

from .. import __version__
from .atomic import write_json_atomic
from .hashing import file_sha256

__all__ = ["write_manifest", "build_manifest", "installed_packages", "input_hashes", "output_entries", "git_sha",
           "MANIFEST_SCHEMA", "NOT_LISTED"]

MANIFEST_SCHEMA = "seanv-manifest/1"
_PACKAGE_DIR = Path(__file__).resolve().parent
#: files of an output folder never listed among its outputs (they describe the run)
NOT_LISTED = ("manifest.json", "result.json")


def git_sha(start: str | Path | None = None) -> str | None:
    """Commit SHA of the git checkout holding ``start`` (default: this package),
    read from ``.git`` files (no git process); None outside a checkout."""
    here = Path(start or _PACKAGE_DIR).resolve()
    for folder in (here, *here.parents):
        dot_git = folder / ".git"
        if dot_git.exists():
            return _read_head(dot_git)
    return None


def _read_head(dot_git: Path) -> str | None:
    try:
        git_dir = dot_git
        if dot_git.is_file():  # worktree or submodule: "gitdir: <path>"
            text = dot_git.read_text().strip()
            if not text.startswith("gitdir:"):
                return None
            git_dir = (dot_git.parent / text.split(":", 1)[1].strip()).resolve()
        head = (git_dir / "HEAD").read_text().strip()
        if not head.startswith("ref:"):
            return head or None  # detached HEAD
        ref = head.split(":", 1)[1].strip()
        common = git_dir
        if (git_dir / "commondir").is_file():
            common = (git_dir / (git_dir / "commondir").read_text().strip()).resolve()
        for base in (git_dir, common):
            if (base / ref).is_file():
                return (base / ref).read_text().strip() or None
            packed = base / "packed-refs"
            if packed.is_file():
                for line in packed.read_text().splitlines():
                    parts = line.split()
                    if len(parts) == 2 and parts[1] == ref:
                        return parts[0]
        return None
    except OSError:
        return None


def _files_under(folder: Path) -> list[Path]:
    out = []
    for dirpath, dirnames, filenames in os.walk(folder):
        dirnames[:] = sorted(d for d in dirnames if not d.startswith("."))
        out.extend(Path(dirpath) / f for f in sorted(filenames)
                   if not f.startswith(".") and os.path.isfile(os.path.join(dirpath, f)))
    return out  # regular files only: a broken or looping link or a FIFO is no input


def input_hashes(inputs: Mapping[str | Path, str] | Iterable[str | Path]) -> dict[str, str]:
    """{path: SHA-256} of the inputs.

    ``inputs`` is either a mapping of already computed digests
    ({path: hex}) or paths: files are hashed (once per process), folders are
    walked (every non-hidden file, sorted).
    """
    if isinstance(inputs, Mapping):
        return {str(k): str(v) for k, v in sorted(inputs.items(), key=lambda kv: str(kv[0]))}
    out: dict[str, str] = {}
    for item in inputs:
        path = Path(item)
        files = _files_under(path) if path.is_dir() else [path]
        for f in files:
            out[str(f)] = file_sha256(f)
    return dict(sorted(out.items()))


def output_entries(out_dir: str | Path, outputs: Iterable[str | Path]) -> list[dict[str, Any]]:
    """[{path, sha256, size}] of the output files, ``path`` relative to
    ``out_dir``, sorted; each file hashed now (outputs change between runs
    of one process, so no digest is reused). ``manifest.json`` and
    ``result.json`` of ``out_dir``, missing files and duplicates are left out."""
    out = Path(out_dir)
    skip = {out / name for name in NOT_LISTED}
    entries: dict[str, dict[str, Any]] = {}
    for item in outputs:
        path = Path(item)
        if path in skip or not path.is_file():
            continue
        rel = str(path.relative_to(out)) if path.is_relative_to(out) else str(path)
        entries[rel] = {"path": rel, **_digest(path)}
    return [entries[k] for k in sorted(entries)]


def _digest(path: Path) -> dict[str, Any]:
    """SHA-256 and size of a file, read in chunks."""
    h, size = hashlib.sha256(), 0
    with open(path, "rb") as fh:
        while chunk := fh.read(1 << 22):
            h.update(chunk)
            size += len(chunk)
    return {"sha256": h.hexdigest(), "size": size}


@functools.lru_cache(maxsize=1)
def _installed() -> tuple[tuple[str, str], ...]:
    from importlib.metadata import distributions

    seen: dict[str, str] = {}
    for dist in distributions():
        name = (dist.metadata["Name"] or "").strip()
        if name and name.lower() not in seen:
            seen[name.lower()] = f"{name}=={dist.version}"
    return tuple(sorted(seen.items()))


def installed_packages() -> list[str]:
    """``name==version`` of every distribution installed in this Python
    (what ``pip freeze`` lists), sorted; read once per process."""
    return [spec for _, spec in _installed()]


def build_manifest(*, config: Any, inputs: Mapping[str | Path, str] | Iterable[str | Path],
                   command: str | Iterable[str], extra: Mapping[str, Any] | None = None,
                   outputs: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    """The manifest as a dict (see :func:`write_manifest`); ``outputs`` as
    :func:`output_entries` gives them."""
    if hasattr(config, "to_dict"):
        config = config.to_dict()
    hashes = input_hashes(inputs)
    combined = hashlib.sha256()
    for path, digest in hashes.items():
        combined.update(f"{path}\0{digest}\n".encode())
    argv = [command] if isinstance(command, str) else [str(a) for a in command]
    doc: dict[str, Any] = {
        "schema": MANIFEST_SCHEMA,
        "package": "seanv-analysis",
        "version": __version__,
        "git_sha": git_sha(),
        "created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "command": argv,
        "command_line": argv[0] if isinstance(command, str) else shlex.join(argv),
        "cwd": os.getcwd(),
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "packages": installed_packages(),
        "config": config,
        "inputs": [{"path": p, "sha256": h} for p, h in hashes.items()],
        "inputs_sha256": combined.hexdigest(),
        "outputs": list(outputs or []),
    }
    if extra:
        doc["extra"] = dict(extra)
    return doc


def write_manifest(out_dir: str | Path, *, config: Any,
                   inputs: Mapping[str | Path, str] | Iterable[str | Path],
                   command: str | Iterable[str], extra: Mapping[str, Any] | None = None,
                   outputs: Iterable[str | Path] = (), created_utc: str | None = None) -> Path:
    """Write ``<out_dir>/manifest.json`` atomically and return its path.

    Parameters
    ----------
    out_dir : output folder of the command
    config : rig config (a :class:`~seanv_analysis.config.RigConfig` or its dict)
    inputs : input files and folders (hashed here, once per process) or a
        ready {path: sha256} mapping (e.g. ``DatasetRead.file_sha256()``)
    command : the command line (``sys.argv``) or a string
    extra : anything else worth keeping (options, bad runs, counts)
    outputs : the files the command wrote (this manifest and ``result.json``
        are never listed); each is hashed now
    created_utc : time stamp to keep when the manifest is written again at
        the end of a run (default: now)

    Returns
    -------
    Path of manifest.json. Fields: schema, package, version, git_sha (None
    outside a checkout), created_utc, command, command_line, cwd, python,
    platform, packages (``name==version`` of every installed distribution, as
    ``pip freeze``), config, inputs [{path, sha256}], inputs_sha256 (one digest over
    all inputs: a cache key), outputs [{path (relative to ``out_dir``),
    sha256, size}], extra. A file of ``out_dir`` not among the outputs was
    not written by this command.

    Examples
    --------
    >>> import tempfile, json
    >>> d = tempfile.mkdtemp()
    >>> p = write_manifest(d, config={"a": 1}, inputs={}, command=["seanv-analyze", "ingest", "x"])
    >>> json.loads(p.read_text())["command_line"]
    'seanv-analyze ingest x'
    """
    doc = build_manifest(config=config, inputs=inputs, command=command, extra=extra,
                         outputs=output_entries(out_dir, outputs))
    if created_utc is not None:
        doc["created_utc"] = created_utc
    return write_json_atomic(Path(out_dir) / "manifest.json", doc)
