"""The rig process itself (``python -m station.rigproc``; started by the daemon, ``client.py``).

It holds the drive's one connection and, on its own, without waiting for the web process:

* refreshes the drive's communication watchdog every 0.2 s (while it lives, the drive turns only
  as the web process's set-points say; when it dies, the drive's own watchdog stops the crank);
* serves the stop port (``commands/stopport.StopPort``): the emergency stop on the drive, then the
  drive read back to standstill, answered from here; the web process is told afterwards;
* carries out the run's procedure the web process asks for (``runhost.py``): a silent web process
  does not end it; its connection closing or the lifeline's end interrupts it;
* stops the crank (ramp down, read back, the emergency stop if it still turns) when the web
  process falls silent for ``link_timeout_s`` while the crank turns outside such a run, or its
  connection closes while the crank turns, or the daemon's end of the lifeline (stdin) closes; then
  it holds the stop;
* while it holds a stop, refuses any set-point other than 0 the web process sends, until the
  operator's acknowledgement releases it (``release``);
* forwards the web process's register reads and writes (``channel.py``) to the drive; its keeper
  is the drive's only one (the web process's keeper asks it, ``keeper``, whether the refreshes go
  through, and that question keeps the link alive).

On start it connects and reads the drive back: it reports ready (one JSON line on stdout) only
once the drive reports standstill, else it ends with exit code 4 and one line saying why."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from drivers.motor.controller import MotorController
from drivers.motor.errors import (
    MotorCommunicationError,
    MotorError,
    MotorExceptionReplyError,
    MotorLinkError,
    MotorProtocolError,
    MotorTimeoutError,
)
from drivers.motor.profile import load_profile
from drivers.motor.transport import RegisterTransport, transport_from_url
from station.rigproc import channel
from station.rigproc.runhost import BACKLOG_BYTES, RunHost, preload_procedure
from station.rigproc.stopport import StopPort
from station.rigproc.turns import OneAtATime, Urgency, set_task_urgency, urgency
from station.run.standstill import DriveCheck, read_back_standstill
from station.service.priority import Priority, lower_below_rig, raise_priority

log = logging.getLogger("station.rigproc")

KEEPER_PERIOD_S = 0.2
START_STANDSTILL_S = 30.0  # a new rig process waits at most this long for the crank to come to rest


@dataclass(frozen=True)
class Spec:
    """What the daemon gives a rig process (one JSON line on its stdin)."""

    socket: str  # the channel's Unix socket path
    motor_url: str  # modbus-tcp://host:port or modbus-rtu:///dev/ttyX
    device_id: int | None
    profile: str | None  # the drive profile (shipped name or YAML path)
    stop_host: str | None  # the stop port's address (None: no stop port)
    stop_port: int
    names: tuple[str, ...]  # taken in the stop port's Host header besides loopback names and addresses
    page_port: int | None
    header_timeout_s: float
    priority: Priority
    link_timeout_s: float
    radius_control: str | None = None  # the simulated rig's control socket (its crank radius); None: set by hand

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Spec:
        return cls(str(d["socket"]), str(d["motor_url"]), d.get("device_id"), d.get("profile"),
                   d.get("stop_host"), int(d.get("stop_port", 0)), tuple(d.get("names", ())), d.get("page_port"),
                   float(d.get("header_timeout_s", 5.0)), d.get("priority", "normal"),
                   float(d.get("link_timeout_s", 3.0)), d.get("radius_control"))


def error_of(exc: BaseException) -> dict[str, Any]:
    """A driver failure as it travels over the channel (``client.raise_error`` raises it again)."""
    register = getattr(exc, "register", "?")
    if isinstance(exc, MotorExceptionReplyError):
        return {"kind": "exception", "register": register, "function": exc.function_code, "code": exc.exception_code}
    kind = ("link" if isinstance(exc, MotorLinkError) else "timeout" if isinstance(exc, MotorTimeoutError)
            else "protocol" if isinstance(exc, MotorProtocolError) else "link")
    detail = str(exc)
    if isinstance(exc, MotorCommunicationError):
        detail = detail.split(": ", 1)[-1]
    return {"kind": kind, "register": register, "detail": f"{type(exc).__name__}: {detail}"
            if not isinstance(exc, MotorError) else detail}


class RigProcess:
    """The rig process's state, on its one event loop."""

    def __init__(self, spec: Spec, motor: MotorController) -> None:
        self.spec = spec
        self.motor = motor
        self.transport: RegisterTransport = motor.transport
        p = motor.profile
        sp = p[p.setpoint]
        self.setpoint = (sp.address, sp.words)
        self.rewrite = p[p.watchdog.rewrite] if p.watchdog.rewrite is not None else None
        self.rewrite_words: list[int] | None = None  # the last words the web process wrote there
        self.io = asyncio.Lock()  # a rewrite refresh never interleaves with the web process's write of it
        self.loop = asyncio.get_running_loop()
        self.latched: dict[str, Any] | None = None  # the stop it holds
        self.count = 0
        self.drive: DriveCheck | None = None
        self.web: asyncio.StreamWriter | None = None
        self.serving: set[asyncio.Task[Any]] = set()  # ``serve_web``, one per connection of the web process
        self.heard = time.monotonic()  # the web process's last question
        self.turning = False  # the web process has set a set-point other than 0 since the last stop
        self.run_id: str | None = None  # the run the crank turns for, as the web process told (op "run")
        self.stop_port: StopPort | None = None
        self.counter = 0
        self.done = asyncio.Event()
        self.keeper_error: str | None = None
        self.answering: set[asyncio.Task[None]] = set()
        self.stream = StreamLink(self)  # the stream process: the DAQ stream into the recording
        self.runs = RunHost(self)  # the run's procedure, carried out here

    # ------------------------------------------------------------------ the drive
    async def keeper(self) -> None:
        """Refresh the drive's watchdog the way it counts it, every :data:`KEEPER_PERIOD_S`."""
        p = self.motor.profile
        set_task_urgency(Urgency.KEEPER)  # its exchanges go before the web process's (``turns``)
        while True:
            try:
                if p.watchdog.refresh is not None:
                    self.counter = (self.counter + 1) & 0xFFFF
                    await self.motor.write(p.watchdog.refresh, self.counter)
                elif self.rewrite is not None:
                    reg = self.rewrite
                    async with self.io:
                        words = self.rewrite_words or await self.transport.read(
                            reg.address, reg.words, f"{reg.name} (watchdog refresh)", reg.read_function)
                        await self.transport.write(reg.address, words, f"{reg.name} (watchdog refresh)")
                else:
                    await self.motor.read_status()
                if self.keeper_error is not None:
                    log.info("watchdog refresh works again")
                self.keeper_error = None
            except MotorError as exc:
                if self.keeper_error is None:
                    log.error("watchdog refresh failed: %s (the drive stops the crank on its own)", exc)
                self.keeper_error = str(exc)
            await asyncio.sleep(KEEPER_PERIOD_S)

    async def stop(self, source: str, why: str, credentials: dict[str, str] | None = None) -> dict[str, Any]:
        """The emergency stop on the drive, the stop held, the drive read back; the web process told.
        The answer has the shape of the main port's (``StopOut``); it names the run the crank turned
        for when the stop was given (the run may end, and say so, while the drive is read back)."""
        with urgency(Urgency.STOP):  # its exchanges go first on the drive's link (``turns``)
            return await self._stop(source, why, credentials)

    async def _stop(self, source: str, why: str, credentials: dict[str, str] | None) -> dict[str, Any]:
        stopped_run = self.run_id
        self.runs.abort("emergency stop")  # a run carried out here ends aborted, not failed on the stop's fault
        self.hold(source, why)
        self.tell({"event": "stopping", "source": source})  # ahead of every answer that shows the stop
        try:
            await asyncio.wait_for(self.motor.emergency_stop(), 2.0)
            ok, detail = True, "emergency stop commanded on the motor controller"
        except Exception as exc:
            ok, detail = False, (f"the motor controller did not take the emergency stop ({type(exc).__name__}: "
                                 f"{exc}); use the hardware emergency stop")
        check = await self.read_back("the emergency stop") if ok else None
        if check is not None:
            detail = f"{detail}; {check.describe()}"
        log.warning("EMERGENCY STOP (%s, rig process): %s", source, detail)
        answer: dict[str, Any] = {"motor_stopped": bool(check is not None and check.standstill), "stop_commanded": ok,
                  "drive": check.to_dict() if check is not None else None,
                  "aborted_runs": [stopped_run] if stopped_run else [],
                  "detail": detail + "; the daemon aborts the run and latches the stop when it hears of it"}
        self.tell({"event": "stopped", "source": source, "detail": detail, "commanded": ok,
                   "drive": answer["drive"], "credentials": credentials or {}})
        return answer

    async def ramp_down(self, why: str) -> None:
        """A lost web process: ramp the crank down, read it back, the emergency stop if it still turns."""
        self.runs.abort(why)  # a run carried out here ends aborted with the reason, its recording closed by it
        log.error("%s: the crank is stopped", why)
        self.hold("link", why)
        with urgency(Urgency.STOP):
            try:
                await asyncio.wait_for(self.motor.stop(), 3.0)
            except Exception as exc:
                log.error("the ramp-down was not taken (%s): the emergency stop", exc)
            check = await self.read_back("the rig process's stop on a lost link")
        if not self.runs.active:
            self.stream.interrupt(why)  # after the crank's stop: the recording is closed as interrupted
        if check is None or not check.standstill:
            await self.stop("link", why)
            return
        self.tell({"event": "stopped", "source": "link", "detail": f"{why}; {check.describe()}", "commanded": True,
                   "drive": check.to_dict(), "credentials": {}})

    async def read_back(self, after: str) -> DriveCheck:
        motor = self.motor
        bound = motor.stop_time_bound_s(motor.map.device.max_frequency_hz) + 2.0
        try:
            check = await asyncio.wait_for(read_back_standstill(motor, after), bound)
        except Exception as exc:
            check = DriveCheck(after, None, None, None, None, bound, time.time(), f"{type(exc).__name__}: {exc}")
        self.drive = check
        return check

    def hold(self, source: str, detail: str) -> None:
        self.count += 1
        self.turning = False
        self.latched = {"latched": True, "since": time.time(), "source": source, "detail": detail,
                        "count": self.count}

    def state(self) -> dict[str, Any]:
        estop = self.latched or {"latched": False, "since": None, "source": None, "detail": None, "count": self.count}
        return {"estop": estop, "drive": self.drive.to_dict() if self.drive is not None else None}

    # ------------------------------------------------------------------ the web process
    def note_run(self, msg: dict[str, Any]) -> None:
        """The run the crank turns for, as a message's ``run_id`` says (empty or None: no run)."""
        self.run_id = str(msg["run_id"])[:80] if msg.get("run_id") else None

    def tell(self, event: dict[str, Any], droppable: bool = False) -> None:
        """``droppable`` (a periodic count): not queued while the web process has not read
        :data:`runhost.BACKLOG_BYTES` of what was told before (it is stopped or hangs)."""
        web = self.web
        if web is not None and not web.is_closing():
            if droppable and web.transport.get_write_buffer_size() > BACKLOG_BYTES:
                return
            web.write(channel.encode(event))  # buffered by the kernel while the web process sleeps

    async def serve_web(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """One web process at a time: a new connection replaces the old one."""
        if self.web is not None:
            self.web.close()
        self.web = writer
        self.heard = time.monotonic()
        me = asyncio.current_task()
        if me is not None:
            self.serving.add(me)
            me.add_done_callback(self.serving.discard)
        try:
            async for msg in channel.messages(reader, "the web process", log):
                self.heard = time.monotonic()
                task = asyncio.create_task(self.answer(writer, msg))
                self.answering.add(task)
                task.add_done_callback(self.answering.discard)
        finally:
            if self.web is writer:
                self.web = None
                if self.runs.active:  # nobody is left to take its result: aborted, its recording closed
                    await self.runs.end("the daemon's web process closed the channel during the run")
                if self.turning:
                    await self.ramp_down("the daemon's web process closed the channel while the crank turns")
                self.stream.interrupt("the daemon's web process closed the channel during the run")
            writer.close()

    async def answer(self, writer: asyncio.StreamWriter, msg: dict[str, Any]) -> None:
        if str(msg.get("op", "")).startswith(STREAM_OPS):  # the stream process answers it
            await self.stream.forward(msg)
            return
        reply: dict[str, Any] = {"id": msg.get("id")}
        try:
            reply.update(await self.do(msg))
        except MotorExceptionReplyError as exc:
            reply["error"] = error_of(exc)
        except MotorError as exc:
            reply["error"] = error_of(exc)
        except (KeyError, TypeError, ValueError) as exc:
            reply["error"] = {"kind": "bad", "detail": f"a malformed question: {exc!r}"[:300]}
        if not writer.is_closing():
            writer.write(channel.encode(reply))

    async def do(self, msg: dict[str, Any]) -> dict[str, Any]:
        op = msg["op"]
        if op == "read":
            words = await self.transport.read(int(msg["address"]), int(msg["count"]), str(msg["what"]),
                                              int(msg.get("function", 3)))
            return {"words": list(words)}
        if op == "write":
            return await self.write(int(msg["address"]), [int(w) for w in msg["words"]], str(msg["what"]),
                                    bool(msg.get("retry", True)))
        if op == "keeper":  # the web process's keeper: whether the drive's refreshes go through
            if "run_id" in msg:  # and the run the crank turns for, as op "run" told
                self.note_run(msg)
            return {"keeper_error": self.keeper_error}
        if op == "hello":
            return {"profile": self.motor.profile.name, "latched": self.latched, "pid": os.getpid(),
                    "run": self.runs.current.run_id if self.runs.current is not None else None}
        if op == "run_start":
            return await self.runs.start(msg)
        if op == "run_abort":
            return {"aborted": self.runs.abort(str(msg.get("reason") or "aborted"), msg.get("run_id"),
                                               interrupt=bool(msg.get("interrupt", False)))}
        if op == "run_outcome":
            return self.runs.outcome(str(msg["run_id"]))
        if op == "release":
            if self.latched is not None:
                log.info("the stop held since %s released (acknowledged)", time.ctime(self.latched["since"]))
            self.latched = None
            return {}
        if op == "run":  # the run the crank turns for (None: no run): a stop's answer names it
            self.note_run(msg)
            return {}
        if op == "page_port":
            if self.stop_port is not None:
                self.stop_port.page_port = int(msg["port"])
            return {}
        return {"error": {"kind": "bad", "detail": f"unknown question {str(op)[:40]!r}"}}

    async def write(self, address: int, words: Sequence[int], what: str, retry: bool) -> dict[str, Any]:
        addr, n = self.setpoint
        moves = addr <= address < addr + n and any(words[: addr + n - address])
        if moves and self.latched is not None:
            return {"error": {"kind": "refused", "register": what,
                              "detail": f"the rig process holds a stop ({self.latched['source']}: "
                                        f"{self.latched['detail']}); an operator acknowledges it first"}}
        if self.rewrite is not None and address == self.rewrite.address:
            async with self.io:
                await self.transport.write(address, words, what, retry=retry)
                self.rewrite_words = list(words)
        else:
            await self.transport.write(address, words, what, retry=retry)
        if addr <= address < addr + n:
            self.turning = moves  # a set-point of 0: the drive ramps down on its own
        return {}

    async def watch_link(self) -> None:
        """A web process silent for ``link_timeout_s`` while the crank turns: the crank is stopped
        (not while a run is carried out here: it goes on to its end without the web process)."""
        while True:
            await asyncio.sleep(KEEPER_PERIOD_S)
            silent = time.monotonic() - self.heard
            if self.runs.active:
                continue
            if self.turning and silent > self.spec.link_timeout_s:
                await self.ramp_down(f"the daemon's web process has been silent for {silent:.1f} s while the "
                                     "crank turns")
            elif self.stream.recording and silent > self.spec.link_timeout_s:
                self.stream.interrupt(f"the daemon's web process has been silent for {silent:.1f} s during "
                                      "the recording")


STREAM_OPS = ("daq_", "record_")  # the questions the stream process answers


class StreamLink:
    """The stream process (``streamproc.py``), started by the rig process: the ``daq_*`` and
    ``record_*`` questions are forwarded to it as they came and its answers and ``stream`` events
    written back to the web process unchanged; nothing on the stop's or the keeper's path waits for
    it.  A stream process that ends fails the questions in flight (``error`` kind ``stream``) and is
    told as a ``stream`` event with the error; the next question starts a new one."""

    def __init__(self, rig: RigProcess) -> None:
        self.rig = rig
        self.proc: subprocess.Popen[bytes] | None = None
        self.writer: asyncio.StreamWriter | None = None
        self.pending: set[Any] = set()  # ids of the questions forwarded and not yet answered
        self.recording = False  # the web process opened a recording and has not closed it
        self.starting: asyncio.Lock | None = None

    async def ensure(self) -> asyncio.StreamWriter:
        if self.starting is None:
            self.starting = asyncio.Lock()
        async with self.starting:
            if self.writer is not None and not self.writer.is_closing():
                return self.writer
            ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
            try:
                self.proc, got = await self.launch(theirs.fileno())
            finally:
                theirs.close()
            reader, self.writer = await asyncio.open_unix_connection(sock=ours, limit=channel.MAX_MESSAGE + 8)
            log.info("stream process %d started (%s)", self.proc.pid, got)
            task = asyncio.create_task(self.read(reader, self.proc), name="stream-process")
            self.rig.answering.add(task)
            task.add_done_callback(self.rig.answering.discard)
            return self.writer

    @staticmethod
    async def launch(fd: int) -> tuple[subprocess.Popen[bytes], str]:
        """Start the stream process from a thread of its own lowered below the rig's priority
        (``priority.lower_below_rig``): the child inherits that, never the keeper's."""
        loop = asyncio.get_running_loop()
        fut: asyncio.Future[tuple[subprocess.Popen[bytes], str]] = loop.create_future()

        def go() -> None:
            try:
                got = lower_below_rig()
                proc = subprocess.Popen([sys.executable, "-m", "station.rigproc.streamproc", str(fd)],
                                        stdin=subprocess.PIPE, pass_fds=(fd,))
                loop.call_soon_threadsafe(fut.set_result, (proc, got))
            except BaseException as exc:
                loop.call_soon_threadsafe(fut.set_exception, exc)

        threading.Thread(target=go, name="stream-launch", daemon=True).start()
        return await fut

    async def forward(self, msg: dict[str, Any]) -> None:
        if self.rig.runs.active:  # the run carried out here holds the bridge and the recording
            self.rig.tell({"id": msg.get("id"), "error": {
                "kind": "busy", "type": "question", "detail": f"{str(msg.get('op'))[:40]}: the rig process carries out "
                f"run {self.rig.runs.current.run_id if self.rig.runs.current else '?'} on the DAQ stream"}})
            return
        try:
            writer = await self.ensure()
        except OSError as exc:
            self.rig.tell({"id": msg.get("id"), "error": {"kind": "stream", "detail":
                                                          f"the stream process cannot be started: {exc}"}})
            return
        self.pending.add(msg.get("id"))
        if msg.get("op") in ("record_open", "record_finish", "record_abandon"):
            self.recording = msg["op"] == "record_open"
        writer.write(channel.encode(msg))

    async def read(self, reader: asyncio.StreamReader, proc: subprocess.Popen[bytes]) -> None:
        async for msg in channel.messages(reader, "the stream process", log):
            if self.rig.runs.asker.take(msg):
                continue  # the answer to the procedure's question in the rig process
            if "event" not in msg:
                if msg.get("id") not in self.pending:
                    continue  # the answer to the rig process's own question (record_interrupt)
                self.pending.discard(msg.get("id"))
            self.rig.tell(msg, droppable="event" in msg and not msg.get("error"))
        if self.proc is proc:
            self.writer, self.recording = None, False
        try:
            code: int | str = await asyncio.wait_for(asyncio.to_thread(proc.wait), 10.0)
        except TimeoutError:
            proc.kill()
            code = "killed: its channel closed and it did not end"
        why = f"the stream process ended (exit code {code}): the DAQ stream and the recording stopped"
        log.error("%s", why)
        self.rig.runs.asker.lost(why)
        for n in self.pending:
            self.rig.tell({"id": n, "error": {"kind": "stream", "detail": why}})
        self.pending.clear()
        ended = {"event": "stream", "samples": None, "lost": None, "error": why}
        self.rig.runs.asker.take(ended)  # a run carried out here fails as on a lost DAQ link
        self.rig.tell(ended)

    def interrupt(self, why: str) -> None:
        """The web process is lost: an open recording is stopped and closed as interrupted."""
        w = self.writer
        self.recording = False
        if w is not None and not w.is_closing():
            w.write(channel.encode({"op": "record_interrupt", "id": None, "reason": why}))

    def close(self) -> None:
        """End the stream process (its lifeline closes: it closes an open recording first)."""
        proc, self.proc = self.proc, None
        if proc is not None and proc.stdin is not None:
            with contextlib.suppress(OSError):
                proc.stdin.close()


class RigStops:
    """The stop port's stops in the rig process (``stopport.Stops``), handed to its loop."""

    def __init__(self, rig: RigProcess) -> None:
        self.rig = rig

    def state(self) -> dict[str, Any]:
        return self.rig.state()

    async def stop(self, source: str, headers: dict[str, str]) -> dict[str, Any]:
        credentials: dict[str, str] = {k: headers[k] for k in ("authorization", "cookie") if k in headers}
        fut = asyncio.run_coroutine_threadsafe(self.rig.stop(source, "POST /stop on the stop port", credentials),
                                               self.rig.loop)
        return await asyncio.wrap_future(fut)


def _say(obj: dict[str, Any]) -> None:
    sys.stdout.write(json.dumps(obj) + "\n")
    sys.stdout.flush()


async def run(spec: Spec) -> int:
    got = raise_priority("rig-process", spec.priority) if spec.priority != "normal" else "normal"
    profile = load_profile(spec.profile)
    t = profile.transport
    motor = MotorController(profile)
    try:
        await motor.connect(OneAtATime(transport_from_url(
            spec.motor_url, device_id=spec.device_id or t.unit_id, baudrate=t.baudrate, parity=t.parity,
            stopbits=t.stopbits, inter_frame_delay_s=t.inter_frame_delay_s)))
        st = await motor.read_status()
        if not st.standstill:
            log.warning("the drive reports %g Hz: waiting for standstill before serving", st.actual_speed_hz)
            st = await motor.settle_to_standstill(START_STANDSTILL_S)
    except Exception as exc:
        _say({"error": f"the drive cannot be reached at {spec.motor_url}: {type(exc).__name__}: {exc}"})
        return 4
    if not st.standstill:
        _say({"error": f"the drive still turns at {st.actual_speed_hz:g} Hz after {START_STANDSTILL_S:g} s: "
                       "not started (use the hardware emergency stop)"})
        return 4
    rig = RigProcess(spec, motor)
    rig.drive = DriveCheck.of("the rig process's start", st, 0.0)
    with contextlib.suppress(FileNotFoundError):
        os.unlink(spec.socket)
    server = await asyncio.start_unix_server(rig.serve_web, spec.socket, limit=channel.MAX_MESSAGE + 8)
    os.chmod(spec.socket, 0o600)
    tasks = [asyncio.create_task(rig.keeper(), name="watchdog-keeper"),
             asyncio.create_task(rig.watch_link(), name="link-watch")]
    stop_port = None
    if spec.stop_host is not None:
        try:
            stop_port = StopPort(RigStops(rig), frozenset(spec.names), spec.stop_host, spec.stop_port,
                                 page_port=spec.page_port, header_timeout_s=spec.header_timeout_s,
                                 priority=spec.priority)
            await asyncio.to_thread(stop_port.start)
            rig.stop_port = stop_port
        except OSError as exc:
            stop_port = None
            log.error("the stop port %d cannot be opened (%s): POST /stop on the main port only", spec.stop_port, exc)

    def lifeline() -> None:  # the daemon's end of stdin: EOF when it ends or dies
        for _ in sys.stdin:
            pass
        rig.loop.call_soon_threadsafe(rig.done.set)

    threading.Thread(target=lifeline, name="lifeline", daemon=True).start()
    _say({"ready": {"pid": os.getpid(), "priority": got,
                    "stop_port": stop_port.port if stop_port is not None else None,
                    "drive": rig.drive.to_dict()}})
    await rig.done.wait()
    log.warning("the daemon ended: the crank is stopped and the rig process ends")
    await rig.runs.end("the station daemon ended during the run")
    if rig.turning:
        await rig.ramp_down("the daemon ended while the crank turns")
    for task in tasks:
        task.cancel()
    if stop_port is not None:
        stop_port.close()
    server.close()
    if rig.web is not None:  # the channel ends as an end of file, not as a task cancelled at the exit
        rig.web.close()
    if rig.serving:
        await asyncio.wait(rig.serving, timeout=1.0)
    rig.stream.close()
    with contextlib.suppress(Exception):
        await motor.close()
    with contextlib.suppress(FileNotFoundError):
        os.unlink(spec.socket)
    return 0


def main() -> int:
    logging.basicConfig(level=logging.INFO, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s rig-process: %(message)s")
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)  # the driver's own errors say what failed
    # the procedure's modules (numpy, h5py with them) before the specification, at the priority the
    # process was started with: a rig process started ahead (the daemon's ``launch``) loads them while
    # the daemon starts.  Loaded at a run's start instead, at the rig's real-time priority, they took
    # one core for a second beside the stream process's and starved the simulated rig (the drive's
    # watchdog expired, the DAQ stalled) on a loaded machine
    preload_procedure()
    line = sys.stdin.readline()
    try:
        spec = Spec.from_json(json.loads(line))
    except (ValueError, KeyError, TypeError) as exc:
        _say({"error": f"expected the rig process's specification as one JSON line on stdin: {exc}"})
        return 2
    return asyncio.run(run(spec))
