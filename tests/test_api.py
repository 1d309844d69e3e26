"""The HTTP API: every endpoint, every error status, results of a finished run, abort, emergency stop.

Most tests run the daemon's app in-process (``tests/station_support.app_in_process``: the real rig
thread on the simulated rig's in-process backends on a virtual clock, real SQLite and HDF5) over a
store seeded with a finished, identified simulated run; the tests that only read or are refused
share one such app (``held``), those that change the store or the rig start their own.  A real
``station serve --sim`` (Modbus TCP, a pty, real time) carries one whole run from POST to results
with its live events, and the emergency stop acknowledged from the command line."""

from __future__ import annotations

import asyncio
import io
import json
import shutil
import time
from collections.abc import Awaitable, Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import h5py
import httpx
import pytest
import yaml

from station.recording import read_recording, read_stored
from tests.recording_support import killed_in_place_write, small_recording
from tests.station_support import (
    AUTH,
    CAPPED,
    FINAL,
    TOKEN,
    Daemon,
    HeldApp,
    Seed,
    app_in_process,
    daemon_config,
    run_body,
    seed_runs,
    start,
    wait_state,
)

pytestmark = pytest.mark.xdist_group("api")  # its module fixture is built once: the module's tests on one worker

T = TypeVar("T")


@pytest.fixture(scope="module")
def seeded(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    """A recordings folder whose store holds one completed, identified 2-step run (10 and 20 Hz)."""
    rec = tmp_path_factory.mktemp("api") / "recordings"
    [rid] = seed_runs(daemon_config(rec), [Seed()])
    return rec, rid


@pytest.fixture(scope="class")
def held(seeded: tuple[Path, str], tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[HeldApp, str]]:
    """The app in-process over a copy of the seeded store (the tests that change it use the original),
    held open for the tests that only read or are refused (:class:`TestOneAppForReading`); its
    client, with the token, and ``anon``, without."""
    rec, rid = seeded
    copy = tmp_path_factory.mktemp("api-held") / "recordings"
    shutil.copytree(rec, copy)
    app = HeldApp(copy, **CAPPED)  # idle between the tests: the lower cap
    try:
        yield app, rid
    finally:
        app.close()


def in_app(rec: Path, fn: Callable[[httpx.AsyncClient], Awaitable[T]], **kw: Any) -> T:
    """``fn(client)`` against the app in-process on the recordings folder ``rec``."""
    async def go() -> T:
        async with app_in_process(rec, **CAPPED, **kw) as (_, c):
            return await fn(c)
    return asyncio.run(go())


@pytest.fixture(scope="module")
def daemon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Daemon]:
    with Daemon(tmp_path_factory.mktemp("api")) as d:
        yield d


@pytest.fixture(scope="module")
def completed(daemon: Daemon) -> dict:
    """A completed, identified 2-step run on the real daemon (shared, read-only), with the SSE events
    seen live."""
    rid = daemon.start_run()
    events = []
    with httpx.stream("GET", f"{daemon.url}/runs/{rid}/events", timeout=60) as r:
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/event-stream")
        name = None
        for line in r.iter_lines():
            if line.startswith("event:"):
                name = line.split(":", 1)[1].strip()
            elif line.startswith("data:"):
                events.append((name, json.loads(line.split(":", 1)[1])))
                if name == "end":
                    break
    return {"id": rid, "events": events, "status": daemon.c().get(f"/runs/{rid}").json()}


# ---------------------------------------------------------------------------------------- reading
@pytest.mark.slow
def test_health_reports_each_device_link(tmp_path: Path) -> None:
    rec_dir = tmp_path / "recordings"  # what an older station may have left: one flagged recording, one unreadable
    rec_dir.mkdir()
    killed_in_place_write(small_recording(rec_dir))
    (rec_dir / "garbage.h5").write_bytes(b"not HDF5" * 64)

    async def go(c: httpx.AsyncClient) -> dict:
        for _ in range(100):  # just after the start: the start-up's database writes may still be queued
            h = (await c.get("/health")).json()
            if h["database"]["pending_writes"] == 0:
                break
            await asyncio.sleep(0.05)
        return h
    h = in_app(rec_dir, go, token=False, workers=1)
    assert h["status"] == "ok"
    assert h["rig"]["connected"] and h["rig"]["simulated"]
    assert h["rig"]["motor"] == {"connected": True, "watchdog_error": None, "link_error": None}
    assert h["rig"]["daq"] == {"link_error": None}
    assert h["database"] == {"ok": True, "journal_mode": "wal", "pending_writes": 0, "error": None}
    assert h["worker"]["processes"] == 1
    # the start-up check repaired the flagged recording and named the unreadable one (and went on)
    assert h["recordings"]["repaired"] == ["20250101T000000-TX-1-abcdef.h5"]
    assert [u["file"] for u in h["recordings"]["unreadable"]] == ["garbage.h5"]


