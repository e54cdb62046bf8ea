"""Injectable plant effects: small, named extensions of the valve model.

These are the "undeclared effects" that the simulator can put into the plant
(``seanv-analyze simulate --effect NAME:k=v,...``) and that
:mod:`seanv_analysis.discover` later looks for in data. Each effect is one
frozen dataclass here, and that class is the only place to extend: it
carries

- its parameters (dataclass fields with defaults; ``PARAMS`` gives units and
  meaning) and their checks (``__post_init__``, :class:`ValueError`);
- its **static form** (``STATIC`` + :meth:`Effect.apply_static`): how it
  changes the flow-step prediction Q = C (theta - theta_d)^2 sqrt(dp) of
  eq. (5), with the threshold theta_d of eq. (3)+(4), for discover's static
  fit: the parameters fitted, their start values and bounds, the flow-step
  variables it reads;
- its **sentence** for the discovery report (``SENTENCE``);
- where it has one, its **dynamic form** for the simulator
  (:meth:`Effect.valve_terms`, :meth:`Effect.plant_terms`): what it adds to
  the plant's valve at run i and to the rest of the plant.

Subclassing :class:`Effect` registers the class in :data:`EFFECTS`; discover's
candidates, its report and the simulator's plant all read the registry and
call these methods, so a new effect is one class (and its test).

"Use" is the 0-based index of a run in the data set's time order
(``started_at``), written ``i`` below.

========================  =====================================================
effect                    functional form
========================  =====================================================
``drift``                 C_side(i) = C (1 - step)^floor((i + offset) / every)
``threshold_shift``       z0_side(i) = z0 + rate_mm_per_run * i
``backlash``              theta_needle = theta_servo - width/2 * approach
                          (play of ``width_deg`` between servo and cam)
``pressure_law``          Q = C (theta - theta_d)^2 dp^exponent  (not 0.5)
``saturation``            Q_sat = Q / (1 + (|Q|/q_max)^s)^(1/s)
``delay``                 theta_needle(t) = theta_servo(t - delay_s)
``sensor_gain``           measured = gain * true  (encoder or a pressure sensor)
``term``                  Q (1 + f), Q + f or theta_d + f of one side, f a
                          closed-form expression (:mod:`.expr`); not a named
                          effect: discover never tries it as a candidate
========================  =====================================================

This module uses numpy and the standard library only; bad parameters raise
:class:`ValueError`, which the command line turns into its one-line error.

Examples
--------
>>> from seanv_analysis.models.effects import parse_effect
>>> e = parse_effect("drift:side=drain,step=0.05,every=3")
>>> float(e.c_multiplier(5))
0.95
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace
from functools import cached_property
from typing import Any, Callable, ClassVar, Iterable, Mapping

import numpy as np

from .expr import Program, compile_expr, evaluate

__all__ = [
    "Effect", "Drift", "ThresholdShift", "Backlash", "PressureLaw", "Saturation", "Delay",
    "SensorGain", "Term", "EFFECTS", "SENSORS", "TERM_MODES", "TERM_MODE_UNITS", "StaticForm", "FlowTerms",
    "TermCorrection", "ValveTerms", "PlantTerms", "plant_param_defaults",
    "static_effects", "vocabulary_effects", "dynamic_effects", "parse_effect", "parse_effects",
    "drift_multiplier", "threshold_shift_mm", "backlash_cam_deg", "backlash_play_deg",
    "saturate_flow", "saturate_flow_core", "true_from_measured",
    "term_variables", "apply_corrections",
]

_SIDES = ("supply", "drain")
#: how a ``term`` acts on its side: Q (1 + f), Q + f [mm^3/s], theta_d + f [deg]
TERM_MODES = ("mul", "add", "threshold")
#: the unit of a ``term``'s correction f in each mode (a ratio, a flow, an angle)
TERM_MODE_UNITS = {"mul": "", "add": "mm^3/s", "threshold": "deg"}
#: sensors a ``sensor_gain`` can act on; 'pressure' is the A/B-port (head) sensor
SENSORS = ("encoder", "pressure", "p_head", "p_supply", "p_load")
#: the simulator's sensor channels and their gain without a ``sensor_gain`` [-]


# Functional forms -----------------------------------------------------------
# Plain arithmetic on floats or numpy arrays (numba-compilable where the
# simulator's kernel needs them).

def drift_multiplier(run_index, *, step, every, offset=0):
    """Multiplier of C after ``run_index`` runs [-].

    (1 - step)^floor((i + offset) / every): C falls by ``step`` (a fraction)
    every ``every`` runs, the first fall after ``every - offset`` runs.
    """
    k = np.floor((np.asarray(run_index, dtype=float) + offset) / every)
    return (1.0 - step) ** k


def threshold_shift_mm(run_index, *, rate_mm_per_run):
    """Offset added to z0 after ``run_index`` runs [mm]: rate * i."""
    return rate_mm_per_run * np.asarray(run_index, dtype=float)


def backlash_cam_deg(theta_deg, approach, *, width_deg):
    """Cam angle at the needle once a play of ``width_deg`` is taken up [deg].

    theta - width/2 * approach, where ``approach`` is +1 when the servo reached
    ``theta_deg`` moving up, -1 moving down (0: centred, unknown).
    """
    return np.asarray(theta_deg, dtype=float) - 0.5 * width_deg * np.asarray(approach, dtype=float)


def backlash_play_deg(cam_previous_deg, servo_deg, width_deg):
    """One step of the play operator [deg]: the cam stays where it was until
    the servo is ``width/2`` away, then it is dragged along.

    clip(cam_previous, servo - width/2, servo + width/2). In steady state
    this equals :func:`backlash_cam_deg` with the last direction of motion.
    """
    half = 0.5 * width_deg
    return min(max(cam_previous_deg, servo_deg - half), servo_deg + half)


def saturate_flow_core(q_mm3_s, q_max_mm3_s, sharpness):
    """Smooth flow cap on plain numbers: Q / (1 + (|Q|/q_max)^s)^(1/s) [mm^3/s].

    ``q_max`` = inf leaves Q unchanged.
    """
    return q_mm3_s / (1.0 + (np.abs(q_mm3_s) / q_max_mm3_s) ** sharpness) ** (1.0 / sharpness)


def saturate_flow(q, q_max, sharpness=8.0):
    """Smooth flow cap (arrays): ~Q well below ``q_max``, -> +-q_max above [mm^3/s].

    Rows with a non-finite ``q_max`` are returned unchanged.
    """
    q = np.asarray(q, dtype=float)
    q_max = np.asarray(q_max, dtype=float)
    m = np.isfinite(q_max)
    if not m.any():     # none capped, the usual case: nothing to do
        return q.copy()
    q_max, m = np.broadcast_to(q_max, q.shape), np.broadcast_to(m, q.shape)
    out = q.copy()
    out[m] = saturate_flow_core(q[m], q_max[m], sharpness)
    return out


def true_from_measured(measured, *, gain, sensor="pressure"):
    """Invert a scale error: measured / gain (``sensor`` names which one)."""
    return np.asarray(measured, dtype=float) / gain


# What an effect changes ---------------------------------------------------------

@dataclass(frozen=True)
class StaticForm:
    """An effect's place in discover's static fit of the flow steps (eq. 5).

    params : parameters fitted jointly with z0 and C of both sides
    x0, lower, upper : start values and bounds of ``params`` (units of the
        parameters)
    fixed : parameters held during the fit: a value (``sensor='pressure'``),
        or None for a discrete parameter that :meth:`Effect.static_search`
        sets on a grid before every fit (drift's ``every``/``offset``)
    needs : the per-run flow-step variables the form reads besides eq. (5)'s
        own inputs (attribute names of discover's ``FlowData``: ``run_index``,
        ``approach``, ``p_head_mpag``, ``q_mm3_s``, ...)
    """

    params: tuple[str, ...]
    x0: tuple[float, ...]
    lower: tuple[float, ...]
    upper: tuple[float, ...]
    fixed: Mapping[str, Any] = field(default_factory=dict)
    needs: tuple[str, ...] = ()

    @property
    def searched(self) -> tuple[str, ...]:
        """Names of the grid-searched parameters (``fixed`` value None)."""
        return tuple(k for k, v in self.fixed.items() if v is None)


@dataclass
class FlowTerms:
    """The per-run terms of the static flow model that effects change (one
    entry per flow step; :meth:`Effect.apply_static` edits its rows in place).

    Q = C c_multiplier (theta - theta_d(p1, dp; z0 + z0_offset))^2 dp^dp_exponent,
    then capped smoothly at ``q_max`` (eq. 3-5, :func:`saturate_flow`).

    theta_deg : cam angle at the needle [deg]
    p_head_mpag : A/B-port pressure as the valve sees it [MPaG]
    z0_offset_mm : added to the side's z0 [mm]
    c_multiplier : multiplies the side's C [-]
    dp_exponent : exponent of dp [-] (0.5: orifice law)
    q_max_mm3_s : flow cap [mm^3/s] (inf: none)
    corrections : closed-form terms applied after all that, in order
        (:class:`TermCorrection`, appended by the ``term`` effect's static
        form; :func:`apply_corrections` evaluates them)
    """

    theta_deg: np.ndarray
    p_head_mpag: np.ndarray
    z0_offset_mm: np.ndarray
    c_multiplier: np.ndarray
    dp_exponent: np.ndarray
    q_max_mm3_s: np.ndarray
    corrections: list = field(default_factory=list)


@dataclass(frozen=True)
class TermCorrection:
    """One closed-form correction of the static flow model: ``program``
    (:class:`~seanv_analysis.models.expr.Program`) acting in ``mode``
    (:data:`TERM_MODES`) on the flow steps where ``rows`` (a boolean mask
    over all of them) is True; ``side`` the valve it belongs to ('' until the
    static model tags it): its 'add' form acts in the other side's runs too,
    the valve sealed there (:func:`sealed_valve_terms`)."""

    rows: np.ndarray
    program: Program
    mode: str
    side: str = ""


@dataclass(frozen=True)
class ValveTerms:
    """How one side of the plant's valve differs from eq. (3)-(5) at one run
    (what the simulator packs for its kernel).

    c_multiplier : multiplies C [-]
    z0_offset_mm : added to z0 [mm]
    dp_exponent : exponent of dp [-]; None keeps the valve's own
    q_max_mm3_s : smooth flow cap [mm^3/s] (inf: none); sharpness: its knee [-]
    term_mode, term_program : a closed-form term of the side (``term``
        effect): its mode (:data:`TERM_MODES`) and compiled expression
        (None: no term)
    """

    c_multiplier: float = 1.0
    z0_offset_mm: float = 0.0
    dp_exponent: float | None = None
    q_max_mm3_s: float = math.inf
    sharpness: float = 8.0
    term_mode: str | None = None
    term_program: Program | None = None


class PlantTerms:
    """What effects add to the plant outside the valve: a value for every
    plant parameter an effect declares (:attr:`Effect.PLANT_PARAMS`: the
    backlash's play, the extra delay, the sensor gains...), by name, from
    its neutral value. Immutable: :meth:`plus` and :meth:`times` return a
    new one (effects fold in order: ``terms = effect.plant_terms(terms)``).
    The simulator packs each value under its name
    (:meth:`seanv_analysis.sim.plant.Plant.packed_params`)."""

    def __init__(self, values: Mapping[str, float] | None = None):
        self._values = {**plant_param_defaults(), **dict(values or {})}

    def __getitem__(self, name: str) -> float:
        return self._values[name]

    def items(self):
        return self._values.items()

    def __eq__(self, other: object) -> bool:
        return isinstance(other, PlantTerms) and self._values == other._values

    def __repr__(self) -> str:
        return f"PlantTerms({self._values!r})"

    def plus(self, name: str, value: float) -> "PlantTerms":
        """A copy with ``value`` added to parameter ``name``."""
        return PlantTerms({**self._values, name: self._values[name] + float(value)})

    def times(self, name: str, factor: float) -> "PlantTerms":
        """A copy with parameter ``name`` multiplied by ``factor``."""
        return PlantTerms({**self._values, name: self._values[name] * float(factor)})


def plant_param_defaults() -> dict[str, float]:
    """{name: neutral value} of every plant parameter the registered effects
    declare (:attr:`Effect.PLANT_PARAMS`), in registration order."""
    out: dict[str, float] = {}
    for cls in EFFECTS.values():
        for name, (neutral, _meaning) in cls.PLANT_PARAMS.items():
            out.setdefault(name, float(neutral))
    return out


# Effect classes ---------------------------------------------------------------

#: registry: effect name -> class, in the order the classes were defined
#: (discover tries its candidates in this order)
EFFECTS: dict[str, type[Effect]] = {}


@dataclass(frozen=True)
class Effect:
    """Base of the injectable effects: name, parameters, JSON form, and the
    hooks for discover (static form, sentence) and the simulator (dynamic form).

    A subclass sets ``name``, ``PARAMS`` ({parameter: "unit, meaning"}) and
    ``SENTENCE``, declares its parameters as dataclass fields with defaults,
    validates them in ``__post_init__`` (errors name the parameter), and
    overrides the hooks it has. Defining the subclass registers it in
    :data:`EFFECTS`; ``class Toy(Effect, register=False)`` does not (a test
    then adds it for its own duration).

    An effect with a ``side`` parameter is "sided": discover tries it once
    per valve side, and at most one effect of its name acts on each side.
    """

    name: ClassVar[str] = ""
    #: {parameter: its meaning, with its unit in brackets at the end of the
    #: quantity ("total play between servo and cam [deg]", "[-]" for a ratio)}
    PARAMS: ClassVar[dict[str, str]] = {}
    #: the plant parameters the effect acts through, outside the valve:
    #: {NAME: (neutral value, "meaning [unit]")}; the simulator packs them by
    #: name and its kernel reads ``pp[_NAME]`` (:mod:`seanv_analysis.sim._pp`)
    PLANT_PARAMS: ClassVar[dict[str, tuple[float, str]]] = {}
    #: one clause for the discovery report, ``str.format``-ed with ``side``
    #: and the fitted parameters (see :meth:`sentence`)
    SENTENCE: ClassVar[str] = ""
    #: the static form for discover's flow-step fit; None: the effect has none
    STATIC: ClassVar[StaticForm | None] = None
    #: the valve side's constant the effect moves with use (``"c_flow"``,
    #: ``"z0_mm"``; None: none): where it is named on the flow steps, that
    #: constant's value at runs outside their sequence (position-control runs)
    #: is not known from them, and the dynamic search refits it on those runs
    CHANGES_WITH_USE: ClassVar[str | None] = None
    #: a named effect of discover's vocabulary (it is tried as a candidate);
    #: False for the generic ``term``, which only holds a given expression
    VOCABULARY: ClassVar[bool] = True
    #: a parameter whose value runs to the end of a string spec, commas
    #: included (it must come last); None: every value ends at a comma
    TAIL_PARAM: ClassVar[str | None] = None

    @classmethod
    def param_units(cls) -> dict[str, str]:
        """{parameter: unit} of its numeric parameters: the unit its name
        carries (the package's unit table, :mod:`seanv_analysis.units`),
        else the bracket of its ``PARAMS`` entry; '-' for a ratio."""
        from ..units import unit_of_key

        out = {}
        for k, text in cls.PARAMS.items():
            named = unit_of_key(k)
            if named is not None:
                out[k] = named[1]
            elif "[" in text and "]" in text.rsplit("[", 1)[1]:
                out[k] = text.rsplit("[", 1)[1].split("]", 1)[0]
        return out

    def __init_subclass__(cls, register: bool = True, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if not register:
            return
        if not cls.name:
            raise ValueError(f"effect class {cls.__qualname__}: set a name")
        known = EFFECTS.get(cls.name)
        if known is not None and (known.__module__, known.__qualname__) != (cls.__module__,
                                                                             cls.__qualname__):
            raise ValueError(f"effect {cls.name!r}: registered twice ({known.__qualname__}, "
                             f"{cls.__qualname__})")
        EFFECTS[cls.name] = cls

    # parameters and text -----------------------------------------------------

    def params(self) -> dict[str, Any]:
        """Parameter values by name."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def to_json_dict(self) -> dict[str, Any]:
        return {"name": self.name, **self.params()}

    def spec(self) -> str:
        """The ``--effect`` string that rebuilds this effect."""
        return self.name + ":" + ",".join(f"{k}={v}" for k, v in self.params().items())

    def describe(self) -> str:
        """One line: name, parameters and the functional form."""
        return f"{self.spec()}  ({type(self).__doc__.strip().splitlines()[0]})"

    def slot(self) -> str | None:
        """What this effect acts on (a valve side, a sensor channel): two
        effects of one name on the same slot are a duplicate."""
        return getattr(self, "side", None)

    @classmethod
    def sided(cls) -> bool:
        """True when the effect acts on one valve side (it has a ``side``)."""
        return "side" in cls.PARAMS

    @classmethod
    def sentence(cls, side: str, params: Mapping[str, Any]) -> str:
        """The report's clause for this effect found on ``side`` with ``params``.

        Raises
        ------
        KeyError, ValueError
            ``params`` lacks a value the sentence names, or one of the wrong kind.
        """
        if not cls.SENTENCE:
            raise KeyError(cls.name)
        return cls.SENTENCE.format(side=side, **params)

    @classmethod
    def from_fit(cls, side: str, params: Mapping[str, Any]) -> Effect:
        """The effect as discover found it: ``side`` and the fitted ``params``
        (keys the class does not take, and None values, are dropped).

        Raises
        ------
        ValueError
            A value out of the parameter's range.
        """
        known = {f.name for f in fields(cls)}
        raw = {"side": side, **{k: v for k, v in params.items() if v is not None}}
        return parse_effect({"name": cls.name, **{k: v for k, v in raw.items() if k in known}})

    # static form (discover) ------------------------------------------------------

    @classmethod
    def static_form(cls, data: Any, side: str) -> StaticForm | None:
        """The candidate on ``side`` ('supply'/'drain'; 'both' when not
        sided) for flow-step ``data`` (discover's ``FlowData``), or None when
        the data cannot identify the effect. Default: :attr:`STATIC`."""
        return cls.STATIC

    @classmethod
    def apply_static(cls, terms: FlowTerms, data: Any, rows: np.ndarray,
                     p: Mapping[str, Any]) -> None:
        """Change the static model's ``terms`` on ``rows`` (boolean mask)
        for parameter values ``p`` (fitted and fixed, by name).

        ``data`` is the flow-step data (discover's ``FlowData``); read only
        the variables named in ``STATIC.needs``.
        """
        raise ValueError(f"effect {cls.name!r} has no static form")

    @classmethod
    def static_search(cls, data: Any, rows: np.ndarray, q_base_mm3_s: np.ndarray,
                      sigma_mm3_s: np.ndarray) -> tuple[tuple[float, ...], dict[str, Any]]:
        """Grid search of the ``fixed`` parameters marked None in the static
        form, on ``rows`` of ``data`` against the base model's flow
        ``q_base_mm3_s`` with noise ``sigma_mm3_s``.

        Returns (start values of the fitted parameters, fixed parameter values).
        """
        raise ValueError(f"effect {cls.name!r}: no grid search for its static form")

    # dynamic form (simulator) ---------------------------------------------------------

    def valve_terms(self, terms: ValveTerms, side: str, run_index: int) -> ValveTerms:
        """``terms`` of the plant valve's ``side`` at run ``run_index`` with
        this effect added. Default: unchanged."""
        return terms

    def plant_terms(self, terms: PlantTerms) -> PlantTerms:
        """``terms`` of the rest of the plant with this effect added.
        Default: unchanged."""
        return terms

    @classmethod
    def has_dynamic_form(cls) -> bool:
        """True when the simulator's plant puts the effect in (it overrides
        :meth:`valve_terms` or :meth:`plant_terms`)."""
        return (cls.valve_terms is not Effect.valve_terms
                or cls.plant_terms is not Effect.plant_terms)

    # validation helpers ------------------------------------------------------------

    def _check_side(self) -> None:
        side = self.side  # only sided effects call this
        if side not in _SIDES:
            raise ValueError(f"{self.name}: side: expected 'supply' or 'drain', got {side!r}")

    def _check(self, ok: bool, param: str, expected: str) -> None:
        if not ok:
            raise ValueError(f"{self.name}: {param}: expected {expected}, "
                             f"got {getattr(self, param)!r}")


@dataclass(frozen=True)
class Drift(Effect):
    """C of one side falls stepwise with use: C (1 - step)^floor((i + offset)/every)."""

    name: ClassVar[str] = "drift"
    PARAMS: ClassVar[dict[str, str]] = {
        "side": "'supply' | 'drain'",
        "step": "fractional fall of C per step [-] (0.05 = 5 %)",
        "every": "runs between steps [runs]",
        "offset": "phase: runs already counted at run 0 [runs]",
    }
    SENTENCE: ClassVar[str] = (
        "the flow coefficient C of the {side} side {direction} by {abs_step:.2%} every {every} runs "
        "(C (1 - step)^floor((i + offset)/every), step = {step:+.4f})")
    STATIC: ClassVar[StaticForm] = StaticForm(("step",), (0.02,), (-0.5,), (0.5,),
                                              {"every": None, "offset": None}, ("run_index",))
    #: longest drift period the static search tries [runs]
    MAX_EVERY: ClassVar[int] = 12
    CHANGES_WITH_USE: ClassVar[str | None] = "c_flow"

    side: str = "drain"
    step: float = 0.05
    every: int = 3
    offset: int = 0

    def __post_init__(self):
        self._check_side()
        self._check(-1.0 < self.step < 1.0, "step", "a fraction in (-1, 1)")
        self._check(int(self.every) == self.every and self.every >= 1, "every", "an integer >= 1")
        self._check(int(self.offset) == self.offset and self.offset >= 0, "offset",
                    "an integer >= 0")

    def c_multiplier(self, run_index):
        """Multiplier of the side's C at run ``run_index`` [-]."""
        return drift_multiplier(run_index, step=self.step, every=self.every, offset=self.offset)

    @classmethod
    def sentence(cls, side, params):
        step = float(params["step"])
        return cls.SENTENCE.format(side=side, **params, direction="falls" if step > 0 else "rises",
                                   abs_step=abs(step))

    @classmethod
    def apply_static(cls, terms, data, rows, p):
        terms.c_multiplier[rows] *= drift_multiplier(data.run_index[rows], **p)

    @classmethod
    def static_search(cls, data, rows, q_base_mm3_s, sigma_mm3_s):
        """Profile the stepwise drift: best (every, offset, step) with z0, C
        at the base fit and a free scale, by a vectorised grid over the step."""
        q = data.q_mm3_s[rows]
        q0 = q_base_mm3_s[rows]
        w = 1.0 / sigma_mm3_s[rows]
        idx = data.run_index[rows]
        steps = np.linspace(-0.3, 0.3, 241)
        # (1 - step)^k for every whole k the grid meets, made once: (steps, k)
        k_all = np.floor(idx + np.arange(cls.MAX_EVERY)[:, None])
        k_lo = float(np.min(k_all, initial=0.0))
        powers = (1.0 - steps[:, None]) ** np.arange(k_lo, np.max(k_all, initial=0.0) + 1)
        results = []
        for every in range(1, cls.MAX_EVERY + 1):
            for offset in range(every):
                k = np.floor((idx + offset) / every)
                mult = powers[:, (k - k_lo).astype(np.intp)]        # (steps, runs)
                g = mult * q0[None, :] * w[None, :]
                y = q * w
                a = (g @ y) / np.maximum(np.sum(g * g, axis=1), 1e-300)  # best scale per step
                rss = np.sum((y[None, :] - a[:, None] * g) ** 2, axis=1)
                j = int(np.argmin(rss))
                results.append((float(rss[j]), every, offset, float(steps[j])))
        # Periods alias (4 % every 3 runs ~ 7.8 % every 6): among fits within
        # 2 units of weighted RSS of the best (indistinguishable), take the
        # shortest period.
        best_rss = min(r[0] for r in results)
        close = [r for r in results if r[0] <= best_rss + 2.0]
        _, every, offset, step = min(close, key=lambda r: (r[1], r[0]))
        return (step,), {"every": every, "offset": offset}

    def valve_terms(self, terms, side, run_index):
        if side != self.side:
            return terms
        return replace(terms, c_multiplier=terms.c_multiplier * float(self.c_multiplier(run_index)))


@dataclass(frozen=True)
class ThresholdShift(Effect):
    """z0 of one side creeps with use: z0 + rate_mm_per_run * i (moves theta_d)."""

    name: ClassVar[str] = "threshold_shift"
    PARAMS: ClassVar[dict[str, str]] = {
        "side": "'supply' | 'drain'",
        "rate_mm_per_run": "change of z0 per run [mm/run] (1e-5 mm ~ 0.002 deg of theta_d)",
    }
    SENTENCE: ClassVar[str] = ("the {side} sealing threshold creeps with use "
                               "(z0 changes {rate_mm_per_run:+.2e} mm per run)")
    STATIC: ClassVar[StaticForm] = StaticForm(("rate_mm_per_run",), (0.0,), (-0.01,), (0.01,),
                                              needs=("run_index",))
    CHANGES_WITH_USE: ClassVar[str | None] = "z0_mm"

    side: str = "supply"
    rate_mm_per_run: float = 2.0e-5

    def __post_init__(self):
        self._check_side()
        self._check(abs(self.rate_mm_per_run) < 1e-2, "rate_mm_per_run", "|rate| < 0.01 mm/run")

    def z0_offset_mm(self, run_index):
        """Offset added to the side's z0 at run ``run_index`` [mm]."""
        return threshold_shift_mm(run_index, rate_mm_per_run=self.rate_mm_per_run)

    @classmethod
    def apply_static(cls, terms, data, rows, p):
        terms.z0_offset_mm[rows] += threshold_shift_mm(data.run_index[rows], **p)

    def valve_terms(self, terms, side, run_index):
        if side != self.side:
            return terms
        return replace(terms, z0_offset_mm=terms.z0_offset_mm + float(self.z0_offset_mm(run_index)))


@dataclass(frozen=True)
class Backlash(Effect):
    """Dead band of width_deg between servo and cam: the needle lags width/2 behind
    the servo in the direction it last moved."""

    name: ClassVar[str] = "backlash"
    PARAMS: ClassVar[dict[str, str]] = {"width_deg": "total play between servo and cam [deg]"}
    PLANT_PARAMS: ClassVar[dict[str, tuple[float, str]]] = {
        "BACKLASH": (0.0, "total play between servo and cam [deg]")}
    SENTENCE: ClassVar[str] = ("the cam has a direction-dependent dead band of {width_deg:.2f} deg "
                               "(backlash)")
    STATIC: ClassVar[StaticForm] = StaticForm(("width_deg",), (0.5,), (0.0,), (10.0,),
                                              needs=("approach",))

    width_deg: float = 2.0

    def __post_init__(self):
        self._check(0.0 <= self.width_deg <= 20.0, "width_deg", "0..20 deg")

    @classmethod
    def static_form(cls, data, side):
        # the play shows only as a difference between the two approach directions
        if np.unique(data.approach[data.approach != 0]).size == 2:
            return cls.STATIC
        return None

    @classmethod
    def apply_static(cls, terms, data, rows, p):
        terms.theta_deg[rows] = backlash_cam_deg(terms.theta_deg[rows], data.approach[rows], **p)

    def plant_terms(self, terms):
        return terms.plus("BACKLASH", self.width_deg)


@dataclass(frozen=True)
class PressureLaw(Effect):
    """Flow of one side follows dp^exponent instead of sqrt(dp)."""

    name: ClassVar[str] = "pressure_law"
    PARAMS: ClassVar[dict[str, str]] = {"side": "'supply' | 'drain'",
                                        "exponent": "n in Q = C (theta - theta_d)^2 dp^n [-]"}
    SENTENCE: ClassVar[str] = "the {side} flow follows dp^{exponent:.2f}, not the orifice law dp^0.5"
    STATIC: ClassVar[StaticForm] = StaticForm(("exponent",), (0.5,), (0.05,), (1.5,))

    side: str = "supply"
    exponent: float = 0.7

    def __post_init__(self):
        self._check_side()
        self._check(0.05 <= self.exponent <= 2.0, "exponent", "0.05..2")

    @classmethod
    def apply_static(cls, terms, data, rows, p):
        terms.dp_exponent[rows] = p["exponent"]

    def valve_terms(self, terms, side, run_index):
        return replace(terms, dp_exponent=self.exponent) if side == self.side else terms


@dataclass(frozen=True)
class Saturation(Effect):
    """Flow of one side is capped smoothly at large openings:
    Q / (1 + (|Q|/q_max)^s)^(1/s)."""

    name: ClassVar[str] = "saturation"
    PARAMS: ClassVar[dict[str, str]] = {"side": "'supply' | 'drain'",
                                        "q_max_mm3_s": "flow cap magnitude [mm^3/s]",
                                        "sharpness": "s, how sharp the knee is [-]"}
    SENTENCE: ClassVar[str] = ("the {side} flow saturates at about {q_max_mm3_s:.0f} mm^3/s "
                               "at large openings")
    #: bounds for a side whose largest |Q| is 1e4 mm^3/s; :meth:`static_form`
    #: scales them to the data's largest |Q|
    STATIC: ClassVar[StaticForm] = StaticForm(("q_max_mm3_s",), (1.2e4,), (1e3,), (1e5,),
                                              needs=("q_mm3_s",))

    side: str = "supply"
    q_max_mm3_s: float = 5000.0
    sharpness: float = 8.0

    def __post_init__(self):
        self._check_side()
        self._check(self.q_max_mm3_s > 0, "q_max_mm3_s", "a positive flow")
        self._check(1.0 <= self.sharpness <= 50.0, "sharpness", "1..50")

    @classmethod
    def static_form(cls, data, side):
        # a cap is only identifiable near the flows measured: start 20 % above
        # the side's largest |Q|, search 0.1x..10x of it
        on_side = data.side == side
        if not np.any(on_side):
            return cls.STATIC
        qmax = float(np.nanmax(np.abs(data.q_mm3_s[on_side])))
        return replace(cls.STATIC, x0=(1.2 * qmax,), lower=(0.1 * qmax,), upper=(10 * qmax,))

    @classmethod
    def apply_static(cls, terms, data, rows, p):
        terms.q_max_mm3_s[rows] = p["q_max_mm3_s"]

    def valve_terms(self, terms, side, run_index):
        if side != self.side:
            return terms
        return replace(terms, q_max_mm3_s=abs(self.q_max_mm3_s), sharpness=self.sharpness)


@dataclass(frozen=True)
class Delay(Effect):
    """Extra transport delay delay_s between the servo and the needle (after the
    servo's own feedback, so the servo log does not show it)."""

    name: ClassVar[str] = "delay"
    PARAMS: ClassVar[dict[str, str]] = {"delay_s": "extra dead time [s]"}
    PLANT_PARAMS: ClassVar[dict[str, tuple[float, str]]] = {
        "DELAY": (0.0, "extra transport delay between servo and needle [s]")}
    # found on position-control runs (discover.dynamic), not by the static fit
    SENTENCE: ClassVar[str] = ("the flow lags Q_ref by an extra {delay_s:.3f} s beyond the nominal "
                               "lag (transport delay)")

    delay_s: float = 0.1

    def __post_init__(self):
        self._check(0.0 <= self.delay_s <= 2.0, "delay_s", "0..2 s")

    def plant_terms(self, terms):
        return terms.plus("DELAY", self.delay_s)


@dataclass(frozen=True)
class SensorGain(Effect):
    """Scale error of one sensor: measured = gain * true."""

    name: ClassVar[str] = "sensor_gain"
    PARAMS: ClassVar[dict[str, str]] = {
        "sensor": "'encoder' | 'pressure' (= 'p_head', the A/B-port sensor) | 'p_supply' | 'p_load'",
        "gain": "measured / true [-]"}
    SENTENCE: ClassVar[str] = "a {sensor} sensor reads {gain:.3f} x the true value"
    # the flow steps see the head sensor only through dp of both sides
    STATIC: ClassVar[StaticForm] = StaticForm(("gain",), (1.0,), (0.5,), (2.0,),
                                              {"sensor": "pressure"}, ("p_head_mpag",))
    #: the plant parameter of each channel's gain
    GAIN_PARAM: ClassVar[dict[str, str]] = {"position_mm": "GAIN_X", "p_supply_mpag": "GAIN_PS",
                                            "p_head_mpag": "GAIN_PH", "p_load_mpag": "GAIN_PL"}
    PLANT_PARAMS: ClassVar[dict[str, tuple[float, str]]] = {
        "GAIN_X": (1.0, "encoder: measured / true [-]"),
        "GAIN_PS": (1.0, "supply pressure sensor: measured / true [-]"),
        "GAIN_PH": (1.0, "head pressure sensor: measured / true [-]"),
        "GAIN_PL": (1.0, "load pressure sensor: measured / true [-]")}

    sensor: str = "pressure"
    gain: float = 1.05

    def __post_init__(self):
        if self.sensor not in SENSORS:
            raise ValueError(f"{self.name}: sensor: expected one of {', '.join(SENSORS)}, "
                             f"got {self.sensor!r}")
        self._check(0.2 <= self.gain <= 5.0, "gain", "0.2..5")

    @property
    def channel(self) -> str:
        """Column the gain applies to: 'position_mm' or 'p_*_mpag'."""
        if self.sensor == "encoder":
            return "position_mm"
        return "p_head_mpag" if self.sensor in ("pressure", "p_head") else f"{self.sensor}_mpag"

    def slot(self) -> str | None:
        return self.channel

    @classmethod
    def apply_static(cls, terms, data, rows, p):
        terms.p_head_mpag[rows] = true_from_measured(terms.p_head_mpag[rows], **p)

    def plant_terms(self, terms):
        return terms.times(self.GAIN_PARAM[self.channel], self.gain)


@dataclass(frozen=True)
class Term(Effect):
    """Closed-form correction f of one side: Q (1 + f), Q + f or theta_d + f.

    The modes 'mul', 'add' and 'threshold'; f an expression of dp, p1,
    dtheta, theta, q, load, run and approach.

    Not a named effect: it carries a formula (one found by a search, or one a
    test injects), so discover never tries it as a candidate
    (``VOCABULARY`` False). The expression grammar, its variables and their
    units are those of :mod:`seanv_analysis.models.expr`; ``expr`` is kept in
    its canonical form. In a string spec ``expr`` runs to the end of the
    spec, commas included (``term:side=supply,mode=mul,expr=clip(dp, 0, 1)``),
    or it is quoted. One term per side.

    Forms: 'mul' Q -> Q (1 + f) [f in -]; 'add' Q -> Q + f [f in mm^3/s, in
    eq. (5)'s signs: the drain side's flow is negative]; 'threshold'
    theta_d -> theta_d + f [f in deg] (eq. 3-4's threshold, so the opening
    and Q follow). q is the side's flow before the term (for 'threshold',
    at the unshifted threshold); dtheta the opening past the threshold in use.
    """

    name: ClassVar[str] = "term"
    PARAMS: ClassVar[dict[str, str]] = {
        "side": "'supply' | 'drain'",
        "mode": "'mul': Q -> Q (1 + expr) | 'add': Q -> Q + expr [mm^3/s] | "
                "'threshold': theta_d -> theta_d + expr [deg]",
        "expr": "the correction: an expression of dp, p1 [MPa], dtheta, theta [deg], "
                "q [mm^3/s], load [MPaG], run, approach [-] (see seanv_analysis.models.expr); "
                "last in a spec, where it may contain commas",
    }
    SENTENCE: ClassVar[str] = "the {side} side needs a closed-form correction: {form}"
    _FORMS: ClassVar[dict[str, str]] = {"mul": "Q -> Q (1 + {expr})",
                                        "add": "Q -> Q + {expr} [mm^3/s]",
                                        "threshold": "theta_d -> theta_d + {expr} [deg]"}
    #: nothing to fit: the expression and mode are fixed (a spec sets them)
    STATIC: ClassVar[StaticForm] = StaticForm((), (), (), (), {"mode": "mul", "expr": "0"},
                                              ("run_index", "approach", "load_mpag"))
    VOCABULARY: ClassVar[bool] = False
    TAIL_PARAM: ClassVar[str] = "expr"

    side: str = "supply"
    mode: str = "mul"
    expr: str = "0"

    def __post_init__(self):
        self._check_side()
        if self.mode not in TERM_MODES:
            raise ValueError(f"{self.name}: mode: expected one of {', '.join(TERM_MODES)}, "
                             f"got {self.mode!r}")
        try:
            program = compile_expr(self.expr)
        except ValueError as exc:
            raise ValueError(f"{self.name}: {exc}") from None
        object.__setattr__(self, "expr", program.text)
        self.__dict__["program"] = program

    @cached_property
    def program(self) -> Program:
        """The compiled expression (:class:`~seanv_analysis.models.expr.Program`)."""
        return compile_expr(self.expr)

    @classmethod
    def sentence(cls, side, params):
        mode = str(params.get("mode", "mul"))
        form = cls._FORMS.get(mode, mode + ": {expr}").format(expr=params.get("expr", "?"))
        return cls.SENTENCE.format(side=side, form=form)

    @staticmethod
    def linear_expr(coefficients: Iterable[float], features: Iterable[str], *,
                    digits: int = 4) -> str:
        """The expression a1*(g1) + a2*(g2) + ... of ``features`` (expression
        texts) with ``coefficients`` written to ``digits`` significant digits
        (the form discover's term search proposes), canonical."""
        parts = [f"{float(a):.{digits}g}*({g})" for a, g in zip(coefficients, features)]
        return compile_expr(" + ".join(parts) or "0").text

    @classmethod
    def apply_static(cls, terms, data, rows, p):
        """The term's correction on ``rows``; with ``features`` (expression
        texts, a fixed parameter) the expression is sum_k a_k g_k of them,
        the a_k the fitted parameters a1, a2, ... (the term search's refit)."""
        mode = p.get("mode", "mul")
        if mode not in TERM_MODES:
            raise ValueError(f"{cls.name}: mode: expected one of {', '.join(TERM_MODES)}, "
                             f"got {mode!r}")
        features = p.get("features")
        expr = (cls.linear_expr([p[f"a{k + 1}"] for k in range(len(features))], features,
                                digits=17) if features else p.get("expr", "0"))
        try:
            program = compile_expr(expr)
        except ValueError as exc:
            raise ValueError(f"{cls.name}: {exc}") from None
        mask = np.zeros(len(terms.theta_deg), bool)
        mask[rows] = True
        terms.corrections.append(TermCorrection(mask, program, mode))

    def valve_terms(self, terms, side, run_index):
        if side != self.side:
            return terms
        return replace(terms, term_mode=self.mode, term_program=self.program)


# Closed-form terms in the static model ------------------------------------------

def term_variables(*, dp_mpa, p1_mpa, dtheta_deg, theta_deg, q_mm3_s, load_mpag, run_index,
                   approach) -> dict[str, np.ndarray]:
    """The variables of :mod:`.expr` by name, from the flow model's
    quantities (units as the names; module doc of :mod:`.expr`)."""
    return {"dp": dp_mpa, "p1": p1_mpa, "dtheta": dtheta_deg, "theta": theta_deg,
            "q": q_mm3_s, "load": load_mpag, "run": run_index, "approach": approach}


def apply_corrections(corrections: Iterable[TermCorrection], rows: np.ndarray, *,
                      flow_at: Callable[[np.ndarray], np.ndarray], theta_deg, theta_d_deg,
                      p1_mpa, dp_mpa, opens_upward: bool, load_mpag, run_index,
                      approach) -> np.ndarray:
    """Flow of one valve side with the closed-form terms of ``corrections``
    [mm^3/s] (eq. 5 and the ``term`` effect's three forms).

    Parameters
    ----------
    corrections : the terms (:class:`TermCorrection`, their ``rows`` masks
        over all flow steps); 'threshold' ones first, then 'mul' and 'add' in
        the order given
    rows : boolean mask of this side's flow steps (the other arrays hold
        these rows only)
    flow_at : theta_d [deg] -> the side's flow of eq. (5) [mm^3/s] at that
        threshold (all other effects applied)
    theta_deg, theta_d_deg : cam angle at the needle and sealing threshold [deg]
    p1_mpa, dp_mpa : the side's upstream pressure and pressure difference [MPa]
    opens_upward : True for the supply side (opening = theta - theta_d)
    load_mpag, run_index, approach : load [MPaG], run order [-], cam
        approach direction [-]

    Returns
    -------
    The flow with the terms [mm^3/s].
    """
    corrections = [c for c in corrections if np.any(c.rows[rows])]
    theta_d = np.asarray(theta_d_deg, dtype=float)
    q = flow_at(theta_d)

    def variables(sub, th_d, q_now):
        d = theta_deg[sub] - th_d[sub]
        return term_variables(dp_mpa=dp_mpa[sub], p1_mpa=p1_mpa[sub],
                              dtheta_deg=d if opens_upward else -d, theta_deg=theta_deg[sub],
                              q_mm3_s=q_now[sub], load_mpag=load_mpag[sub],
                              run_index=run_index[sub], approach=approach[sub])

    shifted = [c for c in corrections if c.mode == "threshold"]
    if shifted:
        th = theta_d.copy()
        for c in shifted:
            sub = c.rows[rows]
            th[sub] = th[sub] + evaluate(c.program, variables(sub, theta_d, q))
        theta_d = th
        q = flow_at(theta_d)
    q = np.array(q, dtype=float)
    for c in corrections:
        if c.mode == "threshold":
            continue
        sub = c.rows[rows]
        f = evaluate(c.program, variables(sub, theta_d, q))
        q[sub] = q[sub] * (1.0 + f) if c.mode == "mul" else q[sub] + f
    return q


def sealed_valve_terms(corrections: Iterable[TermCorrection], *, side: str, theta_deg,
                       theta_d_deg, p1_mpa, dp_mpa, opens_upward: bool, load_mpag, run_index,
                       approach) -> np.ndarray:
    """Flow of valve ``side`` while it is sealed [mm^3/s] (the other side's
    flow steps; the arrays hold those rows, in ``side``'s valve's pressures):
    eq. (5) gives 0 and so do its 'mul' and 'threshold' terms, but an 'add'
    term (a leak past the needle) acts open or sealed, as in the simulator,
    where both valves feed the head at every instant."""
    q = np.zeros(np.shape(theta_deg))
    d = np.asarray(theta_deg, float) - theta_d_deg
    variables = term_variables(dp_mpa=dp_mpa, p1_mpa=p1_mpa,
                               dtheta_deg=d if opens_upward else -d, theta_deg=theta_deg,
                               q_mm3_s=np.zeros_like(q), load_mpag=load_mpag,
                               run_index=run_index, approach=approach)
    for c in corrections:
        if c.mode == "add" and c.side == side:
            q = q + evaluate(c.program, variables)
    return q


# Registry readers ---------------------------------------------------------------

def static_effects() -> list[type[Effect]]:
    """Registered effects with a static form, in registry order (the
    generic ``term`` included; discover's candidates are
    :func:`vocabulary_effects`)."""
    return [cls for cls in EFFECTS.values() if cls.STATIC is not None]


def vocabulary_effects() -> list[type[Effect]]:
    """Discover's candidates: the named effects (``VOCABULARY``) with a
    static form, in registry order; the generic ``term`` is not one."""
    return [cls for cls in static_effects() if cls.VOCABULARY]


def dynamic_effects() -> list[type[Effect]]:
    """Registered effects the simulator's plant can put in, in registry order."""
    return [cls for cls in EFFECTS.values() if cls.has_dynamic_form()]


# Parsing -------------------------------------------------------------------------

def _convert(cls: type[Effect], key: str, text: str):
    ftype = {f.name: f.type for f in fields(cls)}[key]
    ftype = ftype if isinstance(ftype, str) else getattr(ftype, "__name__", str(ftype))
    try:
        if ftype == "int":
            value = float(text)
            if value != int(value):
                raise ValueError
            return int(value)
        if ftype == "float":
            value = float(text)
            if not math.isfinite(value):
                raise ValueError
            return value
    except ValueError:
        raise ValueError(f"{cls.name}: {key}: expected a{'n integer' if ftype == 'int' else ' number'}, "
                         f"got {text!r}") from None
    return text


def parse_effect(spec: str | Effect | dict) -> Effect:
    """Build an effect from ``"name[:param=value,...]"`` (or a dict / an Effect).

    Missing parameters take the class defaults.

    Raises
    ------
    ValueError
        Unknown effect or parameter, or a value of the wrong type or range.
    """
    if isinstance(spec, Effect):
        return spec
    if isinstance(spec, dict):
        d = dict(spec)
        name = d.pop("name", None)
        if name not in EFFECTS:
            raise ValueError(f"effect: unknown effect {name!r}; expected one of {', '.join(EFFECTS)}")
        cls = EFFECTS[name]
        unknown = set(d) - {f.name for f in fields(cls)}
        if unknown:
            raise ValueError(f"{name}: unknown parameter(s) {', '.join(sorted(unknown))}; "
                             f"expected {', '.join(cls.PARAMS)}")
        return cls(**{k: _convert(cls, k, str(v)) for k, v in d.items()})
    text = str(spec).strip()
    name, _, rest = text.partition(":")
    name = name.strip()
    if name not in EFFECTS:
        raise ValueError(f"effect: unknown effect {name!r} in {text!r}; "
                         f"expected one of {', '.join(EFFECTS)}")
    cls = EFFECTS[name]
    kwargs: dict[str, Any] = {}
    for key, value in _spec_items(cls, rest):
        if key not in cls.PARAMS:
            raise ValueError(f"{name}: unknown parameter {key!r}; expected {', '.join(cls.PARAMS)}")
        kwargs[key] = _convert(cls, key, value)
    return cls(**kwargs)


def _spec_items(cls: type[Effect], rest: str) -> list[tuple[str, str]]:
    """(key, value) pairs of the ``param=value,...`` part of a spec. A value
    ends at the next comma, unless it is quoted ('...' or "...") or belongs
    to the class's ``TAIL_PARAM`` (then it runs to the end of the spec)."""
    name = cls.name
    out = []
    i, n = 0, len(rest)
    while i < n:
        if rest[i] in ", \t":
            i += 1
            continue
        comma = rest.find(",", i)
        end = n if comma < 0 else comma
        eq = rest.find("=", i, end)
        if eq < 0:
            raise ValueError(f"{name}: expected param=value, got {rest[i:end].strip()!r}")
        key = rest[i:eq].strip()
        k = eq + 1
        while k < n and rest[k] in " \t":
            k += 1
        if k < n and rest[k] in "'\"":
            close = rest.find(rest[k], k + 1)
            if close < 0:
                raise ValueError(f"{name}: {key}: the quote {rest[k]} is not closed in "
                                 f"{rest[k:]!r}")
            value = rest[k + 1:close]
            i = close + 1
            while i < n and rest[i] in " \t":
                i += 1
            if i < n and rest[i] != ",":
                raise ValueError(f"{name}: {key}: expected ',' after the quoted value, got "
                                 f"{rest[i:]!r}")
        elif key == cls.TAIL_PARAM:
            value = rest[k:].strip()
            i = n
        else:
            value = rest[k:end].strip()
            i = end
        if not value.strip():
            raise ValueError(f"{name}: expected param=value, got {key + '='!r}")
        out.append((key, value))
    return out


def parse_effects(specs: Iterable[str | Effect | dict] | None) -> tuple[Effect, ...]:
    """Parse several effects; one effect of a name per side/sensor at most.

    Raises
    ------
    ValueError
        On a bad spec or a duplicate (same name and side/sensor).
    """
    out = tuple(parse_effect(s) for s in (specs or ()))
    seen = set()
    for e in out:
        key = (e.name, e.slot())
        if key in seen:
            raise ValueError(f"effect: {e.name} given twice" + (f" for {key[1]}" if key[1] else ""))
        seen.add(key)
    return out
