"""``run paper`` as a user feels it (issue 35): whole cold commands, wall time.

Data: the first 240 runs of ``paper-flowsteps`` and the two runs of
``paper-position`` (the issue's "240 flow steps + 2 position runs"), and
``paper-flowsteps`` copied with new run ids to ``MANY_RUNS`` flow steps.

- ``paper_workers``: ``run paper DATA --force`` into a fresh folder with
  ``--workers 1`` and ``--workers 2``, interleaved pairs (the order
  alternates), the median of the per-pair ratios 1/2 (target >= 1.4) and
  the median wall time with 2 workers (target <= 12 s), each stage's time
  from ``result.json``;
- ``many_workers``: the same for ``run flowfit`` on ``MANY_RUNS`` runs
  (target >= 1.4);
- ``dask_vs_local``: ``run paper`` on a local Dask cluster (``dask
  scheduler`` and ``dask worker --nworkers 2 --nthreads 1``, started once)
  against ``--workers 2`` (target <= 1.2);
- ``rerun_after_edit``: ``run paper`` into a fresh folder, then one value of
  one flow-step run's ``pressure.csv`` changed (a new copy of the data set
  each pair), then ``run paper`` again into the same folder (no
  ``--force``): second / first (target <= 0.40), with the stage times of
  the re-run. The sample changed lies before the step's steady window: the
  per-run summary is unchanged, and the data-set stages are reused
  (:mod:`seanv_analysis.batch.stage_memo`);
- ``rerun_after_summary_edit``: the same with that run's whole supply
  pressure log 20 kPa higher, which changes its summary: what depends on the
  flow steps (flow fit, identify, discover, Fig. 4) runs again (reported,
  no target).

Each command's CPU time (user + system, its worker processes included) is
recorded beside its wall time, with the wall time it allows at best on the
machine's cores (``*_cpu_bound_s``: CPU / cores): a wall-time target below
that bound needs less work, not more parallelism.

Every comparison records the 1-minute load average before and after it;
the first pair of each warms the page cache and is not counted.
Quick mode (``SEANV_BENCH_QUICK=1`` or ``--quick``): 1 counted pair each.
Results: ``benchmarks/results/run.json``. Usage: ``python -m benchmarks run``.
"""
from __future__ import annotations

import json
import os
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from .bench_figures import CLI, replicate, run_timed, subset

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "run.json"
PAIRS = 3
QUICK_PAIRS = 1
PAPER_FLOW_RUNS = 240
MANY_RUNS = 960
TARGETS = {"paper_2_workers_s": 12.0, "speedup_2_vs_1": 1.4, "dask_vs_local": 1.2,
           "rerun_after_edit": 0.40}
ENV = {**os.environ, "CI": "1", "MPLBACKEND": "Agg"}


def _run(argv: list[str], out: Path, *, fresh: bool = True) -> dict:
    """One cold command writing into ``out``: wall [s], CPU [s] (user + system
    of the command and the worker processes it waited for; not a Dask
    cluster's), exit code, stage times."""
    if fresh and out.exists():
        shutil.rmtree(out)
    wall, cpu, rc = run_timed([*argv, "--out", str(out), "-q"], env=ENV, check=False)
    try:
        stages = json.loads((out / "result.json").read_text())["timings_s"]
    except (OSError, ValueError, KeyError):
        stages = {}
    return {"wall_s": round(wall, 3), "cpu_s": round(cpu, 2), "exit_code": rc,
            "stages_s": {k: round(v, 2) for k, v in stages.items()}}


def _load() -> list[float]:
    return [round(v, 2) for v in os.getloadavg()]


def compare(a: list[str], b: list[str], out: Path, n: int) -> dict:
    """``n`` counted pairs (a, b) after one warm-up pair, the order
    alternating: medians, per-pair ratios a/b and their median."""
    load0 = _load()
    ra, rb = [], []
    for i in range(n + 1):
        if i % 2:
            y, x = _run(b, out / "b"), _run(a, out / "a")
        else:
            x, y = _run(a, out / "a"), _run(b, out / "b")
        if i:
            ra.append(x)
            rb.append(y)
    return _paired(ra, rb, load0)


def _paired(ra: list[dict], rb: list[dict], load0: list[float], names=("a", "b")) -> dict:
    """Medians of the runs ``ra`` and ``rb`` (counted pairs, in order): wall
    and CPU time, and the wall time the CPU time allows at best on this
    machine's cores (CPU / cores: a command that keeps every core busy the
    whole time); the per-pair ratios a/b and their median, the exit codes,
    the last pair's stage times, the load before (``load0``) and now."""
    a, b = names
    ratios = [x["wall_s"] / y["wall_s"] for x, y in zip(ra, rb)]
    cores = os.cpu_count() or 1
    cpu = {n: statistics.median(r["cpu_s"] for r in rs) for n, rs in ((a, ra), (b, rb))}
    return {"pairs": len(ratios), f"{a}_median_s": round(statistics.median(r["wall_s"] for r in ra), 3),
            f"{b}_median_s": round(statistics.median(r["wall_s"] for r in rb), 3),
            f"{a}_cpu_median_s": round(cpu[a], 2), f"{b}_cpu_median_s": round(cpu[b], 2),
            f"{a}_cpu_bound_s": round(cpu[a] / cores, 2), f"{b}_cpu_bound_s": round(cpu[b] / cores, 2),
            "ratio_median": round(statistics.median(ratios), 3),
            "ratios": [round(r, 3) for r in ratios],
            "exit_codes": sorted({r["exit_code"] for r in ra + rb}),
            f"{a}_stages_s": ra[-1]["stages_s"], f"{b}_stages_s": rb[-1]["stages_s"],
            "load_before": load0, "load_after": _load()}