INVALID = [
    ({"top_mass_kg": 25.7, "steps": [{"crank_frequency_hz": 10, "crank_radius_m": 0.001}]}, ["body", "transducer_id"]),
    (run_body(freqs=(-5.0,)), ["body", "steps", 0, "crank_frequency_hz"]),
    (run_body(radius=0.0), ["body", "steps", 0, "crank_radius_m"]),
    ({**run_body(), "top_mass_kg": "heavy"}, ["body", "top_mass_kg"]),
    ({**run_body(), "steps": []}, ["body", "steps"]),
    ({**run_body(), "colour": "red"}, ["body", "colour"]),
    (run_body(record_s=0), ["body", "steps", 0, "record_s"]),
    # unsafe or impossible on this rig: checked against the limits, the field named
    ({**run_body(), "transducer_id": "OTHER-1"}, ["body", "transducer_id"]),
    (run_body(freqs=(10.0, 150.0)), ["body", "steps", 1, "crank_frequency_hz"]),
    (run_body(freqs=(10.0, 20.0, 80.0), radius=0.01), ["body", "steps", 1, "crank_radius_m"]),
    (run_body(radius=0.2), ["body", "steps", 0, "crank_radius_m"]),
]


class TestOneAppForReading:
    """The tests that only read or are refused, on one app (``held``) held open for them alone: an idle
    app's simulated rig runs its virtual clock as fast as it can, so it is closed once they are done."""

    def test_station_shows_the_limits(self, held: tuple[HeldApp, str]) -> None:
        s = held[0].get("/station", anon=True).json()
        assert s["transducer_id"] == "TX5K-0001" and s["simulated"]
        assert s["limits"]["crank_frequency_hz"] == {"min": 1.0, "max": 100.0}
        assert s["limits"]["peak_force_limit_N"] == pytest.approx(4000.0)

    @pytest.mark.slow  # the document is built on its first request: about a second of CPU
    def test_openapi_documents_every_endpoint(self, held: tuple[HeldApp, str]) -> None:
        spec = held[0].get("/openapi.json", anon=True).json()
        paths = spec["paths"]
        for p, method in [("/runs", "post"), ("/runs", "get"), ("/runs/{run_id}", "get"),
                          ("/runs/{run_id}/events", "get"), ("/runs/{run_id}/results", "get"),
                          ("/runs/{run_id}/plots/{name}.png", "get"), ("/runs/{run_id}/report", "get"),
                          ("/runs/{run_id}/recording", "get"), ("/runs/{run_id}/discrepancy", "get"),
                          ("/runs/{run_id}/discrepancy", "post"),
                          ("/runs/{run_id}/abort", "post"), ("/stop", "post"), ("/health", "get")]:
            assert method in paths[p], (p, method)
        post = paths["/runs"]["post"]
        assert post["requestBody"]["content"]["application/json"]["schema"]["$ref"].endswith("/RunRequest")
        assert {"202", "401", "409", "422"} <= set(post["responses"])
        assert "text/event-stream" in paths["/runs/{run_id}/events"]["get"]["responses"]["200"]["content"]

    def test_web_page_and_assets_are_served(self, held: tuple[HeldApp, str]) -> None:
        async def go(c: httpx.AsyncClient) -> tuple[httpx.Response, httpx.Response, httpx.Response]:
            return await c.get("/"), await c.get("/static/app.js"), await c.get("/static/style.css")
        page, js, css = held[0].call(go, anon=True)
        assert page.status_code == 200 and "EMERGENCY STOP" in page.text and "/static/app.js" in page.text
        assert js.status_code == 200
        assert css.headers["content-type"].startswith("text/css")

    def test_runs_list_and_state_filter(self, held: tuple[HeldApp, str]) -> None:
        app, rid = held

        async def go(c: httpx.AsyncClient) -> None:
            runs = (await c.get("/runs")).json()
            assert runs["count"] >= 1 and rid in [r["id"] for r in runs["runs"]]
            done = (await c.get("/runs", params={"state": "completed"})).json()
            assert all(r["state"] == "completed" for r in done["runs"]) and done["count"] >= 1
            assert (await c.get("/runs", params={"state": "aborted", "limit": 1})).json()["count"] <= 1
            assert (await c.get("/runs", params={"state": "bogus"})).status_code == 422
            assert (await c.get("/runs", params={"limit": 0})).status_code == 422
        app.call(go, anon=True)

    def test_results_have_parameters_with_uncertainties_and_frf(self, held: tuple[HeldApp, str]) -> None:
        app, rid = held
        res = app.get(f"/runs/{rid}/results", anon=True).json()
        params = {p["name"]: p for p in res["parameters"]}
        assert set(params) >= {"S", "k_f", "b_f"}
        for p in params.values():
            assert p["identifiable"] and p["value"] > 0 and 0 < p["std"] < p["value"]
        assert params["k_f"]["unit"] == "N/m"
        assert abs(params["k_f"]["value"] - 2.91e7) < 4 * params["k_f"]["std"] + 0.02 * 2.91e7  # the simulated truth
        assert res["identifiability"]["names"] == ["S", "k_f", "b_f"]
        frf = res["frequency_response"]
        assert [round(s["frequency_hz"]) for s in frf] == [10, 20]
        assert all(s["H_magnitude_std"] > 0 and s["H_phase_std_deg"] > 0 for s in frf)
        assert res["fit"]["n_points"] > 0 and len(res["fit"]["residual_rms_V"]) == 2
        assert res["discrepancy"] == f"/runs/{rid}/discrepancy"

    def test_discrepancy_takes_zero_to_eight_effects_as_an_integer(self, held: tuple[HeldApp, str]) -> None:
        app, rid = held

        async def go(c: httpx.AsyncClient) -> None:
            for bad in ("-1", "9", "true", "2.5"):
                r = await c.get(f"/runs/{rid}/discrepancy", params={"max_effects": bad})
                assert r.status_code == 422 and "max_effects" in r.text, (bad, r.status_code, r.text)
        app.call(go, anon=True)

    def test_writes_need_the_token(self, held: tuple[HeldApp, str]) -> None:
        app, rid = held

        async def go(c: httpx.AsyncClient) -> None:
            r = await c.post("/runs", json=run_body())
            assert r.status_code == 401 and r.headers["www-authenticate"] == "Bearer"
            assert (await c.post("/runs", json=run_body(), headers={"Authorization": "Bearer wrong-token"})
                    ).status_code == 401
            assert (await c.post(f"/runs/{rid}/abort")).status_code == 401
            assert (await c.get(f"/runs/{rid}")).status_code == 200  # reading is open on loopback
        app.call(go, anon=True)

    def test_invalid_or_unsafe_requests_are_422_naming_the_field(self, held: tuple[HeldApp, str]) -> None:
        async def go(c: httpx.AsyncClient) -> None:
            for body, loc in INVALID:
                r = await c.post("/runs", json=body)
                assert r.status_code == 422, (body, r.text)
                locs = [e["loc"] for e in r.json()["errors"]]
                assert loc in locs, (body, locs)
        held[0].call(go)

    def test_peak_force_message_says_the_limit(self, held: tuple[HeldApp, str]) -> None:
        r = held[0].post("/runs", json=run_body(freqs=(50.0,), radius=0.01))
        err = r.json()["errors"][0]
        assert r.status_code == 422 and err["type"] == "limit_error"
        assert "peak force" in err["msg"] and "4000 N" in err["msg"] and err["input"] == 0.01

    def test_malformed_json_is_422_not_500(self, held: tuple[HeldApp, str]) -> None:
        async def go(c: httpx.AsyncClient) -> None:
            r = await c.post("/runs", content=b'{"transducer_id": ', headers={"Content-Type": "application/json"})
            assert r.status_code == 422
            r = await c.post("/runs", content=b'{"transducer_id":"TX5K-0001","top_mass_kg":NaN,"steps":[]}',
                             headers={"Content-Type": "application/json"})
            assert r.status_code == 422
        held[0].call(go)

    def test_unknown_runs_are_404_and_bad_ids_422(self, held: tuple[HeldApp, str]) -> None:
        async def go(c: httpx.AsyncClient) -> None:
            for path in ("", "/events", "/results", "/plots/bode.png", "/report", "/recording", "/discrepancy",
                         "/proposal"):
                r = await c.get(f"/runs/20990101T000000-NOPE-000000{path}")
                assert r.status_code == 404, (path, r.status_code, r.text)
                assert "no run" in r.json()["detail"]
            for path in ("/abort", "/discrepancy"):
                assert (await c.post(f"/runs/20990101T000000-NOPE-000000{path}")).status_code == 404
            assert (await c.get("/runs/bad id!")).status_code == 422
            for evil in ("..%2F..%2Fetc%2Fpasswd", "..", "%2e%2e"):
                r = await c.get(f"/runs/{evil}/recording")
                assert r.status_code in (404, 422), (evil, r.status_code)
        held[0].call(go)


