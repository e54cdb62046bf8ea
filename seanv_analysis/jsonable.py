"""JSON the way every result of the package writes it (core layer), and
how results show in Jupyter (:class:`JsonResult`).

Strict JSON only: NaN and infinities become ``null``, numpy scalars and
arrays plain numbers and lists, paths strings, integers stay integers.
Every result that has a ``--json`` contract defines ``to_json_dict()``;
:class:`JsonResult` adds ``to_json() -> str`` on top (as pandas does).
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

__all__ = ["json_num", "clean_json", "dumps", "JsonResult", "UNIT_SUFFIXES", "unit_of_key",
           "unit_suffix"]

#: The units of the numbers the package writes: a number's unit is the end
#: of its key (``data_schema/json/common.schema.json``), key suffix -> unit
#: in plain text. The HTML report prints it in column headers, results that
#: name keys after a unit take the suffix here (:func:`unit_suffix`) and the
#: JSON Schema tests check every number's key against it. A suffix comes
#: before the shorter ones it ends with (``_mm3_s`` before ``_s``), so the
#: first suffix a key ends with is its unit (:func:`unit_of_key`); of two
#: suffixes of one unit, the first is the one new keys get.
UNIT_SUFFIXES: dict[str, str] = {
    "_mm3_s_deg2_sqrtMPa": "mm^3/(s deg^2 MPa^0.5)",   # C of eq. (5)
    "_mm3_s_deg2": "mm^3/(s deg^2)",                   # alpha of Q = alpha (theta - theta_d)^2
    "_mm3_s_per_mm": "mm^3/s per mm",
    "_deg_per_mm": "deg/mm",
    "_mm3_s": "mm^3/s",
    "_mpag": "MPaG",
    "_MPa": "MPa",
    "_mpa": "MPa",
    "_pct": "%",
    "_frac": "fraction",
    "_deg": "deg",
    "_mm": "mm",
    "_kg": "kg",
    "_hz": "Hz",
    "_m": "m",
    "_s": "s",
    "_N": "N",
    "_n": "N",
}


def unit_of_key(key: str) -> tuple[str, str] | None:
    """(name, unit) of a key ending in a unit suffix of :data:`UNIT_SUFFIXES`
    (``'rmse_mm3_s'`` -> ``('rmse', 'mm^3/s')``), else None (a bare suffix
    is no name: ``'_s'`` -> None)."""
    for suffix, unit in UNIT_SUFFIXES.items():
        if key.endswith(suffix) and len(key) > len(suffix):
            return key[:-len(suffix)], unit
    return None


def unit_suffix(unit: str) -> str | None:
    """The key suffix of a plain-text ``unit`` (``'mm^3/s'`` -> ``'_mm3_s'``,
    ``'MPa'`` -> ``'_MPa'``), None for a unit :data:`UNIT_SUFFIXES` lacks."""
    return next((suffix for suffix, u in UNIT_SUFFIXES.items() if u == unit), None)


def json_num(x: Any) -> float | None:
    """A finite float, or None (JSON null) for NaN/inf/None/non-numbers."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def clean_json(x: Any) -> Any:
    """``x`` made strict-JSON ready, recursively (dicts, lists, tuples)."""
    if isinstance(x, dict):
        return {str(k): clean_json(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [clean_json(v) for v in x]
    if isinstance(x, bool) or x is None or isinstance(x, str):
        return x
    if isinstance(x, int):
        return int(x)
    if isinstance(x, float):
        return json_num(x)
    if isinstance(x, Path):
        return str(x)
    tolist = getattr(x, "tolist", None)  # numpy scalar or array
    if callable(tolist):
        return clean_json(tolist())
    return x


def dumps(obj: Any, *, indent: int | None = None) -> str:
    """Strict JSON text of ``obj`` (see :func:`clean_json`); raises TypeError
    for an object JSON cannot hold."""
    return json.dumps(clean_json(obj), indent=indent, allow_nan=False)


class JsonResult:
    """Mixin for results: ``to_json()`` is the text of ``to_json_dict()``,
    the stable contract the CLI's ``--json`` prints."""

    def to_json_dict(self) -> dict[str, Any]:  # pragma: no cover - overridden
        raise NotImplementedError

    def to_json(self, *, indent: int | None = None) -> str:
        """The ``--json`` contract as strict JSON text (NaN -> null)."""
        return dumps(self.to_json_dict(), indent=indent)

    def _repr_html_(self) -> str:
        """Jupyter: the one-line repr as a caption over ``to_frame()``'s
        table, or over the plain-text ``report()``."""
        import html

        head = f"<p><b>{html.escape(repr(self))}</b></p>"
        to_frame = getattr(self, "to_frame", None)
        if callable(to_frame):
            frame = to_frame()
            if len(frame):
                return head + frame.to_html(float_format=lambda v: f"{v:.4g}")
        report = getattr(self, "report", None)
        return head + (f"<pre>{html.escape(report())}</pre>" if callable(report) else "")
