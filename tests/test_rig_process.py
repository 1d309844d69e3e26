"""The rig process: a real ``station serve`` whose drive, watchdog keeper and stop port live in a
process of their own, against the emulators in a third process (their true state read there).

- the web process stopped (SIGSTOP) during a run: a stop on the stop port still stops the crank
  and the drive is read back at standstill, the run aborted; the daemon latches the stop when it
  runs again; an abort from the web process ends a run carried out in the rig process and the drive
  reads back standstill; left stopped (beyond the 3 s link time-out) during a run, the run goes on in
  the rig process to its end and the page shows it completed;
- the rig process killed (SIGKILL) during a run: the drive's own watchdog stops the crank, the
  daemon starts a new rig process, and after the acknowledgement a later run works, its DAQ stream
  (under the rig process) losing no sample while the web process is stopped for 2.3 s; the stream
  process killed during a run fails that run, and the next one gets a new stream process;
- another process holds the database's write lock while a run records: the stop still reaches the
  drive (its arrival read from the emulators' log, the crank's speed from the emulators); a drive
  that takes the stop and keeps turning is read back so, latched and refused until it stops;
- the simulated rig's crank radius, as the rig process changes it under ``--sim``: on the
  emulators' control socket, at standstill.

One emulators' process and one daemon for the module (``rig``): the tests run in the file's order on
them, each leaving the crank at rest and no stop latched.
"""

from __future__ import annotations

import asyncio
import dataclasses
import os
import signal
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import h5py
import httpx
import pytest

from drivers.sim import SimRigProcess
from drivers.sim.process import SocketCrankRadius
from tests.station_support import NOT_THE_BUSY_TIMEOUT_S, Daemon, WriteLock, daemon_config, free_port, run_body

# with --dist loadgroup: the module's tests on one worker, one emulators' process and one daemon
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("rig_process")]


@dataclasses.dataclass(frozen=True)
class Rig:
    """The module's emulators' process, its daemon (``station serve`` on the emulators as a real rig's
    devices, no workers) and the rig process's stop port."""

    emu: SimRigProcess
    d: Daemon
    stop_port: int


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Rig]:
    tmp = tmp_path_factory.mktemp("rigproc")
    stop_port = free_port()
    with SimRigProcess(crank_radius_m=0.001, commands=True) as emu:
        host, port = emu.addresses.modbus_tcp
        cfg = daemon_config(tmp / "recordings", stop_port=stop_port)
        cfg.pop("simulation")  # a rig of real devices: the emulators' process
        cfg["devices"] = {"motor_url": f"modbus-tcp://{host}:{port}", "daq_port": emu.addresses.daq,
                          "crank_radius_m": 0.001}
        d = Daemon(tmp, workers=0, config=cfg)
        try:
            yield Rig(emu, d.start(), stop_port)
        finally:
            if d.proc is not None and d.proc.poll() is None:
                d.stop()


def _children(pid: int) -> list[int]:
    """The processes whose parent is ``pid`` (by their PPid: a task's ``children`` file loses a child
    whose starting thread has ended)."""
    out: list[int] = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            status = (entry / "status").read_text()
        except OSError:  # ended meanwhile
            continue
        ppid = next((line.split()[1] for line in status.splitlines() if line.startswith("PPid:")), None)
        if ppid == str(pid):
            out.append(int(entry.name))
    return out


def _rig_process(d: Daemon) -> int:
    assert d.proc is not None
    found = [p for p in _children(d.proc.pid)
             if b"station.rigproc" in Path(f"/proc/{p}/cmdline").read_bytes()]
    assert len(found) == 1, found
    return found[0]


def _stream_process(rig: int) -> int:
    """The stream process: the rig process's one child (the DAQ stream into the recording)."""
    found = [p for p in _children(rig) if b"station.rigproc.streamproc" in Path(f"/proc/{p}/cmdline").read_bytes()]
    assert len(found) == 1, found
    return found[0]


