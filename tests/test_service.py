"""The daemon's service layer: the SQLite store, request checks, recordings kept inside their folder,
and what survives the end of the daemon (kill -9 mid-run, SIGTERM mid-run, queued jobs)."""

from __future__ import annotations

import asyncio
import io
import os
import signal
import sqlite3
import subprocess
import time
from pathlib import Path

import h5py
import pytest

from station.config import parse_config
from station.errors import ConfigError, LimitError
from station.lab.store import RunRow, Store
from station.limits import max_radius_m
from station.recording import read_recording
from station.run.request import RunRequest, StepSpec, plan_run
from station.service.manager import RunManager, RunStateError
from station.service.settings import build_settings
from tests.station_support import Daemon, Seed, daemon_config

# an identification in a worker process takes seconds of CPU, several times more on a loaded machine:
# the daemon tests wait for it this long
IDENTIFIED_WITHIN_S = 180.0


def _row(run_id: str, state: str = "queued", created: float | None = None) -> RunRow:
    return RunRow(id=run_id, state=state, transducer_id="TX", top_mass_kg=1.0, request_json="{}",
                  plan_json='{"steps": []}', created=created or time.time(), n_steps=1)


# ---------------------------------------------------------------------------------------- store
def test_store_is_wal_and_keeps_runs_and_jobs(tmp_path: Path) -> None:
    db = tmp_path / "s.db"
    s = Store(db)
    assert s.journal_mode() == "wal"
    s.insert_run(_row("a", created=1.0))
    s.insert_run(_row("b", "running", created=2.0))
    s.update_run("a", state="identifying", samples=5, message="x")
    with pytest.raises(KeyError):
        s.update_run("a", nonsense=1)
    assert [r.id for r in s.list_runs()] == ["b", "a"]
    assert [r.id for r in s.list_runs(states=["identifying"])] == ["a"]
    j1, j2 = s.enqueue_job("a"), s.enqueue_job("b")
    first = s.claim_job()
    assert first is not None and first.id == j1 and first.attempts == 1 and first.state == "running"
    s.close()
    # another connection (another process after a restart) sees every committed change
    s2 = Store(db)
    assert s2.get_run("a").samples == 5  # type: ignore[union-attr]
    assert s2.job_counts() == {"queued": 1, "running": 1, "done": 0, "failed": 0}
    requeued, failed = s2.requeue_running_jobs(max_attempts=3)
    assert [j.id for j in requeued] == [j1] and failed == []
    assert s2.claim_job().id == j1  # type: ignore[union-attr]  # oldest first
    assert s2.claim_job().id == j2  # type: ignore[union-attr]
    assert s2.claim_job() is None
    for _ in range(3):
        s2.requeue_running_jobs(max_attempts=3)
        s2.claim_job()
        s2.claim_job()
    s2.requeue_running_jobs(max_attempts=3)
    jobs = s2.jobs()
    assert [(j.state, j.attempts) for j in jobs] == [("failed", 3), ("failed", 3)]  # not tried forever
    assert "3 times" in jobs[0].error
    assert sqlite3.connect(db).execute("PRAGMA journal_mode").fetchone()[0] == "wal"


