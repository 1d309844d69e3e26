"""The README's first steps, word for word, in a real headless Chromium: start the simulated station,
open the page, log in as the README says with the password the station printed at its start, start a
run from the form, watch it finish, read the results, open the report and the certificate.

Skipped only when /usr/bin/chromium is absent and CI is not set; under CI it must run.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from tests.station_support import Daemon, daemon_config
from tests.web_support import open_page

pytestmark = pytest.mark.slow  # a real daemon, a real run and a real browser

README = Path(__file__).resolve().parents[1] / "README.md"


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


def test_the_readme_works_as_written(browser: object, tmp_path: Path) -> None:
    user = _readme_user()
    cfg = daemon_config(tmp_path / "recordings", render_at_start=True)  # the report renders while the run runs
    cfg["identification"]["methods"] = [{"method": "fd", "model": "auto"}]  # the primary; others: test_web.py
    with Daemon(tmp_path, config=cfg) as d:
        log = d.log()
        assert "simulated station: log in on" in log and "approver" in log
        password = _printed_password(log, user)
        with open_page(browser, d.url + "/") as pg:
            pg.wait_for_function("document.querySelector('#hint-frequency').textContent.length > 0")
            assert user in pg.inner_text("#login-hint")  # the page says whom to log in as, too
            # logged out, starting a run answers in words a person understands
            pg.fill("#frequencies", "10, 20")
            pg.fill("#radius_mm", "1")
            pg.click("#start")
            pg.wait_for_function("document.querySelector('#form-msg').textContent.length > 0")
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
            pg.wait_for_function("document.querySelector('#run-state').textContent === 'completed'", timeout=60_000)
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
