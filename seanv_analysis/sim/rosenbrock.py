"""The simulator's integrator: one step of a 2nd-order linearly implicit
Rosenbrock-W scheme (ROS2, Verwer et al. 1999) for the plant (numba).

Called by the kernel (:mod:`.kernel`); the continuous ODE twin of the plant
that checks and benchmarks it (``tests/sim_rhs.py``) steps the same
functions, so the twin's fixed-step run is the simulator's own integrator on
the same physics.

Scheme (step h, gamma = 1 + 1/sqrt(2), W = I - gamma h A)::

    W k1 = f(t_n, y_n)
    W k2 = f(t_n + h, y_n + h k1) - 2 k1
    y_{n+1} = y_n + 3/2 h k1 + 1/2 h k2

It is L-stable and of order 2 for ANY matrix A (a W-method), so A only needs
the stiff couplings, exactly: here A is the Jacobian of the hydraulic chain,
which ordered as [p_0, q_0, p_1, q_1, ..., p_nseg, v] is tridiagonal (valve
conductance at node 0, node compliances, segment inertance and resistance,
the head-node/piston spring, the friction slope), solved by the Thomas
algorithm; x, theta and the load pressure are slow and enter A only through
their own diagonal (0, servo lag, regulator lag). The dependences A leaves
out (sealing threshold on p_0, chamber volume on x, load pressure on v)
keep order 2, they only cost accuracy where they are stiff (they are not).
Anti-damping parts of the friction slope (Stribeck) are left out of A: an
unstable eigenvalue in W could make it singular.

Inputs that are not states of the plant step (needle angle, supply
pressure with its ripple) are given at both stage times t_n and t_n + h;
the sealing thresholds are given once per step (refreshed at the step
rate, 1 kHz by default). The servo is advanced first by the exact solution
of its rate-limited lag (:func:`servo_step`), so its new angle is the
stage-2 input of the plant step (the servo does not depend on the plant).

Friction modes (``fr_mode``):

- ``FR_SMOOTH``: ``F = (Fc + (Fs - Fc) exp(-(v/vs)^2)) tanh(v/eps) + b v``
  (the ODE twin; ``fr_arg`` = eps [mm/s]);
- ``FR_SLIDE``: Coulomb + Stribeck + viscous in a fixed direction
  ``fr_arg`` = +-1 (the kernel's Karnopp sliding phase; the kernel stops
  the piston after the step if v reversed);
- ``FR_STUCK``: the piston is held (v = 0, dv/dt = 0; Karnopp stuck phase).

Closed-form terms (the ``term`` effect): ``tw``, both sides' programs,
their variables and stack in one float64 array
(:func:`seanv_analysis.sim.jit.pack_terms`; the caller sets run and
approach). A side with a term gets its flow (or threshold) corrected at
every evaluation of f, with the stage's pressures; its valve conductance in
A is then a forward difference in dp of the corrected flow, kept of the
side's sign (so W's pivots stay >= 1). Without terms the arithmetic is
exactly that of the plant without them, and ``tw`` rides in the scratch
tuple ``w`` of :func:`plant_step` (no extra argument in the step loop).

Units: mm, MPa, s, N (as :mod:`.plant`). State layout (``n = 2 nseg + 5``):
p_0..p_nseg [MPaG], q_0..q_{nseg-1} [mm^3/s], x [mm], v [mm/s], servo theta
[deg] (not touched by :func:`plant_step`), load pressure [MPaG].
"""
from __future__ import annotations

import math

from numba import njit

from . import jit as J
from ._pp import (
    _AREA,
    _BULK,
    _DEAD_VOL,
    _DP_SMOOTH,
    _F_COULOMB,
    _F_STATIC,
    _I_SEG,
    _LEAK_G,
    _LOAD_AREA,
    _LOAD_TAU,
    _MASS,
    _N_SEG,
    _P_TANK,
    _R_SEG,
    _SERVO_RATE,
    _SERVO_TAU,
    _V_SEG,
    _V_STRIBECK,
    _VISCOUS,
)

__all__ = ["GAMMA", "FR_SMOOTH", "FR_SLIDE", "FR_STUCK", "plant_f", "plant_step", "servo_step",
           "servo_step_decay", "thresholds", "term_flow", "TERM_DP_STEP"]

