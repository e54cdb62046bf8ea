"""numba-compiled forms of the model equations for the simulator and controllers.

Nothing here is new physics: each compiled function is ``numba.njit`` applied
to the plain core function of :mod:`seanv_analysis.models.sealing`,
:mod:`~seanv_analysis.models.valve` or :mod:`~seanv_analysis.models.effects`,
so the kernel, the controllers and :class:`~seanv_analysis.models.ValveSide`
run the same source. The composites (threshold angle, a side's flow, eq. 6 for
the whole valve) chain the cores exactly as :class:`ValveSide` and
:class:`ValveModel` do.

A valve side is packed for compiled code as ``(params, z_table, theta_table)``
with ``params`` indexed by the ``SP_*`` constants, the closed-form terms of
both sides (the ``term`` effect) in one float64 array: see :mod:`.packing`
(plain numpy; re-exported here). :func:`run_program` is the stack machine of
:mod:`seanv_analysis.models.expr` compiled, so one compiled kernel runs any
expression.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..models import effects as _effects
from ..models import expr as _expr
from ..models import sealing as _sealing
from ..models import valve as _valve
from .numba_cache import configure_numba_cache
from .packing import (  # noqa: F401 -- the layouts, re-exported for the compiled code
    SP_C,
    SP_DN,
    SP_DO,
    SP_EXPONENT,
    SP_K,
    SP_QMAX,
    SP_SHARP,
    SP_SIZE,
    SP_UP,
    SP_Z0,
    TERM_ADD,
    TERM_MUL,
    TERM_NONE,
    TERM_THRESHOLD,
    TV_APPROACH,
    TV_DP,
    TV_DTHETA,
    TV_LOAD,
    TV_P1,
    TV_Q,
    TV_RUN,
    TV_SIZE,
    TV_THETA,
    TW_CODE,
    TW_CONST,
    TW_DRAIN,
    TW_HEADER,
    TW_MODE,
    TW_N,
    TW_STACK,
    TW_SUPPLY,
    TW_VARS,
    pack_model,
    pack_side,
    pack_terms,
)

# before the first cached njit of the package (every compiled module imports
# this one first): the cache folder is keyed by the compiled sources
configure_numba_cache()

__all__ = ["SP_Z0", "SP_C", "SP_EXPONENT", "SP_DN", "SP_DO", "SP_K", "SP_UP", "SP_QMAX",
           "SP_SHARP", "SP_SIZE", "pack_side", "pack_model",
           "fluid_force", "threshold_displacement", "table_segment", "angle_for_height",
           "signed_power", "seat_leakage",
           "opening", "flow", "cam_for_flow", "saturate", "threshold_deg", "side_flow", "side_flow_at",
           "model_cam_for_flow", "backlash_play",
           "TERM_NONE", "TERM_MUL", "TERM_ADD", "TERM_THRESHOLD",
           "TV_DP", "TV_P1", "TV_DTHETA", "TV_THETA", "TV_Q", "TV_LOAD", "TV_RUN", "TV_APPROACH",
           "TV_SIZE", "TW_SUPPLY", "TW_DRAIN", "TW_VARS", "TW_STACK", "TW_HEADER", "TW_MODE",
           "TW_CODE", "TW_N", "TW_CONST", "pack_terms", "run_program"]

_opts = dict(cache=True, nogil=True)

fluid_force = njit(**_opts)(_sealing.fluid_force_core)
threshold_displacement = njit(**_opts)(_sealing.threshold_displacement_core)


@njit(**_opts)
def table_segment(z_table_mm, z_mm):
    """Index lo of the segment with z[lo] <= z < z[lo + 1] of a strictly
    increasing table, for z[0] < z < z[-1] (bisection)."""
    lo, hi = 0, z_table_mm.size - 1
    while hi - lo > 1:
        mid = (lo + hi) >> 1
        if z_table_mm[mid] <= z_mm:
            lo = mid
        else:
            hi = mid
    return lo


@njit(**_opts)
def angle_for_height(z_mm, z_table_mm, theta_table_deg):
    """Scalar form of :func:`.sealing.angle_for_height_core` (inverse of
    eq. 4): the same linear interpolation, clipped at the table ends, by a
    binary search -- numba's ``np.interp`` costs ~150 ns per scalar call,
    this ~20 ns, and the simulator calls it at every step [deg]."""
    n = z_table_mm.size
    if z_mm <= z_table_mm[0]:
        return theta_table_deg[0]
    if z_mm >= z_table_mm[n - 1]:
        return theta_table_deg[n - 1]
    lo = table_segment(z_table_mm, z_mm)
    hi = lo + 1
    w = (z_mm - z_table_mm[lo]) / (z_table_mm[hi] - z_table_mm[lo])
    return theta_table_deg[lo] + w * (theta_table_deg[hi] - theta_table_deg[lo])

signed_power = njit(**_opts)(_valve.signed_power_core)
seat_leakage = njit(**_opts)(_valve.seat_leakage_core)
opening = njit(**_opts)(_valve.opening_core)
flow = njit(**_opts)(_valve.flow_core)
cam_for_flow = njit(**_opts)(_valve.cam_for_flow_core)
saturate = njit(**_opts)(_effects.saturate_flow_core)
backlash_play = njit(**_opts)(_effects.backlash_play_deg)
run_program = njit(**_opts)(_expr.run_program_core)

@njit(**_opts)
def threshold_deg(params, z_table, theta_table, p1_mpa, dp_mpa):
    """Sealing threshold angle, eq. (3) + (4) inverted [deg] (as ValveSide.threshold_deg)."""
    z_thr = threshold_displacement(params[SP_Z0],
                                   fluid_force(p1_mpa, dp_mpa, params[SP_DN], params[SP_DO]),
                                   params[SP_K])
    return angle_for_height(z_thr, z_table, theta_table)


@njit(**_opts)
def side_flow_at(params, theta_d_deg, theta_deg, dp_mpa, smooth_mpa):
    """Flow of one side for a known threshold angle, eq. (5) with the smoothed
    dp law and the flow cap [mm^3/s].

    Returns (Q [mm^3/s], dQ/d(dp) [mm^3/(s MPa)]) -- the slope is the valve
    conductance entry of the ROS2 step's Jacobian (:mod:`seanv_analysis.sim.rosenbrock`).
    """
    o = opening(theta_deg, theta_d_deg, params[SP_UP] > 0.5)
    if o <= 0.0:
        return 0.0, 0.0
    n = params[SP_EXPONENT]
    # dp^n as in valve.signed_power_core: dp max(|dp|, s)^(n-1), with the
    # power evaluated once (sqrt for the orifice law) and reused for the slope
    adp = abs(dp_mpa)
    a = adp if adp > smooth_mpa else smooth_mpa
    if a <= 0.0:
        a = 1e-300
    r = 1.0 / math.sqrt(a) if n == 0.5 else a ** (n - 1.0)
    q = flow(o, dp_mpa * r, params[SP_C])
    slope = r if adp < smooth_mpa else n * r
    dq = params[SP_C] * o * o * slope
    qmax = params[SP_QMAX]
    if qmax < np.inf:
        qs = saturate(q, qmax, params[SP_SHARP])
        # d(sat)/dq = (1 + r^s)^(-1/s - 1), r = |q|/qmax
        r = (abs(q) / qmax) ** params[SP_SHARP]
        dq = dq * (1.0 + r) ** (-1.0 / params[SP_SHARP] - 1.0)
        q = qs
    return q, dq


@njit(**_opts)
def side_flow(params, z_table, theta_table, theta_deg, p1_mpa, dp_mpa, smooth_mpa):
    """Flow of one side, eq. (3)-(5) with the smoothed dp law and the flow cap
    [mm^3/s]; returns (Q, dQ/d(dp))."""
    theta_d = threshold_deg(params, z_table, theta_table, p1_mpa, dp_mpa)
    return side_flow_at(params, theta_d, theta_deg, dp_mpa, smooth_mpa)


@njit(**_opts)
def model_cam_for_flow(q_mm3_s, p_supply_mpag, p_head_mpag, p_tank_mpag, sup, sup_z, sup_th,
                       dr, dr_z, dr_th, cam_min_deg, cam_max_deg, min_dp_mpa):
    """Eq. (6) for the whole valve, clipped (as ValveModel.cam_for_flow) [deg]."""
    if q_mm3_s >= 0.0:
        p1 = p_supply_mpag
        dp = max(p_supply_mpag - p_head_mpag, min_dp_mpa)
        theta_d = threshold_deg(sup, sup_z, sup_th, p1, dp)
        theta = cam_for_flow(q_mm3_s, theta_d, dp ** sup[SP_EXPONENT], sup[SP_C], sup[SP_UP] > 0.5)
    else:
        p1 = p_head_mpag
        dp = max(p_head_mpag - p_tank_mpag, min_dp_mpa)
        theta_d = threshold_deg(dr, dr_z, dr_th, p1, dp)
        theta = cam_for_flow(q_mm3_s, theta_d, dp ** dr[SP_EXPONENT], dr[SP_C], dr[SP_UP] > 0.5)
    return min(max(theta, cam_min_deg), cam_max_deg)
