"""Actuator and load geometry (paper Sec. II-D.2, III-A).

Units: mm, mm^2, MPa, N, mm^3/s.
"""
from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["flow_from_velocity", "load_force_n", "head_pressure_for_load_mpag"]


def flow_from_velocity(velocity_mm_s, piston_area_mm2: float):
    """Flow into the actuator head Q = v A [mm^3/s] (velocity mm/s, area mm^2)."""
    return np.asarray(velocity_mm_s) * piston_area_mm2


def load_force_n(p_load_mpag, rig: Any):
    """Force of the pneumatic load actuator opposing extension [N] (p A_load)."""
    return np.asarray(p_load_mpag) * rig.load_area_mm2


def head_pressure_for_load_mpag(p_load_mpag, rig: Any):
    """Head pressure that balances the load with no friction or motion [MPaG]."""
    return load_force_n(p_load_mpag, rig) / rig.piston_area_mm2
