"""The README's first steps, word for word, in a real headless Chromium: start the simulated station, open
the page, log in as the README says with the password the station printed at its start, start a run from
the form, watch it finish, read the results (the page and the audit trail name who started the run),
open the report and the certificate.  Then the same on a phone's 390 px: no view scrolls sideways (the
run as it records, its results, the main page, the certificate), the page speaks plainly first (the
statistics behind a "details" disclosure), with SI typography, steps counted "step 2 of 5", the time
left of a run, and times in the viewer's local time with its zone.  And, on that phone's run, the
certificate part of the page: the technician enters the room conditions (an out-of-range one is refused
at its input), runs, sees the stored conditions; the draft certificate states them; an approver issues
it from the page; the issued PDF and DCC read back the conditions.

And, on the same daemon after the README's steps, the lab's page flows: choose and mount a transducer,
open a completed run (the third seeded one: the runs started from the form are the README's and the
phone's), review its transducer's history (runs, results, drift plot), approve as another user, read the
audit trail; the technician cannot approve; and every page fits a phone's 390 px without horizontal
scrolling.  With ``$SCREENSHOTS_DIR`` set, screenshots of the views go there for a person to look at
(none otherwise: each costs the browser a full-page render and encode that no assertion reads).  And the
run page's compensation section (on a third seeded run, 10 and 80 Hz): state the application, see the
filter in plain words with its details and plot, download it, correct an uploaded signal file and
download the result; a refusal says why.

And last, the follow-up run: a 3-40 Hz run of a transducer on a soft coupling (k_c = 2 k_f) cannot tell
the coupling from a delay or a low-pass; the page shows the proposed steps under the run's model gap;
one click starts them (the run's own steps plus the added ones).

One daemon and one browser for the module's tests (a daemon's and a browser's start each cost a few
seconds of CPU); its store holds the lab's three seeded runs, the soft coupling's 3-40 Hz run (simulated
with that coupling and identified as the daemon would, so that no real-time run is needed to make it)
and a second transducer before the README's steps begin.

Skipped only when no Chromium is installed and CI is not set; under CI it must run.
"""

from __future__ import annotations

import io
import json
import os
import re
from collections.abc import Iterator
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from lxml import etree
from pypdf import PdfReader

from tests.station_support import Daemon, Seed, daemon_config, seed_runs
from tests.web_support import POLL_MS, log_in, open_page

pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("web_readme")]  # a real daemon, real runs and a real browser

README = Path(__file__).resolve().parents[1] / "README.md"
NS = {"dcc": "https://ptb.de/dcc", "si": "https://ptb.de/si"}
TEMPERATURE_C, HUMIDITY_PCT = 21.3, 47.0  # away from the simulated room sensor's (and the config has none)
DESKTOP = {"width": 1200, "height": 1000}  # the viewport of the lab's desktop flows (CSS px)
# the lab's views, each with what shows that its data have arrived
PAGES = {"#/": "#runs tbody tr", "#/register": "#reg-transducers tbody tr", "#/audit": "#audit tbody tr",
         "#/transducers/TX5K-0001": "#hist-runs tbody tr"}
SEEDS = (Seed(seed=1), Seed(seed=2), Seed((10.0, 80.0), 2e-4, 25.717, seed=1))  # the lab's history
COMPENSATION = 2  # the seeded run the compensation section works on (10 and 80 Hz, 0.2 mm)
K_F, B_F = 2.91e7, 17136.0  # the truth of config/sim-5kN.yaml (N/m, N*s/m)
TIE_STEPS = (3.0, 5.036, 8.455, 14.193, 23.827, 40.0)  # the soft coupling's run (Hz, at 1.25 mm)


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
    """The simulated station as the README starts it (one for the module's tests), with the lab's
    seeded runs (``SEEDS``), the soft coupling's run (``TIE_STEPS``; simulated with that coupling,
    identified as this station would) and a second transducer in its register."""
    tmp = tmp_path_factory.mktemp("readme")
    # the report and the certificate PDF render while the run runs, not after a worker's start
    cfg = daemon_config(tmp / "recordings", render_at_start=True)
    cfg["identification"]["methods"] = [{"method": "fd", "model": "auto"}]  # the primary; others: test_web.py
    coupled = daemon_config(tmp / "recordings")
    coupled["identification"] = cfg["identification"]
    coupled["simulation"]["effects"] = {"coupling_compliance": {"k_c": 2 * K_F, "b_c": 0.5 * B_F}}
    coupled["rig"]["acceleration_hz_per_s"] = 100.0
    tie = seed_runs(coupled, [Seed(TIE_STEPS, 0.00125)])
    with Daemon(tmp, config=cfg, seeds=SEEDS) as d:
        d.seeded = [*d.seeded, *tie]  # the lab's runs, then the soft coupling's
        r = d.c().put("/register/transducers/TX5K-0002", json={
            "type": "HBM U9C", "serial": "SN-42", "capacity_N": 5000.0, "sensitivity_V_per_N": 2e-6,
            "end_mass_kg": 0.1, "owner": "ACME Weighing"})
        assert r.status_code == 200, r.text
        yield d


