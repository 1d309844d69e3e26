"""The run manager: the daemon's service facade over one rig connection (``riglink``), the runs on
it (``runs``), the identification queue (``jobs``), the recordings and their renderings
(``artifacts``), the start-up recovery (``recovery``) and the health (``health``).

A run's Procedure is followed from the rig thread's own event loop (``rigthread.py``), apart from
the web side's (the daemon's rig carries it out in the rig process; an in-process rig on that
loop); processing and identification go to the worker
processes (``worker.py``), queued in the database so that a restart resumes them.  Nothing here
raises HTTP errors: the API layer maps the typed errors (``errors.py``, ``LimitError``) to statuses.
"""

from __future__ import annotations

import asyncio
import hashlib
import logging
import threading
import time
from pathlib import Path
from typing import Any

from station.errors import StationError
from station.lab import audit, certificates, chain, policy, register, users
from station.lab.issued import FOLDER
from station.lab.store import FINAL_STATES, RunRow, Store
from station.recording.repair import FolderCheck, check_folder
from station.service import worker
from station.service.artifacts import Artifacts
from station.service.changes import Changes
from station.service.db import DbAccess
from station.service.disk import RecordingsDisk
from station.service.errors import (
    EStopLatchedError,
    RigBusyError,
    RigUnavailableError,
    RunNotFoundError,
    RunStateError,
)
from station.service.health import database_state, health
from station.service.instance import InstanceLock
from station.service.jobs import MAX_JOB_ATTEMPTS, JobQueue
from station.service.lab import LabService
from station.service.latch import EStopLatch
from station.service.logins import LoginThrottle, PasswordPool
from station.service.recovery import recover
from station.service.riglink import RigConnector, RigLink, default_connector
from station.service.runs import AckReport, LiveRun, Runs, StopReport
from station.service.settings import ServiceSettings

__all__ = [
    "MAX_JOB_ATTEMPTS",
    "AckReport",
    "EStopLatchedError",
    "LiveRun",
    "RigBusyError",
    "RigUnavailableError",
    "RunManager",
    "RunNotFoundError",
    "RunStateError",
    "StopReport",
    "is_final",
]

log = logging.getLogger(__name__)

TOKEN_USER = "admin"  # the configured token (STATION_TOKEN, service.token) acts for this administrator


