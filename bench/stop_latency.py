"""Emergency-stop latency: from ``POST /stop`` to the drive taking its stop command; prints JSON.

The rig's emulator runs as its own process (``python -m drivers.sim --commands``), so the motor's
real state is the emulator's and every command it takes is printed with that process's
``time.monotonic()`` (one clock for every process on the machine).  The daemon is a real
``station serve`` with the real drivers, talking to the emulator over Modbus TCP and a pty like a
real rig (no ``--sim``).  Latency = time the emulator applied the ``emergency_stop`` register write
minus the time just before the bench sent ``POST /stop``.  Cases, each ``--repeats`` times:

- ``idle``: no run, nothing else going on (the baseline);
- ``run_recording``: a run in its record window (20 kHz to HDF5, progress written to the database);
- ``database_locked``: as ``run_recording``, while another process (this bench) holds the database's
  write lock (``BEGIN IMMEDIATE``) from 2 s before the stop to 1 s after it;
- ``disk_full``: a run recording when the recordings disk (a real tmpfs, so the database too) is
  filled to ENOSPC just before the stop (needs root to mount; otherwise null with the reason);
- ``idle_connections``: ``--connections`` (20 000) idle TCP connections to the daemon on loopback,
  opened just before the stop (no request on any of them).  Also reported: how many the daemon kept
  open (its descriptors) and its log lines about open files.
- ``flood_busy``: a run recording, both cores kept busy (two spinning processes of this bench),
  ``--flood`` (5 000) idle TCP connections opened on the main port, 2 s, then the stop.  Also
  reported: stops lost (not answered 200 or not reaching the drive within 10 s: a second stop then
  ends the run) and runs that failed by themselves during the flood (before the stop).

Each case is measured for each ``--via``: ``main`` sends ``POST /stop`` to the daemon's web port (a
new connection each time), ``stop_port`` to its stop port (``service.stop_port``: a listener of its
own, with its own thread and loop); the flood of ``idle_connections`` is on the web port either way.

After each stop the bench waits for the drive's standstill (the daemon's answer says it), then
acknowledges the stop as an operator would.  Everything is bounded in time; the daemon and the
emulator are ended at the close.  Target: <= 100 ms in every case.

Usage: python bench/stop_latency.py [--repeats 3] [--connections 20000] [--cases idle,idle_connections,...]
       [--via main,stop_port] [--flood 5000] [--daemon-tree OTHER_SOURCE_TREE]
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import json
import os
import socket
import sqlite3
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import yaml

from drivers.sim import SimRigProcess

ROOT = Path(__file__).resolve().parent.parent
TOKEN = "bench-token-0123456789"
TARGET_MS = 100.0
RADIUS_M = 0.01
DEADLINE_S = 900.0  # the whole bench ends by itself within this


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Daemon:
    """``station serve`` (real drivers) on the emulator's Modbus TCP port and DAQ pty."""

    def __init__(self, data_dir: Path, emu: SimRigProcess, tmp: Path, tree: Path | None = None) -> None:
        cfg = yaml.safe_load((ROOT / "config" / "sim-5kN.yaml").read_text())
        cfg.pop("simulation", None)
        host, port = emu.addresses.modbus_tcp
        cfg["devices"] = {"motor_url": f"modbus-tcp://{host}:{port}", "daq_port": emu.addresses.daq,
                          "crank_radius_m": RADIUS_M}
        cfg["station"]["recordings_dir"] = str(data_dir)
        cfg["station"]["min_free_mb"] = 1.0
        cfg["rig"]["acceleration_hz_per_s"] = 50.0
        cfg["plan"]["settle_s"] = 0.2
        self.cfg_path = tmp / "station.yaml"
        self.cfg_path.write_text(yaml.safe_dump(cfg))
        self.log_path = tmp / "daemon.log"
        self.port = _free_port()
        self.stop_port: int | None = None
        if tree is None or "stop_port" in (tree / "station" / "config.py").read_text():  # it has the stop port
            self.stop_port = _free_port()
            cfg.setdefault("service", {})["stop_port"] = self.stop_port
            self.cfg_path.write_text(yaml.safe_dump(cfg))
        env = {**os.environ, "STATION_TOKEN": TOKEN, "PYTHONUNBUFFERED": "1"}
        if tree is not None:  # another version of the station (a baseline), with its shipped YAML package
            env["PYTHONPATH"] = f"{tree}{os.pathsep}{tree / '.dev'}"
        with self.log_path.open("wb") as log:
            self.proc = subprocess.Popen([sys.executable, "-m", "station.cli", "serve", "--config", str(self.cfg_path),
                                          "--port", str(self.port), "--workers", "0"],
                                         stdout=log, stderr=subprocess.STDOUT, env=env, cwd=tmp)
        self.client = httpx.Client(base_url=f"http://127.0.0.1:{self.port}",
                                   headers={"Authorization": f"Bearer {TOKEN}"}, timeout=60.0)
        # the stop goes on a new connection each time, as a page's first press or an API client's would
        self.stop_client = httpx.Client(base_url=f"http://127.0.0.1:{self.port}", timeout=60.0,
                                        limits=httpx.Limits(max_keepalive_connections=0))
        self.stop_port_client = httpx.Client(base_url=f"http://127.0.0.1:{self.stop_port}", timeout=60.0,
                                             limits=httpx.Limits(max_keepalive_connections=0))
        deadline = time.monotonic() + 180.0  # a loaded machine (the flood case keeps both cores busy)
        while True:
            if self.proc.poll() is not None:
                raise RuntimeError(f"the daemon exited: {self.log_path.read_text()[-2000:]}")
            with contextlib.suppress(httpx.TransportError):
                if self.client.get("/health").status_code == 200:
                    break
            if time.monotonic() > deadline:
                raise RuntimeError("the daemon did not answer within 180 s")
            time.sleep(0.2)

    def call(self, method: str, url: str, **kw: Any) -> httpx.Response:
        """A request on the kept-alive client, once more on a new connection if the daemon closed the
        old one meanwhile (the connection cap closes idle connections)."""
        try:
            return self.client.request(method, url, **kw)
        except (httpx.ReadError, httpx.RemoteProtocolError, httpx.WriteError):
            return self.client.request(method, url, **kw)

    def fds(self) -> int:
        return len(os.listdir(f"/proc/{self.proc.pid}/fd"))

    def close(self) -> None:
        self.client.close()
        self.stop_client.close()
        self.stop_port_client.close()
        self.proc.terminate()
        try:
            self.proc.wait(30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


def start_run(d: Daemon, tries: int = 3) -> str:
    """A run in its record window; a run that fails before it (e.g. the motor's watchdog expired on a
    machine too loaded to refresh it in time) is acknowledged and started again, ``tries`` times."""
    for k in range(tries):
        try:
            return _start_run(d)
        except RunFailedEarly as exc:
            print(f"retrying the run: {exc}", file=sys.stderr)
            wait_rig_free(d)
            acknowledge(d)
            if k == tries - 1:
                raise
    raise AssertionError("unreachable")


class RunFailedEarly(RuntimeError):
    pass


def _start_run(d: Daemon) -> str:
    body = {"transducer_id": "TX5K-0001", "top_mass_kg": 25.717,
            "steps": [{"crank_frequency_hz": 10.0, "crank_radius_m": RADIUS_M, "record_s": 120.0}]}
    r = d.call("POST", "/runs", json=body)
    if r.status_code != 202:
        raise RuntimeError(f"run refused: {r.status_code} {r.text}")
    rid = str(r.json()["id"])
    deadline = time.monotonic() + 60.0
    while time.monotonic() < deadline:
        st = d.call("GET", f"/runs/{rid}").json()
        if st["state"] == "running" and st["step_state"] == "recording":
            return rid
        if st["state"] not in ("queued", "running"):
            raise RunFailedEarly(f"run ended before recording: {st['state']}: {st['message']}")
        time.sleep(0.1)
    raise RuntimeError("the run did not reach its record window in 60 s")


def acknowledge(d: Daemon) -> None:
    deadline = time.monotonic() + 60.0
    while time.monotonic() < deadline:
        r = d.call("POST", "/stop/acknowledge", json={"operator": "bench"})
        if r.status_code == 200:
            return
        time.sleep(0.3)
    raise RuntimeError(f"the stop could not be acknowledged: {r.status_code} {r.text}")


def wait_rig_free(d: Daemon, timeout_s: float = 60.0) -> bool:
    """Whether the rig is free of runs within ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while d.call("GET", "/health").json()["active_run"]:
        if time.monotonic() > deadline:
            return False
        time.sleep(0.1)
    return True


@contextlib.contextmanager
def db_write_lock(path: Path, hold_before_s: float) -> Iterator[None]:
    db = sqlite3.connect(path, isolation_level=None, timeout=30.0)
    db.execute("BEGIN IMMEDIATE")
    db.execute("CREATE TABLE IF NOT EXISTS bench_lock (x)")
    time.sleep(hold_before_s)
    try:
        yield
        time.sleep(1.0)
    finally:
        db.execute("ROLLBACK")
        db.close()


def fill(path: Path) -> int:
    n = 0
    with path.open("wb", buffering=0) as f:
        block = b"\0" * (1 << 20)
        while True:
            try:
                n += f.write(block)
            except OSError as exc:
                if exc.errno != errno.ENOSPC:
                    raise
                return n


PER_HELPER = 5000  # connections per helper process (a process's open-files limit may be 20 000)
_HELPER = """
import contextlib, socket, sys, time
port, n, limit_s = int(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3])
socks = []
deadline = time.monotonic() + limit_s
for _ in range(n):
    if time.monotonic() > deadline:
        break
    s = socket.socket()
    s.setblocking(False)
    s.connect_ex(("127.0.0.1", port))
    socks.append(s)
