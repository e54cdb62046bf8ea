"""The per-run task the workers run: read a run, look its result up in the
cache by content, compute it on a miss.

A stage hands the batch mapper a plain per-run function ``func(run,
**kwargs)`` (:mod:`seanv_analysis.stages`); the task wraps it: the run is read
in the worker (reading is the costly part, so it happens in parallel), its
files' hashes make the cache key with the stage's parameters, and the task
returns the value with the hashes and file stats, so the parent can skip the
run entirely next time.
"""
from __future__ import annotations

import os
from typing import Any, Callable, Mapping

from .cache import read_entry, run_key, write_entry

__all__ = ["cached_run_task", "file_hashes"]


def file_hashes(run) -> tuple[dict[str, str], dict[str, tuple[int, int]]]:
    """({file name: sha256}, {file name: (size, mtime_ns)}) of the files a run was read from."""
    hashes: dict[str, str] = {}
    stats: dict[str, tuple[int, int]] = {}
    for path, digest in run.file_sha256.items():
        st = os.stat(path)
        name = os.path.basename(path)   # a file's path: its name
        hashes[name] = digest
        stats[name] = (st.st_size, st.st_mtime_ns)
    return hashes, stats


def cached_run_task(run_dir: str, *, func: Callable[..., Any], func_kwargs: Mapping[str, Any],
                    stage: str, params: Mapping[str, Any], rig, entries: str | None,
                    use_cache: bool = True, valid: Callable[[Any], bool] | None = None
                    ) -> dict[str, Any]:
    """``func(run, **func_kwargs)`` of the run in ``run_dir``, from the cache
    when an entry for the same files, stage, parameters and rig exists
    (``entries`` None: no cache).

    Returns {'value', 'hashes', 'stats', 'computed': bool} and, when computed,
    'rejected': one line per cache entry found malformed (removed).
    """
    from ..io.reader import read_run

    run = read_run(run_dir, rig=rig)
    hashes, stats = file_hashes(run)
    if entries is None:
        return {"value": func(run, **func_kwargs), "hashes": hashes, "stats": stats,
                "computed": True}
    key = run_key(hashes, stage=stage, params=dict(params), rig=rig.to_dict())
    rejected: list[str] = []
    hit = read_entry(entries, key, rejected=rejected) if use_cache else None
    if hit is not None:
        if valid is None or valid(hit):
            return {"value": hit, "hashes": hashes, "stats": stats, "computed": False}
        rejected.append(f"{key}.json: not what stage '{stage}' stores")
    value = func(run, **func_kwargs)
    if valid is None or valid(value):   # never stored: what would be refused when read back
        write_entry(entries, key, value)
    return {"value": value, "hashes": hashes, "stats": stats, "computed": True,
            "rejected": rejected}
