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
files already written; it computes nothing.
"""
from __future__ import annotations

import base64
import html
import json
import math
import re
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterable

import pandas as pd

from .. import __version__
from ..io.atomic import write_text_atomic
from ..io.manifest import git_sha
from ..jsonable import UNIT_SUFFIXES
from ..models import effects as fx
from ..plots import FIGURES, Figure

__all__ = ["render_report", "write_report"]

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


def _e(x: Any) -> str:
    return html.escape(str(x), quote=True)


def _fmt(v: Any, digits: int = 4) -> str:
    if v is None:
        return "&ndash;"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, (int,)) and not isinstance(v, bool):
        return str(v)
    try:
        f = float(v)
    except (TypeError, ValueError):
        return _e(v)
    if not math.isfinite(f):
        return "&ndash;"
    if f != 0 and (abs(f) >= 1e5 or abs(f) < 1e-3):
        return f"{f:.{digits - 1}e}"
    return f"{f:.{digits}g}" if abs(f) >= 1 else f"{f:.{digits}f}".rstrip("0").rstrip(".")


def _ci(ci: Any, digits: int = 4) -> str:
    try:
        lo, hi = (float(c) for c in ci)
    except (TypeError, ValueError):
        return "<span class='warn'>no interval</span>"
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return "<span class='warn'>no interval (singular covariance / too few runs)</span>"
    return f"[{_fmt(lo, digits)}, {_fmt(hi, digits)}]"


#: units as the report prints them (``_unit`` turns a plain "mm^3/s" into these)
MM3_S = "mm³/s"
C_UNIT = "mm³/(s·deg²·MPa^0.5)"
ALPHA_UNIT = "mm³/(s·deg²)"

#: column names said in words (the others: unit suffix -> "[unit]", words from _WORDS)
_HEADERS = {"run_id": "run", "run_index": "run #", "fit_position_pct": "position fit [%]",
            "rmse_position_mm": "position RMSE [mm]", "fit_flow_pct": "flow fit [%]",
            "rmse_flow_mm3_s": f"flow RMSE [{MM3_S}]", "fit_cam_pct": "cam fit [%]",
            "rmse_cam_deg": "cam RMSE [deg]", "q_mm3_s": f"Q [{MM3_S}]", "dp_mpa": "Δp [MPa]",
            "p1_mpa": "p₁ [MPa]", "p1_threshold_mpa": "p₁ at θ_d [MPa]",
            "dp_threshold_mpa": "Δp at θ_d [MPa]",
            "load_mpag": "load [MPaG]", "load_level_mpag": "load level [MPaG]",
            "cam_deg": "cam [deg]", "excluded": "excluded by", "excluded_detail": "why",
            "started_at": "started (UTC)", "lag_s": "delay [s]", "target_source": "target Q_ref",
            "lag_ci95_lo_s": "delay 95 % interval, low [s]",
            "lag_ci95_hi_s": "delay 95 % interval, high [s]", "lag_applied_s": "delay applied [s]",
            "rmse_mm3_s": f"RMSE [{MM3_S}]", "bias_mm3_s": f"bias [{MM3_S}]",
            "rmse_supply_mm3_s": f"RMSE, supply targets [{MM3_S}]",
            "rmse_drain_mm3_s": f"RMSE, drain targets [{MM3_S}]", "n_samples": "samples",
            "theta_d_deg": "θ_d [deg]", "theta_d_se_deg": "θ_d standard error [deg]",
            "theta_d_model_deg": "θ_d of the model [deg]", "alpha": f"α [{ALPHA_UNIT}]",
            "alpha_se": f"α standard error [{ALPHA_UNIT}]",
            "alpha_model": f"α of the model [{ALPHA_UNIT}]", "success": "fit converged",
            "flagged": "flagged", "n_runs": "runs", "steps": "reference steps",
            "sha256": "SHA-256", "overshoot_measured_mm": "overshoot, measured [mm]",
            "overshoot_simulated_mm": "overshoot, simulated [mm]"}
#: words of a column name said as a reader says them
_WORDS = {"rmse": "RMSE", "ci95": "95 % interval", "lo": "low", "hi": "high",
          "se": "standard error", "n": "number of", "theta": "θ", "alpha": "α", "kp": "Kp", "dp": "Δp", "q": "Q",
          "sha256": "SHA-256"}


def _words(name: str) -> str:
    """``rmse_supply`` -> 'RMSE supply'."""
    return " ".join(_WORDS.get(w, w) for w in name.split("_") if w)


def _header(col: Any) -> str:
    """A column name as a reader wants it: words and the unit in brackets."""
    col = str(col)
    if col in _HEADERS:
        return _HEADERS[col]
    for suffix, unit in _UNITS:
        if col.endswith(suffix) and len(col) > len(suffix):
            return f"{_words(col[:-len(suffix)])} [{unit}]"
    return _words(col)


def _unit(text: Any) -> str:
    """A plain-text unit as printed: 'mm^3/(s deg^2 MPa^0.5)' -> 'mm³/(s·deg²·MPa^0.5)',
    'N s/mm' -> 'N·s/mm' ('mm^3/s per mm' keeps its words: 'mm³/s per mm')."""
    return re.sub(r"(?<=[A-Za-z²³)])(?<!\bper) (?=[A-Za-z(])(?!per\b)", "·", _superscripts(text))


def _superscripts(text: Any) -> str:
    """'mm^3/s' -> 'mm³/s' (squares and cubes; 'MPa^0.5' stays)."""
    return re.sub(r"\^([23])(?![\d.])", lambda m: "²³"[int(m.group(1)) - 2], str(text))


#: column-name suffix -> its unit as printed (the package's one unit table)
_UNITS = tuple((suffix, _unit(text)) for suffix, text in UNIT_SUFFIXES.items())


def _plural(n: int, word: str, plural: str | None = None) -> str:
    """'1 run', '2 runs' (``plural``: the plural when it is not word + 's')."""
    return f"{n} {word if n == 1 else (plural or word + 's')}"


def _table(df: pd.DataFrame, *, left: Iterable[str] = (), wrap: Iterable[str] = (),
           max_rows: int = 400) -> str:
    """``df`` as an HTML table: headers in words with units (:func:`_header`),
    text left-aligned (and the ``left`` columns), the ``wrap`` columns (long
    names, hashes) free to break anywhere on a narrow window."""
    if df is None or len(df) == 0:
        return "<p><i>none</i></p>"
    left, wrap = set(left), set(wrap)
    head = "".join(f"<th>{_e(_header(c))}</th>" for c in df.columns)
    rows = []
    for rec in df.head(max_rows).to_dict(orient="records"):
        cells = []
        for c in df.columns:
            v = rec[c]
            cls = ["l"] if c in left or isinstance(v, str) else []
            cls += ["w"] if c in wrap else []
            attr = f" class='{' '.join(cls)}'" if cls else ""
            cells.append(f"<td{attr}>{_e(v) if isinstance(v, str) else _fmt(v)}</td>")
        rows.append("<tr>" + "".join(cells) + "</tr>")
    more = f"<p><i>{len(df) - max_rows} more rows not shown</i></p>" if len(df) > max_rows else ""
    return f"<table><tr>{head}</tr>{''.join(rows)}</table>{more}"


def _figure(path: Path, caption: str = "") -> str:
    """A figure embedded in the page: PNG as base64, SVG inline."""
    path = Path(path)
    png = path.with_suffix(".png")
    cap = f"<figcaption>{_e(caption or path.stem)}</figcaption>"
    if png.is_file():
        data = base64.b64encode(png.read_bytes()).decode("ascii")
        return (f"<figure><img alt='{_e(path.stem)}' src='data:image/png;base64,{data}'>"
                f"{cap}</figure>")
    svg = path.with_suffix(".svg")
    if svg.is_file():
        text = svg.read_text(encoding="utf-8", errors="replace")
        start = text.find("<svg")
        return f"<figure>{text[start:] if start >= 0 else text}{cap}</figure>"
    return ""


def _figures(paths: Iterable[Path], caption: str = "") -> str:
    seen, out = set(), []
    for p in paths:
        stem = Path(p).with_suffix("")
        if stem in seen or Path(p).suffix not in (".png", ".svg"):
            continue
        seen.add(stem)
        out.append(_figure(Path(p), caption or Path(p).stem))
    return "".join(out)


def _drawn(r) -> list[tuple[Figure, list[Path]]]:
    """(registered figure, its files) for every figure of ``r.figures``, in
    registry order; figures not registered are not shown."""
    out = []
    for fig in FIGURES.values():
        paths = [Path(p) for p in r.figures.get(fig.name, ())]
        if paths:
            out.append((fig, paths))
    return out


def _figure_block(fig: Figure, paths: list[Path]) -> str:
    """One registered figure: its title as heading and caption. A data-set
    figure's main file is ``<name>.<format>``; its other files (one per run,
    as Fig. 7 writes) are folded away. A per-run figure is a grid, each file
    captioned with its name."""
    head = f"<h3 id='fig-{_e(fig.name)}'>{_e(fig.title)}</h3>"
    if fig.per_run:
        return head + f"<div class='grid'>{_figures(paths)}</div>"
    main = [p for p in paths if p.stem == fig.name]
    if not main:
        return head + _figures(paths, fig.title)
    rest = [p for p in paths if p.stem != fig.name]
    out = head + _figures(main, fig.title)
    if rest:
        out += (f"<details><summary>{_e(fig.title)}: one figure per run</summary>"
                f"<div class='grid'>{_figures(rest)}</div></details>")
    return out


def _figure_links(r, section: str) -> str:
    """Links to the drawn figures whose first need is this section's result."""
    links = [f"<a href='#fig-{_e(fig.name)}'>{_e(fig.title)}</a>"
             for fig, _ in _drawn(r) if fig.needs[0] == section]
    return f"<p>Figures: {'; '.join(links)}.</p>" if links else ""


