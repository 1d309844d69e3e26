"""What one batch job returns."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any


@dataclass(frozen=True)
class BatchItem:
    """One recording re-identified (status "ok") or not ("failed", with the error).

    parameters: name -> the identification's JSON form ``{"value", "std", "unit", "identifiable"[,
    "reason"]}`` (SI units, std the standard uncertainty, k = 1); wall_s / cpu_s: elapsed and CPU
    time of the job in the worker (s); stored_as: the result's group in the recording when the batch stored it, else "";
    structure: the model structure the parameters rest on, as identify states it (``assumptions.structure``);
    findings: identify's warnings (name, severity, message), each as in its result.
    """

    path: Path
    run_id: str
    transducer_id: str
    start_time: str
    status: str
    method: str = ""
    model: str = ""
    parameters: dict[str, dict[str, Any]] = field(default_factory=dict)
    error: str = ""
    wall_s: float = 0.0
    stored_as: str = ""
    cpu_s: float = 0.0
    structure: dict[str, Any] = field(default_factory=dict)
    findings: list[dict[str, Any]] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    def to_dict(self) -> dict[str, Any]:
        return {"path": str(self.path), "run_id": self.run_id, "transducer_id": self.transducer_id,
                "start_time": self.start_time, "status": self.status, "method": self.method,
                "model": self.model, "parameters": self.parameters, "error": self.error,
                "wall_s": self.wall_s, "cpu_s": self.cpu_s, "stored_as": self.stored_as,
                "structure": self.structure, "findings": self.findings}