time.sleep(1.0)
ok = 0
for s in socks:
    with contextlib.suppress(OSError):
        s.getpeername()
        ok += s.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR) == 0
print(len(socks), ok, flush=True)
sys.stdin.read()
"""


@contextlib.contextmanager
def idle_connections(port: int, n: int, limit_s: float = 60.0) -> Iterator[tuple[int, int]]:
    """``n`` TCP connections to the daemon that send nothing, held by helper processes (bounded by
    ``limit_s`` each; ended at the close).  Yields (opened, established)."""
    helpers = []
    try:
        for k in range(0, n, PER_HELPER):
            helpers.append(subprocess.Popen([sys.executable, "-c", _HELPER, str(port), str(min(PER_HELPER, n - k)),
                                             str(limit_s)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True))
        opened = est = 0
        for h in helpers:
            assert h.stdout is not None
            a, b = (int(x) for x in h.stdout.readline().split())
            opened, est = opened + a, est + b
        yield opened, est
    finally:
        for h in helpers:
            with contextlib.suppress(OSError):
                assert h.stdin is not None
                h.stdin.close()
        for h in helpers:
            try:
                h.wait(10)
            except subprocess.TimeoutExpired:
                h.kill()


def one_stop(d: Daemon, emu: SimRigProcess, via: str, wait_s: float = 60.0) -> dict[str, Any]:
    client = d.stop_port_client if via == "stop_port" else d.stop_client
    t0 = time.monotonic()
    try:
        r = client.post("/stop")
        status, body = r.status_code, r.json()
    except (httpx.HTTPError, ValueError) as exc:
        status, body = None, {"error": f"{type(exc).__name__}: {exc}"}
    http_ms = (time.monotonic() - t0) * 1e3
    t_cmd = emu.wait_command("emergency_stop", t0, wait_s)
    return {"latency_ms": None if t_cmd is None else (t_cmd - t0) * 1e3, "http_ms": http_ms,
            "status": status, "motor_stopped": body.get("motor_stopped"), "error": body.get("error")}


def measure(name: str, d: Daemon, emu: SimRigProcess, repeats: int,
            around: Callable[[], contextlib.AbstractContextManager[dict[str, Any]]], with_run: bool,
            via: str) -> dict[str, Any]:
    samples = []
    extra: dict[str, Any] = {}
    for _ in range(repeats):
        if with_run:
            start_run(d)
        with around() as info:
            s = one_stop(d, emu, via)
        extra.update(info)
        samples.append(s)
        wait_rig_free(d)
        acknowledge(d)
    lat = [s["latency_ms"] for s in samples if s["latency_ms"] is not None]
    return {"case": name, "via": via, "repeats": repeats, "stops_reaching_the_drive": len(lat),
            "latency_ms_median": round(statistics.median(lat), 2) if lat else None,
            "latency_ms_max": round(max(lat), 2) if lat else None,
            "latency_ms_each": [round(x, 2) for x in lat],
            "http_answer_ms_median": round(statistics.median(s["http_ms"] for s in samples), 1),
            "motor_stopped": [s["motor_stopped"] for s in samples],
            "errors": [s["error"] for s in samples if s["error"]],
            "met": bool(lat) and len(lat) == repeats and max(lat) <= TARGET_MS, **extra}


def nice_of(pid: int) -> str:
    """The nice values of the threads of process ``pid``, in words."""
    nices = sorted({os.getpriority(os.PRIO_PROCESS, int(t)) for t in os.listdir(f"/proc/{pid}/task")})
    return "nice " + ", ".join(str(n) for n in nices)


def renice(pid: int, nice: int) -> str:
    """Every thread of process ``pid`` at ``nice``; what was done, in words."""
    tids = [int(t) for t in os.listdir(f"/proc/{pid}/task")]
    try:
        for tid in tids:
            os.setpriority(os.PRIO_PROCESS, tid, nice)
    except OSError as exc:
        return f"not changed: {exc.strerror}"
    return f"nice {nice} ({len(tids)} threads)"


@contextlib.contextmanager
def cores_busy(n: int = 2) -> Iterator[None]:
    """``n`` processes spinning on the CPU (ended at the close)."""
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]
    try:
        yield
    finally:
        for h in hogs:
            h.kill()
            h.wait()


def flood_busy(d: Daemon, emu: SimRigProcess, repeats: int, flood: int, via: str,
               drive_nice: int | None = None, hogs: int = 2) -> dict[str, Any]:
    """The stop during a run, with ``hogs`` processes spinning (2: both cores busy) and ``flood`` idle
    connections on the main port (``drive_nice``: the emulator's threads at this nice value once the
    run records)."""
    samples, failed_runs, not_ended = [], [], []
    assert emu._proc is not None  # the emulator's process (a bench may look inside)
    reniced = f"{nice_of(emu._proc.pid)} (its own: python -m drivers.sim)"
    for _ in range(repeats):
        rid = start_run(d)
        if drive_nice is not None:
            proc = emu._proc  # the emulator's process (a bench may look inside)
            assert proc is not None
            reniced = renice(proc.pid, drive_nice)
        with cores_busy(hogs), idle_connections(d.port, flood) as (opened, est):
            time.sleep(2.0)  # the flood held during the record window: does the run survive it?
            s = one_stop(d, emu, via, wait_s=10.0)
        s.update(opened=opened, established=est)
        samples.append(s)
        if s["status"] != 200 or s["latency_ms"] is None:  # lost: end the run all the same
            one_stop(d, emu, "stop_port" if d.stop_port else "main")
        if not wait_rig_free(d, 30.0):  # a stop that reached the drive but did not end the run
            not_ended.append(rid)
            one_stop(d, emu, "stop_port" if d.stop_port else "main")
            wait_rig_free(d, 150.0)  # the record window (120 s) ends it at the latest
        st = d.call("GET", f"/runs/{rid}").json()  # aborted by the stop, or failed before it on its own
        if st["state"] != "aborted":
            failed_runs.append(f"{st['state']}: {st['message']}")
        acknowledge(d)
    lat = [s["latency_ms"] for s in samples if s["latency_ms"] is not None]
    lost = sum(1 for s in samples if s["status"] != 200 or s["latency_ms"] is None)
    return {"case": "flood_busy", "via": via, "repeats": repeats, "flood_connections": flood,
            "drive_emulator": reniced, "spinning_processes": hogs,
            "stops_lost": lost, "runs_failed_by_the_flood": len(failed_runs), "run_failures": failed_runs[:5],
            "runs_not_ended_30_s_after_the_stop": not_ended,
            "latency_ms_median": round(statistics.median(lat), 2) if lat else None,
            "latency_ms_max": round(max(lat), 2) if lat else None,
            "latency_ms_each": [round(x, 1) for x in lat],
            "http_answer_ms_median": round(statistics.median(s["http_ms"] for s in samples), 1),
            "statuses": [s["status"] for s in samples], "errors": [s["error"] for s in samples if s["error"]][:5],
            "load_average": os.getloadavg()[0],
            "met": lost == 0 and not failed_runs and not not_ended and bool(lat) and max(lat) <= (
                TARGET_MS if via == "stop_port" else 1000.0)}


@contextlib.contextmanager
def nothing() -> Iterator[dict[str, Any]]:
    yield {}


def mount_tmpfs(path: Path, size_mib: int) -> str | None:
    path.mkdir(parents=True, exist_ok=True)
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_mib}m", "tmpfs", str(path)],
                       capture_output=True, text=True)
    return None if r.returncode == 0 else (r.stderr.strip() or f"mount exited {r.returncode}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--connections", type=int, default=20_000)
    ap.add_argument("--drive-nice", type=int, default=None,
                    help="run the emulator's threads at this nice value (a real drive's timing does not share the "
                    "station's CPU; needs the right to lower it)")
    ap.add_argument("--flood", type=int, default=5_000, help="idle connections of the flood_busy case")
    ap.add_argument("--hogs", type=int, default=2,
                    help="processes spinning during the flood_busy case (2: both cores of the station PC busy)")
    ap.add_argument("--cases", default="idle,run_recording,database_locked,idle_connections,disk_full",
                    help="comma-separated cases to run (default: all)")
    ap.add_argument("--via", default="main,stop_port",
                    help="where the stop is sent: main (the web port), stop_port (its own listener), or both")
    ap.add_argument("--keep-log", type=Path, default=None, help="copy the daemon's log here at the end")
    ap.add_argument("--daemon-tree", type=Path, default=None,
                    help="run the daemon from this source tree (e.g. an older version as the baseline)")
    args = ap.parse_args()
    started = time.monotonic()
    out: dict[str, Any] = {"target_ms": TARGET_MS, "cases": []}
    with tempfile.TemporaryDirectory(prefix="stop-bench-") as tmp_s:
        tmp = Path(tmp_s)
        disk = tmp / "disk"
        why_no_tmpfs = mount_tmpfs(disk, 96)
        d: Daemon | None = None
        with contextlib.ExitStack() as stack:
            emu = stack.enter_context(SimRigProcess(crank_radius_m=RADIUS_M, commands=True))
            if why_no_tmpfs is None:
                stack.callback(subprocess.run, ["umount", "-l", str(disk)], check=False)
            d = Daemon(disk, emu, tmp, args.daemon_tree)
            stack.callback(d.close)
            if args.keep_log is not None:  # also when the bench fails
                stack.callback(lambda: args.keep_log.write_bytes(d.log_path.read_bytes()) if d else None)
            db_path = disk / "station.db"

            @contextlib.contextmanager
            def locked() -> Iterator[dict[str, Any]]:
                with db_write_lock(db_path, 2.0):
                    yield {"lock": "BEGIN IMMEDIATE held by another process 2 s before to 1 s after the stop"}

            @contextlib.contextmanager
            def full() -> Iterator[dict[str, Any]]:
                filler = disk / "filler.bin"
                try:
                    n = fill(filler)
                    st = os.statvfs(disk)
                    yield {"filled_bytes": n, "free_bytes_at_stop": st.f_bavail * st.f_frsize}
                finally:
                    filler.unlink(missing_ok=True)

            @contextlib.contextmanager
            def connections() -> Iterator[dict[str, Any]]:
                assert d is not None
                t = time.monotonic()
                with idle_connections(d.port, args.connections) as (opened, est):
                    time.sleep(1.0)  # let the daemon take them
                    yield {"connections_opened": opened, "connections_established": est,
                           "open_s": round(time.monotonic() - t, 2), "daemon_fds_before_stop": d.fds()}

            cases: list[tuple[str, Callable[[], contextlib.AbstractContextManager[dict[str, Any]]], bool]] = [
                ("idle", nothing, False), ("run_recording", nothing, True), ("database_locked", locked, True),
                ("idle_connections", connections, False)]
            if why_no_tmpfs is None:
                cases.append(("disk_full", full, True))
            wanted = set(args.cases.split(","))
            for name, around, with_run in cases:
                if name not in wanted:
                    continue
                if time.monotonic() - started > DEADLINE_S:
                    out["cases"].append({"case": name, "skipped": "the bench's time limit"})
                    continue
                for via in args.via.split(","):
                    if via == "stop_port" and d.stop_port is None:
                        out["cases"].append({"case": name, "via": via, "skipped": "this daemon has no stop port"})
                        continue
                    out["cases"].append(measure(name, d, emu, args.repeats, around, with_run, via))
            if "flood_busy" in wanted:
                for via in args.via.split(","):
                    if via == "stop_port" and d.stop_port is None:
                        continue
                    out["cases"].append(flood_busy(d, emu, args.repeats, args.flood, via, args.drive_nice, args.hogs))
            if why_no_tmpfs is not None and "disk_full" in wanted:
                out["cases"].append({"case": "disk_full", "skipped": f"no tmpfs could be mounted: {why_no_tmpfs}"})
            text = d.log_path.read_text(errors="replace")
            out["daemon_log"] = {"lines": text.count("\n"), "too_many_open_files": text.count("Too many open files"),
                                 "bytes": len(text)}
    out["all_met"] = all(c.get("met") for c in out["cases"] if "skipped" not in c)
    out["wall_s"] = round(time.monotonic() - started, 1)
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
