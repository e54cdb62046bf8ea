"""The ``term`` effect in the simulator: a closed-form correction of a valve
side, evaluated at every plant step by the compiled stack machine.

What must hold: a flow step with a term settles at the flow the formula
predicts from the clean valve model at the measured pressures (each mode,
and the variables run, load, approach reach the kernel); a position-control
run with a term runs; the compiled machine gives what the Python one gives;
a plant without a term is the plant it was (the packed terms are empty and
the scenario files do not change); bad specs are ConfigErrors naming the
key, and the command line turns them into one line and exit code 2.
"""
from __future__ import annotations

import json
import math
import re

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner
from hypothesis import given, settings
from test_expr import ENVS, TREES, reference, render

from seanv_analysis import load_rig
from seanv_analysis.cli import cli
from seanv_analysis.discover.static import EffectSpec, FlowData, predict_static
from seanv_analysis.errors import ConfigError
from seanv_analysis.models import ValveModel
from seanv_analysis.models import expr as E
from seanv_analysis.signals.derive import summarize_run
from seanv_analysis.sim import Plant, simulate_flow_step, simulate_position_control
from seanv_analysis.sim import jit as J
from seanv_analysis.sim.control import FlowModelController
from seanv_analysis.sim.scenarios import paper_position_profile

RIG = load_rig()
MODEL = ValveModel.from_rig(RIG)


def _row(side, cam, load=0.4, **kw):
    run, _ = simulate_flow_step(RIG, side=side, cam_deg=cam, load_mpag=load, **kw)
    return summarize_run(run)


def _model_flow(side, cam, row):
    """The clean valve's flow (eq. 3-5) at the run's measured pressures."""
    return float(MODEL.side(side).flow(cam, row["p1_mpa"], row["dp_mpa"]))


# the clean plant's settled flow matches eq. (5) within 1 % (test_sim), so
# every check below allows that much
CASES = [("supply", 0.0, 0.3), ("supply", 5.0, 0.45), ("drain", -35.0, 0.3),
         ("drain", -35.0, 0.45)]


@pytest.mark.parametrize("side, cam, load", CASES)
def test_mul_term_scales_the_steady_flow(side, cam, load):
    row = _row(side, cam, load, effects=[f"term:side={side},mode=mul,expr=-0.2*tanh(dp/0.5)"])
    want = _model_flow(side, cam, row) * (1.0 - 0.2 * math.tanh(row["dp_mpa"] / 0.5))
    assert row["q_mm3_s"] == pytest.approx(want, rel=0.01)
    assert abs(row["q_mm3_s"]) > 1000.0


@pytest.mark.parametrize("side, cam, load", CASES)
def test_add_term_adds_to_the_steady_flow(side, cam, load):
    sign = 1.0 if side == "supply" else -1.0       # eq. (5)'s signs: drain flow < 0
    expr = f"{sign * 400:g}*sqrt(dp)"
    row = _row(side, cam, load, effects=[f"term:side={side},mode=add,expr={expr}"])
    want = _model_flow(side, cam, row) + sign * 400.0 * math.sqrt(row["dp_mpa"])
    assert row["q_mm3_s"] == pytest.approx(want, rel=0.01)


@pytest.mark.parametrize("side, cam, load", CASES)
def test_threshold_term_moves_the_sealing_threshold(side, cam, load):
    row = _row(side, cam, load, effects=[f"term:side={side},mode=threshold,expr=0.8 + 0.5*dp"])
    # theta_d + f opens the needle as the cam angle theta - f does (either side)
    shift = 0.8 + 0.5 * row["dp_mpa"]
    want = float(MODEL.side(side).flow(cam - shift, row["p1_mpa"], row["dp_mpa"]))
    assert row["q_mm3_s"] == pytest.approx(want, rel=0.01)
    assert abs(want / _model_flow(side, cam, row) - 1.0) > 0.05


def test_a_term_acts_on_its_side_only():
    row = _row("drain", -35.0, effects=["term:side=supply,mode=mul,expr=-0.5"])
    assert row["q_mm3_s"] == pytest.approx(_model_flow("drain", -35.0, row), rel=0.01)


def test_an_add_term_acts_through_the_sealed_valve_too():
    """A supply 'add' term (a leak past the needle, open or sealed) feeds
    the head during drain runs as well: the simulator's drain flow is eq. (5)
    plus the term at the sealed supply valve's pressure difference (the
    summary's ``dp_sealed_mpa``), and discover's static model predicts the
    same from the summary row."""
    row = _row("drain", -35.0, 0.4, effects=["term:side=supply,mode=add,expr=200*dp"])
    # the supply's pressure difference with the head at the drain run's p1
    assert 1.0 < row["dp_sealed_mpa"] < 3.3 - row["p1_mpa"] + 0.1
    want = _model_flow("drain", -35.0, row) + 200.0 * row["dp_sealed_mpa"]
    assert row["q_mm3_s"] == pytest.approx(want, rel=0.01)
    assert abs(200.0 * row["dp_sealed_mpa"]) > 0.1 * abs(row["q_mm3_s"])
    data = FlowData.from_summary(pd.DataFrame([{**row, "run_index": 0}]))
    term = EffectSpec("term", "supply", (), (), (), (), {"mode": "add", "expr": "200*dp"})
    assert predict_static(MODEL, data, {"t": (term, np.array([]))})[0] == \
        pytest.approx(want, rel=0.01)


