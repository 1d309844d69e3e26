"""The technicians' page end to end in a real headless Chromium (Debian's, driven by Playwright):
fill the form, watch a simulated run finish, read the results; refused input; the emergency stop; a
drive that does not stop.

And on the same page: an administrator manages the users (adds a technician, a refused password
shown at its field, issues them an API token shown once; the technician sees what the role allows,
lists his own API tokens and revokes one; the administrator disables him and his next request is
refused; the audit trail records each change, without secrets), and a check transducer's history
page shows the control charts of each parameter with their limits, the out-of-control points of a
stepped sensitivity in red, the as-found comparison and the recommended intervals (a
recommendation, never a number made up).

One daemon for the module, on the simulated rig's emulators run as a process of their own (the
configuration's physics loaded into them) and reached as a real rig's devices, so that a test can
make the drive fail to stop (``SimRigProcess.ignore_stops``); its store holds the check
transducer's history before it starts.  The tests run in the file's order, the drive's test last.

Skipped only when no Chromium is installed and CI is not set; under CI it must run.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from drivers.sim import SimRigProcess
from station.config import parse_config, to_rig_physics
from station.lab import policy
from station.lab.store import Store
from tests.history_support import TX, add_runs, add_transducer
from tests.station_support import Daemon, daemon_config, run_body
from tests.web_support import POLL_MS, log_in, open_page

# a real daemon, a real run and a real browser: the end-to-end layer
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("web")]

NEW_PASSWORD = "tomas-secret-pw"


@pytest.fixture(scope="module")
def history(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[str]]:
    """The daemon's folder, its store (in ``recordings``) holding the check transducer's 16 completed
    runs, S stepped by 4 u from the 11th, and its policy; the runs' ids."""
    tmp = tmp_path_factory.mktemp("web")
    data_dir = tmp / "recordings"
    data_dir.mkdir()
    store = Store(data_dir / "station.db")
    try:
        add_transducer(store)
        ids = add_runs(store, data_dir, 16, step_at=10, step_u=4.0)
        policy.put_policy(store, policy.Policy(TX, {"S": 0.005}, 30.0, True), "admin")
    finally:
        store.close()
    return tmp, ids


@pytest.fixture(scope="module")
def rig_and_daemon(history: tuple[Path, list[str]]) -> Iterator[tuple[SimRigProcess, Daemon]]:
    """The emulators' process (the configuration's physics) and the daemon on it as its devices,
    over the store of ``history``."""
    tmp = history[0]
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