def _wait(predicate: object, timeout_s: float, what: str, d: Daemon | None = None) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():  # type: ignore[operator]
            return
        time.sleep(0.05)
    raise AssertionError(f"not within {timeout_s} s: {what}" + (f"\n{d.log()}" if d is not None else ""))


def _answers(url: str) -> bool:
    """``GET url`` answers 200 (False while nothing listens there yet)."""
    try:
        return httpx.get(url, timeout=5.0).status_code == 200
    except httpx.TransportError:
        return False


def _estop(c: httpx.Client) -> dict[str, Any]:
    """The daemon's latch as /health shows it (empty while /health does not answer so)."""
    try:
        h = c.get("/health").json()
    except httpx.TransportError:  # a kept-alive connection the daemon closed after its header time-out
        return {}
    return dict(h.get("estop") or {})


def test_with_the_web_process_stopped_the_stop_port_stops_the_crank_and_reads_it_back(rig: Rig) -> None:
    emu, d, stop_port = rig.emu, rig.d, rig.stop_port
    rid = d.start_run(freqs=(10.0,), record_s=60.0)
    d.wait_state(rid, ("running",), step_state="recording")
    assert emu.status()["speed_hz"] == pytest.approx(10.0)
    # one keeper refreshes the drive (the rig process's, every 0.2 s), not the web process's too
    n0, t0 = emu.status()["watchdog_refreshes"], time.monotonic()
    time.sleep(2.0)
    n1, t1 = emu.status()["watchdog_refreshes"], time.monotonic()
    assert 3 <= n1 - n0 <= (t1 - t0) / 0.2 + 3, (n1 - n0, t1 - t0)
    assert d.proc is not None
    os.kill(d.proc.pid, signal.SIGSTOP)
    try:
        with pytest.raises(httpx.TimeoutException):  # the web process answers nothing now
            httpx.get(f"{d.url}/health", timeout=1.0)
        t0 = time.monotonic()
        r = httpx.post(f"http://127.0.0.1:{stop_port}/stop", timeout=10.0)
        arrived = emu.wait_command("emergency_stop", t0)
        assert r.status_code == 200, r.text
        body = r.json()
        assert body["stop_commanded"] and body["motor_stopped"], body
        assert body["drive"]["standstill"] is True and body["drive"]["speed_hz"] == 0.0
        assert arrived is not None  # the drive took the emergency stop, not a lost link's ramp
        assert emu.status()["speed_hz"] == 0.0
        st = httpx.get(f"http://127.0.0.1:{stop_port}/stop", timeout=5.0).json()
        assert st["estop"]["latched"] and st["drive"]["standstill"] is True
    finally:
        os.kill(d.proc.pid, signal.SIGCONT)
    # the web process runs again: the run is aborted, the stop latched and recorded
    assert d.wait_state(rid)["state"] == "aborted"
    c = d.c()
    _wait(lambda: _estop(c).get("latched"), 10.0, "the daemon latches the stop")
    assert c.post("/runs", json={"transducer_id": "TX5K-0001", "top_mass_kg": 25.717, "steps": [
        {"crank_frequency_hz": 10.0, "crank_radius_m": 0.001}]}).status_code == 409
    assert c.post("/stop/acknowledge", json={"operator": "op"}).status_code == 200
    # an abort from the web process reaches the run carried out in the rig process: it ramps the
    # crank down and reads the drive back at standstill
    rid = d.start_run(freqs=(10.0,), record_s=60.0)
    d.wait_state(rid, ("running",), step_state="recording")
    t0 = time.monotonic()
    assert c.post(f"/runs/{rid}/abort").status_code == 202
    st = d.wait_state(rid)
    assert st["state"] == "aborted" and "aborted by" in st["reason"], st
    assert emu.status()["speed_hz"] == 0.0 and emu.wait_command("emergency_stop", t0, timeout_s=0.0) is None
    drive = c.get("/health").json()["drive"]
    assert drive["standstill"] is True and str(rid) in drive["after"], drive
    # a web process that hangs (stopped for longer than the rig process's 3 s link time-out) during
    # a run: the run goes on in the rig process to its end, every step recorded, nothing latched
    rid = d.start_run(freqs=(10.0, 20.0), record_s=2.5)
    d.wait_state(rid, ("running",), step_state="recording")
    t0 = time.monotonic()
    os.kill(d.proc.pid, signal.SIGSTOP)
    try:
        time.sleep(4.0)
        assert emu.status()["speed_hz"] > 0.0  # the crank still turns for the run
    finally:
        os.kill(d.proc.pid, signal.SIGCONT)
    st = d.wait_state(rid, ("identifying", "completed", "failed", "aborted", "interrupted"))
    assert st["state"] in ("identifying", "completed"), (st, d.log())
    assert st["current_step"] == 1 and st["step_state"] == "done" and st["lost_samples"] == 0, st
    with h5py.File(d.data_dir / f"{rid}.h5", "r") as f:
        assert f.attrs["exit_status"] == "completed", dict(f.attrs)
        assert len(f["steps/crank_frequency_hz"]) == 2
    assert emu.status()["speed_hz"] == 0.0 and emu.status()["fault_code"] == 0
    assert emu.wait_command("emergency_stop", t0, timeout_s=0.0) is None
    assert not _estop(c).get("latched")


