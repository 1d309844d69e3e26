"""Debian's headless Chromium for the page tests, driven by Playwright (no browser download).

Importing this module skips the importing test module only when /usr/bin/chromium is absent and CI
is not set; under CI the browser tests must run.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

CHROMIUM = Path("/usr/bin/chromium")
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync"]

if not CHROMIUM.exists() and not os.environ.get("CI"):
    pytest.skip("Debian's chromium is not installed (apt-get install chromium); CI runs this test",
                allow_module_level=True)

if os.environ.get("CI"):
    from playwright import sync_api
else:
    sync_api = pytest.importorskip("playwright.sync_api")

__all__ = ["ARGS", "CHROMIUM", "log_in", "sync_api"]

PASSWORDS = {"tina": "tina-secret-pw", "anton": "anton-secret-pw", "ada": "ada-secret-pw1"}
ROLES = {"tina": "technician", "anton": "approver", "ada": "admin"}


def log_in(page: object, daemon: object, name: str = "tina") -> None:
    """Make user ``name`` (technician tina, approver anton, administrator ada) with the daemon's admin token, then log
    in on the page as a person would (the session cookie is the page's only credential)."""
    r = daemon.c().put(f"/users/{name}", json={"role": ROLES[name], "password": PASSWORDS[name]})  # type: ignore[attr-defined]
    assert r.status_code == 200, r.text
    page.fill("#login-name", name)  # type: ignore[attr-defined]
    page.fill("#login-password", PASSWORDS[name])  # type: ignore[attr-defined]
    page.click("#login")  # type: ignore[attr-defined]
    page.wait_for_selector("#me:not([hidden])", timeout=10_000)  # type: ignore[attr-defined]
