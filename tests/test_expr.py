"""The safe expression grammar of closed-form terms (``models/expr.py``).

What must hold: random expressions of the grammar evaluate, vectorised and
by the scalar stack machine, to what an independent tree-walking reference
gives (IEEE semantics: inf/NaN where numpy gives them); the canonical text
compiles back to an equal program; anything outside the whitelist (names,
attributes, subscripts, keywords, lambda, strings, huge exponents or
lengths, ...) is a ValueError with a one-line message naming it, and no
text is ever executed.
"""
from __future__ import annotations

import ast
import inspect
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from seanv_analysis.models import expr as E

VARS = E.VARIABLES
UNARY = ("tanh", "exp", "log", "sqrt", "abs", "sign")
EXPONENTS = (0.0, 0.5, 1.0, 1.5, 2.0, 3.0, -1.0, -0.5, -2.0)

# ---------------------------------------------------------------------------
# random expression trees, their text, and a reference evaluator
# ---------------------------------------------------------------------------

_leaves = st.one_of(
    st.sampled_from(VARS).map(lambda v: ("var", v)),
    st.one_of(st.sampled_from([0.0, 0.5, 1.0, 2.0, 10.0, 1e-3]),
              st.floats(0.01, 50.0)).map(lambda c: ("const", c)))


def _extend(children):
    return st.one_of(
        st.tuples(st.just("neg"), children),
        st.tuples(st.just("bin"), st.sampled_from("+-*/"), children, children),
        st.tuples(st.just("pow"), children, st.sampled_from(EXPONENTS)),
        st.tuples(st.just("call"), st.sampled_from(UNARY), children),
        st.tuples(st.just("call2"), st.sampled_from(("min", "max")), children, children),
        st.tuples(st.just("clip"), children, children, children))


TREES = st.recursive(_leaves, _extend, max_leaves=10)


def render(t) -> str:
    """The tree as text, every operation in parentheses."""
    kind = t[0]
    if kind == "var":
        return t[1]
    if kind == "const":
        return repr(t[1])
    if kind == "neg":
        return f"(-{render(t[1])})"
    if kind == "bin":
        return f"({render(t[2])} {t[1]} {render(t[3])})"
    if kind == "pow":
        return f"({render(t[1])})**({t[2]!r})"
    if kind == "call":
        return f"{t[1]}({render(t[2])})"
    if kind == "call2":
        return f"{t[1]}({render(t[2])}, {render(t[3])})"
    return f"clip({render(t[1])}, {render(t[2])}, {render(t[3])})"


def reference(t, env):
    """Independent evaluation of a tree on numpy arrays (numpy's IEEE
    semantics; clip as min(max(x, lo), hi))."""
    kind = t[0]
    if kind == "var":
        return np.asarray(env[t[1]], dtype=float)
    if kind == "const":
        return np.float64(t[1])
    if kind == "neg":
        return -reference(t[1], env)
    if kind == "bin":
        a, b = reference(t[2], env), reference(t[3], env)
        return {"+": np.add, "-": np.subtract, "*": np.multiply, "/": np.divide}[t[1]](a, b)
    if kind == "pow":
        x = reference(t[1], env)
        r = np.power(x, t[2])
        # a negative base (-inf too) to a non-integer power: NaN
        return np.where(x < 0, np.nan, r) if t[2] != int(t[2]) else r
    if kind == "call":
        return getattr(np, {"abs": "abs"}.get(t[1], t[1]))(reference(t[2], env))
    if kind == "call2":
        f = np.minimum if t[1] == "min" else np.maximum
        return f(reference(t[2], env), reference(t[3], env))
    x, lo, hi = (reference(a, env) for a in t[1:])
    return np.minimum(np.maximum(x, lo), hi)


def _env(values: list[float]) -> dict[str, np.ndarray]:
    n = len(values) // len(VARS)
    a = np.array(values[:n * len(VARS)]).reshape(len(VARS), n)
    return {v: a[i] for i, v in enumerate(VARS)}


ENVS = st.lists(st.floats(-5.0, 5.0), min_size=len(VARS) * 3, max_size=len(VARS) * 6).map(_env)


def assert_same(actual, desired):
    np.testing.assert_allclose(np.asarray(actual, float), np.asarray(desired, float),
                               rtol=1e-9, atol=1e-12, equal_nan=True)


# ---------------------------------------------------------------------------
# evaluation
# ---------------------------------------------------------------------------

