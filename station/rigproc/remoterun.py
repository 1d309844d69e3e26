"""The web process's side of a run carried out in the rig process (``runhost.py``):
:class:`RemoteProcedure`, the remote form of ``run/procedure.Procedure`` for the daemon's run
manager (``service/runs.py``), with the same outcome (``RunOutcome``, ``motor_fault``,
``drive_check``).

It asks the rig process to carry out the plan (``run_start``: the plan, the run's id, the recordings
folder, the DAQ bridge as the web process connected it, the crank radius now), follows the
``run_progress`` events into ``on_progress``, and returns the outcome the ``run_end`` event carries.
An abort is a message (``run_abort``); a cancellation (the station stops) asks for the run to be
interrupted there (it ends ``interrupted``, as a cancelled procedure does) and waits for its outcome.

Everything here runs on the rig thread's loop (``service/rigthread.py``)."""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any, Protocol

from drivers.motor.errors import MotorLinkError
from station.run.procedure import Progress, RunFailure, RunOutcome
from station.run.request import Plan
from station.run.rig import ConnectedRig
from station.run.standstill import DriveCheck

log = logging.getLogger("station.rigproc")

START_TIMEOUT_S = 60.0  # the plan parsed and the procedure's driver connected there (a loaded machine: slow)
END_WAIT_S = 120.0  # a cancelled run's stop, read-back and recording's close in the rig process


class RunChannel(Protocol):
    """The channel to the rig process as a run uses it (``client.RigSupervisor``)."""

    run_events: dict[str, Callable[[dict[str, Any]], None]]

    async def ask(self, msg: dict[str, Any], timeout_s: float = ...) -> dict[str, Any]: ...

    def send(self, msg: dict[str, Any]) -> bool: ...


def plan_message(plan: Plan) -> dict[str, Any]:
    """The plan as it crosses to the rig process (``runhost.RunHost.start`` builds it again)."""
    cfg = plan.config.model_dump(mode="json", exclude_none=True, exclude={"service": {"token"}})
    return {"config": cfg, "steps": [dict(s.__dict__) for s in plan.steps], "provenance": plan.provenance}


class RemoteProcedure:
    """A run carried out in the rig process (module docstring); ``runs.Runs`` uses it as it uses a
    ``Procedure`` (``run/procedure.RunProcedure``)."""

    def __init__(self, channel: RunChannel, plan: Plan, rig: ConnectedRig, out_dir: Path, *, run_id: str,
                 on_progress: Callable[[Progress], None], disk_reserve: Path | None = None) -> None:
        self.channel = channel
        self.plan = plan
        self.rig = rig
        self.out_dir = Path(out_dir)
        self.run_id = run_id
        self.progress = Progress(run_id, n_steps=len(plan.steps))
        self._on_progress = on_progress
        self.disk_reserve = disk_reserve
        self.motor_fault: tuple[int, str] | None = None
        self.drive_check: DriveCheck | None = None
        self.abort_reason = ""
        self._started = False
        self._ended: asyncio.Future[dict[str, Any]] | None = None

    def abort(self, reason: str = "aborted by operator") -> None:
        """Stop the run (a message to the rig process); the first reason given stays."""
        if not self.abort_reason:
            self.abort_reason = reason
        if self._started:
            self._abort_there(self.abort_reason)

    async def execute(self) -> RunOutcome:
        loop = asyncio.get_running_loop()
        self._ended = loop.create_future()
        self.channel.run_events[self.run_id] = self._event
        try:
            return await self._execute(self._ended)
        finally:
            self.channel.run_events.pop(self.run_id, None)

    async def _execute(self, ended: asyncio.Future[dict[str, Any]]) -> RunOutcome:
        hw = self.rig.daq.hardware
        if hw is None:
            raise RunFailure("the DAQ bridge is not connected: the run cannot be handed to the rig process")
        try:
            await self.channel.ask({"op": "run_start", "run_id": self.run_id, **plan_message(self.plan),
                                    "out_dir": str(self.out_dir), "hardware": asdict(hw),
                                    "radius_m": self.rig.radius.radius_m,
                                    "reserve_file": str(self.disk_reserve) if self.disk_reserve else None},
                                   START_TIMEOUT_S)
        except asyncio.CancelledError:
            self._abort_there("the station was stopped", interrupt=True)
            raise
        except MotorLinkError:  # no answer: a run started there after all is stopped
            self._abort_there("the daemon did not hear the rig process take the run")
            raise
        self._started = True
        self.progress.state = "running"
        if self.abort_reason:
            self._abort_there(self.abort_reason)
        try:
            end = await asyncio.shield(ended)
        except asyncio.CancelledError:  # the station stops: the procedure's own cancellation there
            self._abort_there(self.abort_reason or "the station was stopped during the run", interrupt=True)
            await asyncio.wait({ended}, timeout=END_WAIT_S)
            if not ended.done() or ended.exception() is not None:
                raise
            end = ended.result()
        return self._outcome(end)

    def _abort_there(self, reason: str, *, interrupt: bool = False) -> None:
        """``run_abort`` for this run (``interrupt``: it ends ``interrupted``, as the station's end cuts it off)."""
        self.channel.send({"op": "run_abort", "run_id": self.run_id, "reason": reason, "interrupt": interrupt})

    def _outcome(self, end: dict[str, Any]) -> RunOutcome:
        if end.get("motor_fault"):
            code, name = end["motor_fault"]
            self.motor_fault = (int(code), str(name))
        if end.get("drive"):
            self.drive_check = DriveCheck.from_dict(end["drive"])
        if isinstance(end.get("radius_m"), int | float):
            with contextlib.suppress(AttributeError):
                self.rig.radius.radius_m = float(end["radius_m"])
        status, reason = str(end["status"]), str(end.get("reason", ""))
        if not end.get("path"):
            raise RunFailure(f"the rig process ended the run {status} without a recording: {reason}")
        return RunOutcome(self.run_id, Path(end["path"]), status, reason, int(end.get("lost_samples") or 0))

    def _event(self, msg: dict[str, Any]) -> None:
        """``run_progress``, ``run_end`` (the outcome) or ``lost`` (the channel to the rig process closed)."""
        ended = self._ended
        kind = msg.get("event")
        if kind == "run_progress":
            p = self.progress
            for k in ("state", "step", "n_steps", "step_state", "samples", "lost_samples", "message"):
                if k in msg:
                    setattr(p, k, msg[k])
            self._on_progress(p)
        elif ended is not None and not ended.done():
            if kind == "run_end":
                ended.set_result(msg)
            else:
                ended.set_exception(MotorLinkError("<rig process>", f"the run was lost with the rig process: "
                                                   f"{msg.get('detail', 'its channel closed')}"))
