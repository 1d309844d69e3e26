"""``station serve``: the calibration-station daemon (one uvicorn process with the FastAPI app)."""

from __future__ import annotations

import argparse
import logging
import signal
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from station.rigproc.client import RigProcessConnector
    from station.service.instance import InstanceLock
    from station.service.manager import RunManager
    from station.service.settings import ServiceSettings

log = logging.getLogger("station.serve")
BACKLOG = 4096  # the main port's accept backlog (the kernel caps it at net.core.somaxconn)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("serve", help="run the station daemon (HTTP API and the technicians' web page)")
    p.add_argument("--sim", action="store_true", help="start the simulated rig (emulators) and use it")
    p.add_argument("--config", type=Path, default=None, help="station YAML (default config/sim-5kN.yaml)")
    p.add_argument("--host", default=None, help="listen address (default service.host, 127.0.0.1)")
    p.add_argument("--port", type=int, default=None, help="TCP port (default service.port, 8080; 0: any free)")
    p.add_argument("--workers", type=int, default=None,
                   help="identification worker processes (default service.workers, 1)")
    p.add_argument("--access-log", action="store_true", help="log every HTTP request")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    # imports here, not at the top: ``station --help`` needs none of the daemon's
    from station.service.instance import InstanceLock, check_database
    from station.service.settings import load_settings

    settings = load_settings(args.config, sim=args.sim, host=args.host, port=args.port, workers=args.workers)
    stopped_by: list[int] = []
    # one daemon per recordings folder, before anything is touched (recovery, database, devices)
    with InstanceLock.acquire(settings.recordings_dir, "station serve", host=settings.host,
                              port=settings.port or None) as lock:
        check_database(settings.database)
        code = _serve(args, settings, lock, stopped_by)
    for sig in reversed(stopped_by):  # the signal's own end (SIGTERM: killed by it), after the whole shutdown
        signal.raise_signal(sig)
    return code


def _serve(args: argparse.Namespace, settings: ServiceSettings, lock: InstanceLock, stopped_by: list[int]) -> int:
    from station.rigproc.client import RigProcessConnector

    rig = RigProcessConnector(settings)  # the drive, its watchdog and the stop port in a process of their own
    rig.launch()  # the rig process and, simulated, the emulators start while the daemon does
    try:
        return _serve_on(args, settings, lock, rig, stopped_by)
    finally:
        rig.close()  # the rig process stops a turning crank and ends; then the emulators


def _serve_on(args: argparse.Namespace, settings: ServiceSettings, lock: InstanceLock,
              rig: RigProcessConnector, stopped_by: list[int]) -> int:
    import asyncio  # here, as the rest: registering ``serve`` costs the other commands' starts nothing

    import uvicorn

    from station.api import create_app
    from station.commands.server import StationServer
    from station.service.settings import TOKEN_ENV, is_loopback

    if settings.token_source == "generated":
        log.warning("no token configured (%s or service.token): this session's token is %s", TOKEN_ENV,
                    settings.token)
    if settings.sim:
        _demo_users(settings)
    if not is_loopback(settings.host):
        log.warning("listening on %s: reading needs the token from other machines; use TLS in front of it",
                    settings.host)
    log.info("recordings: %s; database: %s; %d identification worker(s)", settings.recordings_dir,
             settings.database, settings.workers)
    from station.errors import LimitError
    from station.limits import check_drive

    try:  # the page and the API still serve (results, stop); each run is refused with this, at its field
        check_drive(settings.config)
    except LimitError as exc:
        log.error("every run will be refused: %s", exc)
    from station.commands.connections import (
        FD_RESERVE,
        ConnectionBounds,
        connection_cap,
        install_repeat_filter,
        keep_alive_header,
        raise_fd_limit,
    )

    install_repeat_filter()
    svc = settings.config.service
    fd_limit = raise_fd_limit()
    bounds = ConnectionBounds(connection_cap(svc.max_connections, fd_limit), svc.header_timeout_s,
                              ceiling=fd_limit - FD_RESERVE // 2)
    log.info("HTTP: at most %d connections (%d with new ones still silent; open-files limit %d), request heads "
             "within %g s", bounds.max_connections, bounds.ceiling, fd_limit, bounds.header_timeout_s)
    app = create_app(settings, manager_factory=lambda s: _manager(s, rig))
    from station.api.routes.system import stop_on_arrival

    bounds.on_head = stop_on_arrival(app)  # POST /stop goes to the rig as soon as its head is read
    config = uvicorn.Config(app, host=settings.host, port=settings.port, log_config=None, http=bounds.protocol(),
                            access_log=args.access_log, timeout_graceful_shutdown=5, lifespan="on",
                            headers=[keep_alive_header(bounds.header_timeout_s)], backlog=BACKLOG)
    server = StationServer(config, settings, bounds, on_listening=lambda host, port: lock.update(host=host, port=port),
                           rig=rig)
    try:
        asyncio.run(server.serve())
    finally:
        stopped_by.extend(server.stopped_by)  # raised again by ``run`` once the rig process has ended
    return 0 if server.started else 3  # 3: the daemon could not start (the log says why)


def _manager(settings: ServiceSettings, rig: RigProcessConnector) -> RunManager:
    """The run manager on the rig process; a stop the rig process gives is latched and recorded."""
    from station.api.routes.system import who_stopped
    from station.run.standstill import DriveCheck
    from station.service.manager import RunManager

    manager = RunManager(settings, connector=rig)

    def stopped(msg: dict[str, Any]) -> None:
        if msg.get("event") == "stopping":
            manager.runs.stopping_elsewhere()
            return
        drive = DriveCheck.from_dict(msg["drive"]) if msg.get("drive") else None
        manager.runs.stopped_elsewhere(str(msg.get("source", "rig")), str(msg.get("detail", "")),
                                       who_stopped(msg.get("credentials") or {}, settings), drive)
    rig.on_event = stopped
    return manager


def _demo_users(settings: ServiceSettings) -> None:
    """The simulated station's technician and approver, with this start's passwords (logged once)."""
    from station.lab.demo import demo_users
    from station.lab.store import Store

    store = Store(settings.database)
    try:
        made = demo_users(store, settings.password_n)
    finally:
        store.close()
    where = f"http://{settings.host}:{settings.port}/" if settings.port else "the page"
    lines = [f"  {u.name:10s} ({u.role}) password {u.password}" if u.password is not None else
             f"  {u.name:10s} ({u.role}) made by someone else: its own password" for u in made]
    log.warning("simulated station: log in on %s as\n%s\n(new passwords at every start of the simulated "
                "station)", where, "\n".join(lines))
