"""Rig configuration: load, override and query the rig TOML.

Every rig constant lives in ``data_schema/rig/default.toml``; code reads it
from there and never writes a rig number twice.
"""
from __future__ import annotations

import copy
import functools
import math
import os
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from .errors import ConfigError

__all__ = ["RigConfig", "load_rig", "default_rig_path", "schema_dir", "load_contract",
           "user_cache_dir", "private_folder", "BLAS_THREAD_VARIABLES", "default_one_blas_thread",
           "read_toml", "check_rig", "check_document", "rig_value_problem", "rig_key_is_run_json",
           "value_problem", "load_schema", "read_config_bytes", "MAX_CONFIG_BYTES"]

_PACKAGE_DIR = Path(__file__).resolve().parent


def schema_dir() -> Path:
    """Folder holding the data contract and default rig config: the package's
    ``_data_schema/`` (package data, in a wheel too; the source tree's
    top-level ``data_schema`` is a link to it)."""
    folder = _PACKAGE_DIR / "_data_schema"
    if not (folder / "contract.toml").is_file():
        raise ConfigError(f"{folder}: the package's data contract is missing (a broken install?)")
    return folder


#: environment variables that set the BLAS libraries' thread counts
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS")


def default_one_blas_thread() -> None:
    """One BLAS thread for this process and its children unless the user
    set a count: call before numpy loads (the CLI and the test processes
    do). The package's linear algebra is on small matrices, where extra
    BLAS threads only spin (identify + discover on 2 cores: 36 s CPU for
    22 s with them, 23 s for 23 s without) and make the last bits depend
    on the machine's core count."""
    for var in BLAS_THREAD_VARIABLES:
        os.environ.setdefault(var, "1")


def user_cache_dir() -> Path:
    """Where the package keeps what it can make again (the built-in simulated
    data sets, compiled code): ``$SEANV_CACHE_DIR``, else
    ``$XDG_CACHE_HOME/seanv-analysis``, else ``~/.cache/seanv-analysis``.
    Never a results folder: deleting it only costs time."""
    import os

    env = os.environ.get("SEANV_CACHE_DIR")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "seanv-analysis"


def private_folder(path: str | Path) -> bool:
    """Make ``path`` a folder only this user can enter (mode 0700), or check it.

    Compiled code is loaded from such folders only (the simulator's module,
    numba's cache): a folder another user can write to could hold code of
    theirs. A missing folder is made (and its missing parents, 0700); one of
    this user's with a looser mode is made 0700; a link is followed to its
    target, which is checked.

    Returns
    -------
    bool
        True when the folder existed and others could write to it (made 0700
        now): what it holds may have been put there by someone else and must
        not be trusted (the caller empties it).

    Raises
    ------
    ConfigError
        the path is not a folder, is another user's, or cannot be made or
        changed (the message names it, its owner and mode).
    """
    import stat

    path = Path(path)
    try:
        existed = path.exists()
        path.mkdir(mode=0o700, parents=True, exist_ok=True)
        st = os.stat(path)
    except FileExistsError:
        raise ConfigError(f"{path}: not a folder; expected a folder for the compiled code") \
            from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot make the folder ({exc.strerror or exc})") from None
    if not stat.S_ISDIR(st.st_mode):
        raise ConfigError(f"{path}: not a folder; expected a folder for the compiled code")
    uid = _uid()
    if uid is not None and st.st_uid != uid:
        raise ConfigError(f"{path}: owned by user id {st.st_uid}, not by you (id {uid}), mode "
                          f"{stat.S_IMODE(st.st_mode):04o}; compiled code is loaded only from "
                          "a folder of yours that no one else can write to (delete it or set "
                          "SEANV_CACHE_DIR to a folder of yours)")
    mode = stat.S_IMODE(st.st_mode)
    if mode & 0o077:
        try:
            os.chmod(path, 0o700)
        except OSError as exc:
            raise ConfigError(f"{path}: mode {mode:04o} and it cannot be made 0700 "
                              f"({exc.strerror or exc})") from None
    return existed and bool(mode & 0o022)


def _uid() -> int | None:
    """This process's user id (None where the system has none)."""
    getuid = getattr(os, "getuid", None)
    return getuid() if getuid is not None else None


def default_rig_path() -> Path:
    """Path of the shipped default rig config."""
    return schema_dir() / "rig" / "default.toml"


def load_contract() -> dict[str, Any]:
    """The machine-readable data contract (``data_schema/contract.toml``)."""
    with open(schema_dir() / "contract.toml", "rb") as fh:
        return tomllib.load(fh)


