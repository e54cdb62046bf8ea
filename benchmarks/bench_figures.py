"""Figures and ingest as a user feels them (issue 35): whole commands, cold
processes, interleaved pairs (A, B, A, B, ...; the first pair warms the page
cache and numba's cache and is not counted), the median of the per-pair
ratios, the 1-minute load average before and after each comparison.

- ``flowfit`` with its default figures (Fig. 4, PNG and SVG) against
  ``benchmarks/baselines/pandas_flowfit.py`` (a pandas/scipy user's script,
  no figure) on 240 and on 345 flow-step runs of ``paper-flowsteps``
  (target <= 1.0x);
- ``tracking`` and ``validate`` on ``paper-position`` (two 95 s runs) with
  their figures against ``--no-figures`` (target <= 1.5x);
- each comparison also records the CPU time of both commands with their
  worker processes and the ratio the first could reach at best on this
  machine's cores doing the work it does (``cpu_floor_ratio``);
- ``ingest`` (summary and manifest; no ``--samples``) of many flow-step runs
  (``paper-flowsteps`` copied with new run ids until there are
  ``INGEST_RUNS``) against ``flowfit --no-figures`` on the same runs
  (target <= 2.0x).

Quick mode (``SEANV_BENCH_QUICK=1``, or ``python -m benchmarks.bench_figures
--quick``): 2 counted pairs instead of ``PAIRS`` and 960 runs for ingest.
Results: ``benchmarks/results/figures.json``. Usage: ``python -m benchmarks figures``.
"""
from __future__ import annotations

import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "figures.json"
#: counted interleaved pairs per comparison (one more warms up)
PAIRS = 4
QUICK_PAIRS = 2
#: flow-step runs of the ingest comparison (the issue's data set size); quick mode
INGEST_RUNS = 3840
QUICK_INGEST_RUNS = 960
TARGETS = {"flowfit_vs_pandas": 1.0, "tracking_figures": 1.5, "validate_figures": 1.5,
           "ingest_vs_flowfit": 2.0}
CLI = [sys.executable, "-m", "seanv_analysis"]


def _wall(argv: list[str], cwd: Path) -> float:
    """Wall time [s] of one cold process (``CI=1``: no progress bars)."""
    return _timed(argv, cwd)[0]


def _timed(argv: list[str], cwd: Path) -> tuple[float, float]:
    """(wall, CPU) time [s] of one cold process (:func:`run_timed`)."""
    wall, cpu, _ = run_timed(argv, cwd=cwd)
    return wall, cpu


def run_timed(argv: list[str], *, cwd: Path | None = None, env: dict | None = None,
              check: bool = True) -> tuple[float, float, int]:
    """(wall [s], CPU [s], exit code) of one cold process and its children
    (its worker processes): CPU is user + system time, from the children's
    resource usage. ``env`` default: this one with ``CI=1`` (no progress
    bars); ``check``: a non-zero exit raises."""
    import resource

    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    rc = subprocess.run(argv, cwd=cwd, check=check, stdout=subprocess.DEVNULL,
                        stderr=subprocess.DEVNULL,
                        env=env if env is not None else {**os.environ, "CI": "1"}).returncode
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime), rc


def pairs(a: list[str], b: list[str], cwd: Path, n: int) -> dict:
    """``n`` interleaved (a, b) pairs after one uncounted pair: medians [s],
    per-pair ratios a/b and their median, the load before and after; and
    the CPU time [s] of each command with its workers (medians) and
    ``cpu_floor_ratio``: a's CPU spread over every core of the machine,
    over b's wall time, the least ratio a could reach without doing less
    work (a ratio target below it needs a to spend less CPU, not to
    overlap more)."""
    load0 = os.getloadavg()
    ta, tb, ca, cb = [], [], [], []
    for i in range(n + 1):
        (x, cx), (y, cy) = _timed(a, cwd), _timed(b, cwd)
        if i:
            ta.append(x)
            tb.append(y)
            ca.append(cx)
            cb.append(cy)
    ratios = [x / y for x, y in zip(ta, tb)]
    cores = os.cpu_count() or 1
    return {"pairs": n, "a_median_s": round(statistics.median(ta), 3),
            "b_median_s": round(statistics.median(tb), 3),
            "ratio_median": round(statistics.median(ratios), 3),
            "ratios": [round(r, 3) for r in ratios],
            "a_cpu_median_s": round(statistics.median(ca), 3),
            "b_cpu_median_s": round(statistics.median(cb), 3),
            "cpu_floor_ratio": round(statistics.median(ca) / cores / statistics.median(tb), 3),
            "load_before": [round(v, 2) for v in load0],
            "load_after": [round(v, 2) for v in os.getloadavg()]}


