"""Compiled time-stepping kernel of the plant (numba).

One fixed-step loop integrates the whole rig (see :mod:`.plant` for the
physics and the packed parameter layout):

- valve (eq. 3-5 through :mod:`seanv_analysis.models._jit`, sealing
  thresholds refreshed at 1 kHz) feeding node 0 of the tube,
- 20 m tube as ``n_seg`` lumped segments (laminar resistance R and fluid
  inertance I per segment, compliance C = V / B at the nodes),
- actuator head node (tube end + chamber volume) and piston (mass, Coulomb +
  Stribeck + viscous friction with stiction, end stops) against the
  pneumatic load (regulated pressure, first order),
- servo (100 Hz command, dead time, first-order lag, rate limit, position
  quantisation), then the injected cam-side effects (backlash play, extra
  transport delay),
- sensors sampled at 1 kHz (encoder quantisation, pressure noise, sensor
  gain errors) and the controller/servo log at 100 Hz.

Integration is semi-implicit Euler: node pressures are advanced first with
the valve flow linearised in the node pressure (implicit in the valve
conductance, which is stiff near dp = 0), segment flows implicitly in their
resistance, piston last (symplectic). With the default 0.1 ms step every
mode of the default rig is resolved (fastest: head node + piston,
~600 rad/s, omega dt = 0.06).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..control import KIND_CAM, KIND_FLOW_MODEL, controller_step
from ..models import _jit as J

__all__ = ["simulate_kernel", "PP", "PP_SIZE", "MODE_SCHEDULE"]

#: controller kind for an open-loop cam schedule (flow-step runs)
MODE_SCHEDULE = 0


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


PP_SIZE = 39

# module-level copies of the PP indices (numba reads globals, not class attributes)
_DT = 0
_SUBSTEPS = 1
_CTRL_EVERY = 2
_P_SUPPLY = 3
_RIPPLE_AMP = 4
_RIPPLE_HZ = 5
_P_TANK = 6
_N_SEG = 7
_R_SEG = 8
_I_SEG = 9
_V_SEG = 10
_BULK = 11
_AREA = 12
_LOAD_AREA = 13
_DEAD_VOL = 14
_STROKE = 15
_MASS = 16
_F_COULOMB = 17
_F_STATIC = 18
_V_STRIBECK = 19
_VISCOUS = 20
_LOAD_TAU = 21
_LEAK_G = 22
_DP_SMOOTH = 23
_SERVO_DEAD_TICKS = 24
_SERVO_TAU = 25
_SERVO_RATE = 26
_SERVO_RES = 27
_BACKLASH = 28
_DELAY_STEPS = 29
_ENC_RES = 30
_GAIN_X = 31
_GAIN_PS = 32
_GAIN_PH = 33
_GAIN_PL = 34
_P_CAV = 35
_NEUTRAL = 36
_X_STOP_LO = 37
_X_STOP_HI = 38

#: columns of the 1 kHz sensor output
OUT_FAST = ("t_s", "position_mm", "p_supply_mpag", "p_head_mpag", "p_load_mpag",
            "x_true_mm", "q_true_mm3_s")
#: columns of the 100 Hz output
OUT_SLOW = ("t_s", "cam_cmd_deg", "cam_deg", "x_ref_mm", "q_ref_mm3_s", "cam_needle_deg")


@njit(cache=True, nogil=True)
def _step_value(t_breaks, values, t):
    """Value of a step sequence at time t (holds from each break) [-]."""
    i = np.searchsorted(t_breaks, t, side="right") - 1
    if i < 0:
        i = 0
    return values[i]


@njit(cache=True, nogil=True)
def _friction_step(v, f_drive, pp, dt):
    """Piston velocity after one step with Karnopp stiction [mm/s]."""
    m = pp[_MASS]
    fc = pp[_F_COULOMB]
    fs = pp[_F_STATIC]
    if v == 0.0:
        if abs(f_drive) <= fs:
            return 0.0
        return dt * (f_drive - math.copysign(fc, f_drive)) / m
    vs = pp[_V_STRIBECK]
    ff = math.copysign(fc + (fs - fc) * math.exp(-(v / vs) ** 2), v) + pp[_VISCOUS] * v
    v_new = v + dt * (f_drive - ff) / m
    if v_new * v <= 0.0:
        return 0.0
    return v_new


@njit(cache=True, nogil=True)
def simulate_kernel(pp, sup, sup_z, sup_th, dr, dr_z, dr_th,
                    ctrl_kind, cp, csup, csup_z, csup_th, cdr, cdr_z, cdr_th,
                    ref_t, ref_v, load_t, load_v, cmd_t, cmd_v,
                    noise, n_fast, x0_mm, cam0_deg):
    """Run the plant for ``n_fast`` 1 kHz samples.

    Parameters
    ----------
    pp : packed plant parameters (:class:`PP`)
    sup..dr_th : plant valve, packed (``models._jit.pack_side``)
    ctrl_kind : MODE_SCHEDULE (cam from ``cmd_t/cmd_v`` with end-of-stroke
        release), or the controller kinds of :mod:`seanv_analysis.control`
    cp, csup..cdr_th : controller parameters and its valve model, packed
    ref_t, ref_v : position reference step sequence [s], [mm]
    load_t, load_v : load pressure set-point step sequence [s], [MPaG]
    cmd_t, cmd_v : open-loop cam command step sequence [s], [deg]
    noise : (n_fast, 3) standard-normal draws scaled to pressure noise [MPa]
        for p_supply, p_head, p_load
    x0_mm, cam0_deg : initial position and cam angle

    Returns
    -------
    fast : (n_fast, 7) see ``OUT_FAST``; slow : (n_ctrl, 6) see ``OUT_SLOW``;
    t_release : time the flow step's cam was released [s] (NaN if never)
    """
    dt = pp[_DT]
    nsub = int(pp[_SUBSTEPS])
    every = int(pp[_CTRL_EVERY])
    nseg = int(pp[_N_SEG])
    nnode = nseg + 1
    area = pp[_AREA]
    bulk = pp[_BULK]
    rseg = pp[_R_SEG]
    iseg = pp[_I_SEG]
    vseg = pp[_V_SEG]
    smooth = pp[_DP_SMOOTH]
    gl = pp[_LEAK_G]
    ptank = pp[_P_TANK]
    pcav = pp[_P_CAV]
    two_pi_f = 2.0 * math.pi * pp[_RIPPLE_HZ]

    n_ctrl = (n_fast + every - 1) // every
    fast = np.empty((n_fast, 7))
    slow = np.empty((n_ctrl, 6))

    # initial state: at rest, head pressure balancing the load
    p_load = _step_value(load_t, load_v, 0.0)
    p0 = p_load * pp[_LOAD_AREA] / area
    p = np.full(nnode, p0)
    q = np.zeros(nseg)
    x = x0_mm
    v = 0.0
    # node compliances [mm^3/MPa]; the last node grows with the chamber
    cnode = np.empty(nnode)
    for k in range(nnode):
        cnode[k] = vseg / bulk if 0 < k < nseg else 0.5 * vseg / bulk
    # servo: dead-time ring of commands (in ticks), lag state, backlash, delay ring
    ndead = int(pp[_SERVO_DEAD_TICKS])
    cmd_ring = np.full(ndead + 1, cam0_deg)
    theta_s = cam0_deg
    res = pp[_SERVO_RES]
    theta_b = cam0_deg
    ndelay = int(pp[_DELAY_STEPS])
    delay_ring = np.full(ndelay + 1, cam0_deg)
    di = 0
    cstate = np.zeros(3)
    cstate[2] = np.nan
    cam_cmd = cam0_deg
    q_ref = np.nan
    x_ref = np.nan
    released = False
    t_release = np.nan
    theta_d_s = 0.0
    theta_d_d = 0.0
    theta_n = cam0_deg
    ps = pp[_P_SUPPLY]
    half_w = 0.5 * pp[_BACKLASH]
    ctick = 0
    servo_target = cam0_deg
    p_load_set = p_load
    for i in range(n_fast):
        t = i * dt * nsub
        # ---- sensors at 1 kHz (before the controller uses them)
        ps_true = pp[_P_SUPPLY] + pp[_RIPPLE_AMP] * math.sin(two_pi_f * t)
        x_meas = pp[_GAIN_X] * x
        x_meas = round(x_meas / pp[_ENC_RES]) * pp[_ENC_RES]
        ps_meas = pp[_GAIN_PS] * ps_true + noise[i, 0]
        ph_meas = pp[_GAIN_PH] * p[0] + noise[i, 1]
        pl_meas = pp[_GAIN_PL] * p_load + noise[i, 2]
        fast[i, 0] = t
        fast[i, 1] = x_meas
        fast[i, 2] = ps_meas
        fast[i, 3] = ph_meas
        fast[i, 4] = pl_meas
        fast[i, 5] = x
        fast[i, 6] = v * area
        # ---- controller / schedule at 100 Hz
        if i % every == 0:
            if ctrl_kind == MODE_SCHEDULE:
                if not released:
                    cam_cmd = _step_value(cmd_t, cmd_v, t)
                    if t > cmd_t[1] and (x >= pp[_X_STOP_HI] or x <= pp[_X_STOP_LO]):
                        released = True
                        t_release = t
                if released:
                    cam_cmd = pp[_NEUTRAL]
                x_ref = np.nan
                q_ref = np.nan
            else:
                x_ref = _step_value(ref_t, ref_v, t)
                cam_cmd, q_ref, _held = controller_step(
                    ctrl_kind, cp, csup, csup_z, csup_th, cdr, cdr_z, cdr_th, cstate,
                    x_ref, x_meas, ps_meas, ph_meas, ptank)
            # dead time: the servo acts on the command of ndead ticks ago
            cmd_ring[ctick % (ndead + 1)] = cam_cmd
            servo_target = cmd_ring[(ctick + 1) % (ndead + 1)] if ndead > 0 else cam_cmd
            slow[ctick, 0] = t
            slow[ctick, 1] = cam_cmd
            slow[ctick, 2] = round(theta_s / res) * res
            slow[ctick, 3] = x_ref
            slow[ctick, 4] = q_ref
            slow[ctick, 5] = theta_n
            ctick += 1
            p_load_set = _step_value(load_t, load_v, t)
        # ---- sealing thresholds at 1 kHz (eq. 3 + 4, inverted)
        theta_d_s = J.threshold_deg(sup, sup_z, sup_th, ps_true, ps_true - p[0])
        theta_d_d = J.threshold_deg(dr, dr_z, dr_th, p[0], p[0] - ptank)
        for _ in range(nsub):
            ts = t
            ps_t = pp[_P_SUPPLY] + pp[_RIPPLE_AMP] * math.sin(two_pi_f * ts)
            # servo: first-order lag with rate limit, quantised position
            rate = (servo_target - theta_s) / pp[_SERVO_TAU]
            rmax = pp[_SERVO_RATE]
            if rate > rmax:
                rate = rmax
            elif rate < -rmax:
                rate = -rmax
            theta_s += rate * dt
            theta_q = round(theta_s / res) * res
            # backlash play, then extra transport delay to the needle
            theta_b = min(max(theta_b, theta_q - half_w), theta_q + half_w)
            delay_ring[di] = theta_b
            di = (di + 1) % (ndelay + 1)
            theta_n = delay_ring[di]
            # valve flows into node 0 (supply +, drain -) and their conductance
            dps = ps_t - p[0]
            dpd = p[0] - ptank
            qs, gs = J.side_flow_at(sup, theta_d_s, theta_n, dps, smooth)
            qd, gd = J.side_flow_at(dr, theta_d_d, theta_n, dpd, smooth)
            qv = qs + qd + gl * dps - gl * dpd
            g = gs - gd + 2.0 * gl
            # node 0, implicit in the valve conductance
            p[0] += (dt / cnode[0]) * (qv - q[0]) / (1.0 + dt * g / cnode[0])
            for k in range(1, nseg):
                p[k] += dt / cnode[k] * (q[k - 1] - q[k])
            c_last = cnode[nseg] + (pp[_DEAD_VOL] + area * x) / bulk
            p[nseg] += dt / c_last * (q[nseg - 1] - area * v)
            for k in range(nnode):
                if p[k] < pcav:
                    p[k] = pcav
            # segment flows, implicit in the resistance
            for k in range(nseg):
                q[k] = (q[k] + dt / iseg * (p[k] - p[k + 1])) / (1.0 + dt * rseg / iseg)
            # load regulator and piston
            p_load += dt / pp[_LOAD_TAU] * (p_load_set - p_load)
            f_drive = p[nseg] * area - p_load * pp[_LOAD_AREA]
            v = _friction_step(v, f_drive, pp, dt)
            x += v * dt
            if x <= 0.0:
                x = 0.0
                if v < 0.0:
                    v = 0.0
            elif x >= pp[_STROKE]:
                x = pp[_STROKE]
                if v > 0.0:
                    v = 0.0
            t += dt
    return fast, slow, t_release