def _deep_update(base: dict, override: Mapping, where: str) -> dict:
    for key, value in override.items():
        if key not in base:
            raise ConfigError(f"{where}: unknown rig key '{key}'")
        if isinstance(base[key], dict):
            if not isinstance(value, Mapping):
                raise ConfigError(f"{where}: rig key '{key}' must be a table")
            _deep_update(base[key], value, f"{where}.{key}")
        else:
            base[key] = value
    return base


@dataclass(frozen=True)
class RigConfig:
    """Rig constants (nested dict from the TOML) with unit-named keys.

    Use ``rig["actuator"]["piston_diameter_mm"]`` or the derived properties.
    """

    data: dict[str, Any]
    source: str = "default"
    _hash: str = field(default="", compare=False)

    def __getitem__(self, key: str) -> Any:
        return self.data[key]

    def __repr__(self) -> str:
        return f"<RigConfig {self.data.get('name', '?')!r} from {self.source}>"

    def with_overrides(self, overrides: Mapping | None, *, where: str = "rig") -> "RigConfig":
        """A copy with ``overrides`` (same nesting as the TOML) applied."""
        if not overrides:
            return self
        data = _deep_update(copy.deepcopy(self.data), overrides, where)
        return RigConfig(data, source=f"{self.source}+overrides")

    # Derived geometry -------------------------------------------------
    @property
    def piston_area_mm2(self) -> float:
        """Water-actuator piston (head-side) area [mm^2]; 201.06 for 16 mm."""
        return math.pi / 4 * self.data["actuator"]["piston_diameter_mm"] ** 2

    @property
    def load_area_mm2(self) -> float:
        """Pneumatic load piston area on which the load pressure acts [mm^2]."""
        return math.pi / 4 * self.data["load"]["piston_diameter_mm"] ** 2

    @property
    def cam_range_deg(self) -> tuple[float, float]:
        """Model's valid cam range [deg] (-40..10 in the paper)."""
        v = self.data["valve"]
        return float(v["cam_min_deg"]), float(v["cam_max_deg"])

    @property
    def analysis(self) -> dict[str, Any]:
        """Procedure settings (filter thresholds, derivative window)."""
        return self.data["analysis"]

    def to_dict(self) -> dict[str, Any]:
        """Plain nested dict (for manifests and JSON)."""
        return copy.deepcopy(self.data)


def load_rig(path: str | Path | None = None, overrides: Mapping | None = None) -> RigConfig:
    """Load a rig config TOML (default: the shipped one), then apply overrides.

    A user file may give only some keys; the rest come from the default.
    The result is checked against the rig schema (:func:`check_rig`).

    Raises
    ------
    ConfigError
        the file is missing, not a TOML file, names another schema, or a
        key is unknown, of the wrong type or outside its range (one line
        naming the file, the key, the value and what is expected).
    """
    default = default_rig_path()
    with open(default, "rb") as fh:
        data = tomllib.load(fh)
    source = "default"
    if path is not None:
        path = Path(path)
        user = read_toml(path, what="rig config")
        for key in ("schema", "name"):
            if key in user:
                problem = rig_value_problem(key, user[key])
                if problem:
                    raise ConfigError(f"{path}: {key} = {_shown(user[key])} {problem}")
        user.pop("schema", None)
        user.pop("name", None)
        data = _deep_update(data, user, str(path))
        source = str(path)
    rig = RigConfig(data, source=source)
    if overrides:
        rig = rig.with_overrides(overrides)
    check_rig(rig.data, where=source if path is not None else "rig")
    return rig


#: the largest configuration file read (rig, pipeline, model)
MAX_CONFIG_BYTES = 16 << 20


def read_config_bytes(path: str | Path, *, what: str) -> bytes:
    """The bytes of the configuration file ``path`` (a ``what`` file: 'rig
    config', 'pipeline', 'valve model'), links followed.

    Raises
    ------
    ConfigError
        missing, unreadable, not a regular file (a FIFO or a device: never
        read, it could block or never end) or larger than
        :data:`MAX_CONFIG_BYTES` (one line naming the file).
    """
    import stat

    path = Path(path)
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except FileNotFoundError:
        raise ConfigError(f"{path}: {what} not found") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the {what} ({exc.strerror or exc})") from None
    with open(fd, "rb") as fh:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise ConfigError(f"{path}: not a regular file; expected a {what} file")
        if st.st_size > MAX_CONFIG_BYTES:
            raise ConfigError(f"{path}: {st.st_size} bytes; expected a {what} file of at most "
                              f"{MAX_CONFIG_BYTES >> 20} MiB")
        return fh.read(MAX_CONFIG_BYTES + 1)


