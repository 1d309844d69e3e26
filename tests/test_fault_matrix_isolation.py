"""The isolation fault matrix: one test per row of the station's isolation findings that concern
its edges (bad bodies, imports, secrets, the database at start, orphaned workers, a full disk while
identifying).  The row is quoted in each docstring.  The daemon's app runs in-process
(``tests/station_support.app_in_process``) wherever a process boundary is not what is tested; a
killed daemon is a real process (marked slow).  A second daemon on a live daemon's folder is
``tests/test_fault_matrix_service.py``'s (on that module's real daemon)."""

from __future__ import annotations

import asyncio
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx
import pytest

from station.bounded import MAX_YAML_NODES
from station.cli import main
from station.errors import BadInputError, ConfigError, RecordingFormatError
from station.service.instance import LOCK_NAME, InstanceLock
from tests.disk_support import fill_disk, mounted_tmpfs
from tests.station_support import (
    CAPPED_SPEEDUP,
    IDLE_SPEEDUP,
    TOKEN,
    app_in_process,
    daemon_config,
    run_body,
    running_app,
)

pytestmark = pytest.mark.waits  # real processes killed and time-outs: about 9 s of wall time, 2 s of CPU

# --------------------------------------------------------------------------------------- bad bodies
POSTS = ("/runs", "/runs/no-such-run/abort", "/runs/no-such-run/discrepancy", "/stop/acknowledge", "/campaigns")
NOT_JSON = {  # content type: body
    "application/octet-stream": b"\xff\xfe\x00binary",
    "text/plain": json.dumps(run_body()).encode(),  # JSON text sent as text/plain: a cross-site "simple" request
    "application/x-www-form-urlencoded": b"transducer_id=TX5K-0001&top_mass_kg=25",
    "multipart/form-data; boundary=xx": b'--xx\r\nContent-Disposition: form-data; name="a"\r\n\r\n\xff\r\n--xx--\r\n',
    "text/html; charset=utf-8": b"<p>\xe9</p>",
}
BAD_JSON = {  # name: body sent as application/json
    "not UTF-8": b'{"transducer_id": "\xff\xfe"}',
    "an array": b"[1, 2, 3]",
    "a string": b'"runs"',
    "null": b"null",
    "empty": b"",
    "truncated": b'{"runs": [',
    "NaN": b'{"transducer_id": "TX5K-0001", "top_mass_kg": NaN, "operator": NaN, "runs": NaN}',
    "Infinity": b'{"top_mass_kg": Infinity, "runs": [1e999]}',
    "a 5000-digit number": b'{"top_mass_kg": ' + b"9" * 5000 + b"}",
    "nested 100000 deep": b"[" * 100_000 + b"]" * 100_000,
    "a 300 kB string": b'{"transducer_id": "' + b"x" * 300_000 + b'", "operator": "' + b"y" * 300_000 + b'"}',
}


def _assert_clear_4xx(r: httpx.Response, expected: tuple[int, ...], what: str) -> None:
    assert r.status_code in expected, (what, r.status_code, r.text[:500])
    assert r.headers["content-type"] == "application/problem+json", what
    assert "Traceback" not in r.text and 'File "' not in r.text, what
    assert len(r.content) < 3000, (what, len(r.content))  # the input is quoted within a few hundred characters
    assert r.json()["detail"], what


