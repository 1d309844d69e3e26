"""The stream process (``python -m station.rigproc.streamproc FD``): the DAQ stream into the run's
recording, under the rig process, in an interpreter of its own (``docs/safety.md``, *The DAQ stream
under the rig process*).

It holds the DAQ bridge's port (``drivers.daq.DaqBridge``), the acquisition and the recording's
writer (``run/stream.LocalStream``) and answers the ``daq_*`` and ``record_*`` questions that reach
it on the socket ``FD`` (``channel.py``'s framing), telling ``stream`` (samples, lost samples, the
stream's error) every :data:`REPORT_PERIOD_S` while it streams.  It never reads the drive and never
waits for the web process.  When its lifeline (stdin) closes, the rig process ended: a recording
still open is stopped and finished ``interrupted`` (closed, never written again), then it ends.

Started without numpy or h5py loaded in the rig process (they load here), at a priority just below
the rig process's (``service/priority.lower_below_rig``: it preempts the web side, never the keeper
or the stop)."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import socket
import sys
import threading
from dataclasses import asdict
from pathlib import Path
from typing import Any

from drivers.daq.bridge import DaqBridge
from drivers.daq.link import SerialLink
from station.errors import StationError
from station.recording import ChannelSpec, RunMetadata
from station.recording.writer import DiskFullError, is_disk_full
from station.rigproc import channel
from station.run.acquisition import AcquisitionError
from station.run.steady import SteadyCriteria
from station.run.stream import LocalStream

log = logging.getLogger("station.rigproc.stream")

REPORT_PERIOD_S = 0.1
TEXT_FIELDS = ("config_yaml", "drive_profile_yaml", "plan")
MAX_TEXT = 4 * 2**20  # characters of a recording's long texts, all parts together
STEP_FIELDS = ("crank_frequency_hz", "crank_radius_m", "start_sample", "end_sample", "lost_in_window")


def error_of(exc: BaseException) -> dict[str, Any]:
    """A failure as it travels back (``client.RemoteStream`` raises it again)."""
    if is_disk_full(exc) or isinstance(exc, DiskFullError):
        kind = "disk"
    elif type(exc).__module__.startswith("drivers.daq"):
        kind = "daq"
    elif isinstance(exc, AcquisitionError):
        kind = "acquisition"
    elif isinstance(exc, StationError | OSError):
        kind = "recording"
    elif isinstance(exc, KeyError | TypeError | ValueError):
        kind = "bad"
    else:
        kind = "exception"
    return {"kind": kind, "type": type(exc).__name__, "detail": str(exc)[:2000],
            "reserve": isinstance(exc, DiskFullError)}


class StreamServer:
    """The stream's state and its answers, on the stream process's loop."""

    def __init__(self) -> None:
        self.stream: LocalStream | None = None
        self.texts: dict[str, list[str]] = {}
        self.recording = False  # a recording is open (between record_open and record_finish/abandon)
        self.streaming = False  # between record_start and record_stop
        self.lock = asyncio.Lock()  # one question at a time: the stream's steps are a sequence
        self.writer: asyncio.StreamWriter | None = None
        self.closed: dict[str, str] | None = None  # the last recording closed without being asked (interrupt)

    def tell(self, event: dict[str, Any]) -> None:
        w = self.writer
        if w is not None and not w.is_closing():
            w.write(channel.encode(event))

    def _stream(self) -> LocalStream:
        if self.stream is None:
            raise StationError("the DAQ bridge is not connected (daq_connect first)")
        return self.stream

    async def answer(self, msg: dict[str, Any]) -> dict[str, Any]:
        reply: dict[str, Any] = {"id": msg.get("id")}
        try:
            async with self.lock:
                reply.update(await self.do(msg))
        except Exception as exc:
            reply["error"] = error_of(exc)
        return reply

    async def do(self, msg: dict[str, Any]) -> dict[str, Any]:
        op = msg["op"]
        if op == "daq_connect":
            await self.close_bridge()
            bridge = DaqBridge()
            link = SerialLink(str(msg["port"]), baudrate=int(msg["baudrate"]), kind=str(msg["kind"]))
            await asyncio.to_thread(bridge.connect, link)
            self.stream = LocalStream(bridge)
            hw = bridge.hardware
            return {"hardware": asdict(hw) if hw is not None else None}
        if op == "daq_close":
            await self.close_bridge()
            return {}
        stream = self._stream()
        if op == "daq_configure":
            cfg = await stream.configure(rate_hz=float(msg["rate_hz"]), range_disp_V=float(msg["range_disp_V"]),
                                         range_force_V=float(msg["range_force_V"]))
            return {"config": asdict(cfg)}
        if op == "record_text":
            field = str(msg["field"])
            if field not in TEXT_FIELDS:
                raise ValueError(f"record_text: expected a field of {TEXT_FIELDS}, got {field[:40]!r}")
            if sum(len(t) for parts in self.texts.values() for t in parts) + len(str(msg["text"])) > MAX_TEXT:
                self.texts.clear()
                raise ValueError(f"a recording's texts beyond {MAX_TEXT} characters")
            self.texts.setdefault(field, []).append(str(msg["text"]))
            return {}
        if op == "record_open":
            self.closed = None
            if self.recording:
                raise StationError("a recording is open: it is finished or abandoned before the next one")
            texts = {k: "".join(v) for k, v in self.texts.items()}
            self.texts.clear()
            meta = RunMetadata(**msg["meta"], config_yaml=texts.get("config_yaml", ""),
                               drive_profile_yaml=texts.get("drive_profile_yaml"))
            a, b = (ChannelSpec(**c) for c in msg["channels"])
            plan = json.loads(texts["plan"]) if "plan" in texts else {}
            await stream.open(Path(str(msg["out_dir"])), meta, (a, b), plan=plan,
                              min_free_bytes=int(msg["min_free_bytes"]))
            self.recording = True
            return {"partial": str(stream.partial_path)}
        if op == "record_start":
            await stream.start()
            self.streaming = True
            return {}
        if op == "record_steady":
            crit = SteadyCriteria.from_dict(msg["criteria"])
            verdict = await stream.steady(float(msg["f_set_hz"]), float(msg["fs"]), crit)
            return {"steady": verdict, "end": stream.samples}
        if op == "record_lost":
            return {"lost": await stream.lost_between(int(msg["start"]), int(msg["stop"]))}
        if op == "record_step":
            fields = {k: msg[k] for k in STEP_FIELDS}
            await stream.add_step(**fields, extra=dict(msg.get("extra") or {}))
            return {}
        if op == "record_stop":
            return await self.stop()
        if op in ("record_finish", "record_abandon") and not self.recording and self.closed is not None:
            return self.closed  # closed already as interrupted: never written again
        if op == "record_finish":
            path = await stream.finish(str(msg["status"]), str(msg["reason"]))
            self.recording = False
            return {"path": str(path)}
        if op == "record_abandon":
            await stream.abandon()
            self.recording = False
            return {"partial": str(stream.partial_path)}
        raise ValueError(f"unknown question {str(op)[:40]!r}")

    async def stop(self) -> dict[str, Any]:
        stream = self._stream()
        end = await stream.stop()
        self.streaming = False
        self.report()
        err = end.disk_error
        return {"samples": stream.samples, "lost": end.lost,
                "disk_error": None if err is None else error_of(err)}

    def report(self) -> None:
        """``stream``: the counts, and the stream's error if it has one."""
        stream = self.stream
        if stream is None:
            return
        error: str | None = None
        try:
            stream.check()
        except AcquisitionError as exc:
            error = str(exc)
        self.tell({"event": "stream", "samples": stream.samples, "lost": stream.lost_samples, "error": error})

    async def reporter(self) -> None:
        while True:
            await asyncio.sleep(REPORT_PERIOD_S)
            if self.streaming:
                self.report()

    async def interrupt(self, reason: str) -> None:
        """The rig process or the web process is gone: an open recording is stopped and closed."""
        async with self.lock:
            if self.stream is None or not self.recording:
                return
            log.error("%s: the recording is closed as interrupted", reason)
            with contextlib.suppress(Exception):
                await self.stop()
            try:
                path = str(await self.stream.finish("interrupted", reason))
            except Exception as exc:
                log.error("the recording could not be closed (%s): left partial", exc)
                with contextlib.suppress(Exception):
                    await self.stream.abandon()
                path = str(self.stream.partial_path)
            self.recording = False
            self.closed = {"path": path, "partial": path, "closed_as": "interrupted", "reason": reason}

    async def close_bridge(self) -> None:
        stream, self.stream = self.stream, None
        if stream is not None:
            await asyncio.to_thread(stream.close)


