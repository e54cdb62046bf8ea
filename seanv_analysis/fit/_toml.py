"""Minimal TOML writer for model files (nested tables of numbers, strings,
booleans and flat lists). The standard library reads TOML but does not write it."""
from __future__ import annotations

import json
import math
from typing import Any, Mapping

__all__ = ["dumps_toml"]


def _value(v: Any) -> str:
    if v is None:  # only inside lists (None keys are left out): TOML has no null
        return "nan"
    if v is None:  # TOML has no null: a missing number (e.g. no interval) is nan
        return "nan"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)  # a JSON string is a valid TOML basic string
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if hasattr(v, "item"):  # numpy scalar
        return _value(v.item())
    raise TypeError(f"value {v!r}: expected a number, string, bool or list for TOML")


def _key(k: str) -> str:
    return k if k.replace("_", "").replace("-", "").isalnum() else json.dumps(k)


def _table(d: Mapping[str, Any], prefix: str, lines: list[str]) -> None:
    subs = []
    for k, v in d.items():
        if v is None:
            continue
        if isinstance(v, Mapping):
            subs.append((k, v))
        else:
            lines.append(f"{_key(k)} = {_value(v)}")
    for k, v in subs:
        name = f"{prefix}.{_key(k)}" if prefix else _key(k)
        lines.append("")
        lines.append(f"[{name}]")
        _table(v, name, lines)


def dumps_toml(d: Mapping[str, Any], *, header: str = "") -> str:
    """TOML text of a nested dict (None values are left out; None in a list is nan).

    Examples
    --------
    >>> print(dumps_toml({"a": 1.5, "t": {"b": "x"}}))
    a = 1.5
    <BLANKLINE>
    [t]
    b = "x"
    <BLANKLINE>
    """
    lines = [f"# {line}" for line in header.splitlines()] if header else []
    _table(d, "", lines)
    return "\n".join(lines) + "\n"
