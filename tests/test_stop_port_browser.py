"""The stop port against DNS rebinding, in a real headless Chromium.

A page of another site (``http://rebind.test:<stop port>/``) whose name then resolves to 127.0.0.1
(Chromium's ``--host-resolver-rules``; the page itself is what the other site served before the
name was rebound, handed to the browser by Playwright) makes a same-origin ``fetch('/stop')``: the
browser sends ``Host: rebind.test:<port>``, ``Sec-Fetch-Site: same-origin`` and its own Origin, so
no cross-site rule catches it; the stop port's Host check must.  The same page under ``localhost``
(a page of this computer) stops.

Chromium's own Private Network Access checks would block the public page's request to a loopback
address; Firefox and Safari have none, so the browser here runs without them (the station must not
rely on them)."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from station.commands.stopport import daemon_stop_port
from station.rigproc.stopport import StopPort
from tests.station_support import HeldApp
from tests.web_support import ARGS, CHROMIUM, sync_api

PAGE = """<!doctype html><html><body><script>
async function go(method) {
  try {
    const r = await fetch('/stop', {method});
    return {status: r.status, body: await r.text()};
  } catch (e) { return {status: 0, body: String(e)}; }
}
</script></body></html>"""

REBINDING = ["--host-resolver-rules=MAP rebind.test 127.0.0.1",
             "--disable-features=BlockInsecurePrivateNetworkRequests,PrivateNetworkAccessSendPreflights,"
             "PrivateNetworkAccessRespectPreflightResults,LocalNetworkAccessChecks"]


@pytest.fixture
def station(tmp_path: Path) -> Iterator[tuple[HeldApp, StopPort]]:
    # the virtual rig at real time: unlimited, its DAQ would stream on a core of its own all along while
    # the browser works (the test needs the stop port, not the rig's speed)
    app = HeldApp(tmp_path / "rec", max_speedup=1.0)
    try:
        port = daemon_stop_port(app.manager, app.manager.settings, "127.0.0.1", 0).start()
        try:
            yield app, port
        finally:
            port.close()
    finally:
        app.close()


@pytest.mark.slow  # ~3 s: the app, a browser of its own (the resolver rule is a launch argument)
def test_a_rebound_name_cannot_stop_or_read_while_localhost_can(station: tuple[HeldApp, StopPort]) -> None:
    app, sp = station
    with sync_api.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM), args=[*ARGS, *REBINDING])
        try:
            def served(name: str) -> Any:
                """A page at http://<name>:<stop port>/ as another site would serve it."""
                ctx = browser.new_context()
                pg = ctx.new_page()
                url = f"http://{name}:{sp.port}/"
                pg.route(url, lambda route: route.fulfill(status=200, content_type="text/html", body=PAGE))
                pg.goto(url)
                return pg

            evil = served("rebind.test")
            for method in ("GET", "POST"):
                got = evil.evaluate("m => go(m)", method)
                assert got["status"] == 403, got
                assert "not a name of this station" in json.loads(got["body"])["detail"]
            assert not app.manager.latch.latched  # nothing was stopped, nothing latched
            # a page of this computer (a loopback name) still stops
            own = served("localhost")
            got = own.evaluate("m => go(m)", "POST")
            assert got["status"] == 200, got
            assert json.loads(got["body"])["stop_commanded"] is True
            assert app.manager.latch.latched
        finally:
            browser.close()
