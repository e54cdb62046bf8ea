"""Whole commands as a user runs them: cold processes, wall time.

Each case is a fresh ``python`` process (imports, numba's on-disk cache,
files written), timed ``REPEATS`` times, interleaved with a bare
``python -c pass`` so the machine's load shows in both; medians and the
1-minute load average before and after are recorded.

- ``import seanv_analysis`` (target < 0.5 s) and ``seanv-analyze --help``
  (target < 0.3 s);
- ``simulate paper-position`` (two 95 s runs, four CSV tables each): real-time
  factor = 190 s simulated / wall s (target >= 300);
- ``run paper`` on the small built-in sets (144 flow steps + the two
  position-control runs): the first run (computes) once, then the cached
  re-run, which recomputes nothing (target < 5 s);
- ``flowfit`` on the 345-run ``paper-flowsteps`` set against
  ``benchmarks/baselines/pandas_flowfit.py`` (a pandas/scipy user's script:
  read_csv, Savitzky-Golay, a steady value per run, ``curve_fit``; no
  intervals, lack-of-fit check, figure or files): both as cold processes,
  interleaved pairs (command, script, command, script, ...), the median of
  each and the median of the per-pair ratios (target <= 1.0), with both
  fits' z0 and C next to the simulator's truth.

Results: ``benchmarks/results/commands.json``. Usage: ``python -m benchmarks commands``.
"""
from __future__ import annotations

import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPEATS = 5
HERE = Path(__file__).resolve().parent
#: simulated seconds of ``simulate paper-position`` (two runs of 95 s)
PAPER_POSITION_S = 2 * 95.0
#: interleaved (command, script) pairs of the flowfit comparison
FLOWFIT_PAIRS = 5
#: the simulator's valve (the shipped rig = the paper's fit); paper-flowsteps
#: adds a drain drift, so the drain C a fit finds is an average over it
FLOWFIT_TRUTH = {"supply": {"z0_mm": -0.155, "C": 17.435},
                 "drain": {"z0_mm": -0.026, "C": -22.636, "note": "drifts over the runs"}}


def _wall(argv: list[str], cwd: Path) -> float:
    t0 = time.perf_counter()
    subprocess.run(argv, cwd=cwd, check=True, stdout=subprocess.DEVNULL,
                   stderr=subprocess.DEVNULL, env={**os.environ, "CI": "1"})
    return time.perf_counter() - t0


def _median(argv, cwd: Path, repeats: int = REPEATS) -> dict:
    """Median wall time of ``argv`` (or ``argv(i)`` for repeat i) with a bare
    interpreter start interleaved."""
    base, ours = [], []
    for i in range(repeats):
        base.append(_wall([sys.executable, "-c", "pass"], cwd))
        ours.append(_wall(argv(i) if callable(argv) else argv, cwd))
    return {"median_s": round(statistics.median(ours), 3),
            "python_start_median_s": round(statistics.median(base), 3)}


def _script_fit(stdout: str) -> dict:
    """{side: {z0_mm, C}} from the baseline script's printed lines."""
    out = {}
    for side, z0, c in re.findall(r"(supply|drain): z0 = (\S+) mm, C = (\S+) ", stdout):
        out[side] = {"z0_mm": float(z0), "C": float(c)}
    return out