#: ROS2 parameter (L-stable choice)
GAMMA = 1.0 + 1.0 / math.sqrt(2.0)
FR_SMOOTH = 0
FR_SLIDE = 1
FR_STUCK = 2


# plant_step and thresholds, the two entry points the callers' step loops
# call, are compiled without numba's reference counting (_nrt=False) and not
# inlined into the callers: they only read and write the arrays they are
# given (no allocation, no array kept), so the counts would be balanced no-ops,
# but inlined into the callers' loops they cost dozens of atomic
# increments/decrements per step that numba's pruning leaves in the branchy
# code (~120 of ~410 ns per step). Called, not inlined: the arguments are
# borrowed, nothing is counted. error_model='numpy': no zero-division checks
# (every divisor here is a parameter validated > 0 or a pivot >= 1), ~4 %.

#: dp step of the forward difference behind a term's valve conductance [MPa]
TERM_DP_STEP = 1e-6


@njit(cache=True, nogil=True)
def _term_value(tw, side, params, th, needle, dp, smooth, q):
    """One side's flow with its closed-form term (``side``: ``J.TW_SUPPLY``
    or ``J.TW_DRAIN``, its header in ``tw``) at threshold ``th`` [deg],
    needle ``needle`` [deg], ``dp`` [MPa], given its flow ``q`` of eq. (5)
    there [mm^3/s]; the other variables are in ``tw``. Returns the corrected
    flow [mm^3/s]."""
    v = int(tw[J.TW_VARS])
    d = needle - th
    tw[v + J.TV_DTHETA] = d if params[J.SP_UP] > 0.5 else -d
    tw[v + J.TV_Q] = q
    e = J.run_program(tw, int(tw[side + J.TW_CODE]), int(tw[side + J.TW_N]),
                      int(tw[side + J.TW_CONST]), v, int(tw[J.TW_STACK]))
    mode = tw[side + J.TW_MODE]
    if mode == J.TERM_MUL:
        return q * (1.0 + e)
    if mode == J.TERM_ADD:
        return q + e
    q2, _g = J.side_flow_at(params, th + e, needle, dp, smooth)   # TERM_THRESHOLD
    return q2


@njit(cache=True, nogil=True, _nrt=False, error_model='numpy')
def term_flow(tw, side, params, th, needle, p1, dp, smooth, load, q, g, want_slope):
    """Flow of one side with its closed-form term (``tw`` from
    ``J.pack_terms``, ``side`` ``J.TW_SUPPLY`` / ``J.TW_DRAIN`` with a mode)
    [mm^3/s], and, with ``want_slope``, its slope d/d(dp) by a forward
    difference of ``TERM_DP_STEP`` [mm^3/(s MPa)] (0 beyond the side's
    sign: >= 0 supply, <= 0 drain); ``q``, ``g``: the side's flow and slope
    without the term (``J.side_flow_at``); ``p1`` [MPa], ``load`` [MPaG]."""
    v = int(tw[J.TW_VARS])
    tw[v + J.TV_DP] = dp
    tw[v + J.TV_P1] = p1
    tw[v + J.TV_THETA] = needle
    tw[v + J.TV_LOAD] = load
    q1 = _term_value(tw, side, params, th, needle, dp, smooth, q)
    if not want_slope:
        return q1, g
    h = TERM_DP_STEP
    qh, _g = J.side_flow_at(params, th, needle, dp + h, smooth)
    tw[v + J.TV_DP] = dp + h
    q2 = _term_value(tw, side, params, th, needle, dp + h, smooth, qh)
    tw[v + J.TV_DP] = dp
    slope = (q2 - q1) / h
    if params[J.SP_C] >= 0.0:
        slope = max(slope, 0.0)
    else:
        slope = min(slope, 0.0)
    if slope != slope:
        slope = 0.0
    return q1, slope


