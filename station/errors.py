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
    """A requested motion exceeds a configured rig or transducer limit, or the configuration asks the
    connected hardware for more than it declares; the message says which and why.

    ``step``: the offending step's index (None: the request as a whole); ``field``: the field to
    change, a request field (``crank_frequency_hz``, ``crank_radius_m``, ``transducer_id``,
    ``steps``) or, with ``in_config``, a dotted configuration path (``rig.acceleration_hz_per_s``);
    ``value``: its value; ``limit``: what it broke (a bound in the field's unit, a ``(min, max)``
    range, or the mounted transducer's id)."""

    def __init__(self, message: str, *, step: int | None = None, field: str = "steps", value: object = None,
                 limit: object = None, in_config: bool = False) -> None:
        super().__init__(message)
        self.step = step
        self.field = field
        self.value = value
        self.limit = limit
        self.in_config = in_config

    @property
    def loc(self) -> list[str | int]:
        """Where the field is, as a validation error's ``loc``: in the request body (steps counted
        from 0), or in the station's configuration (``["config", "rig", "acceleration_hz_per_s"]``)."""
        if self.in_config:
            return ["config", *self.field.split(".")]
        step: list[str | int] = ["steps", self.step] if self.step is not None else []
        return ["body", *step, self.field]


class HardwareMismatchError(ConfigError):
    """The configuration disagrees with what a connected device reports of itself (e.g. the DAQ
    bridge's ``HW?``): ``field`` (dotted configuration path), ``configured`` and ``reported`` values,
    ``device`` (``daq`` or ``motor``).  Raised at connect, before the motor is enabled."""

    def __init__(self, message: str, *, field: str, configured: object, reported: object, device: str) -> None:
        super().__init__(message)
        self.field = field
        self.configured = configured
        self.reported = reported
        self.device = device
