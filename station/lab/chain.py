"""The audit trail as a hash chain, and the files it vouches for.

Every entry holds the hash of the entry before it (``prev``), the SHA-256 of the files it concerns
(``files``: a path relative to the recordings folder -> its SHA-256, or None for a file that is gone
on purpose) and its own hash over all of that (``hash``).  Rewriting, deleting or inserting an entry
breaks a link; a file changed outside the station no longer has the hash its latest entry gave it.

* :func:`entry_hash` is the rule (documented in ``docs/operations.md``, so that anyone can check a
  trail with sqlite3 and a SHA-256 tool);
* :func:`verify_chain` walks the whole trail (start-up, ``/integrity``, before a certificate is
  issued, ``station verify``) and names the first broken link; a break an administrator has reviewed
  (an ``audit.exception`` entry naming it) is listed but no longer blocks;
* :func:`expected_files` is what a run's files must be (the chain's latest word on each); the
  entries it relies on are checked on the way (their own hash and their link to the entry before);
* :func:`check_files` compares files on disk with it.  The daemon calls it before it reads a
  recording, a results file or a certificate (``service/artifacts.Artifacts.guard``).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import sqlite3
from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from station.lab.integrity import RecordingTamperedError, sha256_file

GENESIS = "0" * 64  # the ``prev`` of the first entry
EXCEPTION = "audit.exception"  # an administrator's reviewed exception for a broken link
RESULTS_SUFFIX = ".results"
TMP_MARK = ".tmp-"  # results being written (station.recording.stored): not yet part of anything


class ChainBrokenError(RecordingTamperedError):
    """The audit trail's chain is broken where no reviewed exception covers it (409)."""


def entry_hash(row: Mapping[str, Any]) -> str:
    """SHA-256 (hex) of an entry: the canonical JSON (sorted keys, no spaces) of its id, time (the
    REAL as Python's ``repr``), who, action, target, details and files (both as the stored JSON text)
    and the previous entry's hash."""
    doc = {"id": int(row["id"]), "at": repr(float(row["at"])), "who": row["who"], "action": row["action"],
           "target": row["target"], "details": row["details"], "files": row["files"], "prev": row["prev"]}
    return hashlib.sha256(json.dumps(doc, sort_keys=True, separators=(",", ":"),
                                     ensure_ascii=False).encode()).hexdigest()


def head(db: sqlite3.Connection) -> tuple[int, str]:
    """(id, hash) of the newest entry ((0, GENESIS) for an empty trail)."""
    r = db.execute("SELECT id, hash FROM audit ORDER BY id DESC LIMIT 1").fetchone()
    return (0, GENESIS) if r is None else (int(r[0]), str(r[1]))


@dataclass(frozen=True)
class Break:
    """A broken link: the entry where the chain stops holding, and why."""

    id: int
    reason: str
    excepted_by: int | None = None  # the reviewed exception's entry id, if any

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class ChainState:
    """The result of walking the trail: entries checked, the head, every break (oldest first)."""

    entries: int
    head_id: int
    head: str
    breaks: list[Break] = field(default_factory=list)

    @property
    def open_breaks(self) -> list[Break]:
        return [b for b in self.breaks if b.excepted_by is None]

    @property
    def ok(self) -> bool:
        return not self.open_breaks

    def describe(self) -> str:
        if self.ok:
            note = f" ({len(self.breaks)} reviewed exception(s))" if self.breaks else ""
            return f"audit chain intact: {self.entries} entries, head {self.head_id} {self.head[:16]}...{note}"
        b = self.open_breaks[0]
        return (f"audit chain broken at entry {b.id}: {b.reason}"
                + (f" ({len(self.open_breaks) - 1} more break(s) after it)" if len(self.open_breaks) > 1 else ""))

    def to_dict(self) -> dict[str, Any]:
        return {"ok": self.ok, "entries": self.entries, "head_id": self.head_id, "head": self.head,
                "breaks": [b.to_dict() for b in self.breaks], "detail": self.describe()}

    def require(self) -> None:
        """ChainBrokenError unless intact (or every break reviewed)."""
        if not self.ok:
            raise ChainBrokenError(self.describe() + "; nothing is issued until an administrator has reviewed "
                                   "it (station verify --except ENTRY --reason ...)")


