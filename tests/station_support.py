"""The daemon two ways, for the API tests.

- :func:`app_in_process`: ``create_app`` in this process through httpx's ASGI transport, with the
  real rig thread, SQLite and HDF5, the simulated rig's in-process backends on a virtual clock (a
  run's seconds take milliseconds), and a store that :func:`seed_runs` may have filled with
  finished simulated recordings (identified, as the worker would have left them).  Everything that
  does not need a real process, socket or signal runs here.
- :class:`Daemon`: a real ``station serve --sim`` process on a free loopback port (Modbus TCP and a
  pty to the emulators, real time), for kills, signals, the browser and generated HTTP clients.

Both use the same short configuration (:func:`daemon_config`: 2-step runs, settle 0.2 s, record
0.5 s, 50 Hz/s ramps) and the same token.
"""

from __future__ import annotations

import asyncio
import contextlib
import copy
import json
import os
import shutil
import signal
import socket
import sqlite3
import subprocess
import sys
import threading
import time
from collections.abc import AsyncIterator, Awaitable, Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import httpx
import uvicorn
import yaml

from station.commands.connections import ConnectionBounds
from station.config import StationConfig, parse_config
from station.lab.store import RunRow, Store
from tests.conftest import fast_dict

if TYPE_CHECKING:
    from station.service.manager import RunManager

TOKEN = "test-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
T = TypeVar("T")
# The tests' users: name -> password and role (made with the admin token, then logged in as each).
PASSWORDS = {"tina": "tina-secret-pw", "anton": "anton-secret-pw", "ada": "ada-secret-pw1"}
ROLES = {"tina": "technician", "anton": "approver", "ada": "admin"}
FINAL = ("completed", "aborted", "failed", "interrupted")
# the cap most API tests put on an in-process rig's virtual clock (x real time; see SpeedLimit)
CAPPED_SPEEDUP = 20.0
# ... and, where a test says so, the cap while no run is on the rig (its idle DAQ still streams: at
# 20 times real time that is 40 % of a core while the test waits on a worker process, at 4 times 8 %)
IDLE_SPEEDUP = 4.0
# both caps, as the in-process apps' keyword arguments (``app_in_process(rec, **CAPPED)``)
CAPPED: dict[str, float] = {"max_speedup": CAPPED_SPEEDUP, "idle_speedup": IDLE_SPEEDUP}
ON_RIG_DONE = (*FINAL, "identifying")


def daemon_config(data_dir: Path, **service: Any) -> dict[str, Any]:
    """The daemon tests' configuration as parsed YAML (recordings and database in ``data_dir``; the
    render worker starts on first use unless ``render_at_start=True``; passwords stored at the
    simulated station's least scrypt cost)."""
    d = fast_dict(steps=((10.0, 0.001), (20.0, 0.001)), acceleration_hz_per_s=50.0, recordings_dir=data_dir,
                  service={"render_at_start": False, **service})
    # the simulated station's least password cost (2**10, not 2**14: some 3 ms a hash or check, not
    # 70 ms); the tests make and log in users often, what a cost changes is tested in test_service.py
    d["simulation"]["password_cost_log2"] = 10
    return d


def run_body(freqs: tuple[float, ...] = (10.0, 20.0), radius: float = 0.001, **step: Any) -> dict[str, Any]:
    return {"transducer_id": "TX5K-0001", "top_mass_kg": 25.717,
            "steps": [{"crank_frequency_hz": f, "crank_radius_m": radius, **step} for f in freqs]}


# ---------------------------------------------------------------------------------------- seeded runs
@dataclass(frozen=True)
class Seed:
    """A finished run to put in a store: its steps (Hz, m), top mass (kg), record time (s), seed;
    ``identified=False``: acquired, its identification job queued (as the rig side leaves it)."""

    freqs: Sequence[float] = (10.0, 20.0)
    radius_m: float = 0.001
    top_mass_kg: float = 25.717
    record_s: float = 0.5
    seed: int = 1
    identified: bool = True


