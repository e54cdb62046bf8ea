"""Continuous-time right-hand side f(t, y) of the simulator's plant (numba),
for checking and benchmarking the simulator's integrator against a general
ODE solver.

A helper of ``tests/test_sim_rhs.py`` and ``benchmarks/bench_sim.py``, not
part of the package: the simulator itself runs
:func:`seanv_analysis.sim.kernel.simulate_kernel`. Both call the same
compiled plant physics (:func:`seanv_analysis.sim.rosenbrock.plant_f`), and
:func:`fixed_step` integrates it with the kernel's own ROS2 step
(:func:`~seanv_analysis.sim.rosenbrock.plant_step`,
:func:`~seanv_analysis.sim.rosenbrock.servo_step`).

Same physics as the kernel, from the same packed parameter vector
(:class:`seanv_analysis.sim.kernel.PP`) and the same compiled valve functions
(:mod:`seanv_analysis.sim.jit`): supply with pump ripple, valve eq. (3)-(5)
per side with the smoothed dp law and the leakage conductance, the tube as
``n_seg`` lumped R-I segments with C at the nodes (last node grows with the
chamber), first-order load regulator, piston with Coulomb + Stribeck +
viscous friction, servo first-order lag with rate limit (:func:`servo_rate`).

Differences from the kernel, all needed to make the plant an ODE a
general-purpose solver can integrate (each is a switch or absent):

- friction: the kernel's Karnopp stiction (a velocity reset, not a force)
  is replaced by the regularised law
  ``F = (Fc + (Fs - Fc) exp(-(v/vs)^2)) tanh(v / eps_v) + b v``;
  it equals the kernel's sliding friction for |v| >> eps_v and holds the
  piston (creep ~ eps_v) while |F_drive| < Fs;
- servo position quantisation is optional (``quantise``: a discontinuous
  staircase in theta, off for the solver comparison);
- :func:`derivs` evaluates the sealing thresholds at every call (the
  kernel, and :func:`fixed_step`, at the start of each step, moved
  linearly in the pressures for the second stage);
- the servo target is one step (dead time already applied): ``theta0``
  before ``t_on``, ``theta1`` after (an open-loop flow step; no controller);
- no cavitation floor, no end stops, no backlash / delay effects
  (:func:`check_supported` refuses plants that need them).

State ``y`` (length ``2 n_seg + 5``): node pressures p_0..p_nseg [MPaG],
segment flows q_0..q_{nseg-1} [mm^3/s], piston x [mm], v [mm/s], servo
angle theta [deg], load pressure [MPaG]. Layout helpers: :func:`layout`.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from seanv_analysis.sim import jit as J  # first: configures the numba cache
from seanv_analysis.sim import rosenbrock as RB
from seanv_analysis.sim.kernel import PP

__all__ = ["AUX_SIZE", "make_aux", "layout", "initial_state", "servo_rate", "derivs", "rhs",
           "fixed_step", "check_supported", "OpenLoopStep", "open_loop_step", "solve_ivp_grid",
           "odeint_grid", "jacobian", "atol_scale"]

# numba reads module globals, not class attributes: the packed-parameter
# indices this module's compiled functions use, bound once
_DT = PP.DT
_P_SUPPLY = PP.P_SUPPLY
_RIPPLE_AMP = PP.RIPPLE_AMP
_RIPPLE_HZ = PP.RIPPLE_HZ
_P_TANK = PP.P_TANK
_N_SEG = PP.N_SEG
_AREA = PP.AREA
_LOAD_AREA = PP.LOAD_AREA
_SERVO_TAU = PP.SERVO_TAU
_SERVO_RATE = PP.SERVO_RATE
_SERVO_RES = PP.SERVO_RES

# auxiliary parameter vector (open-loop case and regularisation)
_A_T_ON, _A_TH0, _A_TH1, _A_PLOAD, _A_EPS, _A_QUANT = range(6)
AUX_SIZE = 6


def make_aux(*, t_on_s: float, theta0_deg: float, theta1_deg: float, p_load_mpag: float,
             eps_v_mm_s: float = 1e-3, quantise: bool = False) -> np.ndarray:
    """Auxiliary vector: servo-target step (``theta0`` -> ``theta1`` at
    ``t_on``), load set point, friction regularisation velocity, quantisation."""
    aux = np.empty(AUX_SIZE)
    aux[_A_T_ON] = t_on_s
    aux[_A_TH0] = theta0_deg
    aux[_A_TH1] = theta1_deg
    aux[_A_PLOAD] = p_load_mpag
    aux[_A_EPS] = eps_v_mm_s
    aux[_A_QUANT] = 1.0 if quantise else 0.0
    return aux


def layout(pp: np.ndarray) -> dict[str, slice | int]:
    """Indices of the state vector: 'p', 'q' (slices), 'x', 'v', 'theta', 'p_load'."""
    nseg = int(pp[_N_SEG])
    return {"p": slice(0, nseg + 1), "q": slice(nseg + 1, 2 * nseg + 1), "x": 2 * nseg + 1,
            "v": 2 * nseg + 2, "theta": 2 * nseg + 3, "p_load": 2 * nseg + 4,
            "n": 2 * nseg + 5}


def initial_state(pp: np.ndarray, aux: np.ndarray, x0_mm: float) -> np.ndarray:
    """At rest as the kernel starts: head pressure balancing the load,
    no flow, servo at ``theta0``."""
    lay = layout(pp)
    y = np.zeros(lay["n"])
    y[lay["p"]] = aux[_A_PLOAD] * pp[_LOAD_AREA] / pp[_AREA]
    y[lay["x"]] = x0_mm
    y[lay["theta"]] = aux[_A_TH0]
    y[lay["p_load"]] = aux[_A_PLOAD]
    return y


def check_supported(pp: np.ndarray) -> None:
    """Refuse parameter vectors using kernel features the RHS leaves out."""
    if pp[PP.BACKLASH] != 0.0 or pp[PP.DELAY] != 0.0:
        raise ValueError("the continuous RHS does not model backlash / extra delay effects")


@njit(cache=True, nogil=True)
def servo_rate(theta, target, pp):
    """Servo angle rate [deg/s]: first-order lag (time constant
    ``pp[SERVO_TAU]``) towards ``target``, limited to +-``pp[SERVO_RATE]``;
    :func:`seanv_analysis.sim.rosenbrock.servo_step` is its exact solution
    over a step."""
    rate = (target - theta) / pp[_SERVO_TAU]
    rmax = pp[_SERVO_RATE]
    if rate > rmax:
        return rmax
    if rate < -rmax:
        return -rmax
    return rate


@njit(cache=True, nogil=True)
def derivs(t, y, dydt, pp, sup, sup_z, sup_th, dr, dr_z, dr_th, term, aux):
    """f(t, y) into ``dydt``: the simulator's compiled plant physics
    (:func:`~seanv_analysis.sim.rosenbrock.plant_f`, friction tanh-regularised) with the
    sealing thresholds at the current pressures, and the servo lag (target
    ``theta0`` before ``t_on``, ``theta1`` from it)."""
    nseg = int(pp[_N_SEG])
    ith = 2 * nseg + 3
    target = aux[_A_TH1] if t >= aux[_A_T_ON] else aux[_A_TH0]
    theta = y[ith]
    dydt[ith] = servo_rate(theta, target, pp)
    needle = theta
    if aux[_A_QUANT] > 0.5:
        res = pp[_SERVO_RES]
        needle = round(theta / res) * res
    ps = pp[_P_SUPPLY] + pp[_RIPPLE_AMP] * math.sin(2.0 * math.pi * pp[_RIPPLE_HZ] * t)
    p0 = y[0]
    th_s = J.threshold_deg(sup, sup_z, sup_th, ps, ps - p0)
    th_d = J.threshold_deg(dr, dr_z, dr_th, p0, p0 - pp[_P_TANK])
    RB.plant_f(ps, y, needle, th_s, th_d, aux[_A_PLOAD], RB.FR_SMOOTH, aux[_A_EPS], pp, sup, dr,
               term, dydt, False, dydt, dydt, dydt)


@njit(cache=True, nogil=True)
def rhs(t, y, pp, sup, sup_z, sup_th, dr, dr_z, dr_th, term, aux):
    """f(t, y) as a new array (the form ``scipy.integrate.solve_ivp`` calls)."""
    dydt = np.empty(y.size)
    derivs(t, y, dydt, pp, sup, sup_z, sup_th, dr, dr_z, dr_th, term, aux)
    return dydt


@njit(cache=True, nogil=True)
def jacobian(t, y, pp, sup, sup_z, sup_th, dr, dr_z, dr_th, term, aux):
    """df/dy by forward differences, compiled (what a user without an
    analytic Jacobian would hand ``odeint``): one f call per state."""
    n = y.size
    f0 = np.empty(n)
    derivs(t, y, f0, pp, sup, sup_z, sup_th, dr, dr_z, dr_th, term, aux)
    jac = np.empty((n, n))
    f1 = np.empty(n)
    yy = y.copy()
    for j in range(n):
        h = 1e-7 * max(1.0, abs(y[j]))
        yy[j] = y[j] + h
        derivs(t, yy, f1, pp, sup, sup_z, sup_th, dr, dr_z, dr_th, term, aux)
        for i in range(n):
            jac[i, j] = (f1[i] - f0[i]) / h
        yy[j] = y[j]
    return jac


@njit(cache=True, nogil=True)
def fixed_step(y0, n_out, every, pp, sup, sup_z, sup_th, dr, dr_z, dr_th, term, aux):
    """The simulator's integrator over the same physics as :func:`derivs`:
    ROS2 steps of ``pp[DT]`` (:func:`~seanv_analysis.sim.rosenbrock.servo_step`,
    the servo lag solved exactly, then
    :func:`~seanv_analysis.sim.rosenbrock.plant_step`, as the kernel
    calls them), friction
    tanh-regularised (``FR_SMOOTH``), sealing thresholds at the start of
    each step moved linearly to stage 2, servo target held over a step (the
    switch at ``t_on`` is on the step grid: from step ``round(t_on / dt)``),
    supply ripple by a rotation recurrence (re-synchronised every 1000
    steps). Time of step k is
    ``k * dt``. Returns the states at every ``every``-th step,
    ``(n_out, len(y))`` (row 0 = y0)."""
    h = pp[_DT]
    n = y0.size
    nseg = int(pp[_N_SEG])
    ith = 2 * nseg + 3
    y = y0.copy()
    out = np.empty((n_out, n))
    w = (np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n),
         np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n), term)
    thr = np.zeros(7)
    quant = aux[_A_QUANT] > 0.5
    res = pp[_SERVO_RES]
    om = 2.0 * math.pi * pp[_RIPPLE_HZ]
    ch, sh = math.cos(om * h), math.sin(om * h)
    amp = pp[_RIPPLE_AMP]
    psup = pp[_P_SUPPLY]
    ptank = pp[_P_TANK]
    pset = aux[_A_PLOAD]
    eps = aux[_A_EPS]
    step_on = round(aux[_A_T_ON] / h)
    sn, cn = 0.0, 1.0
    step = 0
    for i in range(n_out):
        for k in range(n):
            out[i, k] = y[k]
        if i == n_out - 1:
            break
        for _ in range(every):
            t = step * h
            if step % 1000 == 0:
                sn, cn = math.sin(om * t), math.cos(om * t)
            sn1 = sn * ch + cn * sh
            cn1 = cn * ch - sn * sh
            ps0 = psup + amp * sn
            ps1 = psup + amp * sn1
            target = aux[_A_TH1] if step >= step_on else aux[_A_TH0]
            th0 = y[ith]
            th1 = RB.servo_step(th0, target, h, pp)
            if quant:
                n0 = round(th0 / res) * res
                n1 = round(th1 / res) * res
            else:
                n0 = th0
                n1 = th1
            RB.thresholds(thr, ps0, y[0], ptank, sup, sup_z, sup_th, dr, dr_z, dr_th)
            RB.plant_step(y, h, ps0, ps1, n0, n1, thr, pset, RB.FR_SMOOTH, eps, pp, sup, dr, w)
            y[ith] = th1
            sn, cn = sn1, cn1
            step += 1
    return out


class OpenLoopStep:
    """An open-loop flow step ready for :func:`fixed_step` and
    :func:`solve_ivp_grid`: ``pp``, ``valves`` (packed plant valve), ``term``
    (its closed-form terms, packed: ``Plant.term_at``), ``aux``,
    ``y0``, ``t_on`` [s], ``duration`` [s], ``lay`` (:func:`layout`),
    ``t_grid`` (1 kHz output grid)."""

    def __init__(self, **kw):
        self.__dict__.update(kw)

    @property
    def args(self) -> tuple:
        """Trailing arguments of :func:`derivs` / :func:`rhs` / :func:`fixed_step`."""
        return (self.pp, *self.valves, self.term, self.aux)

    def run_fixed_step(self) -> np.ndarray:
        """States on ``t_grid`` from :func:`fixed_step` (the kernel's ROS2 step
        ``pp[DT]``, 1 kHz out)."""
        every = int(self.pp[PP.SUBSTEPS])
        return fixed_step(self.y0, self.t_grid.size, every, *self.args)


def _term(plant, run_index: int) -> np.ndarray:
    """The plant's closed-form terms as the compiled plant physics takes them
    (``Plant.term_at``; approach stays 0 here: the twin does not track the
    needle's direction)."""
    return plant.term_at(run_index)


def open_loop_step(plant, *, cam_deg: float, load_mpag: float, x0_mm: float = 5.0,
                   t_cmd_s: float = 0.5, duration_s: float = 3.0, eps_v_mm_s: float = 1e-2,
                   quantise: bool = False, run_index: int = 0) -> OpenLoopStep:
    """The flow step of :func:`seanv_analysis.sim.simulate_flow_step` (cam from neutral to
    ``cam_deg`` commanded at ``t_cmd_s``, held) as an ODE case: the servo
    target switches when the kernel's servo would see the command (first
    controller tick at or after ``t_cmd_s`` plus the dead time), i.e. at the
    start of the plant step from which the kernel's servo uses the new
    target (``step_on x dt``, computed as :func:`fixed_step` computes its t)."""
    rig = plant.rig
    neutral = float(rig["servo"]["neutral_deg"])
    pp = plant.packed_params(neutral_deg=neutral, x_stop_mm=(-math.inf, math.inf))
    check_supported(pp)
    dt, nsub, every = pp[PP.DT], int(pp[PP.SUBSTEPS]), int(pp[PP.CTRL_EVERY])
    i = 0
    while i * dt * nsub < t_cmd_s:       # the kernel's controller ticks (1 kHz index i)
        i += every
    step_on = (i + int(pp[PP.SERVO_DEAD_TICKS]) * every) * nsub
    t_on = step_on * dt
    aux = make_aux(t_on_s=t_on, theta0_deg=neutral, theta1_deg=cam_deg, p_load_mpag=load_mpag,
                   eps_v_mm_s=eps_v_mm_s, quantise=quantise)
    rate = float(rig["sensors"]["encoder_rate_hz"])
    n = int(round(duration_s * rate)) + 1
    return OpenLoopStep(pp=pp, valves=plant.valve_at(run_index), term=_term(plant, run_index),
                        aux=aux,
                        y0=initial_state(pp, aux, x0_mm), t_on=t_on, duration=(n - 1) / rate,
                        lay=layout(pp), t_grid=np.arange(n) / rate)


def atol_scale(lay: dict) -> np.ndarray:
    """Typical magnitude of each state (for ``atol = rtol x scale``): 1 MPa,
    1000 mm^3/s, 10 mm, 10 mm/s, 1 deg, 1 MPa."""
    s = np.ones(lay["n"])
    s[lay["q"]] = 1000.0
    s[lay["x"]] = 10.0
    s[lay["v"]] = 10.0
    return s


def solve_ivp_grid(case: OpenLoopStep, *, method: str = "LSODA", rtol: float = 1e-6,
                   atol: float | np.ndarray | None = None, restart_every_s: float | None = None):
    """``scipy.integrate.solve_ivp`` on :func:`rhs` over the case, restarted
    at the servo-target switch (a discontinuity in t), sampled on
    ``t_grid``. ``atol`` defaults to ``rtol x atol_scale``.

    ``restart_every_s``: also restart at every multiple of it (e.g. 0.01 s:
    what a 100 Hz controller in the loop, which changes the servo target at
    every tick, would force on the solver).

    Returns (states ``(len(t_grid), n)``, number of RHS calls, success)."""
    from scipy.integrate import solve_ivp

    if atol is None:
        atol = rtol * atol_scale(case.lay)
    args = case.args

    def fun(t, y):
        return rhs(t, y, *args)

    tg = case.t_grid
    cuts = [0.0, case.t_on, case.duration]
    if restart_every_s:
        n = int(round(case.duration / restart_every_s))
        cuts += [k * restart_every_s for k in range(1, n)]
    cuts = np.unique(np.round(cuts, 12))
    y = case.y0
    parts, nfev, ok = [], 0, True
    for a, b in zip(cuts[:-1], cuts[1:]):
        last = b >= cuts[-1]
        sel = tg[(tg >= a) & ((tg <= b) if last else (tg < b))]
        te = sel if last else np.r_[sel, b]
        s = solve_ivp(fun, (a, b), y, method=method, rtol=rtol, atol=atol, t_eval=te)
        nfev += s.nfev
        ok = ok and s.success
        y = s.y[:, -1]
        parts.append(s.y if last else s.y[:, :-1])
    return np.hstack(parts).T, int(nfev), bool(ok)


def odeint_grid(case: OpenLoopStep, *, rtol: float = 1e-6, atol: float | np.ndarray | None = None,
                with_jacobian: bool = False):
    """``scipy.integrate.odeint`` (LSODA, without ``solve_ivp``'s per-call
    Python layer) on :func:`rhs` over the case, restarted at the servo-target
    switch, on ``t_grid``; ``with_jacobian``: the compiled :func:`jacobian`
    as ``Dfun``. Returns (states ``(len(t_grid), n)``, RHS calls, success)."""
    from scipy.integrate import odeint

    if atol is None:
        atol = rtol * atol_scale(case.lay)
    args = case.args
    tg = case.t_grid
    parts, nfev, ok = [], 0, True
    y = case.y0
    cuts = [0.0, case.t_on, case.duration]
    for k, (a, b) in enumerate(zip(cuts[:-1], cuts[1:])):
        last = k == len(cuts) - 2
        sel = tg[(tg >= a) & ((tg <= b) if last else (tg < b))]
        te = np.unique(np.r_[a, sel, b])
        ys, info = odeint(rhs, y, te, args=args, tfirst=True, rtol=rtol, atol=atol,
                          Dfun=jacobian if with_jacobian else None, full_output=True,
                          mxstep=50000)
        nfev += int(info["nfe"][-1]) + (int(info["nje"][-1]) * y.size if with_jacobian else 0)
        ok = ok and info["message"].startswith("Integration successful")
        keep = np.isin(te, sel)
        parts.append(ys[keep])
        y = ys[-1]
    return np.vstack(parts), nfev, bool(ok)