@pytest.fixture(scope="module")
def daemon(station: Daemon) -> Daemon:
    """The lab's flows' name for the station."""
    return station


def test_the_readme_works_as_written(browser: object, station: Daemon) -> None:
    user = _readme_user()
    d = station
    log = d.log_path.read_text(errors="replace")  # the whole log: the passwords are printed at its start
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
        # the run is the person's: the page and the audit trail name who started it
        rid = pg.url.split("#/runs/")[1]
        assert f"started by {user}" in pg.inner_text("#run-who")
        started = d.c().get("/audit", params={"target": rid, "action": "run.started"}).json()["entries"]
        assert [e["who"] for e in started] == [user], started
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
    assert d.log_path.read_text(errors="replace").count(password) == 1


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


# ------------------------------------------------------------------ the lab's flows, after the README's
def shot(page: object, name: str) -> None:
    """A full-page screenshot ``name`` into ``$SCREENSHOTS_DIR`` when it is set."""
    if os.environ.get("SCREENSHOTS_DIR"):
        d = Path(os.environ["SCREENSHOTS_DIR"])
        d.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(d / name), full_page=True)  # type: ignore[attr-defined]


def test_choose_mount_history_approve_audit(browser: object, daemon: Daemon) -> None:
    # a completed run of the lab's history (the README's and the phone's tests start runs from the form;
    # this one's plots and model gap are made once for the phone's and the compensation's tests too)
    rid = daemon.seeded[COMPENSATION]
    with open_page(browser, daemon.url + "/", viewport=DESKTOP) as pg:
        log_in(pg, daemon, "tina")
        pg.wait_for_selector("#transducer_id option[value='TX5K-0002']", state="attached")
        # the form's plan is the configuration's, a radius per step
        assert pg.input_value("#radius_mm") == "1, 1"
        assert pg.locator("#plan-check tbody tr").nth(0).inner_text().startswith("1")  # steps counted from 1
        pg.select_option("#transducer_id", "TX5K-0002")
        pg.click("#mount")
        pg.wait_for_function(
            "document.querySelector('#banner').textContent.includes('TX5K-0002 is recorded as mounted')",
                 polling=POLL_MS)
        shot(pg, "lab-form.png")
        pg.goto(f"{daemon.url}/#/runs/{rid}")
        pg.wait_for_selector("#results:not([hidden])", timeout=30_000)
        pg.wait_for_function("document.querySelector('#approvals').textContent.includes('not approved')",
                             polling=POLL_MS)
        assert pg.is_disabled("#approve")  # a technician cannot approve
        r = daemon.c().post(f"/runs/{rid}/approve", json={})  # nor can the admin token
        assert r.status_code == 403
        # the transducer's history: the seeded calibrations and the README's and phone's runs, with the drift plot
        pg.click("#run-history")
        pg.wait_for_selector("#hist-runs tbody tr >> nth=2", timeout=30_000)
        assert rid in pg.inner_text("#hist-runs") and pg.locator("#hist-plot svg circle").count() >= 3
        shot(pg, "lab-history.png")

    # a second person, an approver, approves it
    with open_page(browser, daemon.url + "/", viewport=DESKTOP) as pg:
        log_in(pg, daemon, "anton")
        pg.goto(f"{daemon.url}/#/runs/{rid}")
        pg.wait_for_selector("#approve:not([disabled])", timeout=30_000)
        pg.fill("#approve-note", "checked against the budget")
        pg.click("#approve")
        pg.wait_for_function("document.querySelector('#approvals').textContent.includes('approved by anton')",
                             polling=POLL_MS)
        shot(pg, "lab-run-approved.png")
        # the audit trail names who did each of these
        pg.goto(f"{daemon.url}/#/audit")
        pg.wait_for_selector("#audit tbody tr", timeout=10_000)
        text = pg.inner_text("#audit")
        for who, what in (("tina", "register.mounted"), ("anton", "certificate.approved"),
                          ("admin", "register.changed"), ("system", "run.identified")):
            assert re.search(rf"{who}\s+{re.escape(what)}", text), (who, what)
        shot(pg, "lab-audit.png")

    # an administrator enters a reference standard on the page; it is there for the next run
    with open_page(browser, daemon.url + "/", viewport=DESKTOP) as pg:
        log_in(pg, daemon, "ada")
        pg.goto(f"{daemon.url}/#/register")
        pg.wait_for_selector("#reg-admin:not([hidden])", timeout=10_000)
        form = "#std-form"
        for name, value in (("id", "LVDT-7"), ("certificate_id", "DKD-K-123/2026"), ("issuer", "DKD lab 12"),
                            ("due_date", "2027-06-30"), ("uncertainty", "2e-7"), ("uncertainty_unit", "m")):
            pg.fill(f"{form} [name={name}]", value)
        pg.click(f"{form} button")
        pg.wait_for_selector("#reg-standards td:has-text('LVDT-7')", timeout=10_000)
        assert "2027-06-30" in pg.inner_text("#reg-standards")
        shot(pg, "lab-register.png")
    std = daemon.c().get("/register").json()["standards"]
    assert [(s["id"], s["due_date"], s["uncertainty"], s["updated_by"]) for s in std] == \
        [("LVDT-7", "2027-06-30", 2e-7, "ada")]


