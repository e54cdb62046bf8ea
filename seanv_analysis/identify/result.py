"""What ``identify`` found: one entry per rig constant, and the whole result.

Each :class:`Constant` names a key of the rig file (``servo.dead_time_s``,
``valve.supply.needle_y_c_mm``, ...), its identified value with a 95 %
interval, the rig file's value beside it, what in the data constrains it,
and whether it was identified at all: a constant the data cannot tell is
kept at the rig file's value and says why (``identified = False``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from ..estimate import Estimate, Estimates
from ..jsonable import JsonResult, clean_json, json_num
from ..units import key_suffix, unit_suffix

__all__ = ["Constant", "Identification", "json_num", "nest_constants", "suffix_of_unit"]


@dataclass
class Constant:
    """One rig constant as identified from the data.

    Attributes
    ----------
    key : dotted rig-file key, e.g. 'servo.time_constant_s' (None: a derived
        number with no rig key, reported only)
    value : identified value in the key's unit (the rig file's when not identified)
    ci95 : 95 % interval (NaN when unavailable)
    default : the rig file's value
    unit : unit of value
    identified : False when the data cannot tell it (value = default)
    constrained_by : what in the data fixes it (one phrase)
    note : why not identified, or anything a user should know
    confounded_with : rig keys the data cannot tell this constant apart
        from (the combination identified and which part is fixed: ``note``)
    method : how it was obtained, where the part says more than
        ``constrained_by`` ('' otherwise)

    :attr:`estimate` is the constant as the package's one estimate type
    (:class:`~seanv_analysis.estimate.Estimate`); the JSON is made from it.
    """

    key: str | None
    name: str
    value: float
    default: float
    unit: str
    identified: bool
    constrained_by: str
    ci95: tuple[float, float] = (math.nan, math.nan)
    note: str = ""
    confounded_with: tuple[str, ...] = ()
    method: str = ""

    @property
    def estimate(self) -> Estimate:
        """The constant as an :class:`~seanv_analysis.estimate.Estimate`
        named by its rig key (its name when it has none): source
        'identified', 'rig_file' (not identified, the rig file's value
        kept) or 'not_estimated' (a derived number the data cannot give)."""
        source = "identified" if self.identified else ("rig_file" if self.key else
                                                       "not_estimated")
        return Estimate(self.key or self.name, self.value, self.unit, tuple(self.ci95),
                        method=self.method, constrained_by=self.constrained_by, source=source,
                        default=self.default, note=self.note)

    @property
    def suffix(self) -> str:
        """The unit's key suffix (:data:`~seanv_analysis.units.UNIT_SUFFIXES`:
        ``'_mm'``, ``'_mpag'``, ``'_n_s_per_mm'``...; ``'_ratio'`` for a
        dimensionless factor): the JSON's numbers end in it."""
        return suffix_of_unit(self.unit)

    def to_json_dict(self) -> dict[str, Any]:
        """The rig key, :attr:`estimate`'s record (its ``name``, the rig key
        or for a derived number its words; ``value_<unit>``, ``ci95_<unit>``,
        ``stderr_<unit>``, ``default_<unit>``, ``bounds_<unit>``: every
        number's unit is the end of its key; ``unit`` in words, ``source``:
        'identified' or 'rig_file', ``method``, ``constrained_by``,
        ``note``), then ``label`` (the name in words), ``identified``,
        ``confounded_with``: the names of :meth:`Identification.to_frame`'s
        columns."""
        return {"key": self.key, **self.estimate.to_json_dict(), "label": self.name,
                "identified": bool(self.identified),
                "confounded_with": list(self.confounded_with)}

    def line(self) -> str:
        """One line of the text report."""
        lo, hi = self.ci95
        ci = f" [{lo:.4g}, {hi:.4g}]" if math.isfinite(lo) and math.isfinite(hi) else ""
        head = f"{self.name:<34} {self.value:>10.4g}{ci} {self.unit}"
        if not self.identified:
            src = "rig file; " if self.key else ""
            return f"{head}  ({src}not identified: {self.note})"
        extra = f"; {self.note}" if self.note else ""
        ref = f"rig file {self.default:.4g}; " if self.key else ""
        return f"{head}  ({ref}from {self.constrained_by}{extra})"


def suffix_of_unit(unit: str) -> str:
    """Key suffix of a constant's unit: the units table's, ``'_ratio'`` for a
    dimensionless one ('') (:func:`seanv_analysis.units.key_suffix`)."""
    return key_suffix(unit)


def nest_constants(constants) -> dict[str, Any]:
    """Nested {section: {key: value}} (rig-file schema) of the identified
    constants that have a rig key, each to 6 significant digits (as
    rig-identified.toml holds them, so the twin in memory is the file's)."""
    out: dict[str, Any] = {}
    for c in constants:
        if not (c.identified and c.key):
            continue
        parts = c.key.split(".")
        d = out
        for p in parts[:-1]:
            d = d.setdefault(p, {})
        d[parts[-1]] = c.value if isinstance(c.value, bool) else float(f"{c.value:.6g}")
    return out


