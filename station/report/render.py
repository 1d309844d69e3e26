"""HTML pages from Jinja2 templates, and the same HTML as PDF through WeasyPrint: the report's and the
certificate's engine, so the two never disagree and nothing is cut (tables wrap inside the page width)."""

from __future__ import annotations

import logging
from functools import cache, lru_cache
from typing import Any

from jinja2 import Environment, PackageLoader, StrictUndefined, select_autoescape


@cache
def _env(package: str) -> Environment:
    return Environment(loader=PackageLoader(package, "templates"), autoescape=select_autoescape(
        ["html", "j2"]), undefined=StrictUndefined, trim_blocks=True, lstrip_blocks=True)


def render_template(package: str, name: str, **values: Any) -> str:
    """The template ``name`` of ``<package>/templates`` (e.g. ``station.report``) rendered, autoescaped,
    with ``values``."""
    return _env(package).get_template(name).render(**values)


def html_to_pdf(html: str) -> bytes:
    """PDF bytes of an HTML page (WeasyPrint; A4 from the page's @page rule).  The PDFs of the last
    few pages are kept: the same page asked again (a draft certificate, a report served twice) is
    the same bytes, not laid out again (the pages are self-contained: images are data URIs)."""
    return cached_pdf(html)


@lru_cache(maxsize=8)
def cached_pdf(html: str) -> bytes:
    """The cache behind :func:`html_to_pdf` (``cached_pdf.cache_clear()`` drops the up to 8 kept PDFs)."""
    # one line per layout step otherwise (the import parses its own stylesheets)
    logging.getLogger("weasyprint.progress").setLevel(logging.WARNING)
    from weasyprint import HTML  # heavy: loaded on first use

    return bytes(HTML(string=html).write_pdf())