async def serve(sock: socket.socket, lifeline: bool = True) -> None:
    """Answer the questions arriving on ``sock`` until it closes (or, ``lifeline``, stdin does)."""
    server = StreamServer()
    reader, writer = await asyncio.open_unix_connection(sock=sock, limit=channel.MAX_MESSAGE + 8)
    server.writer = writer
    loop = asyncio.get_running_loop()
    gone = asyncio.Event()
    if lifeline:
        def watch() -> None:
            for _ in sys.stdin:
                pass
            loop.call_soon_threadsafe(gone.set)

        threading.Thread(target=watch, name="lifeline", daemon=True).start()
    tasks: set[asyncio.Task[Any]] = {asyncio.create_task(server.reporter())}

    async def answer(msg: dict[str, Any]) -> None:
        if msg.get("op") == "record_interrupt":
            await server.interrupt(str(msg.get("reason", "interrupted"))[:500])
            reply: dict[str, Any] = {"id": msg.get("id")}
        else:
            reply = await server.answer(msg)
        if not writer.is_closing():
            writer.write(channel.encode(reply))

    async def read() -> None:
        async for msg in channel.messages(reader, "the rig process", log):
            task = asyncio.create_task(answer(msg))
            tasks.add(task)
            task.add_done_callback(tasks.discard)

    reading = asyncio.create_task(read())
    ended = asyncio.create_task(gone.wait())
    await asyncio.wait({reading, ended}, return_when=asyncio.FIRST_COMPLETED)
    await server.interrupt("the rig process ended during the run" if ended.done()
                           else "the rig process closed the stream's channel during the run")
    for task in (*tasks, reading, ended):
        task.cancel()
    await server.close_bridge()
    writer.close()


def main() -> int:
    logging.basicConfig(level=logging.INFO, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s stream-process: %(message)s")
    try:
        sock = socket.socket(fileno=int(sys.argv[1]))
    except (IndexError, ValueError, OSError) as exc:
        sys.stderr.write(f"expected the stream's socket as a file descriptor: {exc}\n")
        return 2
    asyncio.run(serve(sock))
    return 0


if __name__ == "__main__":
    sys.exit(main())
