"""The dynamic search's held-out check and the valve it searches with
(seanv_analysis.identify.dynamic): the closed loop's paired segment test,
the rule that confirms a candidate, and the valve constants that change with
use, refitted on the position-control runs.
"""
from __future__ import annotations

import math
import threading
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from seanv_analysis.discover.assemble import changed_with_use
from seanv_analysis.identify.dynamic import (
    _REFINE_MAXFEV,
    DynamicFinding,
    _confirmed,
    _parabola_min,
    _refine,
    _segment_drop_p,
    valve_at_position_runs,
)


def _validation(run_id, starts, seg_sse, *, per_segment=10):
    """A stand-in re-run: ``per_segment`` samples per segment whose flow
    error squares sum to ``seg_sse[k]`` in segment k."""
    t = np.arange(len(starts) * per_segment, dtype=float) * 0.1
    err = np.repeat(np.sqrt(np.asarray(seg_sse, float) / per_segment), per_segment)
    q = np.full(t.size, 100.0)
    return SimpleNamespace(run_id=run_id, segment_starts_s=np.asarray(starts, float),
                           overlay=pd.DataFrame({"t_s": t, "q_mm3_s": q, "q_seg_mm3_s": q - err}))


STARTS = np.arange(8) * 1.0      # 8 segments of 10 samples at 0.1 s


def test_segment_test_is_exact_for_a_drop_in_every_segment():
    """Every one of 8 segments better after: of the 2^8 sign flips only the
    observed one reaches the observed sum, p = 1/256."""
    before = [_validation("r1", STARTS, [400.0, 900, 100, 2500, 300, 700, 1600, 200])]
    after = [_validation("r1", STARTS, [100.0, 300, 50, 900, 100, 200, 400, 100])]
    assert _segment_drop_p(before, after) == pytest.approx(1 / 256)


def test_segment_test_sees_no_drop_where_the_segments_disagree():
    """Half the segments better, half worse by the same amounts: p >= 0.5."""
    sse = [400.0, 900, 100, 2500, 300, 700, 1600, 200]
    worse = [s * 2 for s in sse]
    before = [_validation("r1", STARTS, sse[:4] + worse[4:])]
    after = [_validation("r1", STARTS, worse[:4] + sse[4:])]
    assert _segment_drop_p(before, after) >= 0.5


def test_segment_test_on_many_segments_samples_the_flips():
    """400 segments (an hour of position control): 2^16 random flips, drawn
    in batches; a drop in 300 of them is significant, none is not."""
    rng = np.random.default_rng(1)
    starts = np.arange(400) * 1.0
    sse = rng.uniform(100.0, 1000.0, 400)
    better = np.where(np.arange(400) < 300, 0.5, 1.2) * sse
    before = [_validation("r1", starts, sse)]
    assert _segment_drop_p(before, [_validation("r1", starts, better)]) < 1e-3
    same = sse * rng.choice([0.8, 1.25], 400)
    assert _segment_drop_p(before, [_validation("r1", starts, same)]) > 0.01


def test_segment_test_needs_matched_runs_and_enough_segments():
    """Runs are paired by id and segment starts; fewer than 6 segments: NaN."""
    sse = [400.0, 900, 100, 2500, 300, 700, 1600, 200]
    before = [_validation("r1", STARTS, sse)]
    assert math.isnan(_segment_drop_p(before, [_validation("r2", STARTS, sse)]))
    assert math.isnan(_segment_drop_p(before, [_validation("r1", STARTS + 0.05, sse)]))
    few = [_validation("r1", STARTS[:5], sse[:5])]
    assert math.isnan(_segment_drop_p(few, [_validation("r1", STARTS[:5], sse[:5])]))


