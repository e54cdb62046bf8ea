"""The package's one table of units (core layer).

A number's unit is the end of its name: a JSON key (``rmse_mm3_s``), a
table column (``p_head_mpag``), a rig key (``dead_time_s``). The JSON writer
and its schema tests, the Parquet writer (each column's ``unit`` metadata),
the report's headers and the units the results quote all read
:data:`UNIT_SUFFIXES`; nothing else tables units.
"""
from __future__ import annotations

import re
from typing import Iterable

__all__ = ["UNIT_SUFFIXES", "DIMENSIONLESS_SUFFIXES", "BASE_UNITS", "unit_of_key", "unit_suffix",
           "key_suffix", "units_of_columns", "unit_powers", "unit_text", "ratio_unit"]

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


#: the units a derived unit is made of (:func:`ratio_unit`), in the order its
#: text gives them, with the token its key suffix spells each with
#: ('MPaG', a gauge pressure, counts as MPa in a derived unit; 'run': per run)
BASE_UNITS: dict[str, str] = {"mm": "mm", "s": "s", "deg": "deg", "MPa": "mpa", "N": "n",
                              "kg": "kg", "m": "m", "Hz": "hz", "run": "run"}
_TOKEN = re.compile(r"(sqrt)?(" + "|".join(sorted(BASE_UNITS.values(), key=len, reverse=True))
                    + r")(\d+(?:p\d+)?)?")
_FACTOR = re.compile(r"([A-Za-z]+)(?:\^(-?[\d.]+))?")


def unit_powers(unit: str) -> dict[str, float] | None:
    """The powers of :data:`BASE_UNITS` a plain-text unit is made of
    (``'mm^3/(s MPa^0.5)'`` -> {'mm': 3, 's': -1, 'MPa': -0.5}; '' and '-':
    {}), or None for a text that is not such a product (``'%'``, ``'mm^3/s
    per mm'``)."""
    text = unit.strip()
    if text in ("", "-", "1"):
        return {}
    num, _, den = text.partition("/")
    out: dict[str, float] = {}
    for part, sign in ((num, 1.0), (den.strip().removeprefix("(").removesuffix(")"), -1.0)):
        for factor in part.split():
            m = _FACTOR.fullmatch(factor)
            if factor == "1" and sign > 0:
                continue
            name = "MPa" if m and m.group(1) == "MPaG" else (m.group(1) if m else "")
            if name not in BASE_UNITS:
                return None
            out[name] = out.get(name, 0.0) + sign * float(m.group(2) or 1.0)
    return {k: out[k] for k in BASE_UNITS if out.get(k)}


def _power_text(name: str, p: float) -> str:
    return name if p == 1 else f"{name}^{p:g}"


def unit_text(powers: dict[str, float]) -> str:
    """The plain text of a product of powers of :data:`BASE_UNITS`, in that
    order, as the table writes units ({'mm': 3, 's': -1, 'MPa': -1} ->
    'mm^3/(s MPa)', {'MPa': -2} -> '1/MPa^2', {} -> '')."""
    num = [_power_text(k, powers[k]) for k in BASE_UNITS if powers.get(k, 0) > 0]
    den = [_power_text(k, -powers[k]) for k in BASE_UNITS if powers.get(k, 0) < 0]
    if not den:
        return " ".join(num)
    return (" ".join(num) or "1") + "/" + (den[0] if len(den) == 1 else f"({' '.join(den)})")


def ratio_unit(numerator: str, denominator: str) -> str:
    """The unit of a number in ``numerator`` per ``denominator`` (both
    products of :data:`BASE_UNITS`, or dimensionless): a proposed term's
    coefficient, 'mm^3/s' per 'MPa^2' -> 'mm^3/(s MPa^2)'. Its key suffix
    is the table's where the table has the unit, else derived
    (:func:`key_suffix`).

    Raises
    ------
    ValueError
        either unit is not such a product.
    """
    a, b = unit_powers(numerator), unit_powers(denominator)
    if a is None or b is None:
        bad = numerator if a is None else denominator
        raise ValueError(f"unit: {bad!r} is not a product of powers of "
                         f"{', '.join(BASE_UNITS)}")
    return unit_text({k: a.get(k, 0.0) - b.get(k, 0.0) for k in BASE_UNITS})