# ---------------------------------------------------------------------------------------- checks
def test_a_broken_limit_names_the_step_field_value_and_limit(tmp_path: Path) -> None:
    """plan_run raises one LimitError that says which step, which field, its value and the limit
    (the API puts it at that field of the body; nothing checks the request again to find it)."""
    cfg = parse_config(daemon_config(tmp_path))

    def req(*steps: tuple[float, float], tid: str = "TX5K-0001", mass: float = 25.717) -> RunRequest:
        return RunRequest(transducer_id=tid, top_mass_kg=mass,
                          steps=[StepSpec(crank_frequency_hz=f, crank_radius_m=r) for f, r in steps])
    assert len(plan_run(cfg, req((10, 0.001), (20, 0.001))).steps) == 2
    r_max_40 = max_radius_m(cfg, 40.0)
    heavy = cfg.model_copy(update={"rig": cfg.rig.model_copy(update={"top_mass_kg": 60.0})})
    cases = [(req((10, 0.001), tid="X-1"), (None, "transducer_id", "X-1", "TX5K-0001")),
             (req((10, 0.001), (0.5, 0.001)), (1, "crank_frequency_hz", 0.5, (1.0, 100.0))),
             (req((10, 0.001), (20, 0.00001)), (1, "crank_radius_m", 0.00001, (1e-4, 0.05))),
             (req((10, 0.01), (40, 0.01)), (1, "crank_radius_m", 0.01, pytest.approx(r_max_40))),
             # a heavier top mass makes a step unsafe that was fine before
             (req((20, 0.008), mass=60.0), (0, "crank_radius_m", 0.008, pytest.approx(max_radius_m(heavy, 20.0))))]
    for request, (step, field, value, limit) in cases:
        with pytest.raises(LimitError) as ei:
            plan_run(cfg, request)
        e = ei.value
        assert (e.step, e.field, e.value, e.limit) == (step, field, value, limit), (request, e)
    assert r_max_40 < 0.01


def test_settings_refuse_a_real_rig_without_token(tmp_path: Path) -> None:
    cfg = parse_config(daemon_config(tmp_path))
    with pytest.raises(ConfigError, match="STATION_TOKEN"):
        build_settings(cfg, sim=False, env={})
    with pytest.raises(ConfigError, match="at least 8"):
        build_settings(cfg, sim=False, env={"STATION_TOKEN": "short"})
    s = build_settings(cfg, sim=False, env={"STATION_TOKEN": "long-enough-token"})
    assert s.token == "long-enough-token" and s.token_source == "env" and s.loopback_only
    assert s.database == tmp_path / "station.db"
    assert "long-enough-token" not in repr(s)
    gen = build_settings(cfg, sim=True, env={})
    assert gen.token_source == "generated" and len(gen.token) >= 16
    cfg2 = parse_config({**daemon_config(tmp_path), "service": {"token": "from-the-config-file"}})
    s2 = build_settings(cfg2, sim=True, env={})
    assert s2.token == "from-the-config-file" and s2.config.service.token is None  # never copied into recordings


def test_a_simulated_station_may_store_cheaper_passwords_a_real_one_never(tmp_path: Path) -> None:
    """``simulation.password_cost_log2`` (the tests' daemons: 10) sets the scrypt cost of the passwords
    a --sim station stores, its unknown names' check included; a real rig's station stores the
    product's 2**14 whatever the file says; a hash is checked at the cost stored with it."""
    from station.lab import users

    cfg = parse_config(daemon_config(tmp_path))
    assert build_settings(cfg, sim=False, env={"STATION_TOKEN": "long-enough-token"}).password_n == users.SCRYPT_N
    assert build_settings(cfg, sim=True, env={}).password_n == 2**10
    default = daemon_config(tmp_path)
    del default["simulation"]["password_cost_log2"]
    assert build_settings(parse_config(default), sim=True, env={}).password_n == users.SCRYPT_N == 2**14
    for bad in (9, 15):
        with pytest.raises(ConfigError, match="password_cost_log2"):
            parse_config({**default, "simulation": {**default["simulation"], "password_cost_log2": bad}})
    store = Store(tmp_path / "users.db")
    try:
        users.put_user(store, "tina", users.Role.TECHNICIAN, "admin", password="tina-secret-pw", n=2**10)
        users.put_user(store, "anton", users.Role.APPROVER, "admin", password="anton-secret-pw")
        stored = {r["name"]: r["password"] for r in store.query("SELECT name, password FROM users")}
        assert stored["tina"].startswith("scrypt$1024$8$1$") and stored["anton"].startswith("scrypt$16384$8$1$")
        for n in (2**10, 2**14):  # each hash checked at its own cost on a station of either
            assert users.check_login(store, "tina", "tina-secret-pw", n) is not None
            assert users.check_login(store, "anton", "anton-secret-pw", n) is not None
            assert users.check_login(store, "tina", "anton-secret-pw", n) is None
            assert users.login_candidate(store, "nobody", n)[1].startswith(f"scrypt${n}$")
    finally:
        store.close()


