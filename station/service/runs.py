"""Runs on the rig: check a request against the limits, queue it (one run holds the rig at a
time), carry it out with the Procedure, follow its progress, abort it, stop everything at once.

The bookkeeping (``live``, the database, change notification) belongs to the web side's loop; the
procedure runs on the rig thread's loop (``_carry_out``), or is carried out in the rig process and
followed from there (``ConnectedRig.procedure``: the daemon's rig), and posts its progress back with
``call_soon_threadsafe``.  Aborts and cancellations cross over the other way."""

from __future__ import annotations

import asyncio
import concurrent.futures
import dataclasses
import json
import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from station.config import StationConfig
from station.lab import audit, register
from station.lab.integrity import sha256_file
from station.lab.store import RunRow, Store
from station.recording import new_run_id
from station.run.procedure import Progress, RunOutcome, RunProcedure
from station.run.request import Plan, RunRequest, plan_run
from station.run.rig import ConnectedRig
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
from station.service.latch import EStopLatch
from station.service.riglink import DriveCheck, RigLink

log = logging.getLogger(__name__)

PERSIST_INTERVAL_S = 1.0


@dataclass
class LiveRun:
    """A run that holds the rig (queued or running), in memory."""

    row: RunRow
    plan: Plan
    rig: ConnectedRig  # checked healthy when the run was queued (``RigLink.for_run``, once per run)
    proc: RunProcedure | None = None  # here, or its remote form in the rig process
    task: asyncio.Task[None] | None = None  # on the web loop: waits for the rig side
    rig_task: asyncio.Task[RunOutcome] | None = None  # on the rig loop: the procedure
    cancelled: bool = False
    abort_reason: str | None = None
    last_persist: float = 0.0


@dataclass
class StopReport:
    """``motor_stopped``: the drive, read back after the command, reports standstill; ``commanded``:
    the controller took the emergency stop; ``drive``: its last state read (None: not readable)."""

    motor_stopped: bool
    aborted_runs: list[str]
    detail: str
    commanded: bool = False
    drive: DriveCheck | None = None


@dataclass
class AckReport:
    acknowledged: list[int]  # ids of the emergency stops acknowledged
    by: str
    detail: str


