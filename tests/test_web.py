"""The technicians' page end to end in a real headless Chromium (Debian's, driven by Playwright):
fill the form, watch a simulated run finish, read the results; refused input; the emergency stop; a
drive that does not stop.

One daemon for the module, on the simulated rig's emulators run as a process of their own (the
configuration's physics loaded into them) and reached as a real rig's devices, so that a test can
make the drive fail to stop (``SimRigProcess.ignore_stops``); the tests run in the file's order, the
drive's test last.

Skipped only when no Chromium is installed and CI is not set; under CI it must run.
"""

from __future__ import annotations

import re
from collections.abc import Iterator

import pytest

from drivers.sim import SimRigProcess
from station.config import parse_config, to_rig_physics
from tests.station_support import Daemon, daemon_config, run_body
from tests.web_support import POLL_MS, log_in, open_page

# a real daemon, a real run and a real browser: the end-to-end layer
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("web")]



@pytest.fixture(scope="module")
def rig_and_daemon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[SimRigProcess, Daemon]]:
    """The emulators' process (the configuration's physics) and the daemon on it as its devices."""
    tmp = tmp_path_factory.mktemp("web")
    cfg = daemon_config(tmp / "recordings")
    cfg["plan"]["record_s"] = 1.4  # long enough for the paper's protocol: PSO+ gives its result beside fd's
    physics = to_rig_physics(parse_config(cfg))
    radius = cfg["plan"]["steps"][0]["crank_radius_m"]
    with SimRigProcess(crank_radius_m=radius, seed=cfg["simulation"]["seed"]) as emu:
        emu.load_physics(physics)
        cfg.pop("simulation")
        host, port = emu.addresses.modbus_tcp
        cfg["devices"] = {"motor_url": f"modbus-tcp://{host}:{port}", "daq_port": emu.addresses.daq,
                          "crank_radius_m": radius}
        with Daemon(tmp, config=cfg) as d:
            yield emu, d


@pytest.fixture(scope="module")
def daemon(rig_and_daemon: tuple[SimRigProcess, Daemon]) -> Daemon:
    return rig_and_daemon[1]


@pytest.fixture
def page(browser: object, daemon: Daemon) -> Iterator[object]:
    with open_page(browser, daemon.url + "/") as pg:  # and no JavaScript error on the page
        yield pg


def test_fill_the_form_watch_a_run_finish_read_the_results(page: object, daemon: Daemon) -> None:
    pg = page
    # the limits are shown, the form is prefilled with the station's transducer and plan
    pg.wait_for_function("document.querySelector('#hint-frequency').textContent.length > 0", polling=POLL_MS)
    assert "1–100 Hz" in pg.inner_text("#hint-frequency")
    assert "0.1–50 mm" in pg.inner_text("#hint-radius")
    assert "4000 N" in pg.inner_text("#hint-force")
    assert pg.input_value("#transducer_id") == "TX5K-0001"
    assert pg.is_visible("#estop")
    log_in(pg, daemon)
    pg.fill("#frequencies", "10, 20")
    pg.fill("#radius_mm", "1")
    rows = pg.locator("#plan-check tbody tr")
    assert rows.count() == 2 and "ok" in rows.nth(1).inner_text()
    pg.click("#start")
    pg.wait_for_url(re.compile(r".*#/runs/.+"), timeout=10_000)
    run_id = pg.inner_text("#run-id")
    # live progress: the state moves through running while the page stays open
    pg.wait_for_function("document.querySelector('#run-state').textContent === 'running'", timeout=15_000,
                         polling=POLL_MS)
    pg.wait_for_function("document.querySelector('#run-progress').value > 0", timeout=15_000, polling=POLL_MS)
    assert pg.is_visible("#estop") and pg.is_visible("#abort")
    pg.wait_for_function("document.querySelector('#run-state').textContent === 'completed'", timeout=60_000,
                         polling=POLL_MS)
    pg.wait_for_selector("#results:not([hidden])", timeout=15_000)
    # the parameters with their uncertainties
    for name in ("S", "k_f", "b_f"):
        cell = pg.inner_text(f"#params tr[data-param='{name}'] td.value")
        assert "±" in cell, (name, cell)
    assert pg.inner_text("#params tr[data-param='k_f'] td:nth-child(3)") == "N/m"
    # the model structure the result rests on, and what the data determine under it
    structure = pg.text_content("#res-structure")  # behind the "details" disclosure
    assert "stiff coupling" in structure and "series stiffness" in structure, structure
    assert pg.locator("#frf tbody tr").count() == 2
    # the listed methods side by side: fd (primary) at once, the paper's PSO+ once its worker job is done
    # (behind the "details" disclosure for the expert: opened as a person would)
    pg.click("#methods-details > summary")
    pg.wait_for_selector("#methods tr[data-method='pso+/h2'][data-status='done']", timeout=60_000)
    fd_row, pso_row = "#methods tr[data-method='fd/auto']", "#methods tr[data-method='pso+/h2']"
    assert pg.inner_text(f"{fd_row} td:first-child").startswith("★ fd")
    assert "±" in pg.inner_text(f"{fd_row} td[data-param='k_f']")
    for name in ("S", "k_f", "b_f"):  # a value with its z against fd, or why PSO+ withholds it
        cell = pg.inner_text(f"{pso_row} td[data-param='{name}']")
        assert ("±" in cell and "z" in cell) or cell.startswith("withheld: "), (name, cell)
    results = daemon.c().get(f"/runs/{run_id}/results").json()
    assert [(m["method"], m["status"]) for m in results["methods"]] == [("fd", "done"), ("pso+", "done")]
    assert pg.inner_text("#run-lost") == "0"
    # the plots load (or the page says why there are none); the report and recording are linked
    imgs = pg.locator("#plots img")
    if imgs.count():
        pg.wait_for_function("[...document.querySelectorAll('#plots img')]"
                             ".every(i => i.complete && i.naturalWidth > 0)", timeout=60_000, polling=POLL_MS)
        assert {imgs.nth(i).get_attribute("data-plot") for i in range(imgs.count())} >= {"bode", "residuals"}
    else:
        assert "not available" in pg.inner_text("#plots")
    assert pg.get_attribute("#recording-link", "href") == f"/runs/{run_id}/recording"
    pg.wait_for_function("document.querySelector('#discrepancy').dataset.loaded === '1' || "
                         "document.querySelector('#discrepancy').textContent.startsWith('not available')",
                         timeout=60_000, polling=POLL_MS)
    assert "residual" in pg.text_content("#discrepancy") or "not available" in pg.inner_text("#discrepancy")
    if pg.evaluate("document.querySelector('#discrepancy').dataset.loaded === '1'"):
        # the result's sentence and the model gap's go through the page's one rule for findings that agree
        gap = daemon.c().get(results["discrepancy"]).json()
        rule = pg.evaluate("([c, g]) => pageFindings(c, g)", [results["checks"], gap])
        assert pg.inner_text("#res-summary").endswith(rule["tail"]), rule
        assert pg.text_content("#discrepancy p.plain") == rule["gap"], rule
    assert daemon.c().get(f"/runs/{run_id}").json()["state"] == "completed"
    # the run is listed on the start page
    pg.click("text=start another run")
    pg.wait_for_selector(f"#runs a:has-text('{run_id}')", timeout=10_000)


