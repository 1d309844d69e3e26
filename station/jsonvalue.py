"""The shape of a stored JSON document's values, and reading a number or a list of numbers out of
one with an error that names the key (a finding's numbers, a method's own outputs, the documents'
``to_dict`` forms)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TypeAlias

JsonValue: TypeAlias = "float | int | str | bool | Sequence[JsonValue] | Mapping[str, JsonValue] | None"
"""A number, text, flag or nothing, or a list or mapping of them: what a finding's numbers and a
method's own outputs (``Check.values``, ``IdentificationResult.extra``) hold, as stored."""


def json_float(values: Mapping[str, JsonValue], key: str, default: float | None = None) -> float:
    """``values[key]`` as a float; ``default`` when it is missing or null; else ``ValueError``."""
    v = values.get(key)
    if v is None and default is not None:
        return default
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise ValueError(f"{key!r} is not a number: {v!r}"[:200])
    return float(v)


def json_floats(values: Mapping[str, JsonValue], key: str) -> list[float]:
    """``values[key]`` as a list of floats (null as NaN); else ``ValueError``."""
    v = values.get(key)
    if not isinstance(v, list | tuple) or not all(x is None or (isinstance(x, int | float) and not isinstance(x, bool))
                                          for x in v):
        raise ValueError(f"{key!r} is not a list of numbers"[:200])
    return [float("nan") if x is None else float(x) for x in v]