class Runs:
    """The run on the rig (``live``: at most one) and the stored ones; ``on_acquired(run_id)`` is
    called when a run's acquisition completed and its identification was queued."""

    def __init__(self, cfg: StationConfig, recordings_dir: Path, db: DbAccess, link: RigLink, changes: Changes,
                 closing: asyncio.Event, on_acquired: Callable[[str], None], latch: EStopLatch,
                 disk: RecordingsDisk) -> None:
        self.cfg = cfg
        self.recordings_dir = recordings_dir
        self.latch = latch
        self.disk = disk
        self.db = db
        self.link = link
        self.changes = changes
        self.closing = closing
        self._on_acquired = on_acquired
        self.live: dict[str, LiveRun] = {}
        self._stopping = 0  # emergency stops being commanded (not latched yet): no run may start meanwhile
        self._stopping_lock = threading.Lock()
        self._aborted_elsewhere: list[str] = []  # runs aborted on a stop the rig process is giving (its event)
        self.loop_thread = threading.get_ident()
        self.web_loop: asyncio.AbstractEventLoop | None = None

    def _post(self, fn: Callable[..., Any], *args: Any) -> None:
        """Call ``fn(*args)`` on the web side's loop (from the rig thread)."""
        loop = self.web_loop
        if loop is None or threading.get_ident() == self.loop_thread:
            fn(*args)
        elif not loop.is_closed():
            loop.call_soon_threadsafe(fn, *args)

    def active(self) -> LiveRun | None:
        return next(iter(self.live.values()), None)

    async def submit(self, request: RunRequest, who: str = audit.SYSTEM) -> RunRow:
        """Check and queue a run (202) for user ``who``; raises LimitError (422), RegisterError (422:
        a transducer or standard not registered, a standard overdue), RigBusyError (409),
        RigUnavailableError (503)."""
        if self.closing.is_set():
            raise RigUnavailableError("the daemon is shutting down")
        setup = await self.db.read(lambda store: register.run_setup(store, self.cfg, request.transducer_id,
                                                                      request.standards))
        plan = plan_run(setup.config(self.cfg), request)
        plan = dataclasses.replace(plan, provenance={"operator": who, **setup.to_dict()})
        cur = self.active()
        if cur is not None:
            raise RigBusyError(cur.row.id, cur.row.state)
        self._refuse_if_latched()
        self.disk.check_for_run()
        rig = await self.link.for_run()
        fault = await self.link.motor_fault()  # read, never cleared here
        if fault is not None:
            self.latch.trip("controller", f"motor controller fault {fault[0]} ({fault[1]}) before a run")
        cur = self.active()  # the connection attempt yielded: check again
        if cur is not None:
            raise RigBusyError(cur.row.id, cur.row.state)
        self._refuse_if_latched()
        run_id = new_run_id(request.transducer_id)
        row = RunRow(id=run_id, state="queued", transducer_id=request.transducer_id,
                     top_mass_kg=request.top_mass_kg, request_json=request.model_dump_json(),
                     plan_json=json.dumps(plan.to_dict()), created=time.time(), n_steps=len(plan.steps),
                     message="waiting for the rig" + "".join(f"; WARNING: {w}" for w in setup.warnings),
                     operator=who, transducer_json=json.dumps(setup.transducer.to_dict()),
                     standards_json=setup.standards_json())
        live = LiveRun(row, plan, rig)
        self.live[run_id] = live  # holds the rig while the database takes the row

        def insert(store: Store) -> None:
            with store.transaction() as db:
                store.insert_run(row, db)
                audit.record(db, who, audit.RUN_STARTED, run_id,
                             {"transducer_id": row.transducer_id, "top_mass_kg": row.top_mass_kg,
                              "steps": [[s.crank_frequency_hz, s.crank_radius_m] for s in plan.steps],
                              "standards": [s.id for s in setup.standards], "warnings": list(setup.warnings)})
        try:
            await self.db.call(insert)  # DatabaseBusyError: not queued (503)
        except BaseException:
            self.live.pop(run_id, None)
            raise
        if live.abort_reason:  # an emergency stop came meanwhile
            self._finish(live, "aborted", live.abort_reason)
            return live.row
        live.task = asyncio.create_task(self._execute(live), name=f"run-{run_id}")
        self.changes.changed(run_id)
        log.info("run %s queued: %d steps", run_id, len(plan.steps))
        return row

    def _refuse_if_latched(self) -> None:
        if self._stopping:
            raise EStopLatchedError("an emergency stop is being carried out; no run starts")
        why = self.latch.refusal()
        if why is not None:
            raise EStopLatchedError(why)

    async def _execute(self, live: LiveRun) -> None:
        try:
            await self._execute_and_note(live)
        finally:  # the procedure (and its buffers) is not kept by the run's record: no cycle to wait for
            live.proc, live.rig_task = None, None

    async def _execute_and_note(self, live: LiveRun) -> None:
        run_id = live.row.id
        try:
            fut = self.link.thread.start().submit(self._carry_out(live))
            outcome = await asyncio.wrap_future(fut)
        except asyncio.CancelledError:
            self._finish(live, "interrupted", live.abort_reason or "the station daemon stopped before the run began")
            return
        except Exception as exc:
            log.exception("run %s could not be carried out", run_id)
            self._finish(live, "failed", f"{type(exc).__name__}: {exc}")
            return
        name = outcome.path.name
        sha = await self._hash(outcome.path)
        self._update(live, recording_sha256=sha)
        self.db.post(lambda store: audit.append(store, audit.SYSTEM, audit.RUN_ENDED, run_id,
                                                {"exit_status": outcome.exit_status, "recording": name,
                                                 "sha256": sha, "reason": outcome.reason},
                                                files={name: sha} if sha else None))
        if outcome.exit_status == "completed":
            self._update(live, recording=name, lost_samples=outcome.lost_samples, state="identifying",
                         fraction=1.0, message="acquisition completed; identification queued")
            self.db.post(lambda store: store.enqueue_job(run_id))
            self._on_acquired(run_id)
            self.live.pop(run_id, None)
            self.changes.changed(run_id)
        else:
            state, reason = outcome.exit_status, outcome.reason
            if state == "interrupted" and live.abort_reason:
                reason = live.abort_reason
            elif state == "failed" and live.abort_reason:
                # the operator's stop reached the motor before the procedure saw the abort: the
                # procedure reports the latched e-stop fault; the run was stopped on purpose
                state, reason = "aborted", f"{live.abort_reason} (recording: {outcome.reason})"
            fault = live.proc.motor_fault if live.proc is not None else None
            if fault is not None and not live.abort_reason and not self.latch.latched:
                self.latch.trip("controller", f"motor controller fault {fault[0]} ({fault[1]}) in run {run_id}")
            self._update(live, recording=name, lost_samples=outcome.lost_samples)
            self._finish(live, state, reason)
        self._check_drive(live)

    @staticmethod
    async def _hash(path: Path) -> str | None:
        """The closed recording's SHA-256 (None, logged, if it cannot be read)."""
        try:
            return await asyncio.to_thread(sha256_file, path)
        except OSError as exc:
            log.error("recording %s: SHA-256 not taken (%s)", path.name, exc)
            return None

    def _check_drive(self, live: LiveRun) -> None:
        """The procedure read the drive back after its stop: a crank still turning latches."""
        check = live.proc.drive_check if live.proc is not None else None
        if check is not None and check.standstill is False:
            self.latch.trip("drive", f"{check.describe()} (run {live.row.id}); use the hardware emergency stop")

    async def _carry_out(self, live: LiveRun) -> RunOutcome:
        """On the rig loop: ready the rig for the plan, then the procedure."""
        live.rig_task = asyncio.current_task()
        if live.cancelled:
            raise asyncio.CancelledError
        plan, rig = live.plan, live.rig
        rig.load(plan)
        proc = rig.procedure(plan, self.recordings_dir, run_id=live.row.id,
                             on_progress=lambda p: self._post(self._on_progress, live, dataclasses.replace(p)),
                             on_disk_full=self.disk.release_reserve, disk_reserve=self.disk.path)
        live.proc = proc
        if live.abort_reason:
            proc.abort(live.abort_reason)
        await self._note_run(rig, live.row.id)  # before the run shows as running: a stop then names it
        self._post(self._update, live, {"state": "running", "started": time.time(), "message": "starting"})
        try:
            return await proc.execute()
        finally:
            if proc.drive_check is not None:
                self.link.drive = proc.drive_check
            await self._note_run(rig, None)

    @staticmethod
    async def _note_run(rig: ConnectedRig, run_id: str | None) -> None:
        """Tell the rig process which run the crank turns for: a courtesy for the stop's answer (it
        names the run), so a slow or lost channel never holds the run (the stop does not need it)."""
        if rig.on_run is None:
            return
        try:
            async with asyncio.timeout(1.0):
                await rig.on_run(run_id)
        except Exception as exc:  # the stop does not depend on it: logged, the run goes on
            log.warning("the rig process was not told the run %s: %s", run_id, exc)

    def _finish(self, live: LiveRun, state: str, reason: str) -> None:
        try:
            self._update(live, state=state, reason=reason, message=reason, ended=time.time())
        finally:  # the rig is released whatever happens to the bookkeeping
            self.live.pop(live.row.id, None)
            self.changes.changed(live.row.id)

    def _on_progress(self, live: LiveRun, p: Progress) -> None:
        if threading.get_ident() != self.loop_thread:  # the procedure reports from the loop; be safe
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
            self._save(row.id, values)
        self.changes.changed(row.id)

    def _update(self, live: LiveRun, values: dict[str, Any] | None = None, **kw: Any) -> None:
        values = {**(values or {}), **kw}
        for k, v in values.items():
            setattr(live.row, k, v)
        self._save(live.row.id, values)
        self.changes.changed(live.row.id)

    def _save(self, run_id: str, values: dict[str, Any]) -> None:
        """To the database's writer: written when the database takes it (locked, disk full: later)."""
        self.db.update_run(run_id, values)

    async def abort(self, run_id: str, reason: str = "aborted by operator", who: str = audit.SYSTEM) -> RunRow:
        live = self.live.get(run_id)
        if live is None:
            row = await self.get(run_id)
            raise RunStateError(f"run {run_id} is {row.state}: only a queued or running run can be aborted")
        self._abort(live, reason)
        self.db.post(lambda store: audit.append(store, who, audit.RUN_ABORTED, run_id, {"reason": reason}))
        self._update(live, message=f"aborting: {live.abort_reason}")
        return live.row

    def _abort(self, live: LiveRun, reason: str) -> None:
        """The first reason stays (a later abort does not overwrite an emergency stop)."""
        if not live.abort_reason:
            live.abort_reason = reason
        proc = live.proc
        if proc is not None:
            self.link.thread.call_soon(proc.abort, live.abort_reason)

    def abort_all(self, reason: str = "emergency stop") -> list[str]:
        """Abort every run on the rig now (from any thread: each procedure is told on the rig thread,
        before anything handed to it later, e.g. the emergency stop's command); their ids."""
        aborted = []
        for live in list(self.live.values()):
            self._abort(live, reason)
            aborted.append(live.row.id)
        return aborted

    async def emergency_stop(self, source: str = "api", who: str | Callable[[Store], str] = "anonymous",
                             commanded: concurrent.futures.Future[None] | None = None,
                             aborted_before: Sequence[str] = ()) -> StopReport:
        """Abort every run on the rig, command an emergency stop on the motor right away, latch (no
        run starts until an operator acknowledges it), then read the drive back until it reports
        standstill: a crank still turning after its bound latches a fault of its own (``drive``).
        ``commanded``: the command already handed to the rig thread
        (``RigLink.command_emergency_stop``, as the main port does on a stop's arrival), after
        :meth:`abort_all` aborted the runs ``aborted_before``.

        Nothing here waits on the database: the command goes to the rig thread, the latch is in
        memory and its record is handed to the database's writer."""
        aborted = [*aborted_before, *(r for r in self.abort_all() if r not in aborted_before)]
        with self._stopping_lock:  # the stop port's thread gives stops too
            self._stopping += 1
        try:
            ok, detail = await self.link.emergency_stop(commanded)
        finally:
            with self._stopping_lock:
                self._stopping -= 1
        log.warning("EMERGENCY STOP (%s): %s (aborted runs: %s)", source, detail, aborted or "none")
        self.latch.trip(source, detail + (f"; aborted runs: {', '.join(aborted)}" if aborted else ""), who)
        check = await self.link.verify_standstill("the emergency stop") if ok else None
        if check is not None and check.standstill is False:
            self.latch.trip("drive", f"{check.describe()}; use the hardware emergency stop")
        if check is not None:
            detail = f"{detail}; {check.describe()}"
        return StopReport(bool(check is not None and check.standstill), aborted, detail, ok, check)

    def stopping_elsewhere(self) -> list[str]:
        """The rig process is about to give a stop (its stop port): the runs aborted now, before the
        procedure can read the drive's emergency-stop fault and end as failed; the aborted runs
        (named again by :meth:`stopped_elsewhere`)."""
        aborted = self.abort_all()
        self._aborted_elsewhere.extend(r for r in aborted if r not in self._aborted_elsewhere)
        return aborted

    def stopped_elsewhere(self, source: str, detail: str, who: str | Callable[[Store], str],
                          drive: DriveCheck | None) -> list[str]:
        """A stop the rig process gave on its own (its stop port, a lost link): the runs aborted,
        the latch tripped, the drive's read-back kept (from any thread); the aborted runs."""
        self.stopping_elsewhere()
        aborted, self._aborted_elsewhere = self._aborted_elsewhere, []
        self.latch.trip(source, detail + (f"; aborted runs: {', '.join(aborted)}" if aborted else ""), who)
        if drive is not None:
            self.link.drive = drive
            if drive.standstill is False:
                self.latch.trip("drive", f"{drive.describe()}; use the hardware emergency stop")
        return aborted

    async def acknowledge(self, by: str, note: str = "") -> AckReport:  # by: the user (audited by the latch)
        """An operator acknowledges the emergency stop: the controller's latched fault is reset (and
        read back) and the latch released; refused while the controller still reports a fault."""
        ok, detail = await self.link.reset_faults()
        if not ok:
            raise EStopLatchedError(f"not acknowledged: {detail}")
        rows = await self.latch.acknowledge(by, note)
        return AckReport([r.id for r in rows], by, detail)

    def cancel_all(self, reason: str) -> list[asyncio.Task[None]]:
        """Shutdown: cancel the run on the rig (its procedure stops the motor, closes the recording)."""
        tasks = [lv.task for lv in self.live.values() if lv.task is not None]
        for live in list(self.live.values()):
            if live.task is not None and not live.task.done():
                if not live.abort_reason:
                    live.abort_reason = reason
                self.link.thread.call_soon(self._cancel_on_rig, live)
        return tasks

    @staticmethod
    def _cancel_on_rig(live: LiveRun) -> None:
        """Cancel the run's procedure, once: the shutdown begins twice (the signal handler, then the
        lifespan's close), and a second cancellation would land in the procedure's own stop, cutting
        short the motor's stop and the closing of the recording."""
        if live.cancelled:
            return
        live.cancelled = True
        if live.rig_task is not None and not live.rig_task.done():
            live.rig_task.cancel()

    def _overlaid(self, row: RunRow) -> RunRow:
        """A row read back with the run's changes the database has not taken yet."""
        live = self.live.get(row.id)
        if live is not None:
            return live.row
        pending = self.db.overlay(row.id)
        return dataclasses.replace(row, **pending) if pending else row

    async def get(self, run_id: str) -> RunRow:
        live = self.live.get(run_id)
        if live is not None:
            return live.row
        row = await self.db.read(lambda store: store.get_run(run_id))
        if row is None:
            raise RunNotFoundError(f"no run {run_id!r}")
        return self._overlaid(row)

    async def list_runs(self, *, limit: int = 100, states: list[str] | None = None) -> list[RunRow]:
        rows = await self.db.read(lambda store: store.list_runs(limit=limit, states=states))
        return [self._overlaid(r) for r in rows]
