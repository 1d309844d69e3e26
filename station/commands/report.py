"""``station report``: a recording's calibration report as HTML or PDF (the same page), optionally
with the GUM Supplement 1 Monte Carlo check of its uncertainty budget."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("report", help="a recording's calibration report as HTML and/or PDF")
    p.add_argument("recording", type=Path, metavar="RECORDING")
    p.add_argument("--html", type=Path, metavar="FILE", help="write the HTML page")
    p.add_argument("--pdf", type=Path, metavar="FILE", help="write the PDF (the same page)")
    p.add_argument("--monte-carlo", type=int, default=0, metavar="N",
                   help="add the GUM Supplement 1 check with N trials (refits; about 3 ms each)")
    p.set_defaults(handler=_run)


def _run(args: argparse.Namespace) -> int:
    from station.errors import StationError
    from station.report.html import render_report
    from station.report.render import html_to_pdf

    if args.html is None and args.pdf is None:
        raise StationError("say where to write the report: --html FILE and/or --pdf FILE")
    if not 0 <= args.monte_carlo <= 100_000:
        raise StationError(f"--monte-carlo: expected 0 to 100000 trials, got {args.monte_carlo}")
    page = render_report(args.recording, monte_carlo=args.monte_carlo)
    if args.html is not None:
        args.html.write_text(page, encoding="utf-8")
        print(f"html: {args.html}")
    if args.pdf is not None:
        args.pdf.write_bytes(html_to_pdf(page))
        print(f"pdf: {args.pdf}")
    return 0
