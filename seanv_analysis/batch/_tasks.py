"""Per-run tasks run by the workers (module-level functions, picklable).

Each task gets a run folder path and small options, reads the run itself
(reading is the costly part, so it happens in parallel), looks its result
up in the cache by content key and computes it only on a miss. It returns
the result together with the input hashes and file stats, so the parent
can skip the run entirely next time.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from .cache import read_entry, run_key, write_entry

__all__ = ["ingest_task", "fig6_task", "validate_task", "file_hashes"]


def file_hashes(run) -> tuple[dict[str, str], dict[str, tuple[int, int]]]:
    """({file name: sha256}, {file name: (size, mtime_ns)}) of the files a run was read from."""
    hashes: dict[str, str] = {}
    stats: dict[str, tuple[int, int]] = {}
    for path, digest in run.file_sha256.items():
        p = Path(path)
        st = os.stat(p)
        hashes[p.name] = digest
        stats[p.name] = (st.st_size, st.st_mtime_ns)
    return hashes, stats


def _meta_fields(run) -> dict[str, Any]:
    meta = run.meta
    return {"path": str(Path(meta.path)), "run_id": meta.run_id, "kind": meta.kind,
            "controller": dict(meta.controller or {})}


def ingest_task(run_dir: str, *, rig, method: str, entries: str, use_cache: bool = True
                ) -> dict[str, Any]:
    """Read one run and summarise it (``derive.summarize_run``), cached.

    Returns {'row': summary row dict, 'meta': {...}, 'hashes', 'stats',
    'computed': bool (False when the result came from the cache)}.
    """
    from ..signals import derive
    from ..io.reader import read_run

    run = read_run(run_dir, rig=rig)
    hashes, stats = file_hashes(run)
    key = run_key(hashes, stage="ingest", params={"method": method}, rig=rig.to_dict())
    hit = read_entry(entries, key) if use_cache else None
    if hit is not None:
        return {**hit, "hashes": hashes, "stats": stats, "computed": False}
    value = {"row": derive.summarize_run(run, method=method), "meta": _meta_fields(run)}
    write_entry(entries, key, value)
    return {**value, "hashes": hashes, "stats": stats, "computed": True}


def fig6_task(run_dir: str, *, rig, out_dir: str, formats: tuple[str, ...], entries: str,
              use_cache: bool = True) -> dict[str, Any]:
    """Fig. 6 of one position-control run (``plots.fig6.plot_fig6``), cached
    (a hit needs the figure files still present)."""
    from ..io.reader import read_run
    from ..plots.fig6 import plot_fig6

    run = read_run(run_dir, rig=rig)
    hashes, stats = file_hashes(run)
    key = run_key(hashes, stage="fig6", params={"out_dir": str(out_dir), "formats": list(formats)},
                  rig=rig.to_dict())
    hit = read_entry(entries, key) if use_cache else None
    if hit is not None and all(Path(p).is_file() for p in hit["paths"]):
        return {**hit, "hashes": hashes, "stats": stats, "computed": False}
    folder = Path(out_dir)
    paths = plot_fig6(run, folder)
    paths = [str(p) for p in (paths if isinstance(paths, (list, tuple)) else [paths]) if p]
    value = {"paths": paths, "run_id": run.meta.run_id}
    write_entry(entries, key, value)
    return {**value, "hashes": hashes, "stats": stats, "computed": True}


def validate_task(run_dir: str, *, rig, model: dict[str, Any], effects: tuple[str, ...],
                  seed: int, entries: str, use_cache: bool = True) -> dict[str, Any]:
    """Free-run validation of one position-control run
    (``analysis.validate.validate_run``: the run's controller on the simulated
    plant with ``model``), cached. A run that cannot be validated (DataError)
    is returned as ``{'skipped': reason}``."""
    import warnings

    from ..analysis.validate import validate_run
    from ..errors import DataError
    from ..io.reader import read_run
    from ..models import ValveModel

    run = read_run(run_dir, rig=rig)
    hashes, stats = file_hashes(run)
    key = run_key(hashes, stage="validate",
                  params={"model": model, "effects": list(effects), "seed": seed},
                  rig=rig.to_dict())
    hit = read_entry(entries, key) if use_cache else None
    if hit is not None:
        return {**hit, "hashes": hashes, "stats": stats, "computed": False}
    valve = ValveModel.from_dict(model, rig=rig)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            rv = validate_run(run, valve, rig=rig, seed=seed, effects=tuple(effects))
        rv.simulated = None  # the simulated run is large and not needed downstream
        value = {"validation": rv, "notes": [f"{run.run_id}: {w.message}" for w in caught]}
    except DataError as exc:
        value = {"skipped": " ".join(str(exc).split()), "run_id": run.run_id}
    write_entry(entries, key, value)
    return {**value, "hashes": hashes, "stats": stats, "computed": True}
