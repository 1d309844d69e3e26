"""The daemon's side of the rig process: started, watched and started again by
:class:`RigSupervisor`; the web process's drive driver speaks to the drive through it
(:class:`ChannelTransport`, a register transport over the channel); :class:`RigProcessConnector`
is the daemon's rig connector (``service/riglink.RigConnector``) that puts them together.

With the simulated rig (``--sim``) the emulators run in a process of their own too
(``drivers.sim.process.SimRigProcess``): the rig process reaches the drive emulator over Modbus TCP and
the web process the DAQ emulator over its pseudo-terminal, as they would real devices.

Everything here runs on the rig thread's loop (``service/rigthread.py``), except :meth:`close`."""

from __future__ import annotations

import asyncio
import contextlib
import functools
import itertools
import json
import logging
import os
import subprocess
import sys
import tempfile
import threading
from collections.abc import AsyncIterator, Callable, Sequence
from pathlib import Path
from typing import Any

from drivers.motor.controller import MotorController
from drivers.motor.errors import (
    MotorExceptionReplyError,
    MotorLinkError,
    MotorProtocolError,
    MotorStateError,
    MotorTimeoutError,
)
from drivers.motor.profile import DriveProfile, load_profile
from station.config import StationConfig, to_rig_physics
from station.rigproc import channel
from station.rigproc.remoterun import RemoteProcedure
from station.rigproc.streamclient import RemoteStream
from station.run.hardware import check_daq_hardware
from station.run.procedure import FixedRadius, RadiusActuator
from station.run.rig import ConnectedRig
from station.service.settings import ServiceSettings

log = logging.getLogger("station.rigproc")

START_TIMEOUT_S = 60.0  # a rig process reports ready (or why not) within this (it waits for standstill)
ANSWER_TIMEOUT_S = 10.0  # bounds every question; the rig process's own Modbus time-outs are shorter
LINK_TIMEOUT_S = 3.0  # the rig process stops a turning crank when the web process is silent this long
RESTART_BACKOFF_S = (1.0, 2.0, 5.0, 10.0, 30.0)


def raise_error(err: dict[str, Any]) -> None:
    """Raise the driver error an ``error`` answer carries (as the drive's own transport would)."""
    what = str(err.get("register", "?"))
    kind = err.get("kind")
    if kind == "exception":
        raise MotorExceptionReplyError(what, int(err.get("function", 0)), int(err.get("code", 0)))
    detail = str(err.get("detail", ""))
    if kind == "timeout":
        raise MotorTimeoutError(what, detail)
    if kind == "protocol":
        raise MotorProtocolError(what, detail)
    if kind == "refused":
        raise MotorStateError(f"register {what!r}: {detail}")
    raise MotorLinkError(what, detail or "the rig process answered with an error")