def _rows(db: sqlite3.Connection, sql: str, args: Iterable[Any] = ()) -> list[dict[str, Any]]:
    cur = db.execute(sql, tuple(args))
    names = [d[0] for d in cur.description]
    return [dict(zip(names, r, strict=True)) for r in cur.fetchall()]


def _link_reason(row: Mapping[str, Any], prev: str) -> str | None:
    if row["prev"] != prev:
        return "its link to the entry before does not match (an entry before it was changed, deleted or inserted)"
    if row["hash"] != entry_hash(row):
        return (f"its content does not match its hash (entry {row['id']}, {row['action']} by {row['who']!r}, "
                "was changed)")
    return None


def verify_chain(db: sqlite3.Connection) -> ChainState:
    """Walk the trail from its first entry (module docstring).  After a break the walk goes on from
    the broken entry's stored hash, so that every break is named, not just the first."""
    prev, breaks, n, last = GENESIS, list[Break](), 0, 0
    excepted: dict[int, int] = {}
    cur = db.execute("SELECT id, at, who, action, target, details, files, prev, hash FROM audit ORDER BY id")
    names = [d[0] for d in cur.description]
    for raw in cur:
        row = dict(zip(names, raw, strict=True))
        n += 1
        if int(row["id"]) != last + 1:  # ids are never reused nor skipped (AUTOINCREMENT, audit.record)
            breaks.append(Break(last + 1, f"entries {last + 1} to {int(row['id']) - 1} are missing (deleted)"))
            prev = str(row["prev"])  # the missing entries are the break; this one's own hash is still checked
        why = _link_reason(row, prev)
        if why is not None:
            breaks.append(Break(int(row["id"]), why))
        if row["action"] == EXCEPTION and why is None:
            with contextlib.suppress(ValueError, TypeError, AttributeError):
                excepted.setdefault(int(json.loads(row["details"]).get("entry")), int(row["id"]))
        prev, last = str(row["hash"]), int(row["id"])
    seq = db.execute("SELECT seq FROM sqlite_sequence WHERE name = 'audit'").fetchone()
    if seq is not None and int(seq[0]) > last:
        breaks.append(Break(last + 1, f"entries {last + 1} to {int(seq[0])} are missing (deleted from the end)"))
    return ChainState(n, last, prev, [Break(b.id, b.reason, excepted.get(b.id)) for b in breaks])


def broken_among(db: sqlite3.Connection, ids: Iterable[int]) -> list[int]:
    """Of the entries ``ids`` (a page of the trail), those that do not hold: the content does not
    match the hash, or the link does not match the entry before (for entries deleted before one,
    the first missing id is named).  One indexed look-up per entry: cheap enough for every page."""
    out: set[int] = set()
    for i in sorted(set(ids)):
        rows = _rows(db, "SELECT id, at, who, action, target, details, files, prev, hash FROM audit WHERE id = ?", (i,))
        if not rows:
            continue
        before = db.execute("SELECT id, hash FROM audit WHERE id < ? ORDER BY id DESC LIMIT 1", (i,)).fetchone()
        b_id, b_hash = (0, GENESIS) if before is None else (int(before[0]), str(before[1]))
        if b_id != i - 1:  # the gap is the break; this entry's own content is still checked
            out.add(b_id + 1)
            b_hash = str(rows[0]["prev"])
        if _link_reason(rows[0], b_hash) is not None:
            out.add(i)
    return sorted(out)


