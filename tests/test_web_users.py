"""An administrator manages the users on the page, in a real headless Chromium against a real daemon:
adds a technician (a refused password shown at its field), issues them an API token (shown once),
the technician logs in and sees what the role allows and no users section, lists his own API tokens
(the administrator: everyone's) and revokes one, the administrator disables them and their next
request is refused; the audit trail records each change, without secrets.

And a transducer's history page: the control charts of each parameter with their limits, the
out-of-control points of a stepped sensitivity in red, the as-found comparison and the recommended
intervals (a recommendation, never a number made up).  One daemon for both, its store holding the
transducer's history before it starts."""

from __future__ import annotations

from collections.abc import Iterator

import httpx
import pytest

from station.lab import policy
from station.lab.store import Store
from tests.history_support import TX, add_runs, add_transducer
from tests.station_support import Daemon
from tests.web_support import POLL_MS, log_in, open_page

pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("web_users")]  # a real daemon and a browser

NEW_PASSWORD = "tomas-secret-pw"


@pytest.fixture(scope="module")
def history(tmp_path_factory: pytest.TempPathFactory) -> tuple[Daemon, list[str]]:
    """The daemon (not started) over a store with the check transducer's 16 completed runs, S
    stepped by 4 u from the 11th, and its policy; the runs' ids."""
    d = Daemon(tmp_path_factory.mktemp("web-users"))
    d.data_dir.mkdir(parents=True)
    store = Store(d.data_dir / "station.db")
    add_transducer(store)
    ids = add_runs(store, d.data_dir, 16, step_at=10, step_u=4.0)
    policy.put_policy(store, policy.Policy(TX, {"S": 0.005}, 30.0, True), "admin")
    store.close()
    return d, ids


@pytest.fixture(scope="module")
def daemon(history: tuple[Daemon, list[str]]) -> Iterator[Daemon]:
    with history[0] as d:
        yield d


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
                                                                      history: tuple[Daemon, list[str]]) -> None:
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
