"""Whole-pipeline memo: a re-run with nothing changed reuses the last run.

The per-run cache (:mod:`.cache`) spares a re-run the per-run work, but the
data-set stages (flow fit with its bootstrap, identify, discover, figures)
would still run. After a run that succeeded, ``<out>/.cache/pipeline.json``
records a key and the outputs written (size and mtime). The key is the
SHA-256 of everything the results depend on: the pipeline (stages and
options), the rig config, the code version (package sources), the versions
of the numerical libraries, the data folders, and the content of every file
in every run folder. A later run with the same key whose outputs are all
still there, untouched, reuses ``result.json`` and writes nothing;
otherwise (or with ``force``) it runs.
"""
from __future__ import annotations

import functools
import hashlib
import json
from importlib import metadata
from pathlib import Path
from typing import Any, Iterable

from ..io.atomic import write_json_atomic
from ..io.hashing import file_sha256
from ..io.readback import load_json_back, regular_file_inside
from .cache import code_version, folder_listing

__all__ = ["pipeline_key", "recorded_run", "record_run", "forget_run", "library_versions", "MEMO_NAME"]

MEMO_NAME = "pipeline.json"
_SCHEMA = "seanv-pipeline-memo/1"
#: libraries whose version can move the numbers
_LIBRARIES = ("numpy", "scipy", "pandas", "pyarrow", "numba", "matplotlib")


@functools.lru_cache(maxsize=1)
def _library_versions() -> tuple[tuple[str, str], ...]:
    out = {}
    for name in _LIBRARIES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = ""
    return tuple(out.items())


def library_versions() -> dict[str, str]:
    """{library: version} of the numerical libraries (:data:`_LIBRARIES`)."""
    return dict(_library_versions())


def pipeline_key(pipeline: dict, rig: dict, data: Iterable[Path], run_dirs: Iterable[Path],
                 extra: Any = None) -> str:
    """SHA-256 (hex) of what a pipeline run's results depend on (module doc)."""
    runs = []
    for d in sorted(Path(p).resolve() for p in run_dirs):
        files = {name: file_sha256(d / name) for name in sorted(folder_listing(d))}
        runs.append([str(d), files])
    doc = {"pipeline": pipeline, "rig": rig, "code": code_version(), "libraries": library_versions(),
           "data": [str(Path(p).resolve()) for p in data], "runs": runs, "extra": extra}
    return hashlib.sha256(json.dumps(doc, sort_keys=True, default=str).encode()).hexdigest()


def _stat(path: Path) -> list[int] | None:
    try:
        st = path.stat()
    except OSError:
        return None
    return [st.st_size, st.st_mtime_ns]


def record_run(out_dir: Path, key: str, outputs: Iterable[Path]) -> None:
    """Remember a finished run: its key and each output's size and mtime."""
    out_dir = Path(out_dir)
    files = {}
    for p in outputs:
        st = _stat(Path(p))
        if st is not None:
            files[str(Path(p).resolve())] = st
    write_json_atomic(out_dir / ".cache" / MEMO_NAME,
                      {"schema": _SCHEMA, "key": key, "outputs": files}, indent=0)


def forget_run(out_dir: Path) -> None:
    """Drop the memo (a run is about to rewrite the outputs it describes);
    a ``.cache`` that is a link is not followed."""
    cache = Path(out_dir) / ".cache"
    if cache.is_dir() and not cache.is_symlink():
        (cache / MEMO_NAME).unlink(missing_ok=True)


def _is_failed_run(f: Any) -> bool:
    return (isinstance(f, dict) and set(f) == {"path", "stage", "message"}
            and all(isinstance(v, str) for v in f.values()))


def _is_stat(st: Any) -> bool:
    return isinstance(st, list) and len(st) == 2 and all(type(n) is int for n in st)


#: what :func:`recorded_run` needs of the memo and of ``result.json``
#: (:meth:`~seanv_analysis.batch.runner.PipelineResult.from_recorded` reads these)
_MEMO_SHAPE = {"schema": _SCHEMA.__eq__, "key": str, "outputs": {str: _is_stat}}
_RESULT_SHAPE = {"schema": "seanv-pipeline-result/2".__eq__, "runs_found": int, "runs_read": int,
                 "failed": [_is_failed_run], "excluded": {str: int}, "figures": {str: [str]},
                 "stage_errors": {str: str}, "stage_notes": {str: str}, "outputs": [str],
                 "report": (str, type(None))}


def recorded_run(out_dir: Path, key: str) -> dict | None:
    """The last run's ``result.json`` document when it had ``key`` and every
    output it wrote is unchanged; else None.

    Both files are read as untrusted input (:mod:`seanv_analysis.io.readback`):
    a memo or a ``result.json`` that is malformed, a link, not a regular
    file, or that names a file outside ``out_dir`` (or one the memo did not
    record) is a miss, and the pipeline runs."""
    out_dir = Path(out_dir)
    memo = load_json_back(out_dir / ".cache" / MEMO_NAME, root=out_dir, shape=_MEMO_SHAPE)
    if memo is None or memo["key"] != key:
        return None
    outputs = memo["outputs"]
    for p, st in outputs.items():
        if not regular_file_inside(p, out_dir) or _stat(Path(p)) != st:
            return None
    result = out_dir / "result.json"
    if str(result.resolve()) not in outputs:
        return None
    doc = load_json_back(result, root=out_dir, shape=_RESULT_SHAPE)
    if doc is None:
        return None
    named = [*doc["outputs"], *(p for ps in doc["figures"].values() for p in ps),
             *([doc["report"]] if doc["report"] else [])]
    try:
        if any(str(Path(p).resolve()) not in outputs for p in named):
            return None
    except (OSError, RuntimeError, ValueError):
        return None
    return doc
