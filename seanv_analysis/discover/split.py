"""Fit / held-out splits of runs for model discovery.

Wear shows up over time, so the default hold-out is chronological: the
last ``fraction`` of runs (in ``started_at`` order) are held out and never
used for fitting or selection.
"""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np

__all__ = ["chrono_split", "kfold_splits", "permutation_strata", "permuted_run_order",
           "split_position_runs"]


def split_position_runs(runs: Sequence[Any]) -> tuple[list[Any], list[Any]]:
    """(training, held-out) position-control runs: in time order, every other
    run held out (the second, fourth, ...); one run: trained on, none held out."""
    order = sorted(runs, key=lambda r: (str(r.meta.started_at), r.run_id))
    return order[0::2], order[1::2]


def chrono_split(run_index: np.ndarray, *, fraction: float = 0.3,
                 groups: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Boolean masks (fit, heldout): held out are the last ``fraction`` of runs in time order.

    ``run_index`` is the 0-based time order of each row's run (several rows
    may share a run); the cut is at a run boundary. With ``groups`` (e.g.
    the valve side), the cut is made within each group, so a side measured
    in one block early in the day still has held-out runs of its own.
    """
    if not 0.0 < fraction < 1.0:
        raise ValueError(f"fraction: expected 0 < fraction < 1, got {fraction}")
    run_index = np.asarray(run_index)
    held = np.zeros(run_index.shape, bool)
    labels = np.zeros(run_index.shape) if groups is None else np.asarray(groups)
    for g in np.unique(labels):
        in_g = labels == g
        runs = np.unique(run_index[in_g])
        if runs.size < 2:
            continue
        n_hold = min(max(1, int(round(fraction * runs.size))), runs.size - 1)
        held |= in_g & (run_index >= runs[-n_hold])
    return ~held, held


def kfold_splits(run_index: np.ndarray, *, k: int = 5, seed: int = 0):
    """Yield (fit, heldout) boolean masks for k folds over runs (not rows)."""
    if k < 2:
        raise ValueError(f"k: expected k >= 2, got {k}")
    run_index = np.asarray(run_index)
    runs = np.unique(run_index)
    rng = np.random.default_rng(seed)
    folds = np.array_split(rng.permutation(runs), k)
    for fold in folds:
        held = np.isin(run_index, fold)
        yield ~held, held


def permutation_strata(data, *, tol_mpa: float = 0.02) -> list[np.ndarray]:
    """Run indices of ``data`` (a :class:`.static.FlowData`: its side and
    load_mpag) grouped by side and load level (loads within ``tol_mpa``
    of the level's first are one level; runs without a logged load are one
    level of their side).

    Not finer (e.g. the repeats of one cam angle): where a protocol repeats
    an angle right away, its repeats span a few runs only and a run-order
    effect could not show among them."""
    load = np.asarray(data.load_mpag, float)
    load = np.where(np.isfinite(load), load, -1.0)
    groups: list[np.ndarray] = []
    for side in np.unique(data.side):
        rows = np.flatnonzero(data.side == side)
        ordered = rows[np.argsort(load[rows], kind="stable")]
        start = 0
        for k in range(1, ordered.size + 1):
            if k == ordered.size or load[ordered[k]] - load[ordered[start]] > tol_mpa:
                groups.append(ordered[start:k])
                start = k
    return groups


def permuted_run_order(run_index: np.ndarray, strata, rng: np.random.Generator) -> np.ndarray:
    """A copy of ``run_index`` with the run order permuted within each
    stratum (:func:`permutation_strata`: rows of one side and load level),
    the other rows as they are: a replicate of the data for a test of a
    run-order effect."""
    order = run_index.copy()
    for idx in strata:
        order[idx] = run_index[rng.permutation(idx)]
    return order
