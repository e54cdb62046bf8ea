"""Files the package reads back from an output folder, read as untrusted input.

An output folder may be shared, copied, or edited by hand, so what the
package wrote there earlier (the per-run cache's entries and index, the
pipeline memo, ``result.json``, the figure keys) is checked like any input
before it is used: :func:`read_back` returns a file's bytes only when it is
a regular file (not a link, a FIFO, a device), lies inside the folder it
belongs to (links in between are resolved and must stay inside) and is not
larger than its limit; anything else is a miss (None), never a hang or a
read outside the folder. :func:`load_json_back` does the same for JSON and
checks the document's shape (:func:`conforms`); :func:`inside` tells whether
a path such a file names lies inside a folder.
"""
from __future__ import annotations

import json
import os
import stat
from pathlib import Path
from typing import Any, Callable

__all__ = ["read_back", "load_json_back", "inside", "conforms", "regular_file_inside",
           "Optional", "MAX_JSON_BYTES"]

#: size limit of a small bookkeeping JSON file (index, memo, figure keys, result.json)
MAX_JSON_BYTES = 64 << 20
_O_FLAGS = os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0) \
    | getattr(os, "O_CLOEXEC", 0)


def inside(path: str | Path, root: str | Path) -> bool:
    """``path`` lies inside the folder ``root`` (or is it), with every link
    of its parent folders resolved; the last component must not be ``..``."""
    path = Path(path)
    if path.name in ("", ".", ".."):
        return False
    try:
        parent = path.parent.resolve()
        base = Path(root).resolve()
    except (OSError, RuntimeError):  # a link loop
        return False
    return parent == base or base in parent.parents


def regular_file_inside(path: str | Path, root: str | Path) -> bool:
    """``path`` is a regular file (itself not a link) inside ``root``."""
    if not inside(path, root):
        return False
    try:
        return stat.S_ISREG(os.lstat(path).st_mode)
    except (OSError, ValueError):
        return False


def read_back(path: str | Path, *, root: str | Path, max_bytes: int = MAX_JSON_BYTES
              ) -> bytes | None:
    """The bytes of ``path``, a file the package wrote inside ``root``;
    None when it is missing, a link, not a regular file, outside ``root``
    or larger than ``max_bytes``."""
    if not inside(path, root):
        return None
    try:
        fd = os.open(path, _O_FLAGS)   # a link: ELOOP; a FIFO: opens without waiting
    except (OSError, ValueError):
        return None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode) or st.st_size > max_bytes:
            return None
        chunks, left = [], max_bytes + 1
        while left > 0:
            chunk = os.read(fd, min(left, 1 << 22))
            if not chunk:
                break
            chunks.append(chunk)
            left -= len(chunk)
        data = b"".join(chunks)
        return None if len(data) > max_bytes else data
    except OSError:
        return None
    finally:
        os.close(fd)


def load_json_back(path: str | Path, *, root: str | Path, shape: Any = object,
                   max_bytes: int = MAX_JSON_BYTES) -> Any | None:
    """The JSON document of ``path`` (as :func:`read_back`) when it parses
    (UTF-8, at most a few hundred levels deep) and :func:`conforms` to
    ``shape``; else None."""
    data = read_back(path, root=root, max_bytes=max_bytes)
    if data is None:
        return None
    try:
        doc = json.loads(data)
    except (ValueError, RecursionError):  # not JSON, not UTF-8, nested too deep
        return None
    return doc if conforms(doc, shape) else None


class Optional:
    """A dict key's shape in :func:`conforms` when the key may be missing."""

    def __init__(self, shape: Any):
        self.shape = shape


def conforms(value: Any, shape: Any) -> bool:
    """Whether ``value`` has ``shape``.

    ``shape`` is ``object`` (anything), a type or tuple of types
    (``isinstance``; a bool is not an int or a float unless ``bool`` is
    named), a dict {key: shape} (a dict holding at least those keys, each of
    that shape; :class:`Optional` ones may be missing), a one-item list
    ``[shape]`` (a list of items of that shape), a one-item dict
    ``{str: shape}`` keyed by the type ``str`` (any string keys, values of that
    shape) or a function (a predicate).

    Examples
    --------
    >>> conforms({"a": [1, 2]}, {"a": [int]})
    True
    >>> conforms({"a": [1, True]}, {"a": [int]})
    False
    """
    try:
        return _conforms(value, shape)
    except RecursionError:
        return False


def _conforms(value: Any, shape: Any) -> bool:
    if shape is object:
        return True
    if isinstance(shape, Optional):
        return _conforms(value, shape.shape)
    if isinstance(shape, (type, tuple)):
        types = shape if isinstance(shape, tuple) else (shape,)
        if isinstance(value, bool) and bool not in types:
            return False
        return isinstance(value, types)
    if isinstance(shape, list):
        return isinstance(value, list) and all(_conforms(v, shape[0]) for v in value)
    if isinstance(shape, dict):
        if not isinstance(value, dict):
            return False
        if len(shape) == 1 and next(iter(shape)) is str:
            item = shape[str]
            return all(isinstance(k, str) and _conforms(v, item) for k, v in value.items())
        for key, sub in shape.items():
            if key not in value:
                if isinstance(sub, Optional):
                    continue
                return False
            if not _conforms(value[key], sub):
                return False
        return True
    if callable(shape):
        got = _call(shape, value)
        return got is not NotImplemented and bool(got)
    raise TypeError(f"not a shape: {shape!r}")


def _call(predicate: Callable[[Any], Any], value: Any) -> Any:
    try:
        return predicate(value)
    except (TypeError, ValueError, KeyError, AttributeError, OverflowError):
        return False