@settings(max_examples=300, deadline=None)
@given(tree=TREES, env=ENVS)
def test_numpy_and_scalar_evaluators_agree_with_the_reference(tree, env):
    text = render(tree)
    program = E.compile_expr(text)
    with np.errstate(all="ignore"):
        want = np.broadcast_to(reference(tree, env), env["dp"].shape)
    assert_same(np.broadcast_to(E.evaluate(program, env), want.shape), want)
    for k in range(want.size):
        point = {v: float(env[v][k]) for v in VARS}
        assert_same(E.evaluate_scalar(program, point), want[k])


@settings(max_examples=200, deadline=None)
@given(tree=TREES)
def test_canonical_text_compiles_to_the_same_program(tree):
    program = E.compile_expr(render(tree))
    again = E.compile_expr(program.text)
    assert again == program and hash(again) == hash(program)
    assert again.text == program.text
    assert len(program) <= E.MAX_INSTRUCTIONS
    assert program.stack_size >= 1


@pytest.mark.parametrize("text, point, want", [
    ("0.02*dp**1.5", {"dp": 4.0}, 0.16),
    ("-0.1*tanh((dp-0.8)/0.2)", {"dp": 0.8}, 0.0),
    ("0.05*load", {"load": 0.4}, 0.02),
    ("1e-3*q*sign(dtheta)", {"q": 2000.0, "dtheta": -0.3}, -2.0),
    ("clip(dp, 0.5, 1)", {"dp": 3.0}, 1.0),
    ("min(p1, max(run, approach))", {"p1": 3.0, "run": 2.0, "approach": -1.0}, 2.0),
    ("exp(0) + log(1) + sqrt(4) + abs(-theta)", {"theta": -2.0}, 5.0),
    ("dp**(3/2)", {"dp": 4.0}, 8.0),
    ("-2**2", {}, -4.0),
    ("(-2)**2", {}, 4.0),
    ("2", {}, 2.0),
])
def test_exact_cases(text, point, want):
    assert E.evaluate_scalar(text, point) == pytest.approx(want, abs=1e-15)
    assert float(E.evaluate(text, point)) == pytest.approx(want, abs=1e-15)


@pytest.mark.parametrize("text, want", [
    ("1/(dp-dp)", math.inf), ("-1/(dp-dp)", -math.inf), ("(dp-dp)/(dp-dp)", math.nan),
    ("log(dp-dp)", -math.inf), ("log(-dp)", math.nan), ("sqrt(-dp)", math.nan),
    ("(-dp)**0.5", math.nan), ("(dp-dp)**-1", math.inf), ("exp(1000*dp)", math.inf),
    ("(1e200*dp)**2", math.inf), ("(-1e200*dp)**3", -math.inf), ("sign(log(-dp))", math.nan),
    ("min(log(-dp), 1)", math.nan), ("clip(1, log(-dp), 2)", math.nan),
])
def test_ieee_results_without_exceptions(text, want):
    """Domain errors and overflow give what numpy gives (no Python
    exception in the scalar machine)."""
    with np.errstate(all="ignore"):
        got_np = float(E.evaluate(text, {"dp": 1.0}))
    got = E.evaluate_scalar(text, {"dp": 1.0})
    for g in (got, got_np):
        assert (math.isnan(g) and math.isnan(want)) or g == want, (text, g)


def test_program_api():
    p = E.compile_expr("0.02 * dp ** 1.5 + q*1e-3")
    assert p.text == "0.02*dp**1.5 + q*0.001"
    assert p.variables == ("dp", "q")
    assert p == E.compile_expr("(0.02*dp**(3/2)) + (q*0.001)") and p != E.compile_expr("q*0.001 + 0.02*dp**1.5")
    assert E.compile_expr(p) is p
    assert list(p.constants) == [0.02, 1.5, 0.001]
    q = p.with_constants([0.04, 1.5, 0.0])
    assert q.text == "0.04*dp**1.5 + q*0"
    assert E.evaluate_scalar(q, {"dp": 4.0, "q": 1.0}) == pytest.approx(0.32)
    with pytest.raises(ValueError, match="expected 3 constants"):
        p.with_constants([1.0])
    with pytest.raises(ValueError, match="exponent"):
        p.with_constants([1.0, 100.0, 1.0])
    with pytest.raises(ValueError, match="no value for q"):
        E.evaluate(p, {"dp": 1.0})
    with pytest.raises(ValueError, match="no value for dp"):
        E.evaluate_scalar(p, {"q": 1.0})
    assert not p.code.flags.writeable and not p.constants.flags.writeable
    assert "dp [MPa]" not in E.GRAMMAR and set(E.VARIABLE_UNITS) == set(VARS)