def test_every_page_fits_a_phone(browser: object, daemon: Daemon) -> None:
    with open_page(browser, daemon.url + "/", no_errors=False, viewport={"width": 390, "height": 844},
                   device_scale_factor=1, is_mobile=True, has_touch=True) as pg:
        log_in(pg, daemon, "tina")
        rid = daemon.seeded[COMPENSATION]  # the lab's and compensation tests' run: its plots and model gap made once
        for i, (page, ready) in enumerate((*PAGES.items(), (f"#/runs/{rid}", "#results:not([hidden])"))):
            pg.goto(f"{daemon.url}/{page}")
            pg.wait_for_selector(ready, timeout=30_000)  # the view's data have arrived and are shown
            pg.wait_for_function("[...document.images].every((i) => i.complete)", timeout=60_000, polling=POLL_MS)
            width = pg.evaluate("document.documentElement.scrollWidth")
            assert width <= 390, (page, width)
            shot(pg, f"lab-phone-{i}.png")


def test_design_download_and_correct_a_signal_on_the_page(browser: object, daemon: Daemon, tmp_path: Path) -> None:
    rid = daemon.seeded[COMPENSATION]
    with open_page(browser, daemon.url + f"/#/runs/{rid}") as pg:
        pg.wait_for_selector("#results:not([hidden])", timeout=30_000)
        pg.fill("#comp-mass", "1")
        pg.click("#comp-design")  # the page's POSTs need its session
        pg.wait_for_function("document.querySelector('#comp-msg').textContent.includes('not logged in')",
                             polling=POLL_MS)
        log_in(pg, daemon)
        pg.wait_for_selector("#comp-form input#comp-mass:visible", timeout=30_000)
        pg.fill("#comp-mass", "1")
        pg.fill("#comp-band", "4000")
        pg.click("#comp-design")  # 4 kHz is beyond the calibrated 10 to 80 Hz: refused with the reason
        pg.wait_for_function("!['', 'designing…'].includes(document.querySelector('#comp-msg').textContent)",
                             timeout=60_000, polling=POLL_MS)
        refused = pg.inner_text("#comp-msg")
        assert "refused (422)" in refused and "beyond the calibrated range" in refused, refused
        assert "tick “correct beyond the calibrated frequencies”" in refused
        assert pg.is_hidden("#comp-result")
        pg.check("#comp-extrap")
        pg.click("#comp-design")
        pg.wait_for_selector("#comp-result:not([hidden])", timeout=30_000)
        summary = pg.inner_text("#comp-summary")
        assert "from 0 Hz to 4000 Hz" in summary and "delays the signal by" in summary and "times larger" in summary
        assert pg.locator("#comp-findings li[data-finding='extrapolation']").count() == 1
        assert not pg.is_visible("#comp-table")  # the details wait in their disclosure
        pg.click("#comp-details summary")
        assert "taps (coefficients)" in pg.inner_text("#comp-table") and "64" in pg.inner_text("#comp-table")
        pg.wait_for_function("document.querySelector('#comp-bode').complete && "
                             "document.querySelector('#comp-bode').naturalWidth > 0", timeout=60_000, polling=POLL_MS)
        with pg.expect_download() as dl:
            pg.click("#comp-download")
        filt = json.loads(Path(dl.value.path()).read_text())
        assert filt["format"] == "sinecal-compensation-filter" and filt["taps"] == 64
        api = daemon.c().post(f"/runs/{rid}/compensation", json={
            "sample_rate_hz": 50000, "mounted_mass_kg": 1.0, "band_hz": [0, 4000], "allow_extrapolation": True}).json()
        assert filt["b"] == api["b"]
        # a signal file: a time column and one value column (V)
        t = np.arange(3000) / 50000
        x = 0.2 * np.exp(-((t - 0.03) / 5e-4) ** 2)
        sig = tmp_path / "impact.csv"
        np.savetxt(sig, np.column_stack([t, x]), delimiter=",", header="time_s,force_V", comments="", fmt="%.9g")
        pg.set_input_files("#comp-file", str(sig))
        pg.fill("#comp-noise", "1e-5")
        pg.click("#comp-apply")
        pg.wait_for_selector("#comp-applied:not([hidden])", timeout=30_000)
        assert "3000 samples corrected" in pg.inner_text("#comp-applied-summary")
        assert pg.locator("#comp-signal svg path").count() == 3
        with pg.expect_download() as dl:
            pg.click("#comp-applied-download")
        out = np.loadtxt(dl.value.path(), delimiter=",", skiprows=1)
        as_written = np.loadtxt(sig, delimiter=",", skiprows=1)[:, 1]  # what the page read
        ref = daemon.c().post("/compensation/apply", json={"filter": api, "signal": list(as_written),
                                                           "sample_rate_hz": 50000, "noise_std": 1e-5}).json()
        np.testing.assert_allclose(out[:, 1], ref["estimate"], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(out[:, 2], ref["u"], rtol=1e-12)
        np.testing.assert_allclose(out[:, 0], np.array(ref["time_s"]), atol=1e-12)
        # a file with a NaN: one clear message, nothing corrected
        bad = tmp_path / "bad.csv"
        bad.write_text("force_V\n0.1\nnan\n0.2\n")
        pg.set_input_files("#comp-file", str(bad))
        pg.click("#comp-apply")
        pg.wait_for_function("document.querySelector('#comp-apply-msg').textContent.includes('line 3')",
                             polling=POLL_MS)
        assert "not a finite number" in pg.inner_text("#comp-apply-msg")


# ------------------------------------------------------------------- the follow-up run, last
def test_proposal_of_an_unknown_run_is_404(daemon: Daemon) -> None:
    r = daemon.c().get("/runs/no-such-run/proposal")
    assert r.status_code == 404 and "detail" in r.json()


def test_run_the_proposed_steps_with_one_click(browser: object, daemon: Daemon) -> None:
    rid = daemon.seeded[len(SEEDS)]  # the soft coupling's 3-40 Hz run
    assert daemon.c().get(f"/runs/{rid}").json()["state"] == "completed"
    assert daemon.c().get(f"/runs/{rid}/proposal").status_code == 404  # not analysed yet: a GET computes nothing
    assert daemon.c().post(f"/runs/{rid}/discrepancy", timeout=180).status_code == 200  # the analysis itself
    api = daemon.c().get(f"/runs/{rid}/proposal").json()
    prop = api["proposal"]
    assert prop is not None and prop["steps"], api
    assert "coupling_compliance" in prop["separates"] or prop["separates"] == ["k_f"], prop
    want = [(s["crank_frequency_hz"], s["crank_radius_m"]) for s in prop["run_steps"]]
    assert want[: len(TIE_STEPS)] == [(f, 0.00125) for f in TIE_STEPS]
    assert [(s["crank_frequency_hz"], s["crank_radius_m"]) for s in api["request"]["steps"]] == want
    # the page shows the proposal under the analysis and runs it with one click
    with open_page(browser, daemon.url + "/") as pg:  # and no JavaScript error on the page
        log_in(pg, daemon)
        pg.goto(f"{daemon.url}/#/runs/{rid}")
        pg.wait_for_selector("#run-proposal", timeout=90_000)
        rows = pg.locator("#proposal tbody tr")
        assert rows.count() == len(prop["steps"])
        assert f"{prop['steps'][0]['crank_frequency_hz']:g}" in rows.nth(0).inner_text()
        pg.click("#run-proposal")
        pg.wait_for_url(re.compile(r".*#/runs/(?!" + re.escape(rid) + r"$).+"), timeout=15_000)
        new = pg.inner_text("#run-id")
    assert new != rid
    st = daemon.c().get(f"/runs/{new}").json()
    assert [(s["crank_frequency_hz"], s["crank_radius_m"]) for s in st["steps"]] == want
    # that the proposed run settles the tie is shown end to end in test_discrepancy_propose.py; here
    # the run is stopped to keep the suite short
    assert daemon.c().post(f"/runs/{new}/abort").status_code == 202
    assert daemon.wait_state(new)["state"] in ("aborted", "completed")
