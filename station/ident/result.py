"""Frozen result types of the identification package and their JSON form.

Every estimate carries its standard uncertainty; a parameter that the data cannot determine is
``identifiable=False`` with ``value``/``std`` ``None`` and a ``reason`` (never digits).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any


def _finite_or_none(x: float | None) -> float | None:
    if x is None or not math.isfinite(x):
        return None
    return float(x)


@dataclass(frozen=True)
class ParameterEstimate:
    """One physical parameter: value and standard uncertainty in ``unit`` (SI)."""

    name: str
    unit: str
    value: float | None
    std: float | None
    identifiable: bool
    reason: str = ""
    flag: str = ""  # '', 'poorly_determined' (relative uncertainty above the policy's), 'conditional'
    #                 (on an assumed input, see the result's assumptions)

    def to_dict(self) -> dict[str, Any]:
        if not self.identifiable:
            return {"value": None, "std": None, "unit": self.unit, "identifiable": False,
                    "reason": self.reason}
        out: dict[str, Any] = {"value": _finite_or_none(self.value), "std": _finite_or_none(self.std),
                               "unit": self.unit, "identifiable": True}
        if self.reason:
            out["reason"] = self.reason
        if self.flag:
            out["flag"] = self.flag
        return out


@dataclass(frozen=True)
class Check:
    """One finding of the input checks: name (e.g. 'dead_channel'), severity 'info' | 'warning' |
    'refused', step index or None for the run, message for the operator, the numbers behind it."""

    name: str
    severity: str
    step: int | None
    message: str
    values: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        vals = {k: (_finite_or_none(v) if isinstance(v, float) else v) for k, v in self.values.items()}
        return {"name": self.name, "severity": self.severity, "step": self.step, "message": self.message,
                "values": vals}


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

    def to_dict(self) -> dict[str, Any]:
        return {"mse": _finite_or_none(self.mse),
                "residual_rms_V": [_finite_or_none(v) for v in self.residual_rms_V],
                "chi2_per_dof": _finite_or_none(self.chi2_per_dof), "n_points": self.n_points}


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

    def to_dict(self) -> dict[str, Any]:
        return {"names": list(self.names), "condition_number": _finite_or_none(self.condition_number),
                "correlations": [[_finite_or_none(c) for c in row] for row in self.correlations],
                "identifiable": list(self.identifiable), "reasons": list(self.reasons)}


@dataclass(frozen=True)
class IdentificationResult:
    """What ``identify_recording`` returns: method, model, parameters, fit and conditioning."""

    method: str
    model: str
    parameters: tuple[ParameterEstimate, ...]
    fit: FitSummary
    identifiability: Identifiability | None = None
    notes: tuple[str, ...] = ()
    extra: dict[str, Any] = field(default_factory=dict)
    checks: tuple[Check, ...] = ()
    budget: dict[str, Any] = field(default_factory=dict)
    assumptions: dict[str, Any] = field(default_factory=dict)
    determined: dict[str, Any] = field(default_factory=dict)

    @property
    def result_name(self) -> str:
        """Its name among the results stored beside a recording (``<run>.results/results.<name>.h5``)."""
        return f"identify_{self.method}_{self.model}"

    def parameter(self, name: str) -> ParameterEstimate:
        for p in self.parameters:
            if p.name == name:
                return p
        raise KeyError(name)

    def to_dict(self) -> dict[str, Any]:
        return {"method": self.method, "model": self.model,
                "parameters": {p.name: p.to_dict() for p in self.parameters},
                "fit": self.fit.to_dict(),
                "identifiability": None if self.identifiability is None else self.identifiability.to_dict(),
                "notes": list(self.notes), "extra": self.extra,
                "checks": [c.to_dict() for c in self.checks], "budget": self.budget,
                "assumptions": self.assumptions, "determined": self.determined}
