"""The certificate (and the report) as HTML from Jinja2 templates, and as PDF: the same HTML through
WeasyPrint, so the two never disagree and nothing is cut (tables wrap inside the page width)."""

from __future__ import annotations

import logging
from functools import lru_cache
from typing import Any

from jinja2 import Environment, PackageLoader, StrictUndefined, select_autoescape


@lru_cache(maxsize=1)
def _env() -> Environment:
    return Environment(loader=PackageLoader("station.certificate", "templates"), autoescape=select_autoescape(
        ["html", "j2"]), undefined=StrictUndefined, trim_blocks=True, lstrip_blocks=True)


def render_template(name: str, **values: Any) -> str:
    """A template of ``station/certificate/templates`` rendered (autoescaped) with ``values``."""
    return _env().get_template(name).render(**values)


def bode_uri(content: dict[str, Any]) -> str:
    """The certificate's Bode plot (``validity.bode_svg``) as a data URI, "" without points."""
    import base64

    import numpy as np

    from station.certificate.validity import bode_svg

    if not content.get("response"):
        return ""
    m = content.get("bode_model")
    def arr(key: str) -> Any:
        return None if m is None or m[key] is None else np.array(m[key])

    model = None if not m else (arr("f_hz"), arr("magnitude"), arr("u_magnitude"), arr("phase_rad"), arr("u_phase_rad"))
    svg = bode_svg(content["response"], content["response_unit"], model, float(content["response_k"]))
    return "data:image/svg+xml;base64," + base64.b64encode(svg.encode()).decode()


def certificate_html(content: dict[str, Any]) -> str:
    """The certificate page of ``content.certificate_content(...)``, its Bode plot embedded."""
    return render_template("certificate.html.j2", c=content, bode=bode_uri(content))


def html_to_pdf(html: str) -> bytes:
    """PDF bytes of an HTML page (WeasyPrint; A4 from the page's @page rule)."""
    # one line per layout step otherwise (the import parses its own stylesheets)
    logging.getLogger("weasyprint.progress").setLevel(logging.WARNING)
    from weasyprint import HTML  # heavy: loaded on first use

    return bytes(HTML(string=html).write_pdf())