class RigSupervisor:
    """The rig process (and, simulated, the emulators' process) for the daemon's lifetime."""

    def __init__(self, settings: ServiceSettings, motor_url: str | None = None,
                 radius_control: str | None = None) -> None:
        """``radius_control``: the simulated rig's control socket, where the rig process changes the
        crank radius during the runs it carries out (None: a radius set by hand)."""
        self.settings = settings
        self.radius_control = radius_control
        self.run_events: dict[str, Callable[[dict[str, Any]], None]] = {}  # a run's events (remoterun), by id
        self.cfg = settings.config
        self.motor_url = motor_url or self.cfg.devices.motor_url
        self.on_event: Callable[[dict[str, Any]], None] | None = None  # events (a stop given there), rig loop
        self.on_stream: Callable[[dict[str, Any]], None] | None = None  # the DAQ stream's events, rig loop
        self.page_port: int | None = None
        self.proc: subprocess.Popen[str] | None = None
        self.spare: subprocess.Popen[str] | None = None  # started ahead, not yet given its specification
        self.ready: dict[str, Any] = {}  # the rig process's ready line
        self.error: str | None = None  # why there is none
        self.run_id: str | None = None  # the run the crank turns for (``note_run``; again in every keeper question)
        self.restarts = 0
        self._dir = tempfile.mkdtemp(prefix="sinecal-rig-")
        self.socket = os.path.join(self._dir, "channel")
        self._writer: asyncio.StreamWriter | None = None
        self._pending: dict[int, asyncio.Future[dict[str, Any]]] = {}
        self._ids = itertools.count(1)
        self._tasks: set[asyncio.Task[Any]] = set()
        self._starting: asyncio.Lock | None = None  # made on the rig loop
        self.closing = False

    @property
    def connected(self) -> bool:
        return self._writer is not None and not self._writer.is_closing()

    # ------------------------------------------------------------------ the process
    def _spec(self) -> dict[str, Any]:
        from station.rigproc.stopport import station_names

        svc = self.cfg.service
        return {"socket": self.socket, "motor_url": self.motor_url, "device_id": self.cfg.devices.motor_device_id,
                "profile": self.cfg.rig.motor.profile,
                "stop_host": self.settings.host if self.settings.stop_port is not None else None,
                "stop_port": self.settings.stop_port or 0, "names": sorted(station_names(self.settings)),
                "page_port": self.page_port, "header_timeout_s": min(5.0, svc.header_timeout_s),
                "priority": svc.rig_priority, "link_timeout_s": LINK_TIMEOUT_S, "radius_control": self.radius_control}

    @staticmethod
    def popen() -> subprocess.Popen[str]:
        """A rig process, importing its modules until it reads its specification on stdin: started
        while the daemon starts (:meth:`RigProcessConnector.launch`), given its specification later."""
        return subprocess.Popen([sys.executable, "-m", "station.rigproc"], stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE, text=True, bufsize=1,
                                env={**os.environ, "PYTHONUNBUFFERED": "1"})

    def _spawn(self) -> dict[str, Any]:
        """Start a rig process (or take the one started ahead) and wait for its first line (blocking:
        run in a thread)."""
        proc, self.spare = self.spare, None
        if proc is None or proc.poll() is not None:
            proc = self.popen()
        assert proc.stdin is not None and proc.stdout is not None
        proc.stdin.write(json.dumps(self._spec()) + "\n")
        proc.stdin.flush()
        line: list[str] = []
        reader = threading.Thread(target=lambda: line.append(proc.stdout.readline()),  # type: ignore[union-attr]
                                  name="rig-process-start", daemon=True)
        reader.start()
        reader.join(START_TIMEOUT_S)
        first: dict[str, Any]
        try:
            first = json.loads(line[0]) if line and line[0] else {"error": f"ended with {proc.wait(5)}"}
        except (ValueError, subprocess.TimeoutExpired) as exc:
            first = {"error": f"no answer ({exc})"}
        if "ready" not in first:
            with contextlib.suppress(OSError):
                proc.stdin.close()
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(10)
            if proc.poll() is None:
                proc.kill()
            raise MotorLinkError("<rig process>", f"the rig process did not start: {first.get('error', first)}")
        self.proc = proc
        ready: dict[str, Any] = first["ready"]
        return ready

    async def start(self) -> None:
        """A rig process running and the channel to it connected (MotorLinkError if not)."""
        if self._starting is None:
            self._starting = asyncio.Lock()
        async with self._starting:  # the watch's restart and a run's reconnect never start two
            if self.proc is not None and self.proc.poll() is None and self.connected:
                return
            await self._start()

    async def _start(self) -> None:
        if self.proc is not None and self.proc.poll() is None:  # alive but not connected: ended first
            await asyncio.to_thread(self._end, self.proc, 10.0)
        self.ready = await asyncio.to_thread(self._spawn)
        log.info("rig process %d ready (%s; stop port %s); the drive: %s", self.ready["pid"],
                 self.ready["priority"], self.ready["stop_port"], self.ready["drive"]["detail"])
        reader, self._writer = await asyncio.open_unix_connection(self.socket, limit=channel.MAX_MESSAGE + 8)
        self._spawned(self._read(reader), "rig-channel")
        assert self.proc is not None
        self._spawned(self._watch(self.proc), "rig-process-watch")
        hello = await self.ask({"op": "hello"})
        if self.page_port is not None:
            await self.ask({"op": "page_port", "port": self.page_port})
        if hello.get("latched"):
            held = hello["latched"]
            self._event({"event": "stopped", "source": held["source"], "detail": held["detail"], "commanded": True,
                         "drive": self.ready.get("drive"), "credentials": {}})
        self.error = None

    def _spawned(self, coro: Any, name: str) -> None:
        task = asyncio.create_task(coro, name=name)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _watch(self, proc: subprocess.Popen[str]) -> None:
        """The rig process ended: said, and a new one started (it waits for standstill itself)."""
        code = await asyncio.to_thread(proc.wait)
        if self.closing or proc is not self.proc:
            return
        self.error = (f"the rig process ended (exit code {code}); the drive's own watchdog stops the crank; a new "
                      "one is started once the drive reads back standstill")
        log.error("%s", self.error)
        self._drop()
        for delay in itertools.chain(RESTART_BACKOFF_S, itertools.repeat(RESTART_BACKOFF_S[-1])):
            if self.closing:
                return
            try:
                await self.start()
                self.restarts += 1
                log.warning("rig process started again (%d since the daemon started)", self.restarts)
                return
            except Exception as exc:
                self.error = f"the rig process cannot be started again: {exc}"
                log.error("%s; next attempt in %g s", self.error, delay)
                await asyncio.sleep(delay)

    def _drop(self) -> None:
        writer, self._writer = self._writer, None
        if writer is not None:
            writer.close()
        for fut in self._pending.values():
            if not fut.done():
                fut.set_exception(MotorLinkError("<rig process>", "the channel to the rig process closed"))
        self._pending.clear()
        for handler in list(self.run_events.values()):  # a run carried out there is lost with it
            handler({"event": "lost", "detail": self.error or "the channel to the rig process closed"})

    # ------------------------------------------------------------------ the channel
    async def _read(self, reader: asyncio.StreamReader) -> None:
        async for msg in channel.messages(reader, "the rig process", log):
            if msg.get("event") == "stream":
                if self.on_stream is not None:
                    self.on_stream(msg)
                continue
            if msg.get("event") in ("run_progress", "run_end"):
                handler = self.run_events.get(str(msg.get("run_id")))
                if handler is not None:
                    handler(msg)
                elif msg["event"] == "run_end":
                    log.warning("the rig process ended run %s (%s: %s); no run of this process waits for it",
                                msg.get("run_id"), msg.get("status"), msg.get("reason"))
                continue
            if "event" in msg:
                self._event(msg)
                continue
            fut = self._pending.pop(int(msg.get("id") or 0), None)
            if fut is not None and not fut.done():
                fut.set_result(msg)
        if self._writer is not None and reader is not None:
            self._drop()

    def _event(self, msg: dict[str, Any]) -> None:
        if msg.get("event") == "stopping":
            log.warning("the rig process gives a stop (%s)", msg.get("source"))
        else:
            log.warning("the rig process reports a stop (%s): %s", msg.get("source"), msg.get("detail"))
        if self.on_event is not None:
            try:
                self.on_event(msg)
            except Exception:
                log.exception("handling the rig process's stop failed")

    async def ask(self, msg: dict[str, Any], timeout_s: float = ANSWER_TIMEOUT_S) -> dict[str, Any]:
        """The answer to ``msg``; the driver error it carries raised; MotorLinkError without a channel."""
        reply = await self.exchange(msg, timeout_s)
        if "error" in reply:
            raise_error(reply["error"])
        return reply

    async def exchange(self, msg: dict[str, Any], timeout_s: float = ANSWER_TIMEOUT_S) -> dict[str, Any]:
        """The answer to ``msg`` as it came (an ``error`` in it not raised); MotorLinkError without
        a channel, MotorTimeoutError without an answer within ``timeout_s``."""
        writer = self._writer
        if writer is None or writer.is_closing():
            raise MotorLinkError(str(msg.get("what", msg.get("op"))), self.error or "no rig process")
        n = next(self._ids)
        fut: asyncio.Future[dict[str, Any]] = asyncio.get_running_loop().create_future()
        self._pending[n] = fut
        writer.write(channel.encode({**msg, "id": n}))
        try:
            reply = await asyncio.wait_for(fut, timeout_s)
        except TimeoutError:
            self._pending.pop(n, None)
            raise MotorTimeoutError(str(msg.get("what", msg.get("op"))),
                                    f"the rig process did not answer within {timeout_s:g} s") from None
        return reply

    def send(self, msg: dict[str, Any]) -> bool:
        """Send ``msg`` without waiting for its answer (an abort from a synchronous caller, in the
        order of the channel); False without a channel."""
        writer = self._writer
        if writer is None or writer.is_closing():
            return False
        writer.write(channel.encode({**msg, "id": next(self._ids)}))
        return True

    async def release(self) -> None:
        """The operator acknowledged: the rig process no longer holds its stop."""
        await self.ask({"op": "release"})

    async def note_run(self, run_id: str | None) -> None:
        """Tell the rig process which run the crank turns for (``None``: none), so that a stop on its
        stop port names the run it stops."""
        self.run_id = run_id
        await self.ask({"op": "run", "run_id": run_id})

    async def tell_page_port(self, port: int) -> None:
        self.page_port = port
        if self.connected:
            await self.ask({"op": "page_port", "port": port})

    def close(self, timeout_s: float = 15.0) -> None:
        """End the rig process (it stops a turning crank first); from any thread, after the rig loop."""
        self.closing = True
        for proc in (self.proc, self.spare):
            if proc is not None:
                self._end(proc, timeout_s)
        self.proc = self.spare = None
        with contextlib.suppress(OSError):
            Path(self.socket).unlink(missing_ok=True)
            os.rmdir(self._dir)


    @staticmethod
    def _end(proc: subprocess.Popen[str], timeout_s: float) -> None:
        if proc.poll() is not None:
            return
        assert proc.stdin is not None
        with contextlib.suppress(OSError):
            proc.stdin.close()  # its lifeline: it stops a turning crank and ends
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            log.error("the rig process did not end within %g s: killed", timeout_s)
            proc.kill()
            proc.wait()