def _finding(replay, closed, p_replay, p_segments):
    f = DynamicFinding("backlash", "width_deg", 1.2, (1.0, 1.5), 1e-20, 0.3)
    f.replay_before, f.replay_after = {"rmse_flow_mm3_s": 100.0}, {"rmse_flow_mm3_s": 100 * (1 - replay)}
    f.heldout_before = {"rmse_flow_mm3_s": 150.0}     # the identified twin: not compared
    f.heldout_base_twin = {"rmse_flow_mm3_s": 100.0}  # its line refitted alone
    f.heldout_after = {"rmse_flow_mm3_s": 100 * (1 - closed)}
    f.heldout_p_value, f.heldout_segments_p_value = p_replay, p_segments
    return f


@pytest.mark.parametrize("replay, closed, p_replay, p_segments, named", [
    (0.10, 0.42, 0.09, 0.008, True),     # field-drift-backlash with --identify
    (0.25, 0.42, 0.02, 0.02, True),      # both
    (0.25, 0.05, 0.01, 0.30, True),      # the replay alone
    (0.25, 0.42, 0.03, 0.03, False),     # each above 5 % / 2
    (-0.02, 0.42, 0.90, 0.001, False),   # the replay got worse
    (0.30, -0.05, 0.001, 0.80, False),   # the closed loop got worse
    (0.08, 0.06, 1e-4, 1e-4, False),     # significant, but below the 10 % floor
    (0.25, 0.42, 0.01, math.nan, True),  # no segments: the replay decides
])
def test_a_candidate_is_confirmed_by_either_heldout_error(replay, closed, p_replay, p_segments,
                                                          named):
    """Named when neither held-out error rises and one of them drops by >= 10 %
    with its one-sided p below 2.5 % (5 % over the two); the closed loop's
    drop is from the base twin with its line refitted alone, like the
    replay's."""
    assert _confirmed(_finding(replay, closed, p_replay, p_segments), 0.10, 0.025) is named


def test_effects_of_use_free_their_constant_at_the_position_runs():
    """A drift moves its side's C, a threshold shift its z0; other effects nothing."""
    effects = [SimpleNamespace(name="drift", side="supply"),
               SimpleNamespace(name="pressure_law", side="supply"),
               SimpleNamespace(name="threshold_shift", side="drain"),
               SimpleNamespace(name="drift", side="supply")]
    assert changed_with_use(SimpleNamespace(effects=effects)) == [("supply", "c_flow"),
                                                                  ("drain", "z0_mm")]
    assert changed_with_use(None) == []


@pytest.fixture(scope="module")
def position_target(rig):
    """One position-control run of our simulator (seed 3), ready to replay."""
    from seanv_analysis.identify.closedloop import replay_targets
    from seanv_analysis.sim.scenarios import iter_scenario_runs

    run = next(iter(iter_scenario_runs("paper-position", seed=3, rig=rig)))
    return replay_targets([run], rig)


def test_the_position_runs_set_a_drifted_flow_coefficient(rig, position_target):
    """Given a supply C 8 % low (a drift's average over the flow steps), the
    position run's replay gives back the C it was simulated with (measured:
    0.9996 of it; from the true C, 1.0008)."""
    from seanv_analysis.models import ValveModel

    valve = ValveModel.from_rig(rig)
    c = valve.supply.c_flow
    out, info = valve_at_position_runs(position_target, valve.with_side("supply", c_flow=0.92 * c),
                                       rig, [("supply", "c_flow")])
    assert out.supply.c_flow == pytest.approx(c, rel=0.01)
    assert out.drain == valve.drain
    assert info == [{"side": "supply", "key": "c_flow",
                     "C_flow_steps_mm3_s_deg2_sqrtMPa": pytest.approx(0.92 * c),
                     "C_position_runs_mm3_s_deg2_sqrtMPa": out.supply.c_flow}]
    f = DynamicFinding("delay", "delay_s", 0.0, (0.0, 0.0), 1.0, 0.0, valve_refit=info)
    assert f.valve_refit_sentence() == (f"supply C {out.supply.c_flow:.4g} at the position runs "
                                        f"(flow steps {0.92 * c:.4g}: it changes with use)")


