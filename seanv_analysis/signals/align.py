"""Signal utilities on sampled logs: putting streams on one time base.

Streams of one run come at different rates (encoder and pressure 1 kHz,
servo and controller 100 Hz) and start at different instants;
:func:`align_streams` puts them on a common time base without inventing data
outside the span every stream covers.
"""
from __future__ import annotations

from typing import Collection, Mapping

import numpy as np
import pandas as pd

from ..errors import DataError
from ..io.contract import contract_columns
from ..io.run import Run
from ..io.run_tables import table_columns

__all__ = ["align_streams", "align_columns", "align_run", "align_run_columns",
           "interp_sorted", "same_clock", "HOLD_COLUMNS"]

#: Commands: piecewise constant between samples (the controller holds them),
#: so they are aligned with previous-value hold, never interpolated.
HOLD_COLUMNS = frozenset({"cam_cmd_deg", "x_ref_mm", "q_ref_mm3_s"})


def align_streams(streams: Mapping[str, pd.DataFrame], *, t_s: np.ndarray | None = None,
                  base: str = "encoder", hold: Collection[str] = HOLD_COLUMNS,
                  time_column: str = "t_s") -> pd.DataFrame:
    """Put several sampled streams on one time base.

    Parameters
    ----------
    streams : {name: DataFrame or {column: array}}; each has the time column
        ``t_s`` [s] (strictly increasing, as the reader guarantees) and
        numeric value columns. Value column names must be unique across
        streams.
    t_s : time base [s], optional. Default: the ``base`` stream's own
        timestamps inside the overlap. Instants outside the overlap are
        dropped (never extrapolated); the order of the others is kept.
    base : name of the stream whose timestamps are the default time base
        (the encoder's, the fastest stream of the rig).
    hold : columns aligned by previous-value hold (commands: cam_cmd_deg,
        x_ref_mm, q_ref_mm3_s); every other column is linearly interpolated.
    time_column : name of the time column.

    Returns
    -------
    DataFrame with ``t_s`` first, then every value column of every stream in
    stream order; one row per kept instant.

    Notes
    -----
    The overlap is ``[max_k t_k[0], min_k t_k[-1]]`` over the streams k.
    At an instant t, a measurement column gives
    ``v_i + (v_{i+1} - v_i) (t - t_i) / (t_{i+1} - t_i)`` with
    ``t_i <= t <= t_{i+1}``; a held column gives ``v_i`` with the largest
    ``t_i <= t``. A NaN sample (empty nullable column) gives NaN in the
    intervals it bounds. On the default time base the base stream's columns
    are taken as they are (bit-exact; from a float64 DataFrame they are
    copy-on-write views, so they cost no memory until written).

    Raises
    ------
    DataError
        a stream is empty or the streams' time spans do not overlap.
    ValueError
        ``base`` missing (with ``t_s`` None), a column name repeated across
        streams, or a non-numeric column.

    Examples
    --------
    >>> enc = pd.DataFrame({"t_s": [0.0, 0.001, 0.002, 0.003], "position_mm": [0., 1., 2., 3.]})
    >>> servo = pd.DataFrame({"t_s": [0.0005, 0.0025], "cam_cmd_deg": [-15.0, -8.0]})
    >>> align_streams({"encoder": enc, "servo": servo})
         t_s  position_mm  cam_cmd_deg
    0  0.001          1.0        -15.0
    1  0.002          2.0        -15.0
    """
    out, base_slice = _align(streams, t_s=t_s, base=base, hold=hold, time_column=time_column)
    if base_slice is not None:
        stream = streams[base]
        cols = [c for c in _keys(stream) if c != time_column]
        if isinstance(stream, pd.DataFrame) and all(
                stream[c].dtype == np.float64 for c in (time_column, *cols)):
            # copy-on-write views of the base frame: no copy until written
            view = stream.iloc[base_slice].reset_index(drop=True)
            out[time_column] = view[time_column]
            out.update((c, view[c]) for c in cols)
        else:  # the frame owns its columns (the caller's arrays are not written through it)
            out[time_column] = np.array(out[time_column], dtype=np.float64)
            out.update((c, np.array(out[c], dtype=np.float64)) for c in cols)
    return pd.DataFrame(out, copy=False)


