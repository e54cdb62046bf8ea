"""``seanv-analyze ingest``: validate, calibrate and align rig logs; write
Parquet tables, a per-run summary and a manifest."""
from __future__ import annotations

import json
import os
import sys
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import click

from . import cli
from ._common import OUT_FOLDER, check_out_dir, default_out_dir, echo_bad_runs, verbosity

__all__ = ["ingest_cmd", "ingest"]


def _inside(child: Path, parent: Path) -> bool:
    child, parent = child.resolve(), parent.resolve()
    return child == parent or parent in child.parents


class _SampleWriter:
    """One Parquet file per run kind, written run by run (bounded memory),
    atomically (temp file renamed when the command succeeds)."""

    def __init__(self, out_dir: Path, stack: ExitStack, metadata: dict[str, Any]):
        self.out_dir, self.stack, self.metadata = out_dir, stack, metadata
        self.writers: dict[str, Any] = {}
        self.schemas: dict[str, Any] = {}
        self.rows: dict[str, int] = {}

    def path(self, kind: str) -> Path:
        return self.out_dir / f"{kind}.parquet"

    def write(self, kind: str, run_id: str, samples) -> None:
        import pyarrow as pa
        import pyarrow.compute as pc
        import pyarrow.parquet as pq

        from ..io.atomic import atomic_path
        from ..io.writer import units_from_columns

        if kind in self.schemas:
            samples = samples.reindex(columns=[n for n in self.schemas[kind].names if n != "run_id"])
        table = pa.Table.from_pandas(samples, preserve_index=False)
        ids = pc.fill_null(pa.nulls(table.num_rows, pa.string()), run_id)
        table = table.add_column(0, "run_id", ids)
        if kind not in self.writers:
            units = units_from_columns(table.column_names)
            fields = [f.with_metadata({b"unit": units[f.name].encode()}) for f in table.schema]
            meta = {b"seanv.units": json.dumps(units).encode(),
                    b"seanv.meta": json.dumps({**self.metadata, "kind": kind}, default=str).encode()}
            schema = pa.schema(fields, metadata=meta)
            tmp = self.stack.enter_context(atomic_path(self.path(kind)))
            writer = pq.ParquetWriter(tmp, schema)
            self.stack.callback(writer.close)
            self.writers[kind], self.schemas[kind], self.rows[kind] = writer, schema, 0
        table = table.cast(self.schemas[kind])
        self.writers[kind].write_table(table)
        self.rows[kind] += table.num_rows


def ingest(data: Path, *, out_dir: Path, rig, progress: bool = False) -> dict[str, Any]:
    """Library side of the command: the ``ingest`` stage
    (:mod:`seanv_analysis.stages.dataset`), each run's aligned, derived
    samples also written to ``<kind>.parquet`` as it is read.

    Returns a result dict (also the ``--json`` document); raises
    :class:`~seanv_analysis.errors.DataError` for a single bad run folder.
    """
    from ..errors import DataError
    from ..io.manifest import write_manifest
    from ..io.reader import dataset_plan, is_run_dir
    from ..io.writer import write_table_parquet
    from ..signals.derive import derive_samples, summarize_run
    from ..stages import Context, dataset

    root = Path(data)
    ctx = Context.for_data(root, rig=rig)  # missing / not a folder / no run -> DataError
    if _inside(out_dir, root):
        raise DataError(f"--out: {out_dir} is inside the data folder; outputs never go into raw "
                        "data: choose another --out (default: outputs/<dataset-name>/ingest/ under "
                        "the current folder)", path=root)
    # samples are written in time order (the plan's started_at order), bad metadata last
    order = {str(m.path): i for i, m in enumerate(dataset_plan(root, rig=rig)[0])}
    ctx.run_dirs.sort(key=lambda d: (order.get(str(d), len(order)), str(d)))
    meta = {"rig_source": rig.source, "data": str(root)}
    by_kind: dict[str, int] = {}
    with ExitStack() as stack:
        writer = _SampleWriter(out_dir, stack, meta)
        bar = None
        if progress and len(ctx.run_dirs) > 1:   # drawn on a terminal (seanv_analysis.log)
            from ..log import progress as progress_bar

            bar = stack.enter_context(progress_bar(total=len(ctx.run_dirs), desc="ingest"))

        def summarize_and_write(run, *, method):
            samples = derive_samples(run)  # the derived table is computed once
            try:
                value = {"row": summarize_run(run, method=method, derived=samples),
                         "meta": {"controller": dict(run.meta.controller or {})}}
                writer.write(run.kind, run.run_id, samples)
                by_kind[run.kind] = by_kind.get(run.kind, 0) + 1
            finally:
                if bar is not None:
                    bar.update()
            return value

        ds = dataset.collect(ctx, {}, func=summarize_and_write)
        errors = list(ds.failed)
        if is_run_dir(root) and errors:
            raise DataError(errors[0].message)
        if ds.runs_read == 0:  # no writer was opened: nothing is written
            return _result(root, out_dir, by_kind, ds, {}, None, excluded={})
        summary = ds.contract_table()
    tables = {kind: str(writer.path(kind)) for kind in writer.rows}
    summary_path = write_table_parquet(summary, out_dir / "summary.parquet", metadata=meta)
    result = _result(root, out_dir, by_kind, ds, tables, summary_path,
                     excluded={k: v for k, v in ds.excluded.items() if v})
    result["rows"] = dict(writer.rows)
    manifest = write_manifest(out_dir, config=rig, inputs=ds.input_hashes, command=sys.argv,
                              extra={"ingest": {k: v for k, v in result.items() if k != "manifest"}},
                              outputs=[*tables.values(), summary_path])
    result["manifest"] = str(manifest)
    return result


def _result(root, out_dir, by_kind, ds, tables, summary_path, *, excluded):
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
        "manifest": None,
    }


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
@click.option("--json", "as_json", is_flag=True,
              help="Print the result as one JSON document on stdout (nothing else on stdout).")
def ingest_cmd(data: Path, out_dir: Path | None, rig_file: Path | None, as_json: bool,
               quiet: bool) -> int:
    """Validate, calibrate and align the runs in DATA; write Parquet tables.

    DATA is a data set folder (sub-folders at any depth holding run.json) or
    one run folder. Every run is checked against the data contract (files,
    columns, numbers, strictly increasing t_s, pressures in MPa gauge); raw
    columns (encoder_counts, p_*_v, p_*_kpag, *_pulse) are converted with the
    rig's [calibration]; missing p_tank_mpag is 0 MPaG. Streams are put on the
    encoder's time base inside the span all streams cover (measurements
    interpolated linearly, commands held), and flow is derived.

    \b
    Writes (under --out, default outputs/<dataset-name>/ingest/):
      flow_step.parquet, position_control.parquet
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
      seanv-analyze ingest data/flow/supply-load0.35-cam-8.0-r2 --out /tmp/one
    """
    from ..config import load_rig

    rig = load_rig(rig_file)
    out = Path(out_dir) if out_dir else default_out_dir(data, "ingest")
    check_out_dir(data, out)
    progress = not quiet and not os.environ.get("CI")
    result = ingest(data, out_dir=out, rig=rig, progress=progress)
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
