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
    """A requested motion exceeds a configured rig or transducer limit."""