def align_columns(streams: Mapping[str, Mapping[str, np.ndarray]], *,
                  t_s: np.ndarray | None = None, base: str = "encoder",
                  hold: Collection[str] = HOLD_COLUMNS,
                  time_column: str = "t_s") -> dict[str, np.ndarray]:
    """:func:`align_streams` on numpy arrays, without pandas: {column: array},
    ``t_s`` first, then every value column in stream order.

    Same parameters, arithmetic, errors and numbers as :func:`align_streams`;
    on the default time base the base stream's columns are views of its
    arrays (read them, do not write).
    """
    return _align(streams, t_s=t_s, base=base, hold=hold, time_column=time_column)[0]


def _keys(stream) -> list[str]:
    return list(stream.columns if isinstance(stream, pd.DataFrame) else stream.keys())


def _align(streams, *, t_s, base, hold, time_column) -> tuple[dict[str, np.ndarray], slice | None]:
    """The columns of :func:`align_streams` (the base stream's as views of
    its arrays) and the slice of the base stream kept (None for a given ``t_s``)."""
    if not streams:
        raise ValueError("streams: expected at least one stream")
    columns: dict[str, dict[str, np.ndarray]] = {}
    times: dict[str, np.ndarray] = {}
    seen: dict[str, str] = {}
    for name, stream in streams.items():
        keys = _keys(stream)
        if time_column not in keys:
            raise ValueError(f"streams['{name}']: no '{time_column}' column")
        cols = {}
        for col in keys:
            values = np.asarray(stream[col])
            if values.dtype.kind not in "biuf":
                raise ValueError(f"streams['{name}']: column '{col}' is not numeric "
                                 f"({values.dtype})")
            if col == time_column:
                continue
            if col in seen:
                raise ValueError(f"streams: column '{col}' is in both '{seen[col]}' and '{name}'")
            seen[col] = name
            cols[col] = values
        t = np.asarray(stream[time_column], dtype=np.float64)
        if t.size == 0:
            raise DataError(f"stream '{name}' has no samples; expected at least one")
        times[name], columns[name] = t, cols
    lo = max(float(t[0]) for t in times.values())
    hi = min(float(t[-1]) for t in times.values())
    if lo > hi:
        spans = ", ".join(f"{n} {t[0]:g}..{t[-1]:g} s" for n, t in times.items())
        raise DataError(f"streams do not overlap in time ({spans}); expected a common span")

    base_slice = None
    if t_s is None:
        if base not in times:
            raise ValueError(f"base: no stream named '{base}' (streams: {', '.join(times)})")
        tb = times[base]
        i0 = int(np.searchsorted(tb, lo, side="left"))
        i1 = int(np.searchsorted(tb, hi, side="right"))
        base_slice = slice(i0, i1)
        t = tb[base_slice]
    else:
        t = np.asarray(t_s, dtype=np.float64).ravel()
        t = t[(t >= lo) & (t <= hi)]  # NaN fails both and is dropped too

    t_sorted = base_slice is not None or bool(np.all(t[1:] >= t[:-1]))
    out: dict[str, np.ndarray] = {}
    hold = set(hold)
    for name, cols in columns.items():
        tk = times[name]
        if base_slice is not None and name == base:
            out[time_column] = t
            out.update((c, np.asarray(v, dtype=np.float64)[base_slice]) for c, v in cols.items())
            continue
        counts = idx = None
        same = same_clock(t, tk)  # once for all the stream's columns
        for c, v in cols.items():
            v = np.asarray(v, dtype=np.float64)
            if v.size and v.strides[0] == 0:
                # a constant column (e.g. the reader's default p_tank): stays a
                # zero-stride view, as interpolation or hold would give
                out[c] = np.broadcast_to(v[:1], t.shape)
            elif c not in hold:
                out[c] = _interp_on(t, tk, v, same)
            elif t_sorted:
                if counts is None:
                    # sample i holds over t in [t_i, t_{i+1}); t >= lo >= tk[0]
                    starts = np.searchsorted(t, tk, side="left")
                    counts = np.diff(starts, append=t.size)
                out[c] = np.repeat(v, counts)
            else:
                if idx is None:
                    idx = np.searchsorted(tk, t, side="right") - 1  # largest t_i <= t
                out[c] = v[idx]
    if time_column not in out:
        out[time_column] = np.array(t, dtype=np.float64)
    out = {time_column: out.pop(time_column), **out}
    return out, base_slice