def _token(name: str, p: float) -> str:
    base = BASE_UNITS[name]
    if p == 0.5:
        return "sqrt" + base
    return base if p == 1 else base + f"{p:g}".replace(".", "p")


def _derived_suffix(unit: str) -> str | None:
    """The key suffix of a derived unit (:func:`ratio_unit`): its numerator's
    tokens, '_per', its denominator's (``'mm^3/(s MPa^2)'`` ->
    ``'_mm3_s_per_mpa2'``, ``'1/MPa'`` -> ``'_per_mpa'``); None unless
    ``unit`` is a ratio in :func:`unit_text`'s spelling."""
    powers = unit_powers(unit)
    if not powers or unit_text(powers) != unit or all(p > 0 for p in powers.values()):
        return None
    num = [_token(k, p) for k, p in powers.items() if p > 0]
    den = [_token(k, -p) for k, p in powers.items() if p < 0]
    suffix = "".join(f"_{t}" for t in num) + "_per" + "".join(f"_{t}" for t in den)
    # the table's older spellings read 'mm3_s' as mm^3/s ('_mm3_s_per_mpa':
    # mm^3/(s MPa)): a derived suffix never takes one of them for another unit
    return None if UNIT_SUFFIXES.get(suffix, unit) != unit else suffix


def _unit_of_derived_suffix(key: str) -> tuple[str, str] | None:
    """(name, unit) of a key ending in a derived suffix (:func:`_derived_suffix`)."""
    head, sep, den = key.rpartition("_per_")
    if not sep:
        return None
    powers: dict[str, float] = {}
    for tok, sign in [(t, -1.0) for t in den.split("_")]:
        m = _TOKEN.fullmatch(tok)
        if m is None:
            return None
        powers[_base(m)] = powers.get(_base(m), 0.0) + sign * _power(m)
    parts = head.split("_")
    while len(parts) > 1 and (m := _TOKEN.fullmatch(parts[-1])) is not None:
        powers[_base(m)] = powers.get(_base(m), 0.0) + _power(m)
        parts.pop()
    name = "_".join(parts)
    unit = unit_text(powers)
    if not name or _derived_suffix(unit) != key[len(name):]:
        return None
    return name, unit


def _base(m: re.Match) -> str:
    return next(k for k, v in BASE_UNITS.items() if v == m.group(2))


def _power(m: re.Match) -> float:
    if m.group(1):
        return 0.5
    return float(m.group(3).replace("p", ".")) if m.group(3) else 1.0


def key_suffix(unit: str) -> str:
    """The key suffix a number in ``unit`` takes: the table's
    (:func:`unit_suffix`), a dimensionless one
    (:data:`DIMENSIONLESS_SUFFIXES`), or for a ratio of :data:`BASE_UNITS`
    the table lacks (:func:`ratio_unit`) one derived from its parts
    (``'mm^3/(s MPa^2)'`` -> ``'_mm3_s_per_mpa2'``; :func:`unit_of_key`
    reads it back).

    Raises
    ------
    ValueError
        a unit none of these gives (add it to :data:`UNIT_SUFFIXES`).
    """
    if unit in DIMENSIONLESS_SUFFIXES:
        return DIMENSIONLESS_SUFFIXES[unit]
    suffix = unit_suffix(unit) or _derived_suffix(unit)
    if suffix is None:
        raise ValueError(f"unit: {unit!r} has no key suffix in seanv_analysis.units."
                         "UNIT_SUFFIXES; add it there")
    return suffix


def unit_of_key(key: str) -> tuple[str, str] | None:
    """(name, unit) of a key ending in a unit suffix of :data:`UNIT_SUFFIXES`
    (``'rmse_mm3_s'`` -> ``('rmse', 'mm^3/s')``) or in a derived one
    (:func:`key_suffix`: ``'value_mm3_s_per_mpa2'`` -> ``('value',
    'mm^3/(s MPa^2)')``), else None (a bare suffix is no name: ``'_s'`` ->
    None)."""
    table = next(((key[:-len(suffix)], unit) for suffix, unit in UNIT_SUFFIXES.items()
                  if key.endswith(suffix) and len(key) > len(suffix)), None)
    derived = _unit_of_derived_suffix(key)
    # '_per_mpa' is a derived suffix ending in the table's '_mpa': the longer wins
    if derived is not None and (table is None or len(derived[0]) < len(table[0])):
        return derived
    return table


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
