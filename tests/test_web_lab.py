"""The lab's page flows in a real headless Chromium: choose the transducer, run, review its history
(runs, results, drift plot), approve as another user, read the audit trail; the technician cannot
approve; and every page fits a phone's 390 px without horizontal scrolling.  Screenshots go to
``$SCREENSHOTS_DIR`` (default: the test's temporary folder) for a person to look at."""

from __future__ import annotations

import os
import re
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.station_support import Daemon, Seed
from tests.web_support import log_in, open_page

pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("web_lab")]  # a real daemon, runs and a browser

DESKTOP = {"width": 1200, "height": 1000}  # the viewport of the desktop flows (CSS px)
PAGES = ("#/", "#/register", "#/audit", "#/transducers/TX5K-0001")


@pytest.fixture(scope="module")
def daemon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Daemon]:
    with Daemon(tmp_path_factory.mktemp("weblab"), seeds=[Seed(seed=1), Seed(seed=2)]) as d:
        r = d.c().put("/register/transducers/TX5K-0002", json={
            "type": "HBM U9C", "serial": "SN-42", "capacity_N": 5000.0, "sensitivity_V_per_N": 2e-6,
            "end_mass_kg": 0.1, "owner": "ACME Weighing"})
        assert r.status_code == 200, r.text
        yield d


def shots(tmp_path: Path) -> Path:
    d = Path(os.environ.get("SCREENSHOTS_DIR") or tmp_path)
    d.mkdir(parents=True, exist_ok=True)
    return d


def test_choose_run_history_approve_audit(browser: object, daemon: Daemon, tmp_path: Path) -> None:
    out = shots(tmp_path)
    with open_page(browser, daemon.url + "/", viewport=DESKTOP) as pg:
        log_in(pg, daemon, "tina")
        pg.wait_for_selector("#transducer_id option[value='TX5K-0002']", state="attached")
        # the form's plan is the configuration's, a radius per step
        assert pg.input_value("#radius_mm") == "1, 1"
        assert pg.locator("#plan-check tbody tr").nth(0).inner_text().startswith("1")  # steps counted from 1
        pg.select_option("#transducer_id", "TX5K-0002")
        pg.click("#mount")
        pg.wait_for_function(
            "document.querySelector('#banner').textContent.includes('TX5K-0002 is recorded as mounted')")
        pg.select_option("#transducer_id", "TX5K-0001")
        pg.screenshot(path=str(out / "lab-form.png"), full_page=True)
        pg.click("#start")
        pg.wait_for_url(re.compile(r".*#/runs/.+"), timeout=10_000)
        rid = pg.inner_text("#run-id")
        pg.wait_for_function("document.querySelector('#run-state').textContent === 'completed'", timeout=90_000)
        pg.wait_for_selector("#results:not([hidden])", timeout=30_000)
        assert "started by tina" in pg.inner_text("#run-who")
        pg.wait_for_function("document.querySelector('#approvals').textContent.includes('not approved')")
        assert pg.is_disabled("#approve")  # a technician cannot approve
        r = daemon.c().post(f"/runs/{rid}/approve", json={})  # nor can the admin token
        assert r.status_code == 403
        # the transducer's history: the seeded calibrations and this run, with the drift plot
        pg.click("#run-history")
        pg.wait_for_selector("#hist-runs tbody tr >> nth=2", timeout=30_000)
        assert rid in pg.inner_text("#hist-runs") and pg.locator("#hist-plot svg circle").count() >= 3
        pg.screenshot(path=str(out / "lab-history.png"), full_page=True)

    # a second person, an approver, approves it
    with open_page(browser, daemon.url + "/", viewport=DESKTOP) as pg:
        log_in(pg, daemon, "anton")
        pg.goto(f"{daemon.url}/#/runs/{rid}")
        pg.wait_for_selector("#approve:not([disabled])", timeout=30_000)
        pg.fill("#approve-note", "checked against the budget")
        pg.click("#approve")
        pg.wait_for_function("document.querySelector('#approvals').textContent.includes('approved by anton')")
        pg.screenshot(path=str(out / "lab-run-approved.png"), full_page=True)
        # the audit trail names who did each of these
        pg.goto(f"{daemon.url}/#/audit")
        pg.wait_for_selector("#audit tbody tr", timeout=10_000)
        text = pg.inner_text("#audit")
        for who, what in (("tina", "run.started"), ("tina", "register.mounted"), ("anton", "certificate.approved"),
                          ("admin", "register.changed"), ("system", "run.identified")):
            assert re.search(rf"{who}\s+{re.escape(what)}", text), (who, what)
        pg.screenshot(path=str(out / "lab-audit.png"), full_page=True)

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
        pg.screenshot(path=str(out / "lab-register.png"), full_page=True)
    std = daemon.c().get("/register").json()["standards"]
    assert [(s["id"], s["due_date"], s["uncertainty"], s["updated_by"]) for s in std] == \
        [("LVDT-7", "2027-06-30", 2e-7, "ada")]


def test_every_page_fits_a_phone(browser: object, daemon: Daemon, tmp_path: Path) -> None:
    out = shots(tmp_path)
    with open_page(browser, daemon.url + "/", no_errors=False, viewport={"width": 390, "height": 844},
                   device_scale_factor=1, is_mobile=True, has_touch=True) as pg:
        log_in(pg, daemon, "tina")
        [rid, *_] = daemon.seeded
        for i, page in enumerate((*PAGES, f"#/runs/{rid}")):
            pg.goto(f"{daemon.url}/{page}")
            pg.wait_for_timeout(1500)  # the view's data arrive
            width = pg.evaluate("document.documentElement.scrollWidth")
            assert width <= 390, (page, width)
            pg.screenshot(path=str(out / f"lab-phone-{i}.png"), full_page=True)
