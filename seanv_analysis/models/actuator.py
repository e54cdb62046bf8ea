"""Actuator geometry (paper Sec. II-D.2): flow from the piston velocity.

Units: mm, mm^2, mm/s, mm^3/s.
"""
from __future__ import annotations

import numpy as np

__all__ = ["flow_from_velocity"]


def flow_from_velocity(velocity_mm_s, piston_area_mm2: float):
    """Flow into the actuator head Q = v A [mm^3/s] (velocity mm/s, area mm^2):
    how the flow-step runs measure the valve's flow (eq. 5's Q)."""
    return np.asarray(velocity_mm_s) * piston_area_mm2
