"""The register: the transducers the lab calibrates and the reference standards its measurements
trace to (certificate, issuer, due date, the uncertainty each contributes), and which transducer is
mounted on the station now.

The configuration seeds it (``seed``): its transducer and its ``lab.standards`` are entered when not
there yet, and never overwrite what an administrator changed since.  Every change is audited in the
same transaction (``audit.record``).
"""

from __future__ import annotations

import datetime as dt
import json
import time
from dataclasses import asdict, dataclass, fields
from typing import Any

from station.config import StandardConfig, StationConfig, TransducerConfig
from station.errors import StationError
from station.lab import audit
from station.lab.store import Store
from station.lab.traceability import with_standards

MOUNTED_KEY = "mounted_transducer"


class RegisterError(StationError):
    """A register entry that does not exist, or a change it refuses."""


class UnknownEntryError(RegisterError):
    pass


class OverdueStandardError(RegisterError):
    """A reference standard in use is past its calibration due date (the run is refused)."""


@dataclass(frozen=True)
class Transducer:
    """A transducer under calibration: nominal data (N, V/N, kg) and who owns it."""

    id: str
    capacity_N: float
    sensitivity_V_per_N: float
    end_mass_kg: float | None = None
    end_mass_std_kg: float | None = None
    type: str = ""
    serial: str = ""
    owner: str = ""
    updated: float = 0.0
    updated_by: str = ""

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def to_config(self) -> TransducerConfig:
        """The configuration's transducer section (what the run's limits, recording and
        identification read)."""
        return TransducerConfig(**{k: v for k, v in asdict(self).items() if k not in ("updated", "updated_by")})

    @staticmethod
    def from_config(t: TransducerConfig) -> Transducer:
        return Transducer(**t.model_dump())


@dataclass(frozen=True)
class Standard:
    """A reference standard: ``due_date`` ISO date; ``uncertainty`` in ``uncertainty_unit``."""

    id: str
    kind: str
    certificate_id: str
    issuer: str
    due_date: str
    uncertainty: float
    uncertainty_unit: str
    description: str = ""
    in_use: bool = True
    updated: float = 0.0
    updated_by: str = ""

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def overdue(self, today: dt.date) -> bool:
        return dt.date.fromisoformat(self.due_date) < today

    @staticmethod
    def from_config(s: StandardConfig) -> Standard:
        d = s.model_dump()
        d["due_date"] = s.due_date.isoformat()
        return Standard(**d)


_T_COLS = tuple(f.name for f in fields(Transducer))
_S_COLS = tuple(f.name for f in fields(Standard))


# ---------------------------------------------------------------------------------------------- reads
def transducers(store: Store) -> list[Transducer]:
    return [Transducer(**r) for r in store.query("SELECT * FROM transducers ORDER BY id")]


def transducer(store: Store, transducer_id: str) -> Transducer:
    rows = store.query("SELECT * FROM transducers WHERE id = ?", (transducer_id,))
    if not rows:
        known = ", ".join(t.id for t in transducers(store)) or "none"
        raise UnknownEntryError(f"transducer {transducer_id!r} is not in the register (registered: {known}); "
                                "an administrator adds it (POST /register/transducers or `station register`)")
    return Transducer(**rows[0])


def standards(store: Store, *, in_use: bool | None = None) -> list[Standard]:
    q = "SELECT * FROM standards" + ("" if in_use is None else " WHERE in_use = ?") + " ORDER BY kind, id"
    rows = store.query(q, () if in_use is None else (int(in_use),))
    return [Standard(**{**r, "in_use": bool(r["in_use"])}) for r in rows]


def standard(store: Store, standard_id: str) -> Standard:
    rows = store.query("SELECT * FROM standards WHERE id = ?", (standard_id,))
    if not rows:
        raise UnknownEntryError(f"reference standard {standard_id!r} is not in the register")
    return Standard(**{**rows[0], "in_use": bool(rows[0]["in_use"])})


def mounted(store: Store) -> str | None:
    """The id of the transducer mounted on the station now (None: none chosen yet)."""
    rows = store.query("SELECT value FROM station_state WHERE key = ?", (MOUNTED_KEY,))
    return str(rows[0]["value"]) if rows else None


# ---------------------------------------------------------------------------------------------- writes
def put_transducer(store: Store, t: Transducer, by: str) -> Transducer:
    """Add or change a transducer (audited with the fields before and after)."""
    now = time.time()
    new = Transducer(**{**t.to_dict(), "updated": now, "updated_by": by})
    with store.transaction() as db:
        old = db.execute("SELECT * FROM transducers WHERE id = ?", (t.id,)).fetchone()
        db.execute(f"INSERT OR REPLACE INTO transducers ({', '.join(_T_COLS)}) VALUES "
                   f"({', '.join('?' for _ in _T_COLS)})", tuple(getattr(new, c) for c in _T_COLS))
        audit.record(db, by, audit.REGISTER_CHANGED, t.id,
                     {"entry": "transducer", "before": _clean(dict(old)) if old else None,
                      "after": _clean(new.to_dict())}, at=now)
    return new


