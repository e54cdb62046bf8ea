"""Declarative pipelines: a TOML file naming the stages to run and their options.

A pipeline file looks like::

    [pipeline]
    name = "paper"
    description = "ingest -> flowfit -> tracking -> validate -> discover -> figures -> report"

    [[stages]]
    name = "ingest"
    method = "steady"          # per-run flow estimate: 'steady' | 'peak'

    [[stages]]
    name = "flowfit"
    sides = ["supply", "drain"]

Each ``[[stages]]`` table has a ``name`` (a stage of the catalogue, :mod:`.catalogue`) and
that stage's options (each stage module's ``OPTIONS``, with their defaults;
:func:`stage_options`). Unknown stages or options are a :class:`~seanv_analysis.errors.ConfigError`
naming the file, the stage and the option, so a typo never runs silently with
a default. Shipped pipelines (``paper``, ``flowfit``, ``tracking``) live in
the package (``pipelines/`` of the source tree) and can be given by name.
"""
from __future__ import annotations

import copy
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from ..errors import ConfigError

__all__ = ["STAGE_NAMES", "stage_options", "Stage", "Pipeline", "load_pipeline",  # noqa: F822
           "parse_pipeline", "shipped_pipelines", "pipelines_dir", "PIPELINE_NAME", "MAX_N_BOOT",
           "MAX_SEED", "check_count"]



def _stages():
    from .catalogue import STAGES
    return STAGES


#: What a pipeline name may be (it becomes part of the folder ``run-<name>``):
#: no separator, no "..", nothing a file system or a terminal would take apart.
PIPELINE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")


def _names() -> tuple[str, ...]:
    return tuple(_stages())


def __getattr__(name: str) -> Any:
    """``STAGE_NAMES``: the catalogue's stage names in the order they run (a
    pipeline lists a subset, in this order); read from the catalogue when
    first asked (the stage modules import this one)."""
    if name == "STAGE_NAMES":
        return tuple(_stages())
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


#: the most bootstrap resamples an option may ask for (each refits the model;
#: 200 by default: 1e9 would run for weeks)
MAX_N_BOOT = 10_000
#: the largest seed (numpy's generators take 0 .. 2**32 - 1 as one word)
MAX_SEED = 2**32 - 1


def check_count(value: Any, *, most: int, what: str = "a whole number") -> int:
    """``value`` as an option's whole number in 0..``most``; ValueError (the
    words of what is expected) otherwise."""
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= most:
        raise ValueError(f"{what} from 0 to {most}")
    return value


def stage_options() -> dict[str, dict[str, Any]]:
    """Known options of each stage and their defaults (from the stage modules)."""
    return {name: copy.deepcopy(mod.OPTIONS) for name, mod in _stages().items()}


def pipelines_dir() -> Path:
    """Folder of the shipped pipelines: the package's ``_pipelines/`` (package
    data, in a wheel too; the source tree's top-level ``pipelines`` is a link
    to it)."""
    return Path(__file__).resolve().parents[1] / "_pipelines"


def shipped_pipelines() -> dict[str, Path]:
    """{name: path} of the shipped pipeline files."""
    folder = pipelines_dir()
    if not folder.is_dir():
        return {}
    return {p.stem: p for p in sorted(folder.glob("*.toml"))}


@dataclass(frozen=True)
class Stage:
    """One stage of a pipeline: its name and its options (defaults filled in)."""

    name: str
    options: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, **copy.deepcopy(self.options)}


@dataclass(frozen=True)
class Pipeline:
    """A validated pipeline: name, description, stages in run order and the
    file it came from (None when built from a dict)."""

    name: str
    description: str
    stages: tuple[Stage, ...]
    source: Path | None = None

    def stage(self, name: str) -> Stage | None:
        """The stage called ``name``, or None when the pipeline lacks it."""
        for s in self.stages:
            if s.name == name:
                return s
        return None

    @property
    def stage_names(self) -> list[str]:
        return [s.name for s in self.stages]

    def to_dict(self) -> dict[str, Any]:
        """The pipeline as a TOML-like dict (with defaults filled in)."""
        return {"pipeline": {"name": self.name, "description": self.description},
                "stages": [s.to_dict() for s in self.stages]}


def _check_option(where: str, stage: str, key: str, value: Any) -> Any:
    """The stage's own check of one option (its ValueError says what is expected)."""
    try:
        return _stages()[stage].check_option(key, value)
    except ValueError as exc:
        raise ConfigError(f"{where}: stage '{stage}' option '{key}' = {value!r}; expected {exc}") \
            from None


