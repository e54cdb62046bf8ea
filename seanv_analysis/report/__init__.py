"""Self-contained HTML report of a pipeline run (:func:`write_report`)."""
from .html import render_report, write_report

__all__ = ["render_report", "write_report"]
