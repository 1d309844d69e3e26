"""The run's procedure in the rig process: the web process asks for a plan to be carried out
(``run_start``), the rig process runs ``run/procedure.Procedure`` itself against its own drive
connection and the stream process, tells the run's progress (``run_progress``, at most
:data:`PROGRESS_PERIOD_S` apart unless the step or its state changes) and its end (``run_end``: the
outcome, kept for ``run_outcome`` too); ``run_abort`` stops it.

While a run is carried out here a silent web process (hung, stopped, flooded) no longer stops it:
the run goes on to its end and its recording closes as the procedure decides.  The stop port, a lost
drive link, the drive's watchdog and a fault stop it as they stop any run.  When the web process's
connection closes (it died) or the daemon's lifeline ends, the run is stopped (ramp down, drive read
back, the recording closed ``interrupted`` with the reason, as the stream process closes a run the
daemon's end cuts off): nobody is left to take its result; a later daemon reads how it ended in the
recording (``service/recovery.py``).

The procedure and what it imports (numpy, h5py for the stream's types) are loaded when the rig
process starts, before it reads its specification and raises its priority (``preload_procedure``)."""

from __future__ import annotations

import asyncio
import collections
import contextlib
import importlib
import itertools
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from drivers.clock import REAL_CLOCK, Clock
from drivers.motor.controller import MotorController
from drivers.motor.errors import MotorLinkError, MotorStateError
from station.rigproc import channel

if TYPE_CHECKING:
    from drivers.motor.transport import RegisterTransport
    from station.run.procedure import Procedure, Progress, RadiusActuator, RunOutcome
    from station.run.stream import RecordingStream

log = logging.getLogger("station.rigproc")

PROGRESS_PERIOD_S = 0.25  # a run's progress told at most this often (a change of step or state: at once)
BACKLOG_BYTES = 256 * 1024  # progress and stream events not queued for a web process that reads nothing
KEEP_OUTCOMES = 16  # the last runs' outcomes, for ``run_outcome``
END_WAIT_S = 120.0  # an aborted run's stop, read-back and recording's close, at most


class RigProcess(Protocol):
    """What of the rig process (``serve.RigProcess``) a run carried out there uses."""

    spec: Any  # ``serve.Spec``: its ``radius_control``
    motor: MotorController
    transport: RegisterTransport
    latched: dict[str, Any] | None
    keeper_error: str | None
    run_id: str | None
    turning: bool  # a set-point other than 0 was set since the last stop
    drive: Any  # the drive's last read-back (``run/standstill.DriveCheck``)
    stream: Any  # the stream process (``serve.StreamLink``): ``ensure()`` its channel

    async def write(self, address: int, words: Sequence[int], what: str, retry: bool) -> dict[str, Any]: ...

    def tell(self, event: dict[str, Any], droppable: bool = False) -> None: ...


class DriveSide:
    """The procedure's register transport in the rig process: the drive's one connection, with the
    web process's rules (``RigProcess.write``: a held stop refuses a set-point other than 0; the
    crank counts as turning), and the rig process's keeper as the drive's only one
    (``drivers.motor.transport.PeerKeptWatchdog``)."""

    def __init__(self, rig: RigProcess) -> None:
        self.rig = rig
        self.description = f"the rig process's drive link ({rig.transport.description})"

    @property
    def connected(self) -> bool:
        return bool(getattr(self.rig.transport, "connected", False))

    async def open(self) -> None:
        """The drive's connection is the rig process's, open already."""

    async def read(self, address: int, count: int, what: str, function: int = 0x03) -> list[int]:
        return list(await self.rig.transport.read(address, count, what, function))

    async def write(self, address: int, words: Sequence[int], what: str, *, retry: bool = True) -> None:
        reply = await self.rig.write(address, words, what, retry)
        if "error" in reply:
            raise MotorStateError(f"register {what!r}: {reply['error']['detail']}")

    async def watchdog_status(self) -> None:
        if self.rig.keeper_error is not None:
            raise MotorLinkError("watchdog refresh (rig process)", self.rig.keeper_error[:300])

    async def close(self) -> None:
        """The connection stays the rig process's."""


