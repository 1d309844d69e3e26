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

__all__ = ["ARGS", "CHROMIUM", "sync_api"]
