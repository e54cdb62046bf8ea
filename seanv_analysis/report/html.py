"""One self-contained ``report.html`` of a pipeline run.

Everything is inside the file: CSS inline, figures embedded as base64 PNG
(or inline SVG when only an SVG exists), no script, no external link, so
the file can be mailed or archived as is. Sections:

1. overview: runs read / failed / excluded, the key numbers;
2. identified flow model (eq. 5): z0 and C per side with 95 % intervals
   (method named), next to the rig config's (the paper's) values, and a
   verdict per side: flowfit's lack-of-fit check and what discovery found
   on that side (never a green "ok" beside a finding);
3. flow tracking during position control: delay with its 95 % interval,
   RMSE (residual = shifted actual - target);
4. closed-loop validation table (free-run simulation of each run), with the
   identified and, when discovery found an effect, the augmented model,
   each with its run count and links to its drawn figures;
5. discovery: verdict, effects, held-out error before/after;
6. figures: every figure of the registry :data:`seanv_analysis.plots.FIGURES`
   that was drawn, in registry order, its title as caption (the sections
   above link to the figures drawn from their result);
7. runs excluded by the paper's filters and why; runs that failed;
8. provenance: version, git SHA, command line, pipeline, rig config, input
   file hashes, executor, timings.

Headers are words with units; every table sits in a box that scrolls
sideways, so nothing is cut on a narrow window (checked in headless Chromium
at 1280 and 800 px by ``scripts/check_report_browser.py``).

The report only formats results (their attributes, tables) and the figure
files already written; it computes nothing. The sections of the stage
results (2-5 above) are not listed here: each stage names its own
(``SECTION``), and :func:`render_report` renders those it is given, in order.
"""
from __future__ import annotations

import json
import re
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable, Sequence

import pandas as pd

from .. import __version__
from ..io.atomic import write_text_atomic
from ..io.manifest import git_sha
from ._format import MM3_S, _drawn, _e, _figure_block, _figure_links, _table

__all__ = ["render_report", "write_report", "ReportSection"]

_CSS = """
body{font-family:-apple-system,'Segoe UI',Helvetica,Arial,sans-serif;margin:0;color:#1d232a;background:#f5f6f8}
main{max-width:1100px;margin:0 auto;padding:1.2em 2em 3em;background:#fff}
h1{font-size:1.6em;margin:.3em 0 .1em} h2{font-size:1.25em;border-bottom:2px solid #d7dbe0;padding-bottom:.2em;margin-top:1.8em}
h3{font-size:1.05em;margin:1.2em 0 .4em}
.sub{color:#5b6570;margin:0 0 1em}
table{border-collapse:collapse;margin:.5em 0 1em;font-size:.88em}
th,td{border:1px solid #d7dbe0;padding:.25em .55em;text-align:right;vertical-align:top}
th{background:#eef1f4;text-align:center} td.l,th.l{text-align:left}
.cards{display:flex;flex-wrap:wrap;gap:.8em;margin:1em 0}
.card{border:1px solid #d7dbe0;border-radius:6px;padding:.6em .9em;min-width:150px;background:#fafbfc}
.card b{display:block;font-size:1.35em} .card span{color:#5b6570;font-size:.85em}
.ok{color:#1a7f37} .warn{color:#b35900} .bad{color:#c62828}
figure{margin:.8em 0;text-align:center} figure img,figure svg{max-width:100%;height:auto;border:1px solid #e3e6ea}
figcaption{color:#5b6570;font-size:.85em}
pre{background:#f3f4f6;padding:.6em;overflow-x:auto;font-size:.8em;white-space:pre-wrap}
details{margin:.5em 0} summary{cursor:pointer;color:#24527a}
.note{background:#fff8e5;border-left:4px solid #e0a800;padding:.4em .8em;margin:.6em 0}
.err{background:#fdecea;border-left:4px solid #c62828;padding:.4em .8em;margin:.6em 0}
.scroll{overflow-x:auto;max-width:100%}
.grid{display:grid;grid-template-columns:1fr 1fr;gap:.6em}
nav a{margin-right:1em;color:#24527a;text-decoration:none;font-size:.9em}
.sub{overflow-wrap:anywhere} td.l{overflow-wrap:break-word} td small{color:#5b6570} th.verdict{min-width:12em} td.w{overflow-wrap:anywhere}
@media (max-width:900px){main{padding:.8em 1em 2em}.grid{grid-template-columns:1fr}
.card{min-width:120px}table{font-size:.82em}}
"""



@dataclass(frozen=True)
class ReportSection:
    """One section of the report, named by the stage whose result it shows
    (``SECTION`` of a stage module): its anchor (``#flowfit``), its title,
    ``render(record) -> html`` and, optionally, ``cards(record) -> [(value
    html, label)]``, its key numbers on the overview."""

    anchor: str
    title: str
    render: Callable[[Any], str]
    cards: Callable[[Any], list] | None = None


# sections ---------------------------------------------------------------------