class StreamAsker:
    """The rig process's own questions to the stream process (``streamclient.Asker`` for the
    procedure's ``RemoteStream``): ids of their own, answers taken off before they reach the web
    process (``StreamLink.read``)."""

    def __init__(self, rig: RigProcess) -> None:
        self.rig = rig
        self.on_stream: Callable[[dict[str, Any]], None] | None = None
        self.restarts = 0
        self.pending: dict[str, asyncio.Future[dict[str, Any]]] = {}
        self._ids = itertools.count(1)

    async def exchange(self, msg: dict[str, Any], timeout_s: float = 10.0) -> dict[str, Any]:
        n = f"rig-{next(self._ids)}"
        fut: asyncio.Future[dict[str, Any]] = asyncio.get_running_loop().create_future()
        self.pending[n] = fut
        try:
            writer = await self.rig.stream.ensure()
            writer.write(channel.encode({**msg, "id": n}))
            return await asyncio.wait_for(fut, timeout_s)
        except TimeoutError:
            raise MotorLinkError(str(msg.get("op")), f"the stream process did not answer within {timeout_s:g} s") \
                from None
        except OSError as exc:
            raise MotorLinkError(str(msg.get("op")), f"the stream process cannot be reached: {exc}") from None
        finally:
            self.pending.pop(n, None)

    def take(self, msg: dict[str, Any]) -> bool:
        """An answer to one of these questions, or a ``stream`` event (seen, not taken): True if taken."""
        if msg.get("event") == "stream":
            if self.on_stream is not None:
                self.on_stream(msg)
            return False
        fut = self.pending.get(str(msg.get("id")))
        if fut is None:
            return False
        if not fut.done():
            fut.set_result(msg)
        return True

    def lost(self, why: str) -> None:
        """The stream process ended: the questions in flight fail as the web process's do."""
        for fut in self.pending.values():
            if not fut.done():
                fut.set_result({"error": {"kind": "stream", "detail": why}})


@dataclass
class Devices:
    """``procedure.RigDevices`` in the rig process."""

    motor: MotorController
    daq: RecordingStream
    radius: RadiusActuator
    clock: Clock = REAL_CLOCK


@dataclass
class HostedRun:
    run_id: str
    procedure: Procedure
    task: asyncio.Task[None]
    radius: RadiusActuator