# ---------------------------------------------------------------------------------------- a whole run
@pytest.mark.slow
def test_run_goes_through_its_states_live(completed: dict) -> None:
    names = [n for n, _ in completed["events"]]
    status = [d for n, d in completed["events"] if n != "result"]  # status and end: the RunStatus
    states = [d["state"] for d in status]
    assert names[-1] == "end" and states[-1] == "completed"
    # each listed identification's outcome: fd's result, then the paper's PSO+ refusing 0.5 s records
    results = [(d["method"], d["status"]) for n, d in completed["events"] if n == "result"]
    assert results == [("fd", "done"), ("pso+", "refused")]
    assert names.index("result") < names.index("end")
    assert "running" in states and "identifying" in states
    assert states.index("running") < states.index("identifying") < states.index("completed")
    running = [d for d in status if d["state"] == "running"]
    assert {d["current_step"] for d in running} >= {0, 1}
    # status events are snapshots, at most a few per second: a loaded machine may coalesce the short
    # ramp (about 0.2 s) with the settling that follows, never the step's way to its record altogether
    seen = {d["step_state"] for d in running}
    assert "recording" in seen and seen & {"ramping", "settling"}, seen
    fractions = [d["progress"] for d in running]
    assert fractions == sorted(fractions) and max(fractions) > 0.5
    st = completed["status"]
    assert st["state"] == "completed" and st["lost_samples"] == 0 and st["samples"] > 20_000
    assert st["recording"] == f"{st['id']}.h5" and st["n_steps"] == 2 and st["reason"] == ""
    assert [s["crank_frequency_hz"] for s in st["steps"]] == [10.0, 20.0]
    assert st["steps"][0]["record_s"] == 0.5  # defaulted from the configured plan


