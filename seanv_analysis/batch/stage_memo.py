"""Data-set stage cache: a stage whose inputs did not change is not run again.

The per-run cache (:mod:`.cache`) spares a re-run the per-run work; this one
spares it the data-set stages (flow fit with its bootstrap, identify,
discover) whose inputs are the same as last time, when one run of the data
set was edited in a way that left them alone (a sample outside a flow
step's steady window). ``validate`` does not take part: its work is per run
and cached per run already (its value would store the runs' overlays, 22 MB
for the paper's two position runs, a second time).

A stage takes part when it declares ``raw_inputs(ctx, options) -> [run folder]``:
the runs whose files it reads itself, beyond the data set's per-run summary
(the position-control runs, say; none for the flow fit). Its key is the
SHA-256 (:func:`~seanv_analysis.io.hashing.content_sha256`) of

- the stage, its options, the rig config, the valve model the run started
  from, the code version (package sources) and the numerical libraries';
- the per-run summary (every run's steady flow, pressures, filters: what the
  flow steps give the data-set stages) and the runs that failed;
- the SHA-256 of every file of the runs in ``raw_inputs``;
- each result of the stages before it: a cached stage's by its key (its
  value is a function of it), another's by its content.

``<out>/.cache/stages/<stage>.json`` holds the last value and the warnings
it gave, as plain data (:mod:`.codec`, headed by the SHA-256 of its payload:
never pickle, never code). A value :mod:`.codec` cannot store is simply not
cached; an unreadable entry is a miss (recomputed).
"""
from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Any, Mapping

from ..io.hashing import code_version, content_sha256
from .cache import own_folder, read_entry, write_entry
from .memo import library_versions

__all__ = ["StageMemo", "stage_key"]

_SCHEMA = "seanv-stage-memo/1"


def stage_key(mod: Any, ctx: Any, options: Mapping[str, Any],
              keys: Mapping[str, str]) -> str | None:
    """The cache key of stage module ``mod`` on ``ctx`` (module doc); None
    when the stage does not take part or an input cannot be hashed by
    content. ``keys``: the keys of the stages before it that were cached."""
    reads = getattr(mod, "raw_inputs", None)
    ds = ctx.result("ingest")
    if reads is None or ds is None:
        return None
    folders = [str(p) for p in reads(ctx, options)]
    files = {f: h for f, h in ds.input_hashes.items()
             if any(f.startswith(d.rstrip(os.sep) + os.sep) for d in folders)}
    before = {name: (("key", keys[name]) if name in keys else ("content", value))
              for name, value in ctx.results.items() if name not in ("ingest", mod.NAME)}
    try:
        return content_sha256({
            "schema": _SCHEMA, "stage": mod.NAME, "options": dict(options),
            "rig": ctx.rig.to_dict(), "start_model": ctx.start_model, "code": code_version(),
            "libraries": library_versions(), "summary": ds.summary, "failed": list(ds.failed),
            "runs_read": sorted(folders), "files": sorted(files.items()), "before": before})
    except TypeError:   # an input not hashed by content: the stage simply runs
        return None


class StageMemo:
    """The data-set stage cache of one output folder (``<out>/.cache/stages``).

    :meth:`run` is the runner's way to run a stage: the stored value when
    its key is unchanged (its warnings given again), else the stage's run,
    stored for the next time. ``enabled`` False (``--force``): every look-up
    misses, the values are still stored.
    """

    def __init__(self, cache_dir: str | Path, *, enabled: bool = True):
        self.folder = Path(cache_dir) / "stages"
        own_folder(self.folder)     # a link there is refused, never followed
        self.enabled = enabled
        #: {stage: key} of the stages cached (or storable) in this run
        self.keys: dict[str, str] = {}
        #: the stages whose value came from the cache in this run
        self.reused: list[str] = []
        #: one line per entry found malformed (removed, recomputed)
        self.rejected: list[str] = []

    def run(self, mod: Any, ctx: Any, options: Mapping[str, Any]) -> Any:
        """``mod.run(ctx, options)``, or its stored value (module doc)."""
        key = stage_key(mod, ctx, options, self.keys)
        if key is None:
            return mod.run(ctx, options)
        name = mod.NAME
        entry = read_entry(self.folder, name, rejected=self.rejected) if self.enabled else None
        if _is_entry(entry) and entry["key"] == key:
            self.keys[name] = key
            self.reused.append(name)
            for category, message in entry["warnings"]:
                warnings.warn(message, _category(category), stacklevel=2)
            return entry["value"]
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            value = mod.run(ctx, options)
        given = [(w.category.__name__, str(w.message)) for w in caught]
        for w in caught:    # for the run's own record of warnings, as without the cache
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
        if value is not None and write_entry(self.folder, name, {
                "schema": _SCHEMA, "key": key, "warnings": given, "value": value}):
            self.keys[name] = key
        return value


def _is_entry(entry: Any) -> bool:
    """What :meth:`StageMemo.run` stores: its schema, a key, the warnings as
    (category, message) text pairs and a value (anything else is a miss)."""
    return (isinstance(entry, dict) and entry.get("schema") == _SCHEMA
            and isinstance(entry.get("key"), str) and "value" in entry
            and isinstance(entry.get("warnings"), list)
            and all(isinstance(w, (list, tuple)) and len(w) == 2
                    and all(isinstance(x, str) for x in w) for w in entry["warnings"]))


def _category(name: Any) -> type[Warning]:
    """The warning class of that name among the built-in ones (UserWarning
    otherwise: a cache file names no code)."""
    import builtins

    cls = getattr(builtins, str(name), None)
    return cls if isinstance(cls, type) and issubclass(cls, Warning) else UserWarning
