"""One estimated number, after lmfit's ``Parameter`` (core layer).

Every result of the package that estimates numbers (``FlowFit``,
``Identification``, ``Discovery``) gives them as :class:`Estimate` objects
in ``result.params`` (an :class:`Estimates` mapping, name -> Estimate); its
``to_frame()`` and the result's JSON are made from the same objects, so a
number has one name and one value in both.

An estimate's unit is a unit of the package's one table
(:mod:`seanv_analysis.units`), or a dimensionless one
(:data:`~seanv_analysis.units.DIMENSIONLESS_SUFFIXES`: a ratio, a count of
runs); its JSON keys end in that unit's suffix (``value_mm``,
``ci95_mm``...), its frame gives the unit in a column.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Iterable, Mapping

from .units import key_suffix

__all__ = ["Estimate", "Estimates", "SOURCES", "widen_interval"]

#: where an estimate's value comes from: the data ('identified'), the rig
#: file (or another default) kept because the data cannot tell it
#: ('rig_file'), or nowhere (the estimate failed: value NaN, 'not_estimated')
SOURCES = ("identified", "rig_file", "not_estimated")


def widen_interval(x: float, ci, half: float) -> tuple[float, float]:
    """Interval ``ci`` around ``x`` with a half-width ``half`` added in
    quadrature on each side (an interval with a NaN end, or ``half`` 0,
    is returned as it is)."""
    lo, hi = (float(v) for v in ci)
    if not half or not (math.isfinite(lo) and math.isfinite(hi)):
        return (lo, hi)
    return (x - math.hypot(x - lo, half), x + math.hypot(hi - x, half))


def _num(x: Any) -> float | None:
    """A finite number for JSON (ints stay ints), else None."""
    if x is None:
        return None
    if isinstance(x, bool):
        return float(x)
    if isinstance(x, int):
        return x
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def _float(x: Any) -> float:
    """JSON's null back to NaN."""
    return math.nan if x is None else x


def _nan2() -> tuple[float, float]:
    return (math.nan, math.nan)


