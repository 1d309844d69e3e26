"""Debian's headless Chromium for the page tests, driven by Playwright (no browser download).

The browser is Debian's ``chromium-headless-shell`` (Chromium's headless shell: the same Blink and V8
without the desktop browser's layer, what Playwright itself runs for headless Chromium; a page costs
it about a third of the CPU the full ``chromium`` takes), else Debian's ``chromium``.  Importing
this module skips the importing test module only when neither is installed and CI is not set; under
CI the browser tests must run.
"""

from __future__ import annotations

import contextlib
import os
import weakref
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.station_support import PASSWORDS, ROLES

HEADLESS_SHELL, FULL = Path("/usr/bin/chromium-headless-shell"), Path("/usr/bin/chromium")
CHROMIUM = HEADLESS_SHELL if HEADLESS_SHELL.exists() else FULL
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync"]

# ``page.wait_for_function(..., polling=POLL_MS)``: the condition is checked every 100 ms; Playwright's
# default checks it at every animation frame, which keeps the page's renderer painting (about 7 % of
# a core for as long as a test waits on a run, against 1 %)
POLL_MS = 100

if not CHROMIUM.exists() and not os.environ.get("CI"):
    pytest.skip("Debian's chromium-headless-shell is not installed (apt-get install chromium-headless-shell); "
                "CI runs this test",
                allow_module_level=True)

if os.environ.get("CI"):
    from playwright import sync_api
else:
    sync_api = pytest.importorskip("playwright.sync_api")


__all__ = ["ARGS", "CHROMIUM", "POLL_MS", "chromium", "log_in", "open_page", "sync_api"]


@contextlib.contextmanager
def chromium() -> Iterator[Any]:
    """Debian's Chromium, headless, launched by Playwright (the ``browser`` fixture of tests/conftest.py
    holds one per test module); closed on leaving."""
    with sync_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=str(CHROMIUM), args=ARGS)
        try:
            yield b
        finally:
            b.close()


@contextlib.contextmanager
def open_page(browser: Any, url: str, *, no_errors: bool = True, **context: Any) -> Iterator[Any]:
    """A page at ``url`` in a new browser context of its own (``context``: Playwright's
    ``new_context`` options, e.g. ``viewport``); the context is closed on leaving, and then (with
    ``no_errors``) no JavaScript error may have happened on the page."""
    ctx = browser.new_context(**context)
    errors: list[str] = []
    try:
        pg = ctx.new_page()
        pg.on("pageerror", lambda e: errors.append(str(e)))
        pg.goto(url)
        yield pg
    finally:
        ctx.close()
    assert not no_errors or errors == [], errors


# the users each daemon was given by ``log_in`` (a module's tests log in as the same person again and
# again: the station's password hash, scrypt, is made once per user and daemon, not once per login)
_MADE: weakref.WeakKeyDictionary[Any, set[str]] = weakref.WeakKeyDictionary()


def log_in(page: object, daemon: object, name: str = "tina") -> None:
    """Make user ``name`` (technician tina, approver anton, administrator ada) with the daemon's admin token (once
    per daemon), then log in on the page as a person would (the session cookie is the page's only credential)."""
    made = _MADE.setdefault(daemon, set())
    if name not in made:
        r = daemon.c().put(f"/users/{name}", json={"role": ROLES[name], "password": PASSWORDS[name]})  # type: ignore[attr-defined]
        assert r.status_code == 200, r.text
        made.add(name)
    page.fill("#login-name", name)  # type: ignore[attr-defined]
    page.fill("#login-password", PASSWORDS[name])  # type: ignore[attr-defined]
    page.click("#login")  # type: ignore[attr-defined]
    page.wait_for_selector("#me:not([hidden])", timeout=10_000)  # type: ignore[attr-defined]
