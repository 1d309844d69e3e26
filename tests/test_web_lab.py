"""The lab's page flows in a real headless Chromium: choose the transducer, run, review its history
(runs, results, drift plot), approve as another user, read the audit trail; the technician cannot
approve; and every page fits a phone's 390 px without horizontal scrolling.  With ``$SCREENSHOTS_DIR``
set, screenshots of the views go there for a person to look at (none otherwise: each costs the
browser a full-page render and encode that no assertion reads).

And the run page's compensation section (on a third seeded run, 10 and 80 Hz): state the
application, see the filter in plain words with its details and plot, download it, correct an
uploaded signal file and download the result; a refusal says why."""

from __future__ import annotations

import json
import os
import re
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from tests.station_support import Daemon, Seed
from tests.web_support import POLL_MS, log_in, open_page

pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("web_lab")]  # a real daemon, runs and a browser

DESKTOP = {"width": 1200, "height": 1000}  # the viewport of the desktop flows (CSS px)
PAGES = ("#/", "#/register", "#/audit", "#/transducers/TX5K-0001")
COMPENSATION = 2  # the seeded run the compensation section works on (10 and 80 Hz, 0.2 mm)


@pytest.fixture(scope="module")
def daemon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Daemon]:
    seeds = [Seed(seed=1), Seed(seed=2), Seed((10.0, 80.0), 2e-4, 25.717, seed=1)]
    with Daemon(tmp_path_factory.mktemp("weblab"), seeds=seeds) as d:
        r = d.c().put("/register/transducers/TX5K-0002", json={
            "type": "HBM U9C", "serial": "SN-42", "capacity_N": 5000.0, "sensitivity_V_per_N": 2e-6,
            "end_mass_kg": 0.1, "owner": "ACME Weighing"})
        assert r.status_code == 200, r.text
        yield d


def shot(page: object, name: str) -> None:
    """A full-page screenshot ``name`` into ``$SCREENSHOTS_DIR`` when it is set."""
    if os.environ.get("SCREENSHOTS_DIR"):
        d = Path(os.environ["SCREENSHOTS_DIR"])
        d.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(d / name), full_page=True)  # type: ignore[attr-defined]


def test_choose_run_history_approve_audit(browser: object, daemon: Daemon) -> None:
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
        pg.select_option("#transducer_id", "TX5K-0001")
        shot(pg, "lab-form.png")
        pg.click("#start")
        pg.wait_for_url(re.compile(r".*#/runs/.+"), timeout=10_000)
        rid = pg.inner_text("#run-id")
        pg.wait_for_function("document.querySelector('#run-state').textContent === 'completed'", timeout=90_000,
                             polling=POLL_MS)
        pg.wait_for_selector("#results:not([hidden])", timeout=30_000)
        assert "started by tina" in pg.inner_text("#run-who")
        pg.wait_for_function("document.querySelector('#approvals').textContent.includes('not approved')",
                             polling=POLL_MS)
        assert pg.is_disabled("#approve")  # a technician cannot approve
        r = daemon.c().post(f"/runs/{rid}/approve", json={})  # nor can the admin token
        assert r.status_code == 403
        # the transducer's history: the seeded calibrations and this run, with the drift plot
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
        for who, what in (("tina", "run.started"), ("tina", "register.mounted"), ("anton", "certificate.approved"),
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
        rid = daemon.seeded[COMPENSATION]  # the compensation test's run: its plots and analysis made once for both
        for i, page in enumerate((*PAGES, f"#/runs/{rid}")):
            pg.goto(f"{daemon.url}/{page}")
            pg.wait_for_timeout(1500)  # the view's data arrive
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