# sections ---------------------------------------------------------------------

def _overview(r) -> str:
    s = r.summary
    n_flow = int((s["kind"] == "flow_step").sum()) if not s.empty else 0
    n_pos = int((s["kind"] == "position_control").sum()) if not s.empty else 0
    n_ex = int((s["excluded"].fillna("") != "").sum()) if not s.empty else 0
    cards = [(f"{r.runs_read} / {r.runs_found}", "runs read / found"),
             (f"{n_flow} + {n_pos}", "flow-step + position-control runs"),
             (str(n_ex), "flow-step runs excluded by the filters"),
             (f"<span class='{'bad' if r.failed else 'ok'}'>{len(r.failed)}</span>", "runs failed")]
    if r.tracking is not None:
        cards.append((f"{_fmt(r.tracking.rmse_mm3_s, 3)}", "flow tracking RMSE [mm³/s]"))
        cards.append((f"{_fmt(r.tracking.lag_s, 3)}", "flow delay [s]"))
    if r.discovery is not None:
        cls = "warn" if r.discovery.verdict != "none" else "ok"
        cards.append((f"<span class='{cls}'>{_e(verdict_words(r.discovery, short=True))}</span>",
                      "discovery"))
    body = "".join(f"<div class='card'><b>{v}</b><span>{_e(t)}</span></div>" for v, t in cards)
    parts = [f"<div class='cards'>{body}</div>"]
    for name, msg in r.stage_errors.items():
        parts.append(f"<div class='err'><b>stage {_e(name)} failed:</b> {_e(msg)}</div>")
    for name, msg in r.stage_notes.items():
        parts.append(f"<div class='note'><b>{_e(name)}:</b> {_e(msg)}</div>")
    return "".join(parts)


