"""Layout of the packed plant parameter vector (units in the comments), and
of the kernel's outputs.

One definition for the kernel (:mod:`.kernel`), the integrator step
(:mod:`.rosenbrock`) and the packer (:meth:`.plant.Plant.packed_params`);
numba reads module globals, not class attributes, so the compiled modules
of this package import the ``_NAME = PP.NAME`` bindings below.
"""
from __future__ import annotations

__all__ = ["PP", "PP_SIZE", "MODE_SCHEDULE", "OUT_FAST", "OUT_SLOW"]  # and the _NAME bindings


class PP:
    """Indices of the packed plant parameter vector (units in the names)."""

    DT = 0                # integration step [s]
    SUBSTEPS = 1          # plant steps per 1 kHz sample [-]
    CTRL_EVERY = 2        # 1 kHz samples per controller tick [-]
    P_SUPPLY = 3          # supply pressure [MPaG]
    RIPPLE_AMP = 4        # pump ripple amplitude [MPa]
    RIPPLE_HZ = 5         # pump ripple frequency [Hz]
    P_TANK = 6            # tank pressure [MPaG]
    N_SEG = 7             # tube segments [-]
    R_SEG = 8             # laminar resistance per segment [MPa s/mm^3]
    I_SEG = 9             # inertance per segment [MPa s^2/mm^3]
    V_SEG = 10            # tube volume per segment [mm^3]
    BULK = 11             # effective bulk modulus [MPa]
    AREA = 12             # piston area [mm^2]
    LOAD_AREA = 13        # load piston area [mm^2]
    DEAD_VOL = 14         # head volume at x = 0 [mm^3]
    STROKE = 15           # stroke [mm]
    MASS = 16             # moving mass [N s^2/mm]
    F_COULOMB = 17        # [N]
    F_STATIC = 18         # [N]
    V_STRIBECK = 19       # [mm/s]
    VISCOUS = 20          # [N s/mm]
    LOAD_TAU = 21         # load regulator time constant [s]
    LEAK_G = 22           # leakage conductance per side [mm^3/(s MPa)]
    DP_SMOOTH = 23        # dp smoothing [MPa]
    SERVO_DEAD_TICKS = 24  # servo dead time in controller ticks [-]
    SERVO_TAU = 25        # servo time constant [s]
    SERVO_RATE = 26       # servo rate limit [deg/s]
    SERVO_RES = 27        # servo resolution [deg]
    BACKLASH = 28         # backlash width [deg] (effect)
    DELAY_STEPS = 29      # extra transport delay [plant steps] (effect)
    ENC_RES = 30          # encoder resolution [mm]
    GAIN_X = 31           # encoder gain (effect) [-]
    GAIN_PS = 32          # p_supply sensor gain [-]
    GAIN_PH = 33          # p_head sensor gain [-]
    GAIN_PL = 34          # p_load sensor gain [-]
    P_CAV = 35            # cavitation floor [MPaG]
    NEUTRAL = 36          # cam angle after a flow step's release [deg]
    X_STOP_LO = 37        # flow step: release when x <= this (drain) [mm]
    X_STOP_HI = 38        # flow step: release when x >= this (supply) [mm]
    SUPPLY_DROOP = 39     # supply pressure drop per unit of extending flow [MPa s/mm^3]
    STOP = 40             # set != 0 while a kernel runs: it returns early (Ctrl-C, SIGTERM) [-]


PP_SIZE = 41

#: controller kind of the kernel for an open-loop cam schedule (flow-step runs)
MODE_SCHEDULE = 0
#: columns of the kernel's 1 kHz sensor output
OUT_FAST = ("t_s", "position_mm", "p_supply_mpag", "p_head_mpag", "p_load_mpag",
            "x_true_mm", "q_true_mm3_s")
#: columns of the kernel's 100 Hz output
OUT_SLOW = ("t_s", "cam_cmd_deg", "cam_deg", "x_ref_mm", "q_ref_mm3_s", "cam_needle_deg")


# module-level bindings of the indices, imported by the compiled modules
# (numba reads module globals, not class attributes)
_DT = PP.DT
_SUBSTEPS = PP.SUBSTEPS
_CTRL_EVERY = PP.CTRL_EVERY
_P_SUPPLY = PP.P_SUPPLY
_RIPPLE_AMP = PP.RIPPLE_AMP
_RIPPLE_HZ = PP.RIPPLE_HZ
_P_TANK = PP.P_TANK
_N_SEG = PP.N_SEG
_R_SEG = PP.R_SEG
_I_SEG = PP.I_SEG
_V_SEG = PP.V_SEG
_BULK = PP.BULK
_AREA = PP.AREA
_LOAD_AREA = PP.LOAD_AREA
_DEAD_VOL = PP.DEAD_VOL
_STROKE = PP.STROKE
_MASS = PP.MASS
_F_COULOMB = PP.F_COULOMB
_F_STATIC = PP.F_STATIC
_V_STRIBECK = PP.V_STRIBECK
_VISCOUS = PP.VISCOUS
_LOAD_TAU = PP.LOAD_TAU
_LEAK_G = PP.LEAK_G
_DP_SMOOTH = PP.DP_SMOOTH
_SERVO_DEAD_TICKS = PP.SERVO_DEAD_TICKS
_SERVO_TAU = PP.SERVO_TAU
_SERVO_RATE = PP.SERVO_RATE
_SERVO_RES = PP.SERVO_RES
_BACKLASH = PP.BACKLASH
_DELAY_STEPS = PP.DELAY_STEPS
_ENC_RES = PP.ENC_RES
_GAIN_X = PP.GAIN_X
_GAIN_PS = PP.GAIN_PS
_GAIN_PH = PP.GAIN_PH
_GAIN_PL = PP.GAIN_PL
_P_CAV = PP.P_CAV
_NEUTRAL = PP.NEUTRAL
_X_STOP_LO = PP.X_STOP_LO
_X_STOP_HI = PP.X_STOP_HI
_SUPPLY_DROOP = PP.SUPPLY_DROOP
_STOP = PP.STOP
