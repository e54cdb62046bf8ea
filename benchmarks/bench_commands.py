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
  re-run, which recomputes nothing (target < 5 s).

Results: ``benchmarks/results/commands.json``. Usage: ``python -m benchmarks commands``.
"""
from __future__ import annotations

import json
import os
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
        out["load_1min_after"] = round(os.getloadavg()[0], 2)
    out["targets"] = {
        "import_lt_0.5_s": out["import"]["median_s"] < 0.5,
        "help_lt_0.3_s": out["help"]["median_s"] < 0.3,
        "simulate_rtf_ge_300": out["simulate_paper_position"]["real_time_factor"] >= 300,
        "run_cached_lt_5_s": out["run_paper_cached"]["median_s"] < 5.0,
    }
    (HERE / "results").mkdir(exist_ok=True)
    (HERE / "results" / "commands.json").write_text(json.dumps(out, indent=2) + "\n")
    return out


if __name__ == "__main__":
    print(json.dumps(main(), indent=2))