def test_a_killed_rig_process_leaves_the_crank_to_the_drives_watchdog_and_a_new_one_serves(rig: Rig) -> None:
    emu, d, stop_port = rig.emu, rig.d, rig.stop_port
    c = d.c()
    rid = d.start_run(freqs=(10.0,), record_s=60.0)
    d.wait_state(rid, ("running",), step_state="recording")
    assert emu.status()["speed_hz"] == pytest.approx(10.0)
    old = _rig_process(d)
    stream = _stream_process(old)
    os.kill(old, signal.SIGKILL)
    # nobody refreshes the drive's watchdog now: the drive stops the crank on its own
    _wait(lambda: emu.status()["speed_hz"] == 0.0, 10.0, "the drive's watchdog stops the crank")
    assert emu.status()["fault_code"] != 0
    assert d.wait_state(rid)["state"] == "failed"
    # the stream process saw its lifeline close: it closed the recording as interrupted and ended
    _wait(lambda: not Path(f"/proc/{stream}").exists(), 10.0, "the stream process ends")
    with h5py.File(d.data_dir / f"{rid}.h5", "r") as f:
        assert f.attrs["exit_status"] == "interrupted", dict(f.attrs)
        assert f.attrs["reason"] in ("the rig process ended during the run",  # its lifeline or its socket first
                                     "the rig process closed the stream's channel during the run")
        assert f["raw/displacement"].shape[0] > 0
    _wait(lambda: _rig_process(d) != old, 60.0, "a new rig process")
    assert "the rig process ended" in d.log()
    _wait(lambda: _answers(f"http://127.0.0.1:{stop_port}/stop"), 30.0,
          "the new rig process's stop port")  # it listens once it has read the drive back
    # the drive's fault is never cleared behind the operator's back: it is still there; the operator's
    # acknowledgement resets it once the web process is connected again through the new rig process (a
    # moment after its stop port listens; until then the acknowledgement is refused, 409: nothing reset)
    assert emu.status()["fault_code"] != 0
    _wait(lambda: c.post("/stop/acknowledge", json={"operator": "op"}).status_code == 200, 30.0,
          "the acknowledgement is taken once the web process is connected again", d)
    assert emu.status()["fault_code"] == 0
    # a later run works; its DAQ stream runs under the new rig process: the web process stopped
    # for 2.3 s while it records (beyond the 2 s a silent stream fails a run: the stream in the web
    # process failed it, "DAQ stream stalled") loses neither the run nor a sample
    rid = d.start_run(freqs=(10.0,), record_s=3.0)
    d.wait_state(rid, ("running",), step_state="recording")
    assert d.proc is not None
    os.kill(d.proc.pid, signal.SIGSTOP)
    try:
        time.sleep(2.3)
    finally:
        os.kill(d.proc.pid, signal.SIGCONT)
    st = d.wait_state(rid, ("identifying", "completed", "failed", "aborted"))
    assert st["state"] in ("identifying", "completed"), d.log()
    assert st["lost_samples"] == 0, st
    # the stream process killed during a run: the run fails as for a lost DAQ link (its procedure
    # stops the crank), the recording stays as flushed; the next run gets a new stream process
    rid = d.start_run(freqs=(10.0,), record_s=60.0)
    d.wait_state(rid, ("running",), step_state="recording")
    rig_pid = _rig_process(d)
    os.kill(_stream_process(rig_pid), signal.SIGKILL)
    st = d.wait_state(rid)
    assert st["state"] == "failed" and "the stream process ended" in st["reason"], st
    _wait(lambda: emu.status()["speed_hz"] == 0.0, 10.0, "the run's procedure stops the crank")
    assert (d.data_dir / f"{rid}.h5.partial").exists()  # as flushed: recovered at a restart
    assert c.post("/stop/acknowledge", json={"operator": "op"}).status_code == 200
    rid = d.start_run(freqs=(10.0,), record_s=0.3)
    assert d.wait_state(rid, ("identifying", "completed", "failed", "aborted"))["state"] in (
        "identifying", "completed"), d.log()
    assert _rig_process(d) == rig_pid and _stream_process(rig_pid)  # the same rig process, a new stream process


