"""``station serve``: the calibration-station daemon (one uvicorn process with the FastAPI app)."""

from __future__ import annotations

import argparse
import asyncio
import logging
from pathlib import Path
from types import FrameType

import uvicorn

from station.api import create_app
from station.service.settings import TOKEN_ENV, ServiceSettings, is_loopback, load_settings

log = logging.getLogger("station.serve")


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


class _Server(uvicorn.Server):
    """uvicorn, plus: a shutdown signal stops the run on the rig at once (before open connections
    drain), and the address is logged once the socket is bound."""

    def __init__(self, config: uvicorn.Config, settings: ServiceSettings) -> None:
        super().__init__(config)
        self.settings = settings

    def handle_exit(self, sig: int, frame: FrameType | None) -> None:
        manager = getattr(self.config.app.state, "manager", None) if hasattr(self.config.app, "state") else None
        if manager is not None:
            manager.begin_shutdown()
        super().handle_exit(sig, frame)

    async def startup(self, sockets: list | None = None) -> None:  # type: ignore[type-arg]
        await super().startup(sockets)
        for server in self.servers:
            for sock in server.sockets:
                host, port = sock.getsockname()[:2]
                shown = f"[{host}]" if ":" in host else host
                log.info("station daemon ready: open http://%s:%d/ (API docs: /docs); rig: %s", shown, port,
                         "simulated" if self.settings.sim else "real devices")


def run(args: argparse.Namespace) -> int:
    settings = load_settings(args.config, sim=args.sim, host=args.host, port=args.port, workers=args.workers)
    if settings.token_source == "generated":
        log.warning("no token configured (%s or service.token): this session's token is %s", TOKEN_ENV,
                    settings.token)
    if not is_loopback(settings.host):
        log.warning("listening on %s: reading needs the token from other machines; use TLS in front of it",
                    settings.host)
    log.info("recordings: %s; database: %s; %d identification worker(s)", settings.recordings_dir,
             settings.database, settings.workers)
    app = create_app(settings)
    config = uvicorn.Config(app, host=settings.host, port=settings.port, log_config=None,
                            access_log=args.access_log, timeout_graceful_shutdown=5, lifespan="on")
    asyncio.run(_Server(config, settings).serve())
    return 0