class RunHost:
    """The run carried out in the rig process (at most one) and the last runs' outcomes."""

    def __init__(self, rig: RigProcess) -> None:
        self.rig = rig
        self.asker = StreamAsker(rig)
        self.current: HostedRun | None = None
        self.outcomes: collections.OrderedDict[str, dict[str, Any]] = collections.OrderedDict()
        self._last_progress = 0.0
        self._phase: tuple[Any, ...] = ()
        self._starting = False  # a ``run_start`` connecting the procedure's driver to the drive

    @property
    def active(self) -> bool:
        return self.current is not None

    async def start(self, msg: dict[str, Any]) -> dict[str, Any]:
        """``run_start``: the run accepted (it goes on in a task of its own) or refused (``error``)."""
        run_id = str(msg["run_id"])[:80]
        if self.current is not None:
            return _refused(f"the rig process carries out run {self.current.run_id} already")
        if self._starting:
            return _refused("the rig process is starting another run")
        self._starting = True
        try:
            procedure_mod, stream_mod, config_mod, request_mod = _load()
            if self.rig.latched is not None:
                return _refused(f"the rig process holds a stop ({self.rig.latched['source']}: "
                                f"{self.rig.latched['detail']}); an operator acknowledges it first")
            try:
                cfg = config_mod.parse_config(msg["config"], "the run's configuration")
                plan = request_mod.Plan(cfg, tuple(request_mod.PlannedStep(**s) for s in msg["steps"]),
                                        dict(msg.get("provenance") or {}))
                daq = stream_mod.RemoteStream(self.asker, "", 0, "")
                daq.adopt(msg["hardware"])
                radius = self.radius(procedure_mod, float(msg["radius_m"]))
                steady = _criteria(msg.get("steady"))
            except Exception as exc:  # a plan that does not parse: refused, nothing moved
                return {"error": {"kind": "bad", "detail": f"run_start: {type(exc).__name__}: {exc}"[:500]}}
            reserve = msg.get("reserve_file")
            motor = MotorController(self.rig.motor.profile)
            await motor.connect(DriveSide(self.rig))
            proc = procedure_mod.Procedure(
                plan, Devices(motor, daq, radius), Path(str(msg["out_dir"])), run_id=run_id,
                on_progress=self.progress, steady=steady, reset_faults=bool(msg.get("reset_faults", False)),
                on_disk_full=(lambda: _release(Path(reserve))) if reserve else None)
            task = asyncio.create_task(self._carry_out(proc, daq), name=f"run-{run_id}")
            self.current = HostedRun(run_id, proc, task, radius)
        finally:
            self._starting = False
        self.rig.run_id = run_id
        self._phase, self._last_progress = (), 0.0
        log.info("run %s: carried out in the rig process (%d steps)", run_id, len(plan.steps))
        return {}

    def radius(self, procedure_mod: Any, radius_m: float) -> RadiusActuator:
        """The crank radius's actuator: the simulated rig's, on its control socket (the spec's
        ``radius_control``), else a radius set by hand."""
        if self.rig.spec.radius_control:
            from drivers.sim.process import SocketCrankRadius  # where the rig is built: the simulated rig

            return SocketCrankRadius(self.rig.spec.radius_control, radius_m)
        actuator: RadiusActuator = procedure_mod.FixedRadius(radius_m)
        return actuator

    async def _carry_out(self, proc: Procedure, daq: Any) -> None:
        run_id = proc.run_id
        out: dict[str, Any]
        try:
            outcome: RunOutcome = await proc.execute()
            out = {"status": outcome.exit_status, "reason": outcome.reason[:4000], "path": str(outcome.path),
                   "lost_samples": outcome.lost_samples}
        except Exception as exc:  # a programming error: said, the motor's stop is the procedure's own
            log.exception("run %s: the procedure failed", run_id)
            out = {"status": "failed", "reason": f"{type(exc).__name__}: {exc}"[:4000], "path": None,
                   "lost_samples": 0}
        finally:
            with contextlib.suppress(Exception):
                await proc.rig.motor.close()
            daq.detach()
        hosted = self.current
        out.update({"event": "run_end", "run_id": run_id, "motor_fault": list(proc.motor_fault or ()) or None,
                    "drive": proc.drive_check.to_dict() if proc.drive_check is not None else None,
                    "radius_m": hosted.radius.radius_m if hosted is not None else None, "at": time.time()})
        if proc.drive_check is not None:
            self.rig.drive = proc.drive_check
            if proc.drive_check.standstill:  # e.g. after its emergency stop, which sets no set-point of 0
                self.rig.turning = False
        self.outcomes[run_id] = out
        while len(self.outcomes) > KEEP_OUTCOMES:
            self.outcomes.popitem(last=False)
        self.current = None
        if self.rig.run_id == run_id:
            self.rig.run_id = None
        log.info("run %s ended in the rig process: %s %s", run_id, out["status"], out["reason"])
        self.rig.tell(out)

    def progress(self, p: Progress) -> None:
        """The procedure's progress, told at most every :data:`PROGRESS_PERIOD_S` (a new step or state
        at once); not queued for a web process that has not read the last ones."""
        phase = (p.state, p.step, p.step_state)
        now = time.monotonic()
        same = phase == self._phase
        if same and now - self._last_progress < PROGRESS_PERIOD_S:
            return
        self._phase, self._last_progress = phase, now
        self.rig.tell({"event": "run_progress", "run_id": p.run_id, "state": p.state, "step": p.step,
                       "n_steps": p.n_steps, "step_state": p.step_state, "samples": p.samples,
                       "lost_samples": p.lost_samples, "message": p.message[:500]}, droppable=same)

    def abort(self, reason: str, run_id: str | None = None, *, interrupt: bool = False) -> str | None:
        """Abort the run (``run_id``: only that one); ``interrupt``: as the station's end cuts it
        off (it ends ``interrupted``).  The run aborted, or None."""
        hosted = self.current
        if hosted is None or (run_id is not None and run_id != hosted.run_id):
            return None
        if interrupt:
            hosted.procedure.interrupt(reason[:500])
        else:
            hosted.procedure.abort(reason[:500])
        return hosted.run_id

    async def end(self, reason: str) -> None:
        """The web process or the daemon is gone: the run, if one goes on, is stopped and ends
        ``interrupted`` (as a run the daemon's end cuts off); returns once it ended."""
        hosted = self.current
        if hosted is None:
            return
        log.warning("run %s interrupted: %s", hosted.run_id, reason)
        self.abort(reason, interrupt=True)
        await asyncio.wait({hosted.task}, timeout=END_WAIT_S)

    def outcome(self, run_id: str) -> dict[str, Any]:
        """``run_outcome``: the run's outcome if it ended here (null while it goes on or if unknown)."""
        return {"running": self.current is not None and self.current.run_id == run_id,
                "outcome": self.outcomes.get(run_id)}


def preload_procedure() -> None:
    """Import the procedure's modules (numpy, h5py with them) now: the rig process does so before it
    reads its specification, at normal priority, so that no run's start pays for it."""
    _load()


def _load() -> tuple[Any, Any, Any, Any]:
    """The procedure's modules: procedure, stream client, configuration, request."""
    return tuple(importlib.import_module(m) for m in (  # type: ignore[return-value]
        "station.run.procedure", "station.rigproc.streamclient", "station.config", "station.run.request"))


def _refused(detail: str) -> dict[str, Any]:
    return {"error": {"kind": "refused", "register": "run", "detail": detail}}


def _criteria(d: dict[str, Any] | None) -> Any:
    if not d:
        return None
    from station.run.steady import SteadyCriteria

    return SteadyCriteria(**d)


def _release(path: Path) -> int:
    """The daemon's disk reserve freed so the recording can be closed (``service/disk.py``); bytes freed."""
    from station.service.disk import release_file  # loaded with the recording's modules, not at import

    size = release_file(path)
    if size:
        log.error("recordings disk full: reserve file of %.0f MiB released to close the recording", size / 2**20)
    return size
