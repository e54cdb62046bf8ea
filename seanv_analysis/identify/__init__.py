"""Identify the rig from its own logs: the constants the paper does not publish.

Needle geometry (eq. 4's centre), servo dead time / time constant / rate
limit, actuator friction and the flow path's lag, each with a 95 % interval,
what in the data constrains it, and the training vs held-out error with the
rig file's value and with the identified one. What the data cannot tell
keeps the rig file's value and says why.

This layer sits above the simulator and the fits: it fits the simulator's
own servo step and matches the simulator's line to the measured lag.
"""
from .engine import PARTS, identify_rig, split_runs
from .result import Constant, Identification

__all__ = ["identify_rig", "PARTS", "split_runs", "Constant", "Identification"]
