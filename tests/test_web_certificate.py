"""The run form's room conditions and the certificate part of the page in a real headless Chromium:
a technician enters the conditions (an out-of-range one is refused at its input), runs, sees the
stored conditions on the run; the draft certificate states them; a second person, an approver,
issues it from the page; the issued PDF and DCC read back the conditions."""

from __future__ import annotations

import io
import re
from collections.abc import Iterator

import pytest
from lxml import etree
from pypdf import PdfReader

from tests.station_support import Daemon, daemon_config
from tests.web_support import log_in, open_page

pytestmark = pytest.mark.slow  # a real daemon, a run and a browser

NS = {"dcc": "https://ptb.de/dcc", "si": "https://ptb.de/si"}
TEMPERATURE_C, HUMIDITY_PCT = 21.3, 47.0  # away from the simulated room sensor's (and the config has none)


@pytest.fixture(scope="module")
def daemon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Daemon]:
    tmp = tmp_path_factory.mktemp("webcert")
    cfg = daemon_config(tmp / "recordings", render_at_start=True)  # the certificate PDF does not wait for a start
    cfg["plan"]["record_s"] = 0.5
    cfg.setdefault("identification", {})["methods"] = [{"method": "fd", "model": "auto"}]  # one result suffices
    with Daemon(tmp, config=cfg) as d:
        yield d


def test_conditions_from_the_form_reach_the_issued_certificate(browser: object, daemon: Daemon) -> None:
    with open_page(browser, daemon.url + "/") as pg:
        log_in(pg, daemon, "tina")
        env = daemon.c().get("/station").json()["environment"]
        # the inputs carry the API's ranges; empty says what the run then states
        assert pg.get_attribute("#temperature_c", "min") == str(int(env["temperature_c"]["min"]))
        assert pg.get_attribute("#relative_humidity_pct", "max") == str(int(env["relative_humidity_pct"]["max"]))
        assert "simulated room sensor" in pg.inner_text("#hint-humidity")
        pg.fill("#frequencies", "10")
        pg.fill("#radius_mm", "1")
        pg.fill("#temperature_c", str(TEMPERATURE_C))
        pg.fill("#relative_humidity_pct", "120")  # the API refuses it at its field
        pg.click("#start")
        slot = '#run-form .err[data-for="relative_humidity_pct"]'
        pg.wait_for_function(f"document.querySelector('{slot}').textContent.includes('100')")
        assert "environment.relative_humidity_pct" in pg.inner_text(slot)
        assert pg.inner_text('#run-form .err[data-for="temperature_c"]') == ""
        assert re.search(r"#/$|/$", pg.url)  # no run was started
        pg.fill("#relative_humidity_pct", str(HUMIDITY_PCT))
        pg.click("#start")
        pg.wait_for_url(re.compile(r".*#/runs/.+"), timeout=10_000)
        rid = pg.inner_text("#run-id")
        pg.wait_for_selector("#results:not([hidden])", timeout=60_000)
        stored = pg.inner_text("#res-environment")
        assert "21.3" in stored and "47.0" in stored and "entered with the run" in stored, stored
        # the draft certificate (the page's link) states them
        draft = pg.request.get(daemon.url + pg.get_attribute("#cert-html", "href"))
        assert draft.ok
        html = draft.text()
        assert re.search(r'id="temperature">21\.3 °C', html) and re.search(r'id="humidity">47 %', html)
        assert "entered with the run" in html

    # a second person, an approver, issues it from the page
    with open_page(browser, f"{daemon.url}/#/runs/{rid}") as pg:
        log_in(pg, daemon, "anton")
        pg.goto(f"{daemon.url}/#/runs/{rid}")
        pg.wait_for_selector("#results:not([hidden])", timeout=30_000)
        pg.click("#cert-form button[type=submit]")
        pg.wait_for_function("document.querySelector('#cert-msg').textContent.startsWith('issued ')", timeout=30_000)
        number = pg.inner_text("#cert-msg").removeprefix("issued ").strip()
        # once issued, issuing is offered no more; the page says which certificate was issued
        assert not pg.is_visible("#cert-issue") and pg.inner_text("#cert-state") == f"issued: {number}"
        issued = daemon.c().get("/certificates").json()["certificates"]
        assert [c["number"] for c in issued if c["run_id"] == rid] == [number]
        # the page's downloads now read back the issued certificate's conditions
        pdf = pg.request.get(daemon.url + pg.get_attribute("#cert-pdf", "href"))
        assert pdf.ok and pdf.headers["content-type"].startswith("application/pdf")
        text = "\n".join(p.extract_text() for p in PdfReader(io.BytesIO(pdf.body())).pages)
        assert number in text and "21.3 °C" in text and "47 %" in text, text
        xml = pg.request.get(daemon.url + pg.get_attribute("#cert-xml", "href"))
        assert xml.ok
        doc = etree.fromstring(xml.body())
        reals = doc.findall(".//dcc:influenceCondition//si:real", NS)
        values = {r.findtext("si:unit", namespaces=NS): float(r.findtext("si:value", namespaces=NS)) for r in reals}
        assert values == {r"\degreecelsius": TEMPERATURE_C, r"\percent": HUMIDITY_PCT}, values
