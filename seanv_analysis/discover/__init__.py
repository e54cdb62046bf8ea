"""Close the loop: residual of the model on measured data -> the effect the
model lacks -> refit -> error before and after on held-out runs.

This package sees only what a rig records: it never imports the simulator
and never reads ``_truth.json``. Closed-loop checks go through ``validate``.
The candidate effects are the registered effects of
:mod:`seanv_analysis.models.effects` that have a static form.
"""
from .assemble import MIN_FLOW_RUNS, NoTwin, discover_dataset
from .engine import discover_flow_steps, noise_model, residual_variables
from .result import Discovery, EffectFinding
from .split import chrono_split, kfold_splits, split_position_runs
from .static import FlowData, predict_static

__all__ = ["discover_dataset", "MIN_FLOW_RUNS", "NoTwin", "discover_flow_steps", "noise_model",
           "residual_variables", "Discovery", "EffectFinding", "FlowData", "predict_static",
           "chrono_split", "kfold_splits", "split_position_runs"]
