"""The identification queue: jobs are rows in the database (a restart resumes them); a dispatcher
hands them to the worker processes, retries a job whose worker died, and notes the outcome.

An outcome the database refuses to take (its disk full, a lock held elsewhere) is not dropped: it
is logged, kept in memory and shown in ``/health`` (``worker.unrecorded``), and written again every
few seconds until the database takes it.  The job stays ``running`` in the database meanwhile, so a
daemon stopped before then runs it again at its next start.  The database is reached through
``db.py``, never from the event loop."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

from station.lab import audit
from station.lab.store import Store
from station.run.methods import SETTLED, MethodOutcome, write_outcomes
from station.service import worker
from station.service.artifacts import Artifacts
from station.service.changes import Changes
from station.service.db import DbAccess
from station.service.errors import DatabaseBusyError

log = logging.getLogger(__name__)

MAX_JOB_ATTEMPTS = 3
RECORD_RETRY_S = 5.0  # how often an outcome the database refused is written again
MAX_TRACKED_OUTCOMES = 256  # runs whose method outcomes the daemon keeps in memory (RunStatus.methods)


class JobQueue:
    """Runs identification jobs on ``pool`` (``workers`` at a time; 0: jobs wait in the queue)."""

    def __init__(self, db: DbAccess, pool: worker.WorkerPool, workers: int,
                 artifacts: Artifacts, changes: Changes, closing: asyncio.Event) -> None:
        self.db = db
        self.pool = pool
        self.workers = workers
        self.artifacts = artifacts
        self.changes = changes
        self.closing = closing
        self._wake = asyncio.Event()
        self._dispatcher: asyncio.Task[None] | None = None
        self._tasks: set[asyncio.Task[None]] = set()
        self.unrecorded: dict[str, str] = {}  # run id -> the outcome the database has not taken yet, and why
        # run id -> every listed method's outcome, for the runs this daemon identified (newest kept)
        self.outcomes: OrderedDict[str, list[MethodOutcome]] = OrderedDict()

    def start(self) -> None:
        self._dispatcher = asyncio.create_task(self._dispatch(), name="job-dispatcher")

    def wake(self) -> None:
        self._wake.set()

    async def stop_dispatcher(self) -> None:
        if self._dispatcher is not None:
            self._dispatcher.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._dispatcher

    def cancel_jobs(self) -> None:
        for t in list(self._tasks):  # their jobs were allowed to finish or were stopped before
            t.cancel()

    async def _dispatch(self) -> None:
        slots = asyncio.Semaphore(max(1, self.workers))
        while not self.closing.is_set():
            if self.workers == 0:
                await self.closing.wait()
                return
            await slots.acquire()
            try:
                job = await self.db.call(lambda store: store.claim_job())
            except DatabaseBusyError as exc:
                log.warning("identification queue: %s", exc)
                job = None
            if job is None:
                slots.release()
                self._wake.clear()
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._wake.wait(), 5.0)
                continue
            t = asyncio.create_task(self._run_job(job.id, job.run_id, job.attempts), name=f"job-{job.id}")
            self._tasks.add(t)

            def done(t: asyncio.Task[None]) -> None:
                self._tasks.discard(t)
                slots.release()
            t.add_done_callback(done)

    async def _run_job(self, job_id: int, run_id: str, attempts: int) -> None:
        try:
            await self._run_job_once(job_id, run_id, attempts)
        except asyncio.CancelledError:
            raise
        except Exception:  # never a silent end of a job task
            log.exception("run %s: identification job %d ended unexpectedly", run_id, job_id)

    async def _run_job_once(self, job_id: int, run_id: str, attempts: int) -> None:
        try:
            row = await self.db.read(lambda store: store.get_run(run_id), timeout_s=60.0)
        except DatabaseBusyError as exc:
            log.warning("run %s: identification put back in the queue: %s", run_id, exc)
            why = str(exc)
            await self._record(run_id, "put back in the queue", lambda store: store.finish_job(job_id, "queued", why))
            return
        if row is None or not row.recording:
            await self._record(run_id, "the job has no run or recording",
                               lambda store: store.finish_job(job_id, "failed", "run or recording unknown"))
            return
        path = self.artifacts.recording_path(row)
        self._set_row(run_id, message=f"identifying (attempt {attempts})")  # written when the database can
        try:
            async with self.artifacts.file_lock(run_id):
                out = await self.pool.run(worker.identify_job, str(path))
        except asyncio.CancelledError:
            raise
        except (worker.WorkerCrashed, OSError) as exc:
            if attempts < MAX_JOB_ATTEMPTS and not self.closing.is_set():
                log.warning("run %s: identification attempt %d: %s; queued again", run_id, attempts, exc)
                err = str(exc)
                if await self._record(run_id, f"attempt {attempts} failed ({err}); to be queued again",
                                      lambda store: store.finish_job(job_id, "queued", err)):
                    await asyncio.sleep(1.0)
                    self._wake.set()
                return
            if self.closing.is_set():
                return  # left running in the database: requeued at the next start
            await self._job_failed(job_id, run_id, f"{type(exc).__name__}: {exc}")
            return
        except Exception as exc:
            await self._job_failed(job_id, run_id, f"{type(exc).__name__}: {exc}")
            return
        done = f"identified ({out['method']}, {out['model']}) in {out['wall_s']:.1f} s"
        outcomes = [MethodOutcome.from_dict(d) for d in out.get("outcomes", [])]
        rest = len(outcomes) - 1
        later = f"; {rest} more method{'s' if rest > 1 else ''} to follow" if rest > 0 else ""
        # the primary shows as done (event 'result') only once the run is completed in the database;
        # meanwhile it is 'running', so that the event stream does not end before the others follow
        self.outcomes[run_id] = [replace(outcomes[0], status="running"), *outcomes[1:]] if outcomes else []
        while len(self.outcomes) > MAX_TRACKED_OUTCOMES:
            self.outcomes.popitem(last=False)

        row_values = {"state": "completed", "result_name": out["result_name"], "ended": time.time(),
                      "message": done + later}

        def note_primary(store: Store) -> None:  # the primary result is the run's: completed now
            if rest <= 0:
                store.finish_job(job_id, "done")
            store.update_run(run_id, **row_values)
            audit.seal_results(store, audit.SYSTEM, audit.RUN_IDENTIFIED, run_id, path,  # its results' hashes
                               {"result": out["result_name"], "method": out["method"], "model": out["model"]})
        if not await self._record(run_id, f"{done}, result {out['result_name']}", note_primary, row_values):
            return
        self.outcomes[run_id] = outcomes
        self.changes.changed(run_id)
        log.info("run %s identified (%s)%s", run_id, out["result_name"], later)
        if rest > 0:
            await self._secondaries(job_id, run_id, path, outcomes, done)

    async def _secondaries(self, job_id: int, run_id: str, path: Path, outcomes: list[MethodOutcome],
                           done: str) -> None:
        """The listed methods after the primary, one worker job each, without the recording's lock
        (they only read it; the results page stays readable meanwhile).  A refusal, a failure or a
        dead worker is that method's outcome: the run stays completed.  The job is done once every
        method has an outcome (a daemon stopped before computes them again at its next start)."""
        for i in range(1, len(outcomes)):
            if self.closing.is_set():
                return  # the job stays running in the database: requeued at the next start
            outcomes[i] = replace(outcomes[i], status="running")
            self.changes.changed(run_id)
            try:
                got = MethodOutcome.from_dict(await self.pool.run(worker.secondary_job, str(path), i))
            except asyncio.CancelledError:
                raise
            except Exception as exc:  # a dead worker, an unpicklable answer: this method's outcome only
                if self.closing.is_set():
                    return
                got = replace(outcomes[i], status="failed", reason=f"{type(exc).__name__}: {exc}")
            outcomes[i] = got
            details = {"kind": "method", "method": got.label, "status": got.status}
            try:  # written and vouched for in the audit trail under the recording's lock
                async with self.artifacts.file_lock(run_id):
                    await asyncio.to_thread(write_outcomes, path, list(outcomes))
                    await self.db.call(lambda s, d=details: audit.seal_results(  # type: ignore[misc]
                        s, audit.SYSTEM, audit.RESULT_STORED, run_id, path, d))
            except Exception as exc:
                log.error("run %s: the outcome of %s could not be stored: %s", run_id, got.label, exc)
            log.info("run %s: %s %s%s", run_id, got.label, got.status, f" ({got.reason})" if got.reason else "")
            self.changes.changed(run_id)
        summary = ", ".join(f"{o.label} {o.status}" for o in outcomes[1:])

        row_values = {"message": f"{done}; {summary}"}

        def note_all(store: Store) -> None:
            store.finish_job(job_id, "done")
            store.update_run(run_id, **row_values)
        await self._record(run_id, f"all methods settled ({summary})", note_all, row_values)

    def identifying(self, run_id: str) -> bool:
        """True while a listed method of the run has no outcome yet (the daemon's own view)."""
        return any(o.status not in SETTLED for o in self.outcomes.get(run_id, ()))

    async def _job_failed(self, job_id: int, run_id: str, error: str) -> None:
        log.error("run %s: identification failed: %s", run_id, error)
        msg = f"identification failed: {error}"

        row_values = {"state": "failed", "reason": msg, "message": msg, "ended": time.time()}

        def note_failed(store: Store) -> None:
            store.finish_job(job_id, "failed", error)
            store.update_run(run_id, **row_values)
        await self._record(run_id, msg, note_failed, row_values)

    async def _record(self, run_id: str, outcome: str, write: Callable[[Store], None],
                      row_values: dict[str, Any] | None = None) -> bool:
        """``write(store)`` the outcome of a job into the database (in the database's writer thread);
        while the database does not take it, keep it (log, ``unrecorded``, /health) and try
        again every RECORD_RETRY_S.  False when the daemon shut down first (the job is still
        ``running`` in the database: it runs again at the next start)."""
        since = time.monotonic()
        while True:
            try:
                await self.db.call(write, timeout_s=RECORD_RETRY_S,
                                   run_values=None if row_values is None else (run_id, row_values))
            except DatabaseBusyError as exc:
                why = self.db.last_error or str(exc)
                if run_id not in self.unrecorded:
                    log.error("run %s: %s; the database cannot record it (%s): kept, and written again every "
                              "%.0f s", run_id, outcome, why, RECORD_RETRY_S)
                self.unrecorded[run_id] = f"{outcome}; not recorded yet: {why}"
                if self.closing.is_set():
                    log.error("run %s: shut down before the database took the outcome (%s); the job runs again "
                              "at the next start", run_id, outcome)
                    return False
                continue
            if self.unrecorded.pop(run_id, None) is not None:
                log.info("run %s: outcome recorded after %.0f s: %s", run_id, time.monotonic() - since, outcome)
            self.changes.changed(run_id)
            return True

    def _set_row(self, run_id: str, **values: Any) -> None:
        self.db.update_run(run_id, values)
        self.changes.changed(run_id)
