"""A small, safe expression grammar for closed-form correction terms.

A correction term of the valve model (the ``term`` effect of
:mod:`seanv_analysis.models.effects`, and the terms discover proposes) is a
short formula such as ``0.02*dp**1.5``, ``-0.1*tanh((dp - 0.8)/0.2)`` or
``1e-3*q*sign(dtheta)``. :func:`compile_expr` parses the text with Python's
:mod:`ast` (mode ``'eval'``; nothing is ever ``eval``-ed or ``exec``-ed),
accepts only the whitelist below and compiles it to a flat postfix
:class:`Program`, which

- :func:`evaluate` runs vectorised on numpy arrays, and
- :func:`run_program_core` runs on one set of scalars: a plain function
  (a small stack machine over one float64 array holding code, constants,
  variables and stack, :func:`program_memory`) written so that numba
  compiles it, so the simulator's compiled kernel evaluates ANY accepted
  expression from its arrays without being compiled again per expression.

Grammar
-------
- numbers: decimal literals (``2``, ``0.5``, ``1e-3``); finite;
- variables (:data:`VARIABLES`), for one valve side at one instant:

  ============  =========  ======================================================
  name          unit       meaning
  ============  =========  ======================================================
  ``dp``        MPa        the side's pressure difference (supply p_s - p_h,
                           drain p_h - p_t)
  ``p1``        MPa        the side's upstream pressure (supply p_s, drain p_h)
  ``dtheta``    deg        opening past the side's sealing threshold theta_d,
                           not clipped: theta - theta_d on the supply side,
                           theta_d - theta on the drain side (> 0: open)
  ``theta``     deg        cam angle at the needle
  ``q``         mm^3/s     the side's flow of eq. (5) before the term (signed as
                           in the paper: the drain side's flow is negative)
  ``load``      MPaG       load pressure
  ``run``       run        0-based index of the run in time order
  ``approach``  -          +1 / -1: the cam last moved up / down (0: unknown)
  ============  =========  ======================================================

- derived variables (:data:`DERIVED`, :func:`define_variable`): a name for
  an expression of the variables above (e.g. a downstream pressure
  ``p1 - dp``), expanded where it is used, so the evaluators and the
  simulator's kernel need nothing new; a new one is one
  :func:`define_variable` call;
- operators ``+ - * / **`` and unary ``-`` / ``+``; the exponent of ``**``
  must be a constant (a number, or arithmetic of numbers such as ``3/2``)
  with ``|exponent| <=`` :data:`MAX_EXPONENT`;
- calls (positional arguments only) of :data:`FUNCTIONS`: ``tanh(x)``,
  ``exp(x)``, ``log(x)`` (natural), ``sqrt(x)``, ``abs(x)``, ``sign(x)``,
  ``min(a, b)``, ``max(a, b)``, ``clip(x, lo, hi)`` (= min(max(x, lo), hi));
- at most :data:`MAX_LENGTH` characters, :data:`MAX_DEPTH` levels of
  nesting and :data:`MAX_INSTRUCTIONS` program steps.

Everything else (attributes, subscripts, keywords, comparisons, lambda,
strings, other names...) is a :class:`ValueError` whose one-line message
names the offending part.

Arithmetic follows IEEE 754 as numpy does, in both evaluators: x/0 is
+-inf (0/0 NaN), log(0) = -inf, log(x < 0), sqrt(x < 0) and a negative base
to a non-integer power are NaN (-inf included), overflow is inf, and
min/max/clip/sign propagate NaN.

Examples
--------
>>> p = compile_expr("-0.1 * tanh((dp-0.8)/0.2)")
>>> p.text
'-0.1*tanh((dp - 0.8)/0.2)'
>>> float(evaluate(p, {"dp": 0.8}))
-0.0
>>> compile_expr("0.02*dp**(3/2)") == compile_expr("0.02 * dp ** 1.5")
True
"""
from __future__ import annotations

import ast
import math
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from ..units import unit_powers, unit_text

__all__ = ["VARIABLES", "VARIABLE_UNITS", "FUNCTIONS", "MAX_LENGTH", "MAX_DEPTH",
           "MAX_INSTRUCTIONS", "MAX_EXPONENT", "Program", "compile_expr", "evaluate",
           "evaluate_scalar", "program_memory", "run_program_core", "GRAMMAR", "DERIVED",
           "Derived", "define_variable", "variable_names", "searched_variables", "unit_of"]

