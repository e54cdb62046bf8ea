"""The simulator's output by column name, on numpy only (no pandas).

The kernel returns one array per rate (rows = samples, columns =
``kernel.OUT_FAST`` / ``OUT_SLOW``); :class:`Signals` names its columns and
:func:`contract_tables` cuts them into a run's tables (the data contract's
columns, each a contiguous float64 array), which
:class:`~seanv_analysis.io.run_tables.RunTables` turns into DataFrames only
when one is asked for, so ``simulate`` writes its CSV files without pandas.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from ..io.run_tables import RunTables

__all__ = ["Signals", "contract_tables"]

#: the run's tables and their columns, as the data contract orders them
_FAST_TABLES = {"encoder": ("t_s", "position_mm"),
                "pressure": ("t_s", "p_supply_mpag", "p_head_mpag", "p_load_mpag")}
_SLOW_TABLES = {"servo": ("t_s", "cam_cmd_deg", "cam_deg"),
                "controller": ("t_s", "x_ref_mm", "q_ref_mm3_s")}


class Signals:
    """A 2-D kernel output ``data`` (samples x columns) with column ``names``.

    ``signals["t_s"]`` is a column (a contiguous copy, float64);
    ``signals[mask]`` the rows where the boolean ``mask`` holds.
    """

    def __init__(self, data: np.ndarray, names: Sequence[str]):
        self.data = np.asarray(data, dtype=np.float64)
        self.names = tuple(names)

    def __getitem__(self, key):
        if isinstance(key, str):
            return np.ascontiguousarray(self.data[:, self.names.index(key)])
        return Signals(self.data[np.asarray(key)], self.names)

    def __len__(self) -> int:
        return self.data.shape[0]


def contract_tables(fast: Signals, slow: Signals, *, controller: bool) -> RunTables:
    """The run's tables (encoder, pressure, servo and, with ``controller``,
    controller) from the kernel's fast (1 kHz) and slow (100 Hz) outputs."""
    tables = {name: {c: fast[c] for c in cols} for name, cols in _FAST_TABLES.items()}
    tables["servo"] = {c: slow[c] for c in _SLOW_TABLES["servo"]}
    if controller:
        tables["controller"] = {c: slow[c] for c in _SLOW_TABLES["controller"]}
    return RunTables(tables)
