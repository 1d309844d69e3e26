"""uvicorn's server with the station's start-up log and shutdown order (used by ``station serve``)."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable, Iterator
from types import FrameType
from typing import TYPE_CHECKING

import uvicorn

from station.commands.connections import ConnectionBounds
from station.commands.gate import GatedServer, gate_priority
from station.commands.stopport import daemon_stop_port
from station.rigproc.stopport import StopPort
from station.service.priority import raise_priority
from station.service.settings import ServiceSettings

if TYPE_CHECKING:
    from station.rigproc.client import RigProcessConnector

log = logging.getLogger("station.serve")


class StationServer(GatedServer):
    """uvicorn behind the accept gate (``gate.py``), plus: a shutdown signal stops the run on the
    rig at once (before open connections drain), the address is logged once the socket is bound,
    and the signal that stopped the server is kept in ``stopped_by`` (not raised again as uvicorn
    does when it stops)."""

    def __init__(self, config: uvicorn.Config, settings: ServiceSettings, bounds: ConnectionBounds,
                 on_listening: Callable[[str, int], None] | None = None,
                 rig: RigProcessConnector | None = None) -> None:
        """``bounds``: the connections' (``config.http`` is ``bounds.protocol()``); ``rig``: the rig
        process, which owns the stop port (else it is opened here)."""
        super().__init__(config, bounds, gate_priority(settings.config.service.rig_priority))
        self.settings = settings
        self.rig = rig
        self.on_listening = on_listening
        self.stop_port: StopPort | None = None
        self.stopped_by: list[int] = []  # the signals that stopped the server, in the order received

    @contextlib.contextmanager
    def capture_signals(self) -> Iterator[None]:
        """uvicorn's, without raising the signals again as the server stops: SIGTERM's default action
        would end the process there, before the rest of the daemon's shutdown (the rig process, which
        stops a turning crank, then the emulators).  The caller raises them once that is done."""
        with super().capture_signals():
            try:
                yield
            finally:
                captured = getattr(self, "_captured_signals", [])  # uvicorn >= 0.29 raises these again
                self.stopped_by.extend(captured)
                captured.clear()

    def handle_exit(self, sig: int, frame: FrameType | None) -> None:
        manager = getattr(self.config.app.state, "manager", None) if hasattr(self.config.app, "state") else None
        if manager is not None:
            manager.begin_shutdown()
        super().handle_exit(sig, frame)

    async def startup(self, sockets: list | None = None) -> None:
        await super().startup(sockets)
        for sock in self.bound_sockets():
            host, port = sock.getsockname()[:2]
            shown = f"[{host}]" if ":" in host else host
            log.info("station daemon ready: open http://%s:%d/ (API docs: /docs); rig: %s", shown, port,
                     "simulated" if self.settings.sim else "real devices")
            if self.on_listening is not None:
                self.on_listening(host, port)
        if self.started and self.stop_port is None:
            self._raise_rig_priority()
            if self.rig is None:
                self._start_stop_port()
            else:
                self._tell_rig_process()

    def _raise_rig_priority(self) -> None:
        """The rig thread asks for ``service.rig_priority`` (logged: what the system gave)."""
        manager = getattr(getattr(self.config.app, "state", None), "manager", None)
        wanted = self.settings.config.service.rig_priority
        if manager is not None and wanted != "normal":
            manager.link.thread.call_soon(raise_priority, "rig-control", wanted)

    def _tell_rig_process(self) -> None:
        """The rig process's stop port takes the station's own page (on the main port) as this station."""
        manager = getattr(getattr(self.config.app, "state", None), "manager", None)
        bound = [s.getsockname()[1] for s in self.bound_sockets()]
        sup = self.rig.supervisor if self.rig is not None else None
        if manager is None or not bound or sup is None:
            return
        try:
            manager.link.thread.submit(sup.tell_page_port(int(bound[0])))
        except RuntimeError as exc:  # pragma: no cover - the rig thread runs once the manager started
            log.error("the rig process cannot be told the main port: %s", exc)

    def _start_stop_port(self) -> None:
        """The stop port (``service.stop_port``), once the app's manager runs; a port that cannot be
        bound is logged as an error (the main port's ``POST /stop`` still stops)."""
        bound = [s.getsockname()[1] for s in self.bound_sockets()]
        port = self.settings.stop_port
        manager = getattr(getattr(self.config.app, "state", None), "manager", None)
        if port is None or manager is None:
            return
        try:
            self.stop_port = daemon_stop_port(manager, self.settings, self.settings.host, port,
                                      page_port=int(bound[0]) if bound else None,
                                      header_timeout_s=min(5.0, self.settings.config.service.header_timeout_s),
                                      priority=self.settings.config.service.rig_priority).start()
        except OSError as exc:
            log.error("the stop port %d cannot be opened (%s): POST /stop on the main port only", port, exc)

    async def shutdown(self, sockets: list | None = None) -> None:
        if self.stop_port is not None:
            self.stop_port.close()
            self.stop_port = None
        await super().shutdown(sockets)