# ------------------------------------------------------------------------------------------- files
def run_files(run_id: str, recording: str | None) -> tuple[str, str]:
    """(recording key, results prefix) of a run's files in the chain (paths in the recordings folder)."""
    rec = recording or f"{run_id}.h5"
    stem = rec[: -len(".h5")] if rec.endswith(".h5") else rec
    return rec, f"{stem}{RESULTS_SUFFIX}/"


def results_hashes_names(recording: Path) -> list[str]:
    """Every results file beside a recording (not those being written), by its path in the
    recordings folder."""
    _, prefix = run_files("", recording.name)
    folder = recording.parent / prefix.rstrip("/")
    if not folder.is_dir():
        return []
    return [prefix + p.name for p in sorted(folder.iterdir())
            if TMP_MARK not in p.name and not p.name.startswith(".") and not p.is_dir()]


def results_hashes(recording: Path) -> dict[str, str]:
    """SHA-256 of every results file beside a recording, keyed by its path in the recordings folder."""
    return {k: sha256_file(recording.parent / k) for k in results_hashes_names(recording)}


def seal(before: Mapping[str, str | None], now: Mapping[str, str], prefix: str) -> dict[str, str | None]:
    """The ``files`` of an entry that vouches for a folder's files as they are now: each present
    file's hash, None for one the chain knew under ``prefix`` that is no longer there."""
    gone = {k: None for k, v in before.items() if k.startswith(prefix) and v is not None and k not in now}
    return {**gone, **now}


def expected_files(db: sqlite3.Connection, target: str, *, check: bool = True) -> dict[str, str]:
    """The files the chain vouches for under ``target`` (a run id): its latest hash of each.  Every
    entry relied on is checked (its hash, its link): ChainBrokenError naming the entry otherwise
    (``check`` False: not checked, for a writer that only needs to know what was vouched for)."""
    out: dict[str, str] = {}
    for row in checked_entries(db, "target = ? AND files != '{}'", (target,), f"run {target}'s files", check=check):
        _fold(out, row["files"])
    return out


def checked_entries(db: sqlite3.Connection, where: str, args: Iterable[Any], what: str, *,
                    check: bool = True) -> list[dict[str, Any]]:
    """The entries matching ``where`` (an SQL condition on the audit table), oldest first, each
    checked on the way (its own hash, its link to the entry before): ChainBrokenError naming the
    entry and ``what`` it vouches for otherwise."""
    rows = _rows(db, f"SELECT id, at, who, action, target, details, files, prev, hash FROM audit WHERE {where} "
                     "ORDER BY id", args)
    for row in rows if check else ():
        before = db.execute("SELECT hash FROM audit WHERE id < ? ORDER BY id DESC LIMIT 1", (row["id"],)).fetchone()
        why = _link_reason(row, GENESIS if before is None else str(before[0]))
        if why is not None:
            raise ChainBrokenError(f"audit entry {row['id']} vouching for {what}: {why}")
    return rows


def _fold(out: dict[str, str], files: str) -> None:
    """An entry's word on its files over what earlier entries said (None: the file is gone)."""
    for k, v in json.loads(files).items():
        if v is None:
            out.pop(k, None)
        else:
            out[k] = str(v)


def check_files(root: Path, expected: Mapping[str, str], present: Iterable[str], what: str,
                hash_of: Any = sha256_file) -> None:
    """Compare files on disk with the chain: every expected one present with its hash, nothing
    present the chain does not know.  RecordingTamperedError naming every file that differs."""
    bad = []
    present = set(present)
    for key, sha in sorted(expected.items()):
        p = root / key
        if not p.is_file():
            bad.append(f"{key} is missing")
            continue
        actual = hash_of(p)
        if actual != sha:
            bad.append(f"{key} was changed (SHA-256 {actual[:16]}... instead of {sha[:16]}...)")
    bad += [f"{key} is not in the audit trail (added outside the station)" for key in sorted(present - set(expected))]
    if bad:
        raise RecordingTamperedError(f"{what}: " + "; ".join(bad) + "; refused")


