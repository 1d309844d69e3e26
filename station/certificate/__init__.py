"""Calibration certificates (ISO/IEC 17025 section 7.8): ``content`` (what a certificate states, from a
recording and its stored results), ``render`` (Jinja2 HTML, the same HTML to PDF through WeasyPrint).
See docs/certificate.md."""