@dataclass
class Identification(JsonResult):
    """Result of :func:`seanv_analysis.identify.identify_rig`.

    Attributes
    ----------
    constants : every constant looked at, identified or not
    rig : the rig config with the identified constants applied (what
        ``validate`` and ``discover`` simulate with)
    model : the valve model refitted with the identified geometry (or None)
    fits : per part ('geometry', 'servo', 'friction', 'flow_path'): training
        and held-out error with the rig file's constants and the identified ones
    notes : what a user should know (data that could not be used, ...)
    """

    constants: list[Constant]
    rig: Any
    model: Any = None
    fits: dict[str, dict[str, Any]] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    success: bool = True

    def identified(self) -> list[Constant]:
        return [c for c in self.constants if c.identified and c.key]

    @property
    def params(self) -> Estimates:
        """Every constant looked at as an
        :class:`~seanv_analysis.estimate.Estimate`, by rig key (by name for
        a derived number with no key), as lmfit's ``result.params``;
        ``params.to_frame()`` is their table. A key given twice keeps the
        later constant, as the identified rig does (:func:`nest_constants`)."""
        return Estimates((e.name, e) for e in (c.estimate for c in self.constants))

    def overrides(self) -> dict[str, Any]:
        """Nested {section: {key: value}} of the identified constants (rig-file schema)."""
        return nest_constants(self.constants)

    def to_json_dict(self) -> dict[str, Any]:
        return {"schema": "seanv-identify/4",
                "constants": [c.to_json_dict() for c in self.constants],
                "identified_keys": [c.key for c in self.identified()],
                "not_separable": [{"key": c.key, "from": list(c.confounded_with),
                                   "note": c.note} for c in self.constants
                                  if c.confounded_with],
                "fits": _unit_keys(clean_json(self.fits)), "notes": list(self.notes)}

    def report(self) -> str:
        lines = ["identify: the rig's unpublished constants from its own logs",
                 f"  {len(self.identified())} of {len(self.constants)} constants identified "
                 "(95 % intervals; the others keep the rig file's value)"]
        lines += ["  " + c.line() for c in self.constants]
        for part, f in self.fits.items():
            subs = [(f"{part} ({k})", v) for k, v in f.items() if isinstance(v, dict)] \
                if "metric" not in f else [(part, f)]
            for label, g in subs:
                held = ("heldout" in g or "heldout_default" in g)
                lines.append(f"  {label}: {g.get('metric', '')}: training "
                             f"{_fmt(g.get('train_default'))} -> {_fmt(g.get('train'))}"
                             + (f", held-out {_fmt(g.get('heldout_default'))} -> "
                                f"{_fmt(g.get('heldout'))}" if held else "")
                             + " (rig file -> identified)")
        lines += [f"  note: {n}" for n in self.notes]
        return "\n".join(lines)

    def to_frame(self):
        """One row per constant (a long table: each row's numbers are in its
        ``unit``): key, then :attr:`params`' table (name, value, 95 %
        interval ci95_lo/ci95_hi, stderr, rig-file default, unit, source,
        method, what constrains it, note), label (the name in words),
        identified: the JSON's ``constants`` under the same names."""
        frame = Estimates.frame_of(c.estimate for c in self.constants)
        frame.insert(0, "key", [c.key for c in self.constants])
        frame["label"] = [c.name for c in self.constants]
        frame["identified"] = [bool(c.identified) for c in self.constants]
        return frame

    def __repr__(self) -> str:
        return (f"<Identification: {len(self.identified())}/{len(self.constants)} constants "
                f"identified: {', '.join(c.key for c in self.identified()) or 'none'}>")


def _fmt(v: Any) -> str:
    v = json_num(v)
    return "n/a" if v is None else f"{v:.4g}"


#: a fit block's metric names its unit in brackets; the JSON keys carry it
#: (the suffix of :data:`~seanv_analysis.jsonable.UNIT_SUFFIXES`)
_SCORES = ("train", "heldout", "train_default", "heldout_default", "train_flow",
           "heldout_flow", "heldout_default_flow")


def _unit_keys(x: Any) -> Any:
    """Fit blocks (dicts with a ``metric`` '... [unit] ...') with the unit
    appended to their score keys: ``heldout`` -> ``heldout_mm3_s``."""
    if not isinstance(x, dict):
        return x
    out = {k: _unit_keys(v) for k, v in x.items()}
    metric = out.get("metric")
    if isinstance(metric, str) and "[" in metric:
        suffix = unit_suffix(metric.split("[", 1)[1].split("]", 1)[0])
        if suffix is not None:
            out = {(f"{k}{suffix}" if k in _SCORES else k): v for k, v in out.items()}
    return out