def test_unsafe_input_is_refused_with_the_field_named(page: object, daemon: Daemon) -> None:
    pg = page
    pg.wait_for_function("document.querySelector('#hint-frequency').textContent.length > 0", polling=POLL_MS)
    log_in(pg, daemon)
    pg.fill("#frequencies", "10, 60")
    pg.fill("#radius_mm", "10")
    assert "radius too large" in pg.locator("#plan-check tbody tr").nth(1).inner_text()
    pg.click("#start")
    err = pg.locator(".err[data-for='crank_radius_m']")
    err.wait_for(timeout=10_000)
    pg.wait_for_function("document.querySelector(\".err[data-for='crank_radius_m']\").textContent.length > 0",
                         polling=POLL_MS)
    text = err.inner_text()
    assert "step 2 crank_radius_m" in text and "peak force" in text  # steps counted from 1 for people
    assert "#/runs/" not in pg.url


def test_without_login_the_page_says_so_and_emergency_stop_works(page: object, daemon: Daemon) -> None:
    pg = page
    pg.wait_for_function("document.querySelector('#hint-frequency').textContent.length > 0", polling=POLL_MS)
    pg.fill("#frequencies", "10")
    pg.fill("#radius_mm", "1")
    pg.click("#start")
    pg.wait_for_function("document.querySelector('#form-msg').textContent.includes('log in')", polling=POLL_MS)
    # a run started elsewhere is stopped from the page
    rid = daemon.start_run(freqs=(10.0,), record_s=30.0)
    daemon.wait_state(rid, ("running",))
    pg.click("#estop")
    pg.wait_for_selector("#banner:not([hidden])")
    assert "EMERGENCY STOP" in pg.inner_text("#banner") and rid in pg.inner_text("#banner")
    assert daemon.wait_state(rid)["state"] == "aborted"
    assert "stop port: POST /stop (origin http://127.0.0.1:" in daemon.log()  # the page used the stop port
    # the stop latches: the page shows it, and an operator with the token acknowledges it there
    pg.wait_for_selector("#latch:not([hidden])", timeout=15_000)
    assert "page" in pg.inner_text("#latch") and pg.is_disabled("#start")
    r = daemon.c().post("/runs", json=run_body(freqs=(10.0,)))
    assert r.status_code == 409 and "latched" in r.json()["detail"]
    log_in(pg, daemon)
    pg.fill("#ack-note", "crank checked")
    pg.click("#ack")
    pg.wait_for_selector("#latch", state="hidden", timeout=15_000)
    assert "acknowledged by tina" in pg.inner_text("#banner")
    h = daemon.c().get("/health").json()
    assert not h["estop"]["latched"] and h["estop"]["last_acknowledged_by"] == "tina"


def test_a_drive_that_does_not_stop_is_shown_on_the_page(browser: object,
                                                        rig_and_daemon: tuple[SimRigProcess, Daemon]) -> None:
    """The emulator plays a drive that takes the stop and keeps turning: the page's stop says so at
    once, and its header shows the drive fault until the drive is repaired."""
    emu, d = rig_and_daemon
    rid = d.start_run(freqs=(10.0,), record_s=60.0)
    d.wait_state(rid, ("running",), step_state="recording")
    emu.ignore_stops()
    try:
        with open_page(browser, d.url + "/", no_errors=False) as pg:
            pg.click("#estop")
            pg.wait_for_selector("#banner:not([hidden])", timeout=15_000)
            assert "THE CRANK STILL TURNS" in pg.inner_text("#banner")
            pg.wait_for_selector("#drive-fault", timeout=15_000)
            assert "DRIVE DOES NOT STOP" in pg.inner_text("#health") and pg.is_disabled("#start")
            emu.ignore_stops(False)  # repaired: the page's acknowledgement is taken, the fault goes
            log_in(pg, d)
            pg.click("#ack")
            pg.wait_for_selector("#drive-fault", state="detached", timeout=15_000)
            assert "acknowledged by tina" in pg.inner_text("#banner")
    finally:
        emu.ignore_stops(False)  # the daemon's end stops the crank