def seed_runs(config: dict[str, Any], seeds: Sequence[Seed]) -> list[str]:
    """Simulate, process and identify each run (as the daemon's worker would) into the configured
    recordings folder and store it as ``completed`` in the daemon's database (or as ``identifying``
    with its job queued, see :class:`Seed`); returns the run ids.

    ``config``: the daemon's configuration as parsed YAML.  The recordings are simulated from the
    physics (``station.simulate``), not by the code under test."""
    from station.lab import audit
    from station.lab.integrity import sha256_file
    from station.run.calibrate import process_and_identify
    from station.run.request import RunRequest, plan_run
    from station.service.settings import build_settings
    from station.simulate import simulate_run

    cfg = parse_config(config)
    settings = build_settings(cfg, sim=True, workers=0, env={"STATION_TOKEN": TOKEN})
    store = Store(settings.database)
    ids = []
    try:
        for s in seeds:
            body = run_body(tuple(s.freqs), s.radius_m, record_s=s.record_s)
            body["top_mass_kg"] = s.top_mass_kg
            request = RunRequest.model_validate(body)
            plan = plan_run(cfg, request)
            run = copy.deepcopy(config)
            run["plan"].update(record_s=s.record_s, steps=[
                {"crank_frequency_hz": f, "crank_radius_m": s.radius_m} for f in s.freqs])
            run["rig"]["top_mass_kg"] = s.top_mass_kg
            path = simulate_run(parse_config(run), settings.recordings_dir, seed=s.seed)
            result_name = process_and_identify(path).result_name if s.identified else None
            now = time.time()
            store.insert_run(RunRow(
                id=path.stem, state="completed" if s.identified else "identifying",
                transducer_id=request.transducer_id,
                top_mass_kg=request.top_mass_kg, request_json=request.model_dump_json(),
                plan_json=json.dumps(plan.to_dict()), created=now, n_steps=len(plan.steps), started=now,
                ended=now, step=len(plan.steps) - 1, step_state="done", fraction=1.0,
                samples=int(sum(st.record_s for st in plan.steps) * cfg.daq.sample_rate_hz),
                message="identified (seeded)" if s.identified else "acquisition completed; identification queued",
                recording=path.name, result_name=result_name, recording_sha256=sha256_file(path)))
            if not s.identified:
                store.enqueue_job(path.stem)
            # the audit chain vouches for the recording and its results, as the daemon's would
            audit.append(store, audit.SYSTEM, audit.RUN_ENDED, path.stem, {"recording": path.name},
                         files={path.name: sha256_file(path)})
            if s.identified:
                audit.seal_results(store, audit.SYSTEM, audit.RUN_IDENTIFIED, path.stem, path, {"seeded": True})
            ids.append(path.stem)
    finally:
        store.close()
    return ids


# ---------------------------------------------------------------------------------------- in process
class SpeedLimit:
    """Keeps a virtual clock at most ``speedup`` times faster than real time: a participant that
    wakes every ``step_s`` of virtual time and, awake (time stands still while a participant is),
    lets ``step_s / speedup`` of real time pass since its last wake before it waits again.

    An in-process rig streams its DAQ through the clock even when idle, as fast as a core allows
    (about 100 times real time), while a test waits on something else (a worker process, another
    test of a module that holds the app); limited, it leaves that core to the work waited on.  A run
    still takes its seconds of virtual time in a small part of them in real time."""

    def __init__(self, clock: Any, speedup: float, step_s: float = 0.1, *,
                 idle: tuple[Callable[[], bool], float] | None = None) -> None:
        """``idle``: (is the rig idle?, the cap then): a lower cap while nothing waits on the rig."""
        self.clock = clock
        self._idle = idle
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(speedup, step_s), daemon=True,
                                        name="virtual-clock-speed-limit")
        self._thread.start()

    def _run(self, speedup: float, step_s: float) -> None:
        last = time.monotonic()
        while not self._stop.is_set():
            self.clock.wait_for(self._stop.is_set, step_s)
            idle = self._idle is not None and self._idle[0]()
            hold_s = step_s / (self._idle[1] if idle and self._idle is not None else speedup)
            left = hold_s - (time.monotonic() - last)
            if left > 0 and not self._stop.is_set():
                time.sleep(left)  # awake: the clock waits
            last = time.monotonic()

    def close(self) -> None:
        self._stop.set()
        self.clock.notify()
        self._thread.join(5.0)


