"""The report's section of each stage result: the flow fit, the identified
rig, tracking, the closed-loop validation and discovery. Each stage module
names its section once (``SECTION`` in :mod:`seanv_analysis.stages`); the
report renders the sections the catalogue gives it, in its order.

Each ``*_section(r)`` reads the pipeline record ``r`` (results by name:
``r.flowfit``, ``r.discovery``... None when absent) and returns HTML; a
``*_cards(r)`` gives the overview's key numbers of that result.
"""
from __future__ import annotations

from typing import Any

from ..models import effects as fx
from ..plots import Figure
from ._format import (
    C_UNIT,
    MM3_S,
    _ci,
    _drawn,
    _e,
    _figure_links,
    _fmt,
    _plural,
    _superscripts,
    _table,
    _unit,
)

__all__ = ["flowfit_section", "identify_section", "tracking_section", "tracking_cards",
           "validation_section", "discovery_section", "discovery_cards", "verdict_words"]


def flowfit_section(r) -> str:
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
            f"<td class='l'>{_side_verdict(f, r.discovery, getattr(fit, 'flow_method', ''))}</td></tr>")
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
    if getattr(fit, "flow_method", "") == "peak":   # the biased estimate: said first
        from ..fit import PEAK_BIAS

        notes.insert(0, f"<span class='warn'>{_e(PEAK_BIAS)}.</span>")
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


def _side_verdict(f, discovery, flow_method: str = "") -> str:
    """The model table's verdict cell of one side: flowfit's status
    (``SideFit.status``: failed / lack of fit / ok) and discovery's findings;
    green "ok" only when neither flags the side."""
    status = getattr(f, "status", None) or ("ok" if f.success else "failed")
    flags = _side_findings(f.side, discovery)
    if flow_method == "peak":
        flags.insert(0, "on the biased 'peak' flow estimate (note below)")
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


def identify_section(r) -> str:
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
                    f"</td><td>{_fmt(c.value)}</td><td>{_ci(c.ci95, why=None)}</td>"
                    f"<td>{_fmt(c.default)}</td>"
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


def tracking_section(r) -> str:
    tr = r.tracking
    out = []
    if tr is None:
        why = r.stage_errors.get("tracking") or r.stage_notes.get("tracking") or "stage not in this pipeline"
        out.append(f"<p>No tracking result ({_e(why)}).</p>")
    else:
        ci = tr.lag_ci95_s
        lag = (f"{_fmt(tr.lag_s, 3)} s (estimated" + (f", 95 % interval {_ci(ci, 3)} s, block "
                                                      "bootstrap" if ci else "") + ")"
               + ("" if tr.shift_source == "estimated"
                  else f"; shift {_fmt(tr.shift_s, 3)} s given"))
        lo, hi = tr.range_mm3_s
        out.append("<table>"
                   f"<tr><td class='l'>flow delay (actual behind target)</td><td>{lag}</td></tr>"
                   f"<tr><td class='l'>RMSE of shifted actual &minus; target, targets in "
                   f"[{_fmt(lo)}, {_fmt(hi)}] {MM3_S}, pooled over the {_e(tr.pooled)} "
                   f"({_e(', '.join(tr.pooled_runs))})</td><td>{_fmt(tr.rmse_mm3_s, 4)} {MM3_S} "
                   f"(paper: 516 {MM3_S}, its run with a commanded Q_ref)</td></tr>"
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


def validation_section(r) -> str:
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


def discovery_section(r) -> str:
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
    """{parameter: unit} of an effect's parameters, from its estimates
    (:attr:`~seanv_analysis.discover.result.EffectFinding.estimates`; empty
    when it has none)."""
    try:
        return {e.quantity: e.unit for e in effect.estimates.values()}
    except (AttributeError, TypeError, ValueError):
        return {}


def _effect_params(effect) -> str:
    """'step = 0.005 [-] [0.0048, 0.0051]; every = 3 (no interval)'."""
    units = _param_units(effect)
    parts = []
    for k, v in effect.params.items():
        unit = f" {_e(_unit(units[k]))}" if units.get(k) not in (None, "", "-") else ""
        parts.append(f"{_e(k)} = {_fmt(v)}{unit} {_ci(effect.params_ci95.get(k))}")
    return "<br>".join(parts)


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


def tracking_cards(r) -> list[tuple[str, str]]:
    """The overview's tracking numbers: RMSE and delay."""
    if r.tracking is None:
        return []
    return [(f"{_fmt(r.tracking.rmse_mm3_s, 3)}",
             f"flow tracking RMSE [mm³/s], {r.tracking.pooled}"),
            (f"{_fmt(r.tracking.shift_s, 3)}", f"flow delay compensated [s], {r.tracking.shift_source}")]


def discovery_cards(r) -> list[tuple[str, str]]:
    """The overview's discovery verdict."""
    if r.discovery is None:
        return []
    cls = "warn" if r.discovery.verdict != "none" else "ok"
    return [(f"<span class='{cls}'>{_e(verdict_words(r.discovery, short=True))}</span>",
             "discovery")]
