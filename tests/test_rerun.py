"""Closed-loop re-run per segment from the logged state (analysis.rerun)."""
from __future__ import annotations

import numpy as np
import pytest

from seanv_analysis.analysis.rerun import _holding, segment_starts
from seanv_analysis.analysis.validate import validate_run
from seanv_analysis.config import load_rig
from seanv_analysis.models import ValveModel
from seanv_analysis.sim.control import CamController


def _rest_then_move(t, moving):
    """Flow 0 except over the ``moving`` spans [s], where it is 3000 mm^3/s."""
    q = np.zeros(t.size)
    for a, b in moving:
        q[(t >= a) & (t < b)] = 3000.0
    return q


def test_segments_start_at_rest_before_each_change():
    t = np.arange(0.0, 20.0, 0.001)
    q = _rest_then_move(t, [(5.0, 6.0), (10.0, 11.0)])
    cam = np.full(t.size, -15.0)
    s = segment_starts(t, q, cam, [5.0, 10.0, 15.0], lead_s=0.1, rest_mm3_s=50.0)
    np.testing.assert_allclose(s, [0.0, 4.9, 9.9, 14.9])


def test_a_moving_rig_starts_no_segment_until_it_rests():
    """Flow from 5 to 9.5 s: the change at 10 s gets its start in the rest
    before it (9.9 s); one at 8 s, moving over the 2 s searched before it,
    gets none."""
    t = np.arange(0.0, 20.0, 0.001)
    q = _rest_then_move(t, [(5.0, 9.5)])
    cam = np.full(t.size, -15.0)
    s = segment_starts(t, q, cam, [8.0, 10.0], lead_s=0.1, rest_mm3_s=50.0)
    np.testing.assert_allclose(s, [0.0, 9.9])
    # a servo still moving is no rest either: the start moves back to where it was still
    cam[(t > 9.75) & (t < 9.95)] = np.linspace(-15, -10, int(((t > 9.75) & (t < 9.95)).sum()))
    s = segment_starts(t, q, cam, [10.0], lead_s=0.1, rest_mm3_s=50.0)
    assert s[-1] == pytest.approx(9.75, abs=0.051) and s[-1] <= 9.75 + 1e-9


def test_controller_hold_follows_its_rule():
    c = CamController.from_rig(load_rig())
    band = c.convergence_band_mm
    t = np.arange(0.0, 10.0, 0.01)
    ref_t, ref_v = np.array([0.0, 2.0]), np.array([0.0, 30.0])
    x = np.where(t < 2.0, 0.0, np.minimum(30.0 + band / 2, (t - 2.0) * 20.0))
    assert _holding(c, t, x, ref_t, ref_v, 5.0)            # converged within the band
    assert not _holding(c, t, np.where(t < 2, 0.0, 25.0), ref_t, ref_v, 5.0)
    assert _holding(c, t, np.zeros(t.size), ref_t, ref_v, 1.0)   # on its first reference


@pytest.mark.parametrize("flow_model", [True, False])
def test_segments_of_the_true_plant_fit_as_the_free_run(flow_model, tmp_path):
    """Our simulator's run re-run on the same plant: each segment started
    from the logged state reproduces the run nearly as well as the free
    re-run (what the state the logs do not give costs: < 4 % of flow fit)."""
    from seanv_analysis.io import read_run
    from seanv_analysis.sim import simulate_scenario

    simulate_scenario("paper-position", tmp_path, seed=5)
    name = "position-with-flow-model" if flow_model else "position-without-flow-model"
    rig = load_rig()
    v = validate_run(read_run(tmp_path / name), ValveModel.from_rig(rig), rig=rig)
    row = v.row
    assert row["n_segments"] >= 5
    assert row["fit_flow_pct"] > 98.0
    assert row["fit_flow_segments_pct"] > 95.0 and row["fit_position_segments_pct"] > 99.0
    assert row["fit_flow_segments_pct"] > row["fit_flow_pct"] - 4.0