@njit(cache=True, nogil=True, inline='always')
def plant_f(ps, y, needle, th_s, th_d, p_load_set, fr_mode, fr_arg, pp, sup, dr, tw, dydt,
            want_jac, jl, jd, ju):
    """f of the plant states at supply pressure ``ps`` [MPaG], needle angle
    ``needle`` [deg], sealing thresholds ``th_s``, ``th_d`` [deg], load set
    point ``p_load_set`` [MPaG], friction mode ``fr_mode`` / ``fr_arg``
    (module doc), the sides' closed-form terms ``tw`` (module doc), into
    ``dydt`` (the servo entry is left alone).

    With ``want_jac``: the tridiagonal Jacobian of the chain
    [p_0, q_0, ..., p_nseg, v] into ``jl`` (sub), ``jd`` (diagonal), ``ju``
    (super), chain index j (p_k at 2k, q_k at 2k + 1, v at 2 nseg + 1),
    units 1/s and the states' unit ratios. The friction slope enters only
    where it damps (>= 0)."""
    nseg = int(pp[_N_SEG])
    iq = nseg + 1
    ix = 2 * nseg + 1
    iv = ix + 1
    ipl = ix + 3
    area = pp[_AREA]
    bulk = pp[_BULK]
    gl = pp[_LEAK_G]
    ptank = pp[_P_TANK]
    smooth = pp[_DP_SMOOTH]
    inv_i = 1.0 / pp[_I_SEG]
    r_i = pp[_R_SEG] * inv_i
    inv_c_end = 2.0 * bulk / pp[_V_SEG]
    inv_c_mid = bulk / pp[_V_SEG]
    x = y[ix]
    v = y[iv]
    # valve into node 0 (eq. 3-5 for the given thresholds) and its conductance
    p0 = y[0]
    dps = ps - p0
    dpd = p0 - ptank
    qs, gs = J.side_flow_at(sup, th_s, needle, dps, smooth)
    qd, gd = J.side_flow_at(dr, th_d, needle, dpd, smooth)
    if tw[J.TW_SUPPLY + J.TW_MODE] != 0.0:
        qs, gs = term_flow(tw, J.TW_SUPPLY, sup, th_s, needle, ps, dps, smooth, y[ipl], qs, gs,
                           want_jac)
    if tw[J.TW_DRAIN + J.TW_MODE] != 0.0:
        qd, gd = term_flow(tw, J.TW_DRAIN, dr, th_d, needle, p0, dpd, smooth, y[ipl], qd, gd,
                           want_jac)
    qv = qs + qd + J.seat_leakage(gl, dps, dpd)        # models.valve.seat_leakage_core
    g = gs - gd + 2.0 * gl
    # node pressures (C = V / B; half segments at the ends, chamber at the last)
    dydt[0] = (qv - y[iq]) * inv_c_end
    for k in range(1, nseg):
        dydt[k] = (y[iq + k - 1] - y[iq + k]) * inv_c_mid
    inv_c_last = 1.0 / (0.5 * pp[_V_SEG] / bulk + (pp[_DEAD_VOL] + area * x) / bulk)
    dydt[nseg] = (y[iq + nseg - 1] - area * v) * inv_c_last
    # segment flows: I dq/dt = p_k - p_{k+1} - R q
    for k in range(nseg):
        dydt[iq + k] = (y[k] - y[k + 1]) * inv_i - r_i * y[iq + k]
    # load regulator
    dydt[ipl] = (p_load_set - y[ipl]) / pp[_LOAD_TAU]
    dydt[ix] = v
    # piston
    m = pp[_MASS]
    f_drive = y[nseg] * area - y[ipl] * pp[_LOAD_AREA]
    if fr_mode == FR_STUCK:
        dydt[iv] = 0.0
        dff = 0.0
    else:
        fc = pp[_F_COULOMB]
        dfs = pp[_F_STATIC] - fc
        vs = pp[_V_STRIBECK]
        u2 = (v / vs) ** 2
        # exp(-u2) < 1e-21 beyond 48 (and tanh = +-1 in double beyond 20):
        # skipped, the same numbers
        e = math.exp(-u2) if u2 < 48.0 else 0.0
        de = dfs * e * (-2.0 * v / (vs * vs))          # d/dv of the Stribeck term
        if fr_mode == FR_SMOOTH:
            eps = fr_arg
            z = v / eps
            th = math.tanh(z) if abs(z) < 20.0 else math.copysign(1.0, z)
            fmag = fc + dfs * e
            ff = fmag * th + pp[_VISCOUS] * v
            dff = fmag * (1.0 - th * th) / eps + de * th + pp[_VISCOUS]
        else:
            s = fr_arg
            ff = s * (fc + dfs * e) + pp[_VISCOUS] * v
            dff = s * de + pp[_VISCOUS]
        dydt[iv] = (f_drive - ff) / m
    if want_jac:
        nc = 2 * nseg + 2
        jd[0] = -g * inv_c_end
        jl[0] = 0.0
        ju[0] = -inv_c_end
        for k in range(1, nseg):
            jl[2 * k] = inv_c_mid
            jd[2 * k] = 0.0
            ju[2 * k] = -inv_c_mid
        for k in range(nseg):
            jl[2 * k + 1] = inv_i
            jd[2 * k + 1] = -r_i
            ju[2 * k + 1] = -inv_i
        jn = 2 * nseg
        jl[jn] = inv_c_last
        jd[jn] = 0.0
        stuck = fr_mode == FR_STUCK
        ju[jn] = 0.0 if stuck else -area * inv_c_last
        jl[nc - 1] = 0.0 if stuck else area / m
        jd[nc - 1] = -max(dff, 0.0) / m
        ju[nc - 1] = 0.0


