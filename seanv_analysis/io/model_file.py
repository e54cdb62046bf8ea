"""Valve model files: the ``model.json`` / ``model.toml`` that ``flowfit``
writes and ``--model`` of the other commands reads.

The content is :meth:`ValveModel.to_dict` (schema ``seanv-valve-model/1``):
per side z0 [mm], C [mm^3/(s deg^2 MPa^n)], n and the needle geometry
(paper eq. 3-5, Table II), and the valid cam range [deg]. The models layer
builds and serialises the object; reading and writing the file is here.
"""
from __future__ import annotations

import json
import math
import tomllib
from pathlib import Path
from typing import Any, Mapping

from ..errors import ConfigError
from ..models import ValveModel
from .atomic import write_text_atomic

__all__ = ["read_model", "write_model_toml", "dumps_toml"]


def read_model(path: str | Path, *, rig: Any) -> ValveModel:
    """Read a valve model file (``.toml``, else JSON).

    ``rig`` (a :class:`~seanv_analysis.config.RigConfig`) supplies the needle
    geometry of a side and the cam range when the file leaves them out
    (a hand-written file may give only z0 [mm] and C per side).

    Raises
    ------
    ConfigError
        the file is missing or is not a valve model file (the message names it).
    """
    path = Path(path)
    try:
        if path.suffix == ".toml":
            with open(path, "rb") as fh:
                d = tomllib.load(fh)
        else:
            d = json.loads(path.read_text())
        model = ValveModel.from_dict(d, rig=rig)
        for side in (model.supply, model.drain):
            # builds the eq. (4) table now, so a bad geometry is reported with the file
            side.geometry.angle_for_height(0.0)
        return model
    except FileNotFoundError:
        raise ConfigError(f"{path}: model file not found") from None
    except (KeyError, TypeError, ValueError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"{path}: not a valve model file ({exc})") from None


def write_model_toml(path: str | Path, model: ValveModel, *, header: str = "") -> Path:
    """Write ``model`` as TOML (:meth:`ValveModel.to_dict`), atomically; returns the path.

    ``header`` becomes ``#`` comment lines at the top (e.g. the units).
    """
    return write_text_atomic(path, dumps_toml(model.to_dict(), header=header))


# The standard library reads TOML but does not write it; model files need
# only nested tables of numbers, strings, booleans and flat lists.

def _value(v: Any) -> str:
    if v is None:  # only inside lists (None keys are left out): TOML has no null
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
