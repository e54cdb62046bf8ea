"""The step law of the paper's position controllers (Sec. III-A/B), compiled.

:func:`controller_step` is the one law behind :class:`.control.FlowModelController`,
:class:`.control.CamController` and the simulator's kernel
(:func:`.kernel.simulate_kernel`); the parameter and state layouts are
:mod:`.packing`'s (``_CP_*``, ``_ST_*``). Units: mm, deg, MPaG, mm^3/s.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from . import jit as J  # first: configures the numba cache
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
    KIND_FLOW_MODEL,
)

__all__ = ["controller_step", "controller_replay"]


@njit(cache=True, nogil=True)
def controller_step(kind, cp, sup, sup_z, sup_th, dr, dr_z, dr_th, state,
                    x_ref_mm, x_mm, p_supply_mpag, p_head_mpag, p_tank_mpag):
    """One step of either controller; updates ``state`` in place.

    The cam is held once |e| <= the band (a band of 0: never held) and
    released at the next reference or when |e| > the release band.

    Returns (cam command [deg], Q_ref [mm^3/s] or NaN, held 0/1).
    """
    e = x_ref_mm - x_mm
    if not (x_ref_mm == state[_ST_XREF]):
        state[_ST_HELD] = 0.0
    state[_ST_XREF] = x_ref_mm
    if state[_ST_HELD] > 0.5 and abs(e) > cp[_CP_RELEASE]:
        state[_ST_HELD] = 0.0
    if kind == KIND_FLOW_MODEL:
        q_ref = cp[_CP_KP] * e
        if state[_ST_HELD] < 0.5 and abs(e) <= cp[_CP_BAND] and cp[_CP_BAND] > 0.0:
            state[_ST_HELD] = 1.0
            # 3 deg below the supply sealing threshold at the measured pressures
            state[_ST_HOLD_DEG] = J.model_cam_for_flow(
                0.0, p_supply_mpag, p_head_mpag, p_tank_mpag, sup, sup_z, sup_th, dr, dr_z, dr_th,
                -np.inf, np.inf, cp[_CP_MIN_DP]) - cp[_CP_HOLD]
        if state[_ST_HELD] > 0.5:
            theta = state[_ST_HOLD_DEG]
        else:
            theta = J.model_cam_for_flow(q_ref, p_supply_mpag, p_head_mpag, p_tank_mpag,
                                         sup, sup_z, sup_th, dr, dr_z, dr_th,
                                         -np.inf, np.inf, cp[_CP_MIN_DP])
    else:
        q_ref = np.nan
        if state[_ST_HELD] < 0.5 and abs(e) <= cp[_CP_BAND] and cp[_CP_BAND] > 0.0:
            state[_ST_HELD] = 1.0
            state[_ST_HOLD_DEG] = cp[_CP_HOLD]
        if state[_ST_HELD] > 0.5:
            theta = state[_ST_HOLD_DEG]
        else:
            theta = cp[_CP_HOLD] + cp[_CP_KP] * e
    theta = min(max(theta, cp[_CP_CAM_MIN]), cp[_CP_CAM_MAX])
    return theta, q_ref, state[_ST_HELD]


@njit(cache=True, nogil=True)
def controller_replay(kind, cp, sup, sup_z, sup_th, dr, dr_z, dr_th, state,
                      x_ref_mm, x_mm, p_supply_mpag, p_head_mpag, p_tank_mpag):
    """:func:`controller_step` over logged ticks (arrays of one length):
    the cam command [deg] of each tick, NaN where the reference or the
    position is not finite (that tick is skipped: the state carries over);
    a non-finite supply or head pressure counts as 0 MPaG. ``state`` is
    updated in place."""
    n = x_ref_mm.size
    out = np.full(n, np.nan)
    for i in range(n):
        if not (np.isfinite(x_mm[i]) and np.isfinite(x_ref_mm[i])):
            continue
        ps = p_supply_mpag[i] if np.isfinite(p_supply_mpag[i]) else 0.0
        ph = p_head_mpag[i] if np.isfinite(p_head_mpag[i]) else 0.0
        theta, _, _ = controller_step(kind, cp, sup, sup_z, sup_th, dr, dr_z, dr_th, state,
                                      x_ref_mm[i], x_mm[i], ps, ph, p_tank_mpag[i])
        out[i] = theta
    return out
