"""Validation of the data contract: run.json and column checks.

Every check raises :class:`~seanv_analysis.errors.DataError` whose message
names the file, the field or column, the row where it applies, the bad value
and what was expected. Rows are 1-based data rows: the header line is not
counted (row 1 is the first line after the header; blank lines, which the
CSV reader skips, are not counted either). Checks are vectorised (numpy);
only the first offending row is reported.
"""
from __future__ import annotations

import json
import math
import os
import re
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..config import RigConfig
from ..errors import DataError
from .contract import contract
from .run import RunMeta

__all__ = ["parse_run_json", "read_run_json", "check_finite", "check_increasing",
           "check_time_plausible", "time_limits_s", "check_link", "check_folder_link",
           "check_pressure", "check_rig_overrides", "format_value", "one_line",
           "max_pressure_mpag"]

_SAFE_ID = re.compile(r"[A-Za-z0-9_][A-Za-z0-9._+=@-]*")


def format_value(value: Any, *, limit: int = 60) -> str:
    """Short printable form of a bad value for an error message."""
    if isinstance(value, float):
        if math.isnan(value):
            return "NaN"
        return repr(value)
    if isinstance(value, (bytes, bytearray)):
        text = repr(bytes(value[:limit]))
    else:
        try:
            text = json.dumps(value, default=str, ensure_ascii=True)
        except (TypeError, ValueError):
            text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def one_line(text: Any) -> str:
    """``text`` (or an exception's message) on one line: runs of blanks and
    line ends become one space, so every error fits one line of a report."""
    return " ".join(str(text).split())


def _as_path(path: str | Path) -> Path:
    """``path`` as a Path; a Path as it is (``Path(path)`` would parse its
    parts again: ~5 us a call, several a run)."""
    return path if isinstance(path, Path) else Path(path)


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _is_finite_number(value: Any) -> bool:
    """A JSON number that is finite as a float (an integer literal too large
    for a float, e.g. 400 digits, is not: ``math.isfinite`` would raise)."""
    if not _is_number(value):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


#: plausibility limit of pressures [MPa gauge] when the rig config has none
_DEFAULT_MAX_PRESSURE_MPAG = 50.0


def max_pressure_mpag(rig: RigConfig) -> float:
    """The rig's ``analysis.max_plausible_pressure_mpag`` [MPa gauge]: larger
    pressures are taken as kPa or Pa written as MPa (default 50)."""
    try:
        return float(rig.analysis.get("max_plausible_pressure_mpag", _DEFAULT_MAX_PRESSURE_MPAG))
    except (KeyError, TypeError, ValueError):
        return _DEFAULT_MAX_PRESSURE_MPAG


#: (max run span, min and max median sample interval) [s] when the rig file
#: has none (data_schema/rig/default.toml [analysis])
_DEFAULT_TIME_LIMITS_S = (3600.0, 1e-6, 0.5)


def time_limits_s(rig: RigConfig) -> tuple[float, float, float]:
    """The rig's ``analysis.max_run_duration_s``, ``min_sample_interval_s``
    and ``max_sample_interval_s`` [s] (see :func:`check_time_plausible`)."""
    keys = ("max_run_duration_s", "min_sample_interval_s", "max_sample_interval_s")
    out = []
    for key, default in zip(keys, _DEFAULT_TIME_LIMITS_S):
        try:
            out.append(float(rig.analysis.get(key, default)))
        except (KeyError, TypeError, ValueError, AttributeError):
            out.append(default)
    return out[0], out[1], out[2]


