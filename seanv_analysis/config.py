"""Rig configuration: load, override and query the rig TOML.

Every rig constant lives in ``data_schema/rig/default.toml``; code reads it
from there and never writes a rig number twice.
"""
from __future__ import annotations

import copy
import math
import os
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from .errors import ConfigError

__all__ = ["RigConfig", "load_rig", "default_rig_path", "schema_dir", "load_contract",
           "user_cache_dir", "private_folder", "BLAS_THREAD_VARIABLES", "default_one_blas_thread"]

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
    """
    default = default_rig_path()
    with open(default, "rb") as fh:
        data = tomllib.load(fh)
    source = "default"
    if path is not None:
        path = Path(path)
        try:
            with open(path, "rb") as fh:
                user = tomllib.load(fh)
        except FileNotFoundError:
            raise ConfigError(f"{path}: rig config not found") from None
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise ConfigError(f"{path}: not a valid TOML file ({exc})") from None
        user.pop("schema", None)
        user.pop("name", None)
        data = _deep_update(data, user, str(path))
        source = str(path)
    rig = RigConfig(data, source=source)
    return rig.with_overrides(overrides) if overrides else rig
