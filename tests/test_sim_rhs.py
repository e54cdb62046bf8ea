"""The continuous right-hand side of the plant (tests/sim_rhs.py, also used
by the solver benchmark) is the kernel's physics, and the simulator's integrator
(the ROS2 step of sim/rosenbrock.py, which the kernel calls) is accurate and
2nd order on it: its fixed-step run matches the kernel's true trajectory and
a tight LSODA solution of the same RHS."""
from __future__ import annotations

import math

import numpy as np
import pytest
import sim_rhs as R

from seanv_analysis import load_rig
from seanv_analysis.sim import Plant, simulate_flow_step
from seanv_analysis.sim import rosenbrock as RB
from seanv_analysis.sim.kernel import PP

CAM, LOAD, X0 = 5.0, 0.4, 5.0


@pytest.fixture(scope="module")
def plant():
    return Plant.from_rig(load_rig())


def _case(dt_s: float | None = None, eps_v: float = 1e-2) -> R.OpenLoopStep:
    rig = load_rig(overrides={"sim": {"time_step_s": dt_s}}) if dt_s else load_rig()
    return R.open_loop_step(Plant.from_rig(rig), cam_deg=CAM, load_mpag=LOAD, x0_mm=X0,
                            eps_v_mm_s=eps_v, quantise=False)


@pytest.fixture(scope="module")
def reference():
    """LSODA at rtol 1e-10 on the benchmark's case (step-independent)."""
    case = _case()
    ref, _, ok = R.solve_ivp_grid(case, method="LSODA", rtol=1e-10,
                                  atol=1e-12 * R.atol_scale(case.lay))
    assert ok
    return ref


def _errors(case, ys, ref):
    ix, iv, ip = case.lay["x"], case.lay["v"], case.lay["p"]
    return (float(np.abs(ys[:, ix] - ref[:, ix]).max()),
            float(np.abs(ys[:, iv] - ref[:, iv]).max() * case.pp[PP.AREA]),
            float(np.abs(ys[:, ip] - ref[:, ip]).max()))


def test_rosenbrock_binds_the_shared_indices():
    """The integrator step reads the packed parameters at the indices of the
    one layout (sim/_pp.py) the kernel and the packer use."""
    for name in ("P_TANK", "N_SEG", "R_SEG", "I_SEG", "V_SEG", "BULK", "AREA", "LOAD_AREA",
                 "DEAD_VOL", "MASS", "F_COULOMB", "F_STATIC", "V_STRIBECK", "VISCOUS",
                 "LOAD_TAU", "LEAK_G", "DP_SMOOTH", "SERVO_TAU", "SERVO_RATE"):
        assert getattr(RB, "_" + name) == getattr(PP, name), name


def test_fixed_step_rhs_matches_kernel(plant):
    """Same servo quantisation, tight friction regularisation (1e-3 mm/s):
    only Karnopp stiction vs tanh differ (same ROS2 step, same thresholds)."""
    _, trace = simulate_flow_step(plant.rig, side="supply", cam_deg=CAM, load_mpag=LOAD,
                                  plant=plant, pre_s=0.5, hold_max_s=2.5, post_s=0.0)
    case = R.open_loop_step(plant, cam_deg=CAM, load_mpag=LOAD, x0_mm=X0, eps_v_mm_s=1e-3,
                            quantise=True)
    ys = case.run_fixed_step()
    x, q = ys[:, case.lay["x"]], ys[:, case.lay["v"]] * case.pp[R.PP.AREA]
    assert x.size == trace["x_true_mm"].size
    assert x[-1] - x[0] > 30.0                       # it really moved
    assert np.abs(x - trace["x_true_mm"]).max() < 0.02
    assert np.sqrt(np.mean((q - trace["q_true_mm3_s"]) ** 2)) < 20.0
    assert np.abs(q[-1000:] - trace["q_true_mm3_s"][-1000:]).max() < 5.0


def test_rosenbrock_error_vs_tight_reference(reference):
    """The simulator's step (1 ms) on the benchmark case: measured max errors
    0.0021 mm, 215 mm^3/s (at the piston's breakaway), 0.0026 MPa, and
    1.1 mm^3/s after 1.2 s; bounds with ~1.5x margin. A scheme one order
    lower, or a wrong Jacobian sign, is far outside them (the old
    semi-implicit Euler needed 0.1 ms for 0.0012 mm)."""
    case = _case()
    assert case.pp[PP.DT] == pytest.approx(1e-3)
    ys = case.run_fixed_step()
    ex, eq, ep = _errors(case, ys, reference)
    assert ex < 0.003
    assert eq < 320.0
    assert ep < 0.004
    # away from the breakaway (t > 1.2 s, steady flow) the flow error is small
    iv = case.lay["v"]
    late = case.t_grid > 1.2
    assert np.abs(ys[late, iv] - reference[late, iv]).max() * case.pp[PP.AREA] < 2.0


def test_rosenbrock_converges_at_order_2(reference):
    """Halving the step (1 -> 0.5 -> 0.25 -> 0.125 ms) divides the max
    position error by ~3.3-4 and the pressure error of the sliding phase
    (t > 1.2 s) by ~3.6-4 (observed orders 1.7-2.0; 1st order would give
    ~1). The piston's breakaway (friction knee, explicit Stribeck
    anti-damping) converges less regularly, so the pressure is taken after it."""
    errs = []
    for dt in (1e-3, 5e-4, 2.5e-4, 1.25e-4):
        case = _case(dt)
        ys = case.run_fixed_step()
        late = case.t_grid > 1.2
        ip = case.lay["p"]
        errs.append((_errors(case, ys, reference)[0],
                     float(np.abs(ys[late, ip] - reference[late, ip]).max())))
    errs = np.array(errs)
    order_x = np.log2(errs[:-1, 0] / errs[1:, 0])
    order_p = np.log2(errs[:-1, 1] / errs[1:, 1])
    assert np.all(order_x > 1.6) and np.all(order_x < 2.5), order_x
    assert np.all(order_p > 1.6) and np.all(order_p < 2.5), order_p


