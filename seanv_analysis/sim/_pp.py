"""Layout of the packed plant parameter vector, and of the kernel's outputs.

The plant's parameters have names (:data:`PLANT`: unit and meaning of each),
and so have those the effects add outside the valve (each effect's
``PLANT_PARAMS`` in :mod:`seanv_analysis.models.effects`): one vector holds
them all, in that order, and this module is the one place that lowers the
names to indices. :class:`PP` maps a name to its index for the packer
(:meth:`.plant.Plant.packed_params`, which fills the vector by name); the
compiled modules read ``pp[_NAME]``, a module-level binding made here for
every name (numba reads module globals, not class attributes). A new plant
effect declares its parameter in its class and reads ``pp[_ITS_NAME]`` in
the kernel: nothing else changes.
"""
from __future__ import annotations

from ..models.effects import plant_param_defaults

__all__ = ["PP", "PP_SIZE", "PLANT", "NAMES", "MODE_SCHEDULE", "OUT_FAST", "OUT_SLOW"]

#: the plant's own parameters, in the order of the packed vector
PLANT: dict[str, str] = {
    "DT": "integration step [s]",
    "SUBSTEPS": "plant steps per 1 kHz sample [-]",
    "CTRL_EVERY": "1 kHz samples per controller tick [-]",
    "P_SUPPLY": "supply pressure [MPaG]",
    "RIPPLE_AMP": "pump ripple amplitude [MPa]",
    "RIPPLE_HZ": "pump ripple frequency [Hz]",
    "P_TANK": "tank pressure [MPaG]",
    "N_SEG": "tube segments [-]",
    "R_SEG": "laminar resistance per segment [MPa s/mm^3]",
    "I_SEG": "inertance per segment [MPa s^2/mm^3]",
    "V_SEG": "tube volume per segment [mm^3]",
    "BULK": "effective bulk modulus [MPa]",
    "AREA": "piston area [mm^2]",
    "LOAD_AREA": "load piston area [mm^2]",
    "DEAD_VOL": "head volume at x = 0 [mm^3]",
    "STROKE": "stroke [mm]",
    "MASS": "moving mass [N s^2/mm]",
    "F_COULOMB": "Coulomb friction [N]",
    "F_STATIC": "breakaway friction [N]",
    "V_STRIBECK": "Stribeck velocity [mm/s]",
    "VISCOUS": "viscous friction [N s/mm]",
    "LOAD_TAU": "load regulator time constant [s]",
    "LEAK_G": "leakage conductance per side [mm^3/(s MPa)]",
    "DP_SMOOTH": "dp smoothing [MPa]",
    "SERVO_DEAD_TICKS": "servo dead time in controller ticks [-]",
    "SERVO_TAU": "servo time constant [s]",
    "SERVO_RATE": "servo rate limit [deg/s]",
    "SERVO_RES": "servo resolution [deg]",
    "ENC_RES": "encoder resolution [mm]",
    "P_CAV": "cavitation floor [MPaG]",
    "NEUTRAL": "cam angle after a flow step's release [deg]",
    "X_STOP_LO": "flow step: release when x <= this (drain) [mm]",
    "X_STOP_HI": "flow step: release when x >= this (supply) [mm]",
    "SUPPLY_DROOP": "supply pressure drop per unit of extending flow [MPa s/mm^3]",
    "STOP": "set != 0 while a kernel runs: it returns early (Ctrl-C, SIGTERM) [-]",
}

#: every parameter of the packed vector, in order: the plant's, then the
#: effects' (in the order the effects are registered)
NAMES: tuple[str, ...] = (*PLANT, *(n for n in plant_param_defaults() if n not in PLANT))

#: name -> index in the packed vector (``PP.BULK``)
PP = type("PP", (), {"__doc__": "Indices of the packed plant parameter vector, by name "
                                "(:data:`NAMES`; units in :data:`PLANT` and the effects' "
                                "``PLANT_PARAMS``).",
                     **{name: i for i, name in enumerate(NAMES)}})

PP_SIZE = len(NAMES)

#: controller kind of the kernel for an open-loop cam schedule (flow-step runs)
MODE_SCHEDULE = 0
#: columns of the kernel's 1 kHz sensor output
OUT_FAST = ("t_s", "position_mm", "p_supply_mpag", "p_head_mpag", "p_load_mpag",
            "x_true_mm", "q_true_mm3_s")
#: columns of the kernel's 100 Hz output
OUT_SLOW = ("t_s", "cam_cmd_deg", "cam_deg", "x_ref_mm", "q_ref_mm3_s", "cam_needle_deg")

# the module-level binding ``_NAME`` of every index, imported by the compiled
# modules (numba reads module globals, not class attributes)
globals().update({f"_{name}": i for i, name in enumerate(NAMES)})
