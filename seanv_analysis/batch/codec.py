"""Plain-data encoding of cached results (no pickle, no code).

A cached result (a run's, or a data-set stage's: :mod:`.stage_memo`) is a
tree of dicts, lists, tuples, numbers, strings, numpy arrays and scalars,
pandas DataFrames/Series/Timestamps, paths and the dataclasses of the
package's result modules (:data:`DATACLASS_MODULES`). :func:`encode` turns
it into JSON-ready data (arrays and numpy scalars as their raw bytes in
base64, bit-exact: a value decoded has the content digest of the one
encoded, :func:`~seanv_analysis.io.hashing.content_sha256`); :func:`decode`
builds it again. Decoding only ever creates those types: a tag it does not
know, a dataclass of another module, an object dtype, is a
:class:`CodecError` (the cache then recomputes), so whatever a file holds,
reading it runs no code but a listed dataclass's own checks.
"""
from __future__ import annotations

import base64
import dataclasses
import importlib
import math
from pathlib import Path, PurePath
from typing import Any

import numpy as np
import pandas as pd

__all__ = ["encode", "decode", "CodecError", "DATACLASS_MODULES"]


class CodecError(ValueError):
    """A value that cannot be stored as plain data, or a file that is not
    what :func:`encode` writes."""


#: the dataclasses a cached result may hold (explicit allow-list: the
#: results of the per-run work and of the data-set stages): {module: the
#: names of its dataclasses allowed, or None for every dataclass it defines
#: (the result modules; the effects of the model registry)}
DATACLASS_MODULES: dict[str, tuple[str, ...] | None] = {
    "seanv_analysis.analysis.validate": None,
    "seanv_analysis.config": ("RigConfig",),
    "seanv_analysis.discover.result": None,
    "seanv_analysis.discover.static": None,
    "seanv_analysis.fit.flowfit": None,
    "seanv_analysis.fit._leakage": None,
    "seanv_analysis.identify.result": None,
    "seanv_analysis.models.effects": None,
    "seanv_analysis.models.sealing": None,
    "seanv_analysis.models.valve": None,
    "seanv_analysis.stages.base": ("FailedRun",),
    "seanv_analysis.stages.discover": ("DiscoverResult",),
    "seanv_analysis.stages.validate": ("ValidateResult",),
}


def _allowed(module: Any, name: Any) -> bool:
    names = DATACLASS_MODULES.get(module, ()) if isinstance(module, str) else ()
    return isinstance(name, str) and (names is None or name in names)


def _dataclass_of(module: Any, name: Any) -> type:
    """The dataclass ``module.name`` when it is on the allow-list (its module
    imported then, not before: a worker decoding a run's entry needs one)."""
    if not _allowed(module, name) or not name.isidentifier():
        raise CodecError(f"dataclass {module}.{name} is not on the allow-list")
    cls = getattr(importlib.import_module(module), name, None)
    if not (isinstance(cls, type) and dataclasses.is_dataclass(cls) and cls.__module__ == module):
        raise CodecError(f"{module}.{name} is not a dataclass of that module")
    return cls


_NUMERIC_KINDS = "biufcmM"   # bool, int, uint, float, complex, timedelta, datetime