@pytest.mark.slow
def test_results_of_a_live_run(daemon: Daemon, completed: dict) -> None:
    res = daemon.c().get(f"/runs/{completed['id']}/results").json()
    k_f = {p["name"]: p for p in res["parameters"]}["k_f"]
    assert k_f["identifiable"] and abs(k_f["value"] - 2.91e7) < 4 * k_f["std"] + 0.02 * 2.91e7
    assert [round(s["frequency_hz"]) for s in res["frequency_response"]] == [10, 20]


@pytest.mark.slow
def test_plots_report_recording_and_discrepancy(seeded: tuple[Path, str]) -> None:
    rec_dir, rid = seeded

    async def go(c: httpx.AsyncClient) -> None:
        res = (await c.get(f"/runs/{rid}/results")).json()
        assert res["plots"] == {n: f"/runs/{rid}/plots/{n}.png" for n in ("bode", "timefit", "residuals",
                                                                            "convergence")}
        # one plot through its URL (one route serves every name); each is drawn into the report
        r = await c.get(res["plots"]["bode"])
        assert r.status_code == 200 and r.headers["content-type"] == "image/png"
        assert r.content[:8] == b"\x89PNG\r\n\x1a\n"
        r = await c.get(f"/runs/{rid}/plots/nosuchplot.png")
        assert r.status_code == 404 and "bode" in r.json()["detail"]
        assert res["report"] == f"/runs/{rid}/report"
        rep = await c.get(res["report"])
        assert rep.status_code == 200 and rep.headers["content-type"].startswith("text/html")
        assert "TX5K-0001" in rep.text
        for n in res["plots"]:  # base64 of the PNG signature
            assert f'<img alt="{n} plot" src="data:image/png;base64,iVBORw0KGgo' in rep.text, n
        rec = await c.get(f"/runs/{rid}/recording")
        assert rec.status_code == 200 and rec.headers["content-type"] == "application/x-hdf5"
        assert f'filename="{rid}.h5"' in rec.headers["content-disposition"]
        with h5py.File(io.BytesIO(rec.content), "r") as f:
            assert f.attrs["run_id"] == rid and f.attrs["exit_status"] == "completed"
            assert "results" not in f or not len(f["results"])  # results live beside the recording
        assert any(k.startswith("identify_") for k in read_stored(rec_dir / f"{rid}.h5"))
        path = rec_dir / f"{rid}.h5"
        size = path.stat().st_size
        missing = await c.get(f"/runs/{rid}/discrepancy")  # a GET reads only: nothing stored yet
        assert missing.status_code == 404 and f"POST /runs/{rid}/discrepancy" in missing.json()["detail"]
        assert (await c.post(f"/runs/{rid}/discrepancy")).status_code == 401  # computing and storing needs the token
        disc = await c.post(f"/runs/{rid}/discrepancy", headers=AUTH, timeout=120)
        assert disc.status_code == 200, disc.text
        d = disc.json()
        assert set(d) == {"base_gap", "effects", "final_gap", "parameters_before", "parameters_after",
                          "unexplained", "ties", "notes", "drive", "proposal", "proposal_note", "structure"}
        assert isinstance(d["ties"], list) and isinstance(d["notes"], list)
        assert d["final_gap"] <= d["base_gap"] + 1e-12
        for _ in range(3):  # stored beside the recording; GETs read it and write nothing
            again = await c.get(f"/runs/{rid}/discrepancy")
            assert again.status_code == 200 and again.json() == d
        assert path.stat().st_size == size
        assert "discrepancy" in read_stored(path)  # where the report and `station discrepancy --save` look
        report = (await c.get(f"/runs/{rid}/report")).text
        assert "has not been run" not in report and "Model discrepancy" in report
    in_app(rec_dir, go, token=False, render=True)


