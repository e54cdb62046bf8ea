"""The process set-up of the CLI and the workers (:mod:`seanv_analysis.batch.process_setup`)."""
from __future__ import annotations

import pytest

REPLAY_FAULTS = """
import resource, sys
from seanv_analysis.batch.process_setup import return_large_blocks_to_os
return_large_blocks_to_os()
from seanv_analysis.config import load_rig
from seanv_analysis.identify.closedloop import flow_sse, replay_on_twin, replay_targets, with_bulk
from seanv_analysis.io.reader import read_run
from seanv_analysis.models import ValveModel
rig = load_rig()
tg = replay_targets([read_run(sys.argv[1], rig=rig)], rig)
valve = ValveModel.from_rig(rig)
replay_on_twin(tg, valve, rig)
f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
sse = [flow_sse(replay_on_twin(tg, valve, with_bulk(rig, 100.0 + i)))[0] for i in range(5)]
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0, sse[0])
"""


@pytest.mark.skipif(not __import__("sys").platform.startswith("linux"), reason="glibc")
def test_replays_reuse_the_heap_instead_of_faulting_it_in_again(golden_data):
    """The CLI's and the workers' malloc keeps freed heap for the next
    replay (:func:`~seanv_analysis.batch.process_setup.return_large_blocks_to_os`):
    a replay of a 95 s position-control run took about 3500 minor page
    faults before (its columns, overlay and derived signals made and freed
    each time), a handful now."""
    import subprocess
    import sys

    run = sorted((golden_data / "position").iterdir())[0]
    out = subprocess.run([sys.executable, "-c", REPLAY_FAULTS, str(run)], check=True,
                         capture_output=True, text=True).stdout.split()
    faults, sse = int(out[0]), float(out[1])
    assert faults < 5 * 500, faults
    assert sse > 0
