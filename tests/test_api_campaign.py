"""POST /campaigns on the daemon's app in-process over a store seeded with two finished runs of the
simulated transducer with different top masses, identified jointly (once, stored, for the tests
that read the campaign); the refusals and error statuses."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.station_support import CAPPED, HeldApp, Seed, daemon_config, seed_runs

# the campaign is computed in the render worker (a process start)
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("api_campaign")]
Runs = tuple[HeldApp, list[str]]
END_MASS = 0.12  # the simulated transducer's (config/sim-5kN.yaml)


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[HeldApp, list[str]]]:
    rec = tmp_path_factory.mktemp("campaign") / "recordings"
    ids = seed_runs(daemon_config(rec), [Seed((10.0, 80.0), 2e-4, top, seed=s)
                                         for s, top in ((1, 5.0), (2, 25.717))])
    app = HeldApp(rec, **CAPPED)  # idle while the render worker computes: the lower cap
    try:
        yield app, ids
    finally:
        app.close()


@pytest.fixture(scope="module")
def stored(runs: Runs) -> dict[str, Any]:
    """The two runs' campaign, computed once and stored beside both recordings (the response)."""
    d, ids = runs
    r = d.post("/campaigns", json={"runs": ids, "store": True})
    assert r.status_code == 200, r.text
    return dict(r.json())


def test_two_runs_separate_the_end_mass(runs: Runs, stored: dict[str, Any]) -> None:
    ids, out = runs[1], stored
    assert out["status"] == "separated" and out["runs"] == ids
    me = out["parameters"]["m_e"]
    assert abs(me["value"] - END_MASS) < 3 * me["std"]
    assert all("/" not in rec["path"] for rec in out["recordings"])  # no server paths
    assert [rec["load_mass_kg"]["value"] for rec in out["recordings"]] == pytest.approx([5.45, 26.167])


def test_one_run_is_conditional_on_the_stated_end_mass(runs: Runs) -> None:
    d, ids = runs
    out = d.post("/campaigns", json={"runs": ids[:1]}).json()
    assert out["status"] == "conditional" and out["parameters"]["m_e"]["value"] is None
    assert next(c for c in out["checks"] if c["name"] == "end_mass_separation")["severity"] == "refused"


def test_errors(runs: tuple[HeldApp, list[str]], tmp_path: Path) -> None:
    d, ids = runs
    c = d
    r = c.post("/campaigns", json={"runs": [ids[0], ids[0]]})
    assert r.status_code == 422 and "more than once" in r.json()["errors"][0]["msg"]
    assert c.post("/campaigns", json={"runs": ["no-such-run"]}).status_code == 404
    assert c.post("/campaigns", json={"runs": []}).status_code == 422
    assert c.post("/campaigns", json={"runs": ["../etc"]}).status_code == 422


def test_campaigns_need_the_token_and_the_runs_report_shows_the_stored_campaign(runs: Runs,
                                                                               stored: dict[str, Any]) -> None:
    d, ids = runs
    assert d.post("/campaigns", json={"runs": ids}, anon=True).status_code == 401  # a computation: the token, always
    assert d.post("/campaigns", json={"runs": ids, "store": True}, anon=True).status_code == 401
    assert stored["stored_as"] == "<run>.results/results.campaign.h5"
    html = d.get(f"/runs/{ids[0]}/report").text
    assert "Multi-mass campaign" in html and 'data-key="campaign.m_e"' in html