#: the variables an expression may use, in the order of their index
VARIABLES = ("dp", "p1", "dtheta", "theta", "q", "load", "run", "approach")
#: unit and meaning of each variable
VARIABLE_UNITS = {
    "dp": "MPa, the side's pressure difference (supply p_s - p_h, drain p_h - p_t)",
    "p1": "MPa, the side's upstream pressure (supply p_s, drain p_h)",
    "dtheta": "deg, opening past the sealing threshold, not clipped (supply theta - theta_d, "
              "drain theta_d - theta; > 0 open)",
    "theta": "deg, cam angle at the needle",
    "q": "mm^3/s, the side's flow of eq. (5) before the term (drain flow negative)",
    "load": "MPaG, load pressure",
    "run": "run, 0-based index of the run in time order",
    "approach": "-, +1/-1: the cam last moved up/down (0 unknown)",
}


@dataclass(frozen=True)
class Derived:
    """A derived variable: its definition (an expression of :data:`VARIABLES`
    and earlier derived ones), its unit and meaning, and whether discover's
    term search puts it in its library."""

    definition: str
    meaning: str
    search: bool = False


#: derived variables by name (:func:`define_variable`)
DERIVED: dict[str, Derived] = {}


def variable_names() -> tuple[str, ...]:
    """Every name an expression may read: :data:`VARIABLES`, then :data:`DERIVED`."""
    return (*VARIABLES, *DERIVED)


def searched_variables() -> dict[str, str]:
    """The derived variables discover's term search puts in its library:
    {name: expression text} (the name itself)."""
    return {name: name for name, d in DERIVED.items() if d.search}


def define_variable(name: str, definition: str, meaning: str, *, search: bool = False) -> Derived:
    """Add a derived variable: ``name`` stands for ``definition`` (an
    expression of the variables) wherever an expression uses it. ``meaning``
    starts with its unit ("MPa, ..."), as :data:`VARIABLE_UNITS`.

    Raises
    ------
    ValueError
        ``name`` is not an identifier, is a variable, a function or a derived
        variable already; ``definition`` is not an expression of the grammar.
    """
    if not name.isidentifier() or name in variable_names() or name in FUNCTIONS:
        raise ValueError(f"define_variable: name {name!r}; expected a new identifier (not "
                         f"{', '.join(variable_names())} or a function)")
    compile_expr(definition)   # refuses anything outside the grammar
    DERIVED[name] = Derived(definition, meaning, search)
    VARIABLE_UNITS[name] = meaning
    return DERIVED[name]


#: the functions and their number of arguments
FUNCTIONS = {"tanh": 1, "exp": 1, "log": 1, "sqrt": 1, "abs": 1, "sign": 1, "min": 2,
             "max": 2, "clip": 3}
#: longest accepted expression [characters]
MAX_LENGTH = 400
#: deepest accepted nesting of the expression tree [levels]
MAX_DEPTH = 32
#: longest accepted program [instructions]
MAX_INSTRUCTIONS = 128
#: largest accepted |exponent| of ``**``
MAX_EXPONENT = 16.0
#: one line that says what the grammar accepts (for error messages and --help)
GRAMMAR = ("numbers, the variables " + ", ".join(VARIABLES) + ", + - * / ** (constant exponent), "
           "unary -, and " + ", ".join(f"{f}()" for f in FUNCTIONS))

# Opcodes. Each instruction is a pair (opcode, argument) in Program.code.
OP_CONST = 1     # push constants[arg]
OP_VAR = 2       # push variables[arg]
OP_NEG = 3       # x -> -x
OP_ADD = 4       # a b -> a + b
OP_SUB = 5
OP_MUL = 6
OP_DIV = 7
OP_POW = 8       # x -> x ** constants[arg]
OP_TANH = 9
OP_EXP = 10
OP_LOG = 11
OP_SQRT = 12
OP_ABS = 13
OP_SIGN = 14
OP_MIN = 15      # a b -> min(a, b)
OP_MAX = 16
OP_CLIP = 17     # x lo hi -> min(max(x, lo), hi)

_BINARY = {ast.Add: OP_ADD, ast.Sub: OP_SUB, ast.Mult: OP_MUL, ast.Div: OP_DIV}
_CALLS = {"tanh": OP_TANH, "exp": OP_EXP, "log": OP_LOG, "sqrt": OP_SQRT, "abs": OP_ABS,
          "sign": OP_SIGN, "min": OP_MIN, "max": OP_MAX, "clip": OP_CLIP}