def _name_from_file(source: str | Path | None) -> str:
    """A pipeline's name when its file gives none: the file's stem, with
    characters a name may not hold replaced by '-'."""
    stem = re.sub(r"[^A-Za-z0-9._-]", "-", Path(source).stem if source else "")[:64]
    stem = stem.lstrip("._-")
    return stem or "pipeline"


def parse_pipeline(doc: Mapping[str, Any], *, source: str | Path | None = None) -> Pipeline:
    """Validate a pipeline document (the parsed TOML) and fill in defaults.

    Parameters
    ----------
    doc : dict with a ``pipeline`` table (``name``, ``description``) and a
        ``stages`` array of tables (``name`` + options)
    source : file it came from, used in error messages

    Returns
    -------
    Pipeline

    Raises
    ------
    ConfigError
        no stages, an unknown stage or option, a stage listed twice, stages
        out of order, a badly typed option.

    Examples
    --------
    >>> p = parse_pipeline({"pipeline": {"name": "x"}, "stages": [{"name": "ingest"}]})
    >>> p.stage("ingest").options
    {'method': 'steady'}
    """
    where = str(source) if source is not None else "pipeline"
    unknown_top = sorted(set(doc) - {"pipeline", "stages"})
    if unknown_top:
        raise ConfigError(f"{where}: unknown table(s) {unknown_top}; expected [pipeline] and [[stages]]")
    head = doc.get("pipeline", {})
    if not isinstance(head, Mapping):
        raise ConfigError(f"{where}: [pipeline] must be a table with name and description")
    name = head.get("name") or _name_from_file(source)
    if not isinstance(name, str) or not PIPELINE_NAME.fullmatch(name):
        raise ConfigError(f"{where}: [pipeline] name = {name!r}; expected a name of letters, "
                          "digits, '.', '_' or '-' (at most 64, starting with a letter or digit): "
                          "it becomes part of the output folder run-<name>")
    description = head.get("description", "")
    if not isinstance(description, str):
        raise ConfigError(f"{where}: [pipeline] description = {description!r}; expected a string")
    raw = doc.get("stages")
    if not isinstance(raw, list) or not raw:
        raise ConfigError(f"{where}: no [[stages]]; expected at least one of {', '.join(_names())}")
    stages: list[Stage] = []
    for i, item in enumerate(raw):
        if not isinstance(item, Mapping) or "name" not in item:
            raise ConfigError(f"{where}: stage #{i + 1} has no name; expected name = one of "
                              f"{', '.join(_names())}")
        sname = item["name"]
        if not isinstance(sname, str) or sname not in _names():
            raise ConfigError(f"{where}: unknown stage '{sname}'; expected one of {', '.join(_names())}")
        if any(s.name == sname for s in stages):
            raise ConfigError(f"{where}: stage '{sname}' is listed twice")
        known = stage_options()[sname]
        options = copy.deepcopy(known)
        for key, value in item.items():
            if key == "name":
                continue
            if key not in known:
                raise ConfigError(f"{where}: stage '{sname}' has unknown option '{key}'; known: "
                                  f"{', '.join(known) or '(none)'}")
            options[key] = _check_option(where, sname, key, value)
        stages.append(Stage(sname, options))
    order = [_names().index(s.name) for s in stages]
    if order != sorted(order):
        raise ConfigError(f"{where}: stages out of order ({', '.join(s.name for s in stages)}); "
                          f"expected the order {' -> '.join(_names())}")
    return Pipeline(name, description, tuple(stages), Path(source) if source else None)


def load_pipeline(pipeline: str | Path | Pipeline | Mapping[str, Any]) -> Pipeline:
    """Load a pipeline from a TOML file, a shipped name (``paper``) or a dict.

    Raises
    ------
    ConfigError
        the file does not exist (and is not a shipped name), is not a
        regular file, not UTF-8, not valid TOML or nested too deeply, or
        fails :func:`parse_pipeline`.
    """
    if isinstance(pipeline, Pipeline):
        return pipeline
    if isinstance(pipeline, Mapping):
        return parse_pipeline(pipeline)
    path = Path(pipeline)
    if not path.is_file():
        shipped = shipped_pipelines()
        if str(pipeline) in shipped:
            path = shipped[str(pipeline)]
        else:
            names = ", ".join(shipped) or "(none found)"
            raise ConfigError(f"pipeline: {pipeline} is neither a file nor a shipped pipeline; "
                              f"shipped: {names}")
    from ..config import read_toml

    # a regular file of at most a few MB, UTF-8, not nested too deeply: else one line
    return parse_pipeline(read_toml(path, what="pipeline"), source=path)
