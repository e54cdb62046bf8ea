"""The field data (../shared/field-data): logs of a rig nobody here wrote.

Every analysis command a user runs on them, end to end as a user runs it
(``seanv-analyze discover``, ``discover --identify``, ``identify`` and ``run
paper`` on each of the three sets, in fresh processes), and what they say
against the sets' truth (``_truth/<set>.json``):

- no traceback, no internal error (exit code 0 or 1: 1 only for bad runs);
- the effects ``discover`` names vs the undeclared ones (a confusion matrix:
  effect injected x effect named) and the held-out error drop of each;
- ``identify``'s constants vs the truth: which 95 % intervals hold it (the
  coverage of each constant; a Stribeck friction law is reported against
  its effective Coulomb force at the runs' speeds, a documented reading);
- ``validate`` on field-slow-servo: the limit cycle's amplitude and period.

Writes ``benchmarks/results/bench_field.json``. Takes ~15 min on 2 cores.
"""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent

#: truth key of each identified constant the truth gives (identify's rig key)
TRUTH_KEYS = {
    "servo.dead_time_s": ("plant", "servo_dead_time_s"),
    "servo.time_constant_s": ("plant", "servo_time_constant_s"),
    "tube.effective_bulk_modulus_mpa": ("plant", "line_bulk_modulus_mpa"),
    "actuator.coulomb_friction_n": ("plant", "coulomb_friction_n"),
    "actuator.static_friction_n": ("plant", "static_friction_n"),
    "load.regulator_time_constant_s": ("plant", "load_regulator_time_constant_s"),
    "valve.supply.needle_y_c_mm": ("supply", "y_c_mm"),
    "valve.drain.needle_y_c_mm": ("drain", "y_c_mm"),
    "valve.supply.z0_mm": ("supply", "z0_mm"),
    "valve.drain.z0_mm": ("drain", "z0_mm"),
    "valve.supply.c_flow": ("supply", "C"),
    "valve.drain.c_flow": ("drain", "C"),
}

#: the words a truth file uses for an effect -> the name discover gives it
EFFECT_NAMES = {"drift_supply": ("drift", "supply"), "drift_drain": ("drift", "drain"),
                "backlash": ("backlash", "both"), "delay": ("delay", "both")}


def _unpacked() -> Path:
    """The field data unpacked (tests/field_data.py finds the archive)."""
    sys.path.insert(0, str(REPO / "tests"))
    from field_data import unpack_field_data

    root = unpack_field_data(Path(tempfile.gettempdir()) / "seanv-bench-field")
    if root is None:
        raise FileNotFoundError("no ../shared/field-data next to the repository")
    return root


def _cli(*args: str) -> tuple[int, dict | None, str, float]:
    """(exit code, --json document or None, stderr, wall time [s]) of one command."""
    t0 = time.perf_counter()
    res = subprocess.run([sys.executable, "-m", "seanv_analysis", *args], capture_output=True,
                         text=True, cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)})
    wall = time.perf_counter() - t0
    try:
        doc = json.loads(res.stdout) if res.stdout.strip().startswith("{") else None
    except ValueError:
        doc = None
    return res.returncode, doc, res.stderr, wall


def _named(doc: dict | None) -> list[tuple[str, str]]:
    return [(e["name"], e["side"]) for e in (doc or {}).get("effects", [])]


def _coverage(doc: dict, truth: dict) -> dict[str, dict]:
    out = {}
    for c in doc.get("constants", []):
        where = TRUTH_KEYS.get(c.get("key"))
        if where is None or where[1] not in truth.get(where[0], {}):
            continue
        true = float(truth[where[0]][where[1]])
        value = next((v for k, v in c.items() if k.startswith("value")), None)
        ci = next((v for k, v in c.items() if k.startswith("ci95")), None) or [None, None]
        lo, hi = (math.nan if v is None else float(v) for v in ci)
        out[c["key"]] = {"truth": true, "value": value, "ci95": [lo, hi],
                         "identified": bool(c.get("identified")),
                         "covers": bool(c.get("identified") and lo <= true <= hi)}
    return out


def _drop(candidate: dict, before_key: str, after_key: str) -> float | None:
    """1 - after / before of a dynamic candidate's held-out flow RMSE (the
    replay: ``replay_heldout_*``; the closed loop per segment:
    ``heldout_before`` (the identified twin: the headline),
    ``heldout_base_twin`` (its line refitted alone: what the check compares)
    and ``heldout_after``)."""
    before = (candidate.get(before_key) or {}).get("rmse_flow_mm3_s")
    after = (candidate.get(after_key) or {}).get("rmse_flow_mm3_s")
    if not before or after is None:
        return None
    return round(1.0 - after / before, 3)


