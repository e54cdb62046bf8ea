"""Compiled time-stepping kernel of the plant (numba).

One fixed-step loop integrates the whole rig (see :mod:`.plant` for the
physics and the packed parameter layout):

- valve (eq. 3-5 through :mod:`seanv_analysis.sim.jit`, sealing
  thresholds refreshed at every step) feeding node 0 of the tube,
- 20 m tube as ``n_seg`` lumped segments (laminar resistance R and fluid
  inertance I per segment, compliance C = V / B at the nodes),
- actuator head node (tube end + chamber volume) and piston (mass, Coulomb +
  Stribeck + viscous friction with stiction, end stops) against the
  pneumatic load (regulated pressure, first order),
- servo (100 Hz command, dead time, first-order lag, rate limit, position
  quantisation), then the injected cam-side effects (backlash play, extra
  transport delay),
- sensors sampled at 1 kHz (encoder quantisation, pressure noise, sensor
  gain errors) and the controller/servo log at 100 Hz;
- the valve sides' closed-form terms (``term`` effect), if any, evaluated
  at every plant step by the compiled stack machine of
  :mod:`seanv_analysis.models.expr` (``approach``: the direction the
  needle last moved, 0 until it moves).

Integration: the 2nd-order linearly implicit Rosenbrock-W scheme ROS2
(:mod:`.rosenbrock`, the same compiled step the plant's ODE twin in the
tests and the solver benchmark use) at ``sim.time_step_s`` (default 1 ms = one step
per 1 kHz sample): W = I - gamma h A with A the exact tridiagonal Jacobian
of the hydraulic chain (valve conductance at node 0, tube R-I-C ladder,
head-node/piston spring, damping part of the friction slope), solved by a
two-sided Thomas sweep; L-stable, so the stiff modes are damped, the
slow ones (tube LC modes ~5-10 Hz, head node + piston ~600 rad/s,
omega h = 0.6) integrated to 2nd order. Per step: the servo lag (exact
solution of the rate-limited lag), then quantisation, backlash and the delay line give the
needle angle at the step's end (stage 2's input; stage 1 uses the previous
one); sealing thresholds at the step's start, moved linearly in the
pressures for stage 2; then the non-ODE parts after the step: Karnopp
stiction (a held piston stays at v = 0 while |F_drive| <= F_s; a sliding
one that reversed is stopped), cavitation floor, end stops.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from . import jit as J  # first: configures the numba cache
from . import rosenbrock as RB
from ._pp import (
    _AREA,
    _BACKLASH,
    _CTRL_EVERY,
    _DELAY,
    _DT,
    _ENC_RES,
    _F_STATIC,
    _GAIN_PH,
    _GAIN_PL,
    _GAIN_PS,
    _GAIN_X,
    _LOAD_AREA,
    _N_SEG,
    _NEUTRAL,
    _P_CAV,
    _P_SUPPLY,
    _P_TANK,
    _RIPPLE_AMP,
    _RIPPLE_HZ,
    _SERVO_DEAD_TICKS,
    _SERVO_RES,
    _SERVO_TAU,
    _STOP,
    _STROKE,
    _SUBSTEPS,
    _SUPPLY_DROOP,
    _X_STOP_HI,
    _X_STOP_LO,
    MODE_SCHEDULE,
    OUT_FAST,
    OUT_SLOW,
    PP,
    PP_SIZE,
)
from .control_law import controller_replay, controller_step  # noqa: F401 (exported: .compiled)

__all__ = ["simulate_kernel", "servo_track", "PP", "PP_SIZE", "MODE_SCHEDULE", "OUT_FAST", "OUT_SLOW"]


@njit(cache=True, nogil=True)
def _step_value(t_breaks, values, t):
    """Value of a step sequence at time t (holds from each break) [-]."""
    i = np.searchsorted(t_breaks, t, side="right") - 1
    if i < 0:
        i = 0
    return values[i]


@njit(cache=True, nogil=True)
def simulate_kernel(pp, sup, sup_z, sup_th, dr, dr_z, dr_th, tw,
                    ctrl_kind, cp, csup, csup_z, csup_th, cdr, cdr_z, cdr_th,
                    ref_t, ref_v, load_t, load_v, cmd_t, cmd_v,
                    noise, n_fast, x0_mm, cam0_deg, p0_mpag, hold0_deg):
    """Run the plant for ``n_fast`` 1 kHz samples.

    Parameters
    ----------
    pp : packed plant parameters (:class:`PP`)
    sup..dr_th : plant valve, packed (``sim.jit.pack_side``)
    tw : the valve sides' closed-form terms, packed (``sim.jit.pack_terms``,
        with the run's index; modes ``TERM_NONE``: none); the kernel writes
        the terms' variables and stack into it
    ctrl_kind : MODE_SCHEDULE (cam from ``cmd_t/cmd_v`` with end-of-stroke
        release), or the controller kinds of :mod:`seanv_analysis.sim.control`
    cp, csup..cdr_th : controller parameters and its valve model, packed
    ref_t, ref_v : position reference step sequence [s], [mm]
    load_t, load_v : load pressure set-point step sequence [s], [MPaG]
    cmd_t, cmd_v : open-loop cam command step sequence [s], [deg]
    noise : (n_fast, 3) standard-normal draws scaled to pressure noise [MPa]
        for p_supply, p_head, p_load
    x0_mm, cam0_deg : initial position and cam angle
    p0_mpag : initial pressure of every tube node and the head [MPaG];
        NaN: the pressure that balances the initial load (at rest)
    hold0_deg : the controller starts holding this cam angle [deg] (it had
        converged on the initial reference); NaN: it starts free

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
    ix = 2 * nseg + 1
    iv = ix + 1
    ith = ix + 2
    ipl = ix + 3
    area = pp[_AREA]
    load_area = pp[_LOAD_AREA]
    fs = pp[_F_STATIC]
    ptank = pp[_P_TANK]
    pcav = pp[_P_CAV]
    stroke = pp[_STROKE]
    psup = pp[_P_SUPPLY]
    amp = pp[_RIPPLE_AMP]
    om = 2.0 * math.pi * pp[_RIPPLE_HZ]
    # supply ripple by a rotation recurrence per plant step, re-synchronised
    # (sin, cos) every 1000 steps
    ch, sh = math.cos(om * dt), math.sin(om * dt)
    sn, cn = 0.0, 1.0

    n_ctrl = (n_fast + every - 1) // every
    fast = np.empty((n_fast, 7))
    slow = np.empty((n_ctrl, 6))

    # state (layout of .rosenbrock): at rest, head pressure balancing the load
    # (or the given one: a run re-started from a logged state)
    p_load = _step_value(load_t, load_v, 0.0)
    y = np.zeros(2 * nseg + 5)
    p_init = p_load * load_area / area if math.isnan(p0_mpag) else p0_mpag
    for k in range(nnode):
        y[k] = p_init
    y[ix] = x0_mm
    y[ith] = cam0_deg
    y[ipl] = p_load
    w = (np.zeros(y.size), np.zeros(y.size), np.zeros(y.size), np.zeros(y.size),
         np.zeros(y.size), np.zeros(y.size), np.zeros(y.size), np.zeros(y.size),
         np.zeros(y.size), np.zeros(y.size), tw)
    thr = np.zeros(7)
    # closed-form terms: approach tracked here from the needle's motion (the
    # plant sets the other variables; run is packed)
    has_term = tw[J.TW_SUPPLY + J.TW_MODE] != 0.0 or tw[J.TW_DRAIN + J.TW_MODE] != 0.0
    i_approach = int(tw[J.TW_VARS]) + J.TV_APPROACH
    # servo: dead-time ring of commands (in ticks), backlash, delay ring
    ndead = int(pp[_SERVO_DEAD_TICKS])
    cmd_ring = np.full(ndead + 1, cam0_deg)
    res = pp[_SERVO_RES]
    theta_b = cam0_deg
    ndelay = int(round(pp[_DELAY] / pp[_DT]))   # the extra delay in whole plant steps
    delay_ring = np.full(ndelay + 1, cam0_deg)
    di = 0
    cstate = np.zeros(3)
    cstate[2] = np.nan
    if not math.isnan(hold0_deg):       # (held, hold angle, reference it holds for)
        cstate[0] = 1.0
        cstate[1] = hold0_deg
        cstate[2] = _step_value(ref_t, ref_v, 0.0)
    cam_cmd = cam0_deg
    q_ref = np.nan
    x_ref = np.nan
    released = False
    t_release = np.nan
    theta_n = cam0_deg
    backlash_deg = pp[_BACKLASH]
    ctick = 0
    servo_target = cam0_deg
    servo_decay = math.exp(-dt / pp[_SERVO_TAU])   # the servo lag's, over one plant step
    p_load_set = p_load
    step = 0
    for i in range(n_fast):
        if i % 256 == 0 and pp[_STOP] != 0.0:   # stopped from outside (Ctrl-C): return now
            break
        t = i * dt * nsub
        if step % 1000 == 0:
            sn, cn = math.sin(om * step * dt), math.cos(om * step * dt)
        # ---- sensors at 1 kHz (before the controller uses them)
        # the supply droops with the flow it delivers (the piston extending)
        droop = pp[_SUPPLY_DROOP] * max(y[iv] * area, 0.0)
        ps_true = psup - droop + amp * sn
        x = y[ix]
        x_meas = pp[_GAIN_X] * x
        x_meas = round(x_meas / pp[_ENC_RES]) * pp[_ENC_RES]
        ps_meas = pp[_GAIN_PS] * ps_true + noise[i, 0]
        ph_meas = pp[_GAIN_PH] * y[0] + noise[i, 1]
        pl_meas = pp[_GAIN_PL] * y[ipl] + noise[i, 2]
        fast[i, 0] = t
        fast[i, 1] = x_meas
        fast[i, 2] = ps_meas
        fast[i, 3] = ph_meas
        fast[i, 4] = pl_meas
        fast[i, 5] = x
        fast[i, 6] = y[iv] * area
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
            slow[ctick, 2] = round(y[ith] / res) * res
            slow[ctick, 3] = x_ref
            slow[ctick, 4] = q_ref
            slow[ctick, 5] = theta_n
            ctick += 1
            p_load_set = _step_value(load_t, load_v, t)
        for sub in range(nsub):
            if sub > 0 and step % 1000 == 0:
                sn, cn = math.sin(om * step * dt), math.cos(om * step * dt)
            sn1 = sn * ch + cn * sh
            cn1 = cn * ch - sn * sh
            droop = pp[_SUPPLY_DROOP] * max(y[iv] * area, 0.0)
            ps0 = psup - droop + amp * sn
            ps1 = psup - droop + amp * sn1
            # servo (the rate-limited lag solved exactly over the step),
            # quantised position, backlash play, extra transport delay ->
            # needle at the step's end
            theta_s = RB.servo_step_decay(y[ith], servo_target, dt, pp, servo_decay)
            theta_q = round(theta_s / res) * res
            theta_b = J.backlash_play(theta_b, theta_q, backlash_deg)
            delay_ring[di] = theta_b
            di = (di + 1) % (ndelay + 1)
            needle1 = delay_ring[di]
            # sealing thresholds (eq. 3 + 4, inverted) at the step's start
            RB.thresholds(thr, ps0, y[0], ptank, sup, sup_z, sup_th, dr, dr_z, dr_th)
            # Karnopp: a held piston stays held while |F_drive| <= F_s
            v = y[iv]
            if v == 0.0:
                f_drive = y[nseg] * area - y[ipl] * load_area
                if abs(f_drive) <= fs:
                    mode = RB.FR_STUCK
                    sgn = 0.0
                else:
                    mode = RB.FR_SLIDE
                    sgn = math.copysign(1.0, f_drive)
            else:
                mode = RB.FR_SLIDE
                sgn = math.copysign(1.0, v)
            if has_term:
                if needle1 > theta_n:
                    tw[i_approach] = 1.0
                elif needle1 < theta_n:
                    tw[i_approach] = -1.0
            RB.plant_step(y, dt, ps0, ps1, theta_n, needle1, thr, p_load_set, mode, sgn, pp,
                          sup, dr, w)
            y[ith] = theta_s
            theta_n = needle1
            # a sliding piston that reversed within the step sticks
            if mode == RB.FR_SLIDE and y[iv] * sgn <= 0.0:
                y[iv] = 0.0
            for k in range(nnode):
                if y[k] < pcav:
                    y[k] = pcav
            if y[ix] <= 0.0:
                y[ix] = 0.0
                if y[iv] < 0.0:
                    y[iv] = 0.0
            elif y[ix] >= stroke:
                y[ix] = stroke
                if y[iv] > 0.0:
                    y[iv] = 0.0
            sn, cn = sn1, cn1
            step += 1
    return fast, slow, t_release


@njit(cache=True, nogil=True)
def servo_track(t_cmd, cmd, t0, h, n, dead_s, pp, theta0):
    """The servo alone on a logged command (:func:`.servo.servo_response`):
    ``n`` steps of ``h`` [s] from ``t0`` [s], acting on the command of
    ``dead_s`` earlier (held between its samples ``t_cmd``, ``cmd``), the
    lag and rate limit of ``pp`` (``_SERVO_TAU``, ``_SERVO_RATE``); the
    angle [deg] after each step."""
    out = np.empty(n)
    theta = theta0
    j = 0
    m = t_cmd.size
    decay = math.exp(-h / pp[_SERVO_TAU])   # the lag's, over each step of h
    for i in range(n):
        if i % 65536 == 0 and pp[_STOP] != 0.0:   # stopped from outside (Ctrl-C): return now
            break
        t_eff = t0 + i * h - dead_s
        while j + 1 < m and t_cmd[j + 1] <= t_eff:
            j += 1
        target = cmd[j] if t_cmd[j] <= t_eff else cmd[0]
        theta = RB.servo_step_decay(theta, target, h, pp, decay)
        out[i] = theta
    return out
