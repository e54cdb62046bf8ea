"""The paper's exclusion filters on the per-run summary (Sec. II-D.2).

A flow-step run is excluded from the flow fit for one reason, checked in
this order (the first that applies is recorded; later ones that also apply
are listed in the detail text):

1. ``cam_range``: commanded cam outside ``analysis.cam_range_deg``
   (inclusive bounds are kept). The model is not valid there, whatever the
   flow, so this comes first.
2. ``invalid``: a value the fit or a later filter needs is NaN or infinite
   (``q_mm3_s``, ``dp_mpa``, ``p1_mpa``, ``cam_deg``; ``load_mpag`` on the
   drain side), or the side is not 'supply'/'drain'. The flow filters
   cannot judge such a run.
3. ``leakage``: ``|Q| <= analysis.leakage_flow_mm3_s`` (50 mm^3/s): no flow
   beyond internal leakage, on either side.
4. ``friction``: drain side with ``load_mpag <= analysis.friction_load_max_mpag``
   (0.2 MPaG) and ``|Q| <= analysis.friction_flow_mm3_s`` (500 mm^3/s):
   actuator friction, not the valve, limits the flow.

Both threshold comparisons are inclusive (a flow of exactly 50 mm^3/s is
leakage, a load of exactly 0.2 MPaG counts as low). Only ``kind ==
'flow_step'`` rows are judged; other rows get ``excluded = ''``.
Thresholds come from the rig config only.
"""
from __future__ import annotations

import math
from typing import Any, Mapping

import numpy as np
import pandas as pd

from ..errors import ConfigError, DataError

__all__ = ["EXCLUSION_REASONS", "apply_filters", "exclusion_counts"]

#: Exclusion reasons in precedence order.
EXCLUSION_REASONS = ("cam_range", "invalid", "leakage", "friction")

_NEEDED = ("side", "q_mm3_s", "dp_mpa", "p1_mpa", "cam_deg", "load_mpag")


def _thresholds(rig: Any) -> dict[str, float]:
    try:
        a = rig.analysis
        lo, hi = (float(v) for v in a["cam_range_deg"])
        out = {"leak": float(a["leakage_flow_mm3_s"]),
               "load": float(a["friction_load_max_mpag"]),
               "fric": float(a["friction_flow_mm3_s"]), "cam_lo": lo, "cam_hi": hi}
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise ConfigError(f"rig: [analysis] needs leakage_flow_mm3_s, friction_load_max_mpag, "
                          f"friction_flow_mm3_s and cam_range_deg = [min, max] ({exc})") from None
    if lo > hi:
        raise ConfigError(f"rig: analysis.cam_range_deg {[lo, hi]} has min > max")
    return out


def _num(row: Mapping[str, Any], col: str) -> float:
    try:
        return float(row[col])
    except (KeyError, TypeError, ValueError):
        return math.nan


def _reasons(row: Mapping[str, Any], th: dict[str, float]) -> list[tuple[str, str]]:
    """Every reason that applies to one flow-step row ({column: value}), in
    precedence order."""
    out: list[tuple[str, str]] = []
    q, cam, load = _num(row, "q_mm3_s"), _num(row, "cam_deg"), _num(row, "load_mpag")
    side = row.get("side", "")
    if math.isfinite(cam) and not th["cam_lo"] <= cam <= th["cam_hi"]:
        out.append(("cam_range", f"cam {cam:g} deg outside [{th['cam_lo']:g}, {th['cam_hi']:g}] "
                                 "deg"))
    bad = [c for c in ("q_mm3_s", "dp_mpa", "p1_mpa", "cam_deg")
           if not math.isfinite(_num(row, c))]
    if side == "drain" and not math.isfinite(load):
        bad.append("load_mpag")
    if side not in ("supply", "drain"):
        out.append(("invalid", f"side {side!r}; expected 'supply' or 'drain'"))
    elif bad:
        vals = ", ".join(f"{c} = {_num(row, c)}" for c in bad)
        out.append(("invalid", f"{vals}; expected finite numbers"))
    if math.isfinite(q) and abs(q) <= th["leak"]:
        out.append(("leakage", f"|Q| = {abs(q):.1f} mm^3/s <= {th['leak']:g} mm^3/s"))
    if (side == "drain" and math.isfinite(q) and math.isfinite(load) and load <= th["load"]
            and abs(q) <= th["fric"]):
        out.append(("friction", f"drain, load {load:g} MPaG <= {th['load']:g} MPaG and "
                                f"|Q| = {abs(q):.1f} mm^3/s <= {th['fric']:g} mm^3/s"))
    return out


