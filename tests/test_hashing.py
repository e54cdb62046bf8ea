"""io.hashing.content_sha256: the content hash of results (figure keys)."""
from __future__ import annotations

import dataclasses
import os
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest

from seanv_analysis.io.hashing import content_sha256


@dataclasses.dataclass
class _Result:
    names: set
    table: pd.DataFrame
    by_load: dict


def _value() -> _Result:
    return _Result({"supply", "drain", "tank"},
                   pd.DataFrame({"q_mm3_s": [1.0, -2.5, np.nan], "side": ["supply", "drain", None]}),
                   {0.3: 512.0, 0.45: np.float64(530.25)})


_SCRIPT = """
import dataclasses, sys
import numpy as np, pandas as pd
sys.path.insert(0, {tests!r})
from test_hashing import _value
from seanv_analysis.io.hashing import content_sha256
print(content_sha256(_value()))
"""


def test_same_content_same_hash_in_another_process():
    """Sets of strings iterate in another order in each process (hash
    randomisation), so a pickle of them differs; the content hash does not."""
    here = content_sha256(_value())
    env = {**os.environ, "PYTHONHASHSEED": "12345"}
    out = subprocess.run([sys.executable, "-c", _SCRIPT.format(tests=os.path.dirname(__file__))],
                         capture_output=True, text=True, env=env, check=True)
    assert out.stdout.strip() == here


def test_any_change_of_content_changes_the_hash():
    base = content_sha256(_value())
    v = _value()
    v.table.loc[1, "q_mm3_s"] = -2.5000000001                 # one value, a few ulps
    assert content_sha256(v) != base
    v = _value()
    v.by_load[0.3] = 513.0
    assert content_sha256(v) != base
    v = _value()
    v.names.add("head")
    assert content_sha256(v) != base
    assert content_sha256([1, 2]) != content_sha256((1, 2)) != content_sha256([1.0, 2.0])
    assert content_sha256(np.arange(3, dtype=np.int32)) != content_sha256(np.arange(3))


def test_unknown_types_are_refused():
    with pytest.raises(TypeError, match="value: cannot hash a object by content"):
        content_sha256({"x": object()})
