"""The calibration report as PDF: the report's own HTML page (``html.render_report``) through the
HTML-to-PDF engine the certificates use (WeasyPrint, ``station.report.render.html_to_pdf``),
so the PDF says exactly what the page says and nothing runs off the page (the print stylesheet
wraps every table inside the A4 width; images scale to it)."""

from __future__ import annotations

from pathlib import Path

from station.report.html import render_report
from station.report.render import html_to_pdf


def render_report_pdf(recording_path: Path) -> bytes:
    """The report as PDF bytes (the HTML page, plots included, on A4 landscape pages)."""
    return html_to_pdf(render_report(Path(recording_path)))
