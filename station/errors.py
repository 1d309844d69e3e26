"""Typed errors of the station layer.  The CLI prints them; the API maps them to HTTP statuses."""

from __future__ import annotations


class StationError(Exception):
    """Base class: a failure with a message meant for the operator."""

    exit_code = 1


class BadInputError(StationError):
    """Input (config, file, request) rejected: the message says what was expected and what came."""

    exit_code = 2


class ConfigError(BadInputError):
    """A configuration file or value is invalid."""


class RecordingFormatError(BadInputError):
    """A recording or interchange file is malformed."""


class LimitError(BadInputError):
    """A requested motion exceeds a configured rig or transducer limit; the message says which and why.

    ``step``: the offending step's index (None: the request as a whole); ``field``: the request field
    to change (``crank_frequency_hz``, ``crank_radius_m``, ``transducer_id``, ``steps``); ``value``:
    its requested value; ``limit``: what it broke (a bound in the field's unit, a ``(min, max)``
    range, or the mounted transducer's id)."""

    def __init__(self, message: str, *, step: int | None = None, field: str = "steps", value: object = None,
                 limit: object = None) -> None:
        super().__init__(message)
        self.step = step
        self.field = field
        self.value = value
        self.limit = limit