# ---------------------------------------------------------------------------------------- errors


@pytest.mark.slow
def test_busy_rig_409_abort_and_results_states(tmp_path: Path) -> None:
    async def go(c: httpx.AsyncClient) -> None:
        rid = await start(c, freqs=(10.0,), record_s=30.0)
        await wait_state(c, rid, ("running",), step_state="recording")
        busy = await c.post("/runs", json=run_body())
        assert busy.status_code == 409 and rid in busy.json()["detail"]
        assert (await c.get(f"/runs/{rid}/results")).status_code == 409
        assert (await c.get(f"/runs/{rid}/recording")).status_code == 409  # still being written
        assert (await c.get(f"/runs/{rid}/plots/bode.png")).status_code == 409
        st = (await c.get(f"/runs/{rid}")).json()
        assert st["samples"] > 0 and st["current_step"] == 0
        r = await c.post(f"/runs/{rid}/abort")
        assert r.status_code == 202 and r.json()["id"] == rid
        st = await wait_state(c, rid, FINAL)
        assert st["state"] == "aborted" and st["reason"] == "aborted by admin"
        assert (await c.post(f"/runs/{rid}/abort")).status_code == 409
        res = await c.get(f"/runs/{rid}/results")
        assert res.status_code == 409 and "aborted" in res.json()["detail"]
        rec = await c.get(f"/runs/{rid}/recording")
        assert rec.status_code == 200
        with h5py.File(io.BytesIO(rec.content), "r") as f:
            assert f.attrs["exit_status"] == "aborted"
        assert (await c.get(f"/runs/{rid}/discrepancy")).status_code == 409
        assert (await c.get(f"/runs/{rid}/proposal")).status_code == 409
        # the rig is free again
        rid2 = await start(c, freqs=(10.0,), record_s=30.0)
        await wait_state(c, rid2, ("running",))
        await c.post(f"/runs/{rid2}/abort")
        await wait_state(c, rid2, FINAL)
    in_app(tmp_path, go)


