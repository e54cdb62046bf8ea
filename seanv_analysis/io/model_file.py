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
from dataclasses import fields
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..errors import ConfigError
from ..models import ValveModel
from .atomic import write_text_atomic

__all__ = ["read_model", "read_model_file", "write_model_toml", "dumps_toml"]


def read_model(path: str | Path, *, rig: Any) -> ValveModel:
    """Read a valve model file (``.toml``, else JSON) for a command that uses
    the valve alone (tracking, discover).

    ``rig`` (a :class:`~seanv_analysis.config.RigConfig`) supplies the needle
    geometry of a side and the cam range when the file leaves them out
    (a hand-written file may give only z0 [mm] and C per side).

    Raises
    ------
    ConfigError
        the file is missing or not a valve model file (:func:`read_model_file`),
        or it holds effects or a proposed term (discover's
        ``model_augmented.json``), which a valve alone cannot carry: refused,
        never ignored.
    """
    model, effects = read_model_file(path, rig=rig)
    if effects:
        raise ConfigError(f"{path}: holds effects or a proposed term ({', '.join(effects)}), "
                          "which this command cannot apply; expected a valve model (flowfit's "
                          "model.json / model.toml), or use `validate --model`, which applies them")
    return model


def read_model_file(path: str | Path, *, rig: Any) -> tuple[ValveModel, tuple[str, ...]]:
    """Read a valve model file and the effects it carries.

    The file is checked against the model schema
    (``_data_schema/model/schema.toml``: known keys, types, finite values in
    range, schema version, the cam range increasing, a side's geometry whole);
    discover's ``effects`` become simulator effect specs
    (:func:`seanv_analysis.models.effects.parse_effect`), its ``proposed_term``
    a ``term:`` spec, last.

    Returns
    -------
    (ValveModel, effect specs)

    Raises
    ------
    ConfigError
        the file is missing, not a regular file, not TOML/JSON, or not a valve
        model file (one line naming the file, the key, the value and what is
        expected).
    """
    from ..config import check_document, read_toml
    from ..models import effects as fx
    from ..models.sealing import NeedleGeometry

    path = Path(path)
    d = read_toml(path, what="model file") if path.suffix == ".toml" else _read_json(path)
    where = str(path)
    if not isinstance(d, dict):
        raise ConfigError(f"{path}: not a valve model file (a {type(d).__name__}, expected "
                          "an object with supply and drain)")
    d = dict(d)
    for side in ("supply", "drain"):
        s = d.get(side)
        if isinstance(s, dict) and "C" in s:
            if "c_flow" in s:
                raise ConfigError(f"{path}: {side} gives both C and c_flow; expected one")
            d[side] = {("c_flow" if k == "C" else k): v for k, v in s.items()}
    check_document(d, "model", where=f"{where}: not a valve model file")
    geometry_keys = {f.name for f in fields(NeedleGeometry)}
    for side in ("supply", "drain"):
        geom = d[side].get("geometry")
        if geom is not None and set(geom) != geometry_keys:
            raise ConfigError(f"{path}: {side}.geometry lacks "
                              f"{', '.join(sorted(geometry_keys - set(geom)))}; expected all of "
                              f"{', '.join(sorted(geometry_keys))} (or no geometry: the rig's)")
    specs = []
    for i, e in enumerate(d.get("effects", [])):
        try:
            if not isinstance(e, dict) or not isinstance(e.get("params", {}), dict):
                raise ValueError("expected a table with name, side and params")
            cls = fx.EFFECTS.get(e.get("name"))
            if cls is None or not cls.VOCABULARY:
                raise ValueError(f"unknown effect {e.get('name')!r}; expected one of "
                                 f"{', '.join(c.name for c in fx.vocabulary_effects())}")
            specs.append(cls.from_fit(str(e.get("side", "both")), e.get("params", {})).spec())
        except (ValueError, TypeError, KeyError) as exc:
            raise ConfigError(f"{path}: effects[{i}]: {' '.join(str(exc).split())}") from None
    term = d.get("proposed_term")
    if term is not None:
        try:
            if fx.parse_effect(term).name != "term":
                raise ValueError("expected a term:side=...,mode=...,expr=... spec")
        except (ValueError, TypeError, KeyError) as exc:
            raise ConfigError(f"{path}: proposed_term = {term[:60]!r}: "
                              f"{' '.join(str(exc).split())}") from None
        specs.append(term)
    try:
        model = ValveModel.from_dict(d, rig=rig)
        for side in (model.supply, model.drain):
            # builds the eq. (4) table now, so a bad geometry is reported with the file
            side.geometry.angle_for_height(0.0)
            if not np.all(np.isfinite(side.geometry.height_table[0])):
                raise ValueError(f"{side.side}: the geometry gives no finite eq. (4) table")
    except (KeyError, TypeError, ValueError, ArithmeticError) as exc:
        raise ConfigError(f"{path}: not a valve model file ({' '.join(str(exc).split())})") \
            from None
    if not model.cam_min_deg < model.cam_max_deg:   # the rig's, when the file has none
        raise ConfigError(f"{path}: cam range [{model.cam_min_deg}, {model.cam_max_deg}] is "
                          "not increasing")
    return model, tuple(specs)


def _read_json(path: Path) -> Any:
    """A JSON model file's document (:func:`~seanv_analysis.config.read_config_bytes`)."""
    from ..config import read_config_bytes

    raw = read_config_bytes(path, what="model file")
    try:
        return json.loads(raw)
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not a valve model file (not UTF-8: byte {exc.start})") from None
    except RecursionError:
        raise ConfigError(f"{path}: not a valve model file (nested too deeply)") from None
    except ValueError as exc:
        raise ConfigError(f"{path}: not a valve model file (not JSON: {exc})") from None


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