@pytest.mark.slow
def test_every_bad_body_on_every_post_endpoint_is_a_clear_4xx(tmp_path: Path) -> None:
    """| non-UTF-8 bodies | 500 with a 5.4 kB traceback on `POST /runs`, `/stop/acknowledge`,
    `/campaigns` for every non-JSON content type (octet-stream, text/plain, form, multipart) |"""

    async def go() -> None:
        async with app_in_process(tmp_path / "rec", max_speedup=CAPPED_SPEEDUP, idle_speedup=IDLE_SPEEDUP) as (m, c):
            for path in POSTS:
                for ctype, body in NOT_JSON.items():
                    r = await c.post(path, content=body, headers={"Content-Type": ctype})
                    _assert_clear_4xx(r, (415,), f"{path} {ctype}")
                    assert "application/json" in r.json()["detail"]
                for name, body in BAD_JSON.items():
                    r = await c.post(path, content=body, headers={"Content-Type": "application/json"})
                    # 404: a run's action on an unknown run reads no body; 413: over service.max_body_bytes
                    _assert_clear_4xx(r, (404, 413, 422) if "no-such-run" in path else (413, 422), f"{path} {name}")
                # without the token: 401 before anything is read, whatever the type
                for ctype in ("application/json", "text/plain"):
                    r = await c.post(path, content=b"{}", headers={"Content-Type": ctype, "Authorization": ""})
                    _assert_clear_4xx(r, (401,), f"{path} anonymous {ctype}")
            # the published API says so: every POST but the emergency stop documents 413 and 415
            doc = (await c.get("/openapi.json")).json()
            posts = {p: op["post"] for p, op in doc["paths"].items() if "post" in op and p != "/stop"}
            assert len(posts) >= len(POSTS)
            for p, op in posts.items():
                assert {"401", "413", "415"} <= set(op["responses"]), (p, sorted(op["responses"]))
            # the emergency stop takes any body (it never reads it) and still stops
            r = await c.post("/stop", content=b"\xff", headers={"Content-Type": "application/octet-stream"})
            assert r.status_code == 200 and r.json()["motor_stopped"] is True
            assert m.store.list_runs() == []  # nothing started
    asyncio.run(go())


def test_campaigns_need_the_token_even_on_loopback(tmp_path: Path) -> None:
    """| non-UTF-8 bodies | `/campaigns` needs no token and accepts cross-site text/plain |"""

    async def go() -> None:
        async with app_in_process(tmp_path / "rec", max_speedup=CAPPED_SPEEDUP, idle_speedup=IDLE_SPEEDUP) as (_, c):
            anon = {"Authorization": "", "Content-Type": "text/plain", "Origin": "http://evil.example",
                    "Sec-Fetch-Site": "cross-site"}
            r = await c.post("/campaigns", content=json.dumps({"runs": ["x"]}).encode(), headers=anon)
            assert r.status_code == 401
            r = await c.post("/campaigns", json={"runs": ["x"]}, headers={"Authorization": ""})
            assert r.status_code == 401
            r = await c.post("/campaigns", json={"runs": ["no-such-run"]})  # with the token: reaches the route
            assert r.status_code == 404
            info = (await c.get("/station")).json()
            assert "POST /campaigns" in info["token_required"]
    asyncio.run(go())