def subset(src: Path, dst: Path, n: int) -> Path:
    """The first ``n`` run folders of ``src`` (name order = time order) copied to ``dst``."""
    dst.mkdir(parents=True)
    for run in sorted(p for p in src.iterdir() if (p / "run.json").is_file())[:n]:
        shutil.copytree(run, dst / run.name)
    return dst


def replicate(src: Path, dst: Path, n: int) -> Path:
    """``n`` run folders from the runs of ``src`` copied over and over, each
    copy with its own run id (``-c<k>``) and started a day later per copy."""
    from datetime import datetime, timedelta

    runs = sorted(p for p in src.iterdir() if (p / "run.json").is_file())
    dst.mkdir(parents=True)
    for i in range(n):
        k, j = divmod(i, len(runs))
        run = runs[j]
        target = dst / f"c{k:02d}-{run.name}"
        shutil.copytree(run, target)
        doc = json.loads((run / "run.json").read_text())
        doc["run_id"] = f"{doc['run_id']}-c{k}"
        start = datetime.fromisoformat(doc["started_at"].replace("Z", "+00:00"))
        doc["started_at"] = (start + timedelta(days=k)).strftime("%Y-%m-%dT%H:%M:%SZ")
        (target / "run.json").write_text(json.dumps(doc, indent=2) + "\n")
    return dst


def _save(out: dict) -> None:
    """Write the results so far (a later comparison that fails loses none)."""
    RESULTS.parent.mkdir(exist_ok=True)
    RESULTS.write_text(json.dumps(out, indent=2) + "\n")


def main(quick: bool | None = None) -> dict:
    if quick is None:
        quick = bool(os.environ.get("SEANV_BENCH_QUICK"))
    n = QUICK_PAIRS if quick else PAIRS
    n_ingest = QUICK_INGEST_RUNS if quick else INGEST_RUNS
    out: dict = {"quick": quick, "cpus": os.cpu_count(), "targets": TARGETS}
    script = [sys.executable, str(HERE / "baselines" / "pandas_flowfit.py")]
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        _wall([*CLI, "simulate", "paper-flowsteps", "--out", str(tmp / "flow345"), "-q"], tmp)
        _wall([*CLI, "simulate", "paper-position", "--out", str(tmp / "pos"), "-q"], tmp)
        subset(tmp / "flow345", tmp / "flow240", 240)
        for runs in (240, 345):
            data = str(tmp / f"flow{runs}")
            out[f"flowfit_vs_pandas_{runs}"] = pairs(
                [*CLI, "flowfit", data, "--out", str(tmp / f"ff{runs}"), "-q"],
                [*script, data], tmp, n)
            _save(out)
        for cmd in ("tracking", "validate"):
            base = [*CLI, cmd, str(tmp / "pos"), "-q"]
            out[f"{cmd}_figures"] = pairs([*base, "--out", str(tmp / f"{cmd}-fig")],
                                          [*base, "--out", str(tmp / f"{cmd}-nofig"),
                                           "--no-figures"], tmp, n)
            _save(out)
        many = replicate(tmp / "flow345", tmp / "many", n_ingest)
        out["ingest_vs_flowfit"] = {"runs": n_ingest, **pairs(
            [*CLI, "ingest", str(many), "--out", str(tmp / "ing"), "-q"],
            [*CLI, "flowfit", str(many), "--out", str(tmp / "ffmany"), "-q", "--no-figures"],
            tmp, max(1, n - 1))}
    out["meets_targets"] = {
        "flowfit_vs_pandas_240_le_1.0": out["flowfit_vs_pandas_240"]["ratio_median"] <= 1.0,
        "flowfit_vs_pandas_345_le_1.0": out["flowfit_vs_pandas_345"]["ratio_median"] <= 1.0,
        "tracking_figures_le_1.5": out["tracking_figures"]["ratio_median"] <= 1.5,
        "validate_figures_le_1.5": out["validate_figures"]["ratio_median"] <= 1.5,
        "ingest_vs_flowfit_no_figures_le_2.0": out["ingest_vs_flowfit"]["ratio_median"] <= 2.0,
    }
    _save(out)
    return out


if __name__ == "__main__":
    print(json.dumps(main(quick=True if "--quick" in sys.argv[1:] else None), indent=2))
