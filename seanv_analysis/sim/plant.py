"""The simulated rig: parameters from the rig config, the plant's valve and
the injected effects, packed for the compiled kernel (:mod:`.kernel`).

Physics (units: mm, MPa, s, N):

- Tube (20 m, bore d): laminar resistance R = 128 mu L / (pi d^4),
  fluid inertance I = k_I rho L / A_t (``tube.inertance_factor`` k_I: 1 for
  the water column, smaller where the line behaves as a lumped, damped
  one), compliance C = V / B_eff with the
  effective bulk modulus of water in the nylon tube (rig ``tube``),
  split into ``sim.tube_segments`` lumped segments.
- Actuator: m dv/dt = p_head A - p_load A_load - F_friction, friction
  Coulomb + Stribeck + viscous with stiction (Karnopp), end stops at 0 and
  the stroke.
- Supply: ``supply.pressure_mpag`` at no flow, less ``supply.droop_mpa_s_per_mm3``
  x the flow the extending piston draws, plus the pump ripple.
- Load: regulated pneumatic pressure, first order towards its set point.
- Valve: eq. (3)-(5) of :mod:`seanv_analysis.models` per side, the sqrt(dp)
  law linear below ``valve.plant.dp_smoothing_mpa``, plus a small leakage
  conductance of each sealed needle (``valve.plant``).
- Servo: dead time, first-order lag, rate limit, quantisation (rig ``servo``).
- Effects: each injected effect adds its dynamic form
  (:meth:`~seanv_analysis.models.effects.Effect.valve_terms`: C multiplier,
  z0 offset, dp exponent, flow cap, closed-form term of a valve side at run i;
  :meth:`~seanv_analysis.models.effects.Effect.plant_terms`: backlash, extra
  delay, sensor gains); the plant only folds them in, in the order given.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Iterable

import numpy as np

from ..config import RigConfig
from ..errors import ConfigError
from ..models import ValveModel
from ..models.effects import Effect, PlantTerms, ValveTerms, parse_effects
from . import packing as P
from ._pp import PP, PP_SIZE

__all__ = ["Plant", "tube_constants"]


def tube_constants(rig: RigConfig) -> dict[str, float]:
    """Lumped constants of the whole tube: R [MPa s/mm^3], I [MPa s^2/mm^3],
    V [mm^3], C [mm^3/MPa], and the hydraulic time constant I/R [s]."""
    tube, fluid = rig["tube"], rig["fluid"]
    length = tube["length_m"] * 1000.0
    d = tube["inner_diameter_mm"]
    area = math.pi / 4 * d * d
    mu = fluid["dynamic_viscosity_pa_s"] * 1e-6           # MPa s
    rho = fluid["density_kg_per_m3"] * 1e-12               # N s^2/mm^4
    r = 128.0 * mu * length / (math.pi * d ** 4)
    inert = rho * length / area * float(tube["inertance_factor"])
    volume = area * length
    return {"R": r, "I": inert, "V": volume, "C": volume / tube["effective_bulk_modulus_mpa"],
            "tau_I_over_R_s": inert / r}


@dataclass(frozen=True)
class Plant:
    """The rig as the simulator sees it: rig config, the plant's valve model
    (the "true" valve) and injected effects.

    Parameters
    ----------
    rig : rig config (all constants)
    valve : the true valve (default: the rig's, i.e. the paper's fit)
    effects : injected effects (names or :class:`~seanv_analysis.models.effects.Effect`)
    """

    rig: RigConfig
    valve: ValveModel
    effects: tuple[Effect, ...] = field(default=())

    @classmethod
    def from_rig(cls, rig: RigConfig, *, valve: ValveModel | None = None,
                 effects: Iterable[str | Effect | dict] = ()) -> "Plant":
        """The plant of ``rig`` with ``valve`` (default: the rig's) and ``effects``.

        Raises
        ------
        ConfigError
            A bad effect spec (unknown name or parameter, value out of range,
            the same effect twice on one side/sensor).
        """
        try:
            parsed = parse_effects(effects)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        return cls(rig, valve if valve is not None else ValveModel.from_rig(rig), parsed)

    def valve_terms(self, side: str, run_index: int) -> ValveTerms:
        """What the effects change on ``side`` of the valve at run
        ``run_index`` (C multiplier, z0 offset, dp exponent, flow cap), in the
        order they were given."""
        terms = ValveTerms()
        for e in self.effects:
            terms = e.valve_terms(terms, side, run_index)
        return terms

    def plant_terms(self) -> PlantTerms:
        """What the effects add outside the valve (backlash, delay, sensor gains)."""
        terms = PlantTerms()
        for e in self.effects:
            terms = e.plant_terms(terms)
        return terms

    def valve_at(self, run_index: int) -> tuple:
        """Packed plant valve (both sides) at run ``run_index`` with the valve
        effects folded in (:meth:`valve_terms`)."""
        packed = []
        for name in ("supply", "drain"):
            t = self.valve_terms(name, run_index)
            packed += list(P.pack_side(self.valve.side(name), c_multiplier=t.c_multiplier,
                                       z0_offset_mm=t.z0_offset_mm, dp_exponent=t.dp_exponent,
                                       q_max_mm3_s=t.q_max_mm3_s, sharpness=t.sharpness))
        return tuple(packed)

    def term_at(self, run_index: int) -> np.ndarray:
        """The plant valve's closed-form terms at run ``run_index``, packed
        for the kernel (``sim.packing.pack_terms``: both sides' programs, the
        run index, room for the variables and the stack; a fresh array)."""
        terms = [self.valve_terms(name, run_index) for name in ("supply", "drain")]
        return P.pack_terms(*((t.term_mode, t.term_program) if t.term_program is not None
                              else None for t in terms), run_index=float(run_index))

    @property
    def has_terms(self) -> bool:
        """True when a closed-form term (``term`` effect) acts on a side."""
        return any(e.name == "term" for e in self.effects)

    def packed_params(self, *, neutral_deg: float, x_stop_mm: tuple[float, float]) -> np.ndarray:
        """Packed plant parameter vector for the kernel (:class:`.kernel.PP`)."""
        rig = self.rig
        s = rig["sim"]
        tube = tube_constants(rig)
        nseg = int(s["tube_segments"])
        if nseg < 1:
            raise ConfigError(f"sim.tube_segments: expected >= 1, got {nseg}")
        if not float(rig["tube"]["inertance_factor"]) > 0:
            raise ConfigError(f"tube.inertance_factor: expected > 0 (1: the water column), got "
                              f"{rig['tube']['inertance_factor']}")
        if not float(rig["supply"]["droop_mpa_s_per_mm3"]) >= 0:
            raise ConfigError(f"supply.droop_mpa_s_per_mm3: expected >= 0, got "
                              f"{rig['supply']['droop_mpa_s_per_mm3']}")
        dt = float(s["time_step_s"])
        rate = float(rig["sensors"]["encoder_rate_hz"])
        substeps = round(1.0 / (rate * dt))
        if substeps < 1 or abs(substeps * dt * rate - 1.0) > 1e-9:
            raise ConfigError(f"sim.time_step_s: expected 1/(k x encoder rate), got {dt}")
        ctrl_every = round(rate / float(rig["controller"]["rate_hz"]))
        act, servo, sup = rig["actuator"], rig["servo"], rig["supply"]
        pp = np.zeros(PP_SIZE)
        pp[PP.DT] = dt
        pp[PP.SUBSTEPS] = substeps
        pp[PP.CTRL_EVERY] = ctrl_every
        pp[PP.P_SUPPLY] = sup["pressure_mpag"]
        pp[PP.SUPPLY_DROOP] = sup["droop_mpa_s_per_mm3"]
        pp[PP.RIPPLE_AMP] = sup["ripple_amplitude_mpa"]
        pp[PP.RIPPLE_HZ] = sup["ripple_frequency_hz"]
        pp[PP.P_TANK] = sup["tank_pressure_mpag"]
        pp[PP.N_SEG] = nseg
        pp[PP.R_SEG] = tube["R"] / nseg
        pp[PP.I_SEG] = tube["I"] / nseg
        pp[PP.V_SEG] = tube["V"] / nseg
        pp[PP.BULK] = rig["tube"]["effective_bulk_modulus_mpa"]
        pp[PP.AREA] = rig.piston_area_mm2
        pp[PP.LOAD_AREA] = rig.load_area_mm2
        pp[PP.DEAD_VOL] = act["dead_volume_mm3"]
        pp[PP.STROKE] = act["stroke_mm"]
        pp[PP.MASS] = act["moving_mass_kg"] * 1e-3
        pp[PP.F_COULOMB] = act["coulomb_friction_n"]
        pp[PP.F_STATIC] = max(act["static_friction_n"], act["coulomb_friction_n"])
        pp[PP.V_STRIBECK] = act["stribeck_velocity_mm_s"]
        pp[PP.VISCOUS] = act["viscous_friction_n_s_per_mm"]
        pp[PP.LOAD_TAU] = rig["load"]["regulator_time_constant_s"]
        plant = rig["valve"]["plant"]
        pp[PP.LEAK_G] = plant["leakage_conductance_mm3_s_per_mpa"]
        pp[PP.DP_SMOOTH] = plant["dp_smoothing_mpa"]
        pp[PP.SERVO_DEAD_TICKS] = round(servo["dead_time_s"] * rig["controller"]["rate_hz"])
        pp[PP.SERVO_TAU] = servo["time_constant_s"]
        pp[PP.SERVO_RATE] = servo["max_rate_deg_s"]
        pp[PP.SERVO_RES] = servo["resolution_deg"]
        pp[PP.ENC_RES] = rig["sensors"]["encoder_resolution_mm"]
        for name, value in self.plant_terms().items():   # the effects' parameters, by name
            pp[getattr(PP, name)] = value
        pp[PP.P_CAV] = s["cavitation_pressure_mpag"]
        pp[PP.NEUTRAL] = neutral_deg
        pp[PP.X_STOP_LO], pp[PP.X_STOP_HI] = x_stop_mm
        return pp

    def truth(self) -> dict[str, Any]:
        """Everything the plant is made of (for ``_truth.json``)."""
        return {"valve": self.valve.to_dict(), "effects": [e.to_json_dict() for e in self.effects],
                "rig": self.rig.to_dict(), "tube": tube_constants(self.rig)}