@contextlib.asynccontextmanager
async def running_app(rec_dir: Path, *, config: dict[str, Any] | None = None, workers: int = 0,
                      render: bool = False, min_free_mb: float | None = None, max_speedup: float | None = None,
                      idle_speedup: float | None = None, **service: Any) -> AsyncIterator[Any]:
    """The daemon's FastAPI app, started (its lifespan entered) in this process on the simulated rig
    (virtual clock, no wire).  ``config``: as parsed YAML (default :func:`daemon_config` with
    ``service``); ``workers``: identification processes (0: runs stop at ``identifying``);
    ``render``: start the render worker at once (plots, report, discrepancy); ``min_free_mb``: the
    recordings disk's reserve; ``max_speedup``: the virtual clock at most this many times faster
    than real time (:class:`SpeedLimit`; None: as fast as it goes); ``idle_speedup``: with
    ``max_speedup``, the cap while no run is queued or on the rig (e.g. :data:`IDLE_SPEEDUP`)."""
    from drivers.sim.clock import VirtualClock
    from station.api import create_app
    from station.run.rig import connect
    from station.service.manager import RunManager
    from station.service.settings import ServiceSettings, build_settings

    managers: list[RunManager] = []

    def idle() -> bool:
        return bool(managers) and not managers[0].runs.live

    @contextlib.asynccontextmanager
    async def virtual_rig(cfg: StationConfig, sim: bool) -> AsyncIterator[Any]:
        clock = VirtualClock()
        limit = None if max_speedup is None else SpeedLimit(
            clock, max_speedup, idle=None if idle_speedup is None else (idle, idle_speedup))
        try:
            async with connect(cfg, sim=sim, sim_clock=clock) as rig:
                yield rig
        finally:
            if limit is not None:
                limit.close()

    class Manager(RunManager):
        def __init__(self, settings: ServiceSettings) -> None:
            super().__init__(settings, connector=virtual_rig)
            managers.append(self)

    d = config if config is not None else daemon_config(rec_dir, **service)
    d.setdefault("service", {})["render_at_start"] = render
    if min_free_mb is not None:
        d["station"]["min_free_mb"] = min_free_mb
    settings = build_settings(parse_config(d), sim=True, workers=workers, env={"STATION_TOKEN": TOKEN})
    app = create_app(settings, manager_factory=Manager)
    async with app.router.lifespan_context(app):
        yield app


def asgi_client(app: Any, *, token: bool = True, client: str = "127.0.0.1") -> httpx.AsyncClient:
    """A client of the app in this process (with the token unless ``token=False``), calling from ``client``."""
    t = httpx.ASGITransport(app=app, client=(client, 40000))
    return httpx.AsyncClient(transport=t, base_url="http://127.0.0.1", headers=AUTH if token else None, timeout=60)


async def login(app: Any, name: str) -> httpx.AsyncClient:
    """A client of the app in this process logged in as user ``name`` (made beforehand with its
    :data:`PASSWORDS` entry), by its session cookie, not the token; the cookie is HttpOnly, SameSite=Strict."""
    c = asgi_client(app, token=False)
    r = await c.post("/login", json={"name": name, "password": PASSWORDS[name]})
    assert r.status_code == 200, r.text
    assert "httponly" in r.headers["set-cookie"].lower() and "samesite=strict" in r.headers["set-cookie"].lower()
    return c


def estops(m: RunManager) -> list[dict[str, Any]]:
    """The emergency stops in the database, once the daemon's writer has taken what it queued."""
    assert m.db.flush(5.0), m.db.last_error
    db = sqlite3.connect(m.settings.database)
    db.row_factory = sqlite3.Row
    try:
        return [dict(r) for r in db.execute("SELECT * FROM estops ORDER BY id")]
    finally:
        db.close()


@contextlib.asynccontextmanager
async def app_in_process(rec_dir: Path, *, token: bool = True, client: str = "127.0.0.1",
                         **kw: Any) -> AsyncIterator[tuple[Any, httpx.AsyncClient]]:
    """:func:`running_app` (``kw``) and a client of it; yields (the run manager, the client)."""
    async with running_app(rec_dir, **kw) as app, asgi_client(app, token=token, client=client) as c:
        yield app.state.manager, c