def test_threshold_by_approach_direction():
    """The kernel tracks the direction the needle last moved: a threshold
    shifted by 0.4 approach opens the supply needle less when the cam
    arrives moving up than when it comes down from an overshoot."""
    eff = ["term:side=supply,mode=threshold,expr=0.4*approach"]
    flows = {}
    for approach in (+1, -1):
        row = _row("supply", 0.0, effects=eff, approach=approach)
        assert row["cam_approach"] == approach
        want = float(MODEL.supply.flow(0.0 - 0.4 * approach, row["p1_mpa"], row["dp_mpa"]))
        assert row["q_mm3_s"] == pytest.approx(want, rel=0.01)
        flows[approach] = row["q_mm3_s"]
    assert flows[-1] > 1.1 * flows[+1]


def test_run_and_load_reach_the_kernel():
    eff = ["term:side=drain,mode=mul,expr=0.01*run + 0.5*(load - 0.4)"]
    for run_index, load in ((0, 0.4), (6, 0.4), (0, 0.3), (6, 0.5)):
        row = _row("drain", -35.0, load, effects=eff, run_index=run_index)
        ratio = row["q_mm3_s"] / _model_flow("drain", -35.0, row)
        assert ratio == pytest.approx(1.0 + 0.01 * run_index + 0.5 * (load - 0.4), rel=0.01)


def test_position_control_with_a_term_runs_and_differs():
    ref, load, duration = paper_position_profile()
    ctrl = FlowModelController.from_rig(RIG)
    runs = {}
    for name, eff in (("clean", []),
                      ("term", ["term:side=supply,mode=mul,expr=-0.3*tanh(dp/0.5)",
                                "term:side=drain,mode=threshold,expr=0.3*approach"])):
        run, trace = simulate_position_control(RIG, controller=ctrl, x_ref=ref, load=load,
                                               duration_s=20.0, effects=eff)
        assert np.all(np.isfinite(trace["q_true_mm3_s"]))
        runs[name] = trace["x_true_mm"]
    # the loop still tracks (within a few mm at the end of the first step),
    # but not along the same path
    assert not np.array_equal(runs["clean"], runs["term"])
    assert abs(runs["term"][-1] - runs["clean"][-1]) < 3.0


def test_a_term_that_is_not_finite_is_a_config_error():
    with pytest.raises(ConfigError, match="term: the plant's state became non-finite"):
        simulate_flow_step(RIG, side="supply", cam_deg=5.0, load_mpag=0.3, hold_max_s=0.3,
                           effects=["term:side=supply,mode=mul,expr=log(dp - 100)"])


@pytest.mark.parametrize("spec, match", [
    ("term:side=middle", "term: side"),
    ("term:mode=times", "term: mode"),
    ("term:expr=dp.real", "term: expr .*attribute access"),
    ("term:expr=sin(dp)", "term: expr .*unknown function 'sin'"),
    ("term:side=supply,expr=dp**99", "term: expr .*exponent 99 is beyond"),
])
def test_bad_term_specs_are_config_errors_naming_the_key(spec, match):
    with pytest.raises(ConfigError, match=match):
        Plant.from_rig(RIG, effects=[spec])
    with pytest.raises(ConfigError, match=match):
        simulate_flow_step(RIG, side="supply", cam_deg=0.0, load_mpag=0.3, effects=[spec])


# ---------------------------------------------------------------------------
# the compiled machine and the packing
# ---------------------------------------------------------------------------

@settings(max_examples=150, deadline=None)
@given(tree=TREES, env=ENVS)
def test_compiled_machine_agrees_with_the_reference(tree, env):
    """``sim.jit.run_program`` (the kernel's) on the packed memory gives
    what the reference and the Python machine give, for any expression,
    with one compiled signature."""
    program = E.compile_expr(render(tree))
    with np.errstate(all="ignore"):
        want = np.broadcast_to(reference(tree, env), env["dp"].shape)
    for k in range(want.size):
        xs = [float(env[v][k]) for v in E.VARIABLES]
        mem, at = E.program_memory(program, xs)
        got = J.run_program(mem, *at)
        np.testing.assert_allclose(got, want[k], rtol=1e-9, atol=1e-12, equal_nan=True)
    assert len(J.run_program.signatures) == 1


def test_one_compiled_kernel_for_every_expression(monkeypatch):
    """Different expressions, modes and no term at all run the same compiled
    kernel (the program is data): no compilation per expression. (numba's
    JIT kernel, which could compile more; the ahead-of-time one has one
    signature by construction.)"""
    from seanv_analysis.sim import compiled
    from seanv_analysis.sim.kernel import simulate_kernel

    monkeypatch.setitem(compiled._loaded, "simulate_kernel", simulate_kernel)
    for eff in ([], ["term:side=supply,mode=mul,expr=0.1*tanh(dp)"],
                ["term:side=drain,mode=threshold,expr=0.2*approach + 0*run",
                 "term:side=supply,mode=add,expr=clip(q, 0, 50)/10"]):
        simulate_flow_step(RIG, side="supply", cam_deg=0.0, load_mpag=0.3, hold_max_s=0.2,
                           effects=eff)
    assert len(simulate_kernel.signatures) == 1
    assert len(J.run_program.signatures) <= 1    # (0: only inside the cached kernel)


