"""What the lab decided for a transducer: its tolerances (per parameter, relative), the interval
assigned to it, whether it is the station's check transducer (the one that stays on the rig and is
re-measured by the nightly batch), and the adjustments made after a calibration (the as-left values
a user set in the instrument).  Every change is audited in the same transaction.

The audit chain vouches for both tables row by row: each change's entry holds the whole row as
written (a policy's ``after``, an adjustment's parameter, value, unit and note; the entry's time and
user are the row's).  Every read compares the rows it returns with the chain's latest entry for each
(the entries' own hashes and links checked on the way) and refuses, naming the row and the fields,
when a row was changed, added or deleted outside the station (sqlite3 on the database file);
``/integrity`` and ``station verify`` compare every row (:func:`record_mismatches`).
"""

from __future__ import annotations

import json
import math
import sqlite3
import time
from dataclasses import asdict, dataclass, field
from typing import Any

from station.lab import audit, chain
from station.lab.integrity import RecordingTamperedError
from station.lab.register import RegisterError
from station.service.store import Store

POLICY_CHANGED = "register.policy_changed"
AS_LEFT_RECORDED = "calibration.as_left"

TRENDED = ("S", "k_f", "b_f", "f_0")  # the parameters a history charts


class PolicyError(RegisterError):
    """A policy or adjustment the register refuses (unknown parameter, a tolerance outside (0, 1), an
    adjustment of a run that is not the transducer's or not completed)."""


class RecordTamperedError(RecordingTamperedError):
    """A row of the lab's tables differs from what the audit chain vouches for (409)."""


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


# ------------------------------------------------------------------ rows vouched for by the chain
Fields = dict[str, Any]
Vouched = dict[Any, tuple[int, Fields]]  # key -> (the audit entry's id, the row it records)


def _policy_fields(tolerances: Any, interval_days: Any, check_standard: Any, at: Any, by: Any) -> Fields:
    tol = {str(k): float(v) for k, v in (tolerances or {}).items()}
    return {"tolerances": tol, "interval_days": None if interval_days is None else float(interval_days),
            "check_standard": bool(check_standard), "updated": float(at), "updated_by": str(by)}


def _as_left_fields(transducer_id: Any, value: Any, unit: Any, note: Any, at: Any, by: Any) -> Fields:
    return {"transducer_id": str(transducer_id), "value": float(value), "unit": str(unit), "note": str(note),
            "at": float(at), "by": str(by)}


def _details(e: dict[str, Any]) -> dict[str, Any]:
    try:
        d = json.loads(e["details"])
    except ValueError:
        return {}
    return d if isinstance(d, dict) else {}


def _vouched_policies(entries: list[dict[str, Any]]) -> Vouched:
    out: Vouched = {}
    for e in entries:
        after = _details(e).get("after") or {}
        out[e["target"]] = (int(e["id"]), _policy_fields(after.get("tolerances"), after.get("interval_days"),
                                                         after.get("check_standard"), e["at"], e["who"]))
    return out


def _vouched_as_left(entries: list[dict[str, Any]], transducer_id: str | None = None) -> Vouched:
    out: Vouched = {}
    for e in entries:
        d = _details(e)
        if transducer_id is None or d.get("transducer") == transducer_id:
            out[(e["target"], str(d.get("parameter")))] = (int(e["id"]), _as_left_fields(
                d.get("transducer"), d.get("value", math.nan), d.get("unit"), d.get("note", ""), e["at"], e["who"]))
    return out


def _stored_policies(rows: list[Any]) -> dict[Any, Fields]:
    return {r["transducer_id"]: _policy_fields(json.loads(r["tolerances_json"]), r["interval_days"],
                                               r["check_standard"], r["updated"], r["updated_by"]) for r in rows}


def _stored_as_left(rows: list[Any]) -> dict[Any, Fields]:
    return {(r["run_id"], r["parameter"]): _as_left_fields(r["transducer_id"], r["value"], r["unit"], r["note"],
                                                           r["at"], r["by"]) for r in rows}


def _differences(table: str, vouched: Vouched, stored: dict[Any, Fields]) -> list[str]:
    """Each row of ``table`` that is not what its latest audit entry recorded."""
    out = []
    for key in sorted(set(vouched) | set(stored), key=str):
        name = f"{table} {key if isinstance(key, str) else '/'.join(key)}"
        if key not in stored:
            out.append(f"{name}: deleted outside the station (audit entry {vouched[key][0]} records it)")
        elif key not in vouched:
            out.append(f"{name}: not in the audit trail (added outside the station)")
        elif changed := [f for f, v in vouched[key][1].items() if stored[key].get(f) != v]:
            out.append(f"{name}: {', '.join(changed)} changed outside the station (audit entry "
                       f"{vouched[key][0]} records {', '.join(f'{f}={vouched[key][1][f]!r}' for f in changed)})")
    return out


def _policy_differences(db: sqlite3.Connection, transducer_id: str | None, *, check: bool = True) -> list[str]:
    if transducer_id is None:
        rows = db.execute("SELECT * FROM transducer_policy").fetchall()
        entries = chain.checked_entries(db, "action = ?", (POLICY_CHANGED,), "the transducers' policies",
                                        check=check)
    else:
        rows = db.execute("SELECT * FROM transducer_policy WHERE transducer_id = ?", (transducer_id,)).fetchall()
        entries = chain.checked_entries(db, "target = ? AND action = ?", (transducer_id, POLICY_CHANGED),
                                        f"the policy of {transducer_id}", check=check)
    return _differences("transducer_policy", _vouched_policies(entries), _stored_policies(rows))