class ChannelTransport:
    """The drive's registers through the rig process (a ``drivers.motor.transport.RegisterTransport``)."""

    def __init__(self, supervisor: RigSupervisor) -> None:
        self.supervisor = supervisor
        self.description = f"the rig process ({supervisor.motor_url})"

    @property
    def connected(self) -> bool:
        return self.supervisor.connected

    @property
    def error(self) -> str | None:
        """Why the rig process cannot be reached (for /health); None while it can."""
        return None if self.supervisor.connected else self.supervisor.error

    async def open(self) -> None:
        await self.supervisor.start()

    async def read(self, address: int, count: int, what: str, function: int = 0x03) -> list[int]:
        reply = await self.supervisor.ask({"op": "read", "address": address, "count": count, "what": what,
                                           "function": function})
        words = reply.get("words")
        if not isinstance(words, list) or len(words) != count:
            raise MotorProtocolError(what, f"expected {count} register(s) from the rig process, got {words!r}"[:200])
        return [int(w) for w in words]

    async def write(self, address: int, words: Sequence[int], what: str, *, retry: bool = True) -> None:
        await self.supervisor.ask({"op": "write", "address": address, "words": [int(w) for w in words],
                                   "what": what, "retry": retry})

    async def watchdog_status(self) -> None:
        """The rig process refreshes the drive's watchdog (its keeper is the drive's only one): ask
        whether its refreshes go through (``drivers.motor.transport.PeerKeptWatchdog``); the question
        is also this process's sign of life to it, and names the run the crank turns for (a ``run``
        message lost to a channel being re-established is made good within one keeper period)."""
        reply = await self.supervisor.ask({"op": "keeper", "run_id": self.supervisor.run_id})
        err = reply.get("keeper_error")
        if err:
            raise MotorLinkError("watchdog refresh (rig process)", str(err)[:300])

    async def close(self) -> None:
        """The web process's driver lets go; the rig process and its connection stay."""


