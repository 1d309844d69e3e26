"""A finding shown on a run's page never contradicts another on the same page: the page's one rule
(``pageFindings`` in the served words.js) in a real headless Chromium, on the findings that used to
contradict each other (a misfit beside "the model explains the measurement", a coupling and a clock
skew each asserted, a model-gap effect beside "nothing needs checking").

The contradictions are judged here by the words a person reads, not by the rule's own code.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.web_support import open_page

# a real browser (launched once for the module; the cases take under a second)
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("web_findings")]

WORDS = Path(__file__).resolve().parent.parent / "station" / "api" / "static" / "words.js"
EXPLAINED = "The transducer model explains the measurement"
NOTHING = "Nothing needs checking."
COUPLING_ASSERTED = "The mounting (coupling) is probably not stiff"
SKEW_ASSERTED = "The two converters' clocks run at slightly different rates."


def _check(name: str, severity: str = "warning") -> dict[str, Any]:
    return {"name": name, "severity": severity, "step": None, "message": f"{name} (details)"}


def _gap(*effects: str, unexplained: tuple[str, ...] = ()) -> dict[str, Any]:
    return {"effects": [{"name": e} for e in effects], "unexplained": list(unexplained)}


@pytest.fixture(scope="module")
def page(browser: object) -> Iterator[Any]:
    """An empty page with the words the daemon serves (the renderer's words and rules, no daemon)."""
    with open_page(browser, "about:blank") as pg:
        pg.add_script_tag(content=WORDS.read_text(encoding="utf-8"))
        yield pg


def _shown(page: Any, checks: list[dict[str, Any]], gap: dict[str, Any] | None) -> tuple[list[str], str, str]:
    out = page.evaluate("([c, g]) => pageFindings(c, g)", [checks, gap])
    return out["lines"], out["gap"] or "", out["tail"]


def _contradictions(checks: list[dict[str, Any]], gap: dict[str, Any] | None, lines: list[str], gap_text: str,
                    tail: str) -> list[str]:
    """What a reader of the page would find contradictory, from the findings themselves."""
    warnings = [c for c in checks if c["severity"] != "info"]
    effects = gap["effects"] if gap else []
    out = []
    if gap_text.startswith(EXPLAINED) and warnings:
        out.append(f"'{EXPLAINED}' beside {[c['name'] for c in warnings]}")
    if tail == NOTHING and (warnings or effects or (gap and gap["unexplained"])):
        out.append(f"'{NOTHING}' beside findings")
    asserted = [s for s in (COUPLING_ASSERTED, SKEW_ASSERTED) if any(s in line for line in lines)]
    if len(asserted) > 1:
        out.append(f"two causes of one misfit each asserted: {asserted}")
    if asserted and effects and not any(e["name"] in ("coupling_compliance", "clock_skew") for e in effects) \
            and "either may be the cause" not in gap_text:
        out.append(f"{asserted} asserted beside the model gap's {[e['name'] for e in effects]}")
    return out


CASES = [
    ([], _gap()),
    ([_check("model_misfit")], _gap()),
    ([_check("coupling_suspected"), _check("clock_skew")], None),
    ([_check("coupling_suspected"), _check("clock_skew"), _check("model_misfit")], _gap("clock_skew")),
    ([_check("coupling_suspected")], _gap("conditioner_lowpass")),
    ([_check("coupling_suspected")], _gap("coupling_compliance")),
    ([_check("coupling_not_excluded", "info")], _gap("mains_interference")),
    ([_check("polarity", "info")], _gap(unexplained=("force line at 137 Hz",))),
    ([_check("clock_skew"), _check("displacement_vs_radius")], _gap("channel_delay", "mains_interference")),
]


def test_no_finding_on_the_page_contradicts_another(page: Any) -> None:
    for checks, gap in CASES:
        lines, gap_text, tail = _shown(page, checks, gap)
        assert len(lines) == len(checks)
        assert _contradictions(checks, gap, lines, gap_text, tail) == [], (checks, gap, lines, gap_text, tail)


def test_the_rule_keeps_what_is_not_contradicted(page: Any) -> None:
    """An ideal run says so; a misfit no effect explains says that instead; one cause named by both
    the identification and the model gap is asserted as it is."""
    lines, gap_text, tail = _shown(page, [], _gap())
    assert gap_text.startswith(EXPLAINED) and tail == NOTHING
    lines, gap_text, tail = _shown(page, [_check("model_misfit")], _gap())
    assert gap_text.startswith("No known effect explains the misfit") and tail != NOTHING, gap_text
    lines, gap_text, tail = _shown(page, [_check("coupling_suspected")], _gap("coupling_compliance"))
    assert lines[0].endswith(COUPLING_ASSERTED + ": the stiffness found is that of transducer and mounting together.")
    lines, _, _ = _shown(page, [_check("coupling_suspected"), _check("clock_skew")], None)
    assert all("One possible cause of the misfit" in line for line in lines), lines
    assert "converters' clocks running apart" in lines[0] and "not stiff" in lines[1], lines