def _as_left_differences(db: sqlite3.Connection, transducer_id: str | None, *, check: bool = True) -> list[str]:
    if transducer_id is None:
        rows = db.execute("SELECT * FROM as_left").fetchall()
        entries = chain.checked_entries(db, "action = ?", (AS_LEFT_RECORDED,), "the adjustments", check=check)
    else:
        rows = db.execute("SELECT * FROM as_left WHERE transducer_id = ?", (transducer_id,)).fetchall()
        entries = chain.checked_entries(
            db, "action = ? AND target IN (SELECT id FROM runs WHERE transducer_id = ? "
                "UNION SELECT run_id FROM as_left WHERE transducer_id = ?)",
            (AS_LEFT_RECORDED, transducer_id, transducer_id), f"the adjustments of {transducer_id}", check=check)
    return _differences("as_left", _vouched_as_left(entries, transducer_id), _stored_as_left(rows))


def _refuse(found: list[str]) -> None:
    if found:
        raise RecordTamperedError("; ".join(found) + "; refused (station verify lists every such row)")


def record_mismatches(db: sqlite3.Connection) -> list[str]:
    """Every row of ``transducer_policy`` and ``as_left`` that differs from the audit chain's latest
    entry for it, or that has none, and every row the chain records that is gone (``/integrity``,
    ``station verify``, after the caller walked the chain: the entries' links are not checked again)."""
    return _policy_differences(db, None, check=False) + _as_left_differences(db, None, check=False)


def policy(store: Store, transducer_id: str) -> Policy:
    """A transducer's policy as the chain vouches for it (RecordTamperedError otherwise)."""
    with store.reading() as db:
        _refuse(_policy_differences(db, transducer_id))
        r = db.execute("SELECT * FROM transducer_policy WHERE transducer_id = ?", (transducer_id,)).fetchone()
    if r is None:
        return Policy(transducer_id)
    return Policy(transducer_id, {str(k): float(v) for k, v in json.loads(r["tolerances_json"]).items()},
                  r["interval_days"], bool(r["check_standard"]), r["updated"], r["updated_by"])


def check_transducers(store: Store) -> list[str]:
    """The check transducers (every policy compared with the chain first: RecordTamperedError)."""
    with store.reading() as db:
        _refuse(_policy_differences(db, None))
        rows = db.execute("SELECT transducer_id FROM transducer_policy WHERE check_standard = 1 "
                          "ORDER BY transducer_id").fetchall()
    return [r[0] for r in rows]


def put_policy(store: Store, p: Policy, by: str) -> Policy:
    """Set a transducer's policy (audited, before and after)."""
    _check(p.tolerances, p.interval_days)
    now = time.time()
    new = Policy(p.transducer_id, dict(p.tolerances), p.interval_days, p.check_standard, now, by)
    with store.transaction() as db:
        old = db.execute("SELECT tolerances_json, interval_days, check_standard FROM transducer_policy "
                         "WHERE transducer_id = ?", (p.transducer_id,)).fetchone()
        outside = _policy_differences(db, p.transducer_id, check=False)  # found now, and overwritten
        db.execute("INSERT OR REPLACE INTO transducer_policy (transducer_id, tolerances_json, interval_days, "
                   "check_standard, updated, updated_by) VALUES (?, ?, ?, ?, ?, ?)",
                   (new.transducer_id, json.dumps(new.tolerances), new.interval_days, int(new.check_standard),
                    now, by))
        audit.record(db, by, POLICY_CHANGED, p.transducer_id,
                     {"before": None if old is None else {"tolerances": json.loads(old[0]), "interval_days": old[1],
                                                          "check_standard": bool(old[2])},
                      "after": {"tolerances": new.tolerances, "interval_days": new.interval_days,
                                "check_standard": new.check_standard}}
                     | ({"found_changed_outside": outside} if outside else {}), at=now)
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
        outside = [d for d in _as_left_differences(db, a.transducer_id, check=False)
                   if d.startswith(f"as_left {a.run_id}/{a.parameter}:")]  # found now, and overwritten
        db.execute("INSERT OR REPLACE INTO as_left (run_id, transducer_id, parameter, value, unit, note, at, by) "
                   "VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                   (a.run_id, a.transducer_id, a.parameter, a.value, a.unit, a.note, a.at, a.by))
        audit.record(db, a.by, AS_LEFT_RECORDED, a.run_id,
                     {"transducer": a.transducer_id, "parameter": a.parameter, "value": a.value, "unit": a.unit,
                      "note": a.note} | ({"found_changed_outside": outside} if outside else {}), at=a.at)
    return a


def as_left_of(store: Store, transducer_id: str) -> dict[str, dict[str, AsLeft]]:
    """{run_id: {parameter: AsLeft}} of a transducer's adjustments, as the chain vouches for them
    (RecordTamperedError otherwise)."""
    out: dict[str, dict[str, AsLeft]] = {}
    with store.reading() as db:
        _refuse(_as_left_differences(db, transducer_id))
        rows = db.execute("SELECT * FROM as_left WHERE transducer_id = ?", (transducer_id,)).fetchall()
    for r in rows:
        out.setdefault(r["run_id"], {})[r["parameter"]] = AsLeft(**dict(r))
    return out
