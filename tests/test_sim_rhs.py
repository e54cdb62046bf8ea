"""The continuous right-hand side of the plant (sim/_rhs.py, used by the
solver benchmark) is the kernel's physics: its fixed-step run matches the
kernel's true trajectory, and LSODA on the same RHS matches the fixed step."""
from __future__ import annotations

import numpy as np
import pytest

from seanv_analysis import load_rig
from seanv_analysis.sim import Plant, simulate_flow_step
from seanv_analysis.sim import _rhs as R

CAM, LOAD, X0 = 5.0, 0.4, 5.0


@pytest.fixture(scope="module")
def plant():
    return Plant.from_rig(load_rig())


def test_fixed_step_rhs_matches_kernel(plant):
    """Same servo quantisation, tight friction regularisation (1e-3 mm/s):
    only Karnopp stiction vs tanh and the 1 kHz threshold refresh differ."""
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


def test_lsoda_matches_fixed_step(plant):
    """Continuous servo (no quantisation), the benchmark's regularisation."""
    case = R.open_loop_step(plant, cam_deg=CAM, load_mpag=LOAD, x0_mm=X0, eps_v_mm_s=1e-2,
                            quantise=False)
    ys = case.run_fixed_step()
    ref, nfev, ok = R.solve_ivp_grid(case, method="LSODA", rtol=1e-7)
    assert ok and nfev > 0
    ix, iv = case.lay["x"], case.lay["v"]
    assert np.abs(ys[:, ix] - ref[:, ix]).max() < 0.005
    assert np.abs(ys[:, iv] - ref[:, iv]).max() * case.pp[R.PP.AREA] < 50.0
    assert np.abs(ys[:, case.lay["p"]] - ref[:, case.lay["p"]]).max() < 0.05


def test_rhs_refuses_cam_effects():
    plant = Plant.from_rig(load_rig(), effects=["backlash:width_deg=1.0"])
    with pytest.raises(ValueError):
        R.open_loop_step(plant, cam_deg=CAM, load_mpag=LOAD)
