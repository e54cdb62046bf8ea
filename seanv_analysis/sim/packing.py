"""Packing of a valve model and of the closed-form terms for compiled code.

Plain numpy, no numba: the simulator's runner and controllers pack their
arguments here, and only the compiled functions themselves
(:mod:`.jit`, :mod:`.kernel`) need numba. The layouts:

- a valve side is ``(params, z_table, theta_table)`` with ``params``
  indexed by the ``SP_*`` constants (:func:`pack_side`);
- both sides' closed-form terms (the ``term`` effect) are one float64 array
  (:func:`pack_terms`), indexed by the ``TW_*``/``TV_*`` constants;
- a controller (:mod:`.control`, :mod:`.control_law`) is its kind
  (``KIND_*``), its parameters (``_CP_*``, ``CP_SIZE``) and its state
  (``_ST_*``).
"""
from __future__ import annotations

import math

import numpy as np

from ..models import expr as _expr

__all__ = ["SP_Z0", "SP_C", "SP_EXPONENT", "SP_DN", "SP_DO", "SP_K", "SP_UP", "SP_QMAX",
           "SP_SHARP", "SP_SIZE", "pack_side", "pack_model",
           "TERM_NONE", "TERM_MUL", "TERM_ADD", "TERM_THRESHOLD",
           "TV_DP", "TV_P1", "TV_DTHETA", "TV_THETA", "TV_Q", "TV_LOAD", "TV_RUN", "TV_APPROACH",
           "TV_SIZE", "TW_SUPPLY", "TW_DRAIN", "TW_VARS", "TW_STACK", "TW_HEADER", "TW_MODE",
           "TW_CODE", "TW_N", "TW_CONST", "pack_terms", "KIND_FLOW_MODEL", "KIND_CAM", "CP_SIZE"]

#: controller kinds (the kernel's MODE_SCHEDULE = 0 is the open-loop schedule)
KIND_FLOW_MODEL = 1
KIND_CAM = 2
# packed controller parameters
_CP_KP, _CP_BAND, _CP_RELEASE, _CP_CAM_MIN, _CP_CAM_MAX, _CP_HOLD, _CP_MIN_DP = range(7)
CP_SIZE = 7
# packed controller state: held (0/1), hold angle [deg], previous reference [mm]
_ST_HELD, _ST_HOLD_DEG, _ST_XREF = range(3)

# packed side parameters
SP_Z0, SP_C, SP_EXPONENT, SP_DN, SP_DO, SP_K, SP_UP, SP_QMAX, SP_SHARP = range(9)
SP_SIZE = 9


# closed-form terms: modes, the index of each variable of models.expr, and
# the layout of the packed terms' memory (pack_terms)
TERM_NONE, TERM_MUL, TERM_ADD, TERM_THRESHOLD = 0, 1, 2, 3
_TERM_MODE_IDS = {"mul": TERM_MUL, "add": TERM_ADD, "threshold": TERM_THRESHOLD}
(TV_DP, TV_P1, TV_DTHETA, TV_THETA, TV_Q, TV_LOAD, TV_RUN,
 TV_APPROACH) = (_expr.VARIABLES.index(v) for v in ("dp", "p1", "dtheta", "theta", "q", "load",
                                                    "run", "approach"))
TV_SIZE = len(_expr.VARIABLES)
#: header of the packed terms: per side (supply at TW_SUPPLY, drain at
#: TW_DRAIN) mode, code offset, number of instructions, constants offset;
#: then the offsets of the variables and of the stack
TW_SUPPLY, TW_DRAIN, TW_VARS, TW_STACK, TW_HEADER = 0, 4, 8, 9, 10
TW_MODE, TW_CODE, TW_N, TW_CONST = 0, 1, 2, 3


def pack_terms(supply=None, drain=None, *, run_index: float = 0.0) -> np.ndarray:
    """The two valve sides' closed-form terms for compiled code, in one
    float64 array (one argument, so passing it costs the step loop nothing):
    a header (``TW_*``: per side its mode ``TERM_*``, code offset, number of
    instructions, constants offset; the offsets of the variables and of the
    stack), then each side's program (:func:`models.expr.program_memory`
    layout: opcode/argument pairs as floats, constants), the variables
    (``TV_*``; ``run`` = ``run_index``) and a stack for the deeper program.

    ``supply``, ``drain``: (mode, :class:`~seanv_analysis.models.expr.Program`)
    or None (no term: mode ``TERM_NONE``). A fresh array per run: the
    compiled code writes the variables and the stack into it.
    """
    head = np.zeros(TW_HEADER)
    parts = [head]
    at = TW_HEADER
    depth = 1
    for base, term in ((TW_SUPPLY, supply), (TW_DRAIN, drain)):
        mode, program = term if term is not None else (None, None)
        if mode is None or program is None or len(program) == 0:
            continue
        n = len(program)
        head[base + TW_MODE] = _TERM_MODE_IDS[mode]
        head[base + TW_CODE] = at
        head[base + TW_N] = n
        head[base + TW_CONST] = at + 2 * n
        parts += [program.code.astype(np.float64), np.asarray(program.constants, np.float64)]
        at += 2 * n + program.constants.size
        depth = max(depth, program.stack_size)
    head[TW_VARS] = at
    head[TW_STACK] = at + TV_SIZE
    variables = np.zeros(TV_SIZE)
    variables[TV_RUN] = run_index
    parts += [variables, np.zeros(depth)]
    return np.ascontiguousarray(np.concatenate(parts))


def pack_side(side, *, c_multiplier: float = 1.0, z0_offset_mm: float = 0.0,
              dp_exponent: float | None = None, q_max_mm3_s: float = math.inf,
              sharpness: float = 8.0):
    """(params, z_table, theta_table) of a :class:`ValveSide` for compiled code,
    optionally with effect modifications folded in (C multiplier, z0 offset,
    dp exponent, flow cap)."""
    g = side.geometry
    params = np.empty(SP_SIZE)
    params[SP_Z0] = side.z0_mm + z0_offset_mm
    params[SP_C] = side.c_flow * c_multiplier
    params[SP_EXPONENT] = side.dp_exponent if dp_exponent is None else dp_exponent
    params[SP_DN] = g.needle_diameter_mm
    params[SP_DO] = g.seat_diameter_mm
    params[SP_K] = g.spring_constant_n_per_mm
    params[SP_UP] = 1.0 if side.opens_upward else 0.0
    params[SP_QMAX] = q_max_mm3_s
    params[SP_SHARP] = sharpness
    z, theta = g.height_table
    return params, np.ascontiguousarray(z, dtype=float), np.ascontiguousarray(theta, dtype=float)


def pack_model(model):
    """(supply params, z, theta, drain params, z, theta) of a :class:`ValveModel`."""
    return pack_side(model.supply) + pack_side(model.drain)