@njit(cache=True, nogil=True, inline='always')
def _factor(wl, wd, wu, cp, den, nc):
    """Twisted (two-sided) LU of the tridiagonal chain matrix W (sub ``wl``,
    diagonal ``wd``, super ``wu``): eliminated from the top down to the
    middle position m = nc // 2 and from the bottom up to it, two
    independent recurrences the CPU overlaps. ``cp`` gets the eliminated
    coupling, ``den`` 1 / pivot. No pivoting: W = I - gamma h A with A's
    diagonal <= 0 and its off-diagonal pairs of opposite sign (the chain is
    an R-L-C ladder), so every pivot is >= 1."""
    m = nc // 2
    inv = 1.0 / wd[0]
    den[0] = inv
    cp[0] = wu[0] * inv
    for j in range(1, m):
        inv = 1.0 / (wd[j] - wl[j] * cp[j - 1])
        den[j] = inv
        cp[j] = wu[j] * inv
    inv = 1.0 / wd[nc - 1]
    den[nc - 1] = inv
    cp[nc - 1] = wl[nc - 1] * inv
    for j in range(nc - 2, m, -1):
        inv = 1.0 / (wd[j] - wu[j] * cp[j + 1])
        den[j] = inv
        cp[j] = wl[j] * inv
    den[m] = 1.0 / (wd[m] - wl[m] * cp[m - 1] - wu[m] * cp[m + 1])


@njit(cache=True, nogil=True, inline='always')
def _solve(r, o, tmp, wl, wu, cp, den, nseg, d_pl):
    """Solve W k = r into ``o`` (may be ``r``): the chain by the factorised
    twisted sweep (:func:`_factor`), x (W = 1) and the load pressure
    (``d_pl``) by their diagonals; the servo entry is left alone. Chain
    order p_0, q_0, p_1, ..., q_{nseg-1}, p_nseg, v (gathered into ``tmp``)."""
    iq = nseg + 1
    iv = 2 * nseg + 2
    nc = 2 * nseg + 2
    m = nc // 2
    for k in range(nseg):
        tmp[2 * k] = r[k]
        tmp[2 * k + 1] = r[iq + k]
    tmp[nc - 2] = r[nseg]
    tmp[nc - 1] = r[iv]
    # the recurrences carry their value in a register (prev), not through memory
    top = tmp[0] * den[0]
    tmp[0] = top
    for j in range(1, m):
        top = (tmp[j] - wl[j] * top) * den[j]
        tmp[j] = top
    bot = tmp[nc - 1] * den[nc - 1]
    tmp[nc - 1] = bot
    for j in range(nc - 2, m, -1):
        bot = (tmp[j] - wu[j] * bot) * den[j]
        tmp[j] = bot
    mid = (tmp[m] - wl[m] * top - wu[m] * bot) * den[m]
    tmp[m] = mid
    prev = mid
    for j in range(m - 1, -1, -1):
        prev = tmp[j] - cp[j] * prev
        tmp[j] = prev
    prev = mid
    for j in range(m + 1, nc):
        prev = tmp[j] - cp[j] * prev
        tmp[j] = prev
    for k in range(nseg):
        o[k] = tmp[2 * k]
        o[iq + k] = tmp[2 * k + 1]
    o[nseg] = tmp[nc - 2]
    o[iv] = tmp[nc - 1]
    o[iv - 1] = r[iv - 1]              # x: W = 1
    o[iv + 2] = r[iv + 2] / d_pl       # load pressure


