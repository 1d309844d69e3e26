"""The identification queue: jobs are rows in the database (a restart resumes them); a dispatcher
hands them to the worker processes, retries a job whose worker died, and notes the outcome."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from typing import Any

from station.service import worker
from station.service.artifacts import Artifacts
from station.service.changes import Changes
from station.service.store import Store

log = logging.getLogger(__name__)

MAX_JOB_ATTEMPTS = 3


class JobQueue:
    """Runs identification jobs on ``pool`` (``workers`` at a time; 0: jobs wait in the queue)."""

    def __init__(self, store: Store, pool: worker.WorkerPool, workers: int,
                 artifacts: Artifacts, changes: Changes, closing: asyncio.Event) -> None:
        self.store = store
        self.pool = pool
        self.workers = workers
        self.artifacts = artifacts
        self.changes = changes
        self.closing = closing
        self._wake = asyncio.Event()
        self._dispatcher: asyncio.Task[None] | None = None
        self._tasks: set[asyncio.Task[None]] = set()

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
            job = self.store.claim_job()
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
        row = self.store.get_run(run_id)
        if row is None or not row.recording:
            self.store.finish_job(job_id, "failed", "run or recording unknown")
            return
        path = self.artifacts.recording_path(row)
        self._set_row(run_id, message=f"identifying (attempt {attempts})")
        try:
            async with self.artifacts.file_lock(run_id):
                out = await self.pool.run(worker.identify_job, str(path))
        except asyncio.CancelledError:
            raise
        except (worker.WorkerCrashed, OSError) as exc:
            if attempts < MAX_JOB_ATTEMPTS and not self.closing.is_set():
                log.warning("run %s: identification attempt %d: %s; queued again", run_id, attempts, exc)
                self.store.finish_job(job_id, "queued", str(exc))
                await asyncio.sleep(1.0)
                self._wake.set()
                return
            if self.closing.is_set():
                return  # left running in the database: requeued at the next start
            self._job_failed(job_id, run_id, f"{type(exc).__name__}: {exc}")
            return
        except Exception as exc:
            self._job_failed(job_id, run_id, f"{type(exc).__name__}: {exc}")
            return
        self.store.finish_job(job_id, "done")
        self._set_row(run_id, state="completed", result_name=out["result_name"], ended=time.time(),
                      message=f"identified ({out['method']}, {out['model']}) in {out['wall_s']:.1f} s")
        log.info("run %s identified (%s)", run_id, out["result_name"])

    def _job_failed(self, job_id: int, run_id: str, error: str) -> None:
        log.error("run %s: identification failed: %s", run_id, error)
        self.store.finish_job(job_id, "failed", error)
        msg = f"identification failed: {error}"
        self._set_row(run_id, state="failed", reason=msg, message=msg, ended=time.time())

    def _set_row(self, run_id: str, **values: Any) -> None:
        self.store.update_run(run_id, **values)
        self.changes.changed(run_id)
