"""Ingest speed and memory against a bare ``pyarrow.csv.read_csv``.

One hour of rig logs (encoder and pressure at 1 kHz, servo at 100 Hz) is
written twice into a temp folder: as 60 one-minute flow-step runs (the
usual shape of a flow-step data set) and as one 60-minute run (a long
position-control style log; worst case for per-run memory). For each:

- ``bare``: ``pyarrow.csv.read_csv`` of every CSV file (default options);
- ``ingest``: read + validate + calibrate + align (``signals.align.align_run``);
- ``ingest_hash``: the same plus the SHA-256 of every file (for the manifest);
- ``ingest_derive``: plus ``derive.derive_samples`` + ``derive.summarize_run``
  (when ``seanv_analysis.signals.derive`` exists; another engineer's stage);
- ``cli``: the whole ``ingest --samples`` command function (also writes the Parquet
  tables, the summary and the manifest).

Every mode runs in a fresh interpreter (cold allocator, warm page cache:
what a CLI run sees), ``REPEATS`` times interleaved; the time is the best
of them, measured inside the process after the imports; peak RSS is the
child's ``VmHWM`` (whole process, interpreter and libraries included),
compared with the raw CSV size. Ratios, so the machine's speed cancels out.

Targets: time <= 2.5 x bare, peak RSS < 4 x raw size (``meets_targets``
per mode).
Usage: ``python -m benchmarks.bench_ingest`` (or ``python -m benchmarks ingest``).
"""
from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "ingest.json"
REPEATS = 3
TIME_TARGET = 2.5
RSS_TARGET = 4.0


# data ------------------------------------------------------------------------

def _write_csv(path: Path, columns: dict[str, np.ndarray]) -> None:
    import pyarrow as pa
    import pyarrow.csv as pacsv

    pacsv.write_csv(pa.table(columns), path,
                    write_options=pacsv.WriteOptions(quoting_style="none"))


def write_hour(root: Path, *, n_runs: int, seed: int = 0) -> Path:
    """``n_runs`` flow-step runs totalling one hour at 1 kHz (CSV, contract
    layout, values at sensor resolution: 0.001 mm, 0.0001 MPa, 0.01 deg)."""
    rng = np.random.default_rng(seed)
    duration = 3600.0 / n_runs
    n_fast = int(round(duration * 1000)) + 1
    n_slow = int(round(duration * 100))
    for i in range(n_runs):
        run = root / f"run{i:03d}"
        run.mkdir(parents=True)
        side = "supply" if i % 2 == 0 else "drain"
        cam = -8.0 if side == "supply" else -30.0
        t = np.arange(n_fast) / 1000.0
        v = 10.0 if side == "supply" else -10.0
        x = np.round(10.0 + np.clip(v * (t % 6.0 - 1.0), -5, 50) + 40 * (side == "drain"), 3)
        _write_csv(run / "encoder.csv", {"t_s": t, "position_mm": x})
        _write_csv(run / "pressure.csv", {
            "t_s": t + 0.0003,
            "p_supply_mpag": np.round(3.3 + rng.normal(0, 0.005, n_fast), 4),
            "p_head_mpag": np.round(1.6 + rng.normal(0, 0.005, n_fast), 4),
            "p_load_mpag": np.round(0.35 + rng.normal(0, 0.002, n_fast), 4),
        })
        ts = 0.002 + np.arange(n_slow) / 100.0
        _write_csv(run / "servo.csv", {
            "t_s": ts, "cam_cmd_deg": np.where(ts % 6.0 < 1.0, -15.0, cam),
            "cam_deg": np.round(np.where(ts % 6.0 < 1.0, -15.0, cam) + rng.normal(0, 0.02, n_slow), 2),
        })
        meta = {"schema": "seanv-run/1", "run_id": f"run{i:03d}", "kind": "flow_step",
                "started_at": f"2026-03-02T{10 + i // 60:02d}:{i % 60:02d}:00Z",
                "load_mpag": 0.35, "side": side, "cam_deg": cam}
        (run / "run.json").write_text(json.dumps(meta))
    return root


def _csv_files(root: Path) -> list[Path]:
    return sorted(root.rglob("*.csv"))


# modes -------------------------------------------------------------------------

def bare(root: Path) -> int:
    import pyarrow.csv as pacsv

    rows = 0
    for f in _csv_files(root):
        rows += pacsv.read_csv(f).num_rows
    return rows


def _derive():
    import importlib

    try:
        return importlib.import_module("seanv_analysis.signals.derive")
    except ModuleNotFoundError as exc:
        if exc.name != "seanv_analysis.signals.derive":
            raise
        return None


def ingest(root: Path, *, hash_files: bool = False, derive: bool = False) -> int:
    """Read + validate + calibrate + align every run (+ hash, + derive)."""
    from seanv_analysis.io.reader import RunError, iter_dataset
    from seanv_analysis.signals.align import align_run

    mod = _derive() if derive else None
    if derive and mod is None:
        return -1
    rows = 0
    for item in iter_dataset(root, hash_files=hash_files):
        if isinstance(item, RunError):
            raise RuntimeError(item.message)
        if mod is not None:
            samples = mod.derive_samples(item)
            mod.summarize_run(item, derived=samples)
        else:
            samples = align_run(item)
        rows += len(samples)
    return rows