def test_packed_terms_layout():
    s = E.compile_expr("-0.2*tanh(dp/0.5)")
    d = E.compile_expr("clip(q, -1, 1)*approach + run")
    tw = J.pack_terms(("mul", s), ("threshold", d), run_index=7)
    assert tw[J.TW_SUPPLY + J.TW_MODE] == J.TERM_MUL and tw[J.TW_DRAIN + J.TW_MODE] == J.TERM_THRESHOLD
    v = int(tw[J.TW_VARS])
    assert tw[v + J.TV_RUN] == 7.0 and int(tw[J.TW_STACK]) == v + J.TV_SIZE
    assert tw.size == int(tw[J.TW_STACK]) + max(s.stack_size, d.stack_size)
    tw[v + J.TV_DP], tw[v + J.TV_Q], tw[v + J.TV_APPROACH] = 0.4, 3.0, -1.0
    for side, prog in ((J.TW_SUPPLY, s), (J.TW_DRAIN, d)):
        got = J.run_program(tw, int(tw[side + J.TW_CODE]), int(tw[side + J.TW_N]),
                            int(tw[side + J.TW_CONST]), v, int(tw[J.TW_STACK]))
        want = E.evaluate_scalar(prog, {"dp": 0.4, "q": 3.0, "approach": -1.0, "run": 7.0})
        assert got == pytest.approx(want, rel=1e-14)
    # no term: both modes 0, the variables and a stack still there
    empty = J.pack_terms(None, None, run_index=3)
    assert empty[J.TW_SUPPLY] == empty[J.TW_DRAIN] == J.TERM_NONE
    assert empty.size == J.TW_HEADER + J.TV_SIZE + 1


def test_plant_without_term_packs_no_term_and_one_with_packs_it():
    plain = Plant.from_rig(RIG, effects=["drift:side=drain"])
    assert not plain.has_terms
    tw = plain.term_at(4)
    assert tw[J.TW_SUPPLY] == tw[J.TW_DRAIN] == 0.0
    assert tw[int(tw[J.TW_VARS]) + J.TV_RUN] == 4.0
    plant = Plant.from_rig(RIG, effects=["term:side=drain,mode=add,expr=-5*dp"])
    assert plant.has_terms
    tw = plant.term_at(2)
    assert tw[J.TW_SUPPLY] == 0.0 and tw[J.TW_DRAIN] == J.TERM_ADD
    assert plant.valve_terms("drain", 2).term_program == E.compile_expr("-5*dp")
    assert plant.valve_terms("supply", 2).term_program is None
    truth = json.dumps(plant.truth())
    assert '"expr": "-5*dp"' in truth


# ---------------------------------------------------------------------------
# the command line
# ---------------------------------------------------------------------------

def test_simulate_cli_with_a_term(tmp_path):
    spec = "term:side=supply,mode=mul,expr=-0.1*clip(dp, 0, 2)"
    res = CliRunner().invoke(cli, ["simulate", "paper-position-model", "--out",
                                   str(tmp_path / "d"), "--effect", spec, "--write-truth",
                                   "--quiet"])
    assert res.exit_code == 0, res.output
    assert "with term:side=supply,mode=mul,expr=-0.1*clip(dp, 0, 2)" in res.output
    truth = json.loads((tmp_path / "d" / "_truth.json").read_text())
    assert truth["effects"] == [{"name": "term", "side": "supply", "mode": "mul",
                                 "expr": "-0.1*clip(dp, 0, 2)"}]


@pytest.mark.parametrize("spec, match", [
    ("term:side=supply,expr=__import__('os').system('true')", "attribute access is not allowed"),
    ("term:side=supply,expr=dp**1000", "exponent 1000 is beyond"),
    ("term:side=supply,mode=pow,expr=dp", "term: mode: expected one of mul, add, threshold"),
    ("term:side=supply,expr=" + "dp+" * 200 + "1", "longer than 400 characters"),
])
def test_simulate_cli_bad_term_is_one_line_exit_2(tmp_path, spec, match):
    res = CliRunner().invoke(cli, ["simulate", "paper-position-model", "--out",
                                   str(tmp_path / "e"), "--effect", spec])
    assert res.exit_code == 2
    out = res.output.strip()
    assert "\n" not in out and "Traceback" not in out
    assert out.startswith("error:") and re.search(match, out), out
    assert not (tmp_path / "e").exists() or not any((tmp_path / "e").rglob("run.json"))


def test_simulate_help_documents_the_term_spec():
    res = CliRunner().invoke(cli, ["simulate", "--help"])
    text = " ".join(res.output.split())
    assert "term:side=supply,mode=mul,expr=" in text
    assert "commas" in text and "dtheta" in text
