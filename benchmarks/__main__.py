"""Run every benchmark module (``bench_*.py``) and collect their results.

Each module has a ``main() -> dict`` that measures ratios in one run (so the
machine's speed cancels out) and writes ``benchmarks/results/<name>.json``.
Usage: ``python -m benchmarks [NAME ...]`` (default: all).
"""
from __future__ import annotations

import importlib
import json
import pkgutil
import sys
import time
import traceback
from pathlib import Path

HERE = Path(__file__).resolve().parent


def main(argv: list[str]) -> int:
    names = sorted(m.name for m in pkgutil.iter_modules([str(HERE)]) if m.name.startswith("bench_"))
    if argv:
        names = [n for n in names if n.removeprefix("bench_") in argv or n in argv]
    results, failed = {}, []
    for name in names:
        t0 = time.perf_counter()
        print(f"== {name}", flush=True)
        try:
            results[name] = importlib.import_module(f"benchmarks.{name}").main()
        except Exception:  # a failing benchmark must not hide the others
            traceback.print_exc()
            failed.append(name)
            continue
        print(json.dumps(results[name], indent=2, default=str))
        print(f"   ({time.perf_counter() - t0:.1f} s)", flush=True)
    out = HERE / "results"
    out.mkdir(exist_ok=True)
    (out / "summary.json").write_text(json.dumps(results, indent=2, default=str) + "\n")
    if failed:
        print("failed: " + ", ".join(failed), file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