def test_the_position_runs_set_a_shifted_threshold(rig, position_target):
    """Given a supply z0 0.01 mm off (~2 deg of theta_d), the replay gives
    back the z0 the run was simulated with."""
    from seanv_analysis.models import ValveModel

    valve = ValveModel.from_rig(rig)
    z0 = valve.supply.z0_mm
    out, _ = valve_at_position_runs(position_target, valve.with_side("supply", z0_mm=z0 + 0.01),
                                    rig, [("supply", "z0_mm")])
    assert out.supply.z0_mm == pytest.approx(z0, abs=0.002)


def test_only_constants_that_change_with_use_are_refitted(rig, position_target):
    from seanv_analysis.models import ValveModel

    with pytest.raises(ValueError, match="needle_y_c_mm"):
        valve_at_position_runs(position_target, ValveModel.from_rig(rig), rig,
                               [("supply", "needle_y_c_mm")])


def test_the_closed_loop_check_takes_the_position_runs_constant_not_the_trend(rig):
    """discover's closed-loop check runs the position-control runs with the
    C the dynamic search set from them and without the drift that C
    replaces (the drift extrapolated to those runs is what the refit
    replaces); the other side's drift and the other effects stay."""
    from seanv_analysis.discover.result import at_position_runs
    from seanv_analysis.models import ValveModel

    model = ValveModel.from_rig(rig)
    specs = ["drift:side=drain,step=0.05,every=3,offset=0",
             "drift:side=supply,step=0.02,every=3,offset=0", "backlash:width_deg=1.2"]
    refit = [{"side": "drain", "key": "c_flow", "C_flow_steps_mm3_s_deg2_sqrtMPa": -18.55,
              "C_position_runs_mm3_s_deg2_sqrtMPa": -22.44}]
    out, kept = at_position_runs(model, specs, refit)
    assert out.drain.c_flow == -22.44 and out.supply == model.supply
    assert kept == specs[1:]
    assert at_position_runs(model, specs, []) == (model, specs)


def test_the_joint_refinement_finds_a_tilted_valley_in_its_budget():
    """The grid's best (value, log B) refined on an error valley along a
    diagonal (a softer line mimics a delay), its floor at (0.083 s, log 290):
    COBYQA lands within 5 % of the floor's value in at most
    _REFINE_MAXFEV evaluations and never returns worse than its start."""
    calls = []

    def sse(z):
        v, lb = z
        calls.append(z)
        u, w = (v - 0.083) / 0.02, (lb - math.log(290.0)) / 0.1
        return 1e6 * (1.0 + (u - w) ** 2 + 0.2 * (u + w) ** 2)

    start = (0.1, math.log(300.0))
    v, lb, c = _refine(sse, start, (0.06, 0.15), (math.log(100.0), math.log(900.0)))
    assert len(calls) <= _REFINE_MAXFEV + 1          # + the start
    assert c <= sse(start) and v == pytest.approx(0.083, rel=0.05)
    assert math.exp(lb) == pytest.approx(290.0, rel=0.05)


def test_the_profile_refit_takes_the_parabolas_vertex():
    """Three evaluations about x and one at the parabola's vertex: an exact
    parabola's minimum, and no fourth evaluation where it opens downwards."""
    stop = threading.Event()
    calls = []

    def f(x):
        calls.append(x)
        return 5.0 + 3.0 * (x - 0.13) ** 2

    assert _parabola_min(f, 0.0, 0.2, 0.5, stop) == pytest.approx(5.0)
    assert len(calls) == 4 and calls[-1] == pytest.approx(0.13)
    calls.clear()
    assert _parabola_min(lambda x: calls.append(x) or -x * x, 0.0, 0.2, 0.5, stop) == pytest.approx(-0.04)
    assert len(calls) == 3
