"""Physics of the SEANV rig: one home per equation (paper eq. 1-6).

The fit, the controller and the simulator all call these functions.
"""
from .sealing import (NeedleGeometry, fluid_force_n, needle_height_mm, spring_force_n,
                      threshold_displacement_mm)
from .valve import SIDES, ValveModel, ValveSide, side_pressures, signed_power
from .actuator import flow_from_velocity, head_pressure_for_load_mpag, load_force_n

__all__ = [
    "NeedleGeometry", "fluid_force_n", "needle_height_mm", "spring_force_n",
    "threshold_displacement_mm", "SIDES", "ValveModel", "ValveSide", "side_pressures",
    "signed_power", "flow_from_velocity", "head_pressure_for_load_mpag", "load_force_n",
]
