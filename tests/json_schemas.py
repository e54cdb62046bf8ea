"""Check a command's JSON output against its schema in data_schema/json/,
and the units rule: every number's unit is the end of its key."""
from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path

from seanv_analysis import jsonable
from seanv_analysis.units import unit_of_key

SCHEMAS = Path(__file__).resolve().parents[1] / "seanv_analysis" / "_data_schema" / "json"
URN = "urn:seanv-analysis:schema:"

#: unit suffixes of keys (the package's table; data_schema/json/common.schema.json
#: says what they mean)
UNIT_SUFFIXES = tuple(jsonable.UNIT_SUFFIXES)
#: dimensionless numbers: counts, p values, ratios, seeds
DIMENSIONLESS = ("n_", "runs", "rows", "p_value", "steps", "seed", "run_index", "z_score",
                 "cam_approach")   # ... an ordinal, a standard score, a direction (+1/-1)
DIMENSIONLESS_END = ("_p", "_ratio", "_runs", "_changes", "_samples")


@lru_cache(maxsize=None)
def _registry():
    from referencing import Registry, Resource

    resources = []
    for path in SCHEMAS.glob("*.schema.json"):
        doc = json.loads(path.read_text())
        resources.append((doc["$id"], Resource.from_contents(doc)))
    return Registry().with_resources(resources)


def check_schema(command: str, doc) -> None:
    """Raise jsonschema.ValidationError when ``doc`` breaks ``command``'s schema."""
    from jsonschema import Draft202012Validator

    schema = _registry().contents(URN + command)
    Draft202012Validator(schema, registry=_registry()).validate(doc)


def _has_unit(key: str) -> bool:
    """The key ends in a unit of the package's table, or in a unit derived
    from it (a proposed term's coefficient: ``value_mm3_per_s_mpa2``;
    :func:`seanv_analysis.units.unit_of_key`)."""
    return key.endswith(UNIT_SUFFIXES) or unit_of_key(key) is not None


def keys_without_unit(doc, path: str = "", key: str = "") -> list[str]:
    """Paths of numbers whose key names no unit and is not a count, p value
    or ratio: every number's unit is the end of its own key (``value_mm``,
    not ``value`` beside ``"unit": "mm"``; but a discover effect's spec,
    ``params`` beside its ``estimates``). ``/pipeline`` (the
    pipeline file echoed), ``/excluded``, ``/computed``, ``/cached`` (counts
    per reason or stage) are not checked; the members of a dict whose own key
    ends in a unit (``timings_s``) take that unit, those of a count
    (``runs_by_kind``, ``rows``) are counts."""
    out: list[str] = []
    if isinstance(doc, dict):
        if _has_unit(key) or key.startswith(DIMENSIONLESS):
            return []  # {name: value} in the unit of its key, or counts
        for k, v in doc.items():
            if k in ("pipeline", "excluded", "computed", "cached") or (
                    k == "params" and "estimates" in doc):
                continue
            out += keys_without_unit(v, f"{path}/{k}", k)
    elif isinstance(doc, list):
        for v in doc:
            # a list's records are checked key by key; its numbers by the list's key
            out += keys_without_unit(v, f"{path}[]", "" if isinstance(v, dict) else key)
    elif isinstance(doc, (int, float)) and not isinstance(doc, bool):
        ok = _has_unit(key) or key.startswith(DIMENSIONLESS) or key.endswith(DIMENSIONLESS_END)
        if not ok and path not in out:
            out.append(path)
    return sorted(set(out))


#: to_frame() columns that are not numbers with a unit: labels, flags, texts
TEXT_COLUMNS = ("run_id", "side", "kind", "status", "target_source", "controller", "name", "key",
                "unit", "identified", "constrained_by", "pooled", "flagged", "path", "dataset")


def columns_without_unit(frame) -> list[str]:
    """Numeric columns of a result's ``to_frame()`` whose name names no unit
    and is not a count, p value or ratio (the JSON's rule). A long table, one
    row per quantity with a ``unit`` column (identify's constants), gives
    each row's numbers in its unit: its value columns are not checked."""
    import pandas as pd

    if "unit" in frame.columns:
        return []
    out = []
    for col in frame.columns:
        name = str(col)
        if name in TEXT_COLUMNS or not pd.api.types.is_numeric_dtype(frame[col]) \
                or pd.api.types.is_bool_dtype(frame[col]):
            continue
        if not (name.endswith(UNIT_SUFFIXES) or name.startswith(DIMENSIONLESS)
                or name.endswith(DIMENSIONLESS_END)):
            out.append(name)
    return out
