"""The stop port in the daemon's own process (``station/rigproc/stopport.py`` is the listener; the
daemon runs it in the rig process, ``station/rigproc``): its stop is the main port's
``Runs.emergency_stop``.  For an in-process daemon (tests, benches of the in-process form)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from station.api.routes.system import stop_answer, who_stopped
from station.rigproc.stopport import StopPort, station_names

if TYPE_CHECKING:
    from station.service.manager import RunManager
    from station.service.settings import ServiceSettings


class ManagerStops:
    """The stop port in the daemon's own process: the main port's ``Runs.emergency_stop``."""

    def __init__(self, manager: RunManager, settings: ServiceSettings) -> None:
        self.manager = manager
        self.settings = settings

    def state(self) -> dict[str, Any]:
        link = self.manager.link
        latch = self.manager.latch.state()
        return {"estop": {k: latch[k] for k in ("latched", "since", "source", "detail", "count")},
                "drive": link.drive.to_dict() if link.drive is not None else None}

    async def stop(self, source: str, headers: dict[str, str]) -> dict[str, Any]:
        rep = await self.manager.runs.emergency_stop(source, who_stopped(headers, self.settings))
        return stop_answer(rep).model_dump(mode="json")


def daemon_stop_port(manager: RunManager, settings: ServiceSettings, host: str, port: int, **kw: Any) -> StopPort:
    """The stop port in the daemon's own process (not started)."""
    return StopPort(ManagerStops(manager, settings), station_names(settings), host, port, **kw)
