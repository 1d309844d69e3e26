"""Calibration report of a run: result plots (PNG), an HTML page and a figure-based PDF.

Modules: ``data`` (what a report needs from a recording: the identification, H(f), the per-step
signals, the discrepancy result; cached per file version), ``quantities`` (dynamic sensitivity and
its uncertainty, number formatting), ``plots`` (``PLOT_NAMES``, ``render_plot``), ``html``
(``render_report``) and ``pdf`` (``render_report_pdf``).  See docs/report.md.

Importing this package loads none of them (the daemon lists ``PLOT_NAMES`` from ``names`` without
matplotlib); the names below load their module on first use.
"""

from __future__ import annotations

import importlib
from typing import Any

from station.report.names import PLOT_NAMES

_LAZY = {"render_plot": "station.report.plots", "render_report": "station.report.html",
         "render_report_pdf": "station.report.pdf"}
__all__ = ["PLOT_NAMES", "render_plot", "render_report", "render_report_pdf"]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