def _flowfit(r) -> str:
    fit = r.flowfit
    if fit is None:
        why = r.stage_errors.get("flowfit", "stage not in this pipeline")
        return f"<p>No flow fit ({_e(why)}).</p>"
    rows = []
    for side, f in fit.sides.items():
        ref_z0, ref_c = _rig_side_values(r.rig, side)
        rows.append(
            f"<tr><td class='l'>{_e(side)}</td><td>{_fmt(f.z0_mm, 5)}</td><td>{_ci(f.z0_ci95, 5)}</td>"
            f"<td>{_fmt(ref_z0, 5)}</td>"
            f"<td>{_fmt(f.c_flow, 4)}</td><td>{_ci(f.c_ci95)}</td>"
            f"<td>{_fmt(ref_c, 4)}</td>"
            f"<td>{_fmt(f.rmse_mm3_s, 4)}</td><td>{f.n_runs}</td>"
            f"<td class='l'>{_side_verdict(f, r.discovery)}</td></tr>")
    methods = sorted({f.ci_method for f in fit.sides.values() if f.ci_method})
    table = ("<table><tr><th class='l'>side</th><th>z0 [mm]</th><th>z0 95 % interval [mm]</th>"
             f"<th>z0 paper/rig [mm]</th><th>C [{C_UNIT}]</th><th>C 95 % interval [{C_UNIT}]</th>"
             f"<th>C paper/rig [{C_UNIT}]</th><th>RMSE [{MM3_S}]</th><th>runs used</th>"
             "<th class='l verdict'>verdict (flowfit's lack-of-fit check; discovery)</th>"
             "</tr>" + "".join(rows) + "</table>")
    plant = [e for e in _effects(r.discovery)  # in no side's row: the plant's
             if e.side not in fit.sides and not (e.side == "both" and _static(e))]
    if plant:
        names = ", ".join(f"{e.name} ({e.sentence()})" for e in plant)
        table += (f"<p>Discovery also found {_e(names)}: the plant, not eq. (5); see "
                  "<a href='#discovery'>Discovery</a>.</p>")
    notes = [f"Residual = measured &minus; model. Intervals: {_e('; '.join(methods) or 'n/a')}."]
    for side, f in fit.sides.items():  # the lack-of-fit check of every side, flagged or not
        line = f.lack_of_fit_line() if hasattr(f, "lack_of_fit_line") else ""
        if line:
            notes.append(f"{_e(side)}: {_e(line)}")
    notes += [f"<span class='warn'>warning:</span> {_e(w)}" for w in getattr(fit, "warnings", [])]
    per_load = getattr(fit, "per_load", None)
    pl = ""
    if per_load is not None and len(per_load):
        pl = "<details><summary>per load level (threshold angle and quadratic coefficient)</summary>" \
             + _table(per_load, left=("side",)) + "</details>"
    return table + "".join(f"<p>{n}</p>" for n in notes) + pl + _figure_links(r, "flowfit")