def test_a_pdf_is_the_kept_html_page_through_the_engine_and_each_is_drawn_once(tmp_path: Path) -> None:
    """The report's and a draft certificate's PDF: the page the render worker drew (kept, as the HTML
    form is served) sent to its PDF job, in either order; each form drawn once until a result is
    stored beside the recording (then again).  The render worker counted (its jobs recorded, not run)."""
    from station.service.artifacts import Artifacts

    jobs: list[tuple[str, tuple[object, ...]]] = []

    class Pool:
        async def run(self, fn: object, *args: object) -> object:
            name = getattr(fn, "__name__", "")
            jobs.append((name, args))
            page = f"<html>{name} {len(jobs)}</html>"
            return {"report_job": page, "pdf_job": b"%PDF " + str(args[0]).encode(),
                    "certificate_job": page.encode()}[name]

    (tmp_path / "r1.h5").write_bytes(b"a recording")
    row = RunRow(id="r1", state="completed", transducer_id="TX", top_mass_kg=25.0, request_json="{}",
                 plan_json="{}", created=0.0, n_steps=1, recording="r1.h5")

    async def get_row(run_id: str) -> RunRow:
        return row

    art = Artifacts(tmp_path, Pool(), get_row)  # type: ignore[arg-type]

    async def go() -> None:
        page = await art.report("r1")
        assert await art.report_pdf("r1") == b"%PDF " + page.encode()
        assert [j[0] for j in jobs] == ["report_job", "pdf_job"] and jobs[1][1] == (page,)
        cert_pdf = await art.certificate("r1", "pdf")  # the PDF first: its page drawn for it, then kept
        cert = await art.certificate("r1", "html")
        assert cert_pdf == b"%PDF " + cert and b"certificate_job" in cert
        assert [j[0] for j in jobs[2:]] == ["certificate_job", "pdf_job"] and jobs[2][1][1] == "html"
        for _ in range(2):  # kept: nothing drawn again
            assert (await art.report_pdf("r1"), await art.certificate("r1", "pdf")) == (b"%PDF " + page.encode(),
                                                                                      cert_pdf)
        assert len(jobs) == 4
        results = tmp_path / "r1.results"
        results.mkdir()
        (results / "results.discrepancy.h5").write_bytes(b"a result")  # stored later: drawn again
        assert await art.report_pdf("r1") != b"%PDF " + page.encode()
        assert [j[0] for j in jobs[4:]] == ["report_job", "pdf_job"]
    asyncio.run(go())


def test_recording_paths_stay_inside_the_recordings_folder(tmp_path: Path) -> None:
    cfg = parse_config(daemon_config(tmp_path / "rec"))
    m = RunManager(build_settings(cfg, sim=True, env={}))
    try:
        outside = tmp_path / "secret.h5"
        outside.write_bytes(b"x")
        for name in ("../secret.h5", str(outside), "/etc/passwd", "nope.h5"):
            row = _row("r1", "completed")
            row.recording = name
            with pytest.raises(RunStateError):
                m.artifacts.recording_path(row)
        (tmp_path / "rec" / "ok.h5").write_bytes(b"x")
        row = _row("r2", "completed")
        row.recording = "ok.h5"
        assert m.artifacts.recording_path(row) == (tmp_path / "rec" / "ok.h5").resolve()
    finally:
        m.store.close()


# ---------------------------------------------------------------------------------------- restarts
def _alive(pids: list[int]) -> list[int]:
    """Those of ``pids`` still running (a zombie waiting for its reaper has exited)."""
    out = []
    for p in pids:
        try:
            status = Path(f"/proc/{p}/status").read_text()
        except OSError:
            continue
        if "zombie" not in status.lower():
            out.append(p)
    return out


def _children(pid: int) -> list[int]:
    out = subprocess.run(["pgrep", "-P", str(pid)], capture_output=True, text=True).stdout
    return [int(p) for p in out.split()]