@njit(cache=True, nogil=True, inline='always')
def _threshold_lin(params, z_table, theta_table, p1_mpa, dp_mpa, hint):
    """:func:`seanv_analysis.sim.jit.threshold_deg` (same arithmetic,
    same value) and its partial derivatives d/dp1, d/d(dp) [deg/MPa]: eq. (1)
    and (3) are linear in the pressures, the inverse of eq. (4) is the
    height table interpolated linearly (slope of the segment, 0 beyond the
    table's ends). The table segment is looked up next to ``hint`` (the
    previous call's) first, by bisection otherwise (``J.table_segment``, as
    ``angle_for_height``): z[lo] <= z < z[lo + 1] of a strictly increasing
    table. Returns (theta, d/dp1, d/d(dp), segment)."""
    z_thr = J.threshold_displacement(params[J.SP_Z0],
                                     J.fluid_force(p1_mpa, dp_mpa, params[J.SP_DN],
                                                   params[J.SP_DO]),
                                     params[J.SP_K])
    q = math.pi / 4 / params[J.SP_K]
    dz_dp1 = -q * params[J.SP_DN] ** 2
    dz_ddp = q * params[J.SP_DO] ** 2
    n = z_table.size
    if z_thr <= z_table[0]:
        return theta_table[0], 0.0, 0.0, hint
    if z_thr >= z_table[n - 1]:
        return theta_table[n - 1], 0.0, 0.0, hint
    lo = hint
    if 0 <= lo < n - 1 and z_table[lo] <= z_thr:
        while lo < n - 2 and z_table[lo + 1] <= z_thr and lo - hint < 3:
            lo += 1
        ok = z_thr < z_table[lo + 1]
    elif 1 <= lo < n and z_table[lo - 1] <= z_thr:
        lo -= 1
        ok = True
    else:
        ok = False
    if not ok:
        lo = J.table_segment(z_table, z_thr)
    hi = lo + 1
    w = (z_thr - z_table[lo]) / (z_table[hi] - z_table[lo])
    theta = theta_table[lo] + w * (theta_table[hi] - theta_table[lo])
    slope = (theta_table[hi] - theta_table[lo]) / (z_table[hi] - z_table[lo])
    return theta, slope * dz_dp1, slope * dz_ddp, lo


@njit(cache=True, nogil=True, _nrt=False, error_model='numpy')
def thresholds(thr, ps, p0, p_tank, sup, sup_z, sup_th, dr, dr_z, dr_th):
    """Sealing thresholds at supply pressure ``ps`` and node-0 pressure ``p0``
    [MPaG] into ``thr`` (length 7): [theta_d supply, theta_d drain] [deg],
    then d theta_d,s / d ps, d theta_d,s / d p0, d theta_d,d / d p0
    [deg/MPa] (supply side: p1 = ps, dp = ps - p0; drain side: p1 = p0,
    dp = p0 - p_tank); ``thr[5:7]`` keep the table segments between calls
    (start at 0)."""
    th, a, b, seg = _threshold_lin(sup, sup_z, sup_th, ps, ps - p0, int(thr[5]))
    thr[0] = th
    thr[2] = a + b
    thr[3] = -b
    thr[5] = seg
    th, a, b, seg = _threshold_lin(dr, dr_z, dr_th, p0, p0 - p_tank, int(thr[6]))
    thr[1] = th
    thr[4] = a + b
    thr[6] = seg