def _effects(discovery) -> list:
    """The effects discovery found (none when it did not run)."""
    return list(getattr(discovery, "effects", None) or [])


def _static(effect) -> bool:
    """Whether ``effect`` changes the steady flow of eq. (5) (it has a static
    form), so a side's fit averages over it; a dynamic one (a delay, the
    line's stiffness) does not."""
    cls = fx.EFFECTS.get(str(effect.name))
    return cls is not None and getattr(cls, "STATIC", None) is not None


def _side_findings(side: str, discovery) -> list[str]:
    """What discovery says against ``side``'s eq. (5) fit: each effect found on
    it (or a static one on both sides), named with its meaning; a structured
    residual no effect explains."""
    out = [f"discovery found {e.name}: {e.sentence()}" for e in _effects(discovery)
           if e.side == side or (e.side == "both" and _static(e))]
    if getattr(discovery, "verdict", None) == "unexplained":
        out.append("discovery: the residual is structured and no known effect explains it")
    return out


def _side_verdict(f, discovery) -> str:
    """The model table's verdict cell of one side: flowfit's status
    (``SideFit.status``: failed / lack of fit / ok) and discovery's findings;
    green "ok" only when neither flags the side."""
    status = getattr(f, "status", None) or ("ok" if f.success else "failed")
    flags = _side_findings(f.side, discovery)
    if status == "lack of fit":
        flags.insert(0, "lack of fit (flowfit's check against the repeated runs, below)")
    msg = f" <small>{_e(f.message)}</small>" if f.message else ""
    if status == "failed":
        return f"<span class='bad'>fit failed</span>{msg}"
    if flags:
        return f"<span class='warn'>{'<br>'.join(_e(x) for x in flags)}</span>{msg}"
    if getattr(f, "lack_of_fit", None) is None:
        return f"ok (lack of fit not tested){msg}"
    return f"<span class='ok'>ok</span>{msg}"


