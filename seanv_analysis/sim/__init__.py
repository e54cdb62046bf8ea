"""Built-in plant simulator of the SEANV rig, its scenarios and injectable effects.

- :class:`Plant` (:mod:`.plant`): valve (eq. 3-5), 20 m tube, actuator with
  friction, pneumatic load, servo, sensors; effects from
  :mod:`seanv_analysis.models.effects`.
- :func:`simulate_flow_step`, :func:`simulate_position_control`,
  :func:`simulate_cam_replay` (:mod:`.run`): one run in memory, tables as
  recorded (the replay: the plant driven open loop by a logged cam command).
- :func:`simulate_scenario` (:mod:`.scenarios`): a whole data set on disk.
"""
from .plant import Plant, tube_constants
from .run import SimTrace, simulate_cam_replay, simulate_flow_step, simulate_position_control

__all__ = ["Plant", "tube_constants", "SimTrace", "simulate_flow_step",
           "simulate_position_control", "simulate_cam_replay", "simulate_scenario", "SCENARIOS"]


def __getattr__(name):
    if name in ("simulate_scenario", "SCENARIOS"):
        from . import scenarios
        return getattr(scenarios, name)
    raise AttributeError(name)