def _overview(r, sections: Sequence[ReportSection]) -> str:
    s = r.summary
    n_flow = int((s["kind"] == "flow_step").sum()) if not s.empty else 0
    n_pos = int((s["kind"] == "position_control").sum()) if not s.empty else 0
    n_ex = int((s["excluded"].fillna("") != "").sum()) if not s.empty else 0
    cards = [(f"{r.runs_read} / {r.runs_found}", "runs read / found"),
             (f"{n_flow} + {n_pos}", "flow-step + position-control runs"),
             (str(n_ex), "flow-step runs excluded by the filters"),
             (f"<span class='{'bad' if r.failed else 'ok'}'>{len(r.failed)}</span>", "runs failed")]
    for sec in sections:
        if sec.cards is not None:
            cards += sec.cards(r)
    body = "".join(f"<div class='card'><b>{v}</b><span>{_e(t)}</span></div>" for v, t in cards)
    parts = [f"<div class='cards'>{body}</div>"]
    for name, msg in r.stage_errors.items():
        parts.append(f"<div class='err'><b>stage {_e(name)} failed:</b> {_e(msg)}</div>")
    for name, msg in r.stage_notes.items():
        parts.append(f"<div class='note'><b>{_e(name)}:</b> {_e(msg)}</div>")
    return "".join(parts)


def _figures_section(r) -> str:
    drawn = _drawn(r)
    if not drawn:
        why = r.stage_notes.get("figures") or r.stage_errors.get("figures") or "none drawn"
        return f"<p>No figure ({_e(why)}).</p>"
    root = getattr(r, "out_dir", None)
    root = Path(root) if root is not None else None
    return "".join(_figure_block(fig, paths, root) for fig, paths in drawn)


def _runs(r) -> str:
    s = r.summary
    out = []
    counts = ", ".join(f"{k}: {v}" for k, v in r.excluded.items()) or "none"
    out.append(f"<p>Excluded from the flow fit by the paper's filters (Sec. II-D.2): {_e(counts)}.</p>")
    if not s.empty:
        ex = s[s["excluded"].fillna("") != ""]
        if len(ex):
            by = ex.groupby(["excluded", "side"]).size().unstack(fill_value=0)
            by.columns = [f"{side} side [runs]" for side in by.columns]
            out.append("<p>Excluded runs by reason and side:</p>"
                       + _table(by.reset_index().rename(columns={"excluded": "reason"}),
                                left=("reason",)))
            cols = [c for c in ("run_index", "run_id", "side", "load_mpag", "cam_deg", "q_mm3_s",
                                "excluded", "excluded_detail") if c in ex.columns]
            ex = ex[cols].copy()
            if "q_mm3_s" in ex:
                ex["q_mm3_s"] = ex["q_mm3_s"].round(1) + 0.0  # no -0.0, no 1e-11 noise
            out.append(f"<details{' open' if len(ex) <= 20 else ''}><summary>the {len(ex)} "
                       "excluded runs and why</summary>"
                       + _table(ex, left=("run_id", "side", "excluded", "excluded_detail"),
                                max_rows=5000) + "</details>")
    if r.failed:
        out.append(f"<h3 class='bad'>Failed runs ({len(r.failed)})</h3>")
        df = pd.DataFrame([f.to_json_dict() for f in r.failed])
        out.append(_table(df, left=("path", "stage", "message")))
    else:
        out.append("<p class='ok'>No run failed.</p>")
    out.append(_figure_links(r, "runs"))
    if not s.empty:
        cols = [c for c in ("run_index", "run_id", "kind", "side", "started_at", "load_mpag",
                            "cam_deg", "q_mm3_s", "dp_mpa", "excluded") if c in s.columns]
        df = s[cols].copy()
        if "started_at" in df:
            df["started_at"] = df["started_at"].astype(str)
        out.append("<details><summary>all runs read (per-run summary)</summary>"
                   + _table(df, left=("run_id", "kind", "side", "started_at", "excluded"), max_rows=2000)
                   + "</details>")
    return "".join(out)


