"""POST /runs/{id}/compensation (and its plot) and POST /compensation/apply on the daemon's app
in-process over a store seeded with one finished, identified run of the simulated transducer."""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np
import pytest

from tests.station_support import HeldApp, Seed, daemon_config, seed_runs

pytestmark = pytest.mark.slow  # a seeded store and a daemon app
Held = tuple[HeldApp, str]
BODY = {"sample_rate_hz": 50000, "mounted_mass_kg": 1.0, "band_hz": [0, 4000], "allow_extrapolation": True}


@pytest.fixture(scope="module")
def held(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Held]:
    rec = tmp_path_factory.mktemp("comp") / "recordings"
    ids = seed_runs(daemon_config(rec), [Seed((10.0, 80.0), 2e-4, 25.717, seed=1)])
    app = HeldApp(rec, max_speedup=1.0)  # no run on its rig: its idle DAQ streamed in real time, not at a core's speed
    try:
        yield app, ids[0]
    finally:
        app.close()


def test_design_then_apply(held: Held) -> None:
    d, rid = held
    r = d.post(f"/runs/{rid}/compensation", json=BODY)
    assert r.status_code == 200, r.text
    filt = r.json()
    assert filt["taps"] == 64 and filt["unit_out"] == "N" and filt["sample_rate_hz"] == 50000
    assert "extrapolation" in {c["name"] for c in filt["findings"]}
    assert "/" not in filt["transducer"]["origin"]  # no server paths
    png = d.post(f"/runs/{rid}/compensation/plot", json=BODY)
    assert png.status_code == 200 and png.content[:4] == b"\x89PNG"
    x = list(0.002 * 100 * np.exp(-((np.arange(500) - 250) / 20.0) ** 2))
    a = d.post("/compensation/apply", json={"filter": filt, "signal": x, "sample_rate_hz": 50000, "noise_std": 1e-4})
    assert a.status_code == 200, a.text
    out = a.json()
    assert len(out["estimate"]) == len(out["u"]) == 500 and min(out["u"]) > 0 and out["delay_removed"]
    assert math.isclose(out["time_s"][0], -filt["delay_s"])


def test_refusals_are_422_with_the_reason(held: Held) -> None:
    d, rid = held
    r = d.post(f"/runs/{rid}/compensation", json={**BODY, "allow_extrapolation": False})
    assert r.status_code == 422 and "beyond the calibrated range" in r.text
    r = d.post(f"/runs/{rid}/compensation", json={"sample_rate_hz": 50000, "mounted_mass_kg": 1.0})
    assert r.status_code == 422 and "band_hz or cutoff_hz" in r.text
    filt = d.post(f"/runs/{rid}/compensation", json=BODY).json()
    r = d.post("/compensation/apply", json={"filter": filt, "signal": [0.0] * 10, "sample_rate_hz": 20000})
    assert r.status_code == 422 and "designed for 50000 Hz" in r.text
    r = d.post("/compensation/apply", json={"filter": {"format": "x"}, "signal": [0.0], "sample_rate_hz": 1})
    assert r.status_code == 422 and "not a compensation filter" in r.text
    r = d.post("/compensation/apply", content=b'{"filter": %s, "signal": [0.0, NaN], "sample_rate_hz": 50000}'
               % __import__("json").dumps(filt).encode(), headers={"Content-Type": "application/json"})
    assert r.status_code == 422 and "not finite" in r.text
    r = d.post("/runs/no-such-run/compensation", json=BODY)
    assert r.status_code in (404, 422)