def _daemon_children(pid: int) -> dict[str, list[int]]:
    """The daemon's child processes by what they are: its identification workers, its rig process
    and (simulated) the emulators' process; each must end with the daemon."""
    kinds: dict[str, list[int]] = {"rig process": [], "emulators": [], "workers": []}
    for p in _children(pid):
        try:
            cmd = Path(f"/proc/{p}/cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        kind = ("rig process" if b"station.rigproc" in cmd else "emulators" if b"drivers.sim" in cmd
                else "workers")
        kinds[kind].append(p)
    return kinds


def _wait_gone(pids: list[int], timeout_s: float = 20.0) -> list[int]:
    """Those of ``pids`` still running after up to ``timeout_s`` (a loaded machine ends them slowly)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and _alive(pids):
        time.sleep(0.1)
    return _alive(pids)


@pytest.mark.slow
@pytest.mark.waits  # two daemon starts, a kill and a restart: about 20 s, mostly waiting
def test_kill_9_mid_run_then_restart_recovers_and_sigterm_mid_run_closes_the_run_and_every_process(
        tmp_path: Path) -> None:
    """A daemon killed -9 mid-run: its rig process and the emulators' process end with it (on the end
    of their stdin); the next daemon closes the run as interrupted with a readable recording, resumes
    the queued identification and takes new runs.  Sent SIGTERM in turn mid-run, with a worker process
    that has identified runs, it stops the run, closes its recording and ends its rig process, the
    emulators and its workers.  (Workers end with a daemon killed -9 on PR_SET_PDEATHSIG:
    ``tests/test_fault_matrix_isolation.py::test_workers_die_with_their_daemon``.)"""
    data = tmp_path / "recordings"
    # first daemon without workers: the identification of run A (acquired, seeded) stays queued
    first = Daemon(tmp_path, workers=0, data_dir=data, name="first", seeds=[Seed(identified=False)]).start()
    try:
        [a] = first.seeded
        st = first.wait_state(a, ("identifying",))
        assert st["recording"] == f"{a}.h5"
        b = first.start_run(freqs=(10.0,), record_s=30.0)
        first.wait_state(b, ("running",), step_state="recording")
        # 2 s of samples acquired (on a loaded machine the acquisition's clock is not the wall's), then
        # past the writer's next flush (every 0.5 s): at least the first second is on the disk
        deadline = time.monotonic() + 60.0
        while first.c().get(f"/runs/{b}").json()["samples"] < 40_000 and time.monotonic() < deadline:
            time.sleep(0.1)
        time.sleep(1.5)
        assert (data / f"{b}.h5.partial").exists()
        assert first.proc is not None
        kids = _daemon_children(first.proc.pid)
        assert kids["rig process"] and kids["emulators"], kids
    finally:
        first.kill()
    assert first.proc is not None and first.proc.returncode == -signal.SIGKILL
    pids = [p for ps in kids.values() for p in ps]  # nothing of it is left running
    assert not _wait_gone(pids), subprocess.run(
        ["ps", "-o", "pid,ppid,stat,cmd", "-p", ",".join(map(str, pids))], capture_output=True, text=True).stdout
    db = sqlite3.connect(data / "station.db")
    assert dict(db.execute("SELECT id, state FROM runs").fetchall()) == {a: "identifying", b: "running"}
    assert db.execute("SELECT run_id, state FROM jobs").fetchall() == [(a, "queued")]
    db.close()

    second = Daemon(tmp_path, workers=1, data_dir=data, name="second").start()
    try:
        c = second.c()
        st = c.get(f"/runs/{b}").json()
        assert st["state"] == "interrupted" and "daemon stopped during the run" in st["reason"]
        assert st["recording"] == f"{b}.h5" and not (data / f"{b}.h5.partial").exists()
        rec = c.get(f"/runs/{b}/recording")
        assert rec.status_code == 200
        path = tmp_path / "b.h5"
        path.write_bytes(rec.content)
        r = read_recording(path)
        assert r.exit_status == "interrupted" and r.complete and r.displacement_m.size > 20_000
        # the queued job of run A resumed in the new daemon's worker
        st = second.wait_state(a, ("completed", "failed"), timeout_s=IDENTIFIED_WITHIN_S)
        assert st["state"] == "completed", st
        res = c.get(f"/runs/{a}/results").json()
        assert {p["name"] for p in res["parameters"] if p["identifiable"]} >= {"S", "k_f", "b_f"}
        for _ in range(200):  # the job is done once the methods listed after the primary have their outcome
            jobs = c.get("/health").json()["worker"]["jobs"]
            if jobs.get("done") == 1:
                break
            time.sleep(0.05)
        assert jobs.get("done") == 1, jobs
        # and the rig takes new runs
        n = second.start_run(freqs=(10.0,))
        assert second.wait_state(n, timeout_s=IDENTIFIED_WITHIN_S)["state"] == "completed"
        # SIGTERM mid-run, with a worker process that has identified runs
        assert second.proc is not None
        kids = _daemon_children(second.proc.pid)
        assert all(kids.values()), kids  # workers, the rig process and the emulators' process
        rid = second.start_run(freqs=(10.0,), record_s=30.0)
        second.wait_state(rid, ("running",), step_state="recording")
        # uvicorn >= 0.29: killed by the signal, raised again once the daemon has shut down (within
        # ``Daemon.stop``'s bound)
        assert second.stop(signal.SIGTERM) in (0, -signal.SIGTERM)
    finally:
        if second.proc is not None and second.proc.poll() is None:
            second.kill()
    log = second.log()
    assert "interrupted: the station was stopped during the run" in log
    assert "did not end within" not in log  # the run ended itself: no emergency stop after the shutdown's wait
    assert "Traceback" not in log  # the rig process's channel ends cleanly too
    # the daemon ended its rig process (which stops a turning crank) and then the emulators itself,
    # before it ended: none is left to end on its own once the daemon is gone
    assert _alive(kids["rig process"] + kids["emulators"]) == [], kids
    path = data / f"{rid}.h5"
    assert path.exists() and not (data / f"{rid}.h5.partial").exists()
    rec_ = read_recording(path)  # closed properly by the procedure (it stops the motor first)
    assert rec_.complete and rec_.exit_status == "interrupted"
    db = sqlite3.connect(data / "station.db")
    state, reason, recording = db.execute("SELECT state, reason, recording FROM runs WHERE id = ?",
                                          (rid,)).fetchone()
    db.close()
    assert state == "interrupted" and "shut down" in reason and recording == path.name
    assert _wait_gone([p for ps in kids.values() for p in ps]) == [], kids
    with h5py.File(io.BytesIO(path.read_bytes()), "r") as f:
        assert f.attrs["exit_status"] == "interrupted"


@pytest.mark.slow  # a run on the simulated rig, started and stopped
def test_a_second_shutdown_call_never_cuts_short_the_stop_and_the_closing_of_the_recording(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A daemon begins its shutdown twice: from the signal handler, then from the lifespan's close.
    The run on the rig is cancelled once: the second call, arriving while the procedure stops the
    motor, must not cut that stop short, nor the closing of the recording; the run's row names the
    closed recording and the audit chain holds its SHA-256."""
    import threading

    from station.lab import audit
    from station.lab.integrity import sha256_file
    from station.run.procedure import Procedure
    from tests.station_support import CAPPED_SPEEDUP, IDLE_SPEEDUP, app_in_process, start, wait_state

    stopping, second_call_made = threading.Event(), threading.Event()
    stop_motor = Procedure._stop_motor

    async def stop_after_the_second_call(self: Procedure, *, hard: bool) -> None:
        stopping.set()
        await asyncio.to_thread(second_call_made.wait, 30.0)  # the second call reaches the rig loop first
        await stop_motor(self, hard=hard)
    monkeypatch.setattr(Procedure, "_stop_motor", stop_after_the_second_call)
    rec_dir = tmp_path / "rec"

    async def go() -> str:
        async with app_in_process(rec_dir, max_speedup=CAPPED_SPEEDUP, idle_speedup=IDLE_SPEEDUP) as (m, c):
            rid = await start(c, freqs=(10.0,), record_s=30.0)
            await wait_state(c, rid, ("running",), step_state="recording")
            tasks = m.begin_shutdown()  # the signal handler
            assert await asyncio.to_thread(stopping.wait, 30.0)
            m.begin_shutdown()  # the lifespan's close, while the procedure stops the motor
            second_call_made.set()
            _, pending = await asyncio.wait(tasks, timeout=60.0)
            assert not pending
            return rid
    rid = asyncio.run(go())
    store = Store(rec_dir / "station.db")
    try:
        row = store.get_run(rid)
        assert row is not None and row.state == "interrupted" and "shut down" in row.reason
        assert row.recording == f"{rid}.h5", row
        path = rec_dir / row.recording
        assert not (rec_dir / f"{rid}.h5.partial").exists()
        rec = read_recording(path)
        assert rec.complete and rec.exit_status == "interrupted"
        [ended] = audit.entries(store, target=rid, action=audit.RUN_ENDED)
        assert ended.files == {path.name: sha256_file(path)} and row.recording_sha256 == sha256_file(path)
    finally:
        store.close()


