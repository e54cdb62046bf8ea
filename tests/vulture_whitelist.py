"""Names vulture (tests/test_architecture.py::test_no_dead_code) cannot see
used, each with why it stays. Anything else it reports is dead code: delete it."""
# ruff: noqa
# module-level __getattr__ / __dir__ (PEP 562: lazy names, read by Python itself)
__getattr__
__dir__
# Jupyter calls _repr_html_ (the results' notebook display)
_._repr_html_
# a signal handler's signature (signal.signal calls it with both)
signum
# results' public fields and properties, read by users (and their JSON through asdict)
lags_s  # analysis.lag.LagEstimate: the cross-correlation curve
correlation
binned  # discover.diagnostics.Trend: the binned residual for a figure
train_sse_drop  # identify.dynamic.DynamicFinding (to_json_dict via asdict)
n_cycles  # analysis.limitcycle.LimitCycle: cycles counted and where
windows_s
_.span_s  # io.run.Run: the time span of a run
_.with_constants  # models.expr.Program: refit a form's numbers
valid_start_s  # signals.derive.Derived: where the filter is valid
valid_end_s
edge_mode
cam_cmd_deg  # signals.derive / sim.control: the commanded cam of a step
settled_from_feedback
_.initial_state  # sim.control.Controller: a notebook user's first state (docs example)
# numba's and numba.pycc's configuration attributes, read by numba
_.output_dir
_.target_cpu
_.release_gil
_.CACHE_LOCATOR_CLASSES
_._cache_path
# numpy's flags attribute
_.writeable
# called from other processes' command lines and from the tests
_child  # benchmarks/bench_ingest.py: `python -c "... _child(...)"`
layout  # scripts/check_report_browser.py: tests/test_report.py renders with it
# seanv_analysis/__init__.py: a command subpackage made callable (read by
# inspect.signature, set on module objects: Python reads them)
_.__signature__
_.__class__
_.eval  # fit.FlowFit.eval: a notebook user's model prediction (as lmfit's result.eval)