def flowfit_vs_pandas(tmp: Path, data: Path | None = None, pairs: int = FLOWFIT_PAIRS) -> dict:
    """Whole ``seanv-analyze flowfit DATA --out X -q`` vs the pandas user's
    script on the same data (345 runs of ``paper-flowsteps`` unless ``data``),
    cold processes, interleaved; load average before and after."""
    cli = [sys.executable, "-m", "seanv_analysis"]
    if data is None:
        data = tmp / "flow345"
        _wall([*cli, "simulate", "paper-flowsteps", "--out", str(data), "-q"], tmp)
    script = [sys.executable, str(HERE / "baselines" / "pandas_flowfit.py"), str(data)]
    load0 = os.getloadavg()
    ours, base = [], []
    for i in range(pairs + 1):   # pair 0 warms the page cache and numba's cache
        a = _wall([*cli, "flowfit", str(data), "--out", str(tmp / "ff"), "-q"], tmp)
        b = _wall(script, tmp)
        if i:
            ours.append(a)
            base.append(b)
    load1 = os.getloadavg()
    ratios = [a / b for a, b in zip(ours, base)]
    doc = json.loads((tmp / "ff" / "flowfit.json").read_text())
    printed = subprocess.run(script, cwd=tmp, check=True, capture_output=True, text=True).stdout
    return {
        "runs": sum(1 for _ in Path(data).rglob("run.json")),
        "pairs": pairs,
        "flowfit_median_s": round(statistics.median(ours), 3),
        "pandas_script_median_s": round(statistics.median(base), 3),
        "ratio_median": round(statistics.median(ratios), 3),
        "ratios": [round(r, 3) for r in ratios],
        "load_before": [round(x, 2) for x in load0],
        "load_after": [round(x, 2) for x in load1],
        "fits": {"truth": FLOWFIT_TRUTH,
                 "flowfit": {side: {"z0_mm": doc[side]["z0_mm"],
                                    "C": doc[side]["C_mm3_s_deg2_sqrtMPa"]}
                             for side in ("supply", "drain") if side in doc},
                 "pandas_script": _script_fit(printed)},
    }


def main() -> dict:
    cli = [sys.executable, "-m", "seanv_analysis"]
    load0 = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        out: dict = {"load_1min_before": round(load0, 2)}
        out["import"] = _median([sys.executable, "-c", "import seanv_analysis"], tmp)
        out["help"] = _median([*cli, "--help"], tmp)
        # numba's on-disk cache filled once, as after a user's first command
        _wall([*cli, "simulate", "paper-position", "--out", str(tmp / "warm")], tmp)
        sim = _median(lambda i: [*cli, "simulate", "paper-position", "--out",
                                 str(tmp / f"pos{i}"), "-q"], tmp, repeats=3)
        sim["real_time_factor"] = round(PAPER_POSITION_S / sim["median_s"], 1)
        out["simulate_paper_position"] = sim
        (tmp / "data").mkdir()
        (tmp / "pos0").rename(tmp / "data" / "pos")
        _wall([*cli, "simulate", "paper-flowsteps-small", "--out", str(tmp / "data" / "flow"), "-q"], tmp)
        run = [*cli, "run", "paper", str(tmp / "data"), "--out", str(tmp / "run"), "-q"]
        out["run_paper_first_s"] = round(_wall(run, tmp), 2)
        out["run_paper_cached"] = _median(run, tmp, repeats=3)
        out["flowfit_vs_pandas"] = flowfit_vs_pandas(tmp)
        out["load_1min_after"] = round(os.getloadavg()[0], 2)
    out["targets"] = {
        "import_lt_0.5_s": out["import"]["median_s"] < 0.5,
        "help_lt_0.3_s": out["help"]["median_s"] < 0.3,
        "simulate_rtf_ge_300": out["simulate_paper_position"]["real_time_factor"] >= 300,
        "run_cached_lt_5_s": out["run_paper_cached"]["median_s"] < 5.0,
        "flowfit_vs_pandas_le_1.0": out["flowfit_vs_pandas"]["ratio_median"] <= 1.0,
    }
    (HERE / "results").mkdir(exist_ok=True)
    (HERE / "results" / "commands.json").write_text(json.dumps(out, indent=2) + "\n")
    return out


if __name__ == "__main__":
    # ``python -m benchmarks.bench_commands flowfit [DATA]``: only the flowfit comparison
    if sys.argv[1:2] == ["flowfit"]:
        with tempfile.TemporaryDirectory() as t:
            given = Path(sys.argv[2]).resolve() if len(sys.argv) > 2 else None
            print(json.dumps(flowfit_vs_pandas(Path(t), given), indent=2))
    else:
        print(json.dumps(main(), indent=2))