def test_serve_refuses_a_bad_configuration_at_start_up(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    import station.commands.server
    from station.cli import main

    class NeverServe:  # a refusal must come before the server is built
        def __init__(self, *a: object, **k: object) -> None:
            raise AssertionError("the daemon started on a configuration it should refuse")
    monkeypatch.setattr(station.commands.server, "StationServer", NeverServe)
    monkeypatch.delenv("STATION_TOKEN", raising=False)
    monkeypatch.chdir(tmp_path)
    cfg = tmp_path / "bad.yaml"
    cfg.write_text("service: {port: 99999}\n" + (Path(__file__).parent.parent / "config" / "sim-5kN.yaml").read_text())
    assert main(["serve", "--config", str(cfg)]) == 2
    assert "service.port" in capsys.readouterr().err
    ok = tmp_path / "ok.yaml"
    ok.write_text((Path(__file__).parent.parent / "config" / "sim-5kN.yaml").read_text())
    assert main(["serve", "--config", str(ok)]) == 2
    assert "STATION_TOKEN" in capsys.readouterr().err  # a real rig needs a token


def test_worker_pool_survives_a_dying_worker() -> None:

    from station.service.worker import WorkerCrashed, WorkerPool

    async def go() -> tuple[int, int]:
        pool = WorkerPool("test", 1)
        try:
            with pytest.raises(WorkerCrashed):
                await pool.run(os._exit, 3)
            pid = await pool.run(os.getpid)  # a fresh process takes the next job
            return pid, pool.crashes
        finally:
            pool.shutdown(5.0)
    pid, crashes = asyncio.run(go())
    assert pid != os.getpid() and crashes == 1


def test_worker_processes_run_single_threaded_blas() -> None:

    from station.service.worker import WorkerPool

    async def go() -> tuple[str | None, str | None]:
        pool = WorkerPool("test", 1)
        try:
            return (await pool.run(os.getenv, "OPENBLAS_NUM_THREADS"),
                    await pool.run(os.getenv, "OMP_NUM_THREADS"))
        finally:
            pool.shutdown(5.0)
    assert asyncio.run(go()) == ("1", "1")


@pytest.mark.slow  # the connection attempts back off for ~3 s
def test_unreachable_rig_health_degraded_runs_503_stop_still_accepted(tmp_path: Path) -> None:
    """The daemon's app in-process with the real rig's connector: nothing listens at the motor's
    address and the DAQ port does not exist."""
    from station.api import create_app
    from station.service.settings import build_settings
    from tests.station_support import TOKEN, asgi_client, free_port, run_body

    d = daemon_config(tmp_path / "rec")
    del d["simulation"]
    d["devices"] = {"motor_url": f"modbus-tcp://127.0.0.1:{free_port()}", "daq_port": str(tmp_path / "no-such-tty")}
    app = create_app(build_settings(parse_config(d), sim=False, env={"STATION_TOKEN": TOKEN}))

    async def go() -> None:
        async with app.router.lifespan_context(app), asgi_client(app) as c:
            h = (await c.get("/health")).json()
            assert h["status"] == "degraded" and not h["rig"]["connected"] and h["rig"]["error"]
            assert not h["rig"]["simulated"] and h["database"]["ok"]
            r = await c.post("/runs", json=run_body())
            assert r.status_code == 503 and "not connected" in r.json()["detail"]
            s = await c.post("/stop")
            assert s.status_code == 200 and s.json()["accepted"] and not s.json()["motor_stopped"]
            assert "hardware emergency stop" in s.json()["detail"]
            assert (await c.get("/runs")).json()["count"] == 0
    asyncio.run(go())


def test_start_up_recovery_of_every_kind_of_cut_off_run(tmp_path: Path) -> None:
    import numpy as np

    from station.recording import ChannelSpec, RecordingWriter, RunMetadata
    from station.simulate import simulate_run

    rec_dir = tmp_path / "rec"
    cfg = parse_config(daemon_config(rec_dir))
    settings = build_settings(cfg, sim=True, env={})
    store = Store(settings.database)
    for rid, state in (("r-partial", "running"), ("r-done", "running"), ("r-aborted", "running"),
                       ("r-queued", "queued"), ("r-ident", "identifying"), ("r-job", "identifying")):
        row = _row(rid, state)
        row.recording = f"{rid}.h5" if state == "identifying" else None
        store.insert_run(row)
    store.enqueue_job("r-job")
    assert store.claim_job() is not None  # left running by the dead daemon
    store.close()
    meta = RunMetadata(run_id="r-partial", transducer_id="TX5K-0001", source="calibrate", sample_rate_hz=20_000.0,
                       load_mass_kg=26.0, end_mass_kg=0.12, sensitivity_V_per_N=2e-3, capacity_N=5000.0,
                       config_yaml="{}")
    chans = (ChannelSpec("displacement", "i2", "count", "m", scale=1e-6),
             ChannelSpec("force", "i2", "count", "V", scale=1e-4))
    w = RecordingWriter(rec_dir, meta, chans, min_free_bytes=0)
    w.append(np.arange(5000, dtype="i2"), np.arange(5000, dtype="i2"))
    w.flush()
    w.abandon()
    done = simulate_run(cfg, tmp_path / "sim")
    done.rename(rec_dir / "r-done.h5")
    ab = RecordingWriter(rec_dir, RunMetadata(**{**meta.__dict__, "run_id": "r-aborted"}), chans, min_free_bytes=0)
    ab.finish("aborted", "technician pressed abort")

    m = RunManager(settings)
    try:
        out = m.recover()
        runs = {r.id: r for r in m.store.list_runs()}
        assert runs["r-partial"].state == "interrupted" and runs["r-partial"].recording == "r-partial.h5"
        rec = read_recording(rec_dir / "r-partial.h5")
        assert rec.complete and rec.exit_status == "interrupted" and rec.displacement_m.size == 5000
        assert runs["r-queued"].state == "interrupted" and "no recording" in runs["r-queued"].reason
        assert runs["r-done"].state == "identifying"  # it had finished: identified now
        assert (runs["r-aborted"].state, runs["r-aborted"].reason) == ("aborted", "technician pressed abort")
        jobs = {j.run_id: j for j in m.store.jobs()}
        assert set(jobs) == {"r-done", "r-ident", "r-job"} and all(j.state == "queued" for j in jobs.values())
        assert set(out["interrupted"]) == {"r-partial", "r-queued"} and out["ended"] == ["r-aborted"]
        # every recording closed by the recovery is hashed into the audit chain, like any closed one
        from station.lab import audit
        from station.lab.integrity import sha256_file
        recovered = {e.target: e for e in audit.entries(m.store, action=audit.RECORDING_RECOVERED)}
        assert set(recovered) == {"r-partial", "r-done", "r-aborted"}
        for rid, e in recovered.items():
            sha = sha256_file(rec_dir / f"{rid}.h5")
            assert e.files == {f"{rid}.h5": sha} and runs[rid].recording_sha256 == sha
    finally:
        m.store.close()