def test_an_internal_error_is_a_short_json_500_and_the_traceback_goes_to_the_log(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """| non-UTF-8 bodies | ... a 5.4 kB traceback (no traceback reaches a user, whatever fails) |"""

    def broken(**_: Any) -> None:
        raise RuntimeError("a bug deep inside")

    async def go() -> None:
        async with running_app(tmp_path / "rec", max_speedup=CAPPED_SPEEDUP, idle_speedup=IDLE_SPEEDUP) as app:
            app.state.manager.runs.list_runs = broken
            t = httpx.ASGITransport(app=app, client=("127.0.0.1", 40000), raise_app_exceptions=False)
            async with httpx.AsyncClient(transport=t, base_url="http://127.0.0.1") as c:
                r = await c.get("/runs")
        assert r.status_code == 500 and r.headers["content-type"] == "application/problem+json", r.text
        assert r.json() == {"type": "urn:sinecal:problem:internal-error", "title": "Internal error of the station "
                            "daemon", "status": 500, "instance": "/runs",
                            "detail": "internal error of the station daemon; the details are in its log"}
    with caplog.at_level("ERROR", logger="station.api.main"):
        asyncio.run(go())
    assert "GET /runs: internal error" in caplog.text and "a bug deep inside" in caplog.text


# --------------------------------------------------------------------------------------- imports
def _alias_bomb(levels: int = 9) -> str:
    """A few hundred bytes that expand to 9**levels nodes (the billion laughs)."""
    lines = ['a0: &a0 ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    lines += [f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 9)}]" for i in range(1, levels + 1)]
    return "\n".join(lines) + "\n"


def test_import_bounds_yaml_aliases_file_sizes_and_quotes(tmp_path: Path) -> None:
    """| import amplification | a 685-byte YAML with nested aliases -> a 351 MB error message and 1.4 GB
    of memory; step files are read whole with no size limit (512 MB sparse file -> 6.9 GB RSS) |"""
    import resource

    from station.interchange import MAX_STEP_FILE_BYTES, import_run

    out = tmp_path / "out"
    src = tmp_path / "run"
    src.mkdir()
    bomb = _alias_bomb()
    assert len(bomb) < 700 and MAX_YAML_NODES < 9 ** 9
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    for text in (bomb, "format: sinecal-csv\nformat_version: 1\ntransducer:\n  " + bomb.replace("\n", "\n  ")):
        (src / "RUN.yaml").write_text(text)
        with pytest.raises(RecordingFormatError) as exc:
            import_run(src / "RUN.yaml", out)
        assert len(str(exc.value)) < 1000, len(str(exc.value))
    assert "expands to more than" in str(exc.value)
    # a RUN.yaml that is right but for a huge value: quoted within a few hundred characters
    run = {"format": "sinecal-csv", "format_version": 1, "sample_rate_hz": 20000, "crank_radius_m": 0.001,
           "top_mass_kg": 25.0, "transducer": {"id": "T" * 100_000, "capacity_N": 5000, "sensitivity_V_per_N": 1e-3},
           "steps": [{"file": "s.csv", "crank_frequency_hz": 10}]}
    (src / "RUN.yaml").write_text(json.dumps(run))
    with pytest.raises(RecordingFormatError) as exc:
        import_run(src / "RUN.yaml", out)
    assert "transducer.id" in str(exc.value) and len(str(exc.value)) < 1000
    # a step file over the limit (sparse: no disk used) is refused by its size, unread
    run["transducer"]["id"] = "T1"  # type: ignore[index]
    (src / "RUN.yaml").write_text(json.dumps(run))
    with (src / "s.csv").open("wb") as f:
        f.write(b"t_s,displacement_m,force_V\n")
        f.truncate(MAX_STEP_FILE_BYTES + 1)
    with pytest.raises(RecordingFormatError) as exc:
        import_run(src / "RUN.yaml", out)
    assert f"exceeds the limit of {MAX_STEP_FILE_BYTES} bytes" in str(exc.value)
    assert (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0) < 200 * 1024  # kB: nothing read whole
    assert not out.exists() or not any(out.iterdir())  # nothing written


def test_configuration_yaml_is_bounded_the_same_way(tmp_path: Path) -> None:
    """| import amplification | (the station configuration goes through the same loader) |"""
    from station.config import load_config

    p = tmp_path / "station.yaml"
    p.write_text(_alias_bomb())
    with pytest.raises(ConfigError) as exc:
        load_config(p)
    assert "expands to more than" in str(exc.value) and len(str(exc.value)) < 1000
    p.write_text("rig: [" * 50_000)
    with pytest.raises(ConfigError) as exc2:
        load_config(p)
    assert len(str(exc2.value)) < 1000
    with p.open("wb") as f:
        f.truncate(2 << 20)
    with pytest.raises(ConfigError, match="exceeds the limit"):
        load_config(p)
    # shared aliases of a small document still load (YAML as users write it)
    from station.bounded import load_yaml

    assert load_yaml("a: &x [1, 2]\nb: *x\nc: {d: *x}\n", "t") == {"a": [1, 2], "b": [1, 2], "c": {"d": [1, 2]}}
    with pytest.raises(BadInputError):
        load_yaml(_alias_bomb(6), "t", max_nodes=9 ** 6)


# --------------------------------------------------------------------------------------- secrets
@pytest.mark.slow
def test_an_invalid_token_is_never_printed(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """| token echoed | an invalid configured token (e.g. with spaces) is printed in the start-up error |"""
    import yaml

    secrets = ["my zq-secret passphrase", "zqshort", "zqtab\tzqsecret-9876", "ümlaut-zqsecret-1234"]
    for secret in secrets:
        d = daemon_config(tmp_path / "rec")
        d["service"] = {"token": secret}
        cfg = tmp_path / "station.yaml"
        cfg.write_text(yaml.safe_dump(d))
        monkeypatch.delenv("STATION_TOKEN", raising=False)
        assert main(["serve", "--config", str(cfg)]) == 2
        monkeypatch.setenv("STATION_TOKEN", secret)
        assert main(["serve", "--sim", "--config", str(cfg)]) == 2
        d["service"] = {"tokn": secret}  # a misspelt key
        cfg.write_text(yaml.safe_dump(d))
        assert main(["serve", "--sim", "--config", str(cfg)]) == 2
        out = capsys.readouterr()
        text = out.out + out.err
        assert "service.token" in text and "service.tokn: unknown key" in text
        for part in secret.split():
            assert part not in text, (secret, text)
    # a valid token is in no representation of the configuration or the settings
    from station.config import config_to_yaml, load_config
    from station.service.settings import build_settings

    d = daemon_config(tmp_path / "rec")
    d["service"] = {"token": "zq-valid-secret-token"}
    cfg.write_text(yaml.safe_dump(d))
    loaded = load_config(cfg)
    settings = build_settings(loaded, sim=True, env={})
    assert settings.token == "zq-valid-secret-token"
    for shown in (repr(loaded), str(loaded), repr(settings), config_to_yaml(loaded), config_to_yaml(settings.config)):
        assert "zq-valid" not in shown


# --------------------------------------------------------------------------------------- one daemon per folder
def _hold_lock(folder: Path, note: dict[str, Any]) -> subprocess.Popen[bytes]:
    """Another process holding the folder's station lock (as a daemon would), until killed."""
    folder.mkdir(parents=True, exist_ok=True)
    code = ("import fcntl, json, os, sys, time\n"
            f"fd = os.open({str(folder / LOCK_NAME)!r}, os.O_RDWR | os.O_CREAT)\n"
            "fcntl.flock(fd, fcntl.LOCK_EX)\n"
            f"os.write(fd, json.dumps({{**{note!r}, 'pid': os.getpid()}}).encode())\n"
            "print('locked', flush=True)\n"
            "time.sleep(600)\n")
    p = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE)
    assert p.stdout is not None and p.stdout.readline() == b"locked\n"
    return p


def _snapshot(folder: Path) -> dict[str, tuple[int, int]]:
    return {p.name: (p.stat().st_size, p.stat().st_mtime_ns) for p in folder.iterdir() if p.name != LOCK_NAME}


def test_a_second_station_on_the_folder_touches_nothing(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """| a second daemon on the same recordings folder damages the running one | (in process: the first
    is another process holding the lock; a database with a live run and its partial recording) |"""
    import yaml

    from station.lab.store import RunRow, Store

    rec = tmp_path / "rec"
    rec.mkdir()
    store = Store(rec / "station.db")
    store.insert_run(RunRow(id="live", state="running", transducer_id="TX5K-0001", top_mass_kg=25.0,
                            request_json="{}", plan_json="{}", created=time.time(), n_steps=2))
    store.close()
    (rec / "live.h5.partial").write_bytes(b"\x89HDF live partial recording")
    cfg = tmp_path / "station.yaml"
    cfg.write_text(yaml.safe_dump(daemon_config(rec)))
    before = _snapshot(rec)
    holder = _hold_lock(rec, {"what": "station serve", "host": "127.0.0.1", "port": 8123, "hostname": "rig-pc"})
    try:
        monkeypatch.setenv("STATION_TOKEN", "test-token-0123456789")
        assert main(["serve", "--sim", "--config", str(cfg), "--port", "0"]) == 1
        err = capsys.readouterr().err
        assert f"PID {holder.pid}" in err and "http://127.0.0.1:8123/" in err and "rig-pc" in err, err
        assert str(rec) in err and "touched nothing" in err and "Traceback" not in err
        assert main(["calibrate", "--sim", "--config", str(cfg), "--out", str(rec)]) == 1
        assert f"PID {holder.pid}" in capsys.readouterr().err
        assert _snapshot(rec) == before  # no recovery, no rename, no database write
        assert Store(rec / "station.db").get_run("live").state == "running"  # type: ignore[union-attr]
    finally:
        holder.kill()
        holder.wait()
    # the holder gone (however it ended), the lock is free again: no stale lock file blocks a start
    with InstanceLock.acquire(rec, "test") as lock:
        assert json.loads((rec / LOCK_NAME).read_text())["pid"] == os.getpid()
        assert InstanceLock.acquire(rec, "test") is lock  # re-entrant within the process
        lock.release()
    assert not (rec / LOCK_NAME).exists()  # a clean end leaves no lock file


def test_the_daq_port_is_opened_exclusively(tmp_path: Path) -> None:
    """| a second daemon ... opens the DAQ port and sends STOP | (the serial port is exclusive) |"""
    import pty

    from drivers.daq.link import DaqLinkError, SerialLink

    master, slave = pty.openpty()
    try:
        name = os.ttyname(slave)
        first = SerialLink(name, baudrate=115200)
        try:
            with pytest.raises(DaqLinkError, match="another program has it open"):
                SerialLink(name, baudrate=115200)
        finally:
            first.close()
        SerialLink(name, baudrate=115200).close()  # free again once closed
    finally:
        os.close(master)
        os.close(slave)


def test_the_motor_rtu_port_is_opened_exclusively(tmp_path: Path) -> None:
    """| a second daemon ... opens the DAQ port and sends STOP | (the Modbus RTU port is exclusive too: a
    second program cannot send the motor a command while the station holds the line) |"""
    import pty

    import serial

    from drivers.motor.errors import MotorLinkError
    from drivers.motor.transport import LinkPolicy, ModbusTransport

    master, slave = pty.openpty()
    try:
        held = serial.Serial(os.ttyname(slave), exclusive=True)  # the station's line
        try:
            t = ModbusTransport.rtu(os.ttyname(slave), policy=LinkPolicy(reconnect_attempts=1, backoff_initial_s=0.01))
            with pytest.raises(MotorLinkError):
                asyncio.run(t.open())
            assert not t.connected
        finally:
            held.close()
    finally:
        os.close(master)
        os.close(slave)


# --------------------------------------------------------------------------------------- the database at start
def _station_db(rec: Path, runs: int = 200) -> Path:
    from station.lab.store import RunRow, Store

    rec.mkdir(parents=True, exist_ok=True)
    store = Store(rec / "station.db")
    for i in range(runs):
        store.insert_run(RunRow(id=f"run-{i}", state="completed", transducer_id="TX5K-0001", top_mass_kg=25.0,
                                request_json="{}", plan_json="{}" + " " * 500, created=float(i), n_steps=2))
    store._db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    store.close()
    return rec / "station.db"


@pytest.mark.parametrize("damage", ["truncated", "garbage", "locked"])
@pytest.mark.slow
def test_a_damaged_or_locked_database_at_start_is_one_clear_message(
        damage: str, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    """| damaged database at start | truncated, garbage or locked `station.db`: exit 3 with a traceback
    instead of a message that names the file and the fix |"""
    import yaml

    rec = tmp_path / "rec"
    db = _station_db(rec)
    holder = None
    if damage == "truncated":
        with db.open("r+b") as f:
            f.truncate(db.stat().st_size // 3)
    elif damage == "garbage":
        db.write_bytes(os.urandom(64 * 1024))
    else:  # another process keeps a write transaction open (e.g. a sqlite3 shell)
        code = (f"import sqlite3, time\ndb = sqlite3.connect({str(db)!r}, isolation_level=None)\n"
                "db.execute('BEGIN EXCLUSIVE')\nprint('locked', flush=True)\ntime.sleep(600)\n")
        holder = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE)
        assert holder.stdout is not None and holder.stdout.readline() == b"locked\n"
    cfg = tmp_path / "station.yaml"
    cfg.write_text(yaml.safe_dump(daemon_config(rec)))
    monkeypatch.setenv("STATION_TOKEN", TOKEN)
    try:
        code = main(["serve", "--sim", "--config", str(cfg), "--port", "0"])
    finally:
        if holder is not None:
            holder.kill()
            holder.wait()
    err = capsys.readouterr().err
    assert code != 0
    assert "Traceback" not in err and f"the station database {db}" in err, err
    lines = [ln for ln in err.splitlines() if "error" in ln.lower()]
    assert len(lines) == 1, err  # one message
    if damage == "locked":
        assert "locked by another process" in err and "close that program" in err
    else:
        assert "damaged" in err and f"mv {db} {db}.damaged" in err and ".recover" in err


def test_a_daemon_that_cannot_start_says_why_in_one_line(tmp_path: Path) -> None:
    """| damaged database at start | ... exit 3 with a traceback (whatever else stops a start: one line) |"""
    from station.api import create_app
    from station.config import parse_config
    from station.errors import StationError
    from station.service.settings import build_settings

    settings = build_settings(parse_config(daemon_config(tmp_path / "rec")), sim=True, workers=0,
                              env={"STATION_TOKEN": TOKEN})

    def broken(_: Any) -> Any:
        raise StationError("the recordings folder went away")

    app = create_app(settings, manager_factory=broken)
    sent: list[dict[str, Any]] = []

    async def go() -> None:
        messages = iter([{"type": "lifespan.startup"}])

        async def receive() -> dict[str, Any]:
            return next(messages)

        async def send(message: dict[str, Any]) -> None:
            sent.append(message)
        with pytest.raises(StationError):
            await app({"type": "lifespan", "asgi": {"version": "3.0"}, "state": {}}, receive, send)
    asyncio.run(go())
    assert sent[-1]["type"] == "lifespan.startup.failed"
    assert sent[-1]["message"] == ("the station daemon cannot start: station.errors.StationError: the recordings "
                                   "folder went away (details: -v)")


# --------------------------------------------------------------------------------------- orphaned worker
_POOL_PARENT = """
import sys, time
sys.path.insert(0, sys.argv[2])  # the repository, for tests.worker_support (the worker gets this path too)
from station.service import worker
from tests.worker_support import busy_sleep
pool = worker.WorkerPool("identification", 1)
ex = pool._get()
fut = ex.submit(time.sleep, 0.0)
print(" ".join(map(str, pool.pids())), flush=True)
if sys.argv[1] != "starting":
    fut.result()  # the worker is up; then a 4 s job (a job, not a bare call: only a job keeps an
    ex.submit(busy_sleep, 4.0)  # orphaned worker alive until it is done)
    time.sleep(0.5)
    print("ready", flush=True)
time.sleep(600)
"""


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except FileNotFoundError:
        return False
    return state not in ("Z", "X")  # a zombie is dead (waiting for PID 1 to reap it)


@pytest.mark.parametrize("when", ["starting", pytest.param("busy", marks=pytest.mark.slow)])
def test_workers_die_with_their_daemon(when: str, tmp_path: Path) -> None:
    """| orphaned worker | a daemon killed while a worker starts leaves the worker alive (parent PID 1,
    143 MB, 14 min later) |  (the daemon here: a process with the daemon's WorkerPool, killed -9)"""
    parent = subprocess.Popen([sys.executable, "-c", _POOL_PARENT, when, str(Path(__file__).resolve().parent.parent)],
                              stdout=subprocess.PIPE, cwd=tmp_path)
    assert parent.stdout is not None
    pids = [int(p) for p in parent.stdout.readline().split()]
    if when != "starting":
        assert parent.stdout.readline() == b"ready\n"
    parent.kill()  # while the worker still imports (starting) or runs its 4 s job (busy)
    parent.wait()
    assert pids and (when == "starting" or all(_alive(p) for p in pids))
    deadline = time.monotonic() + 20.0
    while time.monotonic() < deadline and any(_alive(p) for p in pids):
        time.sleep(0.1)
    assert not any(_alive(p) for p in pids), pids


# --------------------------------------------------------------------------------------- full disk while identifying
class _IdentifyingWorker:
    """The worker boundary of the JobQueue (one class under test): the identification succeeds, and
    meanwhile the database's disk fills up (a real ENOSPC on a tmpfs)."""

    started, crashes = True, 0

    def __init__(self, disk: Path) -> None:
        self.disk = disk
        self.calls = 0

    async def run(self, fn: Any, *args: Any) -> dict[str, Any]:
        from station.service import worker

        assert fn is worker.identify_job
        self.calls += 1
        fill_disk(self.disk / f"filler-{self.calls}")
        return {"result_name": "identify_fd_h2", "method": "fd", "model": "h2", "wall_s": 0.5}


async def _until(cond: Any, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, "condition not met in time"
        await asyncio.sleep(0.02)


def test_a_full_disk_while_identifying_keeps_the_result_until_the_database_takes_it(
        tmp_path: Path, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch) -> None:
    """| a full disk while identifying | the worker's result is dropped when the database write fails, no
    log line; the run stays `identifying` until a restart |"""
    from station.lab.store import RunRow, Store
    from station.service import jobs
    from station.service.artifacts import Artifacts
    from station.service.changes import Changes
    from station.service.db import DbAccess
    from station.service.recovery import recover

    monkeypatch.setattr(jobs, "RECORD_RETRY_S", 0.05)
    rec = tmp_path / "rec"
    rec.mkdir()
    with mounted_tmpfs(tmp_path, 4) as disk:
        store = Store(disk / "station.db")
        for rid in ("r1", "r2"):
            (rec / f"{rid}.h5").write_bytes(b"recording")
            store.insert_run(RunRow(id=rid, state="identifying", transducer_id="TX5K-0001", top_mass_kg=25.0,
                                    request_json="{}", plan_json="{}", created=time.time(), n_steps=1,
                                    recording=f"{rid}.h5"))

        async def go(rid: str, free_space: bool) -> jobs.JobQueue:
            closing = asyncio.Event()
            store.enqueue_job(rid)
            db = DbAccess(store).start()

            async def get_row(run_id: str) -> RunRow:
                return await db.read(lambda s: s.get_run(run_id))  # type: ignore[return-value]
            q = jobs.JobQueue(db, _IdentifyingWorker(disk), 1,  # type: ignore[arg-type]
                              Artifacts(rec, None, get_row), Changes(closing), closing)  # type: ignore[arg-type]
            q.start()
            await _until(lambda: rid in q.unrecorded)
            assert "identified (fd, h2)" in q.unrecorded[rid] and "identify_fd_h2" in q.unrecorded[rid]
            assert "full" in q.unrecorded[rid]
            assert store.get_run(rid).state == "identifying"  # type: ignore[union-attr]
            if free_space:
                for f in disk.glob("filler-*"):
                    f.unlink()
                await _until(lambda: store.get_run(rid).state == "completed")  # type: ignore[union-attr]
                assert store.get_run(rid).result_name == "identify_fd_h2"  # type: ignore[union-attr]
                await _until(lambda: q.unrecorded == {})  # dropped once the write returned
            closing.set()
            await q.stop_dispatcher()
            await asyncio.gather(*q._tasks, return_exceptions=True)
            await asyncio.to_thread(db.close, 0.5)
            return q

        with caplog.at_level("INFO", logger="station.service.jobs"):
            asyncio.run(go("r1", free_space=True))
        logged = caplog.text
        assert "run r1: identified (fd, h2)" in logged and "the database cannot record it" in logged
        assert "run r1: outcome recorded after" in logged
        # shut down while the database still refuses: the job is left running, so the next start runs it again
        asyncio.run(go("r2", free_space=False))
        assert "runs again at the next start" in caplog.text
        for f in disk.glob("filler-*"):
            f.unlink()
        assert [j.state for j in store.jobs(run_id="r2")] == ["running"]
        out = recover(store, rec, jobs.MAX_JOB_ATTEMPTS)
        assert "r2" in out["requeued"] and [j.state for j in store.jobs(run_id="r2")] == ["queued"]
        store.close()