def test_real_daemon_stop_with_the_database_locked_and_a_drive_that_ignores_it(rig: Rig) -> None:
    """The stop of ``tests/test_stop_isolation.py`` on the real daemon: the motor's real state is the
    emulators' process's: the stop command's arrival is read from its log, the crank's speed from the
    emulators themselves."""
    emu, d = rig.emu, rig.d
    c = d.c()
    # another process holds the database's write lock while a run records
    rid = d.start_run(freqs=(10.0,), record_s=60.0)
    d.wait_state(rid, ("running",), step_state="recording")
    lock = WriteLock(d.data_dir / "station.db")
    try:
        t0 = time.monotonic()
        r = c.post("/stop")
        assert time.monotonic() - t0 < NOT_THE_BUSY_TIMEOUT_S
        arrived = emu.wait_command("emergency_stop", t0)
        assert arrived is not None and arrived - t0 < NOT_THE_BUSY_TIMEOUT_S
        assert r.status_code == 200 and r.json()["motor_stopped"], r.text
        assert emu.status()["speed_hz"] == 0.0
    finally:
        lock.release()
    assert d.wait_state(rid)["state"] == "aborted"
    assert c.post("/stop/acknowledge", json={"operator": "op"}).status_code == 200
    # a drive that takes the stop and keeps turning
    rid = d.start_run(freqs=(10.0,), record_s=60.0)
    d.wait_state(rid, ("running",), step_state="recording")
    emu.ignore_stops()
    try:
        body = c.post("/stop").json()
        assert body["stop_commanded"] and not body["motor_stopped"], body
        assert body["drive"]["speed_hz"] == pytest.approx(10.0) and emu.status()["speed_hz"] == pytest.approx(10.0)
        h = c.get("/health").json()
        assert h["status"] == "degraded" and h["drive"]["standstill"] is False and h["estop"]["source"] == "drive"
        assert c.post("/runs", json=run_body(freqs=(10.0,), radius=0.001)).status_code == 409
        assert c.post("/stop/acknowledge", json={"operator": "op"}).status_code == 409
    finally:
        emu.ignore_stops(False)  # repaired: the crank comes to rest (and the module's later tests run)
    assert c.post("/stop/acknowledge", json={"operator": "op"}).status_code == 200
    assert c.get("/health").json()["drive"]["standstill"] is True


def test_the_crank_radius_changes_on_the_emulators_control_socket_at_standstill(rig: Rig) -> None:
    """The simulated rig's crank radius, as the rig process changes it under ``--sim``."""
    emu = rig.emu
    assert emu.status()["speed_hz"] == 0.0
    radius = SocketCrankRadius(str(emu.addresses.control), 0.001)
    asyncio.run(radius.set_radius(0.002))
    assert emu.status()["radius_m"] == 0.002 and radius.radius_m == 0.002