def cli(root: Path, out: Path) -> int:
    from seanv_analysis.cli.ingest_cmd import ingest as ingest_command
    from seanv_analysis.config import load_rig

    result = ingest_command(root, out_dir=out, rig=load_rig(), samples=True)
    return sum(result["rows"].values())


_MODES = ("none", "bare", "ingest", "ingest_hash", "ingest_derive", "cli")


def _child(mode: str, root: str, out: str) -> None:
    """Run one mode in this (fresh) process; print elapsed time and peak RSS.
    Every mode (bare included) gets the CLI's process set-up
    (:func:`seanv_analysis.batch.process_setup.return_large_blocks_to_os`)."""
    from seanv_analysis.batch.process_setup import return_large_blocks_to_os

    return_large_blocks_to_os()
    import seanv_analysis.cli.ingest_cmd  # noqa: F401  (imports not timed)
    import seanv_analysis.io  # noqa: F401
    _derive()  # scipy.signal etc.: imports not timed
    import pyarrow.csv  # noqa: F401

    root_p = Path(root)
    t0 = time.perf_counter()
    if mode == "bare":
        bare(root_p)
    elif mode == "ingest":
        ingest(root_p)
    elif mode == "ingest_hash":
        ingest(root_p, hash_files=True)
    elif mode == "ingest_derive":
        ingest(root_p, derive=True)   # content hashing is timed separately (ingest_hash)
    elif mode == "cli":
        cli(root_p, Path(out))
    elapsed = time.perf_counter() - t0
    print(json.dumps({"time_s": elapsed, "peak_rss_mb": _vm_hwm_mb()}))


def _vm_hwm_mb() -> float:
    """Peak resident set of this process [MB] (VmHWM; reset by exec, unlike
    ru_maxrss, which a child inherits from the parent it was forked from)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _run_child(mode: str, root: Path, out: Path) -> dict:
    code = (f"import sys; sys.path.insert(0, {str(HERE.parent)!r}); "
            "import benchmarks.bench_ingest as b; b._child(*sys.argv[1:4])")
    env = {k: v for k, v in os.environ.items() if k != "CI"}
    proc = subprocess.run([sys.executable, "-c", code, mode, str(root), str(out)],
                          capture_output=True, text=True, check=True, env=env)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def measure(root: Path, label: str, tmp: Path) -> dict:
    """Each mode in a fresh interpreter (cold allocator, warm page cache, as
    a CLI run), ``REPEATS`` times interleaved; best time, peak RSS."""
    raw_mb = sum(f.stat().st_size for f in _csv_files(root)) / 2**20
    bare(root)  # warm the page cache
    runs: dict[str, list[dict]] = {m: [] for m in _MODES}
    for r in range(REPEATS):
        for mode in _MODES:
            runs[mode].append(_run_child(mode, root, tmp / f"out-{label}-{r}"))
    t = {m: min(x["time_s"] for x in runs[m]) for m in _MODES}
    rss = {m: max(x["peak_rss_mb"] for x in runs[m]) for m in _MODES}
    out = {
        "raw_csv_mb": round(raw_mb, 1),
        "time_s": {m: round(t[m], 3) for m in _MODES if m != "none"},
        "peak_rss_mb": {m: round(v, 1) for m, v in rss.items()},
    }
    for m in _MODES[2:]:
        out[f"time_ratio_{m}_vs_bare"] = round(t[m] / t["bare"], 2)
    for m in _MODES[1:]:
        out[f"rss_ratio_{m}_vs_raw"] = round(rss[m] / raw_mb, 2)
    out["rss_ratio_ingest_net_of_interpreter_vs_raw"] = round((rss["ingest"] - rss["none"]) / raw_mb, 2)
    return out


def main() -> dict:
    """Run both layouts, print and write ``benchmarks/results/ingest.json``."""
    with tempfile.TemporaryDirectory(prefix="bench-ingest-") as tmp:
        tmp = Path(tmp)
        layouts = {"60x1min": 60, "1x60min": 1}
        results = {"derive_included": _derive() is not None, "repeats": REPEATS,
                   "cpu_count": os.cpu_count(), "targets": {"time_ratio_max": TIME_TARGET,
                                                            "rss_ratio_max": RSS_TARGET}}
        for label, n in layouts.items():
            t0 = time.perf_counter()
            root = write_hour(tmp / label / "data", n_runs=n)
            gen = time.perf_counter() - t0
            results[label] = measure(root, label, tmp)
            results[label]["rows_aligned"] = ingest(root)
            results[label]["generate_s"] = round(gen, 1)
            r = results[label]
            r["meets_targets"] = {
                m: bool(r[f"time_ratio_{m}_vs_bare"] <= TIME_TARGET
                        and r[f"rss_ratio_{m}_vs_raw"] < RSS_TARGET)
                for m in ("ingest", "ingest_hash", "ingest_derive")}
    RESULTS.parent.mkdir(exist_ok=True)
    RESULTS.write_text(json.dumps(results, indent=2) + "\n")
    return results


if __name__ == "__main__":
    print(json.dumps(main(), indent=2))