_ARITY = {OP_CONST: 0, OP_VAR: 0, OP_NEG: 1, OP_POW: 1, OP_TANH: 1, OP_EXP: 1, OP_LOG: 1,
          OP_SQRT: 1, OP_ABS: 1, OP_SIGN: 1, OP_ADD: 2, OP_SUB: 2, OP_MUL: 2, OP_DIV: 2,
          OP_MIN: 2, OP_MAX: 2, OP_CLIP: 3}
#: exp(x) overflows above this [-]
_EXP_MAX = 709.782712893384


# ---------------------------------------------------------------------------
# the program
# ---------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class Program:
    """A compiled expression: postfix instructions and their constants.

    Attributes
    ----------
    code : int64 array of (opcode, argument) pairs, flat (length 2 x the
        number of instructions); the argument indexes ``constants``
        (constants, exponents) or :data:`VARIABLES`
    constants : float64 array
    stack_size : deepest stack the program needs [-]
    text : the canonical form of the expression (what a report prints;
        :func:`compile_expr` of it gives an equal program)

    Two programs are equal when their instructions and constants are (so
    ``dp*2`` and ``2*dp`` differ, ``dp*2`` and ``dp * (2)`` do not).
    The arrays are read-only.
    """

    code: np.ndarray
    constants: np.ndarray
    stack_size: int
    text: str

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Program):
            return NotImplemented
        return (self.code.tobytes() == other.code.tobytes()
                and self.constants.tobytes() == other.constants.tobytes())

    def __hash__(self) -> int:
        return hash((self.code.tobytes(), self.constants.tobytes()))

    def __repr__(self) -> str:
        return f"Program({self.text!r})"

    def __str__(self) -> str:
        return self.text

    def __len__(self) -> int:
        """Number of instructions."""
        return int(self.code.size // 2)

    @property
    def variables(self) -> tuple[str, ...]:
        """The variables the expression reads, in :data:`VARIABLES` order."""
        ops, args = self.code[0::2], self.code[1::2]
        used = set(args[ops == OP_VAR].tolist())
        return tuple(v for i, v in enumerate(VARIABLES) if i in used)

    def with_constants(self, values) -> "Program":
        """The same expression with its constants replaced by ``values``
        (same length and order as :attr:`constants`, exponents included):
        e.g. to refit the numbers of a form without parsing it again.

        Raises
        ------
        ValueError
            Wrong length, a non-finite value, or an exponent out of range.
        """
        c = np.array(values, dtype=float).ravel()
        if c.shape != self.constants.shape:
            raise ValueError(f"expr: expected {self.constants.size} constants, got {c.size}")
        if not np.all(np.isfinite(c)):
            raise ValueError("expr: constants must be finite")
        ops, args = self.code[0::2], self.code[1::2]
        exps = c[args[ops == OP_POW]]
        if np.any(np.abs(exps) > MAX_EXPONENT):
            raise ValueError(f"expr: an exponent beyond +-{MAX_EXPONENT:g}")
        return _make_program(self.code.copy(), c)


def _make_program(code: np.ndarray, constants: np.ndarray) -> Program:
    code = np.ascontiguousarray(code, dtype=np.int64)
    constants = np.ascontiguousarray(constants, dtype=np.float64)
    code.setflags(write=False)
    constants.setflags(write=False)
    depth = size = 0
    for k in range(code.size // 2):
        op = int(code[2 * k])
        arity = _ARITY[op]
        depth += 1 - arity if arity else 1
        size = max(size, depth)
    return Program(code, constants, size, _decompile(code, constants))


def unit_of(program: Program | str) -> str:
    """The unit of an expression's value (a product of powers of
    :data:`seanv_analysis.units.BASE_UNITS`, in its text: ``'dp**2'`` ->
    'MPa^2', ``'dp*dtheta'`` -> 'deg MPa', ``'tanh(dp/0.4)'`` -> ''), from
    its variables' units (:data:`VARIABLE_UNITS`, 'MPaG' as 'MPa'): a number
    added to, compared with or clipped against a quantity takes its unit, a
    factor is dimensionless, and tanh, exp, log and sign give a pure number
    (their argument read as scaled).

    Raises
    ------
    ValueError
        a sum or a comparison of two different units (``'dp + dtheta'``).
    """
    prog = compile_expr(program)
    stack: list[dict[str, float] | None] = []   # None: a bare number, unit free
    for op, arg in zip(prog.code[0::2].tolist(), prog.code[1::2].tolist()):
        if op == OP_CONST:
            stack.append(None)
        elif op == OP_VAR:
            stack.append(unit_powers(VARIABLE_UNITS[VARIABLES[arg]].split(",", 1)[0]) or {})
        elif op in (OP_TANH, OP_EXP, OP_LOG, OP_SIGN):
            stack[-1] = {}
        elif op == OP_SQRT:
            stack[-1] = _scaled(stack[-1], 0.5)
        elif op == OP_POW:
            stack[-1] = _scaled(stack[-1], float(prog.constants[arg]))
        elif op in (OP_MUL, OP_DIV):
            b, a = stack.pop(), stack.pop()
            stack.append(None if a is None and b is None else _product(
                a or {}, _scaled(b or {}, 1.0 if op == OP_MUL else -1.0)))
        elif _ARITY[op] >= 2:       # + - min max clip: one unit for all
            args = [stack.pop() for _ in range(_ARITY[op])]
            known = [a for a in args if a is not None]
            if any(a != known[0] for a in known):
                raise ValueError(f"expr: {prog.text!r} adds or compares different units "
                                 f"({', '.join(sorted({unit_text(a) or '-' for a in known}))})")
            stack.append(known[0] if known else None)
    return unit_text(stack[-1] or {})


def _scaled(powers: dict[str, float] | None, k: float) -> dict[str, float] | None:
    return None if powers is None else {u: p * k for u, p in powers.items()}


def _product(a: dict[str, float], b: dict[str, float]) -> dict[str, float]:
    out = {u: a.get(u, 0.0) + b.get(u, 0.0) for u in {**a, **b}}
    return {u: p for u, p in out.items() if p}


# ---------------------------------------------------------------------------
# parsing and compiling
# ---------------------------------------------------------------------------

class _Compiler:
    """AST -> postfix code, refusing everything outside the grammar."""

    def __init__(self, text: str):
        self.text = text
        self.code: list[int] = []
        self.constants: list[float] = []

    # errors -----------------------------------------------------------------
    def fail(self, node: ast.AST | None, what: str) -> ValueError:
        part = ""
        if node is not None:
            seg = ast.get_source_segment(self.text, node)
            if seg and seg != self.text:
                part = f"{seg!r}: " if len(seg) <= 60 else f"{seg[:57]!r}...: "
        return ValueError(f"expr {self._short()}: {part}{what}")

    def _short(self) -> str:
        t = self.text if len(self.text) <= 80 else self.text[:77] + "..."
        return repr(t)

    # constants ----------------------------------------------------------------
    def _number(self, node: ast.AST) -> float | None:
        """The value of a number literal (None: not a number literal)."""
        if not isinstance(node, ast.Constant):
            return None
        v = node.value
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            kind = type(v).__name__
            raise self.fail(node, f"a {kind} constant is not allowed; expected a number")
        try:
            f = float(v)
        except OverflowError:
            f = math.inf
        if not math.isfinite(f):
            raise self.fail(node, "the number is not finite")
        return f

    def constant_value(self, node: ast.AST, depth: int) -> float:
        """Fold a constant expression (the exponent of ``**``)."""
        if depth > MAX_DEPTH:
            raise self.fail(None, f"nested deeper than {MAX_DEPTH} levels")
        v = self._number(node)
        if v is not None:
            return v
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
            x = self.constant_value(node.operand, depth + 1)
            return -x if isinstance(node.op, ast.USub) else x
        if isinstance(node, ast.BinOp) and isinstance(node.op, (ast.Add, ast.Sub, ast.Mult,
                                                                ast.Div, ast.Pow)):
            a = self.constant_value(node.left, depth + 1)
            b = self.constant_value(node.right, depth + 1)
            if isinstance(node.op, ast.Pow) and abs(b) > MAX_EXPONENT:
                raise self.fail(node, f"exponent {b:g} is beyond +-{MAX_EXPONENT:g}")
            try:
                r = {ast.Add: lambda: a + b, ast.Sub: lambda: a - b, ast.Mult: lambda: a * b,
                     ast.Div: lambda: a / b, ast.Pow: lambda: a ** b}[type(node.op)]()
            except (ZeroDivisionError, OverflowError):
                r = math.nan
            if isinstance(r, complex) or not math.isfinite(r):
                raise self.fail(node, "the constant is not a finite real number")
            return float(r)
        raise self.fail(node, "the exponent of ** must be a constant (a number, or arithmetic "
                              "of numbers)")

    # code -----------------------------------------------------------------------
    def emit(self, op: int, arg: int = 0) -> None:
        self.code += [op, arg]
        if len(self.code) // 2 > MAX_INSTRUCTIONS:
            raise self.fail(None, f"longer than {MAX_INSTRUCTIONS} instructions")

    def push_constant(self, value: float) -> None:
        self.constants.append(float(value))
        self.emit(OP_CONST, len(self.constants) - 1)

    def visit(self, node: ast.AST, depth: int) -> None:
        if depth > MAX_DEPTH:
            raise self.fail(None, f"nested deeper than {MAX_DEPTH} levels")
        v = self._number(node)
        if v is not None:
            self.push_constant(v)
            return
        if isinstance(node, ast.Name):
            if node.id in VARIABLES:
                self.emit(OP_VAR, VARIABLES.index(node.id))
                return
            if node.id in DERIVED:   # expanded where it is used (checked when defined)
                self.visit(ast.parse(DERIVED[node.id].definition, mode="eval").body, depth + 1)
                return
            if node.id in FUNCTIONS:
                raise self.fail(node, f"{node.id} is a function: call it, e.g. {node.id}(dp)")
            raise self.fail(node, f"unknown name {node.id!r}; expected one of "
                                  f"{', '.join(variable_names())}")
        if isinstance(node, ast.UnaryOp):
            if isinstance(node.op, ast.UAdd):
                self.visit(node.operand, depth + 1)
                return
            if isinstance(node.op, ast.USub):
                lit = self._number(node.operand)
                if lit is not None:                 # a negative number: one constant
                    self.push_constant(-lit)
                    return
                self.visit(node.operand, depth + 1)
                # -(-c) folds too, so the canonical text compiles to the same program
                if self.code[-2] == OP_CONST:
                    k = self.code[-1]
                    self.constants[k] = -self.constants[k]
                    return
                self.emit(OP_NEG)
                return
            raise self.fail(node, f"the operator {_op_name(node.op)} is not allowed")
        if isinstance(node, ast.BinOp):
            if isinstance(node.op, ast.Pow):
                self.visit(node.left, depth + 1)
                e = self.constant_value(node.right, depth + 1)
                if abs(e) > MAX_EXPONENT:
                    raise self.fail(node, f"exponent {e:g} is beyond +-{MAX_EXPONENT:g}")
                self.constants.append(e)
                self.emit(OP_POW, len(self.constants) - 1)
                return
            op = _BINARY.get(type(node.op))
            if op is None:
                raise self.fail(node, f"the operator {_op_name(node.op)} is not allowed")
            self.visit(node.left, depth + 1)
            self.visit(node.right, depth + 1)
            self.emit(op)
            return
        if isinstance(node, ast.Call):
            f = node.func
            if not isinstance(f, ast.Name):
                raise self.fail(f, f"{_node_name(f)} is not allowed (only "
                                   + ", ".join(f"{g}()" for g in FUNCTIONS) + " may be called)")
            if f.id not in FUNCTIONS:
                raise self.fail(node, f"unknown function {f.id!r}; expected one of "
                                      f"{', '.join(FUNCTIONS)}")
            if node.keywords:
                raise self.fail(node, f"{f.id}() takes no keyword arguments")
            if any(isinstance(a, ast.Starred) for a in node.args):
                raise self.fail(node, f"{f.id}() takes no *arguments")
            n = FUNCTIONS[f.id]
            if len(node.args) != n:
                raise self.fail(node, f"{f.id}() takes {n} argument{'s' if n > 1 else ''}, "
                                      f"got {len(node.args)}")
            for a in node.args:
                self.visit(a, depth + 1)
            self.emit(_CALLS[f.id])
            return
        raise self.fail(node, f"{_node_name(node)} is not allowed; allowed: {GRAMMAR}")


def _op_name(op: ast.AST) -> str:
    return {ast.Mod: "'%'", ast.FloorDiv: "'//'", ast.MatMult: "'@'", ast.BitAnd: "'&'",
            ast.BitOr: "'|'", ast.BitXor: "'^'", ast.LShift: "'<<'", ast.RShift: "'>>'",
            ast.Invert: "'~'", ast.Not: "'not'"}.get(type(op), type(op).__name__)


def _node_name(node: ast.AST) -> str:
    return {ast.Attribute: "attribute access", ast.Subscript: "a subscript",
            ast.Lambda: "lambda", ast.Compare: "a comparison", ast.BoolOp: "and/or",
            ast.IfExp: "if/else", ast.List: "a list", ast.Tuple: "a tuple", ast.Dict: "a dict",
            ast.Set: "a set", ast.ListComp: "a comprehension", ast.GeneratorExp: "a generator",
            ast.DictComp: "a comprehension", ast.SetComp: "a comprehension",
            ast.JoinedStr: "an f-string", ast.Starred: "*unpacking", ast.NamedExpr: "':='",
            ast.Await: "await", ast.Yield: "yield", ast.YieldFrom: "yield",
            ast.Slice: "a slice"}.get(type(node), type(node).__name__)


def compile_expr(text: str | Program) -> Program:
    """Parse and compile an expression of the grammar (module doc) [-].

    Parameters
    ----------
    text : the expression, e.g. ``"0.02*dp**1.5"`` (a :class:`Program` is
        returned as it is)

    Returns
    -------
    Program

    Raises
    ------
    ValueError
        Anything outside the grammar; the one-line message starts with
        ``expr`` and names the offending part.
    """
    if isinstance(text, Program):
        return text
    if not isinstance(text, str):
        raise ValueError(f"expr: expected a string, got {type(text).__name__}")
    shown = repr(text if len(text) <= 80 else text[:77] + "...")
    if len(text) > MAX_LENGTH:
        raise ValueError(f"expr {shown}: longer than {MAX_LENGTH} characters ({len(text)})")
    if not text.strip():
        raise ValueError("expr: empty; expected an expression such as 0.02*dp**1.5")
    if not text.strip().isprintable():
        raise ValueError(f"expr {shown}: contains a control character")
    try:
        tree = ast.parse(text.strip(), mode="eval")
    except SyntaxError as exc:
        col = f" at column {exc.offset}" if exc.offset else ""
        why = f" ({exc.msg})" if exc.msg and exc.msg != "invalid syntax" else ""
        raise ValueError(f"expr {shown}: invalid syntax{col}{why}") from None
    except (RecursionError, MemoryError, ValueError):
        raise ValueError(f"expr {shown}: cannot be parsed (nested too deeply?)") from None
    comp = _Compiler(text.strip())
    try:
        comp.visit(tree.body, 0)
    except RecursionError:
        raise ValueError(f"expr {shown}: nested deeper than {MAX_DEPTH} levels") from None
    return _make_program(np.array(comp.code, dtype=np.int64),
                         np.array(comp.constants, dtype=np.float64))


# ---------------------------------------------------------------------------
# canonical text
# ---------------------------------------------------------------------------

# precedence of the printed forms: + - (1), * / (2), unary minus and
# negative numbers (3), ** (4), atoms (5)
_INFIX = {OP_ADD: (" + ", 1), OP_SUB: (" - ", 1), OP_MUL: ("*", 2), OP_DIV: ("/", 2)}
_NAMES = {v: k for k, v in _CALLS.items()}


def _number_text(v: float) -> str:
    s = repr(float(v))
    return s[:-2] if s.endswith(".0") else s


def _decompile(code: np.ndarray, constants: np.ndarray) -> str:
    """The canonical infix text of a program: minimal parentheses, one space
    around binary + and -, numbers as Python's shortest round-trip form."""
    stack: list[tuple[str, int]] = []
    for k in range(code.size // 2):
        op, arg = int(code[2 * k]), int(code[2 * k + 1])
        if op == OP_CONST:
            v = float(constants[arg])
            stack.append((_number_text(v), 3 if math.copysign(1.0, v) < 0 else 5))
        elif op == OP_VAR:
            stack.append((VARIABLES[arg], 5))
        elif op == OP_NEG:
            s, p = stack.pop()
            stack.append(("-" + (s if p >= 3 else f"({s})"), 3))
        elif op == OP_POW:
            s, p = stack.pop()
            stack.append(((s if p >= 5 else f"({s})") + "**" + _number_text(constants[arg]), 4))
        elif op in _INFIX:
            b, pb = stack.pop()
            a, pa = stack.pop()
            sym, prec = _INFIX[op]
            left = a if pa >= prec else f"({a})"
            right = b if pb > prec else f"({b})"
            stack.append((left + sym + right, prec))
        else:
            n = _ARITY[op]
            args = [stack.pop()[0] for _ in range(n)][::-1]
            stack.append((f"{_NAMES[op]}({', '.join(args)})", 5))
    return stack[0][0] if stack else ""


# ---------------------------------------------------------------------------
# evaluation
# ---------------------------------------------------------------------------

def evaluate(program: Program | str, variables: Mapping[str, object]) -> np.ndarray:
    """Value of ``program`` on arrays of the variables, vectorised (numpy
    broadcasting) [the unit of the quantity the term stands for].

    Parameters
    ----------
    program : a :class:`Program` or an expression's text
    variables : {name: number or array} for (at least) the variables the
        program reads

    Raises
    ------
    ValueError
        A bad expression, or a variable it reads is not given.
    """
    program = compile_expr(program)
    missing = [v for v in program.variables if v not in variables]
    if missing:
        raise ValueError(f"expr {program.text!r}: no value for {', '.join(missing)}")
    code, consts = program.code, program.constants
    stack: list = []
    with np.errstate(all="ignore"):
        for k in range(code.size // 2):
            op, arg = int(code[2 * k]), int(code[2 * k + 1])
            if op == OP_CONST:
                stack.append(np.float64(consts[arg]))
            elif op == OP_VAR:
                stack.append(np.asarray(variables[VARIABLES[arg]], dtype=float))
            elif op == OP_NEG:
                stack.append(np.negative(stack.pop()))
            elif op == OP_POW:
                x, e = stack.pop(), consts[arg]
                r = np.power(x, e)
                if e != math.floor(e):      # negative base, non-integer power: NaN
                    r = np.where(np.less(x, 0.0), np.nan, r)   # (also -inf, which
                stack.append(r)                                 # numpy's sqrt path lets by)
            elif op in (OP_TANH, OP_EXP, OP_LOG, OP_SQRT, OP_ABS, OP_SIGN):
                f = {OP_TANH: np.tanh, OP_EXP: np.exp, OP_LOG: np.log, OP_SQRT: np.sqrt,
                     OP_ABS: np.abs, OP_SIGN: np.sign}[op]
                stack.append(f(stack.pop()))
            elif op == OP_CLIP:
                hi, lo, x = stack.pop(), stack.pop(), stack.pop()
                stack.append(np.minimum(np.maximum(x, lo), hi))
            else:
                b, a = stack.pop(), stack.pop()
                f = {OP_ADD: np.add, OP_SUB: np.subtract, OP_MUL: np.multiply,
                     OP_DIV: np.divide, OP_MIN: np.minimum, OP_MAX: np.maximum}[op]
                stack.append(f(a, b))
    if not stack:
        return np.asarray(0.0)
    return np.asarray(stack[0], dtype=float)


def program_memory(program: Program, variables=None) -> tuple[np.ndarray, tuple[int, ...]]:
    """``program`` laid out in one float64 array for :func:`run_program_core`:
    its code (opcodes and arguments as floats, exact), constants, the
    variables (:data:`VARIABLES` order; ``variables``, or zeros) and its
    stack. Returns (memory, (code_at, n_instructions, constants_at,
    variables_at, stack_at)), the offsets in elements."""
    n = len(program)
    nc = program.constants.size
    nv = len(VARIABLES)
    mem = np.zeros(2 * n + nc + nv + max(program.stack_size, 1))
    mem[:2 * n] = program.code
    mem[2 * n:2 * n + nc] = program.constants
    if variables is not None:
        mem[2 * n + nc:2 * n + nc + nv] = variables
    return mem, (0, n, 2 * n, 2 * n + nc, 2 * n + nc + nv)


def evaluate_scalar(program: Program | str, variables: Mapping[str, float]) -> float:
    """Value of ``program`` at one point, by :func:`run_program_core` (the
    stack machine the simulator's kernel compiles) [-].

    Raises
    ------
    ValueError
        A bad expression, or a variable it reads is not given.
    """
    program = compile_expr(program)
    missing = [v for v in program.variables if v not in variables]
    if missing:
        raise ValueError(f"expr {program.text!r}: no value for {', '.join(missing)}")
    xs = [float(variables.get(v, 0.0)) for v in VARIABLES]
    mem, at = program_memory(program, xs)
    with np.errstate(all="ignore"):     # the memory's numpy scalars would warn
        return float(run_program_core(mem, *at))


def run_program_core(memory, code_at, n_instructions, constants_at, variables_at, stack_at):
    """Run one program on scalars, everything in one float64 array
    ``memory`` (:func:`program_memory`): ``n_instructions`` (opcode,
    argument) pairs from ``code_at``, the constants from ``constants_at``
    (an argument indexes them), the variables from ``variables_at``
    (:data:`VARIABLES` order) and the stack from ``stack_at`` (room for the
    program's ``stack_size``). Returns the value (0.0 for an empty program).

    Plain Python that numba compiles (``sim.jit.run_program``): no
    allocation, no exception, IEEE results as :func:`evaluate` gives them
    (module doc). One array, so compiled callers pass one argument.
    """
    sp = stack_at
    k = code_at
    n = code_at + 2 * n_instructions
    while k < n:
        op = int(memory[k])
        arg = int(memory[k + 1])
        k += 2
        if op == OP_CONST:
            memory[sp] = memory[constants_at + arg]
            sp += 1
        elif op == OP_VAR:
            memory[sp] = memory[variables_at + arg]
            sp += 1
        elif op == OP_NEG:
            memory[sp - 1] = -memory[sp - 1]
        elif op == OP_ADD:
            sp -= 1
            memory[sp - 1] = memory[sp - 1] + memory[sp]
        elif op == OP_SUB:
            sp -= 1
            memory[sp - 1] = memory[sp - 1] - memory[sp]
        elif op == OP_MUL:
            sp -= 1
            memory[sp - 1] = memory[sp - 1] * memory[sp]
        elif op == OP_DIV:
            sp -= 1
            a = memory[sp - 1]
            b = memory[sp]
            if b == 0.0:
                if a == 0.0 or a != a:
                    memory[sp - 1] = math.nan
                else:
                    memory[sp - 1] = math.copysign(math.inf, a) * math.copysign(1.0, b)
            else:
                memory[sp - 1] = a / b
        elif op == OP_POW:
            a = memory[sp - 1]
            e = memory[constants_at + arg]
            integral = e == math.floor(e)
            odd = integral and 0.5 * e != math.floor(0.5 * e)
            if a != a:
                r = 1.0 if e == 0.0 else math.nan
            elif a < 0.0 and not integral:
                r = math.nan
            elif abs(a) == math.inf:
                if e == 0.0:
                    r = 1.0
                else:
                    m = math.inf if e > 0.0 else 0.0
                    r = -m if (a < 0.0 and odd) else m
            elif a == 0.0:
                if e < 0.0:
                    r = math.copysign(math.inf, a) if odd else math.inf
                elif e == 0.0:
                    r = 1.0
                else:
                    r = math.copysign(0.0, a) if odd else 0.0
            elif e * math.log(abs(a)) > _EXP_MAX:
                r = -math.inf if (a < 0.0 and odd) else math.inf
            else:
                r = a ** e
            memory[sp - 1] = r
        elif op == OP_TANH:
            memory[sp - 1] = math.tanh(memory[sp - 1])
        elif op == OP_EXP:
            x = memory[sp - 1]
            memory[sp - 1] = math.inf if x > _EXP_MAX else math.exp(x)
        elif op == OP_LOG:
            x = memory[sp - 1]
            if x > 0.0:
                memory[sp - 1] = math.log(x)
            elif x == 0.0:
                memory[sp - 1] = -math.inf
            else:
                memory[sp - 1] = math.nan
        elif op == OP_SQRT:
            x = memory[sp - 1]
            memory[sp - 1] = math.nan if x < 0.0 else math.sqrt(x)
        elif op == OP_ABS:
            memory[sp - 1] = abs(memory[sp - 1])
        elif op == OP_SIGN:
            x = memory[sp - 1]
            if x > 0.0:
                memory[sp - 1] = 1.0
            elif x < 0.0:
                memory[sp - 1] = -1.0
            elif x == 0.0:
                memory[sp - 1] = 0.0
            else:
                memory[sp - 1] = math.nan
        elif op == OP_MIN or op == OP_MAX:
            sp -= 1
            a = memory[sp - 1]
            b = memory[sp]
            if a != a or b != b:
                memory[sp - 1] = math.nan
            elif op == OP_MIN:
                memory[sp - 1] = a if a < b else b
            else:
                memory[sp - 1] = a if a > b else b
        elif op == OP_CLIP:
            sp -= 2
            x = memory[sp - 1]
            lo = memory[sp]
            hi = memory[sp + 1]
            if x != x or lo != lo or hi != hi:
                memory[sp - 1] = math.nan
            else:
                if x < lo:
                    x = lo
                if x > hi:
                    x = hi
                memory[sp - 1] = x
    if sp == stack_at:
        return 0.0
    return memory[stack_at]
