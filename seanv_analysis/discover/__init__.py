"""Close the loop: residual of the model on measured data -> the effect the
model lacks -> refit -> error before and after on held-out runs.

This package sees only what a rig records: it never imports the simulator
and never reads ``_truth.json``. Closed-loop checks go through ``validate``.
"""
from .engine import discover_flow_steps, noise_model
from .result import Discovery, EffectFinding
from .split import chrono_split, kfold_splits

__all__ = ["discover_flow_steps", "noise_model", "Discovery", "EffectFinding",
           "chrono_split", "kfold_splits"]
