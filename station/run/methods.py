"""The identifications a finished run gets: each (method, model) of ``identification.methods``, the
first being the primary result, the others computed after it, beside it.

The list comes from the configuration stored in the recording (the daemon's, or the run request's
own list), so a recording says which identifications it asked for.  Each method's result is stored
beside the recording as ``results/identify_<method>_<model>`` (its checks, identifiability and
budget with it); how each one went is the result ``methods`` (``MethodOutcome`` per method, in the
listed order): its seed, its compute time, and for a method that gave no result, why.  A method
that refuses the data (``BadInputError``: e.g. a record too short for the paper's protocol) or
fails is ``refused`` or ``failed`` with the reason; only the primary's failure fails a run.

``agreement`` compares a method's parameters with the primary's in units of their combined
standard uncertainty, z = (x - x_primary) / sqrt(u^2 + u_primary^2); a parameter either withholds
has no z, and the reason says which method withholds it and why.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from pydantic import ValidationError

from station.config import IdentificationConfig, MethodChoice
from station.errors import BadInputError
from station.ident.paper.protocol import SwarmSize
from station.ident.result import IdentificationResult
from station.recording import Recording, read_result, write_result

if TYPE_CHECKING:
    from station.ident.response.checked import CheckedResponse  # scipy.optimize: not in the daemon

log = logging.getLogger(__name__)

METHODS_RESULT = "methods"  # the stored outcome of every listed method, beside the recording
MethodStatus = Literal["pending", "running", "done", "refused", "failed"]
STATUSES: tuple[MethodStatus, ...] = ("pending", "running", "done", "refused", "failed")
SETTLED: tuple[MethodStatus, ...] = ("done", "refused", "failed")


@dataclass(frozen=True)
class MethodOutcome:
    """How one listed identification went.

    method, model: as listed (model ``auto`` for fd resolves to the result's model, ``result_model``);
    primary: the first listed; status: pending | running | done | refused | failed; seed: of its
    random draws; result_name: the stored result (done only); compute_s / cpu_s: wall-clock and
    processor time of the identification in its worker, s; reason: why there is no result."""

    method: str
    model: str
    primary: bool
    status: MethodStatus
    seed: int = 0
    result_name: str | None = None
    result_model: str | None = None
    compute_s: float | None = None
    cpu_s: float | None = None
    reason: str = ""

    @property
    def label(self) -> str:
        return f"{self.method}/{self.model}"

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> MethodOutcome:
        status = str(d.get("status", "failed"))
        return cls(str(d["method"]), str(d["model"]), bool(d.get("primary", False)),
                   next((s for s in STATUSES if s == status), "failed"),
                   int(d.get("seed") or 0), d.get("result_name"), d.get("result_model"),
                   None if d.get("compute_s") is None else float(d["compute_s"]),
                   None if d.get("cpu_s") is None else float(d["cpu_s"]), str(d.get("reason") or ""))

    @classmethod
    def pending(cls, choice: MethodChoice, primary: bool) -> MethodOutcome:
        return cls(choice.method, choice.model_key, primary, "pending", choice.seed)


def identification_of(rec: Recording) -> IdentificationConfig:
    """The identification settings stored with the recording (its configuration snapshot); the
    defaults for a recording without them (imported, or older than the setting) or whose list no
    longer validates (its chain kept if that does)."""
    doc = rec.config.get("identification") if isinstance(rec.config, dict) else None
    doc = doc if isinstance(doc, dict) else {}
    for attempt in (doc, {"chain": doc.get("chain", {})}, {}):
        try:
            return IdentificationConfig.model_validate(attempt)
        except ValidationError as exc:
            log.warning("%s: stored identification settings refused (%s); falling back", rec.path,
                        exc.errors()[0].get("msg", exc))
    return IdentificationConfig()


def identify_method(path: Path, rec: Recording, choice: MethodChoice, swarm: SwarmSize, *, primary: bool,
                    response: CheckedResponse | None = None) -> tuple[MethodOutcome, IdentificationResult | None]:
    """Identify ``rec`` (at ``path``) with one listed method and store its result beside it.  A
    secondary method's refusal or failure comes back as its outcome; the primary's is raised."""
    from station.ident.identify import identify_recording, store_result  # the estimators: in the worker only

    t0, c0 = time.perf_counter(), time.process_time()
    base = MethodOutcome.pending(choice, primary)

    def took(**kw: Any) -> MethodOutcome:
        return MethodOutcome(**{**base.to_dict(), "compute_s": time.perf_counter() - t0,
                                "cpu_s": time.process_time() - c0, **kw})
    try:
        model = None if choice.model_key == "auto" else choice.model_key  # fd's own choice of Eq. 9 / Eq. 8
        res = identify_recording(rec, choice.method, model, seed=choice.seed, swarm=swarm,
                                 response=response)
        store_result(path, res)
    except BadInputError as exc:
        if primary:
            raise
        log.info("%s: %s refused: %s", path.name, choice.label, exc)
        return took(status="refused", reason=str(exc)), None
    except Exception as exc:
        if primary:
            raise
        log.exception("%s: %s failed", path.name, choice.label)
        return took(status="failed", reason=f"{type(exc).__name__}: {exc}"), None
    return took(status="done", result_name=res.result_name, result_model=res.model), res


def swarm_of(ident: IdentificationConfig) -> SwarmSize:
    return SwarmSize(ident.swarm.n_particles, ident.swarm.n_iterations)


def write_outcomes(path: Path, outcomes: Sequence[MethodOutcome]) -> None:
    """Store every listed method's outcome beside the recording (atomically, replacing the last)."""
    write_result(path, METHODS_RESULT, {"methods": [o.to_dict() for o in outcomes]})


def read_outcomes(path: Path) -> list[MethodOutcome]:
    """The stored outcomes, in the listed order ([] for a run identified before methods were listed)."""
    doc = read_result(path, METHODS_RESULT)
    return [MethodOutcome.from_dict(d) for d in (doc or {}).get("methods", [])]


def agreement(primary: IdentificationResult, other: IdentificationResult) -> dict[str, dict[str, Any]]:
    """Per parameter both results name: the difference other - primary (in its unit), the combined
    standard uncertainty sqrt(u^2 + u_primary^2) and z, their ratio; z None with the reason when
    either withholds the parameter (or states no uncertainty)."""
    out: dict[str, dict[str, Any]] = {}
    for name, p in primary.parameters.items():
        q = other.parameters.get(name)
        if q is None:
            continue
        why = ""
        if not p.identifiable or p.value is None:
            why = f"{primary.method} withholds it: {p.reason or 'not identifiable'}"
        elif not q.identifiable or q.value is None:
            why = f"{other.method} withholds it: {q.reason or 'not identifiable'}"
        elif p.std is None or q.std is None or not math.isfinite(p.std) or not math.isfinite(q.std):
            why = "no standard uncertainty stated"
        if why:
            out[name] = {"difference": None, "combined_std": None, "z": None, "unit": p.unit, "reason": why}
            continue
        assert p.value is not None and q.value is not None and p.std is not None and q.std is not None
        diff = q.value - p.value
        comb = math.hypot(p.std, q.std)
        out[name] = {"difference": diff, "combined_std": comb, "z": diff / comb if comb > 0 else None,
                     "unit": p.unit, "reason": "" if comb > 0 else "zero combined uncertainty"}
    return out


def identify_primary(path: Path, rec: Recording, response: CheckedResponse | None = None
                     ) -> tuple[list[MethodOutcome], IdentificationResult]:
    """The primary (first listed) identification, stored, and every outcome stored with the others
    ``pending``: the outcomes and the primary's result."""
    ident = identification_of(rec)
    outcomes = [MethodOutcome.pending(c, i == 0) for i, c in enumerate(ident.methods)]
    outcomes[0], res = identify_method(path, rec, ident.methods[0], swarm_of(ident), primary=True, response=response)
    assert res is not None  # the primary raises rather than refuse
    write_outcomes(path, outcomes)
    return outcomes, res


def identify_secondary(path: Path, rec: Recording, index: int) -> MethodOutcome:
    """Listed method ``index`` (>= 1), its result stored; its outcome (the caller stores the outcomes)."""
    ident = identification_of(rec)
    return identify_method(path, rec, ident.methods[index], swarm_of(ident), primary=False)[0]


def identify_all(path: Path, rec: Recording, response: CheckedResponse | None = None) -> IdentificationResult:
    """Every listed method, one after the other (``station calibrate``; the daemon runs each in its
    own worker job): the primary's result, every outcome stored."""
    outcomes, res = identify_primary(path, rec, response)
    ident = identification_of(rec)
    for i in range(1, len(outcomes)):  # the H(f) computed once serves every method here
        outcomes[i] = identify_method(path, rec, ident.methods[i], swarm_of(ident), primary=False, response=response)[0]
        write_outcomes(path, outcomes)
    return res