def encode(value: Any) -> Any:
    """JSON-ready form of ``value`` (see the module docstring)."""
    if isinstance(value, np.generic):   # before float: np.float64 is one
        if value.dtype.kind not in _NUMERIC_KINDS:
            return encode(value.item())
        return {"t": "scalar", "dtype": value.dtype.str,
                "b64": base64.b64encode(value.tobytes()).decode("ascii")}
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, int) and not isinstance(value, np.integer):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else {"t": "float", "v": repr(value)}
    if isinstance(value, dict):
        if all(isinstance(k, str) for k in value):
            return {"t": "dict", "v": {k: encode(v) for k, v in value.items()}}
        return {"t": "kvdict", "v": [[encode(k), encode(v)] for k, v in value.items()]}
    if isinstance(value, (list, tuple)):
        return {"t": "list" if isinstance(value, list) else "tuple", "v": [encode(v) for v in value]}
    if isinstance(value, np.ndarray):
        return _encode_array(value)
    if isinstance(value, pd.DataFrame):
        return {"t": "frame", "columns": [encode(c) for c in value.columns],
                "data": [_encode_column(value.iloc[:, i]) for i in range(value.shape[1])],
                "index": _encode_index(value.index)}
    if isinstance(value, pd.Series):
        return {"t": "series", "name": encode(value.name), "data": _encode_column(value),
                "index": _encode_index(value.index)}
    if isinstance(value, pd.Timestamp):
        return {"t": "timestamp", "v": value.isoformat()}
    if isinstance(value, PurePath):
        return {"t": "path", "v": str(value)}
    cls = type(value)
    if dataclasses.is_dataclass(value) and _allowed(cls.__module__, cls.__qualname__):
        return {"t": "dataclass", "module": cls.__module__, "name": cls.__qualname__,
                "v": {f.name: encode(getattr(value, f.name)) for f in dataclasses.fields(value)}}
    raise CodecError(f"cannot store a {type(value).__name__} as plain data")


def _encode_array(a: np.ndarray) -> dict[str, Any]:
    if a.dtype.kind == "U":     # text of a fixed width: the same dtype back
        return {"t": "strarray", "dtype": a.dtype.str, "shape": list(a.shape),
                "v": a.ravel().tolist()}
    if a.dtype.kind not in _NUMERIC_KINDS:
        if a.dtype.kind in "OS":
            return {"t": "objarray", "v": [encode(v) for v in a.ravel().tolist()],
                    "shape": list(a.shape)}
        raise CodecError(f"cannot store an array of dtype {a.dtype}")
    a = np.ascontiguousarray(a)
    return {"t": "ndarray", "dtype": a.dtype.str, "shape": list(a.shape),
            "b64": base64.b64encode(a.tobytes()).decode("ascii")}


def _encode_column(s: pd.Series) -> dict[str, Any]:
    if isinstance(s.dtype, np.dtype) and s.dtype.kind in _NUMERIC_KINDS:
        return _encode_array(s.to_numpy())
    return {"t": "values", "dtype": str(s.dtype), "v": [encode(v) for v in s.tolist()]}


def _encode_index(index: pd.Index) -> dict[str, Any]:
    if isinstance(index, pd.RangeIndex):
        return {"t": "range", "v": [index.start, index.stop, index.step]}
    return {"t": "index", "v": _encode_column(pd.Series(index))}


def decode(doc: Any) -> Any:
    """The value :func:`encode` stored; :class:`CodecError` for anything else
    (a missing field, a wrong type, an array whose size does not match its
    shape, nesting too deep: whatever the file holds, never another error)."""
    try:
        return _decode(doc)
    except CodecError:
        raise
    except (KeyError, IndexError, TypeError, ValueError, AttributeError, OverflowError,
            RecursionError, MemoryError) as exc:
        raise CodecError(f"malformed entry ({type(exc).__name__}: {exc})") from None