class RunManager:
    """Everything the API needs, for the daemon's lifetime: ``start`` then ``close``."""

    def __init__(self, settings: ServiceSettings, *, connector: RigConnector = default_connector) -> None:
        self.settings = settings
        self.cfg = settings.config
        # one daemon per recordings folder: held before the database, the recovery or a device is touched
        self.instance = InstanceLock.acquire(settings.recordings_dir, "station serve", host=settings.host)
        try:
            self.store = Store(settings.database)
        except BaseException:
            self.instance.release()
            raise
        self.db = DbAccess(self.store)
        self.closing = asyncio.Event()
        self.changes = Changes(self.closing)
        self.link = RigLink(self.cfg, settings.sim, connector)
        self.identify_pool = worker.WorkerPool("identification", settings.workers)
        self.render_pool = worker.WorkerPool("render", 1)
        self.latch = EStopLatch(self.db)
        self.disk = RecordingsDisk(settings.recordings_dir, int(self.cfg.station.min_free_mb * 2**20))
        self.runs = Runs(self.cfg, settings.recordings_dir, self.db, self.link, self.changes, self.closing,
                         self._on_acquired, self.latch, self.disk)
        self.artifacts = Artifacts(settings.recordings_dir, self.render_pool, self.runs.get, self.db)
        self.jobs = JobQueue(self.db, self.identify_pool, settings.workers,
                             self.artifacts, self.changes, self.closing)
        self.artifacts.busy = self.jobs.identifying
        self._warm: asyncio.Task[None] | None = None
        self.started_at = time.time()
        self.folder_check = FolderCheck()
        self.chain: chain.ChainState | None = None  # the audit chain as last walked (start-up, /integrity, issue)
        self.signing_key: Any = None  # the lab's Ed25519 key (station.lab.signing), loaded at start
        self.signing_problem = ""  # why there is none
        self.logins = LoginThrottle(save=lambda key, n, until: self.db.post(
            lambda s: users.keep_lock(s, key, n, until)))
        self.password_pool = PasswordPool()
        self.lab = LabService(self.db, self.logins, self.password_pool, self.cfg.lab.session_minutes,
                              self.cfg.lab.overdue_standards, settings.recordings_dir, self.artifacts,
                              password_n=settings.password_n)

    # ------------------------------------------------------------------ life cycle
    async def start(self) -> None:
        self.runs.loop_thread = threading.get_ident()
        self.runs.web_loop = asyncio.get_running_loop()
        self.folder_check = await asyncio.to_thread(check_folder, self.settings.recordings_dir)
        self.recover()  # before anything is served: nothing else waits on the loop yet
        self.seed_lab()
        self.chain = await asyncio.to_thread(self._walk_chain)
        await asyncio.to_thread(self._load_signing_key)
        if not self.chain.ok:
            log.error("%s; certificates are refused until an administrator records a reviewed exception",
                      self.chain.describe())
        self.latch.load()
        self.db.start()
        await asyncio.to_thread(self.disk.ensure_reserve)
        await self.link.connect()
        self.jobs.start()
        if self.cfg.service.render_at_start:
            self._warm = asyncio.create_task(self._warm_render_pool(), name="render-warm-up")

    async def _warm_render_pool(self) -> None:
        """Start the render worker and load the plotting modules early (the first results page
        would otherwise wait for a process start and the plotting imports)."""
        try:
            await self.artifacts.render_pool.run(worker.warm_up_job)
        except Exception as exc:  # not fatal: retried on the first request
            log.warning("render worker warm-up failed: %s", exc)

    async def close(self) -> None:
        """Shut down: a run on the rig is stopped (motor first) and marked interrupted; running
        identification jobs may finish (up to 30 s), queued ones stay queued for the next start."""
        tasks = self.begin_shutdown()
        if tasks:
            _, pending = await asyncio.wait(tasks, timeout=15.0)
            if pending:
                log.error("a run did not end within 15 s of the shutdown; emergency stop")
                await self.link.emergency_stop()
        await self.link.stop_motor()
        if self._warm is not None:
            self._warm.cancel()
        await self.jobs.stop_dispatcher()
        await asyncio.to_thread(self.identify_pool.shutdown, 30.0)
        await asyncio.to_thread(self.render_pool.shutdown, 30.0)  # it may be writing a discrepancy result
        self.jobs.cancel_jobs()
        await self.link.close()
        await asyncio.to_thread(self.db.close, 5.0)
        self.password_pool.close()
        await asyncio.to_thread(self.store.close)  # after the writer: it may still wait on a lock
        self.instance.release()

    def begin_shutdown(self) -> list[asyncio.Task[None]]:
        """First step of a shutdown, at once (also from the signal handler): live streams end, the run
        on the rig is cancelled (its procedure stops the motor and closes the recording)."""
        self.closing.set()
        self.changes.bump_all()
        return self.runs.cancel_all("the station daemon was shut down during the run")

    def recover(self) -> dict[str, list[str]]:
        """Start-up: runs cut off by the end of the previous daemon become ``interrupted`` (their
        partial recordings recovered), jobs left running go back to the queue."""
        return recover(self.store, self.settings.recordings_dir, MAX_JOB_ATTEMPTS)

    def seed_lab(self) -> None:
        """Start-up: the configuration's transducer and standards into the register (when missing),
        the user the configured token acts for, the login lock-outs kept, and the record of a
        database upgrade."""
        register.seed(self.store, self.cfg)
        users.ensure_user(self.store, TOKEN_USER, users.Role.ADMIN)
        self.logins.load(users.kept_locks(self.store))  # a restart lifts no lock-out
        if self.store.upgraded_from is not None:
            audit.append(self.store, audit.SYSTEM, audit.DATABASE_UPGRADED, str(self.settings.database.name),
                         {"from_schema": self.store.upgraded_from, "backup": str(self.store.backup)})

    async def issue_certificate(self, run_id: str, approver: users.User, prepared_by: str | None,
                                replaces: str | None, reason: str) -> dict[str, Any]:
        """Issue the run's certificate by the lab's rules (``station.lab.certificates``): the audit
        chain intact (walked now), the rules, the run's files as the chain vouches for them, a number
        from the database's sequence, the files written in the render worker, then one
        ``certificate.issued`` entry naming the number and each file's SHA-256.  Any refusal writes
        one ``certificate.refused`` entry and nothing else."""
        row = await self.runs.get(run_id)
        number: str | None = None
        try:
            (await self.verify_chain()).require()
            pub = self.public_key()
            signature = {"algorithm": pub["algorithm"], "key_fingerprint": pub["fingerprint"]}
            if row.state != "completed":
                raise RunStateError(f"run {run_id} is {row.state}: only a completed run has a certificate")
            await self.check_not_held(row)
            prepared = await self.db.read(lambda s: certificates.check_issue(
                s, run_id=run_id, operator=row.operator, approver=approver, prepared_by=prepared_by,
                replaces=replaces, reason=reason))
            await self.artifacts.guard(row, required=True)
            prefix, year = self.cfg.certificate.number_prefix, time.gmtime().tm_year
            folder = self.settings.recordings_dir / FOLDER
            number = await self.db.call(lambda s: certificates.take_number(s, prefix, year, run_id, folder))
            roles = {prepared: "operator", approver.name: str(approver.role)}
            head = await self.db.read(lambda s: chain_head(s))
            out = await self.artifacts.issue_certificate(run_id, prepared, approver.name, roles, replaces, reason,
                                                         number, {**signature, "file": f"{number}.sig"})
            out["hashes"]["sig"] = await asyncio.to_thread(self._sign, number, out["record"], out["hashes"], head)
        except Exception as exc:  # the refusal's one entry, whatever refused it
            why = str(exc) if isinstance(exc, StationError) else f"{type(exc).__name__}: {exc}"
            await self.db.call(lambda s: certificates.record_refusal(s, approver.name, run_id, why, number))
            raise
        record = out["record"]
        await self.db.call(lambda s: certificates.record_issue(s, approver.name, run_id, record, out["hashes"], head))
        return await self.db.read(lambda s: certificates.one(s, record["number"]))

    async def withdraw_certificate(self, who: users.User, number: str, reason: str) -> dict[str, Any]:
        """Withdraw a certificate in force (an approver, with the reason; an audit entry)."""
        return await self.db.call(lambda s: certificates.withdraw(s, who, number, reason))

    async def approve(self, run_id: str, approver: users.User, note: str) -> dict[str, Any]:
        """The second person's approval of a completed run for its certificate: an approver who did
        not start the run, on a recording whose SHA-256 is the one stored when it was closed."""
        if not approver.may(users.Permission.APPROVE):
            raise users.ForbiddenError(f"user {approver.name} ({approver.role}) may not approve; an approver does")
        row = await self.runs.get(run_id)
        if row.state != "completed":
            raise RunStateError(f"run {run_id} is {row.state}: only a completed run can be approved")
        if row.operator == approver.name:
            raise users.ForbiddenError(f"run {run_id} was started by {approver.name}: a second person approves it")
        await self.check_not_held(row)
        sha = await self.artifacts.verified(row, required=True)
        details = {"note": note, "sha256": sha, "operator": row.operator, "recording": row.recording}
        entry = await self.db.call(lambda store: audit.append(store, approver.name, audit.CERTIFICATE_APPROVED,
                                                              run_id, details))
        return {"run_id": run_id, "approved_by": approver.name, "audit_id": entry, **details}

    async def check_not_held(self, row: RunRow) -> None:
        """Refuse (RunStateError) to approve a run made since the check transducer's last good point
        while its newest check is out of control (station.lab.history.check_hold)."""
        from station.lab.history import check_hold

        hold = await self.db.read(lambda s: check_hold(s, self.settings.recordings_dir))
        if hold is not None and row.created > hold.since:
            raise RunStateError(f"run {row.id} is held for review: {hold.reason}")

    def key_path(self) -> Path:
        """The lab's private key file (``lab.signing_key``, relative to the database's folder)."""
        p = Path(self.cfg.lab.signing_key).expanduser()
        return p if p.is_absolute() else self.settings.database.parent / p

    def _load_signing_key(self) -> None:
        """Start-up: the lab's key, created (0600, an audit entry with its fingerprint) on the first
        start; a key that cannot be used is logged and every issue refused with the reason."""
        from station.lab import signing

        path = self.key_path()
        try:
            if not path.exists():
                key, _ = signing.init_key(path)
                audit.append(self.store, audit.SYSTEM, audit.KEY_CREATED, "signing-key",
                             {"fingerprint": signing.fingerprint(key.public_key()), "path": str(path)})
                log.warning("signing key created at %s (back it up: docs/operations.md)", path)
            self.signing_key = signing.load_key(path)
        except (StationError, OSError, ValueError) as exc:
            self.signing_problem = str(exc)
            log.error("no usable signing key: %s; certificates are refused", exc)

    def public_key(self) -> dict[str, str]:
        from station.lab import signing

        if self.signing_key is None:
            raise signing.SigningError(self.signing_problem or "no signing key")
        pub = self.signing_key.public_key()
        return {"algorithm": signing.ALGORITHM, "fingerprint": signing.fingerprint(pub),
                "public_key": signing.public_pem(pub)}

    def _sign(self, number: str, record: dict[str, Any], hashes: dict[str, str], head: tuple[int, str]) -> str:
        """Write ``<number>.sig`` (once): the statement of the issued files signed with the lab's key;
        returns its SHA-256."""
        from station.lab import signing

        files = {f"{number}.{ext}": hashes[ext] for ext in ("html", "pdf", "xml")}
        doc = signing.statement(number, record["sha256"]["content"], files, head,
                                signing.fingerprint(self.signing_key.public_key()))
        data = signing.sign(self.signing_key, doc)
        signing.write_new(self.settings.recordings_dir / FOLDER / f"{number}.sig", data, 0o644)
        return hashlib.sha256(data).hexdigest()

    # ------------------------------------------------------------------ the audit chain
    def _walk_chain(self) -> chain.ChainState:
        with self.store.reading() as db:
            return chain.verify_chain(db)

    async def verify_chain(self) -> chain.ChainState:
        """Walk the audit chain now (in the read pool) and keep the result for /health."""
        self.chain = await self.db.read(lambda s: self._walk_chain(), timeout_s=120.0)
        return self.chain

    async def integrity(self) -> dict[str, Any]:
        """The chain walked and every file it vouches for compared (``/integrity``)."""
        def walk(store: Store) -> tuple[chain.ChainState, dict[str, str], list[str]]:
            with store.reading() as db:
                return chain.verify_chain(db), chain.latest_files(db), policy.record_mismatches(db)
        state, latest, records = await self.db.read(walk, timeout_s=120.0)
        self.chain = state
        # the files are hashed outside the database's read lock (other reads go on meanwhile)
        return await asyncio.to_thread(chain.integrity_report, state, latest, self.settings.recordings_dir, records)

    async def record_exception(self, admin: users.User, entry: int, reason: str) -> dict[str, Any]:
        """An administrator's reviewed exception for a broken link of the chain (itself an entry):
        the break stays listed, it no longer blocks issuing."""
        if not admin.may(users.Permission.ADMIN):
            raise users.ForbiddenError(f"user {admin.name} ({admin.role}) may not record an exception; an admin does")
        state = await self.verify_chain()
        if not any(b.id == entry for b in state.breaks):
            raise RunStateError(f"the audit chain has no broken link at entry {entry} ({state.describe()})")
        await self.db.call(lambda s: audit.append(s, admin.name, audit.AUDIT_EXCEPTION, "audit",
                                                  {"entry": entry, "reason": reason}))
        return (await self.verify_chain()).to_dict()

    def _on_acquired(self, run_id: str) -> None:
        self.jobs.wake()

    # ------------------------------------------------------------------ health
    async def health(self) -> dict[str, Any]:
        act = self.runs.active()
        out = health(self.link, await database_state(self.db), self.identify_pool, self.latch, self.disk,
                     workers=self.settings.workers, sim=self.settings.sim,
                     active_run=act.row.id if act else None, started_at=self.started_at,
                     unrecorded=self.jobs.unrecorded)
        out["recordings"] = self.folder_check.to_dict()  # what the start-up check repaired or could not read
        if self.chain is not None:
            out["audit_chain"] = {"ok": self.chain.ok, "detail": self.chain.describe()}
            if not self.chain.ok:
                out["status"] = "degraded"
        return out


def chain_head(store: Store) -> tuple[int, str]:
    """(id, hash) of the audit chain's newest entry."""
    with store.reading() as db:
        return chain.head(db)


def is_final(state: str) -> bool:
    return state in FINAL_STATES