@dataclass(frozen=True)
class Estimate:
    """One estimated number with its uncertainty and provenance.

    Attributes
    ----------
    name : dotted name in its result's ``params`` ('supply.C',
        'servo.dead_time_s', 'drain.drift.step'); the part after the last
        dot is the quantity (:attr:`quantity`)
    value : the estimate, in ``unit`` (NaN when it failed; an int for a
        count found on a grid)
    unit : its unit: one of :data:`seanv_analysis.units.UNIT_SUFFIXES`'s
        units, or dimensionless ('' or '-': a ratio; 'runs': a count of runs)
    ci95 : 95 % interval (lo, hi) in ``unit``; NaN ends where unknown
    stderr : standard error (1 sigma) in ``unit``; NaN where not known
    method : how it was obtained (the fit and how the interval was made)
    constrained_by : what in the data fixes it (one phrase)
    source : :data:`SOURCES`: 'identified' (from the data), 'rig_file'
        (the data cannot tell it: the default kept), 'not_estimated'
    default : the rig file's (or the model's default) value in ``unit``; NaN: none
    note : anything a user should know (why it was not identified...)
    bounds : (min, max) the fit allowed, in ``unit`` (lmfit's ``min``/``max``;
        infinite: none; :meth:`at_bound` says when the value sits on one, where
        the interval is not to be trusted)
    """

    name: str
    value: float
    unit: str
    ci95: tuple[float, float] = field(default_factory=_nan2)
    stderr: float = math.nan
    method: str = ""
    constrained_by: str = ""
    source: str = "identified"
    default: float = math.nan
    note: str = ""
    bounds: tuple[float, float] = (-math.inf, math.inf)

    def __post_init__(self) -> None:
        if self.source not in SOURCES:
            raise ValueError(f"source: expected one of {', '.join(SOURCES)}, got {self.source!r}")
        key_suffix(self.unit)   # raises ValueError for a unit the table lacks
        object.__setattr__(self, "ci95", (self.ci95[0], self.ci95[1]))
        object.__setattr__(self, "bounds", (self.bounds[0], self.bounds[1]))

    # names -------------------------------------------------------------------
    @property
    def quantity(self) -> str:
        """The name's last part ('supply.C' -> 'C')."""
        return self.name.rsplit(".", 1)[-1]

    @property
    def suffix(self) -> str:
        """The unit's key suffix ('_mm', '_mm3_s_deg2_sqrtMPa', '_ratio'...)."""
        return key_suffix(self.unit)

    @property
    def key(self) -> str:
        """The value's key in a result's wide JSON and frame: quantity and
        unit ('C_mm3_s_deg2_sqrtMPa', 'z0_mm')."""
        return f"{self.quantity}{self.suffix}"

    @property
    def ci95_key(self) -> str:
        """The interval's key beside :attr:`key` ('z0_ci95_mm'); its ends in a
        frame are ``ci95_key`` with '_lo'/'_hi' before the unit."""
        return f"{self.quantity}_ci95{self.suffix}"

    @property
    def stderr_key(self) -> str:
        """The standard error's key beside :attr:`key` ('z0_stderr_mm')."""
        return f"{self.quantity}_stderr{self.suffix}"

    # checks ------------------------------------------------------------------
    @property
    def identified(self) -> bool:
        """True when the data gave the value."""
        return self.source == "identified"

    @property
    def has_interval(self) -> bool:
        """Both ends of the 95 % interval are known."""
        return all(isinstance(v, (int, float)) and math.isfinite(v) for v in self.ci95)

    def inside(self) -> bool:
        """The value lies in its 95 % interval (True where either is unknown)."""
        try:
            v = float(self.value)
        except (TypeError, ValueError):
            return True
        if not (math.isfinite(v) and self.has_interval):
            return True
        lo, hi = self.ci95
        return lo <= v <= hi

    def at_bound(self, rel: float = 1e-6) -> bool:
        """The value sits on a finite bound of the fit (within ``rel`` of the
        bounds' span, or of the value where one bound is infinite)."""
        if not _finite(self.value):
            return False
        lo, hi = self.bounds
        scale = (hi - lo) if math.isfinite(lo) and math.isfinite(hi) else max(abs(self.value), 1.0)
        return any(math.isfinite(b) and abs(self.value - b) <= rel * scale for b in (lo, hi))

    # forms -------------------------------------------------------------------
    def to_json_dict(self) -> dict[str, Any]:
        """The record form: name, ``value_<unit>``, ``ci95_<unit>``,
        ``stderr_<unit>``, ``default_<unit>``, ``bounds_<unit>`` (each
        number's unit is the end of its key; null: unknown, or for a bound,
        none), the unit in words, source, method, constrained_by, note."""
        u = self.suffix
        return {"name": self.name, f"value{u}": _num(self.value),
                f"ci95{u}": [_num(v) for v in self.ci95], f"stderr{u}": _num(self.stderr),
                f"default{u}": _num(self.default), f"bounds{u}": [_num(v) for v in self.bounds],
                "unit": self.unit, "source": self.source, "method": self.method,
                "constrained_by": self.constrained_by, "note": self.note}

    @classmethod
    def from_json_dict(cls, d: Mapping[str, Any]) -> "Estimate":
        """The estimate of a record (:meth:`to_json_dict`); null -> NaN.

        Raises
        ------
        ValueError
            the record lacks ``name``, ``unit`` or ``value_<unit>``, or its
            unit is not in the table.
        """
        try:
            unit = str(d["unit"])
            u = key_suffix(unit)
            lo, hi = d.get(f"ci95{u}") or (None, None)
            b_lo, b_hi = d.get(f"bounds{u}") or (None, None)
            return cls(str(d["name"]), _float(d[f"value{u}"]), unit, (_float(lo), _float(hi)),
                       _float(d.get(f"stderr{u}")), str(d.get("method", "")),
                       str(d.get("constrained_by", "")), str(d.get("source", "identified")),
                       _float(d.get(f"default{u}")), str(d.get("note", "")),
                       (-math.inf if b_lo is None else b_lo, math.inf if b_hi is None else b_hi))
        except KeyError as exc:
            raise ValueError(f"estimate record: no {exc.args[0]!r}; expected name, unit and "
                             "value_<unit> (Estimate.to_json_dict)") from None

    def wide_items(self) -> dict[str, Any]:
        """{key: value, <quantity>_ci95_lo<unit>: lo, ..._hi...: hi}: the
        estimate's columns in a wide frame (one row per side, say)."""
        q, u = self.quantity, self.suffix
        return {self.key: self.value, f"{q}_ci95_lo{u}": self.ci95[0],
                f"{q}_ci95_hi{u}": self.ci95[1]}

    def to_row(self) -> dict[str, Any]:
        """The estimate's row in a long frame (:meth:`Estimates.to_frame`):
        its numbers in its ``unit`` column."""
        return {"name": self.name, "value": self.value, "ci95_lo": self.ci95[0],
                "ci95_hi": self.ci95[1], "stderr": self.stderr, "default": self.default,
                "unit": self.unit, "source": self.source, "method": self.method,
                "constrained_by": self.constrained_by, "note": self.note,
                "at_bound": self.at_bound()}

    def __repr__(self) -> str:
        lo, hi = self.ci95
        parts = [f"stderr {self.stderr:.2g}"] if _finite(self.stderr) else []
        parts.append(f"95 % [{lo:.6g}, {hi:.6g}]" if self.has_interval else "no 95 % interval")
        if self.at_bound():
            parts.append("at a bound of the fit")
        if not self.identified:
            parts.append(self.source.replace("_", " "))
        val = f"{self.value:.6g}" if _finite(self.value) else repr(self.value)
        return f"<Estimate {self.name} = {val} {self.unit} ({'; '.join(parts)})>"


def _finite(x: Any) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x)


class Estimates(dict):
    """A result's estimates by name (lmfit's ``result.params``): a dict
    name -> :class:`Estimate`, with ``to_frame()`` (one row each) and
    ``to_json_dict()`` ({name: record})."""

    @classmethod
    def of(cls, estimates: Iterable[Estimate]) -> "Estimates":
        """Keyed by their names (a name given twice raises ValueError)."""
        out = cls()
        for e in estimates:
            if e.name in out:
                raise ValueError(f"estimate {e.name!r} given twice")
            out[e.name] = e
        return out

    def to_frame(self):
        """One row per estimate (a long table: each row's numbers in its
        ``unit``): name, value, ci95_lo, ci95_hi, stderr, default, unit,
        source, method, constrained_by, note, at_bound."""

        return self.frame_of(self.values())

    @staticmethod
    def frame_of(estimates: Iterable[Estimate]):
        """The long table of ``estimates`` (:meth:`to_frame`), in their order."""
        import pandas as pd

        cols = list(Estimate("x", 0.0, "").to_row())
        return pd.DataFrame([e.to_row() for e in estimates], columns=cols)

    def to_json_dict(self) -> dict[str, dict[str, Any]]:
        """{name: the estimate's record (:meth:`Estimate.to_json_dict`)}."""
        return {k: e.to_json_dict() for k, e in self.items()}

    @classmethod
    def from_json_dict(cls, d: Mapping[str, Mapping[str, Any]]) -> "Estimates":
        """The estimates of :meth:`to_json_dict`'s document."""
        return cls.of(Estimate.from_json_dict(r) for r in d.values())
