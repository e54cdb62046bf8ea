"""The recipe for an effect on the plant (docs/architecture.md): two files,
the effect's class (its plant parameter declared by name) and its term in
the kernel (``pp[_NAME]``). Followed here on a copy of the package: a toy
effect that offsets the encoder, simulated by the copy's kernel in a fresh
process.

The kernel runs as the Python source numba compiles (``NUMBA_DISABLE_JIT=1``):
compiling the edited kernel from nothing took 22 s of the suite's CPU for a
term of the same form (``pp[_GAIN_X] * x``) the compiled kernel already has;
the source is the recipe; numba compiles that source as it stands
(``tests/test_compiled.py``: the ahead-of-time kernel equals the JIT bit for bit)."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import seanv_analysis

TOY_EFFECT = '''

@dataclass(frozen=True)
class PositionOffset(Effect):
    """The encoder reads the position plus a constant offset."""

    name: ClassVar[str] = "position_offset"
    PARAMS: ClassVar[dict[str, str]] = {"offset_mm": "offset of the reading [mm]"}
    PLANT_PARAMS: ClassVar[dict[str, tuple[float, str]]] = {
        "POSITION_OFFSET": (0.0, "encoder offset [mm]")}
    SENTENCE: ClassVar[str] = "the encoder reads {offset_mm:.3f} mm off"

    offset_mm: float = 0.5

    def plant_terms(self, terms):
        return terms.plus("POSITION_OFFSET", self.offset_mm)
'''

SCRIPT = """
import json, sys
sys.path.insert(0, sys.argv[1])
from seanv_analysis.sim.run import simulate_flow_step
runs = [simulate_flow_step(side="supply", cam_deg=0.0, load_mpag=0.35, seed=3, effects=e)[0]
        for e in ([], ["position_offset:offset_mm=0.5"])]
x = [r.tables["encoder"]["position_mm"].to_numpy().tolist() for r in runs]
print(json.dumps(x))
"""


@pytest.mark.slow
def test_a_plant_effect_is_its_class_and_its_kernel_term(tmp_path):
    src = Path(seanv_analysis.__file__).parent
    copy = tmp_path / "pkg"
    shutil.copytree(src, copy / "seanv_analysis", ignore=shutil.ignore_patterns("__pycache__"))
    effects = copy / "seanv_analysis" / "models" / "effects.py"
    effects.write_text(effects.read_text() + TOY_EFFECT)                     # file 1
    kernel = copy / "seanv_analysis" / "sim" / "kernel.py"
    text = kernel.read_text()
    text = text.replace("    _GAIN_X,\n", "    _GAIN_X,\n    _POSITION_OFFSET,\n", 1)
    assert "x_meas = pp[_GAIN_X] * x\n" in text
    text = text.replace("x_meas = pp[_GAIN_X] * x\n", "x_meas = pp[_GAIN_X] * x + pp[_POSITION_OFFSET]\n", 1)
    kernel.write_text(text)                                                    # file 2
    env = {**os.environ, "NUMBA_DISABLE_JIT": "1", "SEANV_AOT": "0", "SEANV_NUMBA_CACHE": str(tmp_path / "numba"),
           "SEANV_CACHE_DIR": str(tmp_path / "cache"), "PYTHONDONTWRITEBYTECODE": "1"}
    res = subprocess.run([sys.executable, "-c", SCRIPT, str(copy)], capture_output=True,
                         text=True, env=env, cwd=tmp_path, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    base, offset = json.loads(res.stdout.strip().splitlines()[-1])
    assert len(base) == len(offset) > 100
    res_mm = 0.001   # the encoder's resolution: the offset lands on its grid
    assert all(abs((b2 - b1) - 0.5) <= res_mm + 1e-9 for b1, b2 in zip(base, offset))
