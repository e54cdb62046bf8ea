"""Self-contained HTML report of a pipeline run (:func:`write_report`); the
sections of the stage results (:mod:`.sections`) are named by the stages."""
from . import sections
from .html import ReportSection, render_report, write_report

__all__ = ["render_report", "write_report", "ReportSection", "sections"]