class RigProcessConnector:
    """The daemon's rig: the drive and the DAQ stream into the recording through the rig process.
    Simulated (``sim``), the emulators are started once, in a process of their own."""

    def __init__(self, settings: ServiceSettings) -> None:
        self.settings = settings
        self.emulators: Any = None  # drivers.sim.process.SimRigProcess when simulated
        self.supervisor: RigSupervisor | None = None
        self.on_event: Callable[[dict[str, Any]], None] | None = None  # a stop the rig process gave (rig loop)
        self.spare: subprocess.Popen[str] | None = None  # the rig process started ahead (``launch``)

    def launch(self) -> None:
        """Start the rig process (it imports its modules, then waits for its specification) and,
        simulated, the emulators' process now, while the daemon starts: they take seconds, in parallel."""
        if self.supervisor is None and self.spare is None:
            self.spare = RigSupervisor.popen()
        self.launch_emulators()

    def launch_emulators(self) -> None:
        """Simulated: start the emulators' process now (:meth:`__enter__` waits until it serves)."""
        if self.settings.sim and self.emulators is None:
            from drivers.sim.process import SimRigProcess

            cfg = self.settings.config
            seed = cfg.simulation.seed if cfg.simulation else 0
            self.emulators = SimRigProcess(seed=seed, crank_radius_m=cfg.plan.steps[0].crank_radius_m,
                                           profile=cfg.rig.motor.profile, daq_link=cfg.devices.daq_link).launch()

    def _ensure(self, cfg: StationConfig, sim: bool) -> RigSupervisor:
        if self.supervisor is not None:
            return self.supervisor
        url = None
        if sim:
            self.launch_emulators()
            emu = self.emulators.__enter__()
            emu.load_physics(to_rig_physics(cfg))
            url = emu.addresses.modbus_tcp_url
            log.info("simulated rig: the emulators in process %s (Modbus TCP %s, DAQ %s)", emu.pid,
                     url, emu.addresses.daq)
        self.supervisor = RigSupervisor(self.settings, url, self.emulators.addresses.control if sim else None)
        self.supervisor.spare, self.spare = self.spare, None
        self.supervisor.on_event = self._event
        return self.supervisor

    def _event(self, msg: dict[str, Any]) -> None:
        if self.on_event is not None:
            self.on_event(msg)

    @contextlib.asynccontextmanager
    async def __call__(self, cfg: StationConfig, sim: bool) -> AsyncIterator[ConnectedRig]:
        sup = await asyncio.to_thread(self._ensure, cfg, sim)
        profile = load_profile(cfg.rig.motor.profile)
        dev = cfg.devices
        emu = self.emulators
        daq_port = emu.addresses.daq if emu is not None else dev.daq_port
        motor, daq = await self._connect(cfg, profile, sup, daq_port)
        try:
            if emu is not None:
                actuator: RadiusActuator = emu.radius_actuator(cfg.plan.steps[0].crank_radius_m)
                yield ConnectedRig(motor, daq, actuator, f"simulated rig (emulators' process {emu.pid}; drive via the "
                                   f"rig process {sup.ready.get('pid')}, DAQ {daq_port})", simulated=True,
                                   on_load=emu.load_physics, release=sup.release, on_run=sup.note_run,
                                   remote=functools.partial(RemoteProcedure, sup))
            else:
                yield ConnectedRig(motor, daq, FixedRadius(dev.crank_radius_m),
                                   f"rig (motor {profile.name} at {dev.motor_url} via the rig process "
                                   f"{sup.ready.get('pid')}, DAQ {dev.daq_port})", release=sup.release,
                                   on_run=sup.note_run, remote=functools.partial(RemoteProcedure, sup))
        finally:
            with contextlib.suppress(Exception):
                await motor.close()
            with contextlib.suppress(Exception):
                await asyncio.to_thread(daq.close)

    @staticmethod
    async def _connect(cfg: StationConfig, profile: DriveProfile, sup: RigSupervisor,
                       daq_port: str) -> tuple[MotorController, RemoteStream]:
        """The drive's driver and the DAQ stream, both through the rig process, and the configuration
        checked against what the bridge reports (``run/hardware.py``); nothing is written to the drive."""
        motor = MotorController(profile)
        await motor.connect(ChannelTransport(sup))
        daq = RemoteStream(sup, daq_port, cfg.devices.daq_baudrate, cfg.devices.daq_link)
        try:
            hw = await daq.connect()
            check_daq_hardware(cfg, hw)
        except BaseException:
            await asyncio.to_thread(daq.close)
            with contextlib.suppress(Exception):
                await motor.close()
            raise
        log.info("DAQ bridge (via the rig process): %s; %s, %d bits", hw.identity, hw.adc, hw.adc_bits)
        return motor, daq

    def close(self) -> None:
        """End the rig process, then the emulators (after the rig thread's loop ended)."""
        if self.supervisor is not None:
            self.supervisor.close()
        if self.spare is not None:  # started ahead, never given its specification
            RigSupervisor._end(self.spare, 5.0)
            self.spare = None
        if self.emulators is not None:
            self.emulators.__exit__(None, None, None)
            self.emulators = None