def _identify(r) -> str:
    ident = getattr(r, "identify", None)
    if ident is None:
        why = r.stage_errors.get("identify", "stage not in this pipeline")
        return (f"<p>The rig was not identified ({_e(why)}): validate and discover simulate the "
                "rig file's constants, including those the paper does not publish.</p>")
    rows = []
    for c in ident.constants:
        status = ("<span class='ok'>identified</span>" if c.identified
                  else "<span class='warn'>rig file</span>")
        key = _e(c.key).replace(".", ".<wbr>") if c.key else "(reported)"  # may wrap at a dot
        rows.append(f"<tr><td class='l'>{_e(c.name)}</td><td class='l'><code>{key}</code>"
                    f"</td><td>{_fmt(c.value)}</td><td>{_ci(c.ci95)}</td><td>{_fmt(c.default)}</td>"
                    f"<td class='l'>{_e(_unit(c.unit))}</td><td class='l'>{status} {_e(c.constrained_by)}"
                    f"{'; ' + _e(c.note) if c.note else ''}</td></tr>")
    table = ("<table><tr><th class='l'>constant</th><th class='l'>rig key</th><th>identified</th>"
             "<th>95 % interval</th><th>rig file</th><th class='l'>unit</th>"
             "<th class='l'>from</th></tr>" + "".join(rows) + "</table>")
    fit_rows = []
    for part, f in ident.fits.items():
        subs = ([(f"{part} ({k})", v) for k, v in f.items() if isinstance(v, dict)]
                if "metric" not in f else [(part, f)])
        for label, g in subs:
            if not any(k in g for k in ("train", "heldout")):
                continue
            measure = _superscripts(g.get("metric", ""))
            fit_rows.append(f"<tr><td class='l'>{_e(label.replace('_', ' '))}</td>"
                            f"<td class='l'>{_e(measure)}"
                            f"</td><td>{_fmt(g.get('train_default'))}</td><td>{_fmt(g.get('train'))}</td>"
                            f"<td>{_fmt(g.get('heldout_default'))}</td><td>{_fmt(g.get('heldout'))}"
                            "</td></tr>")
    fits = ("<h3>Training and held-out error: rig file's constants vs identified</h3>"
            "<table><tr><th class='l'>part</th><th class='l'>measure</th><th>training, rig file</th>"
            "<th>training, identified</th><th>held-out, rig file</th><th>held-out, identified</th>"
            "</tr>" + "".join(fit_rows) + "</table>") if fit_rows else ""
    cl = ident.fits.get("closed_loop") or {}
    seg = ident.fits.get("closed_loop_segments") or {}
    closed = ""
    if "heldout" in cl:
        closed = (f"<p>Held-out position-control runs re-simulated in closed loop: position fit "
                  f"{_fmt(cl.get('heldout_default'), 3)} % with the rig file's twin, "
                  f"{_fmt(cl.get('heldout'), 3)} % with the identified one; flow fit "
                  f"{_fmt(cl.get('heldout_default_flow'), 3)} % &rarr; "
                  f"{_fmt(cl.get('heldout_flow'), 3)} %.")
        if "heldout" in seg:
            closed += (f" Re-run segment by segment from the logged state (each reference step "
                       f"and load change; no hold's end carried into the next): position fit "
                       f"{_fmt(seg.get('heldout_default'), 3)} % &rarr; "
                       f"{_fmt(seg.get('heldout'), 3)} %, flow fit "
                       f"{_fmt(seg.get('heldout_default_flow'), 3)} % &rarr; "
                       f"{_fmt(seg.get('heldout_flow'), 3)} %.")
        closed += "</p>"
    notes = "".join(f"<div class='note'>{_e(n)}</div>" for n in ident.notes)
    return ("<p>The constants the paper does not publish, identified from this data set's own "
            "logs; what the data cannot tell keeps the rig file's value. Validation and discovery "
            "below simulate the identified twin.</p>" + table + closed + fits + notes)


def _rig_side_values(rig: Any, side: str) -> tuple[Any, Any]:
    """(z0 [mm], C [mm^3/(s deg^2 MPa^0.5)]) of ``side`` in the rig config
    (the paper's fitted values unless the rig says otherwise); None when the
    config has no such entry."""
    try:
        s = rig["valve"][side]
        return s.get("z0_mm"), s.get("c_flow")
    except (TypeError, KeyError, AttributeError):
        return None, None


