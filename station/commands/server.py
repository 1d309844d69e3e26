"""uvicorn's server with the station's start-up log and shutdown order (used by ``station serve``)."""

from __future__ import annotations

import logging
from collections.abc import Callable
from types import FrameType

import uvicorn

from station.service.settings import ServiceSettings

log = logging.getLogger("station.serve")


class StationServer(uvicorn.Server):
    """uvicorn, plus: a shutdown signal stops the run on the rig at once (before open connections
    drain), and the address is logged once the socket is bound."""

    def __init__(self, config: uvicorn.Config, settings: ServiceSettings,
                 on_listening: Callable[[str, int], None] | None = None) -> None:
        super().__init__(config)
        self.settings = settings
        self.on_listening = on_listening

    def handle_exit(self, sig: int, frame: FrameType | None) -> None:
        manager = getattr(self.config.app.state, "manager", None) if hasattr(self.config.app, "state") else None
        if manager is not None:
            manager.begin_shutdown()
        super().handle_exit(sig, frame)

    async def startup(self, sockets: list | None = None) -> None:
        await super().startup(sockets)
        for server in self.servers:
            for sock in server.sockets:
                host, port = sock.getsockname()[:2]
                shown = f"[{host}]" if ":" in host else host
                log.info("station daemon ready: open http://%s:%d/ (API docs: /docs); rig: %s", shown, port,
                         "simulated" if self.settings.sim else "real devices")
                if self.on_listening is not None:
                    self.on_listening(host, port)