def check_time_plausible(t: np.ndarray, *, path: str | Path, column: str,
                         limits_s: tuple[float, float, float] = _DEFAULT_TIME_LIMITS_S) -> None:
    """A table's (increasing) timestamps span at most ``limits_s[0]`` and
    step by a median within ``limits_s[1]..limits_s[2]`` [s]: a t_s jump
    (one row's 1e9) or times logged in ms are refused here, before an
    alignment grid over the span is allocated. The row named is the jump's,
    or row 2 for the sample interval."""
    if t.size < 2:
        return
    max_span, lo, hi = limits_s
    span = float(t[-1] - t[0])
    steps = np.diff(t)
    if span <= max_span and lo <= steps.min() and steps.max() <= hi:
        return  # the median lies between the extremes: no sort needed for a good table
    step = float(np.median(steps))
    ms = "; the times look like milliseconds: expected seconds"
    if not lo <= step <= hi:
        hint = ms if lo <= step / 1000.0 <= hi else ""
        raise DataError(f"median sample interval {step:g} s is outside the plausible "
                        f"{lo:g}..{hi:g} s (rig analysis.min/max_sample_interval_s){hint}",
                        path=path, column=column, row=2)
    if span > max_span:
        i = int(np.argmax(steps))
        if steps[i] >= 0.5 * span:   # one jump makes the span
            raise DataError(f"timestamp {float(t[i + 1])!r} is {float(steps[i]):g} s after the "
                            f"previous row's {float(t[i])!r}: the table would span {span:g} s, "
                            f"above the plausible {max_span:g} s (rig analysis.max_run_duration_s)",
                            path=path, column=column, row=i + 2)
        hint = ms if span / 1000.0 <= max_span else ""
        raise DataError(f"the table spans {span:g} s, above the plausible {max_span:g} s (rig "
                        f"analysis.max_run_duration_s){hint}", path=path, column=column,
                        row=int(t.size))


# links --------------------------------------------------------------------

def check_folder_link(run_dir: str | Path) -> None:
    """Refuse a run folder that is a symbolic link (the first check of
    :func:`check_link`).

    Raises
    ------
    DataError
        naming the link (not its target).
    """
    if os.path.islink(run_dir):
        raise DataError("is a symbolic link to a folder; folders inside a data set are not "
                        "followed through links (the runs there are not read): copy or move "
                        "them into the data set, or give the folder itself as DATA",
                        path=Path(run_dir))


def check_link(run_dir: str | Path, path: str | Path) -> None:
    """Refuse a run folder that is a symbolic link, and a file of the run
    (run.json, a table) that is a symbolic link resolving outside the folder
    holding the run (its data set): such links are never followed, so no
    byte of what they point to is read or echoed. Links inside the data set
    are followed.

    Raises
    ------
    DataError
        naming the link (not its target).
    """
    check_folder_link(run_dir)
    if not os.path.islink(path):
        return
    run_dir, path = Path(run_dir), Path(path)
    base = Path(os.path.realpath(run_dir)).parent
    target = Path(os.path.realpath(path))   # never raises (a looping link is said later)
    if base != target and base not in target.parents:
        raise DataError("is a symbolic link to a file outside the data set; links out of the "
                        "data set are not followed (copy the file into the run folder)",
                        path=path)


# run.json -----------------------------------------------------------------