def test_program_memory_layout_runs_in_place():
    p = E.compile_expr("clip(q, -1, 1)*tanh(dp)")
    mem, at = E.program_memory(p, [0.5, 0, 0, 0, 3.0, 0, 0, 0])
    code_at, n, const_at, var_at, stack_at = at
    assert n == len(p) and mem.size == stack_at + p.stack_size
    assert E.run_program_core(mem, *at) == pytest.approx(math.tanh(0.5))
    # the machine reuses its memory: a second run gives the same value
    assert E.run_program_core(mem, *at) == pytest.approx(math.tanh(0.5))
    assert E.run_program_core(np.zeros(8), 0, 0, 0, 0, 0) == 0.0      # empty program


# ---------------------------------------------------------------------------
# what is refused
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("text, match", [
    ("__import__('os')", "unknown function '__import__'"),
    ("__import__('os').system('touch HACKED')", "attribute access is not allowed"),
    ("a.b", "attribute access is not allowed"),
    ("dp.real", "attribute access is not allowed"),
    ("x[0]", "a subscript is not allowed"),
    ("lambda: 1", "lambda is not allowed"),
    ("dp**1000", "exponent 1000 is beyond"),
    ("9**9**9", "beyond"),
    ("dp**p1", "exponent of \\*\\* must be a constant"),
    ("1" * 401, "longer than 400 characters"),
    ("dp+" * 200 + "1", "longer than 400 characters"),
    ("+".join(["dp"] * 130), "nested deeper|longer than"),
    ("foo", "unknown name 'foo'"),
    ("tanh", "tanh is a function"),
    ("tanh(x=dp)", "takes no keyword arguments"),
    ("min(dp, 1, 2)", "min\\(\\) takes 2 arguments, got 3"),
    ("sqrt()", "takes 1 argument, got 0"),
    ("exp(*[dp])", "takes no \\*arguments"),
    ("'dp'", "a str constant is not allowed"),
    ("True", "a bool constant"),
    ("1j", "a complex constant"),
    ("1e999", "not finite"),
    ("dp % 2", "'%' is not allowed"),
    ("dp // 2", "'//' is not allowed"),
    ("dp < 1", "a comparison is not allowed"),
    ("dp if q else 1", "if/else is not allowed"),
    ("[dp]", "a list is not allowed"),
    ("(dp, q)", "a tuple is not allowed"),
    ("f'{dp}'", "f-string"),
    ("(y := 1)", "':=' is not allowed"),
    ("dp; import os", "invalid syntax"),
    ("import os", "invalid syntax"),
    ("dp\n+ 1", "control character"),
    ("", "empty"),
    ("   ", "empty"),
    ("(" * 300 + "dp" + ")" * 300, "longer than|parsed|nested|syntax"),
])
def test_invalid_expressions_are_refused_in_one_line(text, match):
    with pytest.raises(ValueError, match=match) as info:
        E.compile_expr(text)
    msg = str(info.value)
    assert "\n" not in msg and msg.startswith("expr")


def test_nothing_is_executed(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for text in ("__import__('os').system('touch HACKED')", "open('HACKED', 'w')",
                 "exec('open(1)')", "eval('1')", "globals()", "().__class__"):
        with pytest.raises(ValueError):
            E.compile_expr(text)
    assert not (tmp_path / "HACKED").exists()
    # and the module never calls eval/exec/compile on text
    tree = ast.parse(Path(inspect.getsourcefile(E)).read_text())
    called = {n.func.id for n in ast.walk(tree) if isinstance(n, ast.Call)
              and isinstance(n.func, ast.Name)}
    assert not called & {"eval", "exec", "compile", "__import__"}


@settings(max_examples=300, deadline=None)
@given(text=st.text(alphabet=st.sampled_from(list("dpqr1.e+-*/()_,[]'\" =<lambdatnhxsgiopc")),
                    max_size=60))
def test_any_text_compiles_or_is_a_one_line_value_error(text):
    try:
        program = E.compile_expr(text)
    except ValueError as exc:
        assert "\n" not in str(exc)
        return
    assert E.compile_expr(program.text) == program
    with np.errstate(all="ignore"):
        E.evaluate(program, {v: np.linspace(-2, 2, 5) for v in VARS})


@pytest.mark.parametrize("text,unit", [
    ("dp**2", "MPa^2"), ("sqrt(dp)", "MPa^0.5"), ("tanh(dp/0.4)", ""), ("max(dp - 0.3, 0)", "MPa"),
    ("dp*dtheta", "deg MPa"), ("abs(q)", "mm^3/s"), ("load", "MPa"), ("run", "run"),
    ("min(approach, 0)", ""), ("clip(theta, 1, 2)", "deg"), ("2.5", ""),
])
def test_the_unit_of_an_expression_comes_from_its_variables(text, unit):
    assert E.unit_of(text) == unit


def test_a_sum_of_two_units_has_none():
    with pytest.raises(ValueError, match="different units"):
        E.unit_of("dp + dtheta")
