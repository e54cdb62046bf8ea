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

from .units import UNIT_SUFFIXES, unit_of_key, unit_suffix  # noqa: F401  (re-exported)

__all__ = ["json_num", "clean_json", "dumps", "JsonResult", "UNIT_SUFFIXES", "unit_of_key",
           "unit_suffix"]

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
