"""Rewrite README.md's headline numbers and demo time from the demo's outputs.

    make demo && .venv/bin/python scripts/update_readme_numbers.py [RESULT_JSON]

Writes the block between README's ``<!-- headline:start`` and
``<!-- headline:end -->`` markers with :func:`seanv_analysis.demo.headline`
of the result (default ``outputs/demo/run-paper/result.json``), the
sentence between ``<!-- demo-time:start -->`` and ``<!-- demo-time:end -->``
with :func:`seanv_analysis.demo.timing_text` of the times ``make demo``
measured itself (``outputs/demo/timings.json``: run it on a fresh clone and
once more to have both), and records the numbers it used in
``docs/demo_headline.json``; tests/test_readme.py holds the README to that
record. Run from the repository root.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

from seanv_analysis.demo import (
    README_END,
    README_START,
    README_TIME_END,
    README_TIME_START,
    RECORDED_HEADLINE,
    TIMINGS,
    headline,
    headline_inputs,
    timing_text,
)
from seanv_analysis.io.atomic import write_text_atomic

TITLE = "headline numbers (the drain C above is the average over a drifting valve):"


def main(argv: list[str]) -> int:
    source = Path(argv[0]) if argv else Path("outputs/demo/run-paper/result.json")
    if not source.is_file():
        print(f"error: {source}: not found; run `make demo` first", file=sys.stderr)
        return 2
    record = headline_inputs(json.loads(source.read_text()))
    timings = source.parent.parent / TIMINGS
    if timings.is_file():
        record["timings"] = json.loads(timings.read_text())
    readme = Path("README.md")
    text = readme.read_text()
    start = text.index(README_START)
    start = text.index("\n", start) + 1
    end = text.index(README_END)
    block = f"```text\n{TITLE}\n{headline(record)}\n```\n"
    text = text[:start] + block + text[end:]
    if record.get("timings"):
        start = text.index(README_TIME_START) + len(README_TIME_START)
        text = text[:start] + timing_text(record["timings"]) + text[text.index(README_TIME_END):]
    write_text_atomic(readme, text)
    write_text_atomic(RECORDED_HEADLINE, json.dumps(record, indent=1) + "\n")
    print(f"README.md and {RECORDED_HEADLINE} updated from {source}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
