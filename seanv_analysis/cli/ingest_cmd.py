"""``seanv-analyze ingest``: validate, calibrate and align rig logs; write
Parquet tables, a per-run summary and a manifest."""
from __future__ import annotations

import hashlib
import json
import os
import sys
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import click

from . import cli
from ._common import OUT_FOLDER, check_out_dir, default_out_dir, echo_bad_runs, verbosity

__all__ = ["ingest_cmd", "ingest", "ingest_into", "summarize_keeping_samples", "part_path"]


def _inside(child: Path, parent: Path) -> bool:
    child, parent = child.resolve(), parent.resolve()
    return child == parent or parent in child.parents


#: the folder of the per-run sample parts inside the output folder being
#: written (merged into ``<kind>.parquet`` and removed before the swap)
PARTS = ".samples-parts"


def part_path(parts: str | Path, run_dir: str | Path) -> Path:
    """Where the derived samples of the run in ``run_dir`` go before they are
    merged: ``<parts>/<SHA-256 of the folder path, 16 hex>.parquet``."""
    digest = hashlib.sha256(str(Path(run_dir)).encode()).hexdigest()[:16]
    return Path(parts) / f"{digest}.parquet"


def summarize_keeping_samples(run, *, method: str, parts: str) -> dict[str, Any]:
    """Per-run function of ``ingest --samples`` (module level: it runs in
    worker processes): the run's summary row, as the ``ingest`` stage makes
    it from the derived samples (:func:`~seanv_analysis.signals.derive.derive_samples`,
    computed once), and those samples with a ``run_id`` column first written
    to :func:`part_path` (atomically) for the command to merge."""
    import pyarrow as pa
    import pyarrow.compute as pc
    import pyarrow.parquet as pq

    from ..io.atomic import atomic_path
    from ..signals.derive import derive_samples, summarize_run

    samples = derive_samples(run)
    meta = run.meta
    value = {"row": summarize_run(run, method=method, derived=samples),
             "meta": {"path": str(Path(meta.path)), "run_id": meta.run_id, "kind": meta.kind,
                      "controller": dict(meta.controller or {})}}
    table = pa.Table.from_pandas(samples, preserve_index=False)
    table = table.add_column(0, "run_id", pc.fill_null(pa.nulls(table.num_rows, pa.string()),
                                                       run.run_id))
    path = part_path(parts, meta.path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        pq.write_table(table, tmp)
    return value


def _merge_samples(parts: Path, out_dir: Path, summary, metadata: dict[str, Any]
                   ) -> tuple[dict[str, str], dict[str, int]]:
    """One Parquet file per run kind from the runs' sample parts, in the
    summary's (``started_at``) order, part by part (bounded memory), written
    atomically: the first run of a kind sets the columns; a later run's
    missing column is null, an extra one dropped. Units in the schema
    metadata. Returns ({kind: path}, {kind: rows})."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from ..io.atomic import atomic_path
    from ..io.writer import units_from_columns

    tables: dict[str, str] = {}
    rows: dict[str, int] = {}
    with ExitStack() as stack:
        writers: dict[str, Any] = {}
        schemas: dict[str, Any] = {}
        for run_dir, kind in zip(summary["path"], summary["kind"]):
            table = pq.read_table(part_path(parts, run_dir))
            if kind not in writers:
                units = units_from_columns(table.column_names)
                fields = [f.with_metadata({b"unit": units[f.name].encode()}) for f in table.schema]
                meta = {b"seanv.units": json.dumps(units).encode(),
                        b"seanv.meta": json.dumps({**metadata, "kind": kind}, default=str).encode()}
                schemas[kind] = pa.schema(fields, metadata=meta)
                path = out_dir / f"{kind}.parquet"
                tmp = stack.enter_context(atomic_path(path))
                writers[kind] = pq.ParquetWriter(tmp, schemas[kind])
                stack.callback(writers[kind].close)
                tables[kind], rows[kind] = str(path), 0
            schema = schemas[kind]
            table = pa.table({f.name: (table[f.name] if f.name in table.column_names
                                       else pa.nulls(table.num_rows, f.type)) for f in schema})
            writers[kind].write_table(table.cast(schema))
            rows[kind] += table.num_rows
    return tables, rows


def ingest(data: Path, *, out_dir: Path, rig, progress: bool = False,
           samples: bool = False, final_dir: Path | None = None) -> dict[str, Any]:
    """Library side of the command: the ``ingest`` stage
    (:mod:`seanv_analysis.stages.dataset`, every run's samples aligned and
    derived, so a run whose streams cannot be aligned is a bad run), per-run
    work on all cores for large data sets (as the other commands'), into
    ``out_dir``: ``summary.parquet`` and ``manifest.json``, and with
    ``samples`` each run's derived samples in ``<kind>.parquet``.

    Returns a result dict (also the ``--json`` document; its paths, and the
    manifest's, under ``final_dir`` where ``out_dir`` is a folder to be
    renamed there); raises :class:`~seanv_analysis.errors.DataError` for a
    single bad run folder.
    """
    import shutil

    from ..errors import DataError
    from ..io.manifest import write_manifest
    from ..io.reader import is_run_dir
    from ..io.writer import write_table_parquet
    from ..stages import dataset
    from ._common import stage_context

    root = Path(data)
    out_dir = Path(out_dir)
    parts = out_dir / PARTS
    meta = {"rig_source": rig.source, "data": str(root)}
    # missing / not a folder / no run -> DataError
    with stage_context(root, rig=rig, out_dir=None, quiet=not progress) as ctx:
        if _inside(out_dir, root):
            raise DataError(f"--out: {out_dir} is inside the data folder; outputs never go into "
                            "raw data: choose another --out (default: outputs/<dataset-name>/"
                            "ingest/ under the current folder)", path=root)
        if samples:
            ds = dataset.collect(ctx, {}, func=summarize_keeping_samples,
                                 kwargs={"parts": str(parts)})
        else:
            ds = dataset.collect(ctx, {"derive": True})
    try:
        errors = list(ds.failed)
        if is_run_dir(root) and errors:
            raise DataError(errors[0].message)
        if ds.runs_read == 0:  # nothing is written
            return _result(root, out_dir, {}, ds, {}, None, excluded={}, samples=samples)
        summary = ds.contract_table()
        by_kind = {str(k): int(n) for k, n in summary["kind"].value_counts(sort=False).items()}
        tables, rows = (_merge_samples(parts, out_dir, ds.summary, meta) if samples else ({}, {}))
    finally:
        shutil.rmtree(parts, ignore_errors=True)
    summary_path = write_table_parquet(summary, out_dir / "summary.parquet", metadata=meta)
    result = _result(root, out_dir, by_kind, ds, tables, summary_path,
                     excluded={k: v for k, v in ds.excluded.items() if v}, samples=samples)
    result["rows"] = rows
    final = _moved(result, out_dir, Path(final_dir)) if final_dir is not None else result
    manifest = write_manifest(out_dir, config=rig, inputs=ds.input_hashes, command=sys.argv,
                              extra={"ingest": {k: v for k, v in final.items() if k != "manifest"}},
                              outputs=[*tables.values(), summary_path])
    result["manifest"] = str(manifest)
    return result


def _result(root, out_dir, by_kind, ds, tables, summary_path, *, excluded, samples: bool):
    return {
        "data": str(root),
        "out": str(out_dir),
        "runs": sum(by_kind.values()),
        "runs_by_kind": by_kind,
        "bad_runs": [e.to_json_dict() for e in ds.failed],
        # the block every command's --json carries (ingest keeps excluded runs:
        # their reason is in summary.parquet, none is skipped)
        "inputs": ds.runs_json(),
        "tables": tables,
        "summary": None if summary_path is None else str(summary_path),
        "excluded": excluded,
        "derived": True,
        "filtered": True,
        "samples": bool(samples),
        "manifest": None,
    }


class _NothingRead(Exception):
    """No run could be read: the result rides along; raised inside the
    output folder's swap, so nothing is swapped in."""

    def __init__(self, result: dict[str, Any]):
        super().__init__("no run read")
        self.result = result


def ingest_into(data: Path, out: Path, *, rig, progress: bool = False,
                samples: bool = False) -> dict[str, Any]:
    """:func:`ingest` into a new folder beside ``out``, swapped in whole when
    it is complete (as the other single commands write theirs: no file of an
    earlier data set stays), one command at a time per folder (a lock beside
    it); the result's paths are the final ones. When no run could be read,
    or on an error, ``out`` is left as it was."""
    from ..io.atomic import atomic_folder
    from ..io.outdir import out_lock

    out = Path(out)
    with out_lock(out, beside=True):
        empty = out.is_dir() and not out.is_symlink() and not any(out.iterdir())
        if empty:       # an empty folder (the probe made it, or the user): taken
            out.rmdir()
        try:
            with atomic_folder(out) as tmp:
                result = ingest(data, out_dir=tmp, rig=rig, progress=progress, samples=samples,
                                final_dir=out)
                if result["runs"] == 0:
                    raise _NothingRead(result)
        except _NothingRead as exc:
            result = exc.result
        finally:
            if empty and not out.exists():
                out.mkdir()
    return _moved(result, tmp, out)


def _moved(value: Any, tmp: Path, out: Path) -> Any:
    """``value`` with every path string under ``tmp`` put under ``out``."""
    if isinstance(value, dict):
        return {k: _moved(v, tmp, out) for k, v in value.items()}
    if isinstance(value, list):
        return [_moved(v, tmp, out) for v in value]
    if isinstance(value, str) and (value == str(tmp) or value.startswith(str(tmp) + os.sep)):
        return str(out) + value[len(str(tmp)):]
    return value


@cli.command("ingest")
@verbosity
@click.argument("data", type=click.Path(path_type=Path))
@click.option("--out", "out_dir", type=OUT_FOLDER,
              help="Output folder. Default: outputs/<dataset-name>/ingest/ under the current "
                   "folder (never inside DATA).")
@click.option("--rig", "rig_file", type=click.Path(dir_okay=False, path_type=Path),
              help="Rig config TOML with only the keys you change (calibration, "
                   "analysis.max_plausible_pressure_mpag, ...). Default: "
                   "data_schema/rig/default.toml.")
@click.option("--samples", is_flag=True,
              help="Also write every run's aligned, derived samples (<kind>.parquet; about "
                   "the size of the CSV logs). Default: the per-run summary only.")
@click.option("--json", "as_json", is_flag=True,
              help="Print the result as one JSON document on stdout (nothing else on stdout).")
def ingest_cmd(data: Path, out_dir: Path | None, rig_file: Path | None, samples: bool,
               as_json: bool, quiet: bool) -> int:
    """Validate, calibrate and align the runs in DATA; write Parquet tables.

    DATA is a data set folder (sub-folders at any depth holding run.json) or
    one run folder. Every run is checked against the data contract (files,
    columns, numbers, strictly increasing t_s, pressures in MPa gauge); raw
    columns (encoder_counts, p_*_v, p_*_kpag, *_pulse) are converted with the
    rig's [calibration]; missing p_tank_mpag is 0 MPaG. Streams are put on the
    encoder's time base inside the span all streams cover (measurements
    interpolated linearly, commands held), and flow is derived.

    \b
    Writes (under --out, default outputs/<dataset-name>/ingest/; the folder
    is written whole and swapped in, no file of an earlier run stays):
      flow_step.parquet, position_control.parquet   (only with --samples)
          aligned samples, one row per encoder sample: run_id, t_s [s],
          position_mm, p_supply/head/load/tank_mpag [MPa gauge],
          cam_cmd_deg, cam_deg [deg] (x_ref_mm, q_ref_mm3_s for position
          control); units also in the Parquet schema metadata
      summary.parquet   one row per run (run_id, started_at, load_mpag,
                        cam_deg, q_mm3_s, dp_mpa, excluded, ...)
      manifest.json     package version, git SHA, rig config, SHA-256 of
                        every input file, command line

    \b
    Exit codes: 0 all runs read; 1 some runs bad (listed on stderr at the
    end, the others processed); 2 bad input (a bad single run folder, a
    missing folder, a bad rig file), one line on stderr.

    \b
    Example:
      seanv-analyze ingest data/flow --json
      seanv-analyze ingest data/flow --samples --out /tmp/flow-samples
      seanv-analyze ingest data/flow/supply-load0.35-cam-8.0-r2 --out /tmp/one
    """
    from ..config import load_rig

    rig = load_rig(rig_file)
    out = Path(out_dir) if out_dir else default_out_dir(data, "ingest")
    check_out_dir(data, out, files=[rig_file], owned=(".",))
    progress = not quiet and not os.environ.get("CI")
    result = ingest_into(data, out, rig=rig, progress=progress, samples=samples)
    if as_json:
        click.echo(json.dumps(result))
    else:
        kinds = ", ".join(f"{k}: {n}" for k, n in sorted(result["runs_by_kind"].items()))
        click.echo(f"ingested {result['runs']} run(s) from {data}" + (f" ({kinds})" if kinds else ""))
        if result["excluded"]:
            ex = ", ".join(f"{k}: {n}" for k, n in sorted(result["excluded"].items()))
            click.echo(f"excluded by the filters: {ex}")
        if result["summary"]:
            click.echo(f"outputs: {out}")
    return echo_bad_runs([e["message"] for e in result["bad_runs"]])
