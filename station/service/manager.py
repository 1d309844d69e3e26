"""The run manager: one rig connection for the daemon's lifetime, one run on it at a time, the
identification queue, and the start-up recovery.

A run's Procedure runs as an asyncio task in the daemon's event loop (its heavy parts are in
threads); processing and identification go to the worker processes (``worker.py``), queued in the
database so that a restart resumes them.  Nothing here raises HTTP errors: the API layer maps the
typed errors below (and ``LimitError``) to statuses.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import threading
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from station.config import StationConfig, to_rig_physics
from station.errors import LimitError, StationError
from station.recording import new_run_id, read_recording, recover_partial
from station.run.procedure import Procedure, Progress
from station.run.request import Plan, RunRequest, plan_run
from station.run.rig import ConnectedRig, connect
from station.service import worker
from station.service.settings import ServiceSettings
from station.service.store import ACTIVE_STATES, FINAL_STATES, RunRow, Store

log = logging.getLogger(__name__)

MAX_JOB_ATTEMPTS = 3
PERSIST_INTERVAL_S = 1.0


class RigBusyError(StationError):
    """Another run holds the rig."""

    def __init__(self, run_id: str, state: str) -> None:
        super().__init__(f"run {run_id} holds the rig (state {state}); wait for it or abort it")
        self.run_id = run_id


class RunNotFoundError(StationError):
    pass


class RunStateError(StationError):
    """The run is not in a state that allows the request (e.g. results of a running run)."""


class RigUnavailableError(StationError):
    """No link to the rig."""


class FeatureUnavailableError(StationError):
    """An optional module (plots, report, discrepancy) is not installed: 501."""


class RequestLimitError(LimitError):
    """A LimitError with the request field it is about (``loc``, FastAPI style) and its value."""

    def __init__(self, message: str, loc: tuple[str | int, ...], value: object) -> None:
        super().__init__(message)
        self.loc = loc
        self.value = value


def check_request(cfg: StationConfig, request: RunRequest) -> Plan:
    """plan_run, with the offending field located when a limit is broken."""
    try:
        return plan_run(cfg, request)
    except LimitError as exc:
        if request.transducer_id != cfg.transducer.id:
            raise RequestLimitError(str(exc), ("body", "transducer_id"), request.transducer_id) from None
        fr = cfg.rig.crank_frequency_hz
        for i, s in enumerate(request.steps):
            one = request.model_copy(update={"steps": [s]})
            try:
                plan_run(cfg, one)
            except LimitError:
                if not (math.isfinite(s.crank_frequency_hz) and fr.contains(s.crank_frequency_hz)):
                    raise RequestLimitError(str(exc), ("body", "steps", i, "crank_frequency_hz"),
                                            s.crank_frequency_hz) from None
                raise RequestLimitError(str(exc), ("body", "steps", i, "crank_radius_m"), s.crank_radius_m) from None
        raise RequestLimitError(str(exc), ("body",), None) from None


@dataclass
class LiveRun:
    """A run that holds the rig (queued or running), in memory."""

    row: RunRow
    plan: Plan
    proc: Procedure | None = None
    task: asyncio.Task[None] | None = None
    abort_reason: str | None = None
    last_persist: float = 0.0


@dataclass
class StopReport:
    motor_stopped: bool
    aborted_runs: list[str]
    detail: str


@dataclass
class _Change:
    """Wakes everyone waiting for a change of one run (SSE streams)."""

    version: int = 0
    event: asyncio.Event = field(default_factory=asyncio.Event)

    def bump(self) -> None:
        self.version += 1
        self.event.set()
        self.event = asyncio.Event()


RigConnector = Callable[[StationConfig, bool], contextlib.AbstractAsyncContextManager[ConnectedRig]]


def _default_connector(cfg: StationConfig, sim: bool) -> contextlib.AbstractAsyncContextManager[ConnectedRig]:
    return connect(cfg, sim=sim)


class RunManager:
    def __init__(self, settings: ServiceSettings, *, connector: RigConnector = _default_connector) -> None:
        self.settings = settings
        self.cfg = settings.config
        self.store = Store(settings.database)
        self._connector = connector
        self.rig: ConnectedRig | None = None
        self.rig_error: str | None = None
        self._rig_stack: contextlib.AsyncExitStack | None = None
        self._rig_lock = asyncio.Lock()
        self.live: dict[str, LiveRun] = {}
        self._changes: dict[str, _Change] = {}
        self._file_locks: dict[str, asyncio.Lock] = {}
        self.closing = asyncio.Event()
        self._wake_jobs = asyncio.Event()
        self.identify_pool = worker.WorkerPool("identification", settings.workers)
        self.render_pool = worker.WorkerPool("render", 1)
        self._dispatcher: asyncio.Task[None] | None = None
        self._warm: asyncio.Task[None] | None = None
        self._job_tasks: set[asyncio.Task[None]] = set()
        self._caps: tuple[float, dict[str, Any]] | None = None
        self._cache: dict[tuple[str, str], bytes | str] = {}
        self._loop_thread = threading.get_ident()
        self.started_at = time.time()

    # ------------------------------------------------------------------ life cycle
    async def start(self) -> None:
        self._loop_thread = threading.get_ident()
        self.recover()
        await self._connect_rig()
        self._dispatcher = asyncio.create_task(self._dispatch(), name="job-dispatcher")
        self._warm = asyncio.create_task(self._warm_render_pool(), name="render-warm-up")

    async def _warm_render_pool(self) -> None:
        """Start the render worker and learn the optional modules early (the first results page
        would otherwise wait for a process start and the plotting imports)."""
        try:
            await self.capabilities()
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
                await self._motor_emergency_stop()
        if self.rig is not None:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self.rig.motor.stop(), 3.0)
        if self._warm is not None:
            self._warm.cancel()
        if self._dispatcher is not None:
            self._dispatcher.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._dispatcher
        await asyncio.to_thread(self.identify_pool.shutdown, 30.0)
        await asyncio.to_thread(self.render_pool.shutdown, 30.0)  # it may be writing a discrepancy result
        for t in list(self._job_tasks):  # their jobs were allowed to finish or were stopped above
            t.cancel()
        await self._disconnect_rig()
        self.store.close()

    def begin_shutdown(self) -> list[asyncio.Task[None]]:
        """First step of a shutdown, at once (also from the signal handler): live streams end, the run
        on the rig is cancelled (its procedure stops the motor and closes the recording)."""
        self.closing.set()
        for ch in self._changes.values():
            ch.bump()
        tasks = [lv.task for lv in self.live.values() if lv.task is not None]
        for live in list(self.live.values()):
            if live.task is not None and not live.task.done() and not live.abort_reason:
                live.abort_reason = "the station daemon was shut down during the run"
                live.task.cancel()
        return tasks

    async def _connect_rig(self) -> ConnectedRig | None:
        async with self._rig_lock:
            if self.rig is not None:
                return self.rig
            stack = contextlib.AsyncExitStack()
            try:
                self.rig = await stack.enter_async_context(self._connector(self.cfg, self.settings.sim))
            except Exception as exc:
                await stack.aclose()
                self.rig_error = f"{type(exc).__name__}: {exc}"
                log.error("cannot connect to the rig: %s", self.rig_error)
                return None
            self._rig_stack, self.rig_error = stack, None
            log.info("connected: %s", self.rig.description)
            return self.rig

    async def _disconnect_rig(self) -> None:
        async with self._rig_lock:
            stack, self._rig_stack, self.rig = self._rig_stack, None, None
            if stack is not None:
                try:
                    await stack.aclose()
                except Exception as exc:
                    log.warning("closing the rig connection: %s", exc)

    def _rig_healthy(self, rig: ConnectedRig) -> bool:
        h = rig.health()
        return bool(h["motor"]["connected"]) and not h["motor"]["watchdog_error"] and not h["daq"]["link_error"]

    async def _rig_for_run(self) -> ConnectedRig:
        rig = self.rig
        if rig is not None and not self._rig_healthy(rig):
            log.warning("rig link unhealthy (%s); reconnecting", rig.health())
            await self._disconnect_rig()
            rig = None
        if rig is None:
            rig = await self._connect_rig()
        if rig is None:
            raise RigUnavailableError(f"the rig is not connected: {self.rig_error}")
        return rig

    # ------------------------------------------------------------------ recovery
    def recover(self) -> dict[str, list[str]]:
        """Start-up: runs cut off by the end of the previous daemon become ``interrupted`` (their
        partial recordings recovered), jobs left running go back to the queue."""
        out: dict[str, list[str]] = {"interrupted": [], "ended": [], "identifying": [], "requeued": [],
                                     "failed_jobs": []}
        for row in self.store.list_runs(states=ACTIVE_STATES, limit=1_000_000):
            name, status, file_reason = self._recover_recording(row.id)
            if status in ("aborted", "failed"):  # the run had ended; the daemon died before noting it
                self.store.update_run(row.id, state=status, recording=name, reason=file_reason, message=file_reason,
                                      ended=time.time())
                out["ended"].append(row.id)
                continue
            if status == "completed":  # the run ended, the daemon died before recording it
                self.store.update_run(row.id, state="identifying", recording=name,
                                      message="acquisition completed; identification queued after a restart")
                self.store.enqueue_job(row.id)
                out["identifying"].append(row.id)
                continue
            reason = "the station daemon stopped during the run" + (
                "" if name else "; no recording was written")
            self.store.update_run(row.id, state="interrupted", recording=name, reason=reason, ended=time.time(),
                                  message=reason)
            out["interrupted"].append(row.id)
        requeued, failed = self.store.requeue_running_jobs(MAX_JOB_ATTEMPTS)
        out["requeued"] = [j.run_id for j in requeued]
        for j in failed:
            self.store.update_run(j.run_id, state="failed", ended=time.time(),
                                  reason=f"identification stopped {j.attempts} times; not retried")
            out["failed_jobs"].append(j.run_id)
        pending = {j.run_id for j in self.store.jobs(states=("queued", "running"))}
        for row in self.store.list_runs(states=("identifying",), limit=1_000_000):
            if row.id not in pending:
                self.store.enqueue_job(row.id)
                out["requeued"].append(row.id)
        if any(out.values()):
            log.info("start-up recovery: %s", json.dumps(out))
        return out

    def _recover_recording(self, run_id: str) -> tuple[str | None, str | None, str]:
        """(file name, exit status, reason) of a run's recording, a partial file recovered first."""
        d = self.settings.recordings_dir
        final, partial = d / f"{run_id}.h5", d / f"{run_id}.h5.partial"
        if partial.exists() and not final.exists():
            try:
                recover_partial(partial)
            except Exception as exc:
                log.error("run %s: the partial recording cannot be recovered: %s", run_id, exc)
                return partial.name, None, ""
        if final.exists():
            try:
                rec = read_recording(final)
                return final.name, rec.exit_status, rec.reason
            except Exception as exc:
                log.error("run %s: recording unreadable: %s", run_id, exc)
                return final.name, None, ""
        return None, None, ""

    # ------------------------------------------------------------------ runs
    def active(self) -> LiveRun | None:
        return next(iter(self.live.values()), None)

    async def submit(self, request: RunRequest) -> RunRow:
        """Check and queue a run (202); raises RequestLimitError (422), RigBusyError (409),
        RigUnavailableError (503)."""
        if self.closing.is_set():
            raise RigUnavailableError("the daemon is shutting down")
        plan = check_request(self.cfg, request)
        cur = self.active()
        if cur is not None:
            raise RigBusyError(cur.row.id, cur.row.state)
        await self._rig_for_run()
        cur = self.active()  # the connection attempt yielded: check again
        if cur is not None:
            raise RigBusyError(cur.row.id, cur.row.state)
        run_id = new_run_id(request.transducer_id)
        row = RunRow(id=run_id, state="queued", transducer_id=request.transducer_id,
                     top_mass_kg=request.top_mass_kg, request_json=request.model_dump_json(),
                     plan_json=json.dumps(plan.to_dict()), created=time.time(), n_steps=len(plan.steps),
                     message="waiting for the rig")
        self.store.insert_run(row)
        live = LiveRun(row, plan)
        self.live[run_id] = live
        live.task = asyncio.create_task(self._execute(live), name=f"run-{run_id}")
        self._changed(run_id)
        log.info("run %s queued: %d steps", run_id, len(plan.steps))
        return row

    async def _execute(self, live: LiveRun) -> None:
        run_id, plan = live.row.id, live.plan
        try:
            rig = await self._rig_for_run()
            if rig.sim is not None:
                self._simulate_plan_physics(rig, plan.config)
            proc = Procedure(plan, rig, self.settings.recordings_dir, run_id=run_id,
                             on_progress=lambda p: self._on_progress(live, p))
            live.proc = proc
            if live.abort_reason:
                proc.abort(live.abort_reason)
            self._update(live, state="running", started=time.time(), message="starting")
            outcome = await proc.execute()
        except asyncio.CancelledError:
            self._finish(live, "interrupted", live.abort_reason or "the station daemon stopped before the run began")
            return
        except Exception as exc:
            log.exception("run %s could not be carried out", run_id)
            self._finish(live, "failed", f"{type(exc).__name__}: {exc}")
            return
        name = outcome.path.name
        if outcome.exit_status == "completed":
            self._update(live, recording=name, lost_samples=outcome.lost_samples, state="identifying",
                         fraction=1.0, message="acquisition completed; identification queued")
            self.store.enqueue_job(run_id)
            self._wake_jobs.set()
            self.live.pop(run_id, None)
            self._changed(run_id)
        else:
            state, reason = outcome.exit_status, outcome.reason
            if state == "interrupted" and live.abort_reason:
                reason = live.abort_reason
            elif state == "failed" and live.abort_reason:
                # the operator's stop reached the motor before the procedure saw the abort: the
                # procedure reports the latched e-stop fault; the run was stopped on purpose
                state, reason = "aborted", f"{live.abort_reason} (recording: {outcome.reason})"
            self._update(live, recording=name, lost_samples=outcome.lost_samples)
            self._finish(live, state, reason)

    def _finish(self, live: LiveRun, state: str, reason: str) -> None:
        self._update(live, state=state, reason=reason, message=reason, ended=time.time())
        self.live.pop(live.row.id, None)
        self._changed(live.row.id)

    def _simulate_plan_physics(self, rig: ConnectedRig, cfg: StationConfig) -> None:
        """The simulated rig carries the run's top mass (a real rig has whatever is mounted)."""
        src = getattr(rig.sim, "source", None)
        if src is None or not hasattr(src, "physics"):
            return
        physics = to_rig_physics(cfg)
        if physics == src.physics:
            return
        synth = getattr(src, "synth", None)
        src.set_phase(float(synth.crank_angle_rad) if synth is not None else 0.0)
        src.physics = physics

    def _on_progress(self, live: LiveRun, p: Progress) -> None:
        if threading.get_ident() != self._loop_thread:  # the procedure reports from the loop; be safe
            return
        row = live.row
        changed_phase = (p.step, p.step_state) != (row.step, row.step_state)
        values: dict[str, Any] = {"step": p.step, "step_state": p.step_state, "samples": p.samples,
                                  "lost_samples": p.lost_samples, "fraction": round(p.fraction, 4),
                                  "message": p.message}
        for k, v in values.items():
            setattr(row, k, v)
        now = time.monotonic()
        if changed_phase or now - live.last_persist >= PERSIST_INTERVAL_S:
            live.last_persist = now
            self.store.update_run(row.id, **values)
        self._changed(row.id)

    def _update(self, live: LiveRun, **values: Any) -> None:
        for k, v in values.items():
            setattr(live.row, k, v)
        self.store.update_run(live.row.id, **values)
        self._changed(live.row.id)

    def abort(self, run_id: str, reason: str = "aborted by operator") -> RunRow:
        live = self.live.get(run_id)
        if live is None:
            row = self.get(run_id)
            raise RunStateError(f"run {run_id} is {row.state}: only a queued or running run can be aborted")
        live.abort_reason = reason
        if live.proc is not None:
            live.proc.abort(reason)
        self._update(live, message=f"aborting: {reason}")
        return live.row

    async def emergency_stop(self) -> StopReport:
        """Abort every run on the rig and command an emergency stop on the motor right away."""
        aborted = []
        for live in list(self.live.values()):
            live.abort_reason = "emergency stop"
            if live.proc is not None:
                live.proc.abort("emergency stop")
            aborted.append(live.row.id)
        ok, detail = await self._motor_emergency_stop()
        log.warning("EMERGENCY STOP: %s (aborted runs: %s)", detail, aborted or "none")
        return StopReport(ok, aborted, detail)

    async def _motor_emergency_stop(self) -> tuple[bool, str]:
        rig = self.rig
        if rig is None:
            return False, ("no link to the motor controller; if the crank turns, its watchdog stops it when "
                           "refreshes cease - use the hardware emergency stop")
        try:
            await asyncio.wait_for(rig.motor.emergency_stop(), 2.0)
            return True, "emergency stop commanded on the motor controller"
        except Exception as exc:
            return False, (f"the motor controller did not take the emergency stop ({type(exc).__name__}: {exc}); "
                           "use the hardware emergency stop")

    def get(self, run_id: str) -> RunRow:
        live = self.live.get(run_id)
        if live is not None:
            return live.row
        row = self.store.get_run(run_id)
        if row is None:
            raise RunNotFoundError(f"no run {run_id!r}")
        return row

    def list_runs(self, *, limit: int = 100, states: list[str] | None = None) -> list[RunRow]:
        rows = self.store.list_runs(limit=limit, states=states)
        return [self.live[r.id].row if r.id in self.live else r for r in rows]

    # ------------------------------------------------------------------ change notification
    def _changed(self, run_id: str) -> None:
        self._changes.setdefault(run_id, _Change()).bump()

    def version(self, run_id: str) -> int:
        return self._changes.setdefault(run_id, _Change()).version

    async def wait_change(self, run_id: str, since: int, timeout_s: float) -> int:
        ch = self._changes.setdefault(run_id, _Change())
        if ch.version == since and not self.closing.is_set():
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(ch.event.wait(), timeout_s)
        return self._changes[run_id].version

    # ------------------------------------------------------------------ identification jobs
    async def _dispatch(self) -> None:
        slots = asyncio.Semaphore(max(1, self.settings.workers))
        while not self.closing.is_set():
            if self.settings.workers == 0:
                await self.closing.wait()
                return
            await slots.acquire()
            job = self.store.claim_job()
            if job is None:
                slots.release()
                self._wake_jobs.clear()
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._wake_jobs.wait(), 5.0)
                continue
            t = asyncio.create_task(self._run_job(job.id, job.run_id, job.attempts), name=f"job-{job.id}")
            self._job_tasks.add(t)
            t.add_done_callback(lambda t: (self._job_tasks.discard(t), slots.release()))

    async def _run_job(self, job_id: int, run_id: str, attempts: int) -> None:
        row = self.store.get_run(run_id)
        if row is None or not row.recording:
            self.store.finish_job(job_id, "failed", "run or recording unknown")
            return
        path = self.recording_path(row)
        self._set_row(run_id, message=f"identifying (attempt {attempts})")
        try:
            async with self.file_lock(run_id):
                out = await self.identify_pool.run(worker.identify_job, str(path),
                                                   self.cfg.processing.model_dump())
        except asyncio.CancelledError:
            raise
        except (worker.WorkerCrashed, OSError) as exc:
            if attempts < MAX_JOB_ATTEMPTS and not self.closing.is_set():
                log.warning("run %s: identification attempt %d: %s; queued again", run_id, attempts, exc)
                self.store.finish_job(job_id, "queued", str(exc))
                await asyncio.sleep(1.0)
                self._wake_jobs.set()
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
        self._changed(run_id)

    # ------------------------------------------------------------------ recordings and results
    def recording_path(self, row: RunRow) -> Path:
        """The run's recording, always inside the recordings folder."""
        if not row.recording:
            raise RunStateError(f"run {row.id} has no recording")
        base = self.settings.recordings_dir
        p = (base / Path(row.recording).name).resolve()
        if p.parent != base:
            raise RunStateError(f"run {row.id}: recording outside the recordings folder refused")
        if not p.is_file():
            raise RunStateError(f"run {row.id}: recording {p.name} is missing from the recordings folder")
        return p

    def file_lock(self, run_id: str) -> asyncio.Lock:
        """Serialises the daemon's own accesses to one recording (HDF5 locks files)."""
        return self._file_locks.setdefault(run_id, asyncio.Lock())

    async def read_file(self, run_id: str, fn: Callable[[Path], Any]) -> Any:
        row = self.get(run_id)
        path = self.recording_path(row)
        async with self.file_lock(run_id):
            return await asyncio.to_thread(fn, path)

    async def stream_file(self, run_id: str, chunk: int = 1 << 20) -> AsyncIterator[bytes]:
        row = self.get(run_id)
        path = self.recording_path(row)
        async with self.file_lock(run_id):
            f = await asyncio.to_thread(open, path, "rb")
            try:
                while True:
                    data = await asyncio.to_thread(f.read, chunk)
                    if not data:
                        return
                    yield data
            finally:
                f.close()

    async def capabilities(self) -> dict[str, Any]:
        """Which optional modules exist (checked in a worker, cached for 30 s)."""
        now = time.monotonic()
        if self._caps is None or now - self._caps[0] > 30.0:
            self._caps = (now, await self.render_pool.run(worker.capabilities_job))
        return self._caps[1]

    async def _cached(self, key: tuple[str, str], make: Callable[[], Awaitable[Any]]) -> Any:
        if key not in self._cache:
            value = await make()
            if value is None:
                return None
            if len(self._cache) > 256:
                self._cache.pop(next(iter(self._cache)))
            self._cache[key] = value
        return self._cache[key]

    def _completed_path(self, run_id: str) -> Path:
        row = self.get(run_id)
        if row.state != "completed":
            raise RunStateError(f"run {run_id} is {row.state}: plots, report and analyses exist for "
                                "completed runs only")
        return self.recording_path(row)

    async def plot(self, run_id: str, name: str) -> bytes | None:
        path = self._completed_path(run_id)
        caps = await self.capabilities()
        if caps["plots"] is None:
            raise FeatureUnavailableError("plots are not available: station.report.plots is not installed")
        if name not in caps["plots"]:
            return None

        async def make() -> bytes | None:
            async with self.file_lock(run_id):
                return await self._optional_job(worker.plot_job, str(path), name)
        return await self._cached((run_id, f"plot:{name}"), make)

    async def report(self, run_id: str) -> str:
        path = self._completed_path(run_id)

        async def make() -> str:
            async with self.file_lock(run_id):
                return await self._optional_job(worker.report_job, str(path))
        return await self._cached((run_id, "report"), make)

    async def discrepancy(self, run_id: str, max_effects: int) -> dict[str, Any]:
        path = self._completed_path(run_id)
        async with self.file_lock(run_id):
            out = await self._optional_job(worker.discrepancy_job, str(path), max_effects)
        self._cache.pop((run_id, "report"), None)  # the report names the effects found
        return out

    async def _optional_job(self, fn: Callable[..., Any], *args: Any) -> Any:
        try:
            return await self.render_pool.run(fn, *args)
        except worker.Unavailable as exc:
            self._caps = None
            raise FeatureUnavailableError(str(exc)) from None

    # ------------------------------------------------------------------ health
    def health(self) -> dict[str, Any]:
        rig = self.rig
        links = rig.health() if rig is not None else {
            "motor": {"connected": False, "watchdog_error": None},
            "daq": {"link_error": self.rig_error}, "simulated": self.settings.sim}
        counts = self.store.job_counts()
        db_ok = self.store.ping()
        rig_ok = rig is not None and self._rig_healthy(rig)
        act = self.active()
        return {"status": "ok" if rig_ok and db_ok else "degraded",
                "rig": {"connected": rig is not None, "error": self.rig_error,
                        "description": rig.description if rig is not None else "", **links},
                "database": {"ok": db_ok, "journal_mode": self.store.journal_mode() if db_ok else None},
                "worker": {"processes": self.settings.workers, "started": self.identify_pool.started,
                           "crashes": self.identify_pool.crashes, "jobs": counts},
                "active_run": act.row.id if act else None,
                "uptime_s": time.time() - self.started_at}


def is_final(state: str) -> bool:
    return state in FINAL_STATES
