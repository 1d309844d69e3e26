"""The page's compensation section in a real headless Chromium against a real daemon with one seeded,
identified run: state the application, see the filter in plain words with its details and plot,
download it, correct an uploaded signal file and download the result; a refusal says why."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from tests.station_support import Daemon, Seed
from tests.web_support import log_in, open_page

pytestmark = pytest.mark.slow  # a real daemon and a browser


@pytest.fixture(scope="module")
def daemon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Daemon]:
    with Daemon(tmp_path_factory.mktemp("webcomp"), seeds=[Seed((10.0, 80.0), 2e-4, 25.717, seed=1)]) as d:
        yield d


def test_design_download_and_correct_a_signal_on_the_page(browser: object, daemon: Daemon, tmp_path: Path) -> None:
    rid = daemon.seeded[0]
    with open_page(browser, daemon.url + f"/#/runs/{rid}") as pg:
        pg.wait_for_selector("#results:not([hidden])", timeout=30_000)
        pg.fill("#comp-mass", "1")
        pg.click("#comp-design")  # the page's POSTs need its session
        pg.wait_for_function("document.querySelector('#comp-msg').textContent.includes('not logged in')")
        log_in(pg, daemon)
        pg.wait_for_selector("#comp-form input#comp-mass:visible", timeout=30_000)
        pg.fill("#comp-mass", "1")
        pg.fill("#comp-band", "4000")
        pg.click("#comp-design")  # 4 kHz is beyond the calibrated 10 to 80 Hz: refused with the reason
        pg.wait_for_function("!['', 'designing…'].includes(document.querySelector('#comp-msg').textContent)",
                             timeout=60_000)
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
                             "document.querySelector('#comp-bode').naturalWidth > 0", timeout=60_000)
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
        pg.wait_for_function("document.querySelector('#comp-apply-msg').textContent.includes('line 3')")
        assert "not a finite number" in pg.inner_text("#comp-apply-msg")
