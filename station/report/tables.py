"""HTML building blocks of the calibration report, shared by its sections (``html.py``) and the
multi-mass campaign's (``campaign.py``): escaping, number cells that carry their value for machines,
tables, the parameter rows with their expanded uncertainties and the uncertainty budget."""

from __future__ import annotations

import html
from collections.abc import Mapping
from typing import Any

import numpy as np

from station.ident.result import Estimate
from station.report.quantities import COVERAGE_K, fmt_rel, fmt_unc, fmt_value

MEANING = {"S": "sensitivity of the force signal (static limit of S_dyn)", "m_e": "end mass of the transducer",
           "k_f": "transducer stiffness",
           "b_f": "transducer damping", "k_c": "coupling stiffness", "b_c": "coupling damping"}


def esc(x: Any) -> str:
    return html.escape(str(x))


def num(text: str, value: float | None = None, key: str = "") -> str:
    attrs = f' data-value="{float(value)!r}"' if value is not None and np.isfinite(value) else ""
    attrs += f' data-key="{esc(key)}"' if key else ""
    return f'<td class="num"{attrs}>{esc(text)}</td>'


def table(headers: list[str], rows: list[list[str]], cls: str = "") -> str:
    head = "".join(f"<th>{h}</th>" for h in headers)
    body = "".join("<tr>" + "".join(c if c.startswith("<td") else f"<td>{c}</td>" for c in r) + "</tr>"
                   for r in rows)
    return f'<table class="{cls}"><tr>{head}</tr>{body}</table>'


def param_rows(params: Mapping[str, Estimate], prefix: str, ks: Mapping[str, float] | None = None
               ) -> list[list[str]]:
    """Rows of PARAM_HEADERS; ks: the coverage factor per parameter (from its budget's effective
    degrees of freedom, station.ident.coverage), COVERAGE_K where not given."""
    rows = []
    for name, p in params.items():
        unit = esc(p.unit)
        if not p.identifiable or p.value is None:
            why = p.reason or "no value"
            rows.append([esc(name), esc(MEANING.get(name, "")),
                         f'<td colspan="6" class="na" data-key="{prefix}{esc(name)}">not identifiable: {esc(why)}</td>',
                         unit])
            continue
        v, u = float(p.value), p.std
        k = (ks or {}).get(name, COVERAGE_K)
        meaning = esc(MEANING.get(name, "")) + (f' <span class="na">({esc(p.flag)}: {esc(p.reason)})</span>'
                                               if p.flag else "")
        rows.append([esc(name), meaning, num(fmt_value(v, u), v, f"{prefix}{name}"),
                     num(fmt_unc(u), u, f"{prefix}{name}.u"),
                     num(fmt_unc(k * u) if u is not None else "n/a", k * u if u is not None else None,
                         f"{prefix}{name}.U"), num(f"{k:.3g}", k, f"{prefix}{name}.k"),
                     num(fmt_rel(v, k * u if u is not None else None)),
                     num("" if u is None else f"{fmt_value(v, u)} ± {fmt_unc(k * u)}"), unit])
    return rows


PARAM_HEADERS = ["parameter", "meaning", "value", "u (k = 1)", "U = k u (95 %)", "k", "U rel. (%)", "value ± U",
                 "unit"]


def budget_table(budget: dict[str, Any], prefix: str) -> str:
    if not budget:
        return ""
    sources = list(next(iter(budget.values()))["contributions"])
    rows = [[esc(n)] + [num(fmt_unc(b["contributions"].get(s)) if b["contributions"].get(s) is not None
                            else "conditional") for s in sources]
            + [num(fmt_unc(b["combined"]), b["combined"], f"{prefix}{n}"), esc(b.get("unit", ""))]
            for n, b in budget.items()]
    return ("<h3>Uncertainty budget (standard uncertainties, k = 1)</h3>"
            + table(["parameter", *[esc(s) for s in sources], "combined", "unit"], rows))