def read_run_json(run_dir: str | Path, *, max_pressure_mpag: float = math.inf) -> RunMeta:
    """Read and validate ``<run_dir>/run.json``.

    Raises
    ------
    DataError
        run.json missing, not UTF-8 JSON, not an object, or breaking the
        contract (see :func:`parse_run_json`).
    """
    run_dir = _as_path(run_dir)
    path = run_dir / "run.json"
    check_link(run_dir, path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise DataError("missing; expected a run folder holding run.json "
                        "(metadata) and encoder, pressure, servo tables", path=path) from None
    except IsADirectoryError:
        raise DataError("is a folder; expected a JSON file", path=path) from None
    except OSError as exc:
        raise DataError(f"cannot read file ({exc.strerror}); expected a readable JSON file",
                        path=path) from None
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise DataError(f"not UTF-8 text (byte {format_value(raw[exc.start:exc.start + 4])} at "
                        f"offset {exc.start}); expected a JSON object", path=path) from None
    try:
        obj = json.loads(text)
    except json.JSONDecodeError as exc:
        raise DataError(f"not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg}); "
                        'expected a JSON object like {"schema": "seanv-run/1", "run_id": ...}',
                        path=path) from None
    except RecursionError:
        raise DataError("not usable JSON (nested too deeply); expected a JSON object like "
                        '{"schema": "seanv-run/1", "run_id": ...}', path=path) from None
    except ValueError as exc:  # e.g. an integer literal of more than 4300 digits
        raise DataError(f"not usable JSON ({one_line(exc)[:120]}); expected a JSON object like "
                        '{"schema": "seanv-run/1", "run_id": ...}', path=path) from None
    return parse_run_json(obj, path=path, max_pressure_mpag=max_pressure_mpag)


def parse_run_json(obj: Any, *, path: str | Path, max_pressure_mpag: float = math.inf) -> RunMeta:
    """Validate the decoded content of a run.json against the contract.

    Parameters
    ----------
    obj : decoded JSON
    path : the run.json path (named in messages; its folder is the run folder)
    max_pressure_mpag : plausibility limit for ``load_mpag`` [MPa gauge]

    Raises
    ------
    DataError
        wrong schema version, unknown kind, missing or mistyped field,
        flow_step without side or cam_deg, position_control without
        controller, bad started_at, unsafe run_id.
    """
    path = _as_path(path)
    terms = contract()
    spec = terms["run_json"]

    def fail(field: str, message: str):
        raise DataError(f"field '{field}': {message}", path=path)

    if not isinstance(obj, dict):
        raise DataError(f"top level is a JSON {type(obj).__name__}; expected a JSON object "
                        '{"schema": "seanv-run/1", ...}', path=path)
    for name in spec["required"]:
        if name not in obj:
            fail(name, f"missing; required fields are {', '.join(spec['required'])}")

    schema = obj["schema"]
    if schema != terms["schema"]:
        fail("schema", f"{format_value(schema)} is not supported; expected "
                       f"'{terms['schema']}' (data contract version 1)")

    run_id = obj["run_id"]
    if not isinstance(run_id, str) or not _SAFE_ID.fullmatch(run_id) or len(run_id) > 200:
        fail("run_id", f"{format_value(run_id)} is not a safe file name; expected letters, "
                       "digits and . _ - + = @ (not starting with '.' or '-', no '/')")

    kind = _enum_text(obj["kind"], terms["run_kinds"])
    if kind not in terms["run_kinds"]:
        fail("kind", f"{format_value(kind)} is unknown; expected one of "
                     f"{', '.join(terms['run_kinds'])}")

    started_at = _parse_started_at(obj["started_at"], fail)

    load = obj.get("load_mpag")
    if load is not None:
        if not _is_finite_number(load):
            fail("load_mpag", f"{format_value(load)} is not a finite number; expected "
                              "MPa gauge or null (load varies, read p_load_mpag)")
        if abs(load) > max_pressure_mpag:
            fail("load_mpag", f"{format_value(load)} is above the plausible {max_pressure_mpag:g} "
                              "MPaG (rig analysis.max_plausible_pressure_mpag): looks like kPa "
                              "or Pa; expected MPa gauge")
        load = float(load)

    for name in terms["run_json"]["required_by_kind"].get(kind, []):
        if name not in obj or obj[name] is None:
            fail(name, f"missing; required for kind '{kind}'")

    side = _enum_text(obj.get("side"), terms["sides"])
    cam = obj.get("cam_deg")
    if kind == "flow_step":
        if side not in terms["sides"]:
            fail("side", f"{format_value(side)} is unknown; expected one of "
                         f"{', '.join(terms['sides'])}")
        if not _is_finite_number(cam):
            fail("cam_deg", f"{format_value(cam)} is not a finite number; expected the "
                            "commanded cam angle [deg]")
        cam = float(cam)
    else:
        side = side if side in terms["sides"] else None
        cam = float(cam) if _is_finite_number(cam) else None

    controller = obj.get("controller")
    if kind == "position_control":
        controller = _check_controller(controller, fail)
    elif not isinstance(controller, dict):
        controller = None

    rig = obj.get("rig", {})
    if rig is None:
        rig = {}
    if not isinstance(rig, dict):
        fail("rig", f"{format_value(rig)} is not an object; expected rig-config overrides "
                    'with the rig file\'s nesting, e.g. {"supply": {"pressure_mpag": 3.2}}')

    known = set(spec["required"]) | set(spec["optional"])
    extra = {k: v for k, v in obj.items() if k not in known}
    return RunMeta(run_id=run_id, kind=kind, started_at=started_at, path=path.parent,
                   load_mpag=load, side=side, cam_deg=cam, controller=controller,
                   rig_overrides=rig, extra=extra)


def _enum_text(value: Any, choices) -> Any:
    """``value`` as the contract spells it when it differs only in case or
    surrounding blanks ("Supply", " drain"); otherwise unchanged."""
    if isinstance(value, str):
        key = value.strip().lower()
        for choice in choices:
            if key == choice.lower():
                return choice
    return value


#: instants a summary table can hold (pandas datetime64[ns])
_EARLIEST = datetime(1677, 9, 22, tzinfo=timezone.utc)
_LATEST = datetime(2262, 4, 11, tzinfo=timezone.utc)


def _parse_started_at(value: Any, fail) -> datetime:
    if not isinstance(value, str):
        fail("started_at", f"{format_value(value)} is not a string; expected an ISO 8601 "
                           "time like '2026-03-02T10:14:05Z'")
    try:
        dt = datetime.fromisoformat(value.strip())
    except ValueError:
        fail("started_at", f"{format_value(value)} is not an ISO 8601 time; expected e.g. "
                           "'2026-03-02T10:14:05Z'")
    # A time without zone is taken as UTC (documented in read_run).
    try:
        dt = dt.replace(tzinfo=timezone.utc) if dt.tzinfo is None else dt.astimezone(timezone.utc)
    except OverflowError:  # e.g. 9999-12-31T23:59:59-23:59 is past year 9999 in UTC
        dt = None
    if dt is None or not _EARLIEST <= dt <= _LATEST:
        fail("started_at", f"{format_value(value)} is out of range; expected a time between "
                           f"{_EARLIEST.year + 1} and {_LATEST.year - 1} like "
                           "'2026-03-02T10:14:05Z'")
    return dt


def _check_controller(controller: Any, fail) -> dict[str, Any]:
    spec = contract()["run_json"]["controller"]
    if not isinstance(controller, dict):
        fail("controller", f"{format_value(controller)} is not an object; expected "
                           '{"kp": 480, "flow_model": true, "rate_hz": 100}')
    for name in spec["required"]:
        if name not in controller:
            fail(f"controller.{name}", "missing; required for kind 'position_control'")
    kp = controller["kp"]
    if not _is_finite_number(kp):
        fail("controller.kp", f"{format_value(kp)} is not a finite number; expected the "
                              "proportional gain (mm^3/s per mm with the flow model, deg per mm without)")
    if not isinstance(controller["flow_model"], bool):
        fail("controller.flow_model", f"{format_value(controller['flow_model'])} is not a "
                                      "boolean; expected true or false")
    rate = controller.get("rate_hz")
    if rate is not None and (not _is_finite_number(rate) or not rate > 0):
        fail("controller.rate_hz", f"{format_value(rate)} is not a positive number; "
                                   "expected the control rate [Hz]")
    return dict(controller)


def check_rig_overrides(overrides: Mapping[str, Any], base: Mapping[str, Any], *,
                        path: str | Path, where: str = "rig") -> None:
    """Check run.json "rig" overrides against the rig config and its schema
    (:func:`seanv_analysis.config.check_rig`): every key must exist there,
    tables must stay tables, each value of its type and within its range, and
    the keys a run may not change (the plausibility guards of
    ``analysis``) left alone.

    Raises
    ------
    DataError
        naming the dotted key (``rig.valve.supply.z0_mm``), the bad value and
        what is expected (the keys that exist at that level, for an unknown one).
    """
    from ..config import rig_key_is_run_json, rig_value_problem

    for key, value in overrides.items():
        here = f"{where}.{key}"
        if key not in base:
            known = ", ".join(sorted(base))
            raise DataError(f"field '{here}': unknown rig key; expected one of {known}", path=path)
        ref = base[key]
        if isinstance(ref, Mapping):
            if not isinstance(value, Mapping):
                raise DataError(f"field '{here}': {format_value(value)} is not an object; "
                                "expected a table of rig keys", path=path)
            check_rig_overrides(value, ref, path=path, where=here)
            continue
        dotted = here.split(".", 1)[1]
        if not rig_key_is_run_json(dotted):
            raise DataError(f"field '{here}': a run may not change this plausibility guard; "
                            "expected it in the rig file (--rig) only", path=path)
        problem = rig_value_problem(dotted, value)
        if problem:
            raise DataError(f"field '{here}': {format_value(value)} {problem}", path=path)


# columns ------------------------------------------------------------------

def check_finite(values: np.ndarray, *, path: str | Path, column: str,
                 nullable: bool = False) -> None:
    """Every value finite (or, for a nullable column, no +-inf).

    An empty cell reads as NaN. ``nullable`` columns (cam_deg, q_ref_mm3_s)
    may be empty, partly or entirely.
    """
    with np.errstate(over="ignore", invalid="ignore"):
        total = np.add.reduce(values)
    if np.isfinite(total):
        return  # one pass, no temporary: any NaN or inf would make the sum non-finite
    bad = np.isinf(values) if nullable else ~np.isfinite(values)
    if not bad.any():
        return  # the sum overflowed, or NaN in a nullable column
    i = int(np.argmax(bad))
    v = float(values[i])
    what = "empty cell or NaN" if math.isnan(v) else f"value {v!r}"
    expect = ("a finite number or an empty cell (column may be empty)" if nullable
              else "a finite number in every row")
    raise DataError(f"{what}; expected {expect}", path=path, column=column, row=i + 1)


def check_increasing(t: np.ndarray, *, path: str | Path, column: str = "t_s") -> None:
    """Timestamps strictly increasing (no repeats, no steps back)."""
    if t.size < 2:
        return
    ok = t[1:] > t[:-1]
    if ok.all():
        return
    i = int(np.argmin(ok))
    a, b = float(t[i]), float(t[i + 1])
    if a == b:
        msg = (f"duplicated timestamp {b!r} (same as row {i + 1}); expected strictly "
               "increasing seconds")
    else:
        msg = (f"timestamp {b!r} is before the previous row's {a!r}: not monotonic; "
               "expected strictly increasing seconds")
    raise DataError(msg, path=path, column=column, row=i + 2)


def check_pressure(values: np.ndarray, *, limit_mpag: float, path: str | Path, column: str,
                   source: str | None = None) -> None:
    """Pressure values within +-``limit_mpag`` [MPa gauge]; larger ones are
    taken as kPa or Pa written in an MPa column (an error, never rescaled)."""
    if values.size == 0 or (np.fmax.reduce(values) <= limit_mpag
                            and np.fmin.reduce(values) >= -limit_mpag):
        return  # fmax/fmin skip NaN (an empty nullable cell is no pressure error)
    bad = np.abs(values) > limit_mpag
    if not bad.any():
        return
    i = int(np.argmax(bad))
    conv = f" (converted from '{source}')" if source else ""
    raise DataError(f"value {float(values[i])!r}{conv} is above the plausible {limit_mpag:g} MPaG "
                    "(rig analysis.max_plausible_pressure_mpag): looks like kPa or Pa; expected "
                    "gauge MPa (give kPa as a p_*_kpag column instead)",
                    path=path, column=column, row=i + 1)