def latest_files(db: sqlite3.Connection) -> dict[str, str]:
    """Every file the chain vouches for, with its latest entry's SHA-256."""
    latest: dict[str, str] = {}
    for row in _rows(db, "SELECT files FROM audit WHERE files != '{}' ORDER BY id"):
        _fold(latest, row["files"])
    return latest


def file_mismatches(latest: Mapping[str, str], root: Path) -> list[str]:
    """Every file of ``latest`` (:func:`latest_files`) that is missing or differs, and every results
    or certificate file the chain does not know (``station verify``).  Reads files, not the database."""
    out = []
    for key, sha in sorted(latest.items()):
        p = root / key
        if not p.is_file():
            out.append(f"{key}: missing")
        elif (actual := sha256_file(p)) != sha:
            out.append(f"{key}: SHA-256 {actual} instead of {sha}")
    sealed_dirs = {k.split("/", 1)[0] for k in latest if "/" in k}
    for d in sorted(sealed_dirs):
        folder = root / d
        if folder.is_dir():
            for p in sorted(folder.iterdir()):
                key = f"{d}/{p.name}"
                if p.is_file() and key not in latest and TMP_MARK not in p.name and not p.name.startswith(".") \
                        and (d.endswith(RESULTS_SUFFIX) or p.suffix in (".html", ".pdf", ".xml", ".json", ".sig")):
                    out.append(f"{key}: not in the audit trail")
    return out


def integrity_report(state: ChainState, latest: Mapping[str, str], root: Path,
                     records: list[str] | None = None) -> dict[str, Any]:
    """The whole check (``/integrity``, ``station verify``): the chain as walked (``state``), every
    file it vouches for (``latest``) compared, and the rows of the lab's tables that differ from it
    (``records``, ``station.lab.policy.record_mismatches``); ``ok`` only when all hold."""
    files, records = file_mismatches(latest, root), list(records or [])
    detail = state.describe() + (f"; {len(files)} file(s) differ from the audit trail: " + "; ".join(files)
                                 if files else "; every file it vouches for is as recorded")
    if records:
        detail += f"; {len(records)} row(s) of the lab's tables differ from it: " + "; ".join(records)
    return {**state.to_dict(), "ok": state.ok and not files and not records, "chain_ok": state.ok,
            "files": files, "records": records, "detail": detail}


# ------------------------------------------------------------------------------------------- schema
COLUMNS = {"prev": "TEXT NOT NULL DEFAULT ''", "hash": "TEXT NOT NULL DEFAULT ''",
           "files": "TEXT NOT NULL DEFAULT '{}'"}


def upgrade(db: sqlite3.Connection) -> int:
    """Add the chain's columns to an older trail and chain its entries as they are (inside the
    caller's transaction; the append-only trigger is lifted for that and put back).  Returns how
    many entries were chained."""
    have = {r[1] for r in db.execute("PRAGMA table_info(audit)").fetchall()}
    for name, definition in COLUMNS.items():
        if name not in have:
            db.execute(f"ALTER TABLE audit ADD COLUMN {name} {definition}")
    todo = db.execute("SELECT count(*) FROM audit WHERE hash = ''").fetchone()[0]
    if not todo:
        return 0
    trig = db.execute("SELECT sql FROM sqlite_master WHERE type = 'trigger' AND name = 'audit_no_update'").fetchone()
    db.execute("DROP TRIGGER IF EXISTS audit_no_update")
    prev = GENESIS
    for row in _rows(db, "SELECT id, at, who, action, target, details, files, prev, hash FROM audit ORDER BY id"):
        if row["hash"] == "":
            row["prev"] = prev
            row["hash"] = entry_hash(row)
            db.execute("UPDATE audit SET prev = ?, hash = ? WHERE id = ?", (row["prev"], row["hash"], row["id"]))
        prev = row["hash"]
    if trig is not None:
        db.execute(trig[0])
    return int(todo)
