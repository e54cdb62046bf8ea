"""Formatting shared by the report's sections: escaping, numbers, intervals,
units, tables and the figures drawn (embedded and linked). Pure functions of
what they are given; nothing here knows a stage or a result."""
from __future__ import annotations

import base64
import html
import math
import re
from pathlib import Path
from typing import Any, Iterable

import pandas as pd

from ..plots import FIGURES, Figure
from ..units import UNIT_SUFFIXES


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


#: why a fit's interval is missing, unless the caller knows better
FIT_NO_INTERVAL = "singular covariance / too few runs"


def _ci(ci: Any, digits: int = 4, *, why: str | None = FIT_NO_INTERVAL) -> str:
    """'[lo, hi]', or 'no interval' with ``why`` (None: no reason given here,
    e.g. where a note beside it says it)."""
    try:
        lo, hi = (float(c) for c in ci)
    except (TypeError, ValueError):
        return "<span class='warn'>no interval</span>"
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return f"<span class='warn'>no interval{f' ({_e(why)})' if why else ''}</span>"
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
            "started_at": "started (UTC)", "lag_s": "delay estimate [s]", "target_source": "target Q_ref",
            "lag_ci95_lo_s": "delay estimate 95 % interval, low [s]",
            "lag_ci95_hi_s": "delay estimate 95 % interval, high [s]", "shift_s": "delay compensated (shift) [s]",
            "rmse_mm3_s": f"RMSE [{MM3_S}]", "bias_mm3_s": f"bias [{MM3_S}]",
            "rmse_supply_mm3_s": f"RMSE, supply targets [{MM3_S}]",
            "rmse_drain_mm3_s": f"RMSE, drain targets [{MM3_S}]", "n_samples": "samples",
            "theta_d_deg": "θ_d [deg]", "theta_d_se_deg": "θ_d standard error [deg]",
            "theta_d_model_deg": "θ_d of the model [deg]", "alpha_mm3_s_deg2": f"α [{ALPHA_UNIT}]",
            "alpha_se_mm3_s_deg2": f"α standard error [{ALPHA_UNIT}]",
            "alpha_model_mm3_s_deg2": f"α of the model [{ALPHA_UNIT}]", "success": "fit converged",
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


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: what an SVG of matplotlib never holds and an embedded one must not:
#: scripts, event handlers, foreign HTML, links other than to itself or data images
_SVG_ACTIVE = re.compile(r"<\s*(script|foreignobject|iframe|object|embed)\b|javascript:"
                         r"|\son[a-z]+\s*=|href\s*=\s*[\"'](?!#|data:image/)", re.IGNORECASE)


def _figure_bytes(path: Path, root: Path | None) -> bytes | None:
    """The bytes of a figure file to embed: a regular file (not a link)
    inside the output folder ``root`` (when given); else None."""
    from ..io.readback import read_back

    return read_back(path, root=root if root is not None else path.parent,
                     max_bytes=64 << 20)


def _figure(path: Path, caption: str = "", root: Path | None = None) -> str:
    """A figure embedded in the page: PNG as base64, SVG inline. Only the
    output folder's own files are embedded (``root``: regular files, not
    links, inside it): a PNG that is a PNG, an SVG without script, event
    handlers or outside links."""
    path = Path(path)
    png = path.with_suffix(".png")
    cap = f"<figcaption>{_e(caption or path.stem)}</figcaption>"
    raw = _figure_bytes(png, root)
    if raw is not None and raw.startswith(_PNG_SIGNATURE):
        data = base64.b64encode(raw).decode("ascii")
        return (f"<figure><img alt='{_e(path.stem)}' src='data:image/png;base64,{data}'>"
                f"{cap}</figure>")
    raw = _figure_bytes(path.with_suffix(".svg"), root)
    if raw is not None:
        text = raw.decode("utf-8", errors="replace")
        start = text.find("<svg")
        if start >= 0 and not _SVG_ACTIVE.search(text):
            return f"<figure>{text[start:]}{cap}</figure>"
    return ""


def _figures(paths: Iterable[Path], caption: str = "", root: Path | None = None) -> str:
    seen, out = set(), []
    for p in paths:
        stem = Path(p).with_suffix("")
        if stem in seen or Path(p).suffix not in (".png", ".svg"):
            continue
        seen.add(stem)
        out.append(_figure(Path(p), caption or Path(p).stem, root))
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


def _figure_block(fig: Figure, paths: list[Path], root: Path | None = None) -> str:
    """One registered figure: its title as heading and caption. A data-set
    figure's main file is ``<name>.<format>``; its other files (one per run,
    as Fig. 7 writes) are folded away. A per-run figure is a grid, each file
    captioned with its name. ``root``: the output folder (only its files are embedded)."""
    head = f"<h3 id='fig-{_e(fig.name)}'>{_e(fig.title)}</h3>"
    if fig.per_run:
        return head + f"<div class='grid'>{_figures(paths, root=root)}</div>"
    main = [p for p in paths if p.stem == fig.name]
    if not main:
        return head + _figures(paths, fig.title, root)
    rest = [p for p in paths if p.stem != fig.name]
    out = head + _figures(main, fig.title, root)
    if rest:
        out += (f"<details><summary>{_e(fig.title)}: one figure per run</summary>"
                f"<div class='grid'>{_figures(rest, root=root)}</div></details>")
    return out


def _figure_links(r, section: str) -> str:
    """Links to the drawn figures whose first need is this section's result."""
    links = [f"<a href='#fig-{_e(fig.name)}'>{_e(fig.title)}</a>"
             for fig, _ in _drawn(r) if fig.needs[0] == section]
    return f"<p>Figures: {'; '.join(links)}.</p>" if links else ""
