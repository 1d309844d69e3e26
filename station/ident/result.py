"""Frozen result types of the station and their JSON form, read back by ``from_dict``.

``Estimate`` is the one estimate type (identification, campaign and model-gap results): value and
standard uncertainty; a parameter that the data cannot determine is ``identifiable=False`` with
``value``/``std`` ``None`` and a ``reason`` (never digits).  ``Covariance`` travels with the
identification: names, units and the matrix, whose diagonal is the square of the stated standard
uncertainties.  ``IdentificationResult.to_dict`` is what is stored beside a recording and
``IdentificationResult.from_dict`` reads it back unchanged.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from station.ident.assumptions import Assumptions
from station.ident.uncertainty import (
    Covariance,
    DeterminedQuantity,
    UncertaintyBudget,
    determined_from_dict,
    determined_to_dict,
    finite_or_none,
    float_or_nan,
)
from station.jsonvalue import JsonValue, json_float, json_floats
from station.vocabulary import Flag, Severity

__all__ = ["JsonValue", "json_float", "json_floats"]

@dataclass(frozen=True)
class Estimate:
    """A parameter: value and standard uncertainty in ``unit`` (SI).

    identifiable False: the data do not determine it (value and std None, or NaN, with a reason);
    flag: '' or 'poorly_determined' (relative uncertainty above the policy's) or 'conditional' (on
    an assumed input, see the result's assumptions)."""

    value: float | None
    std: float | None
    unit: str
    identifiable: bool = True
    reason: str = ""
    flag: Flag = Flag.NONE

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Estimate:
        v, s = d.get("value"), d.get("std")
        return cls(None if v is None else float(v), None if s is None else float(s), str(d.get("unit", "")),
                   bool(d.get("identifiable", True)), str(d.get("reason") or ""), Flag(str(d.get("flag") or "")))

    def to_dict(self) -> dict[str, JsonValue]:
        if not self.identifiable:
            return {"value": None, "std": None, "unit": self.unit, "identifiable": False,
                    "reason": self.reason}
        out: dict[str, JsonValue] = {"value": finite_or_none(self.value), "std": finite_or_none(self.std),
                               "unit": self.unit, "identifiable": True}
        if self.reason:
            out["reason"] = self.reason
        if self.flag:
            out["flag"] = str(self.flag)
        return out


def estimates_from_dict(d: Mapping[str, Any] | None) -> dict[str, Estimate]:
    """``{name: Estimate}`` from its JSON form (``{name: Estimate.to_dict()}``)."""
    return {str(n): Estimate.from_dict(p) for n, p in (d or {}).items()}


@dataclass(frozen=True)
class Check:
    """One finding of the input checks: name (e.g. 'dead_channel'), severity 'info' | 'warning' |
    'refused', step index or None for the run, message for the operator, the numbers behind it."""

    name: str
    severity: Severity
    step: int | None
    message: str
    values: dict[str, JsonValue] = field(default_factory=dict)

    def to_dict(self) -> dict[str, JsonValue]:
        vals = {k: (finite_or_none(v) if isinstance(v, float) else v) for k, v in self.values.items()}
        return {"name": self.name, "severity": self.severity, "step": self.step, "message": self.message,
                "values": vals}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Check:
        step = d.get("step")
        return cls(str(d["name"]), Severity(str(d["severity"])), None if step is None else int(step),
                   str(d.get("message", "")),
                   dict(d.get("values") or {}))


@dataclass(frozen=True)
class FitSummary:
    """Goodness of fit.

    mse: mean square of the force residual in V^2 (paper Eq. 15); residual_rms_V: per step RMS in V,
    shape (n_steps,); chi2_per_dof: weighted chi^2 / degrees of freedom (1.0 when the noise model
    is right; NaN when not applicable).
    """

    mse: float
    residual_rms_V: tuple[float, ...]
    chi2_per_dof: float = float("nan")
    n_points: int = 0

    def to_dict(self) -> dict[str, JsonValue]:
        return {"mse": finite_or_none(self.mse),
                "residual_rms_V": [finite_or_none(v) for v in self.residual_rms_V],
                "chi2_per_dof": finite_or_none(self.chi2_per_dof), "n_points": self.n_points}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> FitSummary:
        return cls(float_or_nan(d.get("mse")), tuple(float_or_nan(v) for v in d.get("residual_rms_V") or ()),
                   float_or_nan(d.get("chi2_per_dof")), int(d.get("n_points") or 0))


@dataclass(frozen=True)
class Identifiability:
    """Conditioning of an estimation problem.

    condition_number: of the parameter-scaled, noise-whitened Jacobian (dimensionless);
    correlations: parameter correlation matrix as nested tuples (names order): that of the estimate
    for identifiable parameters; for the others, that of the regularised identifiability assessment
    (chain floor included), where +-1 shows which parameters they are confounded with;
    reasons: per non-identifiable parameter, why.
    """

    names: tuple[str, ...]
    condition_number: float
    correlations: tuple[tuple[float, ...], ...]
    identifiable: tuple[bool, ...]
    reasons: tuple[str, ...]

    def to_dict(self) -> dict[str, JsonValue]:
        return {"names": list(self.names), "condition_number": finite_or_none(self.condition_number),
                "correlations": [[finite_or_none(c) for c in row] for row in self.correlations],
                "identifiable": list(self.identifiable), "reasons": list(self.reasons)}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Identifiability:
        return cls(tuple(d["names"]), float_or_nan(d.get("condition_number")),
                   tuple(tuple(float_or_nan(c) for c in row) for row in d.get("correlations") or ()),
                   tuple(bool(v) for v in d["identifiable"]), tuple(str(r) for r in d["reasons"]))


@dataclass(frozen=True)
class IdentificationResult:
    """What ``identify_recording`` returns: method, model, parameters by name (in the model's
    order), fit and conditioning, checks, GUM budget, assumptions, what the data determine whatever
    the assumptions, and the covariance of the parameters that have a value (None when the method
    gives none)."""

    method: str
    model: str
    parameters: dict[str, Estimate]
    fit: FitSummary
    identifiability: Identifiability | None = None
    notes: tuple[str, ...] = ()
    extra: dict[str, JsonValue] = field(default_factory=dict)
    checks: tuple[Check, ...] = ()
    budget: UncertaintyBudget = field(default_factory=UncertaintyBudget)
    assumptions: Assumptions = field(default_factory=Assumptions)
    determined: dict[str, DeterminedQuantity] = field(default_factory=dict)
    covariance: Covariance | None = None

    @property
    def result_name(self) -> str:
        """Its name among the results stored beside a recording (``<run>.results/results.<name>.h5``)."""
        return f"identify_{self.method}_{self.model}"

    def parameter(self, name: str) -> Estimate:
        return self.parameters[name]

    def to_dict(self) -> dict[str, JsonValue]:
        return {"method": self.method, "model": self.model,
                "parameters": {n: p.to_dict() for n, p in self.parameters.items()},
                "fit": self.fit.to_dict(),
                "identifiability": None if self.identifiability is None else self.identifiability.to_dict(),
                "notes": list(self.notes), "extra": self.extra,
                "checks": [c.to_dict() for c in self.checks], "budget": self.budget.to_dict(),
                "budget_covariances": self.budget.covariances_to_dict(),
                "assumptions": self.assumptions.to_dict(), "determined": determined_to_dict(self.determined),
                "covariance": None if self.covariance is None else self.covariance.to_dict()}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> IdentificationResult:
        """Read back what ``to_dict`` gave (e.g. a stored result).  Results stored before the
        covariance was kept have ``covariance`` None, those stored before the budget's per-source
        covariances were kept have none."""
        ident, cov = d.get("identifiability"), d.get("covariance")
        return cls(str(d["method"]), str(d["model"]),
                   {n: Estimate.from_dict(p) for n, p in (d.get("parameters") or {}).items()},
                   FitSummary.from_dict(d.get("fit") or {}),
                   None if ident is None else Identifiability.from_dict(ident), tuple(d.get("notes") or ()),
                   dict(d.get("extra") or {}), tuple(Check.from_dict(c) for c in d.get("checks") or ()),
                   UncertaintyBudget.from_dict(d.get("budget"), d.get("budget_covariances")),
                   Assumptions.from_dict(d.get("assumptions")), determined_from_dict(d.get("determined")),
                   None if cov is None else Covariance.from_dict(cov))


def estimates(names: Sequence[str], units: Sequence[str], theta: NDArray[np.float64], cov: NDArray[np.float64],
              identifiable: Sequence[bool], reasons: Sequence[str]) -> dict[str, Estimate]:
    """Estimates from a fit: value theta[i] and std sqrt(cov[i, i]) for the identifiable ones,
    None with the reason for the others."""
    std = np.sqrt(np.clip(np.diag(cov), 0, None))
    return {n: Estimate(float(theta[i]) if identifiable[i] else None, float(std[i]) if identifiable[i] else None,
                        u, bool(identifiable[i]), reasons[i])
            for i, (n, u) in enumerate(zip(names, units, strict=True))}


def estimated_covariance(parameters: Mapping[str, Estimate], names: Sequence[str],
                         matrix: NDArray[np.float64]) -> Covariance | None:
    """The covariance of the parameters that have a value: ``matrix`` (n, n) over ``names``
    restricted to them and scaled to their stated standard uncertainties (its correlations kept,
    its diagonal the stds squared), or None when no parameter has a value or the matrix does not
    give a correlation."""
    keep = [i for i, n in enumerate(names) if parameters[n].value is not None and parameters[n].std is not None]
    if not keep:
        return None
    m = np.asarray(matrix, dtype=float)[np.ix_(keep, keep)]
    d = np.sqrt(np.clip(np.diag(m), 0, None))
    if not np.all(np.isfinite(m)) or not np.all(d > 0):
        return None
    std = np.array([float(parameters[names[i]].std or 0.0) for i in keep])
    corr = np.clip(m / np.outer(d, d), -1, 1)
    np.fill_diagonal(corr, 1.0)
    kept = [names[i] for i in keep]
    return Covariance.of(kept, [parameters[n].unit for n in kept], corr * np.outer(std, std))