def put_standard(store: Store, s: Standard, by: str) -> Standard:
    """Add or change a reference standard (audited with the fields before and after)."""
    dt.date.fromisoformat(s.due_date)  # ValueError on a bad date before anything is written
    now = time.time()
    new = Standard(**{**s.to_dict(), "updated": now, "updated_by": by})
    with store.transaction() as db:
        old = db.execute("SELECT * FROM standards WHERE id = ?", (s.id,)).fetchone()
        db.execute(f"INSERT OR REPLACE INTO standards ({', '.join(_S_COLS)}) VALUES "
                   f"({', '.join('?' for _ in _S_COLS)})",
                   tuple(int(v) if isinstance(v, bool) else v for v in (getattr(new, c) for c in _S_COLS)))
        audit.record(db, by, audit.REGISTER_CHANGED, s.id,
                     {"entry": "standard", "before": _clean(dict(old)) if old else None,
                      "after": _clean(new.to_dict())}, at=now)
    return new


def mount(store: Store, transducer_id: str, by: str) -> Transducer:
    """Make ``transducer_id`` (registered) the one mounted on the station."""
    t = transducer(store, transducer_id)
    now = time.time()
    with store.transaction() as db:
        old = db.execute("SELECT value FROM station_state WHERE key = ?", (MOUNTED_KEY,)).fetchone()
        db.execute("INSERT OR REPLACE INTO station_state (key, value, updated, updated_by) VALUES (?, ?, ?, ?)",
                   (MOUNTED_KEY, t.id, now, by))
        audit.record(db, by, audit.TRANSDUCER_MOUNTED, t.id, {"before": old[0] if old else None}, at=now)
    return t


def seed(store: Store, cfg: StationConfig) -> list[str]:
    """Enter the configuration's transducer and reference standards when not registered yet, and
    mount the transducer if none is; returns the ids entered."""
    added = []
    if not store.query("SELECT 1 FROM transducers WHERE id = ?", (cfg.transducer.id,)):
        put_transducer(store, Transducer.from_config(cfg.transducer), audit.SYSTEM)
        added.append(cfg.transducer.id)
    for sc in cfg.lab.standards:
        if not store.query("SELECT 1 FROM standards WHERE id = ?", (sc.id,)):
            put_standard(store, Standard.from_config(sc), audit.SYSTEM)
            added.append(sc.id)
    if mounted(store) is None:
        mount(store, cfg.transducer.id, audit.SYSTEM)
    return added


def _clean(d: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in d.items() if k not in ("updated", "updated_by")}


# ---------------------------------------------------------------------------------------------- a run's
@dataclass(frozen=True)
class RunSetup:
    """What a run uses from the register: the transducer's record, the standards in use, and the
    warnings about overdue standards the configuration lets through (``lab.overdue_standards: warn``)."""

    transducer: Transducer
    standards: tuple[Standard, ...]
    warnings: tuple[str, ...] = ()

    def config(self, cfg: StationConfig) -> StationConfig:
        """The station configuration with this transducer's record in place of the configured one and
        the uncertainties its standards' certificates state (``traceability.with_standards``)."""
        return with_standards(cfg.model_copy(update={"transducer": self.transducer.to_config()}),
                              [s.to_dict() for s in self.standards])

    def to_dict(self) -> dict[str, Any]:
        return {"transducer": self.transducer.to_dict(), "standards": [s.to_dict() for s in self.standards],
                "warnings": list(self.warnings)}

    def standards_json(self) -> str:
        return json.dumps([s.to_dict() for s in self.standards])


def run_setup(store: Store, cfg: StationConfig, transducer_id: str, standard_ids: list[str] | None,
              today: dt.date | None = None) -> RunSetup:
    """The register's records for a run: the transducer (any registered one) and the standards
    (those named, else those marked in use).  A standard past its due date refuses the run
    (:class:`OverdueStandardError`, naming it and its date) or, by configuration, warns."""
    t = transducer(store, transducer_id)
    chosen = [standard(store, s) for s in standard_ids] if standard_ids is not None else standards(store, in_use=True)
    today = today or dt.date.today()
    late = [s for s in chosen if s.overdue(today)]
    notes = tuple(f"reference standard {s.id} ({s.kind}, certificate {s.certificate_id}) was due for "
                  f"calibration on {s.due_date}" for s in late)
    if late and cfg.lab.overdue_standards == "refuse":
        raise OverdueStandardError("; ".join(notes) + ": the run is refused (recalibrate the standard and "
                                   "update the register, or choose another)")
    return RunSetup(t, tuple(chosen), notes)
