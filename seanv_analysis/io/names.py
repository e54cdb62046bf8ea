"""File names derived from run identifiers.

Run ids come from the rig's metadata and may hold spaces, slashes or colons;
every per-run output file (figures, overlay tables) is named through
:func:`safe_name` so the same run always maps to the same, portable name.
"""
from __future__ import annotations

__all__ = ["safe_name"]


def safe_name(text: str) -> str:
    """``text`` with every character other than letters, digits, ``-``, ``_``
    and ``.`` replaced by ``_`` (a name safe on every file system).

    Examples
    --------
    >>> safe_name("run 3/a:b")
    'run_3_a_b'
    """
    return "".join(c if (c.isalnum() or c in "-_.") else "_" for c in str(text))
