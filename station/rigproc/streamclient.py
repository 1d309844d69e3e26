"""The web process's DAQ stream under the rig process: :class:`RemoteStream`, a
``run/stream.RecordingStream`` whose every step is a question of ``channel.py``'s table (``daq_*``,
``record_*``), answered by the stream process (``streamproc.py``) through the rig process, and whose
counts come from the ``stream`` events.  No sample crosses: the procedure learns how many arrived,
how many were lost in a window and whether the newest windows are steady.

Everything here runs on the rig thread's loop (``service/rigthread.py``), except :meth:`close`."""

from __future__ import annotations

import asyncio
import contextlib
import errno
import json
import logging
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any, Protocol

from drivers.daq.bridge import (
    DaqCommandError,
    DaqConfig,
    DaqHardware,
    DaqLinkBudgetError,
    DaqTimeoutError,
)
from drivers.daq.link import DaqLinkError
from drivers.motor.errors import MotorError
from station.errors import StationError
from station.recording import ChannelSpec, RunMetadata
from station.recording.writer import DiskFullError, jsonable
from station.run.acquisition import AcquisitionError
from station.run.steady import SteadyCriteria
from station.run.stream import StreamEnd

log = logging.getLogger("station.rigproc")

TEXT_PART = 8 * 1024  # characters of a long text per message (JSON may escape each to 6 bytes: < 64 KiB)
CONNECT_TIMEOUT_S = 30.0  # the first question starts the stream process (numpy, h5py: seconds on a busy machine)
STOP_TIMEOUT_S = 30.0  # STOP, the trailing gap, the disk queue written out; closing the file
_DAQ_ERRORS: dict[str, type[Exception]] = {
    "DaqLinkError": DaqLinkError, "DaqCommandError": DaqCommandError, "DaqTimeoutError": DaqTimeoutError,
    "DaqLinkBudgetError": DaqLinkBudgetError}


class Asker(Protocol):
    """Who carries the questions to the rig process (``client.RigSupervisor``)."""

    on_stream: Callable[[dict[str, Any]], None] | None
    restarts: int  # rig processes started again since the daemon started

    async def exchange(self, msg: dict[str, Any], timeout_s: float = ...) -> dict[str, Any]: ...


def stream_error(err: dict[str, Any]) -> Exception:
    """The exception an ``error`` answer of the stream process stands for (the in-process stream's
    own types: the procedure and the daemon tell them apart as they do there)."""
    detail = str(err.get("detail", ""))
    kind = err.get("kind")
    if kind == "daq":
        return _DAQ_ERRORS.get(str(err.get("type")), DaqCommandError)(detail)
    if kind == "disk":
        return DiskFullError(detail) if err.get("reserve") else OSError(errno.ENOSPC, detail)
    if kind == "recording":
        return StationError(detail)
    if kind == "stream":
        return AcquisitionError(f"DAQ stream lost: {detail}")
    return AcquisitionError(f"the stream process refused {err.get('type', kind)}: {detail}")


