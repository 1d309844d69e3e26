"""What the lab decided for a transducer: its tolerances (per parameter, relative), the interval
assigned to it, whether it is the station's check transducer (the one that stays on the rig and is
re-measured by the nightly batch), and the adjustments made after a calibration (the as-left values
a user set in the instrument).  Every change is audited in the same transaction.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field
from typing import Any

from station.lab import audit
from station.lab.register import RegisterError
from station.service.store import Store

POLICY_CHANGED = "register.policy_changed"
AS_LEFT_RECORDED = "calibration.as_left"

TRENDED = ("S", "k_f", "b_f", "f_0")  # the parameters a history charts


class PolicyError(RegisterError):
    """A policy or adjustment the register refuses (unknown parameter, a tolerance outside (0, 1), an
    adjustment of a run that is not the transducer's or not completed)."""


@dataclass(frozen=True)
class Policy:
    """A transducer's policy: ``tolerances`` relative (e.g. {"S": 0.005} for ±0.5 % of the as-left
    value), ``interval_days`` the assigned calibration interval (None: none assigned),
    ``check_standard`` True for the station's check transducer."""

    transducer_id: str
    tolerances: dict[str, float] = field(default_factory=dict)
    interval_days: float | None = None
    check_standard: bool = False
    updated: float = 0.0
    updated_by: str = ""

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class AsLeft:
    """An adjustment after run ``run_id``: the value of ``parameter`` set in the user's instrument."""

    run_id: str
    transducer_id: str
    parameter: str
    value: float
    unit: str
    note: str
    at: float
    by: str

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def _check(tolerances: dict[str, float], interval_days: float | None) -> None:
    for name, tol in tolerances.items():
        if name not in TRENDED:
            raise PolicyError(f"no tolerance can be set for {name!r}: the parameters are {', '.join(TRENDED)}")
        if not (isinstance(tol, (int, float)) and math.isfinite(tol) and 0 < tol < 1):
            raise PolicyError(f"the tolerance of {name} is relative and must lie in (0, 1), not {tol!r}")
    if interval_days is not None and not (math.isfinite(interval_days) and 1 <= interval_days <= 3660):
        raise PolicyError(f"the interval must lie between 1 and 3660 days, not {interval_days!r}")


def policy(store: Store, transducer_id: str) -> Policy:
    rows = store.query("SELECT * FROM transducer_policy WHERE transducer_id = ?", (transducer_id,))
    if not rows:
        return Policy(transducer_id)
    r = rows[0]
    return Policy(transducer_id, {str(k): float(v) for k, v in json.loads(r["tolerances_json"]).items()},
                  r["interval_days"], bool(r["check_standard"]), r["updated"], r["updated_by"])


def check_transducers(store: Store) -> list[str]:
    return [r["transducer_id"] for r in
            store.query("SELECT transducer_id FROM transducer_policy WHERE check_standard = 1 ORDER BY transducer_id")]


def put_policy(store: Store, p: Policy, by: str) -> Policy:
    """Set a transducer's policy (audited, before and after)."""
    _check(p.tolerances, p.interval_days)
    now = time.time()
    new = Policy(p.transducer_id, dict(p.tolerances), p.interval_days, p.check_standard, now, by)
    with store.transaction() as db:
        old = db.execute("SELECT tolerances_json, interval_days, check_standard FROM transducer_policy "
                         "WHERE transducer_id = ?", (p.transducer_id,)).fetchone()
        db.execute("INSERT OR REPLACE INTO transducer_policy (transducer_id, tolerances_json, interval_days, "
                   "check_standard, updated, updated_by) VALUES (?, ?, ?, ?, ?, ?)",
                   (new.transducer_id, json.dumps(new.tolerances), new.interval_days, int(new.check_standard),
                    now, by))
        audit.record(db, by, POLICY_CHANGED, p.transducer_id,
                     {"before": None if old is None else {"tolerances": json.loads(old[0]), "interval_days": old[1],
                                                          "check_standard": bool(old[2])},
                      "after": {"tolerances": new.tolerances, "interval_days": new.interval_days,
                                "check_standard": new.check_standard}}, at=now)
    return new


def record_as_left(store: Store, a: AsLeft) -> AsLeft:
    """Record an adjustment (the as-left value) after a run of the transducer (audited)."""
    if a.parameter not in TRENDED:
        raise PolicyError(f"an as-left value is recorded for one of {', '.join(TRENDED)}, not {a.parameter!r}")
    if not math.isfinite(a.value):
        raise PolicyError("an as-left value must be a finite number")
    rows = store.query("SELECT transducer_id, state FROM runs WHERE id = ?", (a.run_id,))
    if not rows or rows[0]["transducer_id"] != a.transducer_id:
        raise PolicyError(f"run {a.run_id!r} is not a run of transducer {a.transducer_id!r}")
    if rows[0]["state"] != "completed":
        raise PolicyError(f"run {a.run_id!r} is {rows[0]['state']}: an adjustment follows a completed calibration")
    with store.transaction() as db:
        db.execute("INSERT OR REPLACE INTO as_left (run_id, transducer_id, parameter, value, unit, note, at, by) "
                   "VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                   (a.run_id, a.transducer_id, a.parameter, a.value, a.unit, a.note, a.at, a.by))
        audit.record(db, a.by, AS_LEFT_RECORDED, a.run_id,
                     {"transducer": a.transducer_id, "parameter": a.parameter, "value": a.value, "unit": a.unit,
                      "note": a.note}, at=a.at)
    return a


def as_left_of(store: Store, transducer_id: str) -> dict[str, dict[str, AsLeft]]:
    """{run_id: {parameter: AsLeft}} of a transducer's adjustments."""
    out: dict[str, dict[str, AsLeft]] = {}
    for r in store.query("SELECT * FROM as_left WHERE transducer_id = ?", (transducer_id,)):
        out.setdefault(r["run_id"], {})[r["parameter"]] = AsLeft(**r)
    return out
