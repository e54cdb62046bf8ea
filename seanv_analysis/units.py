"""The package's one table of units (core layer).

A number's unit is the end of its name: a JSON key (``rmse_mm3_s``), a
table column (``p_head_mpag``), a rig key (``dead_time_s``). The JSON writer
and its schema tests, the Parquet writer (each column's ``unit`` metadata),
the report's headers and the units the results quote all read
:data:`UNIT_SUFFIXES`; nothing else tables units.
"""
from __future__ import annotations

from typing import Iterable

__all__ = ["UNIT_SUFFIXES", "DIMENSIONLESS_SUFFIXES", "unit_of_key", "unit_suffix", "key_suffix",
           "units_of_columns"]

#: key suffix -> unit in plain text. A suffix comes before the shorter ones
#: it ends with (``_mm3_s`` before ``_s``, ``_deg_s`` before ``_s``), so the
#: first suffix a key ends with is its unit (:func:`unit_of_key`); of two
#: suffixes of one unit, the first is the one new keys get. Suffixes are
#: lower case (``_mpa``, ``_n``) but where the unit's spelling is part of a
#: compound (``_mm3_s_deg2_sqrtMPa``).
UNIT_SUFFIXES: dict[str, str] = {
    "_mm3_s_deg2_sqrtMPa": "mm^3/(s deg^2 MPa^0.5)",   # C of eq. (5)
    "_mm3_s_deg2": "mm^3/(s deg^2)",                   # alpha of Q = alpha (theta - theta_d)^2
    "_mm3_s_per_mm": "mm^3/s per mm",
    "_mm3_s_per_mpa": "mm^3/(s MPa)",                  # leakage conductance
    "_mpa_s_per_mm3": "MPa s/mm^3",                    # line resistance, supply droop
    "_mpa_s2_mm3": "MPa s^2/mm^3",                     # line inertance
    "_n_s_per_mm": "N s/mm",                           # viscous friction
    "_mm_per_run": "mm/run",
    "_deg_per_mm": "deg/mm",
    "_mm3_s": "mm^3/s",
    "_mm_s2": "mm/s^2",
    "_mm_s": "mm/s",
    "_deg_s": "deg/s",
    "_mpag": "MPaG",
    "_mpa": "MPa",
    "_MPa": "MPa",                                     # read, never written
    "_pct": "%",
    "_frac": "fraction",
    "_deg": "deg",
    "_mm3": "mm^3",
    "_mm2": "mm^2",
    "_mm": "mm",
    "_kg": "kg",
    "_hz": "Hz",
    "_m": "m",
    "_s": "s",
    "_n": "N",
    "_N": "N",                                         # read, never written
}


#: dimensionless units an estimate may have (:mod:`seanv_analysis.estimate`),
#: with the key suffix its numbers take: a ratio ('' or '-') ends in
#: ``_ratio``, a count of runs in ``_runs`` (the JSON's counts and ratios;
#: not units a key's end is read as, so not in :data:`UNIT_SUFFIXES`)
DIMENSIONLESS_SUFFIXES: dict[str, str] = {"": "_ratio", "-": "_ratio", "runs": "_runs"}


def key_suffix(unit: str) -> str:
    """The key suffix a number in ``unit`` takes: the table's
    (:func:`unit_suffix`), or a dimensionless one
    (:data:`DIMENSIONLESS_SUFFIXES`).

    Raises
    ------
    ValueError
        a unit neither table has (add it to :data:`UNIT_SUFFIXES`).
    """
    if unit in DIMENSIONLESS_SUFFIXES:
        return DIMENSIONLESS_SUFFIXES[unit]
    suffix = unit_suffix(unit)
    if suffix is None:
        raise ValueError(f"unit: {unit!r} has no key suffix in seanv_analysis.units."
                         "UNIT_SUFFIXES; add it there")
    return suffix


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


def units_of_columns(columns: Iterable[object]) -> dict[str, str]:
    """{column: its unit} from the names ('' for a column whose name carries none)."""
    out = {}
    for c in columns:
        found = unit_of_key(str(c))
        out[c] = found[1] if found else ""
    return out
