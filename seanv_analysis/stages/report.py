"""Stage ``report``: one self-contained ``report.html`` of the whole run.

The parameters with 95 % intervals beside the paper's, tracking numbers, the
validation table, the discovery verdict with the held-out error before and
after, the figures (from the registry in :mod:`seanv_analysis.plots`), the
excluded and failed runs, and provenance
(:func:`seanv_analysis.report.write_report`).
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path, PurePath
from typing import Any, Mapping

from .base import Context

__all__ = ["NAME", "NEEDS", "WRITES", "OPTIONS", "ReportResult", "check_option", "run", "write"]

NAME = "report"
ORDER = 100
NEEDS = ("ingest",)
FOLDER = "."
ROLE = "report"
RESULTS = ()
WRITES = ("report.html", "manifest.json")
DESCRIPTION = "one self-contained report.html: numbers, figures, failed runs, provenance"
#: filename: name of the HTML file inside the output folder
OPTIONS: dict[str, Any] = {"filename": "report.html"}
#: what ``filename`` may be: a plain file name in the output folder
REPORT_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,99}\.html")


def check_option(key: str, value: Any) -> Any:
    if key == "filename":
        if not isinstance(value, str) or not REPORT_NAME.fullmatch(value) \
                or PurePath(value).name != value:
            raise ValueError("a file name ending in .html (letters, digits, '.', '_', '-'; "
                             "no folder part)")
    return value


@dataclass(frozen=True)
class ReportResult:
    """The pipeline record the report renders and the file name to write."""

    record: Any
    filename: str = "report.html"

    def to_json_dict(self) -> dict[str, Any]:
        return {"filename": self.filename}


def run(ctx: Context, options: Mapping[str, Any]) -> ReportResult:
    """The record of the run so far (``ctx.record``, kept by the batch runner)."""
    opts = {**OPTIONS, **options}
    return ReportResult(ctx.record, opts["filename"])


def write(result: ReportResult, folder: Path) -> list[Path]:
    """``report.html`` in ``folder``.

    Raises
    ------
    ConfigError
        the file name would put the report anywhere but directly in
        ``folder`` (checked again here, after :func:`check_option`, on the
        resolved path: a result built by hand passes no option check).
    """
    from ..errors import ConfigError
    from ..report import write_report

    try:
        name = check_option("filename", result.filename)
    except ValueError as exc:
        raise ConfigError(f"report: filename = {result.filename!r}; expected {exc}") from None
    target = Path(folder).resolve() / name
    if target.parent != Path(folder).resolve():
        raise ConfigError(f"report: {name!r} resolves outside the output folder {folder}")
    from .catalogue import report_sections

    return [Path(write_report(result.record, target, report_sections()))]