@pytest.mark.slow
def test_emergency_stop_is_always_accepted(daemon: Daemon, tmp_path: Path) -> None:
    c = httpx.Client(base_url=daemon.url, timeout=30)  # no token: stopping is never refused
    r = c.post("/stop")
    assert r.status_code == 200 and r.json()["motor_stopped"] and r.json()["aborted_runs"] == []
    # acknowledged from the command line (`station ack` against the daemon, with the token)
    import os
    import subprocess
    import sys
    cli = subprocess.run([sys.executable, "-m", "station.cli", "ack", "--operator", "cli tester", "--url", daemon.url],
                         capture_output=True, text=True, timeout=60, env={**os.environ, "STATION_TOKEN": TOKEN})
    assert cli.returncode == 0 and "acknowledged by admin" in cli.stdout, cli.stderr  # the token's user
    assert c.get("/health").json()["estop"]["last_acknowledged_by"] == "admin"
    rid = daemon.start_run(freqs=(10.0,), record_s=30.0)
    daemon.wait_state(rid, ("running",), step_state="recording")
    t0 = time.monotonic()
    r = c.post("/stop")
    assert r.status_code == 200 and time.monotonic() - t0 < 2.0
    body = r.json()
    assert body["accepted"] and body["motor_stopped"] and body["aborted_runs"] == [rid]
    st = daemon.wait_state(rid)
    assert st["state"] == "aborted" and st["reason"].startswith("emergency stop")
    path = tmp_path / "estop.h5"
    path.write_bytes(c.get(f"/runs/{rid}/recording").content)
    rec = read_recording(path)
    # an operator's stop is an abort in the file too, even though it latches the e-stop fault
    assert (rec.exit_status, rec.reason) == ("aborted", "emergency stop"), (rec.exit_status, rec.reason)
    assert c.post("/stop", content=b"garbage").status_code == 200
    # the stop latches: no run until an operator acknowledges it (with the token)
    h = c.get("/health").json()
    assert h["status"] == "degraded" and h["estop"]["latched"] and h["estop"]["source"] == "api"
    r = daemon.c().post("/runs", json=run_body(freqs=(10.0,)))
    assert r.status_code == 409 and "emergency stop latched" in r.json()["detail"]
    assert c.post("/stop/acknowledge", json={"operator": "tester"}).status_code == 401
    ack = daemon.c().post("/stop/acknowledge", json={"operator": "tester", "note": "rig checked"})
    assert ack.status_code == 200 and ack.json()["acknowledged"] and not ack.json()["latched"], ack.text
    assert "reset" in ack.json()["detail"]
    rid2 = daemon.start_run(freqs=(10.0,))
    assert daemon.wait_state(rid2, ("identifying", *FINAL))["state"] in ("identifying", "completed")
    daemon.wait_state(rid2)
    h = c.get("/health").json()
    assert h["status"] == "ok" and h["active_run"] is None and not h["estop"]["latched"]
    assert h["estop"]["last_acknowledged_by"] == "admin"


@pytest.mark.slow
def test_reading_from_another_machine_needs_the_token_and_foreign_hosts_are_refused(tmp_path: Path) -> None:
    from station.api import create_app
    from station.service.settings import load_settings

    cfg_path = tmp_path / "station.yaml"
    cfg_path.write_text(yaml.safe_dump(daemon_config(tmp_path / "recordings")))
    settings = load_settings(cfg_path, sim=True, host="0.0.0.0")
    app = create_app(settings)

    async def go() -> tuple[int, int, int]:
        t = httpx.ASGITransport(app=app, client=("192.0.2.7", 5555))
        async with httpx.AsyncClient(transport=t, base_url="http://192.0.2.1") as c:
            no = (await c.get("/station")).status_code
            yes = (await c.get("/station", headers={"Authorization": f"Bearer {settings.token}"})).status_code
        local = create_app(load_settings(cfg_path, sim=True))
        t2 = httpx.ASGITransport(app=local, client=("127.0.0.1", 5555))
        async with httpx.AsyncClient(transport=t2, base_url="http://evil.example") as c:
            rebinding = (await c.get("/station")).status_code
        return no, yes, rebinding
    no, yes, rebinding = asyncio.run(go())
    assert (no, yes, rebinding) == (401, 200, 400)
