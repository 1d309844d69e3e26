"""The service layer's typed errors; ``station.api`` maps each to an HTTP status (nothing below the
API layer knows about HTTP)."""

from __future__ import annotations

from station.errors import StationError


class RigBusyError(StationError):
    """Another run holds the rig (409)."""

    def __init__(self, run_id: str, state: str) -> None:
        super().__init__(f"run {run_id} holds the rig (state {state}); wait for it or abort it")
        self.run_id = run_id


class RunNotFoundError(StationError):
    """No run with this id (404)."""


class ResultNotStoredError(StationError):
    """A result that is computed on request has not been computed yet (404; the message says how)."""


class RunStateError(StationError):
    """The run is not in a state that allows the request, e.g. results of a running run (409)."""


class RigUnavailableError(StationError):
    """No link to the rig (503)."""


class EStopLatchedError(StationError):
    """An emergency stop (or a controller fault) is latched: no run starts until an operator
    acknowledges it (409)."""


class DatabaseBusyError(StationError):
    """The database did not answer or take a change within its bound (locked by another process,
    disk full); nothing was changed (503)."""
