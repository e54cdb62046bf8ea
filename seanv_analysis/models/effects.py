"""Injectable plant effects: small, named extensions of the valve model.

These are the "undeclared effects" that the simulator can put into the plant
(``seanv-analyze simulate --effect NAME:k=v,...``) and that
:mod:`seanv_analysis.discover` later looks for in data. Each effect is a
frozen dataclass with its parameters (units in the names or docstrings) and
its functional form as a plain function below, so the simulator and the
discovery fit use the same equations.

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
========================  =====================================================

Examples
--------
>>> from seanv_analysis.models.effects import parse_effect
>>> e = parse_effect("drift:side=drain,step=0.05,every=3")
>>> float(e.c_multiplier(5))
0.95
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any, ClassVar, Iterable

import numpy as np

from ..errors import ConfigError

__all__ = [
    "Effect", "Drift", "ThresholdShift", "Backlash", "PressureLaw", "Saturation", "Delay",
    "SensorGain", "EFFECTS", "SENSORS", "parse_effect", "parse_effects",
    "drift_multiplier", "threshold_shift_mm", "backlash_cam_deg", "backlash_play_deg",
    "saturate_flow", "saturate_flow_core", "measured_from_true", "true_from_measured",
]

_SIDES = ("supply", "drain")
#: sensors a ``sensor_gain`` can act on; 'pressure' is the A/B-port (head) sensor
SENSORS = ("encoder", "pressure", "p_head", "p_supply", "p_load")


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
    q_max = np.broadcast_to(np.asarray(q_max, dtype=float), q.shape)
    out = q.copy()
    m = np.isfinite(q_max)
    out[m] = saturate_flow_core(q[m], q_max[m], sharpness)
    return out


def measured_from_true(true, *, gain):
    """Sensor reading with a scale error: gain * true."""
    return gain * np.asarray(true, dtype=float)


def true_from_measured(measured, *, gain, sensor="pressure"):
    """Invert a scale error: measured / gain (``sensor`` names which one)."""
    return np.asarray(measured, dtype=float) / gain


# Effect classes ---------------------------------------------------------------

@dataclass(frozen=True)
class Effect:
    """Base of the injectable effects: name, parameters, JSON form.

    Subclasses set ``name`` and ``PARAMS`` ({parameter: "unit, meaning"}) and
    validate their values in ``__post_init__`` (errors name the parameter).
    """

    name: ClassVar[str] = ""
    PARAMS: ClassVar[dict[str, str]] = {}

    def params(self) -> dict[str, Any]:
        """Parameter values by name."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, **self.params()}

    def spec(self) -> str:
        """The ``--effect`` string that rebuilds this effect."""
        return self.name + ":" + ",".join(f"{k}={v}" for k, v in self.params().items())

    def describe(self) -> str:
        """One line: name, parameters and the functional form."""
        return f"{self.spec()}  ({type(self).__doc__.strip().splitlines()[0]})"

    # helpers for validation
    def _check_side(self) -> None:
        side = getattr(self, "side")
        if side not in _SIDES:
            raise ConfigError(f"{self.name}: side: expected 'supply' or 'drain', got {side!r}")

    def _check(self, ok: bool, param: str, expected: str) -> None:
        if not ok:
            raise ConfigError(f"{self.name}: {param}: expected {expected}, "
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


@dataclass(frozen=True)
class ThresholdShift(Effect):
    """z0 of one side creeps with use: z0 + rate_mm_per_run * i (moves theta_d)."""

    name: ClassVar[str] = "threshold_shift"
    PARAMS: ClassVar[dict[str, str]] = {
        "side": "'supply' | 'drain'",
        "rate_mm_per_run": "change of z0 per run [mm/run] (1e-5 mm ~ 0.002 deg of theta_d)",
    }
    side: str = "supply"
    rate_mm_per_run: float = 2.0e-5

    def __post_init__(self):
        self._check_side()
        self._check(abs(self.rate_mm_per_run) < 1e-2, "rate_mm_per_run", "|rate| < 0.01 mm/run")

    def z0_offset_mm(self, run_index):
        """Offset added to the side's z0 at run ``run_index`` [mm]."""
        return threshold_shift_mm(run_index, rate_mm_per_run=self.rate_mm_per_run)


@dataclass(frozen=True)
class Backlash(Effect):
    """Dead band of width_deg between servo and cam: the needle lags width/2 behind
    the servo in the direction it last moved."""

    name: ClassVar[str] = "backlash"
    PARAMS: ClassVar[dict[str, str]] = {"width_deg": "total play between servo and cam [deg]"}
    width_deg: float = 2.0

    def __post_init__(self):
        self._check(0.0 <= self.width_deg <= 20.0, "width_deg", "0..20 deg")

    def cam_at_needle_deg(self, theta_deg, approach):
        """Needle-side cam angle for a servo angle reached from ``approach`` (+1/-1) [deg]."""
        return backlash_cam_deg(theta_deg, approach, width_deg=self.width_deg)


@dataclass(frozen=True)
class PressureLaw(Effect):
    """Flow of one side follows dp^exponent instead of sqrt(dp)."""

    name: ClassVar[str] = "pressure_law"
    PARAMS: ClassVar[dict[str, str]] = {"side": "'supply' | 'drain'",
                                        "exponent": "n in Q = C (theta - theta_d)^2 dp^n [-]"}
    side: str = "supply"
    exponent: float = 0.7

    def __post_init__(self):
        self._check_side()
        self._check(0.05 <= self.exponent <= 2.0, "exponent", "0.05..2")


@dataclass(frozen=True)
class Saturation(Effect):
    """Flow of one side is capped smoothly at large openings:
    Q / (1 + (|Q|/q_max)^s)^(1/s)."""

    name: ClassVar[str] = "saturation"
    PARAMS: ClassVar[dict[str, str]] = {"side": "'supply' | 'drain'",
                                        "q_max_mm3_s": "flow cap magnitude [mm^3/s]",
                                        "sharpness": "s, how sharp the knee is [-]"}
    side: str = "supply"
    q_max_mm3_s: float = 5000.0
    sharpness: float = 8.0

    def __post_init__(self):
        self._check_side()
        self._check(self.q_max_mm3_s > 0, "q_max_mm3_s", "a positive flow")
        self._check(1.0 <= self.sharpness <= 50.0, "sharpness", "1..50")

    def cap(self, q_mm3_s):
        """Capped flow [mm^3/s]."""
        return saturate_flow(q_mm3_s, abs(self.q_max_mm3_s), self.sharpness)


@dataclass(frozen=True)
class Delay(Effect):
    """Extra transport delay delay_s between the servo and the needle (after the
    servo's own feedback, so the servo log does not show it)."""

    name: ClassVar[str] = "delay"
    PARAMS: ClassVar[dict[str, str]] = {"delay_s": "extra dead time [s]"}
    delay_s: float = 0.1

    def __post_init__(self):
        self._check(0.0 <= self.delay_s <= 2.0, "delay_s", "0..2 s")


@dataclass(frozen=True)
class SensorGain(Effect):
    """Scale error of one sensor: measured = gain * true."""

    name: ClassVar[str] = "sensor_gain"
    PARAMS: ClassVar[dict[str, str]] = {
        "sensor": "'encoder' | 'pressure' (= 'p_head', the A/B-port sensor) | 'p_supply' | 'p_load'",
        "gain": "measured / true [-]"}
    sensor: str = "pressure"
    gain: float = 1.05

    def __post_init__(self):
        if self.sensor not in SENSORS:
            raise ConfigError(f"{self.name}: sensor: expected one of {', '.join(SENSORS)}, "
                              f"got {self.sensor!r}")
        self._check(0.2 <= self.gain <= 5.0, "gain", "0.2..5")

    @property
    def channel(self) -> str:
        """Column the gain applies to: 'position_mm' or 'p_*_mpag'."""
        if self.sensor == "encoder":
            return "position_mm"
        return "p_head_mpag" if self.sensor in ("pressure", "p_head") else f"{self.sensor}_mpag"

    def measured(self, true):
        return measured_from_true(true, gain=self.gain)


#: registry: effect name -> class
EFFECTS: dict[str, type[Effect]] = {cls.name: cls for cls in (
    Drift, ThresholdShift, Backlash, PressureLaw, Saturation, Delay, SensorGain)}


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
        raise ConfigError(f"{cls.name}: {key}: expected a{'n integer' if ftype == 'int' else ' number'}, "
                          f"got {text!r}") from None
    return text


def parse_effect(spec: str | Effect | dict) -> Effect:
    """Build an effect from ``"name[:param=value,...]"`` (or a dict / an Effect).

    Missing parameters take the class defaults.

    Raises
    ------
    ConfigError
        Unknown effect or parameter, or a value of the wrong type or range.
    """
    if isinstance(spec, Effect):
        return spec
    if isinstance(spec, dict):
        d = dict(spec)
        name = d.pop("name", None)
        if name not in EFFECTS:
            raise ConfigError(f"effect: unknown effect {name!r}; expected one of {', '.join(EFFECTS)}")
        cls = EFFECTS[name]
        unknown = set(d) - {f.name for f in fields(cls)}
        if unknown:
            raise ConfigError(f"{name}: unknown parameter(s) {', '.join(sorted(unknown))}; "
                              f"expected {', '.join(cls.PARAMS)}")
        return cls(**{k: _convert(cls, k, str(v)) for k, v in d.items()})
    text = str(spec).strip()
    name, _, rest = text.partition(":")
    name = name.strip()
    if name not in EFFECTS:
        raise ConfigError(f"effect: unknown effect {name!r} in {text!r}; "
                          f"expected one of {', '.join(EFFECTS)}")
    cls = EFFECTS[name]
    kwargs: dict[str, Any] = {}
    for item in filter(None, (s.strip() for s in rest.split(","))):
        key, eq, value = item.partition("=")
        key = key.strip()
        if not eq or not value.strip():
            raise ConfigError(f"{name}: expected param=value, got {item!r}")
        if key not in cls.PARAMS:
            raise ConfigError(f"{name}: unknown parameter {key!r}; expected {', '.join(cls.PARAMS)}")
        kwargs[key] = _convert(cls, key, value.strip())
    return cls(**kwargs)


def parse_effects(specs: Iterable[str | Effect | dict] | None) -> tuple[Effect, ...]:
    """Parse several effects; one effect of a name per side/sensor at most.

    Raises
    ------
    ConfigError
        On a bad spec or a duplicate (same name and side/sensor).
    """
    out = tuple(parse_effect(s) for s in (specs or ()))
    seen = set()
    for e in out:
        key = (e.name, e.channel if isinstance(e, SensorGain) else getattr(e, "side", None))
        if key in seen:
            raise ConfigError(f"effect: {e.name} given twice" + (f" for {key[1]}" if key[1] else ""))
        seen.add(key)
    return out