class HeldApp:
    """:func:`running_app` held open across tests (a module fixture): ``call(fn)`` awaits
    ``fn(client)`` on the app's own loop (``anon=True``: a client without the token); ``close()``."""

    def __init__(self, rec_dir: Path, **kw: Any) -> None:
        self.loop = asyncio.new_event_loop()
        self._cm = running_app(rec_dir, **kw)
        self.app = self.loop.run_until_complete(self._cm.__aenter__())
        self.manager = self.app.state.manager
        self.client, self.anon = asgi_client(self.app), asgi_client(self.app, token=False)

    def call(self, fn: Callable[[httpx.AsyncClient], Awaitable[T]], *, anon: bool = False) -> T:
        return self.loop.run_until_complete(fn(self.anon if anon else self.client))

    def get(self, url: str, *, anon: bool = False, **kw: Any) -> httpx.Response:
        return self.loop.run_until_complete((self.anon if anon else self.client).get(url, **kw))

    def post(self, url: str, *, anon: bool = False, **kw: Any) -> httpx.Response:
        return self.loop.run_until_complete((self.anon if anon else self.client).post(url, **kw))

    def close(self) -> None:
        try:
            for c in (self.client, self.anon):
                self.loop.run_until_complete(c.aclose())
            self.loop.run_until_complete(self._cm.__aexit__(None, None, None))
        finally:
            self.loop.close()


async def wait_state(c: httpx.AsyncClient, rid: str, states: tuple[str, ...] = ON_RIG_DONE,
                     step_state: str | None = None, timeout_s: float = 60.0) -> dict[str, Any]:
    """Poll ``GET /runs/{rid}`` until the run is in one of ``states`` (and ``step_state``)."""
    deadline = time.monotonic() + timeout_s
    st: dict[str, Any] = {}
    while time.monotonic() < deadline:
        st = (await c.get(f"/runs/{rid}")).json()
        if st["state"] in states and (step_state is None or st["step_state"] == step_state):
            return st
        await asyncio.sleep(0.05)
    raise AssertionError(f"run {rid} not in {states} after {timeout_s} s: {st}")


async def start(c: httpx.AsyncClient, **kw: Any) -> str:
    """POST /runs with :func:`run_body` (``kw``); the run's id."""
    r = await c.post("/runs", json=run_body(**kw))
    assert r.status_code == 202, r.text
    return str(r.json()["id"])


# ---------------------------------------------------------------------------------------- a real daemon
NOT_THE_BUSY_TIMEOUT_S = 5.0  # the database's busy timeout is 10 s: a stop faster than this did not wait for it

_HOLDER = """
import sqlite3, sys
db = sqlite3.connect(sys.argv[1], isolation_level=None)
db.execute("BEGIN IMMEDIATE")
db.execute("CREATE TABLE IF NOT EXISTS lock_holder (x)")
print("locked", flush=True)
sys.stdin.read()
db.execute("ROLLBACK")
"""


class WriteLock:
    """Another process holding the database's write lock (``BEGIN IMMEDIATE``) until released."""

    def __init__(self, path: Path) -> None:
        self.proc = subprocess.Popen([sys.executable, "-c", _HOLDER, str(path)], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True)
        assert self.proc.stdout is not None and self.proc.stdout.readline().strip() == "locked"

    def release(self) -> None:
        if self.proc.poll() is None:
            assert self.proc.stdin is not None
            self.proc.stdin.close()
            self.proc.wait(10)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.asynccontextmanager
async def served_on_a_socket(app: Any, bounds: ConnectionBounds, *, gated: bool = False,
                             **config: Any) -> AsyncIterator[int]:
    """The in-process ``app`` served by uvicorn on a free loopback port in this event loop, with the
    daemon's connection ``bounds`` (cap and header timeout) and uvicorn's ``config`` options; yields
    the port; stopped on leaving.  ``gated``: behind the daemon's accept gate (``commands/gate.py``),
    else uvicorn accepts on its loop."""
    from station.commands.gate import GatedServer

    port = free_port()
    cfg = uvicorn.Config(app, host="127.0.0.1", port=port, http=bounds.protocol(), lifespan="off", log_config=None,
                         **config)
    server = GatedServer(cfg, bounds) if gated else uvicorn.Server(cfg)
    serving = asyncio.create_task(server.serve())
    try:
        while not server.started:
            if serving.done():
                await serving  # it could not start: its error, not a wait for ever
                raise RuntimeError(f"uvicorn did not start on port {port}")
            await asyncio.sleep(0.02)
        yield port
    finally:
        server.should_exit = True
        await serving