def test_admin_adds_issues_token_and_disables_a_user(browser: object, daemon: Daemon) -> None:
    console: list[str] = []
    with open_page(browser, daemon.url + "/") as admin:
        admin.on("console", lambda m: console.append(m.text))
        log_in(admin, daemon, "ada")
        admin.wait_for_selector("#nav-users:not([hidden])")
        admin.goto(daemon.url + "/#/users")
        admin.wait_for_selector("#users tr[data-user='ada']", timeout=10_000)
        assert [admin.get_attribute(f"#user-roles input >> nth={i}", "value") for i in range(3)] == \
            ["technician", "approver", "admin"]  # the closed set the API publishes
        assert "at least 10 characters" in admin.inner_text("#user-password-rule")

        # the API's refusal of a short password is shown at the password field, and nothing is saved
        admin.fill("#user-name", "tomas")
        admin.check("#user-roles input[value='technician']")
        admin.fill("#user-password", "short")
        admin.click("#user-save")
        admin.wait_for_function("document.querySelector('#user-form .err[data-for=password]').textContent !== ''",
                                polling=POLL_MS)
        assert "10 characters" in admin.inner_text("#user-form .err[data-for=password]")
        assert admin.input_value("#user-password") == ""  # the page keeps no password
        assert "tomas" not in [u["name"] for u in daemon.c().get("/users").json()]

        admin.fill("#user-password", NEW_PASSWORD)
        admin.click("#user-save")
        row = "#users tr[data-user='tomas']"
        admin.wait_for_selector(row, timeout=10_000)
        assert admin.inner_text("#user-form .err[data-for=password]") == ""
        cells = admin.locator(f"{row} td").all_inner_texts()
        assert cells[:3] == ["tomas", "technician", "active"] and cells[3].endswith("by ada"), cells

        # a token for tomas, shown once with the warning; gone from the page after "done"
        admin.select_option("#token-user", "tomas")
        admin.fill("#token-label", "nightly script")
        admin.click("#token-issue")
        admin.wait_for_selector("#token-shown:not([hidden])")
        token = admin.inner_text("#token-text").strip()
        assert token.startswith("sct_") and "not shown again" in admin.inner_text("#token-shown")
        admin.click("#token-done")
        assert admin.is_hidden("#token-shown") and token not in admin.content()
        me = httpx.get(daemon.url + "/me", headers={"Authorization": f"Bearer {token}"}, timeout=10)
        assert me.status_code == 200 and me.json()["user"]["name"] == "tomas", me.text

        # tomas logs in: a technician's page (run form, no register editing), no users section
        with open_page(browser, daemon.url + "/") as tech:
            tech.fill("#login-name", "tomas")
            tech.fill("#login-password", NEW_PASSWORD)
            tech.click("#login")
            tech.wait_for_selector("#me:not([hidden])", timeout=10_000)
            assert tech.inner_text("#me-name") == "tomas (technician)"
            assert tech.is_hidden("#nav-users") and tech.is_visible("#start")
            tech.goto(daemon.url + "/#/users")
            tech.wait_for_selector("#view-home:not([hidden])")
            assert tech.is_hidden("#view-users") and tech.locator("#users tbody tr").count() == 0
            assert tech.evaluate("fetch('/users').then((r) => r.status)") == 403  # the API refuses too
            tech.goto(daemon.url + "/#/register")
            tech.wait_for_selector("#reg-transducers tbody tr", timeout=10_000)
            assert tech.is_hidden("#reg-admin")

            # API tokens: tomas sees his own only, the administrator everyone's; tomas revokes his on the page
            other = daemon.c().post("/users/ada/tokens", json={"label": "ada's script"}).json()["token"]
            later = daemon.c().post("/users/tomas/tokens", json={"label": "spare"}).json()["token"]
            admin.goto(daemon.url + "/#/tokens")
            admin.wait_for_selector("#tokens td:has-text('spare')", timeout=10_000)
            rows = {r.split("\t")[2]: r.split("\t")[1] for r in admin.locator("#tokens tbody tr").all_inner_texts()}
            assert {"nightly script": "tomas", "spare": "tomas", "ada's script": "ada"}.items() <= rows.items(), rows
            tech.click("#nav-tokens a")
            tech.wait_for_selector("#tokens td:has-text('spare')", timeout=10_000)
            mine = [r.split("\t")[1:3] for r in tech.locator("#tokens tbody tr").all_inner_texts()]
            assert sorted(mine) == [["tomas", "nightly script"], ["tomas", "spare"]], mine
            nightly = tech.locator("#tokens tr:has-text('nightly script')")
            tech.once("dialog", lambda d: d.accept())
            nightly.locator(".token-revoke").click()
            tech.wait_for_selector("#tokens tr.bad:has-text('nightly script')", timeout=10_000)
            assert "revoked" in nightly.locator("td").nth(4).inner_text()
            assert nightly.locator(".token-revoke").count() == 0
            assert httpx.get(daemon.url + "/me", headers={"Authorization": f"Bearer {token}"},
                             timeout=10).status_code == 401  # revoked
            assert httpx.get(daemon.url + "/me", headers={"Authorization": f"Bearer {other}"},
                             timeout=10).status_code == 200  # another's untouched
            ada_id = daemon.c().get("/tokens", params={"user": "ada"}).json()[0]["id"]
            assert tech.evaluate(f"fetch('/tokens/{ada_id}', {{method: 'DELETE'}}).then((r) => r.status)") == 404

            # the administrator disables tomas; the next request of tomas's page is refused
            admin.goto(daemon.url + "/#/users")
            admin.wait_for_selector(row, timeout=10_000)
            admin.click(f"{row} .user-edit")
            assert admin.input_value("#user-name") == "tomas"
            assert admin.is_checked("#user-roles input[value='technician']")
            admin.check("#user-disabled")
            admin.click("#user-save")
            admin.wait_for_selector(f"{row}.bad", timeout=10_000)
            assert admin.locator(f"{row} td").nth(2).inner_text() == "disabled"
            tech.reload()
            tech.wait_for_function("document.querySelector('#banner').textContent.includes('session was ended')",
                                   timeout=10_000, polling=POLL_MS)
            assert tech.is_visible("#login-form") and tech.is_hidden("#me")
        assert httpx.get(daemon.url + "/me", headers={"Authorization": f"Bearer {later}"},
                         timeout=10).status_code == 401  # a disabled user's token too

        # the audit trail (API and page): each change by ada, no password or token in it
        admin.goto(daemon.url + "/#/audit")
        admin.wait_for_selector("#audit td:has-text('user.token_issued')", timeout=10_000)
        assert "user:tomas" in admin.inner_text("#audit")
    trail = daemon.c().get("/audit", params={"target": "user:tomas"}).json()["entries"][::-1]
    mine = [(e["who"], e["action"], e["details"].get("disabled")) for e in trail if e["who"] == "ada"]
    assert mine == [("ada", "user.changed", False), ("ada", "user.token_issued", None), ("ada", "user.changed", True)]
    assert [e["action"] for e in trail if e["who"] == "tomas"] == ["user.login", "user.token_revoked"]
    assert trail[0]["details"]["password_changed"] is True and trail[-1]["details"]["password_changed"] is False
    for secret in (token, later, other, NEW_PASSWORD):
        assert secret not in str(trail) and not any(secret in line for line in console)


def test_history_page_shows_the_charts_and_their_out_of_control_points(browser: object, daemon: Daemon,
                                                                      history: tuple[Path, list[str]]) -> None:
    ids = history[1]
    with open_page(browser, daemon.url + f"/#/transducers/{TX}") as page:
        page.wait_for_selector("#hist-trends svg", timeout=20_000)
        text = page.inner_text("#hist-trends")
        assert "check transducer" in text and "sensitivity S" in text and "natural frequency f_0" in text
        assert "EWMA (λ 0.2, limits ±3 s)" in text and "as found in run015" in text
        assert "recommended intervals (for a person to decide)" in text
        # the stepped runs are red on the S charts, and no k_f point is
        red = page.eval_on_selector_all("#hist-trends svg[aria-label='S control chart'] circle[fill='#c00'] title",
                                        "els => els.map(e => e.textContent)")
        assert red and all(t.split(":")[0] in ids[10:] for t in red)
        assert page.eval_on_selector_all("#hist-trends svg[aria-label='k_f control chart'] circle[fill='#c00']",
                                         "els => els.length") == 0


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
