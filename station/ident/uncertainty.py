"""The GUM uncertainty budget of a result as frozen types, and its JSON form.

``Contribution``: one source's standard uncertainty of a parameter (in the parameter's unit; None:
the source is not propagated and the result is conditional on it) and its degrees of freedom
(GUM G.4; infinite for a Type B source or a noise term resting on thousands of samples).
``ParameterBudget``: a parameter's contributions, their combination (root sum of squares) and the
unit.  ``UncertaintyBudget``: the budget per parameter (a read-only mapping, the model's order) and,
where the estimator gives them (the frequency-domain one), the covariance each source adds over
the budgeted parameters, so the correlations a source brings are kept.

JSON (unchanged from the stored results): ``{name: {"contributions": {source: u | None},
"combined": u_c, "unit": ..., ["dof": {source: nu}]}}``, only the finite ``dof`` stored; the
per-source covariances go beside it as ``{source: Covariance.to_dict() | None}``
(``IdentificationResult``'s ``budget_covariances``).
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from station.jsonvalue import JsonValue


def finite_or_none(x: float | None) -> float | None:
    """x as a float, None when it is None or not finite (JSON has no NaN)."""
    if x is None or not math.isfinite(x):
        return None
    return float(x)


def float_or_nan(x: Any) -> float:
    """A stored number back as a float (JSON null is NaN)."""
    return math.nan if x is None else float(x)


@dataclass(frozen=True)
class Covariance:
    """Covariance of estimated parameters: ``names`` and ``units`` (SI) in matrix order, ``matrix``
    (n, n) as nested tuples in the product of the units (e.g. (N/m)^2 on the diagonal of k_f)."""

    names: tuple[str, ...]
    units: tuple[str, ...]
    matrix: tuple[tuple[float, ...], ...]

    @classmethod
    def of(cls, names: Sequence[str], units: Sequence[str], matrix: NDArray[np.float64]) -> Covariance:
        m = np.asarray(matrix, dtype=float)
        if m.shape != (len(names), len(names)) or len(units) != len(names):
            raise ValueError(f"covariance {m.shape} does not match {len(names)} names and {len(units)} units")
        return cls(tuple(names), tuple(units), tuple(tuple(float(c) for c in row) for row in m))

    @property
    def array(self) -> NDArray[np.float64]:
        return np.array(self.matrix, dtype=float).reshape(len(self.names), len(self.names))

    def std(self, name: str) -> float:
        i = self.names.index(name)
        return math.sqrt(max(self.matrix[i][i], 0.0))

    def to_dict(self) -> dict[str, JsonValue]:
        return {"names": list(self.names), "units": list(self.units),
                "matrix": [[finite_or_none(c) for c in row] for row in self.matrix]}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Covariance:
        return cls(tuple(d["names"]), tuple(d["units"]),
                   tuple(tuple(float_or_nan(c) for c in row) for row in d["matrix"]))


@dataclass(frozen=True)
class Contribution:
    """One source of a parameter's budget: its standard uncertainty (the parameter's unit; None:
    not propagated, the result is conditional on it) and degrees of freedom (inf: exactly known)."""

    source: str
    std: float | None
    dof: float = math.inf


@dataclass(frozen=True)
class ParameterBudget:
    """A parameter's budget: contributions in source order, the combined standard uncertainty
    (root sum of squares of the propagated ones) and the unit (SI)."""

    contributions: tuple[Contribution, ...]
    combined: float
    unit: str

    @classmethod
    def of(cls, stds: Mapping[str, float | None], combined: float, unit: str,
           dof: Mapping[str, float] | None = None) -> ParameterBudget:
        """From standard uncertainties per source (and the finite degrees of freedom per source)."""
        nu = dict(dof or {})
        return cls(tuple(Contribution(s, None if u is None else float(u), float(nu.get(s, math.inf)))
                         for s, u in stds.items()), float(combined), unit)

    @property
    def stds(self) -> dict[str, float | None]:
        """Standard uncertainty per source (None: not propagated)."""
        return {c.source: c.std for c in self.contributions}

    @property
    def dof(self) -> dict[str, float]:
        """The finite degrees of freedom per source (the others are infinite)."""
        return {c.source: c.dof for c in self.contributions if math.isfinite(c.dof)}

    def std(self, source: str) -> float | None:
        """The standard uncertainty of ``source`` (KeyError when the budget has no such source)."""
        return self.stds[source]

    def with_contribution(self, source: str, std: float) -> ParameterBudget:
        """This budget with ``source``'s standard uncertainty replaced (or added) and recombined."""
        c = {**self.stds, source: float(std)}
        comb = math.sqrt(sum(v * v for v in c.values() if v is not None))
        return ParameterBudget.of(c, comb, self.unit, self.dof)

    def to_dict(self) -> dict[str, JsonValue]:
        out: dict[str, JsonValue] = {"contributions": {c.source: finite_or_none(c.std) for c in self.contributions},
                               "combined": finite_or_none(self.combined), "unit": self.unit}
        if self.dof:
            out["dof"] = self.dof
        return out

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> ParameterBudget:
        comb = d.get("combined")
        return cls.of({str(s): None if u is None else float(u) for s, u in (d.get("contributions") or {}).items()},
                      math.nan if comb is None else float(comb), str(d.get("unit", "")),
                      {str(s): float(n) for s, n in (d.get("dof") or {}).items() if n is not None})