def apply_filters(summary: pd.DataFrame, rig: Any) -> pd.DataFrame:
    """Mark the runs the paper's filters exclude from the flow fit.

    Parameters
    ----------
    summary : per-run summary (``io.run.SUMMARY_COLUMNS``; at least
        ``q_mm3_s`` [mm^3/s], ``dp_mpa`` [MPa], ``p1_mpa`` [MPa], ``cam_deg``
        [deg], ``side``, ``load_mpag`` [MPaG]; ``kind`` optional, all rows
        are taken as flow steps without it)
    rig : :class:`~seanv_analysis.config.RigConfig`; thresholds from
        ``rig.analysis``: ``leakage_flow_mm3_s``, ``friction_load_max_mpag``,
        ``friction_flow_mm3_s``, ``cam_range_deg``

    Returns
    -------
    DataFrame
        A copy with ``excluded`` ('' or one of :data:`EXCLUSION_REASONS`) and
        ``excluded_detail`` (the numbers behind it, e.g. ``"leakage: |Q| =
        42.0 mm^3/s <= 50 mm^3/s"``, plus ``"(also: friction)"`` when other
        reasons apply too). Rows of other kinds get '' in both.

    Raises
    ------
    ConfigError
        the rig's ``[analysis]`` lacks a threshold.
    DataError
        ``summary`` lacks a needed column.

    Notes
    -----
    Precedence (first that applies wins): cam_range, invalid, leakage,
    friction; see the module docstring for why. Comparisons: cam inside
    ``[min, max]`` inclusive is kept; ``|Q| <= leakage`` is leakage;
    ``load <= friction_load_max`` and ``|Q| <= friction_flow`` is friction.

    Examples
    --------
    >>> from seanv_analysis.config import load_rig
    >>> s = pd.DataFrame({"kind": ["flow_step"] * 2, "side": ["supply", "drain"],
    ...                   "q_mm3_s": [40.0, -300.0], "dp_mpa": [1.7, 0.6],
    ...                   "p1_mpa": [3.3, 0.6], "cam_deg": [-8.0, -30.0],
    ...                   "load_mpag": [0.35, 0.15]})
    >>> apply_filters(s, load_rig())["excluded"].tolist()
    ['leakage', 'friction']
    """
    th = _thresholds(rig)
    missing = [c for c in _NEEDED if c not in summary.columns]
    if missing:
        raise DataError(f"summary has no column(s) {', '.join(missing)}; expected the "
                        "per-run summary columns", column=missing[0])
    out = summary.copy()
    excluded: list[str] = []
    detail: list[str] = []
    # plain {column: value} rows of the columns judged (iterrows built a Series per row)
    judged = [c for c in ("kind", *_NEEDED) if c in out.columns]
    for row in out[judged].to_dict("records"):
        if "kind" in row and row["kind"] != "flow_step":
            excluded.append("")
            detail.append("")
            continue
        reasons = _reasons(row, th)
        if not reasons:
            excluded.append("")
            detail.append("")
            continue
        name, text = reasons[0]
        also = [r for r, _ in reasons[1:] if r != name]
        excluded.append(name)
        detail.append(f"{name}: {text}" + (f" (also: {', '.join(also)})" if also else ""))
    out["excluded"] = np.array(excluded, dtype=object)
    out["excluded_detail"] = np.array(detail, dtype=object)
    return out


def exclusion_counts(summary: pd.DataFrame) -> dict[str, int]:
    """Runs excluded for each reason: ``{"leakage": n, "friction": n,
    "cam_range": n, "invalid": n}`` (every key present, 0 when none).

    Parameters
    ----------
    summary : output of :func:`apply_filters` (column ``excluded``)

    Raises
    ------
    DataError
        no ``excluded`` column, or a value that is not a known reason.
    """
    if "excluded" not in summary.columns:
        raise DataError("summary has no 'excluded' column; expected the output of "
                        "apply_filters", column="excluded")
    values = summary["excluded"].fillna("").astype(str)
    unknown = sorted(set(values) - set(EXCLUSION_REASONS) - {""})
    if unknown:
        raise DataError(f"unknown exclusion reason(s) {unknown}; expected '' or one of "
                        f"{', '.join(EXCLUSION_REASONS)}", column="excluded")
    counts = values.value_counts()
    return {k: int(counts.get(k, 0)) for k in ("leakage", "friction", "cam_range", "invalid")}