def _tracking(r) -> str:
    tr = r.tracking
    out = []
    if tr is None:
        why = r.stage_errors.get("tracking") or r.stage_notes.get("tracking") or "stage not in this pipeline"
        out.append(f"<p>No tracking result ({_e(why)}).</p>")
    else:
        ci = tr.lag_ci95_s
        lag = f"{_fmt(tr.lag_s, 3)} s ({_e(tr.lag_source)}" + (f", 95 % interval {_ci(ci, 3)} s, block bootstrap"
                                                              if ci else "") + ")"
        lo, hi = tr.range_mm3_s
        out.append("<table>"
                   f"<tr><td class='l'>flow delay (actual behind target)</td><td>{lag}</td></tr>"
                   f"<tr><td class='l'>RMSE of shifted actual &minus; target, targets in "
                   f"[{_fmt(lo)}, {_fmt(hi)}] {MM3_S}</td><td>{_fmt(tr.rmse_mm3_s, 4)} {MM3_S} "
                   f"(paper: 516 {MM3_S})</td></tr>"
                   f"<tr><td class='l'>bias (actual &minus; target)</td><td>{_fmt(tr.bias_mm3_s, 4)} {MM3_S}"
                   "</td></tr>"
                   f"<tr><td class='l'>RMSE supply / drain targets</td><td>{_fmt(tr.rmse_supply_mm3_s, 4)} / "
                   f"{_fmt(tr.rmse_drain_mm3_s, 4)} {MM3_S}</td></tr>"
                   f"<tr><td class='l'>samples in range</td><td>{tr.n_samples}</td></tr></table>")
        out.append(f"<h3>Per run ({_plural(len(tr.per_run), 'position-control run')})</h3>"
                   + _table(tr.per_run, left=("run_id", "target_source")))
        for rid, why in tr.skipped.items():
            out.append(f"<div class='note'>skipped {_e(rid)}: {_e(why)}</div>")
    out.append(_figure_links(r, "tracking"))
    return "".join(out)


def _n_kind(r, kind: str) -> int | None:
    """Runs of ``kind`` ('position_control', 'flow_step') the data set holds,
    counted in the per-run summary; None without one."""
    s = getattr(r, "summary", None)
    if s is None or s.empty or "kind" not in s:
        return None
    return int((s["kind"] == kind).sum())


def _validation_table(val) -> str:
    cols = ["run_id", "controller", "fit_position_pct", "rmse_position_mm", "fit_flow_pct",
            "rmse_flow_mm3_s", "fit_cam_pct", "overshoot_measured_mm", "overshoot_simulated_mm",
            "limit_cycle", "limit_cycle_amplitude_measured_mm", "limit_cycle_amplitude_simulated_mm",
            "limit_cycle_period_measured_s", "limit_cycle_period_simulated_s", "flagged"]
    if "limit_cycle" in val.table and (val.table["limit_cycle"] == "none").all():
        cols = [c for c in cols if not c.startswith("limit_cycle")]   # no run hunts
    df = val.table[[c for c in cols if c in val.table.columns]]
    out = _table(df, left=("run_id", "controller"))
    by = val.by_controller()
    if len(by):
        by = by.reset_index()
        out += "<p>Mean per controller:</p>" + _table(by[[
            c for c in ["controller", "n_runs", "fit_position_pct", "rmse_position_mm", "fit_flow_pct",
                        "rmse_flow_mm3_s"] if c in by.columns]], left=("controller",))
    if val.flagged:
        out += f"<div class='note'>flagged (position fit &lt; {_fmt(val.threshold_pct)} %): " \
               f"{_e(', '.join(val.flagged))}</div>"
    for rid, why in (getattr(val, "skipped", None) or {}).items():
        out += f"<div class='note'>not validated: {_e(rid)}: {_e(why)}</div>"
    return out


def _validation_count(r, val) -> str:
    """'2 position-control runs re-run (of 2 in the data set).'"""
    n_data = _n_kind(r, "position_control")
    of = f" (of {n_data} in the data set)" if n_data is not None else ""
    return f"<p>{_plural(len(val.table), 'position-control run')} re-run{of}.</p>"


def _is_augmented(fig: Figure) -> bool:
    """Whether a registered figure draws the augmented model's validation
    (a need or a name that says so) rather than the identified model's."""
    return "validation_augmented" in fig.needs or "augmented" in fig.name


def _validation_figures(r, *, augmented: bool) -> str:
    """Links to the drawn figures of validate's result: the identified
    model's (figures that need "validation") or the augmented model's."""
    drawn = [fig for fig, _ in _drawn(r)
             if ("validation" in fig.needs or "validation_augmented" in fig.needs
                 or fig.name.startswith("validate"))
             and _is_augmented(fig) == augmented]
    if not drawn:
        which = "the augmented model" if augmented else "this model"
        return f"<p>No validation figure drawn for {which}.</p>"
    links = "; ".join(f"<a href='#fig-{_e(fig.name)}'>{_e(fig.title)}</a>" for fig in drawn)
    return f"<p>Figures: {links}.</p>"