def align_run(run: Run, *, t_s: np.ndarray | None = None) -> pd.DataFrame:
    """All streams of a run on one time base.

    Parameters
    ----------
    run : a run as the reader returns it
    t_s : time base [s], optional. Default: the encoder's timestamps
        inside the overlap of every table's time span.

    Returns
    -------
    DataFrame: ``t_s`` [s], position_mm, p_supply/head/load/tank_mpag,
    cam_cmd_deg, cam_deg (and x_ref_mm, q_ref_mm3_s for position_control).
    Measurements are linearly interpolated; commands (cam_cmd_deg,
    x_ref_mm, q_ref_mm3_s) hold their previous value; nothing is
    extrapolated (instants outside the overlap are dropped). Extra and
    raw columns of the files are not included.

    See :func:`align_streams`.
    """
    streams = {}
    for name, df in run.tables.items():
        try:
            wanted = contract_columns(name)
        except KeyError:
            continue
        cols = [c for c in wanted if c in df.columns]
        streams[name] = df if list(df.columns) == cols else df[cols]  # CoW: no copy
    base = "encoder" if "encoder" in streams else next(iter(streams))
    return align_streams(streams, t_s=t_s, base=base)


def align_run_columns(run: Run, *, t_s: np.ndarray | None = None,
                      columns: Collection[str] | None = None) -> dict[str, np.ndarray]:
    """:func:`align_run` as {column: numpy array}, without pandas (the run's
    tables' DataFrames are not built): the same columns and numbers. On the
    encoder's time base its columns are views of the run's arrays (read
    them, do not write). ``columns``: only these value columns (and
    ``t_s``), on the same time base as all of them (every stream still
    bounds it)."""
    streams = {}
    for name in run.tables:
        try:
            wanted = contract_columns(name)
        except KeyError:
            continue
        cols = table_columns(run.tables, name)
        streams[name] = {c: cols[c] for c in wanted
                         if c in cols and (columns is None or c == "t_s" or c in columns)}
    base = "encoder" if "encoder" in streams else next(iter(streams))
    return align_columns(streams, t_s=t_s, base=base)


def same_clock(t: np.ndarray, tk: np.ndarray) -> slice | None:
    """The slice of ``tk`` equal to ``t`` when ``t`` is a contiguous run of
    ``tk`` (two streams on one clock), else None."""
    if not t.size or tk.size < t.size:
        return None
    i0 = int(np.searchsorted(tk, t[0], side="left"))
    if i0 + t.size <= tk.size and tk[i0] == t[0] and tk[i0 + t.size - 1] == t[-1] \
            and np.array_equal(tk[i0:i0 + t.size], t):
        return slice(i0, i0 + t.size)
    return None


def interp_sorted(t: np.ndarray, tk: np.ndarray, v: np.ndarray, *,
                  copy: bool = True) -> np.ndarray:
    """``np.interp(t, tk, v)`` (increasing ``tk``, ends held), except that
    where ``t`` is a contiguous run of ``tk`` (one clock) the samples are
    taken as they are: a copy, or with ``copy=False`` a view of ``v``.

    np.interp per column is also the fastest route on long logs: its search
    starts from the previous answer and it allocates only the result (and
    the slopes); sharing one bracketing search between the columns of a
    stream needed ~25 temporaries of the log's length, whose first touch in
    a fresh process cost more than the searches saved.
    """
    t = np.asarray(t, np.float64)
    tk = np.asarray(tk, np.float64)
    v = np.asarray(v, np.float64)
    one_d = t.ndim == 1 and tk.ndim == 1 and v.shape == tk.shape
    return _interp_on(t, tk, v, same_clock(t, tk) if one_d else None, copy=copy)


def _interp_on(t: np.ndarray, tk: np.ndarray, v: np.ndarray, same: slice | None, *,
               copy: bool = True) -> np.ndarray:
    """:func:`interp_sorted` of float64 arrays given ``same = same_clock(t,
    tk)`` (None: interpolate), so the columns of one stream compare the
    clocks once."""
    if same is not None and v.shape == tk.shape:
        return np.array(v[same]) if copy else v[same]
    return np.interp(t, tk, v)