class Daemon:
    """``station serve --sim`` in a subprocess; ``client`` talks to it (with the token).
    ``config``: the configuration as parsed YAML (default :func:`daemon_config`; without a
    ``simulation`` section the daemon runs on its ``devices``, e.g. an emulator run as its own
    process, without ``--sim``); ``seeds``: finished runs put in its store before it starts
    (:func:`seed_runs`, ids in ``seeded``)."""

    def __init__(self, tmp: Path, *, workers: int = 1, data_dir: Path | None = None, name: str = "daemon",
                 config: dict[str, Any] | None = None, seeds: Sequence[Seed] = (), **service: Any) -> None:
        self.tmp = tmp
        self.data_dir = data_dir or tmp / "recordings"
        cfg = config if config is not None else daemon_config(self.data_dir, **service)
        cfg["station"]["recordings_dir"] = str(self.data_dir)
        self.cfg_path = tmp / f"{name}.yaml"
        self.cfg_path.write_text(yaml.safe_dump(cfg))
        self.sim = cfg.get("simulation") is not None
        self.seeded = seed_runs(cfg, seeds) if seeds else []
        self.log_path = tmp / f"{name}.log"
        self.workers = workers
        self.port = 0
        self.proc: subprocess.Popen[bytes] | None = None
        self.client: httpx.Client | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def start(self, timeout_s: float = 60.0) -> Daemon:  # three processes start (web, rig, emulators) in parallel
        self.port = free_port()
        env = {**os.environ, "STATION_TOKEN": TOKEN, "PYTHONUNBUFFERED": "1"}
        log = self.log_path.open("ab")
        # the daemon dies with the test process, even one killed by a time-out (no daemon left
        # synthesising the simulated rig's signals on a shared machine)
        orphan_guard = ["setpriv", "--pdeathsig", "TERM"] if shutil.which("setpriv") else []
        self.proc = subprocess.Popen(
            [*orphan_guard, sys.executable, "-m", "station.cli", "serve", *(["--sim"] if self.sim else []),
             "--config", str(self.cfg_path), "--port", str(self.port), "--workers", str(self.workers)],
            stdout=log, stderr=subprocess.STDOUT, env=env, cwd=self.tmp)
        log.close()
        self.client = httpx.Client(base_url=self.url, headers=AUTH, timeout=30.0)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"daemon exited with {self.proc.returncode}:\n{self.log()}")
            try:
                if self.client.get("/health").status_code == 200:
                    return self
            except httpx.TransportError:
                pass
            time.sleep(0.1)
        raise RuntimeError(f"daemon not ready in {timeout_s} s:\n{self.log()}")

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")[-6000:] if self.log_path.exists() else ""

    def stop(self, sig: int = signal.SIGTERM, timeout_s: float = 40.0) -> int:
        assert self.proc is not None
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
                raise
        if self.client is not None:
            self.client.close()
        return int(self.proc.returncode)

    def kill(self) -> None:
        self.stop(signal.SIGKILL)

    def __enter__(self) -> Daemon:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.stop()

    # ---- helpers
    def c(self) -> httpx.Client:
        assert self.client is not None
        return self.client

    def start_run(self, **kw: Any) -> str:
        r = self.c().post("/runs", json=run_body(**kw))
        assert r.status_code == 202, r.text
        return str(r.json()["id"])

    def wait_state(self, run_id: str, states: tuple[str, ...] = FINAL, timeout_s: float = 60.0,
                   step_state: str | None = None) -> dict[str, Any]:
        deadline = time.monotonic() + timeout_s
        st: dict[str, Any] = {}
        while time.monotonic() < deadline:
            st = self.c().get(f"/runs/{run_id}").json()
            if st["state"] in states and (step_state is None or st["step_state"] == step_state):
                return st
            time.sleep(0.1)
        raise AssertionError(f"run {run_id} not in {states} after {timeout_s} s: {st}\n{self.log()}")