class RemoteStream:
    """:class:`~station.run.stream.RecordingStream` under the rig process (module docstring)."""

    def __init__(self, supervisor: Asker, port: str, baudrate: int, kind: str) -> None:
        self.supervisor = supervisor
        self.port, self.baudrate, self.kind = port, baudrate, kind
        self._hardware: DaqHardware | None = None
        self._samples = 0
        self._lost = 0
        self._error: str | None = None  # the stream's error in this run (``stream`` events)
        self._lost_link: str | None = None  # the bridge or the stream process lost
        self._partial: Path | None = None
        self._closed_as: tuple[str, str] | None = None
        self._restarts = supervisor.restarts  # a new rig process has a new stream process: connected anew
        self._loop = asyncio.get_running_loop()
        supervisor.on_stream = self._event

    # ------------------------------------------------------------------ the questions
    async def _ask(self, op: str, timeout_s: float = 10.0, **fields: Any) -> dict[str, Any]:
        try:
            reply = await self.supervisor.exchange({"op": op, **fields}, timeout_s)
        except MotorError as exc:  # no rig process, or no answer in time
            raise AcquisitionError(f"DAQ stream: the rig process did not answer {op} ({exc})") from exc
        if "error" in reply:
            exc2 = stream_error(reply["error"])
            if isinstance(exc2, DaqLinkError) or reply["error"].get("kind") == "stream":
                self._lost_link = str(exc2)
            raise exc2
        return reply

    def _event(self, msg: dict[str, Any]) -> None:
        if msg.get("samples") is not None:
            self._samples = int(msg["samples"])
            self._lost = int(msg.get("lost") or 0)
        if msg.get("error"):
            self._error = str(msg["error"])[:2000]
            if msg.get("samples") is None:  # the stream process ended
                self._lost_link = self._error

    async def connect(self) -> DaqHardware:
        """The bridge connected under the rig process (STOP, drain, idle, ``HW?``); what it reports."""
        r = await self._ask("daq_connect", CONNECT_TIMEOUT_S, port=self.port, baudrate=self.baudrate, kind=self.kind)
        hw = r.get("hardware")
        if not isinstance(hw, dict):
            raise DaqCommandError(f"the stream process reported no hardware: {r!r}"[:300])
        self.adopt(hw)
        assert self._hardware is not None
        return self._hardware

    def adopt(self, hardware: dict[str, Any]) -> None:
        """The bridge connected already (by the web process, as ``hardware`` reports it): this
        stream asks the stream process on (the procedure carried out in the rig process)."""
        self._hardware = DaqHardware(**{**hardware, "channels": tuple(hardware["channels"])})
        self._lost_link = None

    def detach(self) -> None:
        """Hear no more of the stream's events (the bridge stays connected: the web process's)."""
        if self.supervisor.on_stream == self._event:
            self.supervisor.on_stream = None

    @property
    def hardware(self) -> DaqHardware | None:
        return self._hardware

    @property
    def link_error(self) -> str | None:
        if self.supervisor.restarts != self._restarts:
            return "the rig process was started again: the DAQ bridge is connected anew"
        return self._lost_link

    @property
    def samples(self) -> int:
        return self._samples

    @property
    def lost_samples(self) -> int:
        return self._lost

    @property
    def closed_as(self) -> tuple[str, str] | None:
        return self._closed_as

    @property
    def partial_path(self) -> Path:
        if self._partial is None:
            raise RuntimeError("no recording is open")
        return self._partial

    async def configure(self, *, rate_hz: float, range_disp_V: float, range_force_V: float) -> DaqConfig:
        r = await self._ask("daq_configure", rate_hz=rate_hz, range_disp_V=range_disp_V, range_force_V=range_force_V)
        return DaqConfig(**r["config"])

    async def open(self, out_dir: Path, meta: RunMetadata, channels: tuple[ChannelSpec, ChannelSpec], *,
                   plan: dict[str, Any], min_free_bytes: int) -> None:
        texts = {"config_yaml": meta.config_yaml, "drive_profile_yaml": meta.drive_profile_yaml,
                 "plan": json.dumps(plan, default=jsonable)}
        for field, text in texts.items():
            for k in range(0, len(text or ""), TEXT_PART):
                await self._ask("record_text", field=field, text=(text or "")[k:k + TEXT_PART])
        fields = {k: v for k, v in asdict(meta).items() if k not in ("config_yaml", "drive_profile_yaml")}
        self._samples, self._lost, self._error, self._partial, self._closed_as = 0, 0, None, None, None
        r = await self._ask("record_open", out_dir=str(out_dir), meta=fields,
                            channels=[asdict(c) for c in channels], min_free_bytes=min_free_bytes)
        self._partial = Path(r["partial"])

    async def start(self) -> None:
        await self._ask("record_start")

    def check(self) -> None:
        if self._error is not None:
            raise AcquisitionError(self._error)

    async def steady(self, f_set_hz: float, fs: float, crit: SteadyCriteria) -> bool | None:
        r = await self._ask("record_steady", f_set_hz=f_set_hz, fs=fs, criteria=crit.to_dict())
        return None if r.get("steady") is None else bool(r["steady"])

    async def lost_between(self, start: int, stop: int) -> int:
        return int((await self._ask("record_lost", start=int(start), stop=int(stop)))["lost"])

    async def add_step(self, **fields: Any) -> None:
        await self._ask("record_step", **fields)

    async def stop(self) -> StreamEnd:
        try:
            r = await self._ask("record_stop", STOP_TIMEOUT_S)
        except Exception as exc:
            log.warning("shutdown step failed: %s", exc)
            return StreamEnd(self._lost, None)
        if r.get("samples") is not None:
            self._samples = int(r["samples"])
        err = r.get("disk_error")
        return StreamEnd(int(r.get("lost") or 0), stream_error(err) if err else None)

    async def finish(self, status: str, reason: str) -> Path:
        r = await self._ask("record_finish", STOP_TIMEOUT_S, status=status, reason=reason)
        if r.get("closed_as"):  # closed before: a lost web process (the rig process's decision)
            log.error("the recording %s was closed as %s by the stream process (%s); not as %s", r["path"],
                      r["closed_as"], r.get("reason"), status)
            self._closed_as = (str(r["closed_as"]), str(r.get("reason", "")))
        return Path(r["path"])

    async def abandon(self) -> None:
        try:
            await self._ask("record_abandon", STOP_TIMEOUT_S)
        except Exception as exc:
            log.error("the recording could not be abandoned: %s", exc)

    def close(self) -> None:
        """Let go of the bridge (from a thread other than the rig loop's; errors logged)."""
        self.detach()
        with contextlib.suppress(Exception):
            asyncio.run_coroutine_threadsafe(self._ask("daq_close"), self._loop).result(5.0)
