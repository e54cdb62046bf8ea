"""Re-running position-control runs on a twin, and their flow error.

The closed-loop fits of :mod:`.flowpath` (the line's bulk modulus) and
:mod:`.dynamic` (delay, backlash) share these two pieces: each run's own
controller, references and loads re-simulated on the twin
(:func:`seanv_analysis.analysis.validate.validate_run`), and the measured vs
simulated actuator flow error with the residuals' effective sample size.
"""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from .noise import integrated_autocorrelation

__all__ = ["validate_on_twin", "flow_sse", "with_bulk"]


def with_bulk(rig, bulk_mpa: float, *, where: str = "identify"):
    """``rig`` with the line's effective bulk modulus ``bulk_mpa`` [MPa]."""
    return rig.with_overrides({"tube": {"effective_bulk_modulus_mpa": float(bulk_mpa)}},
                              where=where)


def validate_on_twin(runs: Sequence[Any], valve, rig, effects: Sequence[str] = ()) -> list[Any]:
    """:func:`~seanv_analysis.analysis.validate.validate_run` of each run on the
    twin ``rig`` with the simulator's ``effects``; runs it cannot re-run are left out."""
    from ..analysis.validate import validate_run
    from ..errors import DataError

    out = []
    for run in runs:
        try:
            out.append(validate_run(run, valve, rig=rig, effects=tuple(effects)))
        except DataError:
            continue
    return out


def flow_sse(validations) -> tuple[float, float, int]:
    """(sum of squared flow errors [(mm^3/s)^2], effective sample count,
    samples) of measured vs simulated actuator flow, NaN samples left out."""
    sse, n_eff, n = 0.0, 0.0, 0
    for v in validations:
        r = (v.overlay["q_mm3_s"] - v.overlay["q_sim_mm3_s"]).to_numpy(float)
        r = r[np.isfinite(r)]
        if r.size < 10:
            continue
        sse += float(np.sum(r * r))
        n_eff += r.size / integrated_autocorrelation(r)
        n += r.size
    return sse, n_eff, n