@njit(cache=True, nogil=True, _nrt=False, error_model='numpy')
def plant_step(y, h, ps0, ps1, needle0, needle1, thr, p_load_set, fr_mode, fr_arg, pp, sup,
               dr, w):
    """Advance the plant states of ``y`` (all but the servo angle) by one
    ROS2 step ``h`` [s] in place. ``ps0``/``ps1`` supply pressure [MPaG] and
    ``needle0``/``needle1`` needle angle [deg] at t_n / t_n + h; ``thr``
    the sealing thresholds at t_n with their slopes (:func:`thresholds`),
    moved linearly to stage 2's pressures (exact within a segment of the
    valve's height table); load set point [MPaG] and friction mode held
    over the step. ``w``: scratch space, a tuple of eleven float arrays
    allocated once per run by the caller: ten of the state's length, then
    the sides' closed-form terms ``tw`` (module doc)."""
    nseg = int(pp[_N_SEG])
    n = y.size
    nc = 2 * nseg + 2
    ith = 2 * nseg + 3
    f1, f2, k1, y2, jl, jd, ju, cp, den, tmp, tw = w
    th_s = thr[0]
    th_d = thr[1]
    plant_f(ps0, y, needle0, th_s, th_d, p_load_set, fr_mode, fr_arg, pp, sup, dr, tw, f1,
            True, jl, jd, ju)
    # W = I - gamma h A on the chain (into jl, jd, ju), factorised
    gh = GAMMA * h
    for j in range(nc):
        jl[j] = -gh * jl[j]
        jd[j] = 1.0 - gh * jd[j]
        ju[j] = -gh * ju[j]
    _factor(jl, jd, ju, cp, den, nc)
    d_pl = 1.0 + gh / pp[_LOAD_TAU]
    _solve(f1, k1, tmp, jl, ju, cp, den, nseg, d_pl)
    k1[ith] = 0.0
    for k in range(n):
        y2[k] = y[k] + h * k1[k]
    dp0 = y2[0] - y[0]
    th_s += thr[2] * (ps1 - ps0) + thr[3] * dp0
    th_d += thr[4] * dp0
    plant_f(ps1, y2, needle1, th_s, th_d, p_load_set, fr_mode, fr_arg, pp, sup, dr, tw, f2,
            False, jl, jd, ju)
    for k in range(n):
        f2[k] -= 2.0 * k1[k]
    _solve(f2, f2, tmp, jl, ju, cp, den, nseg, d_pl)   # k2 in place of its right-hand side
    for k in range(n):
        if k != ith:
            y[k] += h * (1.5 * k1[k] + 0.5 * f2[k])


@njit(cache=True, nogil=True, inline='always')
def servo_step(theta, target, h, pp):
    """Servo angle after a step ``h`` [s] towards ``target`` (held) [deg]:
    the exact solution of the rate-limited first-order lag
    d(theta)/dt = clip((target - theta) / tau, -rate, +rate) (tau =
    ``pp[SERVO_TAU]`` [s], rate = ``pp[SERVO_RATE]`` [deg/s]): at the rate
    limit (a straight line) while |target - theta| > rate x tau,
    exponential from there on. Exact, so the servo adds no integration
    error to the plant's inputs (a ROS2 step of the lag at 1 ms is off by
    ~2e-3 deg after a 20 deg command, at the switch from the rate limit to
    the lag)."""
    return servo_step_decay(theta, target, h, pp, math.exp(-h / pp[_SERVO_TAU]))


@njit(cache=True, nogil=True, inline='always')
def servo_step_decay(theta, target, h, pp, decay):
    """:func:`servo_step` with its lag's decay over the step, ``decay`` =
    exp(-h / tau), given: a loop of equal steps (:func:`.kernel.servo_track`)
    computes it once, the same number every step."""
    tau = pp[_SERVO_TAU]
    e = target - theta
    ae = abs(e)
    lim = pp[_SERVO_RATE] * tau          # |error| [deg] below which the lag is not rate-limited
    if ae <= lim:
        return target - e * decay
    t_lim = (ae - lim) / pp[_SERVO_RATE]  # time [s] spent at the rate limit
    if t_lim >= h:
        return theta + math.copysign(pp[_SERVO_RATE] * h, e)
    return target - math.copysign(lim, e) * math.exp(-(h - t_lim) / tau)
