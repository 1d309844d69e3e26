"""The rig boundary's fault matrix, on the simulated rig: one test per row of the service's share
of the table (the row quoted in each docstring).  Most run the daemon's app in-process (real rig
thread, real drivers on the simulated rig's in-process backends on a virtual clock, real SQLite and
HDF5) through httpx's ASGI transport; the flood and a second daemon on the folder go to a real
``station serve --sim`` over loopback in real time, one for the module (``daemon``)."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import socket
import sqlite3
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import h5py
import httpx
import pytest

from station.config import parse_config
from station.recording import read_recording
from station.run.request import RunRequest
from station.service.manager import RunManager
from station.service.settings import build_settings
from tests.disk_support import fill_disk, mounted_tmpfs
from tests.station_support import (
    AUTH,
    CAPPED_SPEEDUP,
    FINAL,
    IDLE_SPEEDUP,
    ON_RIG_DONE,
    TOKEN,
    Daemon,
    app_in_process,
    daemon_config,
    estops,
    run_body,
    start,
    wait_state,
)

# with --dist loadgroup: the tests on the module's real daemon on one worker, that daemon started once
ON_THE_DAEMON = pytest.mark.xdist_group("fault_matrix_daemon")


@pytest.fixture(scope="module")
def daemon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Daemon]:
    """A real ``station serve --sim`` (no workers: a run ends at ``identifying``) for the module's tests
    over loopback; each leaves the rig free and no stop latched."""
    with Daemon(tmp_path_factory.mktemp("fault-matrix"), workers=0) as d:
        yield d


# ---------------------------------------------------------------------------------------- row 1
@pytest.mark.slow
def test_stop_latches_until_an_operator_acknowledges(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """| `POST /stop`, or the controller's e-stop fault, then a new run | the next run clears the latched
    fault itself (`reset_faults()` at every start) and moves the crank; nothing is logged |"""

    async def go() -> None:
        async with app_in_process(tmp_path / "rec", max_speedup=CAPPED_SPEEDUP, idle_speedup=IDLE_SPEEDUP) as (m, c):
            rid = await start(c, freqs=(10.0,), record_s=30.0)
            await wait_state(c, rid, ("running",), "recording")
            r = await c.post("/stop", headers={"X-Station-Client": "page"})
            assert r.status_code == 200 and r.json()["aborted_runs"] == [rid]
            st = await wait_state(c, rid, FINAL)
            assert st["state"] == "aborted" and st["reason"].startswith("emergency stop")
            # nothing clears it: the controller keeps its e-stop fault, the daemon refuses runs
            assert await m.link.motor_fault() == (2, "emergency_stop")
            r = await c.post("/runs", json=run_body(freqs=(10.0,)))
            assert r.status_code == 409 and "emergency stop latched" in r.json()["detail"]
            assert "acknowledge" in r.json()["detail"]
            assert await m.link.motor_fault() == (2, "emergency_stop")
            h = (await c.get("/health")).json()
            assert h["status"] == "degraded" and h["estop"]["latched"] and h["estop"]["source"] == "page"
            # acknowledging needs a user (the token's: admin); the operator named at the rig goes in the note
            assert (await c.post("/stop/acknowledge", json={"operator": "ab"}, headers={"Authorization": ""})
                    ).status_code == 401
            assert (await c.post("/stop/acknowledge", json={"operator": "x" * 65})).status_code == 422
            r = await c.post("/stop/acknowledge", json={"operator": "A. Tech", "note": "crank checked"})
            assert r.status_code == 200 and r.json()["acknowledged"] and not r.json()["latched"], r.text
            rows = estops(m)
            assert len(rows) == 1 and rows[0]["source"] == "page" and rows[0]["acknowledged_by"] == "admin"
            assert rows[0]["acknowledged"] >= rows[0]["raised"]
            assert rows[0]["note"] == "operator at the rig: A. Tech; crank checked"
            assert await m.link.motor_fault() is None
            h = (await c.get("/health")).json()
            assert h["status"] == "ok" and not h["estop"]["latched"] and h["estop"]["last_acknowledged_by"] == "admin"
            rid2 = await start(c, freqs=(10.0,))
            assert (await wait_state(c, rid2))["state"] == "identifying"
    with caplog.at_level("WARNING"):
        asyncio.run(go())
    text = caplog.text
    assert "emergency stop latched (source page)" in text and "acknowledged by admin" in text and "A. Tech" in text


@pytest.mark.slow
def test_controller_estop_fault_latches_and_a_fault_at_start_is_not_cleared(tmp_path: Path) -> None:
    """| `POST /stop`, or the controller's e-stop fault, then a new run | the next run clears the latched
    fault itself (`reset_faults()` at every start) and moves the crank; nothing is logged |"""

    async def go() -> None:
        async with app_in_process(tmp_path / "rec", max_speedup=CAPPED_SPEEDUP, idle_speedup=IDLE_SPEEDUP) as (m, c):
            assert m.link.rig is not None and m.link.rig.sim is not None
            sim_motor = m.link.rig.sim.motor
            # the controller's own e-stop during a run (its button, not the daemon's)
            rid = await start(c, freqs=(10.0,), record_s=30.0)
            await wait_state(c, rid, ("running",), "recording")
            sim_motor.emergency_stop()
            st = await wait_state(c, rid, FINAL)
            assert st["state"] == "failed" and "emergency_stop" in st["reason"]
            h = (await c.get("/health")).json()
            assert h["estop"]["latched"] and h["estop"]["source"] == "controller"
            r = await c.post("/runs", json=run_body(freqs=(10.0,)))
            assert r.status_code == 409 and "latched" in r.json()["detail"]
            assert (await c.post("/stop/acknowledge", json={"operator": "op"})).status_code == 200
            # a fault already present at the start (here: overcurrent) is reported, not cleared
            sim_motor.inject_fault(3)
            r = await c.post("/runs", json=run_body(freqs=(10.0,)))
            assert r.status_code == 409 and "overcurrent" in r.json()["detail"], r.text
            assert sim_motor.snapshot().fault_code == 3 and sim_motor.speed_hz() == 0.0
            assert estops(m)[-1]["source"] == "controller"
            assert (await c.post("/stop/acknowledge", json={"operator": "op"})).status_code == 200
            assert sim_motor.snapshot().fault_code == 0
            rid2 = await start(c, freqs=(10.0,))
            assert (await wait_state(c, rid2))["state"] == "identifying"
    asyncio.run(go())


# ---------------------------------------------------------------------------------------- row 2
def _raw_post(port: int, path: str, length: int, send_bytes: int, headers: str = "") -> tuple[int, float]:
    """POST announcing ``length`` body bytes, send ``send_bytes`` of them, read the status line."""
    t0 = time.perf_counter()
    with socket.create_connection(("127.0.0.1", port), timeout=30) as s:
        s.sendall((f"POST {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
                   f"Content-Length: {length}\r\n{headers}Connection: close\r\n\r\n").encode())
        with contextlib.suppress(OSError):  # the server may answer and close before all is sent
            chunk = b"[" + b"0," * (2**16)
            sent = 0
            while sent < send_bytes:
                s.sendall(chunk[: min(len(chunk), send_bytes - sent)])
                sent += len(chunk)
        data = b""
        while b"\r\n" not in data:
            part = s.recv(4096)
            if not part:
                break
            data += part
    return int(data.split(b" ", 2)[1]), time.perf_counter() - t0


def _rss_kb(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return 0


@pytest.mark.slow
@ON_THE_DAEMON
def test_flood_during_a_run_loses_no_sample_and_big_bodies_are_refused_unread(daemon: Daemon) -> None:
    """| a 20 MB JSON body to `POST /runs` without a token, during a run | answered 401 after 1.3 s, but
    the run fails: "motor fault 1 (watchdog_expired)"; the body is read and parsed before the token
    check, no size limit, 100 MB took 740 MB of memory |"""
    d = daemon
    assert d.proc is not None
    rid = d.start_run(freqs=(10.0, 20.0), record_s=1.5)
    d.wait_state(rid, ("running",), step_state="recording")
    rss0 = _rss_kb(d.proc.pid)
    lat: dict[str, list[float]] = {"get": [], "big_unauth": [], "big_auth": [], "bad": []}
    codes: dict[str, list[int]] = {k: [] for k in lat}
    lock = threading.Lock()

    def note(kind: str, code: int, dt: float) -> None:
        with lock:
            lat[kind].append(dt)
            codes[kind].append(code)

    def getter(n: int) -> None:
        with httpx.Client(base_url=d.url, timeout=30) as c:
            for i in range(n):
                t0 = time.perf_counter()
                r = c.get(f"/runs/{rid}" if i % 2 else "/health")
                note("get", r.status_code, time.perf_counter() - t0)

    def big_unauth(n: int) -> None:
        for _ in range(n):  # 20 MB announced, 1 MB actually sent: answered before it is read
            code, dt = _raw_post(d.port, "/runs", 20 * 2**20, 2**20)
            note("big_unauth", code, dt)

    def big_auth(n: int) -> None:
        for _ in range(n):  # with the token: over the 1 MiB limit, 413 without reading it
            code, dt = _raw_post(d.port, "/runs", 5 * 2**20, 2**18, f"Authorization: Bearer {TOKEN}\r\n")
            note("big_auth", code, dt)

    def bad(n: int) -> None:
        with httpx.Client(base_url=d.url, timeout=30, headers=AUTH) as c:
            for i in range(n):
                t0 = time.perf_counter()
                body = b"\xff\xfe\x00{" if i % 2 else b'{"transducer_id": true}'
                r = c.post("/runs", content=body, headers={"Content-Type": "application/json"})
                note("bad", r.status_code, time.perf_counter() - t0)

    threads = [threading.Thread(target=getter, args=(60,)) for _ in range(4)]
    threads += [threading.Thread(target=big_unauth, args=(10,)) for _ in range(2)]
    threads += [threading.Thread(target=big_auth, args=(10,)), threading.Thread(target=bad, args=(40,))]
    t0 = time.monotonic()
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    flood_s = time.monotonic() - t0
    rss1 = _rss_kb(d.proc.pid)
    st = d.wait_state(rid, ON_RIG_DONE)
    h = d.c().get("/health").json()
    n = sum(len(v) for v in lat.values())
    figures = {"requests": n, "flood_s": round(flood_s, 2), "rss_growth_MB": round((rss1 - rss0) / 1024, 1),
               "run_state": st["state"], "lost_samples": st["lost_samples"],
               **{f"{k}_median_ms": round(1e3 * sorted(v)[len(v) // 2], 1) for k, v in lat.items() if v},
               **{f"{k}_max_ms": round(1e3 * max(v), 1) for k, v in lat.items() if v}}
    print(json.dumps(figures))
    assert n == 4 * 60 + 2 * 10 + 10 + 40
    assert set(codes["get"]) == {200}
    assert set(codes["big_unauth"]) == {401} and set(codes["big_auth"]) == {413}
    assert set(codes["bad"]) == {422}
    assert st["state"] == "identifying", st
    assert st["lost_samples"] == 0 and st["reason"] == ""
    assert h["rig"]["motor"]["watchdog_error"] is None
    assert rss1 - rss0 < 50 * 1024  # 20 MB bodies were never buffered (40 of them would be 800 MB)


@pytest.mark.slow
@ON_THE_DAEMON
def test_two_real_daemons_on_one_folder_the_live_run_is_untouched(daemon: Daemon) -> None:
    """| a second daemon on the same recordings folder damages the running one | the newcomer marks the
    live run `interrupted`, renames the live `.h5.partial`, opens the DAQ port and sends STOP |"""
    d = daemon
    assert d.proc is not None
    # a record far longer than the newcomer's start-up, however loaded the machine: the run is live
    # throughout; it is ended by the operator afterwards
    rid = d.start_run(freqs=(10.0,), record_s=120.0)
    d.wait_state(rid, ("running",), step_state="recording")
    partial = d.data_dir / f"{rid}.h5.partial"
    assert partial.exists()
    before = d.c().get(f"/runs/{rid}").json()["samples"]
    p = subprocess.run([sys.executable, "-m", "station.cli", "serve", "--sim", "--config", str(d.cfg_path),
                        "--port", "0"], capture_output=True, text=True, timeout=60,
                       env={**os.environ, "STATION_TOKEN": TOKEN})
    assert p.returncode == 1, p.stderr
    assert f"PID {d.proc.pid}" in p.stderr and f"http://127.0.0.1:{d.port}/" in p.stderr, p.stderr
    assert "Traceback" not in p.stderr
    assert partial.exists() and not (d.data_dir / f"{rid}.h5").exists()  # not renamed under the live run
    st = d.c().get(f"/runs/{rid}").json()
    assert (st["state"], st["step_state"]) == ("running", "recording") and st["samples"] > before, st
    assert d.c().post(f"/runs/{rid}/abort").status_code == 202
    st = d.wait_state(rid)
    # ended as the operator asked, nothing lost: the newcomer neither interrupted nor disturbed it
    assert (st["state"], st["lost_samples"]) == ("aborted", 0) and st["reason"].startswith("aborted by"), st
    assert (d.data_dir / f"{rid}.h5").exists() and not partial.exists()
    health = d.c().get("/health").json()
    assert health["status"] == "ok" and not health["estop"]["latched"], health


# ---------------------------------------------------------------------------------------- row 3
@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    """A real 24 MiB file system (tmpfs); needs root, as CI has."""
    with mounted_tmpfs(tmp_path, 24) as mnt:
        yield mnt


def _open_fds(name: str) -> list[str]:
    out = []
    for fd in os.listdir("/proc/self/fd"):
        with contextlib.suppress(OSError):
            target = os.readlink(f"/proc/self/fd/{fd}")
            if name in target:
                out.append(target)
    return out


@pytest.mark.parametrize("guard", ["writer guard off", "writer guard on"])
@pytest.mark.slow
def test_a_real_full_disk_fails_the_run_with_its_cause_and_frees_the_rig(
        tmp_path: Path, small_disk: Path, guard: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """| a real ENOSPC during a run | the API says failed, the database says running, the run holds the
    rig until restart (every POST 409, `/stop` does not release it), abort answers 500, the deleted
    partial file's space is not freed, and after restart the cause is lost |

    The disk is filled for real (a file written until ENOSPC).  With the writer's free-space guard
    off, HDF5's own write meets ENOSPC (the guard checks twice a second and can be outrun); with it
    on, whichever notices first ends the run: both must end the same clean way."""
    filler = small_disk / "filler.bin"
    if guard == "writer guard off":
        from station.recording.writer import RecordingWriter
        monkeypatch.setattr(RecordingWriter, "_check_space", lambda self, nbytes: None)
    cause = "disk full (no space left on device" if guard == "writer guard off" else "disk"

    async def go() -> None:
        # no space kept in reserve by the writer's guard: the disk really fills (ENOSPC)
        async with app_in_process(small_disk, min_free_mb=0.0, max_speedup=CAPPED_SPEEDUP,
                                  idle_speedup=IDLE_SPEEDUP) as (m, c):
            assert (await c.get("/health")).json()["disk"]["reserve_file"]
            rid = await start(c, freqs=(10.0,), record_s=30.0)
            await wait_state(c, rid, ("running",), "recording")
            await asyncio.to_thread(fill_disk, filler)
            st = await wait_state(c, rid, FINAL, timeout_s=30)
            assert st["state"] == "failed" and cause in st["reason"], st
            assert m.runs.live == {}
            # every endpoint answers, none with a 500
            answers = {
                "health": (await c.get("/health")).status_code, "runs": (await c.get("/runs")).status_code,
                "run": (await c.get(f"/runs/{rid}")).status_code,
                "station": (await c.get("/station")).status_code,
                "recording": (await c.get(f"/runs/{rid}/recording")).status_code,
                "results": (await c.get(f"/runs/{rid}/results")).status_code,
                "abort": (await c.post(f"/runs/{rid}/abort")).status_code,
                "new run": (await c.post("/runs", json=run_body(freqs=(10.0,)))).status_code,
            }
            assert answers == {"health": 200, "runs": 200, "run": 200, "station": 200, "recording": 200,
                               "results": 409, "abort": 409, "new run": 503}, answers
            h = (await c.get("/health")).json()
            assert h["status"] == "degraded" and not h["disk"]["ok"] and h["disk"]["reserve_used"] == 1
            # the recording is closed (file released: no descriptor left), with the cause in it
            assert _open_fds(rid) == []
            rec = read_recording(small_disk / f"{rid}.h5")
            assert rec.complete and rec.exit_status == "failed" and cause in rec.reason
            assert rec.displacement_m.size > 10_000
            assert not (small_disk / f"{rid}.h5.partial").exists()
            # the stop still works and releases nothing it should not
            assert (await c.post("/stop")).status_code == 200
            # space back: healthy again, the reserve file is made anew, runs start
            filler.unlink()
            h = (await c.get("/health")).json()
            assert h["disk"]["ok"] and h["disk"]["reserve_file"], h["disk"]
            assert (await c.post("/stop/acknowledge", json={"operator": "op"})).status_code == 200
            rid2 = await start(c, freqs=(10.0,))
            assert (await wait_state(c, rid2))["state"] == "identifying"
        # the database has the cause too (survives a restart)
        db = sqlite3.connect(small_disk / "station.db")
        state, reason = db.execute("SELECT state, reason FROM runs WHERE id = ?", (rid,)).fetchone()
        db.close()
        assert state == "failed" and cause in reason
    asyncio.run(go())


# ---------------------------------------------------------------------------------------- row 4
def test_memory_structures_do_not_grow_with_runs(tmp_path: Path) -> None:
    """| daemon memory | +2.3–3 MB per run, still rising after 30 runs |

    (The RSS over 50 runs is measured by ``bench/service_memory.py``; here: what the daemon keeps
    per run in its own structures stays bounded.)"""
    from station.service.artifacts import CACHE_ENTRIES
    from station.service.changes import MAX_TRACKED

    async def go() -> None:
        cfg = parse_config(daemon_config(tmp_path / "rec"))
        m = RunManager(build_settings(cfg, sim=True, workers=0, env={}))
        try:
            for i in range(MAX_TRACKED + 50):
                m.changes.changed(f"run-{i}")
                async with m.artifacts.file_lock(f"run-{i}"):
                    pass
                m.artifacts._cache[(f"run-{i}", "report")] = "x"
                m.artifacts._trim()
            assert len(m.changes) <= MAX_TRACKED
            assert m.artifacts._file_locks == {}
            assert len(m.artifacts._cache) <= CACHE_ENTRIES
        finally:
            m.store.close()
    asyncio.run(go())


@pytest.mark.slow
def test_a_finished_run_leaves_nothing_behind_without_waiting_for_the_garbage_collector(tmp_path: Path) -> None:
    """| daemon memory | +2.3–3 MB per run, still rising after 30 runs |

    The growth was each run's procedure and its 4.8 MB ring buffer kept alive by a reference cycle
    (procedure -> progress callback -> run record -> procedure) until a full garbage collection."""
    import gc
    import weakref

    async def go() -> None:
        async with app_in_process(tmp_path / "rec", max_speedup=CAPPED_SPEEDUP, idle_speedup=IDLE_SPEEDUP) as (m, c):
            for _ in range(2):
                rid = await start(c, freqs=(10.0,))
                while (live := m.runs.live.get(rid)) is None or live.proc is None or live.proc.acq is None:
                    await asyncio.sleep(0.01)
                proc = weakref.ref(live.proc)
                ring = live.proc.acq.ring
                del live
                await wait_state(c, rid)
                await asyncio.sleep(0.1)
                assert proc() is None, gc.get_referrers(proc())
                assert ring.capacity == 0  # its memory was given back when acquisition stopped
    gc.disable()
    try:
        asyncio.run(go())
    finally:
        gc.enable()


# ---------------------------------------------------------------------------------------- row 5
def test_a_body_that_is_not_utf8_is_refused_clearly(tmp_path: Path) -> None:
    """| a body that is not UTF-8 | 500, connection dropped |"""

    async def go() -> None:
        async with app_in_process(tmp_path / "rec", max_speedup=CAPPED_SPEEDUP, idle_speedup=IDLE_SPEEDUP) as (_, c):
            for ctype in ("application/json", None):
                headers = {"Content-Type": ctype} if ctype else {}
                r = await c.post("/runs", content=b'{"transducer_id": "\xff\xfe"}', headers=headers)
                assert r.status_code == 422, (ctype, r.text)
                d = r.json()["errors"][0]
                assert d["type"] == "body_not_utf8" and "0xff" in d["msg"] and "position 19" in d["msg"]
            r = await c.post("/stop/acknowledge", content=b"\x80", headers={"Content-Type": "application/json"})
            assert r.status_code == 422
    asyncio.run(go())


# ---------------------------------------------------------------------------------------- row 6
def test_booleans_and_strings_are_not_numbers(tmp_path: Path) -> None:
    """| `true` or `"10"` as a frequency | accepted (a 1 Hz run starts) |"""
    good = run_body(freqs=(10.0,))
    assert RunRequest.model_validate_json(json.dumps(good)).steps[0].crank_frequency_hz == 10.0
    as_int = json.loads(json.dumps(good).replace("10.0", "10"))
    assert RunRequest.model_validate(as_int).steps[0].crank_frequency_hz == 10.0  # an integer is a number

    async def go() -> None:
        async with app_in_process(tmp_path / "rec", max_speedup=CAPPED_SPEEDUP, idle_speedup=IDLE_SPEEDUP) as (m, c):
            for field, value, loc in [("crank_frequency_hz", True, ["body", "steps", 0, "crank_frequency_hz"]),
                                      ("crank_frequency_hz", "10", ["body", "steps", 0, "crank_frequency_hz"]),
                                      ("crank_radius_m", "0.001", ["body", "steps", 0, "crank_radius_m"]),
                                      ("settle_s", False, ["body", "steps", 0, "settle_s"])]:
                body = run_body(freqs=(10.0,))
                body["steps"][0][field] = value
                r = await c.post("/runs", json=body)
                assert r.status_code == 422 and r.json()["errors"][0]["loc"] == loc, (field, value, r.text)
                assert "a number expected" in r.json()["errors"][0]["msg"]
            body = run_body(freqs=(10.0,))
            body["top_mass_kg"] = "25.7"
            r = await c.post("/runs", json=body)
            assert r.status_code == 422 and r.json()["errors"][0]["loc"] == ["body", "top_mass_kg"]
            assert m.store.list_runs() == []  # nothing started
    asyncio.run(go())


# ---------------------------------------------------------------------------------------- row 7
def test_after_an_abort_progress_and_the_first_reason_stay(tmp_path: Path) -> None:
    """| after an abort | progress 1.0 and "done"; a later abort overwrites the reason "emergency stop" |"""

    async def go() -> None:
        async with app_in_process(tmp_path / "rec", max_speedup=CAPPED_SPEEDUP, idle_speedup=IDLE_SPEEDUP) as (_, c):
            rid = await start(c, freqs=(10.0, 20.0), record_s=30.0)
            await wait_state(c, rid, ("running",), "recording")
            assert (await c.post("/stop")).status_code == 200
            r = await c.post(f"/runs/{rid}/abort")  # a second stop while the first is under way
            assert r.status_code in (202, 409)
            st = await wait_state(c, rid, FINAL)
            assert st["state"] == "aborted" and st["reason"].startswith("emergency stop"), st
            assert st["progress"] < 1.0 and st["step_state"] != "done", st
            assert st["progress"] == 0.0  # stopped inside the first of two steps
            path = tmp_path / "rec" / f"{rid}.h5"
            with h5py.File(path, "r") as f:
                assert f.attrs["reason"] == "emergency stop"
    asyncio.run(go())


# ---------------------------------------------------------------------------------------- row 8
def test_a_cross_site_request_cannot_reach_stop(tmp_path: Path) -> None:
    """| any web page | can trigger `/stop` with a cross-site form post |"""

    async def go() -> None:
        async with app_in_process(tmp_path / "rec", max_speedup=CAPPED_SPEEDUP, idle_speedup=IDLE_SPEEDUP) as (m, c):
            anon = {"Authorization": ""}
            form = {"Content-Type": "application/x-www-form-urlencoded", **anon}
            for headers in ({"Origin": "http://evil.example", "Sec-Fetch-Site": "cross-site", **form},
                            {"Origin": "http://evil.example", **form},  # a browser without Fetch metadata
                            {"Origin": "null", **form},
                            {"Sec-Fetch-Site": "same-site", **form}):
                r = await c.post("/stop", content=b"a=1", headers=headers)
                assert r.status_code == 403 and "cross-site" in r.json()["detail"], (headers, r.text)
            assert estops(m) == []  # nothing was stopped or latched
            # the page (same origin), an API client and curl (neither header) still can
            page = {"Origin": "http://127.0.0.1", "Sec-Fetch-Site": "same-origin", "X-Station-Client": "page", **anon}
            assert (await c.post("/stop", headers=page)).status_code == 200
            assert (await c.post("/stop", headers=anon)).status_code == 200
            assert [r["source"] for r in estops(m)] == ["page", "api"]
            # acknowledging from another site is refused even with the token
            r = await c.post("/stop/acknowledge", json={"operator": "x"}, headers={"Origin": "http://evil.example"})
            assert r.status_code == 403
    asyncio.run(go())
