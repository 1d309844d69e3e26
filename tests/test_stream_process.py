"""The stream process's answers (``station/rigproc/streamproc.py``), served in process over a socket
pair to a DAQ emulator on a real pseudo-terminal: a recording made by questions alone holds every
sample the bridge sent, in order; a lost rig process closes it as interrupted; what is malformed or
out of order is refused without effect; the process starts just below the rig's priority
(``docs/safety.md``, *The DAQ stream under the rig process*)."""

from __future__ import annotations

import asyncio
import json
import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from station.recording import ChannelSpec, RunMetadata
from station.rigproc import channel
from station.rigproc.streamproc import serve
from station.run.steady import SteadyCriteria
from station.service.priority import BELOW_NICE, BELOW_REALTIME_PRIORITY, lower_below_rig, raise_priority
from tests.daq_support import emulator_on_pty

FS = 20_000.0


class Asker:
    """The rig process's side of the stream's socket: questions, their answers, the events."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer = reader, writer
        self.n = 0
        self.events: list[dict[str, Any]] = []

    async def ask(self, op: str, **fields: Any) -> dict[str, Any]:
        self.n += 1
        self.writer.write(channel.encode({"op": op, "id": self.n, **fields}))
        while True:
            msg = await asyncio.wait_for(channel.receive(self.reader), 10.0)
            assert msg is not None, f"the stream's channel closed before the answer to {op}"
            if "event" in msg:
                self.events.append(msg)
            elif msg["id"] == self.n:
                return msg

    async def until_samples(self, n: int, timeout_s: float = 10.0) -> dict[str, Any]:
        deadline = time.monotonic() + timeout_s
        while not self.events or self.events[-1]["samples"] < n:
            assert time.monotonic() < deadline, self.events[-3:]
            msg = await asyncio.wait_for(channel.receive(self.reader), 5.0)
            assert msg is not None and "event" in msg, msg
            self.events.append(msg)
        return self.events[-1]


@asynccontextmanager
async def stream_server(pty_path: str) -> AsyncIterator[Asker]:
    ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
    served = asyncio.create_task(serve(theirs, lifeline=False))
    reader, writer = await asyncio.open_unix_connection(sock=ours, limit=channel.MAX_MESSAGE + 8)
    a = Asker(reader, writer)
    hw = await a.ask("daq_connect", port=pty_path, baudrate=3_000_000, kind="uart")
    assert hw["hardware"]["channels"] == ["disp", "force"], hw
    conf = await a.ask("daq_configure", rate_hz=FS, range_disp_V=10.0, range_force_V=10.0)
    assert conf["config"]["rate_hz"] == FS, conf
    try:
        yield a
    finally:
        writer.close()  # the rig process's end: the server closes what is open and ends
        await asyncio.wait_for(served, 10.0)


async def open_recording(a: Asker, out: Path, run_id: str) -> str:
    meta = RunMetadata(run_id, "T1", "calibrate", FS, 1.0, None, 1e-3, 5000.0, "")
    fields = {k: v for k, v in meta.__dict__.items() if k not in ("config_yaml", "drive_profile_yaml")}
    channels = [ChannelSpec("displacement", "i2", "count", "m", 1e-6).__dict__,
                ChannelSpec("force", "i2", "count", "V", 1e-4).__dict__]
    big = "# a long configuration\n" + "x" * 70_000  # beyond one message: sent in parts
    for k in range(0, len(big), 30_000):
        assert "error" not in await a.ask("record_text", field="config_yaml", text=big[k:k + 30_000])
    assert "error" not in await a.ask("record_text", field="plan", text=json.dumps({"steps": [1, 2]}))
    r = await a.ask("record_open", out_dir=str(out), meta=fields, channels=channels, min_free_bytes=0)
    assert "partial" in r, r
    return big


def test_a_recording_made_by_questions_holds_every_sample_in_order(tmp_path: Path) -> None:
    async def go() -> None:
        with emulator_on_pty() as (_, path):
            async with stream_server(path) as a:
                big = await open_recording(a, tmp_path, "run-1")
                refused = await a.ask("record_open", out_dir=str(tmp_path), meta={}, channels=[], min_free_bytes=0)
                assert refused["error"]["kind"] == "recording" and "is open" in refused["error"]["detail"]
                assert "error" not in await a.ask("record_start")
                ev = await a.until_samples(8000)
                assert ev["error"] is None and ev["lost"] == 0
                crit = SteadyCriteria(window_s=0.05, windows=2).to_dict()
                r = await a.ask("record_steady", f_set_hz=20.0, fs=FS, criteria=crit)
                assert r["steady"] in (True, False) and r["end"] >= 8000, r  # a verdict on the newest 2 000
                crit = SteadyCriteria(window_s=10.0, windows=20).to_dict()
                r = await a.ask("record_steady", f_set_hz=20.0, fs=FS, criteria=crit)
                assert r["steady"] is None, r  # 4 000 000 samples asked: not there yet
                assert (await a.ask("record_lost", start=0, stop=4000))["lost"] == 0
                step = {"crank_frequency_hz": 20.0, "crank_radius_m": 0.01, "start_sample": 1000,
                        "end_sample": 5000, "lost_in_window": 0}
                assert "error" not in await a.ask("record_step", **step, extra={"settle_s": 1.0})
                stopped = await a.ask("record_stop")
                assert stopped["disk_error"] is None and stopped["lost"] == 0, stopped
                done = await a.ask("record_finish", status="completed", reason="")
        final = Path(done["path"])
        assert final == tmp_path / "run-1.h5" and not (tmp_path / "run-1.h5.partial").exists()
        with h5py.File(final, "r") as f:
            d = f["raw/displacement"][:]
            force = f["raw/force"][:]
            assert f.attrs["exit_status"] == "completed"
            assert bytes(f["config/yaml"][:]).decode() == big
            assert list(f["steps/start_sample"][:]) == [1000]
            assert f["lost_samples"].shape == (0, 2)
        assert d.size == stopped["samples"] >= 8000
        offset = int(d[:1].view(np.uint16)[0])  # the counter, from where the emulator's source stood at START
        expected = ((offset + np.arange(d.size)) % 65536).astype(np.uint16).view(np.int16)
        np.testing.assert_array_equal(d, expected)
        np.testing.assert_array_equal(force, (-expected.astype(np.int32)).astype(np.int16))

    asyncio.run(go())


def test_a_lost_rig_process_closes_the_recording_as_interrupted_and_bad_questions_change_nothing(
        tmp_path: Path) -> None:
    async def go() -> None:
        with emulator_on_pty() as (_, path):
            async with stream_server(path) as a:
                for op, fields, kind in (("record_start", {}, "exception"),  # nothing open to stream into
                                         ("record_text", {"field": "secrets", "text": "x"}, "bad"),
                                         ("record_lost", {"start": "x"}, "bad"), ("launch", {}, "bad")):
                    r = await a.ask(op, **fields)
                    assert r["error"]["kind"] == kind, (op, r)
                assert list(tmp_path.iterdir()) == []
                await open_recording(a, tmp_path, "run-2")
                assert "error" not in await a.ask("record_start")
                await a.until_samples(2000)
            # the socket closed (the rig process's end) while streaming
        with h5py.File(tmp_path / "run-2.h5", "r") as f:
            assert f.attrs["exit_status"] == "interrupted"
            assert "closed the stream's channel" in f.attrs["reason"]
            assert f["raw/displacement"].shape[0] >= 2000

    asyncio.run(go())


def test_the_stream_process_starts_just_below_the_rigs_priority() -> None:
    """A thread at the rig's priority lowers itself (``lower_below_rig``) before it starts the stream
    process: the child inherits that, below the keeper's, above the web side's."""
    out: list[tuple[str, str, str]] = []

    def launcher(wanted: str) -> None:
        got = raise_priority("test", wanted)  # type: ignore[arg-type]
        said = lower_below_rig()
        child = subprocess.run([sys.executable, "-c", "import os; print(os.sched_getscheduler(0), "
                                "os.sched_getparam(0).sched_priority, os.getpriority(os.PRIO_PROCESS, 0))"],
                               capture_output=True, text=True, timeout=30).stdout.strip()
        out.append((got, said, child))

    for wanted in ("realtime", "raised"):
        t = threading.Thread(target=launcher, args=(wanted,))
        t.start()
        t.join()
    (rt_got, rt_said, rt_child), (nice_got, nice_said, nice_child) = out
    if rt_got.startswith("real-time"):
        assert rt_said == f"real-time (SCHED_FIFO {BELOW_REALTIME_PRIORITY})"
        policy, prio, _ = rt_child.split()
        assert (int(policy), int(prio)) == (os.SCHED_FIFO, BELOW_REALTIME_PRIORITY), rt_child
    if nice_got.startswith("raised"):
        assert nice_said == f"raised (nice {BELOW_NICE})"
        assert nice_child.split() == [str(os.SCHED_OTHER), "0", str(BELOW_NICE)], nice_child
    else:  # no privilege to raise: nothing to lower either
        assert nice_said.startswith("normal")
