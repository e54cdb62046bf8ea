"""Physics of the SEANV rig: one home per equation (paper eq. 1-6).

The fit, the controller and the simulator all call these functions. Plain
numpy/scipy: no files, no compiled code (the simulator compiles the
``*_core`` functions itself), bad values raise :class:`ValueError`.
"""
from .actuator import flow_from_velocity
from .sealing import (
    NeedleGeometry,
    fluid_force_n,
    needle_height_mm,
    spring_force_n,
    threshold_displacement_mm,
)
from .valve import (
    SIDES,
    ValveModel,
    ValveSide,
    seat_leakage_mm3_s,
    side_pressures,
    signed_power,
)

__all__ = [
    "NeedleGeometry", "fluid_force_n", "needle_height_mm", "spring_force_n",
    "threshold_displacement_mm", "SIDES", "ValveModel", "ValveSide", "side_pressures",
    "signed_power", "seat_leakage_mm3_s", "flow_from_velocity",
]
