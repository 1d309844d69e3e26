"""The README's first steps, word for word, in a real headless Chromium: start the simulated station,
open the page, log in as the README says with the password the station printed at its start, start a
run from the form, watch it finish, read the results, open the report and the certificate.  Then the
same on a phone's 390 px: no view scrolls sideways (the run as it records, its results, the main
page, the certificate), the page speaks plainly first (the statistics behind a "details"
disclosure), with SI typography, steps counted "step 2 of 5", the time left of a run, and times in
the viewer's local time with its zone.  And, on that phone's run, the certificate part of the page: the
technician enters the room conditions (an out-of-range one is refused at its input), runs, sees the
stored conditions; the draft certificate states them; an approver issues it from the page; the issued
PDF and DCC read back the conditions.  One daemon for the module's tests, each on a run of its own.

Skipped only when no Chromium is installed and CI is not set; under CI it must run.
"""

from __future__ import annotations

import io
import re
from collections.abc import Iterator
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

import pytest
from lxml import etree
from pypdf import PdfReader

from tests.station_support import Daemon, daemon_config
from tests.web_support import POLL_MS, log_in, open_page

pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("web_readme")]  # a real daemon, a real run and a real browser

README = Path(__file__).resolve().parents[1] / "README.md"
NS = {"dcc": "https://ptb.de/dcc", "si": "https://ptb.de/si"}
TEMPERATURE_C, HUMIDITY_PCT = 21.3, 47.0  # away from the simulated room sensor's (and the config has none)


def _readme_user() -> str:
    """Who the README's set-up paragraph says to log in as."""
    text = " ".join(README.read_text().split())
    m = re.search(r"log in at the top of the page as `([a-z]+)` with the password the station printed", text)
    assert m, "the README no longer says whom to log in as"
    return m.group(1)


def _printed_password(log: str, name: str) -> str:
    """The password the station printed for ``name`` at its (latest) start."""
    found = re.findall(rf"^\s+{name}\s+\(\w+\) password (\S+)$", log, re.M)
    assert found, log[-3000:]
    return str(found[-1])


@pytest.fixture(scope="module")
def station(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Daemon]:
    """The simulated station as the README starts it (one for the module's tests)."""
    tmp = tmp_path_factory.mktemp("readme")
    # the report and the certificate PDF render while the run runs, not after a worker's start
    cfg = daemon_config(tmp / "recordings", render_at_start=True)
    cfg["identification"]["methods"] = [{"method": "fd", "model": "auto"}]  # the primary; others: test_web.py
    with Daemon(tmp, config=cfg) as d:
        yield d


def test_the_readme_works_as_written(browser: object, station: Daemon) -> None:
    user = _readme_user()
    d = station
    log = d.log()
    assert "simulated station: log in on" in log and "approver" in log
    password = _printed_password(log, user)
    with open_page(browser, d.url + "/") as pg:
        pg.wait_for_function("document.querySelector('#hint-frequency').textContent.length > 0", polling=POLL_MS)
        assert user in pg.inner_text("#login-hint")  # the page says whom to log in as, too
        # logged out, starting a run answers in words a person understands
        pg.fill("#frequencies", "10, 20")
        pg.fill("#radius_mm", "1")
        pg.click("#start")
        pg.wait_for_function("document.querySelector('#form-msg').textContent.length > 0", polling=POLL_MS)
        msg = pg.inner_text("#form-msg")
        assert msg == "You are not logged in: log in at the top of the page to start a run.", msg
        assert not pg.is_visible("#abort")
        # log in as the README says
        pg.fill("#login-name", user)
        pg.fill("#login-password", password)
        pg.click("#login")
        pg.wait_for_selector("#me:not([hidden])", timeout=10_000)
        assert pg.inner_text("#me-name") == f"{user} (technician)" and not pg.is_visible("#login-hint")
        # start a run, watch it, read the results
        pg.click("#start")
        pg.wait_for_url(re.compile(r".*#/runs/.+"), timeout=10_000)
        pg.wait_for_function("document.querySelector('#run-state').textContent === 'completed'", timeout=60_000,
                             polling=POLL_MS)
        pg.wait_for_selector("#results:not([hidden])", timeout=15_000)
        for name in ("S", "k_f", "b_f"):
            assert "±" in pg.inner_text(f"#params tr[data-param='{name}'] td.value"), name
        # a technician is offered no approval nor issuing (actions only for the roles that may use them)
        assert not pg.is_visible("#approve") and not pg.is_visible("#cert-issue")
        assert pg.inner_text("#cert-state") == "draft"
        # the report and the (draft) certificate open from the results
        for link, words in (("#report-link", "report"), ("#cert-html", "ertificate")):
            with pg.context.expect_page(timeout=60_000) as opened:
                pg.click(link)
            doc = opened.value
            doc.wait_for_load_state(timeout=60_000)
            assert words in doc.title() + doc.inner_text("body")[:2000], (link, doc.title())
            assert "detail" not in doc.inner_text("body")[:200], doc.inner_text("body")[:500]
            doc.close()
    # the station printed the passwords once: not again in the rest of its log
    assert d.log().count(password) == 1