def read_toml(path: str | Path, *, what: str) -> dict[str, Any]:
    """The TOML document of the file ``path`` (:func:`read_config_bytes`).

    Raises
    ------
    ConfigError
        as :func:`read_config_bytes`; or not UTF-8, not TOML, or nested too
        deeply (one line naming the file).
    """
    raw = read_config_bytes(path, what=what)
    try:
        return tomllib.loads(raw.decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not a valid TOML file (not UTF-8: byte {exc.start})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not a valid TOML file ({exc})") from None
    except RecursionError:
        raise ConfigError(f"{path}: not a valid TOML file (nested too deeply)") from None


# The schemas -----------------------------------------------------------------

@functools.lru_cache(maxsize=None)
def load_schema(name: str) -> dict[str, dict[str, Any]]:
    """{dotted key: spec} of ``_data_schema/<name>/schema.toml`` ('rig', 'model')."""
    with open(schema_dir() / name / "schema.toml", "rb") as fh:
        return tomllib.load(fh)["keys"]


def _shown(value: Any) -> str:
    """A value as it appears in a message (short)."""
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _is_number(value: Any) -> bool:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    try:
        return math.isfinite(float(value))
    except OverflowError:
        return False


def _expected(spec: Mapping[str, Any]) -> str:
    """What a key of ``spec`` must be, in words: 'a number > 0 and <= 100 [mm]'."""
    kind = spec["type"]
    if kind == "bool":
        return "true or false"
    if kind == "string":
        return f'"{spec["equals"]}"' if "equals" in spec else "a string"
    noun = {"number": "a finite number", "integer": "an integer",
            "range": "two finite numbers [lo, hi], lo < hi, each"}[kind]
    bounds = []
    if "gt" in spec:
        bounds.append(f"> {spec['gt']:g}")
    if "min" in spec:
        bounds.append(f">= {spec['min']:g}")
    if "lt" in spec:
        bounds.append(f"< {spec['lt']:g}")
    if "max" in spec:
        bounds.append(f"<= {spec['max']:g}")
    unit = f" [{spec['unit']}]" if spec.get("unit") not in (None, "-") else ""
    inf = " (or inf)" if spec.get("inf") else ""
    return f"{noun} {' and '.join(bounds)}{unit}{inf}" if bounds else f"{noun}{unit}{inf}"


def value_problem(spec: Mapping[str, Any], value: Any) -> str | None:
    """What is wrong with ``value`` for a key of ``spec`` (a schema entry),
    as the words after the value ('is not a finite number; expected ...');
    None when it is fine."""
    kind = spec["type"]
    if kind == "bool":
        return None if isinstance(value, bool) else "is not true or false; expected a boolean"
    if spec.get("inf") and value == math.inf and not isinstance(value, bool):
        return None   # a key where +inf means 'never' (e.g. a band never left)
    if kind == "string":
        if not isinstance(value, str):
            return f"is not a string; expected {_expected(spec)}"
        if "equals" in spec and value != spec["equals"]:
            return f"is not a schema this version reads; expected {_expected(spec)}"
        return None
    if kind == "range":
        if (not isinstance(value, list) or len(value) != 2
                or not all(_is_number(v) for v in value)):
            return f"is not two finite numbers; expected {_expected(spec)}"
        if not value[0] < value[1]:
            return f"is not increasing (lo >= hi); expected {_expected(spec)}"
        values = value
    elif kind == "integer":
        if isinstance(value, bool) or not isinstance(value, int):
            return f"is not an integer; expected {_expected(spec)}"
        values = [value]
    else:
        if not _is_number(value):
            return f"is not a finite number; expected {_expected(spec)}"
        values = [value]
    for v in values:
        if spec.get("gt") == 0 and not v > 0:
            return f"is not positive; expected {_expected(spec)}"
        if (("gt" in spec and not v > spec["gt"]) or ("min" in spec and not v >= spec["min"])
                or ("lt" in spec and not v < spec["lt"])
                or ("max" in spec and not v <= spec["max"])):
            return f"is outside the plausible range; expected {_expected(spec)}"
        if spec.get("nonzero") and v == 0:
            return str(spec["nonzero"])
    return None


def check_document(doc: Mapping[str, Any], schema_name: str, *, where: str,
                   required_all: bool = False) -> dict[str, Any]:
    """Check a nested document (a parsed TOML or JSON file) against the
    schema ``schema_name`` (:func:`load_schema`): every key known, each value
    of its type and range, the required keys present (every key with
    ``required_all``, else those marked ``required = true``). A key of type
    "table" may hold anything (it is not looked into); "list" any list.

    Returns
    -------
    dict
        {dotted key: value} of the document's keys.

    Raises
    ------
    ConfigError
        one line: ``where``, the dotted key, its value and what is expected.
    """
    schema = load_schema(schema_name)
    tables = {k.rsplit(".", i)[0] for k in schema for i in range(1, k.count(".") + 1)}
    flat: dict[str, Any] = {}

    def walk(d: Mapping[str, Any], prefix: str) -> None:
        for k, v in d.items():
            key = f"{prefix}{k}"
            if key in schema:
                flat[key] = v
            elif key in tables:
                if not isinstance(v, Mapping):
                    raise ConfigError(f"{where}: {key} = {_shown(v)} is not a table; expected "
                                      f"a table of {', '.join(_below(schema, key))}")
                walk(v, key + ".")
            else:
                level = prefix[:-1]
                known = _below(schema, level) if level else sorted({x.split(".")[0] for x in schema})
                raise ConfigError(f"{where}: unknown key '{key}'; expected one of "
                                  f"{', '.join(known)}")

    walk(doc, "")
    for key, value in flat.items():
        spec = schema[key]
        if spec["type"] == "table":
            problem = None if isinstance(value, Mapping) else "is not a table"
        elif spec["type"] == "list":
            problem = None if isinstance(value, list) else "is not a list"
        else:
            problem = value_problem(spec, value)
        if problem:
            raise ConfigError(f"{where}: {key} = {_shown(value)} {problem}")
    missing = [k for k, spec in schema.items() if k not in flat
               and (spec.get("required") or (required_all and k not in ("schema", "name")))]
    if missing:
        raise ConfigError(f"{where}: {missing[0]} is missing; expected "
                          f"{_expected(schema[missing[0]])}")
    return flat


def _below(schema: Mapping[str, Any], table: str) -> list[str]:
    """The names directly under the dotted ``table`` in ``schema``."""
    n = table.count(".") + 1
    return sorted({k.split(".")[n] for k in schema if k.startswith(table + ".")})


def rig_value_problem(key: str, value: Any) -> str | None:
    """:func:`value_problem` of the rig key ``key`` (dotted, e.g.
    'valve.supply.z0_mm'); 'is not a rig key' for a key the schema lacks."""
    spec = load_schema("rig").get(key)
    if spec is None:
        return "is not a rig key"
    return value_problem(spec, value)


def rig_key_is_run_json(key: str) -> bool:
    """Whether a run.json's "rig" object may change the rig key ``key``."""
    return bool(load_schema("rig").get(key, {}).get("run_json", True))


#: at most this many samples in a run's common time base (max span x encoder rate)
MAX_ALIGNED_SAMPLES = 1e8


def check_rig(data: Mapping[str, Any], *, where: str = "rig") -> None:
    """Check a whole rig (the nested dict of a :class:`RigConfig`) against
    the rig schema (``_data_schema/rig/schema.toml``): every key known and
    present, each of its type and range, and the keys that bound each other
    (cam range, diameters, sample intervals, the aligned samples of a run).

    Raises
    ------
    ConfigError
        one line: ``where``, the dotted key, its value and what is expected.
    """
    flat = check_document(data, "rig", where=where, required_all=True)
    below = [("valve.cam_min_deg", "valve.cam_max_deg", "the model's cam range min < max"),
             ("valve.seat_diameter_mm", "valve.needle_diameter_mm",
              "the seat narrower than the needle (Table II: d_o < d_n)"),
             ("tube.inner_diameter_mm", "tube.outer_diameter_mm", "the tube's bore inside its wall"),
             ("actuator.rod_diameter_mm", "actuator.piston_diameter_mm", "a rod thinner than its piston"),
             ("load.rod_diameter_mm", "load.piston_diameter_mm", "a rod thinner than its piston"),
             ("analysis.min_sample_interval_s", "analysis.max_sample_interval_s",
              "the plausible sample interval's min < max")]
    for lo, hi, what in below:
        if not flat[lo] < flat[hi]:
            raise ConfigError(f"{where}: {lo} = {_shown(flat[lo])} is not below {hi} = "
                              f"{_shown(flat[hi])}; expected {what}")
    samples = flat["analysis.max_run_duration_s"] * flat["sensors.encoder_rate_hz"]
    if samples > MAX_ALIGNED_SAMPLES:
        raise ConfigError(f"{where}: analysis.max_run_duration_s x sensors.encoder_rate_hz = "
                          f"{samples:g} samples on a run's common time base; expected at most "
                          f"{MAX_ALIGNED_SAMPLES:g} (a longer run or faster clock would not fit "
                          "in memory)")
