"""Benchmarks of seanv-analysis (run with `make bench`)."""
from __future__ import annotations

import importlib
import sys
from pathlib import Path
from types import ModuleType

_TESTS = Path(__file__).resolve().parents[1] / "tests"


def tests_module(name: str) -> ModuleType:
    """A helper module of ``tests/`` that a benchmark shares with the tests
    (e.g. ``sim_rhs``, ``synthetic_flow``); imported as the tests import it."""
    if str(_TESTS) not in sys.path:
        sys.path.insert(0, str(_TESTS))
    return importlib.import_module(name)