# a phone; a zone other than UTC (the page shows the viewer's local time)
PHONE: dict[str, Any] = {"viewport": {"width": 390, "height": 844}, "device_scale_factor": 1, "is_mobile": True,
                         "has_touch": True, "timezone_id": "Europe/Berlin"}
WIDTH = "document.scrollingElement.scrollWidth"
# what the run view shows while the run records, sampled every 50 ms (the widest page, the step, the time left)
WATCH = """() => { window.watched = {width: 0, steps: [], eta: []};
  setInterval(() => { const w = window.watched; w.width = Math.max(w.width, document.scrollingElement.scrollWidth);
    if (document.querySelector('#run-state').textContent === 'running') {
      w.steps.push(document.querySelector('#run-step').textContent);
      w.eta.push(document.querySelector('#run-eta').textContent); } }, 50); }"""


def test_a_phone_reads_plain_words_and_nothing_scrolls_sideways(browser: object, station: Daemon) -> None:
    """On a phone's 390 px, the technician enters the room conditions with the run (an out-of-range one
    refused at its input), watches it and reads its results: nothing scrolls sideways, plain words
    first, SI typography, local time; the stored conditions, stated by the draft certificate; an
    approver issues it on the page and the issued PDF and DCC read back the conditions.  (One run for
    the phone's and the conditions' checks.)"""
    d = station
    password = _printed_password(d.log_path.read_text(errors="replace"), "technician")  # printed at start
    with open_page(browser, d.url + "/", **PHONE) as pg:
        pg.wait_for_function("document.querySelector('#hint-frequency').textContent.length > 0", polling=POLL_MS)
        pg.fill("#login-name", "technician")
        pg.fill("#login-password", password)
        pg.click("#login")
        pg.wait_for_selector("#me:not([hidden])", timeout=10_000)
        assert pg.evaluate(WIDTH) <= 390
        # the room conditions: the inputs carry the API's ranges; empty says what the run then states
        env = d.c().get("/station").json()["environment"]
        assert pg.get_attribute("#temperature_c", "min") == str(int(env["temperature_c"]["min"]))
        assert pg.get_attribute("#relative_humidity_pct", "max") == str(int(env["relative_humidity_pct"]["max"]))
        assert "simulated room sensor" in pg.inner_text("#hint-humidity")
        pg.fill("#temperature_c", str(TEMPERATURE_C))
        pg.fill("#relative_humidity_pct", "120")  # the API refuses it at its field
        pg.click("#start")
        slot = '#run-form .err[data-for="relative_humidity_pct"]'
        pg.wait_for_function(f"document.querySelector('{slot}').textContent.includes('100')", polling=POLL_MS)
        assert "environment.relative_humidity_pct" in pg.inner_text(slot)
        assert pg.inner_text('#run-form .err[data-for="temperature_c"]') == ""
        assert re.search(r"#/$|/$", pg.url)  # no run was started
        pg.fill("#relative_humidity_pct", str(HUMIDITY_PCT))
        pg.evaluate(WATCH)
        pg.click("#start")
        pg.wait_for_url(re.compile(r".*#/runs/.+"), timeout=10_000)
        rid = pg.url.split("#/runs/")[1]
        pg.wait_for_function("document.querySelector('#run-state').textContent === 'completed'", timeout=60_000,
                             polling=POLL_MS)
        pg.wait_for_selector("#results:not([hidden])", timeout=15_000)
        pg.wait_for_timeout(200)
        seen = pg.evaluate("window.watched")
        # the run as it recorded and its results: never wider than the phone
        assert seen["width"] <= 390 and pg.evaluate(WIDTH) <= 390, seen["width"]
        n = len(d.c().get(f"/runs/{rid}").json()["steps"])
        assert any(re.fullmatch(rf"step [1-{n}] of {n} \(\d+ Hz\) \w+", s) for s in seen["steps"]), seen["steps"]
        assert any(re.fullmatch(r"about \d+ (s|min) left", e) for e in seen["eta"]), seen["eta"]
        stored = pg.inner_text("#res-environment")
        assert "21.3" in stored and "47.0" in stored and "entered with the run" in stored, stored
        # the draft certificate (the page's link) states them
        draft = pg.request.get(d.url + pg.get_attribute("#cert-html", "href"))
        assert draft.ok
        html = draft.text()
        assert re.search(r'id="temperature">21\.3 °C', html) and re.search(r'id="humidity">47 %', html)
        assert "entered with the run" in html
        # a plain sentence first; the model, the fit and the statistics behind a closed disclosure
        assert pg.inner_text("#res-summary").startswith("The run determined the sensitivity")
        shown = pg.inner_text("#results")
        assert "χ²" not in shown and "Eq." not in shown and "chi2" not in shown, shown
        assert pg.evaluate("!document.querySelector('#res-details').open")
        assert "χ²" in pg.text_content("#res-details") and "Eq. 9" in pg.text_content("#res-details")
        pg.click("#res-details > summary")
        assert "χ²" in pg.inner_text("#res-details") and pg.evaluate(WIDTH) <= 390
        # SI typography: N·s/m (not N*s/m), powers of ten as × 10ⁿ (not e7), a space before the unit
        assert pg.inner_text("#params tr[data-param='b_f'] td:nth-child(3)") == "N·s/m"
        assert not re.search(r"\*|\de[-+]?\d|\d(Hz|mV|°C)\b", shown), shown
        assert pg.text_content("#frf tbody tr:first-child td:first-child") == f"1 of {n}"
        # the page's words for what this run did not show: units, powers of ten, a finding's plain line
        words = pg.evaluate("""() => [unitText('N*s/m'), unitText('V/(m/s^2)'), unitText('us'), withUnit('12.5', 'Hz'),
            withUnit('3', 'deg'), fmtU(29100524.7, 9845.2), localTime(0),
            findingText({name: 'model_misfit', severity: 'warning', step: null, message: 'chi2/dof = 3.31'})]""")
        assert words[:6] == ["N·s/m", "V/(m/s²)", "µs", "12.5 Hz", "3°", "(2.91005 ± 0.00098) × 10⁷"], words
        assert re.fullmatch(r"1970-01-01 01:00:00 (GMT\+1|CET)", words[6]), words[6]
        assert words[7].startswith("Check before using the results: The transducer model does not describe"), words[7]
        # the recent runs: local time with its zone (Berlin in November: UTC+1)
        pg.goto(d.url + "/#/")
        cell = pg.locator(f"#runs tr:has(a[href='#/runs/{rid}']) td:nth-child(5)")
        cell.wait_for(timeout=10_000)
        created = datetime.fromisoformat(d.c().get(f"/runs/{rid}").json()["created"].replace("Z", "+00:00"))
        local = (created + timedelta(hours=1)).strftime("%Y-%m-%d %H:%M:%S")
        assert re.fullmatch(rf"{local} (GMT\+1|CET)", cell.inner_text()), cell.inner_text()
        assert pg.evaluate(WIDTH) <= 390
        # the certificate, too, fits the phone
        pg.goto(f"{d.url}/runs/{rid}/certificate.html")
        pg.wait_for_load_state(timeout=60_000)
        assert "ertificate" in pg.title() and pg.evaluate(WIDTH) <= 390, pg.evaluate(WIDTH)
        # its wide tables scroll within themselves, their words whole (not broken letter by letter)
        narrowest = pg.evaluate("Math.min(...[...document.querySelectorAll('table.results td:first-child')]"
                                ".map((td) => td.getBoundingClientRect().width))")
        assert narrowest >= 100, narrowest

    # a second person, an approver, issues it from the page
    with open_page(browser, f"{d.url}/#/runs/{rid}") as pg:
        log_in(pg, d, "anton")
        pg.goto(f"{d.url}/#/runs/{rid}")
        pg.wait_for_selector("#results:not([hidden])", timeout=30_000)
        pg.click("#cert-form button[type=submit]")
        pg.wait_for_function("document.querySelector('#cert-msg').textContent.startsWith('issued ')", timeout=30_000,
                             polling=POLL_MS)
        number = pg.inner_text("#cert-msg").removeprefix("issued ").strip()
        # once issued, issuing is offered no more; the page says which certificate was issued
        assert not pg.is_visible("#cert-issue") and pg.inner_text("#cert-state") == f"issued: {number}"
        issued = d.c().get("/certificates").json()["certificates"]
        assert [c["number"] for c in issued if c["run_id"] == rid] == [number]
        # the page's downloads now read back the issued certificate's conditions
        pdf = pg.request.get(d.url + pg.get_attribute("#cert-pdf", "href"))
        assert pdf.ok and pdf.headers["content-type"].startswith("application/pdf")
        text = "\n".join(p.extract_text() for p in PdfReader(io.BytesIO(pdf.body())).pages)
        assert number in text and "21.3 °C" in text and "47 %" in text, text
        xml = pg.request.get(d.url + pg.get_attribute("#cert-xml", "href"))
        assert xml.ok
        doc = etree.fromstring(xml.body())
        reals = doc.findall(".//dcc:influenceCondition//si:real", NS)
        values = {r.findtext("si:unit", namespaces=NS): float(r.findtext("si:value", namespaces=NS)) for r in reals}
        assert values == {r"\degreecelsius": TEMPERATURE_C, r"\percent": HUMIDITY_PCT}, values
