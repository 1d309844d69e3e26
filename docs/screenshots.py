"""The screenshots of docs/web.md, taken from the page itself: starts ``station serve --sim`` in a
temporary folder, logs in on the page as the demonstration technician (with the password the station
printed), starts a short calibration from the form and saves, at 1280 and at 390 CSS px, the main page,
the run while it records, its results and its certificate as PNG files (``docs/img/web-*.png``; heights
capped, colours reduced to a palette so that they stay small).  The browser is Debian's headless
Chromium driven by Playwright, as in the page tests.  Prints JSON: each file with its size and the
page's width in CSS px (at 390 px it must not exceed 390: no horizontal scrolling).

    python3 docs/screenshots.py [--out docs/img]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import yaml
from PIL import Image
from playwright.sync_api import sync_playwright

from station.config import default_config_path

CHROMIUM = "/usr/bin/chromium"
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-background-networking"]
WIDTHS: dict[str, Any] = {"1280": {"width": 1280, "height": 900}, "390": {"width": 390, "height": 844}}
MAX_HEIGHT = {"1280": 2000, "390": 2600}  # CSS px kept of a long page (its top)
USER = "technician"


def _config(data: Path) -> dict[str, Any]:
    """The shipped configuration with a shorter plan (its five steps, less settling and recording) and
    the small swarm of the tests (the methods side by side finish in seconds)."""
    cfg = yaml.safe_load(default_config_path().read_text(encoding="utf-8"))
    cfg["station"]["recordings_dir"] = str(data)
    cfg["plan"].update({"settle_s": 0.5, "record_s": 1.5})
    cfg["rig"]["acceleration_hz_per_s"] = 50.0
    cfg.setdefault("identification", {})["swarm"] = {"n_particles": 24, "n_iterations": 60}
    return dict(cfg)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.contextmanager
def station(tmp: Path) -> Iterator[tuple[str, str]]:
    """``station serve --sim`` in ``tmp``; yields its URL and the printed password of :data:`USER`."""
    cfg = tmp / "station.yaml"
    cfg.write_text(yaml.safe_dump(_config(tmp / "recordings")))
    port = _free_port()
    log_path = tmp / "station.log"
    with log_path.open("wb") as log:
        proc = subprocess.Popen([sys.executable, "-m", "station.cli", "serve", "--sim", "--config", str(cfg),
                                 "--port", str(port)], stdout=log, stderr=subprocess.STDOUT, cwd=tmp,
                                env={**os.environ, "PYTHONUNBUFFERED": "1"})
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 180  # a busy machine starts it slowly
        while True:
            with contextlib.suppress(httpx.TransportError):
                if httpx.get(url + "/health", timeout=5).status_code == 200:
                    break
            if time.monotonic() > deadline or proc.poll() is not None:
                raise RuntimeError(f"the station did not start (exit code {proc.poll()}):\n"
                                   + log_path.read_text(errors="replace")[-3000:])
            time.sleep(0.2)
        found = re.findall(rf"^\s+{USER}\s+\(\w+\) password (\S+)$", log_path.read_text(errors="replace"), re.M)
        if not found:
            raise RuntimeError("the station printed no password for " + USER)
        yield url, found[-1]
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(40)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _save(page: Any, path: Path, width: str) -> dict[str, Any]:
    """A full-page screenshot cut to :data:`MAX_HEIGHT` and reduced to a 256-colour palette."""
    page.evaluate("window.scrollTo(0, 0)")  # the sticky header at the top
    page.screenshot(path=str(path), full_page=True)
    with Image.open(path) as im:
        img = im.convert("RGB")
    img = img.crop((0, 0, img.width, min(img.height, MAX_HEIGHT[width])))
    img.quantize(colors=256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE).save(path, optimize=True)
    return {"file": str(path), "bytes": path.stat().st_size, "height_px": img.height,
            "scroll_width_px": page.evaluate("document.scrollingElement.scrollWidth")}


def _log_in(page: Any, password: str) -> None:
    page.wait_for_selector("#login-name")
    page.fill("#login-name", USER)
    page.fill("#login-password", password)
    page.click("#login")
    page.wait_for_selector("#me:not([hidden])", timeout=15_000)


def capture(url: str, password: str, out: Path) -> list[dict[str, Any]]:
    """Shoot each view at each width into ``out``; returns what was saved."""
    out.mkdir(parents=True, exist_ok=True)
    shots: list[dict[str, Any]] = []
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        pages = {}
        for w, viewport in WIDTHS.items():
            phone = w == "390"
            ctx = browser.new_context(viewport=viewport, device_scale_factor=1, is_mobile=phone, has_touch=phone)
            pages[w] = pg = ctx.new_page()
            pg.goto(url + "/")
            _log_in(pg, password)
            pg.wait_for_function("document.querySelector('#hint-frequency').textContent.length > 0")
        # the technician starts the run on the wide page; the phone follows the same run
        pages["1280"].click("#start")
        pages["1280"].wait_for_url(re.compile(r".*#/runs/.+"), timeout=15_000)
        run = pages["1280"].url.split("#/runs/")[1]
        pages["390"].goto(f"{url}/#/runs/{run}")
        recording = "document.querySelector('#run-step').textContent.includes('recording')" \
                    " && document.querySelector('#run-step').textContent.includes('step 3')"
        for pg in pages.values():
            pg.wait_for_function(recording, timeout=120_000, polling=50)
        for w, pg in pages.items():
            shots.append(_save(pg, out / f"web-run-{w}.png", w))
        for w, pg in pages.items():  # (the model gap, further down, is cut off by the height cap)
            pg.wait_for_function("document.querySelector('#run-state').textContent === 'completed'", timeout=180_000)
            pg.wait_for_selector("#results:not([hidden])", timeout=60_000)
            # every method has its outcome and every plot has loaded
            pg.wait_for_function("[...document.querySelectorAll('#methods tbody tr')]"
                                 ".every((r) => !['pending', 'queued', 'running'].includes(r.dataset.status))",
                                 timeout=180_000)
            pg.wait_for_function("[...document.querySelectorAll('#plots img')]"
                                 ".every((i) => i.complete && i.naturalWidth > 0)", timeout=120_000)
            shots.append(_save(pg, out / f"web-results-{w}.png", w))
        for w, pg in pages.items():  # the main page, with the run among the recent ones
            pg.goto(f"{url}/#/")
            pg.wait_for_selector("#runs tbody tr", timeout=15_000)
            shots.append(_save(pg, out / f"web-main-{w}.png", w))
        for w, pg in pages.items():
            pg.goto(f"{url}/runs/{run}/certificate.html", timeout=120_000)
            pg.wait_for_load_state("networkidle", timeout=120_000)
            shots.append(_save(pg, out / f"web-certificate-{w}.png", w))
        browser.close()
    return shots


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "img")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="sinecal-shots-") as tmp, station(Path(tmp)) as (url, password):
        shots = capture(url, password, args.out)
    print(json.dumps({"screenshots": shots}, indent=1))
    return 0 if all(s["scroll_width_px"] <= 390 for s in shots if s["file"].endswith("-390.png")) else 1


if __name__ == "__main__":
    raise SystemExit(main())