def _provenance(r) -> str:
    manifest = {}
    if r.manifest_path and Path(r.manifest_path).is_file():
        try:
            manifest = json.loads(Path(r.manifest_path).read_text())
        except ValueError:
            manifest = {}
    cmd = manifest.get("command_line") or " ".join(r.command)
    rows = [("package version", f"seanv-analysis {__version__}"),
            ("git commit", manifest.get("git_sha") or git_sha() or "not a git checkout"),
            ("command line", cmd),
            ("pipeline", f"{r.pipeline.name} ({r.pipeline.source or 'built in'})"),
            ("data", ", ".join(str(d) for d in r.data)),
            ("executor", r.executor),
            ("rig config", getattr(r.rig, "source", "")),
            ("inputs", f"{len(r.input_hashes)} files, combined SHA-256 "
                       f"{manifest.get('inputs_sha256', '')}"),
            ("created (UTC)", manifest.get("created_utc")
             or datetime.now(timezone.utc).isoformat(timespec="seconds"))]
    out = ["<table>" + "".join(f"<tr><td class='l'><b>{_e(k)}</b></td><td class='l'><code>{_e(v)}"
                                f"</code></td></tr>" for k, v in rows) + "</table>"]
    times = ", ".join(f"{k} {v:.1f} s" for k, v in r.timings_s.items())
    comp = ", ".join(f"{k}: {v} computed / {r.cached.get(k, 0)} cached" for k, v in r.computed.items())
    out.append(f"<p>Timings: {_e(times)}.<br>Per-run tasks: {_e(comp or 'none')}.</p>")
    out.append("<details><summary>pipeline (with defaults)</summary><pre>"
               + _e(json.dumps(r.pipeline.to_dict(), indent=2)) + "</pre></details>")
    if r.rig is not None:
        out.append("<details><summary>rig config</summary><pre>"
                   + _e(json.dumps(r.rig.to_dict(), indent=2, default=str)) + "</pre></details>")
    hashes = pd.DataFrame([{"file": k, "sha256": v} for k, v in sorted(r.input_hashes.items())])
    out.append("<details><summary>input files and SHA-256</summary>"
               + _table(hashes, left=("file", "sha256"), wrap=("file", "sha256"), max_rows=5000)
               + "</details>")
    if r.warnings:
        out.append("<details><summary>warnings</summary><pre>" + _e("\n".join(r.warnings))
                   + "</pre></details>")
    return "".join(out)


def _responsive(body: str) -> str:
    """Tables that fit a narrow window: each in a box that scrolls sideways
    (nothing is cut), headers that may wrap after a '/' or '·' of a unit."""
    body = re.sub(r"(<th[^>]*>)([^<]*)(</th>)",
                  lambda m: m[1] + re.sub(r"([/·])(?=\S)", r"\1<wbr>", m[2]) + m[3], body)
    return body.replace("<table>", "<div class='scroll'><table>").replace("</table>", "</table></div>")


def render_report(result: Any, sections: Sequence[ReportSection] = ()) -> str:
    """The report of a pipeline run as one HTML string.

    Parameters
    ----------
    result : the record of a pipeline run (the batch runner's
        ``PipelineResult``), read through these attributes only:

        - ``pipeline`` (``.name``, ``.description``, ``.source``, ``.to_dict()``),
          ``data`` (input folders), ``executor``, ``command`` (list of str),
          ``rig`` (rig config: ``rig["valve"][side]["z0_mm"]``, ``.to_dict()``)
        - ``runs_found``, ``runs_read``, ``summary`` (per-run DataFrame),
          ``excluded`` ({reason: count}), ``failed`` (objects with ``.to_json_dict()``)
        - ``figures``: {registered figure name: written paths}
        - ``stage_errors``, ``stage_notes`` ({stage: one line}), ``warnings``
        - ``input_hashes`` ({file: sha256}), ``manifest_path`` (or None),
          ``timings_s``, ``computed``, ``cached`` ({stage: number})
        - whatever the ``sections`` read (the stage results by name)
    sections : the stage results' sections, in order (the catalogue's:
        :func:`seanv_analysis.stages.report_sections`), between the overview
        and the figures

    Figures appear in the order of :data:`seanv_analysis.plots.FIGURES`, each
    with its registered title as caption.
    """
    r = result
    sections = [("overview", "Overview", _overview(r, sections)),
                *((sec.anchor, sec.title, sec.render(r)) for sec in sections),
                ("figures", "Figures", _figures_section(r)),
                ("runs", "Runs: excluded and failed", _runs(r)),
                ("provenance", "Provenance", _provenance(r))]
    nav = "".join(f"<a href='#{sid}'>{_e(title.split(':')[0].split('(')[0].strip())}</a>"
                  for sid, title, _ in sections)
    body = "".join(f"<section id='{sid}'><h2>{_e(title)}</h2>{content}</section>"
                   for sid, title, content in sections)
    body = _responsive(body)
    title = f"seanv-analysis report: {r.pipeline.name}"
    sub = (f"{_e(r.pipeline.description)}<br>data: {_e(', '.join(str(d) for d in r.data))}; "
           f"seanv-analysis {_e(__version__)}. Units: mm, MPa gauge, deg, s, {MM3_S}.")
    return ("<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>"
            f"<meta name='viewport' content='width=device-width, initial-scale=1'><title>{_e(title)}</title>"
            f"<style>{_CSS}</style></head><body><main><h1>{_e(title)}</h1><p class='sub'>{sub}</p>"
            f"<nav>{nav}</nav>{body}</main></body></html>\n")


def write_report(result: Any, path: str | Path, sections: Sequence[ReportSection] = ()) -> Path:
    """Write ``report.html`` (atomically) and return its path.

    Parameters
    ----------
    result : the record of a pipeline run, as for :func:`render_report`
        (stages that did not run are shown as such)
    path : output file
    sections : the stage results' sections, as for :func:`render_report`

    Examples
    --------
    >>> write_report(result, "outputs/flow/run-paper/report.html",
    ...              report_sections())  # doctest: +SKIP
    """
    return write_text_atomic(Path(path), render_report(result, sections))
