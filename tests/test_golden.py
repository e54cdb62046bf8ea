"""Golden numbers: the paper pipeline on a fixed small simulated data set.

Every stage's JSON numbers (flow fit, tracking, validation, discovery with
its closed-loop check, exclusions, bad runs, the files written) must stay what
they were when ``tests/golden/paper_pipeline.json`` was recorded. A change of
behaviour shows here; a change of layout must not.

The data (conftest ``golden_data``): 24 flow steps on both sides at two
loads with the paper's drain-side drift (step 5 % every 3 runs, strong enough
for 24 runs), plus the position-control test with and without the flow
model, simulated with the built-in plant (seed 5). The serial run
(``golden_run``) is also what test_batch holds the other executors to. Re-record after an intended change of numbers with::

    SEANV_UPDATE_GOLDEN=1 .venv/bin/python -m pytest tests/test_golden.py
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path

GOLDEN = Path(__file__).parent / "golden" / "paper_pipeline.json"
#: keys of result.json that depend on the machine or the clock, not the numbers
VOLATILE = ("timings_s", "computed", "cached", "executor", "version")


def _portable(obj, replace: dict[str, str]):
    """The document with temporary paths replaced by placeholders."""
    if isinstance(obj, dict):
        return {k: _portable(v, replace) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_portable(v, replace) for v in obj]
    if isinstance(obj, str):
        for old, new in replace.items():
            obj = obj.replace(old, new)
        return obj
    return obj


#: relative tolerance of floats by path prefix (first match wins). The last
#: bits differ between CPUs and numpy/scipy releases (a fresh venv takes the
#: newest): plain fits move ~1e-8. Identification's closed-loop searches
#: (golden section on the line's bulk modulus, stopped at ~1e-4 in log) turn
#: such bits into ~1e-4 (seen: 7e-5 between two scipy/numpy releases).
REL_TOL = (("/identify/", 1e-3), ("/validation/", 1e-3), ("", 1e-6))


def _rel_tol(where: str) -> float:
    return next(tol for prefix, tol in REL_TOL if where.startswith(prefix))


def _compare(got, want, where: str = "") -> list[str]:
    """Differences between two JSON documents; floats equal to :data:`REL_TOL`
    (the last bits may differ between CPUs, the numbers must not)."""
    if isinstance(want, dict) and isinstance(got, dict):
        out = [f"{where}/{k}: missing" for k in want if k not in got]
        out += [f"{where}/{k}: unexpected" for k in got if k not in want]
        for k in want:
            if k in got:
                out += _compare(got[k], want[k], f"{where}/{k}")
        return out
    if isinstance(want, list) and isinstance(got, list):
        if len(want) != len(got):
            return [f"{where}: {len(got)} items, golden {len(want)}"]
        return [d for i, (g, w) in enumerate(zip(got, want)) for d in _compare(g, w, f"{where}[{i}]")]
    if isinstance(want, float) and isinstance(got, (int, float)) and not isinstance(got, bool):
        if math.isnan(want) and math.isnan(got):
            return []
        if math.isclose(got, want, rel_tol=_rel_tol(where), abs_tol=1e-12):
            return []
    elif got == want and type(got) is type(want):
        return []
    return [f"{where}: {got!r}, golden {want!r}"]


def test_paper_pipeline_numbers_unchanged(golden_data, golden_run):
    doc, out = golden_run
    doc = dict(doc)
    for key in VOLATILE:
        doc.pop(key, None)
    doc["outputs"] = sorted(doc["outputs"])
    doc = _portable(doc, {str(out): "<out>", str(golden_data): "<data>"})
    if os.environ.get("SEANV_UPDATE_GOLDEN"):
        GOLDEN.parent.mkdir(exist_ok=True)
        GOLDEN.write_text(json.dumps(doc, indent=1, sort_keys=True) + "\n")
    want = json.loads(GOLDEN.read_text())
    diffs = _compare(doc, want)
    assert not diffs, "\n".join([d for d in diffs if not d.endswith(("missing", "unexpected"))][:40] or diffs[:40])
    # the recorded run exercised every stage
    assert want["stage_errors"] == {}
    assert want["flowfit"] and want["tracking"] and want["validation"]
    assert want["discovery"]["verdict"] == "effect_found"


def test_line_structure_kept_on_our_own_plant(golden_run):
    """On our simulator's runs (its tube an R-I-C ladder, inertance factor 1)
    identify keeps the rig file's line: every more lumped line fits the
    replayed training run worse (its SSE grows as the inertance shrinks)."""
    doc, _ = golden_run
    c = next(c for c in doc["identify"]["constants"] if c["key"] == "tube.inertance_factor")
    assert c["value"] == 1.0 and c["default"] == 1.0
    assert "kept" in c["note"]
