"""No traceback, ever, from an analysis (issue 31): identify and discover,
driven over generated data sets (small and degenerate ones: few runs, one
side, one load, position runs without flow steps, noise-free signals, runs
of the package's simulator with an effect in), end in a result or in the
package's own error (SeanvError), never in another exception."""
from __future__ import annotations

import pytest
from conftest import write_synthetic_dataset
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from seanv_analysis.errors import SeanvError
from seanv_analysis.stages import run_stages

pytestmark = pytest.mark.slow

DATA = st.fixed_dictionaries({
    "n_flow": st.integers(0, 14),
    "n_position": st.integers(0, 2),
    "noise": st.booleans(),
    "load_mpag": st.sampled_from([0.35, 0.1, 0.6]),
    "duration_s": st.sampled_from([0.4, 1.5]),
}).filter(lambda d: d["n_flow"] + d["n_position"] > 0)


def _analyse(root, stages):
    try:
        ctx = run_stages(root, stages, options={"identify": {"n_boot": 0}}
                         if "identify" in stages else None)
    except SeanvError:
        return None                     # the package's own error: a clear message
    return ctx


@settings(max_examples=6, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(params=DATA, stages=st.sampled_from([["ingest", "identify"], ["ingest", "discover"],
                                            ["ingest", "identify", "discover"]]))
def test_identify_and_discover_on_generated_data_end_cleanly(tmp_path_factory, params, stages):
    root = write_synthetic_dataset(tmp_path_factory.mktemp("gen") / "data", **params)
    _analyse(root, stages)


@pytest.mark.parametrize("effect", ["backlash:width_deg=2", "saturation:side=supply,q_max_mm3_s=3000",
                                    "pressure_law:side=drain,exponent=0.8"])
def test_discover_on_a_few_simulated_steps_with_an_effect_ends_cleanly(tmp_path, effect):
    """A handful of the simulator's flow steps (fewer than discovery needs,
    and just enough) with an effect: a result or a clear error."""
    import shutil

    from seanv_analysis.sim import simulate_scenario

    data = simulate_scenario("paper-flowsteps-small", tmp_path / "d", seed=2, effects=[effect])
    runs = sorted(p for p in data.iterdir() if p.is_dir())
    for keep in (8, 20):
        sub = tmp_path / f"sub{keep}"
        sub.mkdir()
        for p in runs[:keep]:
            shutil.copytree(p, sub / p.name)
        _analyse(sub, ["ingest", "discover"])