@dataclass(frozen=True)
class UncertaintyBudget(Mapping[str, ParameterBudget]):
    """The budget per parameter (only the budgeted ones, in the model's order) and the covariance
    each source adds over them (empty when the estimator gives none; None for a source not
    propagated).  Reads as a mapping name -> ``ParameterBudget``."""

    parameters: Mapping[str, ParameterBudget] = field(default_factory=dict)
    covariances: Mapping[str, Covariance | None] = field(default_factory=dict)

    def __getitem__(self, name: str) -> ParameterBudget:
        return self.parameters[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self.parameters)

    def __len__(self) -> int:
        return len(self.parameters)

    def to_dict(self) -> dict[str, JsonValue]:
        return {n: b.to_dict() for n, b in self.parameters.items()}

    def covariances_to_dict(self) -> dict[str, JsonValue]:
        return {s: None if c is None else c.to_dict() for s, c in self.covariances.items()}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None, covariances: Mapping[str, Any] | None = None) -> UncertaintyBudget:
        """Read back ``to_dict`` (and ``covariances_to_dict``; results stored without them have none)."""
        return cls({str(n): ParameterBudget.from_dict(b) for n, b in (d or {}).items()},
                   {str(s): None if c is None else Covariance.from_dict(c) for s, c in (covariances or {}).items()})


_DETERMINED_FIELDS = ("value", "combined", "unit", "note", "range", "conditional_on", "run_id")


@dataclass(frozen=True)
class DeterminedQuantity:
    """A quantity the data determine whatever the assumptions (e.g. S M, the loaded natural frequency,
    the series stiffness): value in ``unit`` (None when only a range is determined) with its budget
    (contributions and combined standard uncertainty; None when it has none), a note, a range
    (low, high; high None: unbounded) and what the range is conditional on, further named numbers
    of the range (``bounds``, e.g. a coupling's lower bound in N/m) and the recording (``run_id``,
    a campaign's per-recording entries).

    JSON (flat, as stored): ``{"value", <source>: u ..., "combined", "unit"[, "note", "range",
    "conditional_on", <bound>: x ..., "run_id"]}``: beside a ``combined`` the other numbers are the
    budget's sources, without one they are bounds."""

    value: float | None
    unit: str
    budget: ParameterBudget | None = None
    note: str = ""
    range: tuple[float, float | None] | None = None
    conditional_on: str = ""
    bounds: Mapping[str, float | None] = field(default_factory=dict)
    run_id: str = ""

    @property
    def combined(self) -> float | None:
        """The combined standard uncertainty (None without a budget)."""
        return None if self.budget is None else self.budget.combined

    def to_dict(self) -> dict[str, JsonValue]:
        out: dict[str, JsonValue] = {"run_id": self.run_id} if self.run_id else {}
        out["value"] = None if self.value is None else float(self.value)
        if self.budget is not None:
            out |= {c.source: finite_or_none(c.std) for c in self.budget.contributions}
            out["combined"] = finite_or_none(self.budget.combined)
        out["unit"] = self.unit
        if self.note:
            out["note"] = self.note
        if self.range is not None:
            out["range"] = list(self.range)
        out |= dict(self.bounds)
        if self.conditional_on:
            out["conditional_on"] = self.conditional_on
        return out

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> DeterminedQuantity:
        rest = {str(k): None if v is None else float(v) for k, v in d.items()
                if k not in _DETERMINED_FIELDS and (v is None or isinstance(v, int | float))}
        budget = None
        if "combined" in d:
            comb = d["combined"]
            budget = ParameterBudget.of(rest, math.nan if comb is None else float(comb), str(d.get("unit", "")))
        rng = d.get("range")
        v = d.get("value")
        return cls(None if v is None else float(v), str(d.get("unit", "")), budget, str(d.get("note") or ""),
                   None if rng is None else (float(rng[0]), None if rng[1] is None else float(rng[1])),
                   str(d.get("conditional_on") or ""), {} if budget is not None else rest,
                   str(d.get("run_id") or ""))


def determined_to_dict(determined: Mapping[str, DeterminedQuantity]) -> dict[str, JsonValue]:
    return {n: q.to_dict() for n, q in determined.items()}


def determined_from_dict(d: Mapping[str, Any] | None) -> dict[str, DeterminedQuantity]:
    return {str(n): DeterminedQuantity.from_dict(q) for n, q in (d or {}).items()}