def edit_one_flow_step(data: Path, *, whole_log: bool = False) -> Path:
    """Change the first flow-step run's supply pressure in place: +1 kPa at
    its sixth row (before the steady window), or +20 kPa over the whole log
    (``whole_log``: its summary changes); the file changed."""
    import pandas as pd

    run = sorted(p.parent for p in (data / "flow").rglob("run.json"))[0]
    path = run / "pressure.csv"
    df = pd.read_csv(path)
    if whole_log:
        df["p_supply_mpag"] += 0.02
    else:
        df.loc[5, "p_supply_mpag"] += 0.001
    df.to_csv(path, index=False)
    return path


def rerun_after_edit(data: Path, tmp: Path, n: int, *, whole_log: bool = False) -> dict:
    """First ``run paper`` into a fresh folder, one flow-step file edited
    (:func:`edit_one_flow_step`), ``run paper`` again into it: per-pair
    ratios second / first."""
    load0 = _load()
    firsts, seconds = [], []
    for i in range(n + 1):
        copy = tmp / f"edit{i}"
        shutil.copytree(data, copy)
        out = tmp / f"edit{i}-out"
        first = _run([*CLI, "run", "paper", str(copy)], out)
        edit_one_flow_step(copy, whole_log=whole_log)
        second = _run([*CLI, "run", "paper", str(copy)], out, fresh=False)
        shutil.rmtree(copy)
        shutil.rmtree(out)
        if i:
            firsts.append(first)
            seconds.append(second)
    return _paired(seconds, firsts, load0, names=("rerun", "first"))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def dask_vs_local(data: Path, tmp: Path, n: int) -> dict:
    """``run paper`` on a local Dask cluster of 2 single-thread worker
    processes against ``--workers 2``."""
    dask = shutil.which("dask", path=str(Path(sys.executable).parent)) or shutil.which("dask")
    if dask is None:
        return {"skipped": "no 'dask' command (pip install dask[distributed])"}
    address = f"tcp://127.0.0.1:{_free_port()}"
    logs = open(tmp / "dask.log", "w")
    procs = [subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port",
                               address.rsplit(":", 1)[1], "--no-dashboard"],
                              stdout=logs, stderr=subprocess.STDOUT, env=ENV)]
    try:
        time.sleep(3.0)
        procs.append(subprocess.Popen([dask, "worker", address, "--nworkers", "2", "--nthreads",
                                       "1", "--no-dashboard"], stdout=logs,
                                      stderr=subprocess.STDOUT, env=ENV))
        time.sleep(8.0)
        return compare([*CLI, "run", "paper", str(data), "--force", "--scheduler", address],
                       [*CLI, "run", "paper", str(data), "--force", "--workers", "2"],
                       tmp / "dask", n)
    finally:
        for p in reversed(procs):
            p.terminate()
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
        logs.close()


def _save(out: dict) -> None:
    RESULTS.parent.mkdir(exist_ok=True)
    RESULTS.write_text(json.dumps(out, indent=2) + "\n")


def main(quick: bool | None = None) -> dict:
    if quick is None:
        quick = bool(os.environ.get("SEANV_BENCH_QUICK"))
    n = QUICK_PAIRS if quick else PAIRS
    out: dict = {"quick": quick, "cpus": os.cpu_count(), "targets": TARGETS}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        sim = [*CLI, "simulate"]
        subprocess.run([*sim, "paper-flowsteps", "--out", str(tmp / "flow345"), "-q"], check=True,
                       env=ENV, stdout=subprocess.DEVNULL)
        data = tmp / "paper240"
        subset(tmp / "flow345", data / "flow", PAPER_FLOW_RUNS)
        subprocess.run([*sim, "paper-position", "--out", str(data / "position"), "-q"],
                       check=True, env=ENV, stdout=subprocess.DEVNULL)
        out["paper_workers"] = compare([*CLI, "run", "paper", str(data), "--force", "--workers", "1"],
                                       [*CLI, "run", "paper", str(data), "--force", "--workers", "2"],
                                       tmp / "pw", n)
        _save(out)
        out["rerun_after_edit"] = rerun_after_edit(data, tmp, n)
        _save(out)
        out["rerun_after_summary_edit"] = rerun_after_edit(data, tmp, n, whole_log=True)
        _save(out)
        out["dask_vs_local"] = dask_vs_local(data, tmp, n)
        _save(out)
        many = replicate(tmp / "flow345", tmp / "many", MANY_RUNS)
        out["many_workers"] = {"runs": MANY_RUNS, **compare(
            [*CLI, "run", "flowfit", str(many), "--force", "--workers", "1"],
            [*CLI, "run", "flowfit", str(many), "--force", "--workers", "2"], tmp / "mw", n)}
    pw, dk = out["paper_workers"], out["dask_vs_local"]
    out["meets_targets"] = {
        "paper_2_workers_le_12_s": pw["b_median_s"] <= TARGETS["paper_2_workers_s"],
        "paper_2_vs_1_ge_1.4": pw["ratio_median"] >= TARGETS["speedup_2_vs_1"],
        "many_2_vs_1_ge_1.4": out["many_workers"]["ratio_median"] >= TARGETS["speedup_2_vs_1"],
        "dask_vs_local_le_1.2": (dk.get("ratio_median", float("inf"))
                                 <= TARGETS["dask_vs_local"]),
        "rerun_after_edit_le_0.40": (out["rerun_after_edit"]["ratio_median"]
                                     <= TARGETS["rerun_after_edit"]),
    }
    _save(out)
    return out


if __name__ == "__main__":
    print(json.dumps(main(quick=True if "--quick" in sys.argv[1:] else None), indent=2))