def _decode(doc: Any) -> Any:
    if doc is None or isinstance(doc, (bool, str, int, float)):
        return doc
    if not isinstance(doc, dict) or "t" not in doc:
        raise CodecError("not an encoded value")
    tag = doc["t"]
    if tag == "float":
        return float(doc["v"])
    if tag == "dict":
        return {k: _decode(v) for k, v in _mapping(doc["v"]).items()}
    if tag == "kvdict":
        return {_hashable(_decode(k)): _decode(v) for k, v in doc["v"]}
    if tag in ("list", "tuple"):
        items = [_decode(v) for v in _sequence(doc["v"])]
        return items if tag == "list" else tuple(items)
    if tag == "ndarray":
        return _decode_array(doc)
    if tag == "strarray":
        dtype = np.dtype(str(doc["dtype"]))
        if dtype.kind != "U" or not all(isinstance(v, str) for v in _sequence(doc["v"])):
            raise CodecError("text array: not text")
        return np.array(doc["v"], dtype=dtype).reshape([int(n) for n in _sequence(doc["shape"])])
    if tag == "scalar":
        return _decode_array({**doc, "shape": []})[()]
    if tag == "objarray":
        return np.array([_decode(v) for v in doc["v"]], dtype=object).reshape(doc["shape"])
    if tag == "frame":
        cols = [_hashable(_decode(c)) for c in _sequence(doc["columns"])]
        data = [_decode_column(d) for d in _sequence(doc["data"])]
        if len(cols) != len(data):
            raise CodecError("frame: columns and data differ in length")
        index = _decode_index(doc["index"])
        frame = pd.DataFrame({i: d for i, d in enumerate(data)}, index=index)
        frame.columns = pd.Index(cols)
        return frame
    if tag == "series":
        return pd.Series(_decode_column(doc["data"]), index=_decode_index(doc["index"]),
                         name=_hashable(_decode(doc["name"])))
    if tag == "timestamp":
        return pd.Timestamp(str(doc["v"]))
    if tag == "path":
        return Path(str(doc["v"]))
    if tag == "dataclass":
        cls = _dataclass_of(doc.get("module"), doc.get("name"))
        fields = {f.name: f for f in dataclasses.fields(cls)}
        values = {k: _decode(v) for k, v in _mapping(doc["v"]).items()}
        if set(values) != set(fields):
            raise CodecError(f"{cls.__name__}: fields {sorted(values)} != {sorted(fields)}")
        obj = cls(**{k: v for k, v in values.items() if fields[k].init})
        for k, v in values.items():   # a field its constructor does not take
            if not fields[k].init:
                object.__setattr__(obj, k, v)
        return obj
    raise CodecError(f"unknown tag {tag!r}")


def _decode_array(doc: dict) -> np.ndarray:
    dtype = np.dtype(str(doc["dtype"]))
    if dtype.kind not in _NUMERIC_KINDS or dtype.hasobject:
        raise CodecError(f"array dtype {dtype} is not plain numbers")
    raw = base64.b64decode(str(doc["b64"]), validate=True)
    shape = [int(n) for n in _sequence(doc["shape"])]
    if dtype.itemsize * math.prod(shape) != len(raw):
        raise CodecError("array: size does not match its shape")
    return np.frombuffer(raw, dtype=dtype).reshape(shape).copy()


def _decode_column(doc: dict):
    if not isinstance(doc, dict):
        raise CodecError("column: not an encoded column")
    if doc.get("t") == "ndarray":
        return _decode_array(doc)
    if doc.get("t") == "values":
        values = [_decode(v) for v in _sequence(doc["v"])]
        dtype = str(doc.get("dtype", "object"))
        try:
            return pd.array(values, dtype=dtype if dtype in ("string", "str", "object",
                                                             "boolean", "Int64", "Float64")
                            else "object")
        except (TypeError, ValueError):
            return pd.array(values, dtype="object")
    raise CodecError("column: unknown encoding")


def _decode_index(doc: dict) -> pd.Index:
    if not isinstance(doc, dict):
        raise CodecError("index: not an encoded index")
    if doc.get("t") == "range":
        start, stop, step = (int(v) for v in _sequence(doc["v"]))
        return pd.RangeIndex(start, stop, step)
    if doc.get("t") == "index":
        return pd.Index(_decode_column(doc["v"]))
    raise CodecError("index: unknown encoding")


def _mapping(v) -> dict:
    if not isinstance(v, dict):
        raise CodecError("expected a mapping")
    return v


def _sequence(v) -> list:
    if not isinstance(v, list):
        raise CodecError("expected a list")
    return v


def _hashable(v):
    try:
        hash(v)
    except TypeError:
        raise CodecError("a dict key or column name that is not hashable") from None
    return v
