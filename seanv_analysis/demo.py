"""``python -m seanv_analysis.demo`` (what ``make demo`` runs).

1. Simulates the paper's data sets with the built-in plant
   (:func:`seanv_analysis.sim.simulate_scenario`):

   - ``flowsteps``: the flow-step runs over the paper's grid (Sec. II-D,
     Fig. 4), with the drain-side drift the paper observed ("the drain-side
     flow rate decreased slightly every three measurements"):
     effect ``drift:side=drain,step=0.005,every=3``, C falling 0.5 % every
     three runs, to 56 % of its first value over the 345 runs of the grid
     (the effect's default step of 5 % would leave the drain side without
     flow after about 100 runs, and the filters would exclude it);
   - ``position``: the position-control test of Sec. III-C (Fig. 6, 7),
     one run with and one without the flow model.

2. Runs ``pipelines/paper.toml`` on them (ingest -> flowfit -> tracking ->
   validate -> discover -> figures -> report) with local worker processes.

3. Prints the summary and where ``report.html`` is.

The simulated data sets are kept under ``outputs/demo/data/`` (made once,
keyed by the simulator's version: package version + hash of its sources) and the per-run results are cached, so a
second ``make demo`` takes seconds. Options: ``--out DIR``, ``--workers N``,
``--force`` (recompute everything), ``--quiet``.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

__all__ = ["DEMO_DATASETS", "DRAIN_DRIFT", "demo_datasets", "main", "timing_text",
           "README_TIME_START", "README_TIME_END", "TIMINGS"]

#: The drift the paper saw on the drain side (Sec. II-D.2, Fig. 4(a)): a slight
#: fall of C every three runs (0.5 %; "use" counts every run of the data set).
from .sim.scenarios import PAPER_DRAIN_DRIFT as DRAIN_DRIFT  # noqa: E402

#: folder name -> (scenario, effects)
DEMO_DATASETS: dict[str, tuple[str, tuple[str, ...]]] = {
    "flowsteps": ("paper-flowsteps", (DRAIN_DRIFT,)),
    "position": ("paper-position", ()),
}


def demo_datasets(root: str | Path | None = None, *, seed: int = 0, progress: bool = False,
                  log=None) -> list[Path]:
    """Simulate the demo data sets under ``root`` (default ``outputs/demo/data``)
    unless they are there already; return their folders.

    A data set is (re)made when its ``.complete`` marker is missing or was
    written for other scenario, effects, seed or simulator
    (:func:`~seanv_analysis.batch.cache.simulator_version`: the package version
    and a hash of the simulator's sources and the default rig).
    """
    from .batch.cache import simulator_version
    from .sim import SCENARIOS, simulate_scenario

    root = Path(root) if root is not None else Path("outputs") / "demo" / "data"
    folders = []
    for name, (scenario, effects) in DEMO_DATASETS.items():
        if scenario not in SCENARIOS:
            if name == "flowsteps":
                raise KeyError(f"simulator has no scenario {scenario!r}")
            continue  # e.g. no 'without the flow model' scenario in this version
        folder = root / name
        stamp = json.dumps({"scenario": scenario, "effects": list(effects), "seed": seed,
                            "version": simulator_version()}, sort_keys=True)
        marker = folder / ".complete"
        folders.append(folder)
        if marker.is_file() and marker.read_text() == stamp:
            continue
        t0 = time.perf_counter()
        if folder.exists():
            import shutil
            shutil.rmtree(folder)
        simulate_scenario(scenario, folder, seed=seed, effects=list(effects), progress=progress)
        marker.write_text(stamp)
        if log:
            log(f"simulated {scenario}" + (f" with {', '.join(effects)}" if effects else "")
                + f" -> {folder} ({time.perf_counter() - t0:.1f} s)")
    return folders


#: The paper's tracking RMSE over Q_ref in -2.5e3..8e3 mm^3/s (Sec. III-C.2) [mm^3/s].
PAPER_TRACKING_RMSE_MM3_S = 516.0


def _ci(values, fmt: str) -> str:
    if not values or any(v is None for v in values):
        return "(no interval)"
    return "[" + ", ".join(format(v, fmt) for v in values) + "]"


#: the README block the demo's headline numbers live in (scripts/update_readme_numbers.py)
README_START, README_END = "<!-- headline:start", "<!-- headline:end -->"
#: the demo result's numbers the README shows, recorded beside it
RECORDED_HEADLINE = Path("docs") / "demo_headline.json"


def headline_inputs(result: dict) -> dict:
    """The part of ``result`` (:meth:`PipelineResult.to_json_dict`) that
    :func:`headline` reads: flowfit, tracking, discovery (the README's
    record adds ``timings``: :func:`timing_text`)."""
    return {k: result.get(k) for k in ("flowfit", "tracking", "discovery")}


def readme_headline(readme_text: str) -> str:
    """The headline text inside the README's marked ```text block."""
    block = readme_text.split(README_START, 1)[1].split(README_END, 1)[0]
    return block.split("```text\n", 1)[1].rsplit("```", 1)[0].rstrip("\n")


def headline(result: dict, rig=None) -> str:
    """The demo's numbers next to the paper's (a few lines of text).

    ``result``: :meth:`PipelineResult.to_json_dict` of the paper pipeline.
    """
    from .config import load_rig
    from .models import ValveModel

    rig = rig or load_rig()
    paper = ValveModel.from_rig(rig)
    rows = [("", "this run (simulated plant)", "paper")]
    fit = result.get("flowfit") or {}
    for side in ("supply", "drain"):
        f = fit.get(side)
        if not f:
            continue
        ps = paper.side(side)
        rows.append((f"{side} z0 [mm]", f"{f['z0_mm']:+.4f} {_ci(f.get('z0_ci95_mm'), '+.4f')}",
                     f"{ps.z0_mm:+.3f}"))
        rows.append((f"{side} C [mm^3/(s deg^2 MPa^0.5)]",
                     f"{f['C_mm3_s_deg2_sqrtMPa']:+.3f} {_ci(f.get('C_ci95_mm3_s_deg2_sqrtMPa'), '+.3f')}", f"{ps.c_flow:+.3f}"))
    tr = result.get("tracking") or {}
    if tr.get("lag_s") is not None:
        rows.append(("flow delay behind Q_ref [s]",
                     f"{tr['lag_s']:.3f} {_ci(tr.get('lag_ci95_s'), '.3f')} (estimated)",
                     f"{rig.analysis.get('nominal_flow_lag_s', 0.25):.2f}"))
        lo, hi = tr.get("range_mm3_s") or (-2.5e3, 8e3)
        rows.append((f"tracking RMSE, Q_ref in {lo / 1e3:g}e3..{hi / 1e3:g}e3 [mm^3/s]",
                     f"{tr['rmse_mm3_s']:.0f} ({tr.get('pooled', 'all runs')})",
                     f"{PAPER_TRACKING_RMSE_MM3_S:.0f}"))
    width = max(len(r[0]) for r in rows)
    w2 = max(len(r[1]) for r in rows)
    lines = [f"{a:<{width}}  {b:<{w2}}  {c}" for a, b, c in rows]
    disc = result.get("discovery") or {}
    if disc:
        found = ", ".join(f"{e['name']} ({e['side']})" for e in disc.get("effects", [])) or "nothing"
        ho = disc.get("heldout", {})
        lines.append(f"discovery: {disc.get('verdict')}: {found}; held-out flow RMSE "
                     f"{ho.get('rmse_before_mm3_s', float('nan')):.0f} -> "
                     f"{ho.get('rmse_after_mm3_s', float('nan')):.0f} mm^3/s "
                     f"({ho.get('n_runs')} held-out runs)")
        for e in disc.get("effects", []):
            if e["name"] == "drift":
                lines.append(f"  drift: C of the {e['side']} side x (1 - {e['params']['step']:.4f}) "
                             f"every {e['params']['every']} runs (paper: 'decreased slightly every "
                             "three measurements')")
        val = disc.get("validation") or {}
        for ctrl, before in (val.get("before") or {}).items():
            after = (val.get("after") or {}).get(ctrl, {})
            if "fit_position_pct" in before and "fit_position_pct" in after:
                lines.append(f"  closed loop ({ctrl} controller): position fit "
                             f"{before['fit_position_pct']:.1f} % -> {after['fit_position_pct']:.1f} % "
                             "with the augmented model")
    return "\n".join(lines)


#: the README sentence on how long ``make demo`` takes (scripts/update_readme_numbers.py)
README_TIME_START, README_TIME_END = "<!-- demo-time:start -->", "<!-- demo-time:end -->"
#: where the demo keeps its timings, under its output folder: the last run
#: of each kind ('fresh': make installed the package first; 'installed';
#: 'reused': nothing had changed)
TIMINGS = "timings.json"


def _duration(s: float) -> str:
    """'28 s', '1 min 50 s'."""
    s = round(s)
    return f"{s // 60} min {s % 60} s" if s >= 60 else f"{s} s"


def timing_text(timings: dict) -> str:
    """How long ``make demo`` took, in one sentence, from the times it
    recorded itself (:data:`TIMINGS`): what the README says."""
    parts = []
    fresh, installed, reused = (timings.get(k) for k in ("fresh", "installed", "reused"))
    if fresh:
        sim, ana = round(fresh["simulation_s"]), round(fresh["analysis_s"])
        parts.append(f"{_duration(fresh['total_s'])} on a fresh clone "
                     f"({_duration(fresh['install_s'])} creating `.venv`, installing and "
                     f"compiling the simulator, {_duration(sim + ana)} for the demo itself: "
                     f"simulating the data sets {_duration(sim)}, the analysis {_duration(ana)})")
    if installed:
        parts.append(f"{_duration(installed['total_s'])} once installed (simulating "
                     f"{_duration(installed['simulation_s'])}, the analysis "
                     f"{_duration(installed['analysis_s'])})")
    if reused:
        parts.append(f"{_duration(reused['total_s'])} when run again with nothing changed")
    if not parts:
        return ""
    cores = next((t.get("cores") for t in (fresh, installed, reused) if t), None)
    return ((f"On {cores} cores, " if cores else "") + "`make demo` took " + "; ".join(parts)
            + " (measured by `make demo` itself: outputs/demo/timings.json)")


def _record_timings(out: Path, kind: str, timing: dict) -> None:
    """Keep ``timing`` as the last run of ``kind`` in ``out / TIMINGS``."""
    from .io.atomic import write_json_atomic

    path = out / TIMINGS
    try:
        doc = json.loads(path.read_text()) if path.is_file() else {}
    except (OSError, ValueError):
        doc = {}
    doc[kind] = timing
    write_json_atomic(path, doc)


def _check_readme(text: str) -> None:
    """In a source checkout: say whether the README shows this run's numbers."""
    readme = Path("README.md")
    if not (readme.is_file() and README_START in readme.read_text()):
        return
    shown = readme_headline(readme.read_text()).splitlines()[1:]
    if shown == text.splitlines():
        print("(README.md shows these numbers)")
    else:
        print("note: README.md's headline numbers differ from this run; "
              "`python scripts/update_readme_numbers.py` rewrites them from "
              "outputs/demo/run-paper/result.json")


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m seanv_analysis.demo``; returns the exit code."""
    parser = argparse.ArgumentParser(prog="python -m seanv_analysis.demo",
                                     description="Simulate the paper's data sets and run "
                                                 "pipelines/paper.toml on them (what `make demo` runs).")
    parser.add_argument("--out", type=Path, default=Path("outputs") / "demo",
                        help="output folder (default: outputs/demo)")
    parser.add_argument("--workers", type=int, default=None,
                        help="worker processes (default: the CPU count)")
    parser.add_argument("--force", action="store_true", help="recompute everything")
    parser.add_argument("--quiet", action="store_true", help="no progress output")
    parser.add_argument("--started-at", type=float, default=None,
                        help="when `make demo` started [s since the epoch]: the total time "
                             "counts from there (what make did first, an install, included)")
    parser.add_argument("--installed-at", type=Path, default=None,
                        help="the install's stamp file: an install newer than --started-at "
                             "was this make's (a fresh clone)")
    args = parser.parse_args(argv)

    from .batch import run_pipeline
    from .errors import SeanvError
    from .log import configure

    configure(quiet=args.quiet)   # progress bars on a terminal (the lines: log below)

    def log(msg: str) -> None:
        if not args.quiet:
            print(msg, file=sys.stderr, flush=True)

    t0 = time.perf_counter()
    wall0 = time.time()
    try:
        log("1/2 simulating the paper's data sets (flow steps with the drain drift the paper "
            "observed; position control with and without the flow model) ...")
        data = demo_datasets(args.out / "data", progress=False, log=log)
        t_sim = time.perf_counter() - t0
        log(f"2/2 running pipelines/paper.toml on {', '.join(map(str, data))} ...")
        result = run_pipeline("paper", data, out_dir=args.out / "run-paper", workers=args.workers,
                              force=args.force, quiet=args.quiet, log=log, reuse=True,
                              command=[sys.executable, "-m", "seanv_analysis.demo", *(argv or sys.argv[1:])])
    except SeanvError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(result.summary_text())
    print("\nheadline numbers (the drain C above is the average over a drifting valve):")
    text = headline(result.to_json_dict())
    print(text)
    _check_readme(text)
    total = time.perf_counter() - t0
    started = args.started_at if args.started_at is not None else wall0
    install = 0.0
    if args.installed_at is not None and args.installed_at.is_file():
        stamp = args.installed_at.stat().st_mtime
        install = max(0.0, stamp - started) if stamp >= started else 0.0
    kind = "fresh" if install > 0 else ("reused" if result.recorded is not None else "installed")
    timing = {"total_s": round(time.time() - started, 1), "install_s": round(install, 1),
              "simulation_s": round(t_sim, 1), "analysis_s": round(total - t_sim, 1),
              "cores": os.cpu_count()}
    _record_timings(args.out, kind, timing)
    print(f"\ndemo finished in {total:.0f} s (simulation {t_sim:.0f} s, analysis "
          f"{total - t_sim:.0f} s)"
          + (f"; make demo took {timing['total_s']:.0f} s in all, {install:.0f} s of it "
             "installing" if install > 0 else ""))
    if result.report_path:
        print(f"open the report: {Path(result.report_path).resolve()}")
    return 0 if result.success else 1


if __name__ == "__main__":
    sys.exit(main())