def _validation(r) -> str:
    if r.validation is None:
        why = r.stage_errors.get("validate") or r.stage_notes.get("validate") or "stage not in this pipeline"
        return f"<p>No validation ({_e(why)}).</p>"
    twin = ("identified twin (the flow model of eq. 5 on the rig identified above)"
            if getattr(r, "identify", None) is not None else "identified flow model (eq. 5)")
    out = ["<p>Each position-control run's controller is re-run on the simulated plant "
           "(free-run simulation, not one-step prediction); fit % = "
           "100 (1 &minus; ||y &minus; y_sim|| / ||y &minus; mean(y)||), y measured, "
           "y_sim simulated.</p>",
           f"<h3>The {_e(twin)}</h3>", _validation_count(r, r.validation),
           _validation_table(r.validation), _validation_figures(r, augmented=False)]
    aug = getattr(r, "validation_augmented", None)
    if aug is not None:
        out += ["<h3>Augmented model (the same, plus the effects discovery found)</h3>",
                _validation_count(r, aug), _validation_table(aug),
                _validation_figures(r, augmented=True)]
    return "".join(out)


def verdict_words(d, *, short: bool = False) -> str:
    """Discovery's verdict said in words (``short``: for the overview card)."""
    names = ", ".join(f"{e.name} ({e.side})" for e in d.effects)
    trend = f"; it trends with {d.trend_variable}" if d.trend_variable else ""
    if short:
        return {"none": "nothing found", "effect_found": f"found: {names}",
                "unexplained": "unexplained residual"}.get(d.verdict, d.verdict)
    return {"none": "nothing found: the model explains the held-out runs",
            "effect_found": f"the model misses {names}",
            "unexplained": "the residual is structured, but no known effect explains it" + trend,
            }.get(d.verdict, d.verdict)


def _discovery(r) -> str:
    d = r.discovery
    if d is None:
        why = r.stage_errors.get("discover", "stage not in this pipeline")
        return f"<p>No discovery ({_e(why)}).</p>"
    cls = {"effect_found": "warn", "none": "ok", "unexplained": "bad"}.get(d.verdict, "")
    before, after = d.rmse_before_mm3_s, d.rmse_after_mm3_s
    out = [f"<p>Verdict: <b class='{cls}'>{_e(verdict_words(d))}</b>.</p>",
           f"<table><tr><th class='l'>held-out runs</th><th>flow RMSE before [{MM3_S}]</th>"
           f"<th>flow RMSE after [{MM3_S}]</th><th>change [%]</th></tr>"
           f"<tr><td class='l'>{_plural(int(d.n_heldout_runs), 'run')} ({_e(d.holdout)})</td>"
           f"<td>{_fmt(before)}</td><td>{_fmt(after)}</td><td>{_fmt(-100 * d.improvement, 3)}</td>"
           "</tr></table>"]
    if d.effects:
        rows = "".join(
            f"<tr><td class='l'>{_e(e.name)}</td><td class='l'>{_e(e.side)}</td>"
            f"<td class='l'>{_e(e.sentence())}</td><td class='l'>{_effect_params(e)}</td>"
            f"<td>{_fmt(e.p_value, 3)}</td><td>{_fmt(e.f_p_value, 3)}</td></tr>"
            for e in d.effects)
        out.append("<table><tr><th class='l'>effect</th><th class='l'>side</th><th class='l'>meaning</th>"
                   "<th class='l'>parameters (95 % Wald interval)</th><th>permutation p</th>"
                   "<th>F-test p</th></tr>" + rows + "</table>")
    if getattr(d, "validation", None):
        out.append(_closed_loop_before_after(d.validation))
    text = "\n".join(line for line in d.report().splitlines()
                     if not line.startswith("Closed loop (validate"))
    out.append(f"<pre>{_e(text)}</pre>")
    out.append(_figure_links(r, "discovery"))
    return "".join(out)


def _param_units(effect) -> dict[str, str]:
    """{parameter: unit} of an effect's parameters, from its JSON form
    (``params_units``; empty when it has none)."""
    try:
        units = effect.to_json_dict().get("params_units") or {}
    except (AttributeError, TypeError):
        return {}
    return {str(k): str(v) for k, v in units.items()}


