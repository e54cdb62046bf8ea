"""Position controllers of the paper (Sec. III-A/B), step-wise at 100 Hz.

Two P controllers on the position error e = x_ref - x [mm]:

- :class:`FlowModelController` (Fig. 5(a)): Q_ref = Kp e (Kp = 480 mm^3/s
  per mm), cam command from the flow model, eq. (6),
  theta_cmd = theta_d(p) +- sqrt(Q_ref / (C dp^n)), with the measured
  pressures and the valve model it is given, clipped to the cam range.
- :class:`CamController` (Fig. 5(b)): theta_cmd = neutral + Kp e
  (Kp = 15 deg/mm, neutral -15 deg), same clipping.

Both hold a fixed cam angle once converged (|e| <= 0.5 mm): 3 deg below
the supply sealing threshold (with the model) or the neutral angle
(without); a band of 0 never holds. The hold ends when the reference
changes, or when |e| grows past ``release_band_mm`` (not in the paper, which
only says the valve was "held"; ``inf`` keeps the hold until the next
reference change, the band itself releases as soon as |e| leaves it).
``identify`` reads all of these from a rig's logs
(:mod:`seanv_analysis.identify.controller`).

The controllers are pure: ``step(state, ...)`` returns the output and the
next state; they know nothing of the simulator, so ``validate`` can run the
same code with an identified model. The step law is compiled with numba
(:func:`.control_law.controller_step`), and the simulator's kernel calls
that same function; this module itself does not import numba.

Examples
--------
>>> from seanv_analysis import load_rig, ValveModel
>>> from seanv_analysis.sim.control import FlowModelController
>>> ctrl = FlowModelController.from_rig(load_rig())
>>> state = ctrl.initial_state()
>>> out, state = ctrl.step(state, x_ref_mm=30.0, x_mm=29.0, p_supply_mpag=3.3, p_head_mpag=1.6)
>>> round(out.q_ref_mm3_s)
480
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import ConfigError
from ..models import ValveModel
from ..models.valve import MIN_DP_MPA
from ._config_errors import config_errors
from .packing import (
    _CP_BAND,
    _CP_CAM_MAX,
    _CP_CAM_MIN,
    _CP_HOLD,
    _CP_KP,
    _CP_MIN_DP,
    _CP_RELEASE,
    _ST_HELD,
    _ST_HOLD_DEG,
    _ST_XREF,
    CP_SIZE,
    KIND_CAM,
    KIND_FLOW_MODEL,
    SP_SIZE,
    pack_model,
)

__all__ = ["ControllerState", "ControllerOutput", "FlowModelController", "CamController",
           "KIND_FLOW_MODEL", "KIND_CAM", "CP_SIZE"]  # controller_step: .control_law


@dataclass(frozen=True)
class ControllerState:
    """State carried between steps: whether the cam is held, at which angle
    [deg], and the previous reference [mm] (NaN before the first step)."""

    held: bool = False
    hold_deg: float = math.nan
    x_ref_prev_mm: float = math.nan

    def packed(self) -> np.ndarray:
        return np.array([1.0 if self.held else 0.0, self.hold_deg, self.x_ref_prev_mm])

    @classmethod
    def from_packed(cls, a) -> "ControllerState":
        return cls(bool(a[_ST_HELD] > 0.5), float(a[_ST_HOLD_DEG]), float(a[_ST_XREF]))


@dataclass(frozen=True)
class ControllerOutput:
    """One controller step: cam command [deg], target flow [mm^3/s] (NaN
    without a flow model) and whether the cam is held (converged)."""

    cam_cmd_deg: float
    q_ref_mm3_s: float
    held: bool


def _release(value: float | None) -> float:
    return math.inf if value is None else float(value)


@dataclass(frozen=True)
class _PController:
    """Shared parts of the two P controllers."""

    convergence_band_mm: float
    release_band_mm: float | None
    cam_min_deg: float
    cam_max_deg: float
    rate_hz: float

    def __post_init__(self):
        if not self.convergence_band_mm >= 0:
            raise ConfigError(f"convergence_band_mm: expected >= 0, got {self.convergence_band_mm}")
        if self.release_band_mm is not None and not self.release_band_mm >= self.convergence_band_mm:
            raise ConfigError(f"release_band_mm: expected >= convergence_band_mm "
                              f"({self.convergence_band_mm}), got {self.release_band_mm}")
        if not self.cam_min_deg < self.cam_max_deg:
            raise ConfigError(f"cam_min_deg: expected < cam_max_deg, got "
                              f"{self.cam_min_deg} >= {self.cam_max_deg}")
        if not self.rate_hz > 0:
            raise ConfigError(f"rate_hz: expected > 0, got {self.rate_hz}")

    def initial_state(self) -> ControllerState:
        """State before the first step (not held, no previous reference)."""
        return ControllerState()

    def step(self, state: ControllerState, x_ref_mm: float, x_mm: float, p_supply_mpag: float,
             p_head_mpag: float, p_tank_mpag: float = 0.0) -> tuple[ControllerOutput, ControllerState]:
        """One control step (call at ``rate_hz``).

        Parameters
        ----------
        state : from :meth:`initial_state` or the previous step
        x_ref_mm, x_mm : reference and measured position [mm]
        p_supply_mpag, p_head_mpag, p_tank_mpag : measured pressures [MPaG]

        Returns
        -------
        (ControllerOutput, next ControllerState)
        """
        from .control_law import controller_step  # numba, on first use

        kind, cp, tables = self.jit_spec()
        st = state.packed()
        theta, q, held = controller_step(kind, cp, *tables, st, float(x_ref_mm), float(x_mm),
                                         float(p_supply_mpag), float(p_head_mpag),
                                         float(p_tank_mpag))
        return ControllerOutput(float(theta), float(q), bool(held > 0.5)), ControllerState.from_packed(st)

    def replay(self, x_ref_mm, x_mm, p_supply_mpag, p_head_mpag, p_tank_mpag) -> np.ndarray:
        """The cam command [deg] :meth:`step` gives at each logged tick (arrays
        of one length, from :meth:`initial_state`), in one compiled loop; NaN
        where the reference or the position is not finite (the tick is
        skipped), a non-finite supply or head pressure taken as 0 MPaG."""
        from . import compiled  # ahead of time (numba's JIT where it cannot be built)

        kind, cp, tables = self.jit_spec()
        arrays = [np.ascontiguousarray(a, dtype=float) for a in
                  (x_ref_mm, x_mm, p_supply_mpag, p_head_mpag, p_tank_mpag)]
        return compiled.controller_replay()(int(kind), cp, *tables,
                                            self.initial_state().packed(), *arrays)

    def _cp(self, kp: float, hold: float) -> np.ndarray:
        cp = np.empty(CP_SIZE)
        cp[_CP_KP] = kp
        cp[_CP_BAND] = self.convergence_band_mm
        cp[_CP_RELEASE] = _release(self.release_band_mm)
        cp[_CP_CAM_MIN] = self.cam_min_deg
        cp[_CP_CAM_MAX] = self.cam_max_deg
        cp[_CP_HOLD] = hold
        cp[_CP_MIN_DP] = MIN_DP_MPA
        return cp


@dataclass(frozen=True, init=False)
class FlowModelController(_PController):
    """P controller on flow with the valve model (paper Fig. 5(a)).

    Q_ref = Kp e [mm^3/s]; theta_cmd from eq. (6) with ``model`` and the
    measured p_supply, p_head (and p_tank), clipped to [cam_min, cam_max];
    held at theta_d,supply - ``hold_below_threshold_deg`` once |e| <=
    ``convergence_band_mm``.

    Parameters
    ----------
    model : the valve model used in eq. (6) (the paper's fit, or an identified one)
    kp_mm3_s_per_mm : Kp [mm^3/s per mm] (480 in the paper)
    hold_below_threshold_deg : hold angle below the supply threshold [deg] (3)
    convergence_band_mm, release_band_mm : hold when |e| <= band; release when
        |e| > release band (None: only a new reference releases) [mm]
    cam_min_deg, cam_max_deg : command range [deg] (-40..10)
    rate_hz : control rate [Hz] (100)
    """

    model: ValveModel = None  # type: ignore[assignment]
    kp_mm3_s_per_mm: float = 480.0
    hold_below_threshold_deg: float = 3.0
    _packed: tuple = field(default=(), init=False, repr=False, compare=False)

    def __init__(self, model: ValveModel, *, kp_mm3_s_per_mm: float = 480.0,
                 hold_below_threshold_deg: float = 3.0, convergence_band_mm: float = 0.5,
                 release_band_mm: float | None = 1.0, cam_min_deg: float | None = None,
                 cam_max_deg: float | None = None, rate_hz: float = 100.0):
        if not isinstance(model, ValveModel):
            raise ConfigError(f"model: expected a ValveModel, got {type(model).__name__}")
        set_ = object.__setattr__
        set_(self, "model", model)
        set_(self, "kp_mm3_s_per_mm", float(kp_mm3_s_per_mm))
        set_(self, "hold_below_threshold_deg", float(hold_below_threshold_deg))
        set_(self, "convergence_band_mm", float(convergence_band_mm))
        set_(self, "release_band_mm", None if release_band_mm is None else float(release_band_mm))
        set_(self, "cam_min_deg", float(model.cam_min_deg if cam_min_deg is None else cam_min_deg))
        set_(self, "cam_max_deg", float(model.cam_max_deg if cam_max_deg is None else cam_max_deg))
        set_(self, "rate_hz", float(rate_hz))
        if not self.kp_mm3_s_per_mm > 0:
            raise ConfigError(f"kp_mm3_s_per_mm: expected > 0, got {kp_mm3_s_per_mm}")
        self.__post_init__()
        with config_errors():  # e.g. a needle geometry without a monotonic eq. (4)
            set_(self, "_packed", pack_model(model))

    @classmethod
    def from_rig(cls, rig: Any, model: ValveModel | None = None, **overrides) -> "FlowModelController":
        """Paper settings from the rig config's [controller] table; ``model``
        defaults to the rig's valve (the paper's fit)."""
        c = rig["controller"]
        kw = dict(kp_mm3_s_per_mm=c["kp_flow_mm3_s_per_mm"],
                  hold_below_threshold_deg=c["hold_below_supply_threshold_deg"],
                  convergence_band_mm=c["convergence_band_mm"],
                  release_band_mm=c.get("release_band_mm"), rate_hz=c["rate_hz"])
        kw.update(overrides)
        if model is None:
            with config_errors():
                model = ValveModel.from_rig(rig)
        return cls(model, **kw)

    def jit_spec(self):
        """(kind, packed parameters, packed model tables) for compiled code."""
        return KIND_FLOW_MODEL, self._cp(self.kp_mm3_s_per_mm, self.hold_below_threshold_deg), self._packed

    def run_json(self) -> dict[str, Any]:
        """run.json ``controller`` object (data contract)."""
        return {"kp": self.kp_mm3_s_per_mm, "flow_model": True, "rate_hz": self.rate_hz}

    def to_json_dict(self) -> dict[str, Any]:
        return {**self.run_json(), "hold_below_threshold_deg": self.hold_below_threshold_deg,
                "convergence_band_mm": self.convergence_band_mm,
                "release_band_mm": self.release_band_mm,
                "cam_range_deg": [self.cam_min_deg, self.cam_max_deg], "model": self.model.to_dict()}


@dataclass(frozen=True, init=False)
class CamController(_PController):
    """P controller on the cam angle, no valve model (paper Fig. 5(b)).

    theta_cmd = neutral + Kp e [deg], clipped; held at ``neutral_deg`` once
    |e| <= ``convergence_band_mm``.

    Parameters
    ----------
    kp_deg_per_mm : Kp [deg per mm] (15 in the paper)
    neutral_deg : servo neutral, both needles sealed [deg] (-15)
    convergence_band_mm, release_band_mm, cam_min_deg, cam_max_deg, rate_hz :
        as :class:`FlowModelController`
    """

    kp_deg_per_mm: float = 15.0
    neutral_deg: float = -15.0

    def __init__(self, *, kp_deg_per_mm: float = 15.0, neutral_deg: float = -15.0,
                 convergence_band_mm: float = 0.5, release_band_mm: float | None = 1.0,
                 cam_min_deg: float = -40.0, cam_max_deg: float = 10.0, rate_hz: float = 100.0):
        set_ = object.__setattr__
        set_(self, "kp_deg_per_mm", float(kp_deg_per_mm))
        set_(self, "neutral_deg", float(neutral_deg))
        set_(self, "convergence_band_mm", float(convergence_band_mm))
        set_(self, "release_band_mm", None if release_band_mm is None else float(release_band_mm))
        set_(self, "cam_min_deg", float(cam_min_deg))
        set_(self, "cam_max_deg", float(cam_max_deg))
        set_(self, "rate_hz", float(rate_hz))
        if not self.kp_deg_per_mm > 0:
            raise ConfigError(f"kp_deg_per_mm: expected > 0, got {kp_deg_per_mm}")
        self.__post_init__()

    @classmethod
    def from_rig(cls, rig: Any, **overrides) -> "CamController":
        """Paper settings from the rig config ([controller], [servo] neutral, cam range)."""
        c = rig["controller"]
        lo, hi = rig.cam_range_deg
        kw = dict(kp_deg_per_mm=c["kp_cam_deg_per_mm"], neutral_deg=rig["servo"]["neutral_deg"],
                  convergence_band_mm=c["convergence_band_mm"],
                  release_band_mm=c.get("release_band_mm"), cam_min_deg=lo, cam_max_deg=hi,
                  rate_hz=c["rate_hz"])
        kw.update(overrides)
        return cls(**kw)

    def jit_spec(self):
        """(kind, packed parameters, dummy tables) for compiled code."""
        dummy = np.zeros(SP_SIZE)
        grid = np.array([0.0, 1.0])
        return KIND_CAM, self._cp(self.kp_deg_per_mm, self.neutral_deg), \
            (dummy, grid, grid, dummy, grid, grid)

    def run_json(self) -> dict[str, Any]:
        """run.json ``controller`` object (data contract)."""
        return {"kp": self.kp_deg_per_mm, "flow_model": False, "rate_hz": self.rate_hz}

    def to_json_dict(self) -> dict[str, Any]:
        return {**self.run_json(), "neutral_deg": self.neutral_deg,
                "convergence_band_mm": self.convergence_band_mm,
                "release_band_mm": self.release_band_mm,
                "cam_range_deg": [self.cam_min_deg, self.cam_max_deg]}


def __getattr__(name: str):
    if name == "controller_step":  # compiled (numba): imported on first use
        from .control_law import controller_step

        return controller_step
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
