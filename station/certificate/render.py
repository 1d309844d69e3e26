"""The certificate as HTML (its template, ``station.report.render``'s engine), its Bode plot embedded; the PDF is the
same HTML through ``station.report.render.html_to_pdf``."""

from __future__ import annotations

import json
from functools import lru_cache
from typing import Any

from station.report.render import render_template


def bode_uri(content: dict[str, Any]) -> str:
    """The certificate's Bode plot (``validity.bode_svg``) as a data URI, "" without points."""
    if not content.get("response"):
        return ""
    # a function of the points, the model's curve, the unit and k only: drawn once for the same ones
    return _bode_uri(json.dumps([content["response"], content["response_unit"], content.get("bode_model"),
                                 float(content["response_k"])], sort_keys=True))


@lru_cache(maxsize=8)
def _bode_uri(inputs: str) -> str:
    import base64

    import numpy as np

    from station.certificate.validity import bode_svg

    points, unit, m, k = json.loads(inputs)

    def arr(key: str) -> Any:
        return None if m is None or m[key] is None else np.array(m[key])

    model = None if not m else (arr("f_hz"), arr("magnitude"), arr("u_magnitude"), arr("phase_rad"), arr("u_phase_rad"))
    svg = bode_svg(points, unit, model, k)
    return "data:image/svg+xml;base64," + base64.b64encode(svg.encode()).decode()


def certificate_html(content: dict[str, Any]) -> str:
    """The certificate page of ``content.certificate_content(...)``, its Bode plot embedded."""
    return render_template("station.certificate", "certificate.html.j2", c=content, bode=bode_uri(content))
