"""Calibration report of a run: result plots (PNG), an HTML page and a figure-based PDF (issue 6).

Modules: ``data`` (what a report needs from a recording: the identification, H(f), the per-step
signals, the discrepancy result; cached per file version), ``quantities`` (dynamic sensitivity and
its uncertainty, number formatting), ``plots`` (``PLOT_NAMES``, ``render_plot``), ``html``
(``render_report``) and ``pdf`` (``render_report_pdf``).  See docs/report.md.
"""

from station.report.html import render_report
from station.report.pdf import render_report_pdf
from station.report.plots import PLOT_NAMES, render_plot

__all__ = ["PLOT_NAMES", "render_plot", "render_report", "render_report_pdf"]