def test_lsoda_matches_fixed_step():
    """Continuous servo (no quantisation), the benchmark's regularisation:
    a general solver on the RHS agrees with the fixed step."""
    case = _case()
    ys = case.run_fixed_step()
    ref, nfev, ok = R.solve_ivp_grid(case, method="LSODA", rtol=1e-7)
    assert ok and nfev > 0
    ex, eq, ep = _errors(case, ys, ref)
    assert ex < 0.005 and eq < 350.0 and ep < 0.05


def test_servo_step_exact():
    """The servo step is the exact solution of the rate-limited first-order
    lag: against the closed form, for a small command (never rate-limited,
    exponential) and a large one (at the rate limit, then exponential), in
    steps of 1 ms and 7 ms and in one step."""
    pp = Plant.from_rig(load_rig()).packed_params(
        neutral_deg=-15.0, x_stop_mm=(-math.inf, math.inf))
    tau, rate = pp[PP.SERVO_TAU], pp[PP.SERVO_RATE]
    lim = rate * tau                                   # |error| where the rate limit ends [deg]

    def exact(e0, t):                                  # angle at t, from 0 towards e0
        t_lim = max(abs(e0) - lim, 0.0) / rate
        if t <= t_lim:
            return math.copysign(rate * t, e0)
        e_lim = min(abs(e0), lim)
        return e0 - math.copysign(e_lim, e0) * math.exp(-(t - t_lim) / tau)

    for e0 in (1.0, -40.0, 40.0):
        for h, n in ((1e-3, 300), (7e-3, 43), (0.3, 1)):
            th = 0.0
            for k in range(n):
                th = RB.servo_step(th, e0, h, pp)
                if k in (0, n // 3, n - 1):
                    assert th == pytest.approx(exact(e0, (k + 1) * h), abs=1e-9), (e0, h, k)
    # at the rate limit the angle moves by exactly rate x h
    assert RB.servo_step(0.0, 100.0, 1e-3, pp) == pytest.approx(rate * 1e-3, rel=1e-12)


def test_rhs_refuses_cam_effects():
    plant = Plant.from_rig(load_rig(), effects=["backlash:width_deg=1.0"])
    with pytest.raises(ValueError):
        R.open_loop_step(plant, cam_deg=CAM, load_mpag=LOAD)


@pytest.mark.parametrize("nseg", [1, 2, 3, 4])
@pytest.mark.parametrize("stuck", [False, True])
def test_chain_solve_equals_dense_solve(nseg, stuck):
    """The step's twisted tridiagonal solve (_factor + _solve) of
    W k = r, W = I - gamma h A on the chain [p_0, q_0, ..., p_nseg, v]
    (x and the load pressure by their diagonals), equals a dense solve of
    the same W to rounding: random R-L-C ladders (A's diagonal <= 0,
    off-diagonal pairs of opposite sign), and the stuck piston (couplings
    of v zeroed, as plant_f sets them)."""
    rng = np.random.default_rng(10 * nseg + stuck)
    nc = 2 * nseg + 2
    n = 2 * nseg + 5
    for _ in range(20):
        a_l = np.zeros(nc)
        a_d = -rng.uniform(0.0, 1e3, nc) * (rng.random(nc) < 0.7)
        a_u = np.zeros(nc)
        for j in range(nc - 1):
            c = 10.0 ** rng.uniform(-3, 6)
            ratio = 10.0 ** rng.uniform(-6, 2)
            sgn = rng.choice([-1.0, 1.0])
            a_u[j] = sgn * c                     # A[j, j + 1]
            a_l[j + 1] = -sgn * c * ratio        # A[j + 1, j], opposite sign
        if stuck:
            a_u[nc - 2] = a_l[nc - 1] = a_d[nc - 1] = 0.0
        gh = RB.GAMMA * 1e-3
        wl, wd, wu = -gh * a_l, 1.0 - gh * a_d, -gh * a_u
        dense = np.diag(wd) + np.diag(wl[1:], -1) + np.diag(wu[:-1], 1)
        r = rng.normal(size=n)
        d_pl = 1.0 + gh / 0.05
        cp, den, tmp, o = np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n)
        RB._factor(wl, wd, wu, cp, den, nc)
        RB._solve(r, o, tmp, wl, wu, cp, den, nseg, d_pl)
        iq, iv = nseg + 1, 2 * nseg + 2
        chain = np.r_[np.ravel(np.c_[np.arange(nseg), iq + np.arange(nseg)]), nseg, iv]
        k = np.linalg.solve(dense, r[chain])
        scale = np.abs(k).max()
        assert np.abs(o[chain] - k).max() <= 1e-12 * scale
        assert o[iv - 1] == r[iv - 1] and o[iv + 2] == pytest.approx(r[iv + 2] / d_pl, rel=1e-15)
        if stuck:
            assert o[iv] == pytest.approx(r[iv] / wd[nc - 1], rel=1e-15)