def _effect_params(effect) -> str:
    """'step = 0.005 [-] [0.0048, 0.0051]; every = 3 (no interval)'."""
    units = _param_units(effect)
    parts = []
    for k, v in effect.params.items():
        unit = f" {_e(_unit(units[k]))}" if units.get(k) not in (None, "", "-") else ""
        parts.append(f"{_e(k)} = {_fmt(v)}{unit} {_ci(effect.params_ci95.get(k))}")
    return "<br>".join(parts)


def _figures_section(r) -> str:
    drawn = _drawn(r)
    if not drawn:
        why = r.stage_notes.get("figures") or r.stage_errors.get("figures") or "none drawn"
        return f"<p>No figure ({_e(why)}).</p>"
    return "".join(_figure_block(fig, paths) for fig, paths in drawn)


def _closed_loop_before_after(validation: dict) -> str:
    """Mean closed-loop fit per controller, identified vs augmented model
    (read from discovery's ``validation`` dict by :func:`_metric`)."""
    before, after = validation.get("before") or {}, validation.get("after") or {}
    if not isinstance(before, dict) or not isinstance(after, dict):
        return ""
    metrics = (("fit_position_pct", "position fit", "%"), ("rmse_position_mm", "position RMSE", "mm"),
               ("fit_flow_pct", "flow fit", "%"), ("rmse_flow_mm3_s", "flow RMSE", MM3_S))
    if any(_metric(m, "rmse_flow_segments_mm3_s") is not None
           for m in (*before.values(), *after.values())):
        metrics += (("fit_flow_segments_pct", "flow fit per segment", "%"),
                    ("rmse_flow_segments_mm3_s", "flow RMSE per segment", MM3_S))
    head = "".join(f"<th>{_e(name)}, identified [{unit}]</th><th>{_e(name)}, augmented [{unit}]</th>"
                   for _, name, unit in metrics)
    rows = []
    for ctrl in sorted(set(before) | set(after)):
        b, a = before.get(ctrl) or {}, after.get(ctrl) or {}
        cells = "".join(f"<td>{_fmt(_metric(b, key))}</td><td>{_fmt(_metric(a, key))}</td>"
                        for key, _, _ in metrics)
        rows.append(f"<tr><td class='l'>{_e(ctrl)}</td>{cells}</tr>")
    return ("<p>Closed loop (free-run simulation of the position-control runs; per segment: "
            "each reference step and load change re-run from the logged state), mean per "
            "controller, identified model vs augmented model:</p>"
            f"<table><tr><th class='l'>controller</th>{head}</tr>" + "".join(rows) + "</table>")


def _metric(means: Any, key: str) -> Any:
    """``means[key]`` of one controller's mean metrics in discovery's
    ``validation`` dict (validate's column names); None when absent. The one
    place the report reads that dict's keys."""
    return means.get(key) if isinstance(means, dict) else None


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


def render_report(result: Any) -> str:
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
        - ``flowfit``, ``identify`` (optional attribute), ``tracking``, ``validation``,
          ``validation_augmented``, ``discovery``: stage results, None when the
          stage did not run
        - ``figures``: {registered figure name: written paths}
        - ``stage_errors``, ``stage_notes`` ({stage: one line}), ``warnings``
        - ``input_hashes`` ({file: sha256}), ``manifest_path`` (or None),
          ``timings_s``, ``computed``, ``cached`` ({stage: number})

    Figures appear in the order of :data:`seanv_analysis.plots.FIGURES`, each
    with its registered title as caption.
    """
    r = result
    sections = [("overview", "Overview", _overview(r)),
                ("flowfit", "Identified flow model (eq. 5)", _flowfit(r)),
                ("identify", "The rig identified from its logs", _identify(r)),
                ("tracking", "Flow tracking during position control (Sec. III-C)", _tracking(r)),
                ("validation", "Closed-loop validation", _validation(r)),
                ("discovery", "Discovery: what the model misses", _discovery(r)),
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


def write_report(result: Any, path: str | Path) -> Path:
    """Write ``report.html`` (atomically) and return its path.

    Parameters
    ----------
    result : the record of a pipeline run, as for :func:`render_report`
        (stages that did not run are shown as such)
    path : output file

    Examples
    --------
    >>> write_report(result, "outputs/flow/run-paper/report.html")  # doctest: +SKIP
    """
    return write_text_atomic(Path(path), render_report(result))