#: the fields of each dynamic candidate in the results, in order
CANDIDATE_FIELDS = ("name", "named", "p_value", "p_value_heldout (replay)", "replay drop",
                    "p_value_heldout_segments", "closed-loop drop vs the base twin",
                    "closed-loop drop vs the identified twin (headline)")


def main() -> dict:
    data = _unpacked()
    from field_data import FIELD_SETS as SETS
    out: dict = {"sets": {}, "confusion": {}, "coverage": {}, "candidate_fields": CANDIDATE_FIELDS}
    with tempfile.TemporaryDirectory() as tmp:
        for name in SETS:
            truth = json.loads((data / "_truth" / f"{name}.json").read_text())
            d = data / name
            row: dict = {"expected": truth["expected"]}
            runs = {
                "discover": ("discover", str(d), "--json", "-q", "--no-figures"),
                "discover_identify": ("discover", str(d), "--identify", "--json", "-q",
                                      "--no-figures"),
                "identify": ("identify", str(d), "--json", "-q"),
                "run_paper": ("run", "paper", str(d), "--json", "-q", "--no-figures",
                              "--workers", "2"),
            }
            docs = {}
            for key, args in runs.items():
                code, doc, err, wall = _cli(*args, "--out", f"{tmp}/{name}-{key}")
                docs[key] = doc
                row[key] = {"exit_code": code, "wall_s": round(wall, 1),
                            "traceback": "Traceback" in err,
                            "internal_error": code == 3 or "internal error" in err}
            for key in ("discover", "discover_identify"):
                doc = docs[key] or {}
                row[key].update(verdict=doc.get("verdict"), named=_named(doc),
                                heldout=doc.get("heldout"),
                                candidates=[(c["name"], c["named"], c.get("p_value"),
                                             c.get("p_value_heldout"),
                                             _drop(c, "replay_heldout_before",
                                                   "replay_heldout_after"),
                                             c.get("p_value_heldout_segments"),
                                             _drop(c, "heldout_base_twin", "heldout_after"),
                                             _drop(c, "heldout_before", "heldout_after"))
                                            for c in (doc.get("position_control") or {})
                                            .get("candidates", [])])
            injected = sorted({EFFECT_NAMES[k] for k in truth.get("effects", {})
                               if k in EFFECT_NAMES})
            out["confusion"][name] = {"injected": injected,
                                      "named_discover": _named(docs["discover"]),
                                      "named_discover_identify": _named(docs["discover_identify"])}
            if docs["identify"]:
                out["coverage"][name] = _coverage(docs["identify"], truth)
            if name == "field-slow-servo":
                code, doc, err, wall = _cli("identify", str(d), "--json", "-q",
                                            "--out", f"{tmp}/{name}-id2")
                code, doc, err, wall = _cli("validate", str(d), "--rig",
                                            f"{tmp}/{name}-id2/rig-identified.toml", "--json",
                                            "-q", "--no-figures", "--out", f"{tmp}/{name}-val")
                cam = next((r for r in (doc or {}).get("runs", []) if r.get("controller") == "cam"),
                           {})
                row["validate"] = {"exit_code": code, "flagged": (doc or {}).get("flagged"),
                                   **{k: cam.get(k) for k in cam if k.startswith("limit_cycle")}}
            out["sets"][name] = row
    cov = [c["covers"] for s in out["coverage"].values() for c in s.values()]
    out["coverage_rate"] = sum(cov) / len(cov) if cov else math.nan
    # each set's undeclared effects named, and nothing else, by both commands
    out["confusion_ok"] = {
        name: {key: sorted(map(tuple, c[f"named_{key}"])) == sorted(map(tuple, c["injected"]))
               for key in ("discover", "discover_identify")}
        for name, c in out["confusion"].items()}
    out["no_traceback"] = all(not r[k]["traceback"] and not r[k]["internal_error"]
                              for r in out["sets"].values()
                              for k in ("discover", "discover_identify", "identify", "run_paper"))
    res = HERE / "results"
    res.mkdir(exist_ok=True)
    (res / "bench_field.json").write_text(json.dumps(out, indent=1, default=str) + "\n")
    return out


if __name__ == "__main__":
    print(json.dumps(main(), indent=1, default=str))
