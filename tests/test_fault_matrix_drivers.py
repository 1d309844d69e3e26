"""Fault matrix of the rig boundary, driver side: one test per row of the review table.

Each docstring quotes the row ("case | what happened before"); the test shows what happens now on
the simulated rig (real ptys, a real pymodbus server, the DAQ-bridge emulator).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator

import numpy as np
import pytest

from drivers.daq import DaqBridge, DaqTimeoutError, FrameError, SampleBlock, SampleGap, SerialLink
from drivers.daq.protocol import SEQ_MODULUS, StreamDecoder, encode_samples
from drivers.sim import SimRig
from drivers.sim.daq_emulator import DaqEmulator
from drivers.sim.pty import open_pty

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


class CounterSource:
    """Displacement = running sample counter (mod 2^16), force = its negative."""

    def __init__(self) -> None:
        self.k = 0

    def configure(self, rate_hz: float, range_disp_V: float, range_force_V: float) -> None:
        return None

    def advance(self, n: int, f_end_hz: float) -> tuple[np.ndarray, np.ndarray]:
        d = (np.arange(self.k, self.k + n) % 65536).astype(np.uint16).view(np.int16)
        self.k += n
        return d, (-d.astype(np.int32)).astype(np.int16)


@pytest.fixture
def bridge_pty() -> Iterator[tuple[DaqEmulator, str]]:
    pty = open_pty()
    emu = DaqEmulator(pty.master, CounterSource(), lambda: 20.0, seed=3, on_close=pty.forget_master).start()
    yield emu, pty.path
    emu.close()
    pty.close()


_KILLED_STATION = """
import sys, time
from drivers.daq import DaqBridge, SerialLink
daq = DaqBridge()
daq.connect(SerialLink(sys.argv[1]))
daq.configure(rate_hz=20000, frame_samples=256)
daq.start()
daq.get_event(2.0)
print("streaming", flush=True)
time.sleep(60)
"""


def test_station_killed_mid_run_then_a_new_run() -> None:
    """the station killed mid-run, then a new run | refused with a traceback: the bridge is still
    streaming (`ERR 3 busy: expected STOP before CONF`)"""
    with SimRig(seed=4, rtu=False) as rig:
        proc = subprocess.Popen([sys.executable, "-c", _KILLED_STATION, rig.addresses.daq],
                                stdout=subprocess.PIPE, text=True, cwd=REPO)
        try:
            assert proc.stdout is not None and proc.stdout.readline().strip() == "streaming"
            assert rig.daq.streaming
        finally:
            proc.send_signal(signal.SIGKILL)
            proc.wait(timeout=5)
        time.sleep(0.2)  # the bridge keeps streaming into a port nobody reads
        assert rig.daq.streaming
        daq = DaqBridge()
        daq.connect(SerialLink(rig.addresses.daq))  # STOP, drain, check idle
        try:
            assert not rig.daq.streaming
            cfg = daq.configure(rate_hz=20_000, frame_samples=256)
            assert cfg.frame_samples == 256
            daq.start()
            first = daq.get_event(1.0)
            assert isinstance(first, SampleBlock) and first.first_index == 0
            summary = daq.stop()
            events = list(daq.events(0.3))
            assert summary.stats.crc_errors == 0 and summary.stats.gaps == 0
            got = first.count + sum(e.count for e in events if isinstance(e, SampleBlock))
            assert got == summary.samples_sent
        finally:
            daq.close()


def test_a_daq_command_that_times_out(bridge_pty: tuple[DaqEmulator, str]) -> None:
    """a DAQ command that times out | its late reply is taken as the answer to the next command"""
    emu, path = bridge_pty
    daq = DaqBridge(reply_timeout_s=0.3)
    daq.connect(SerialLink(path))
    try:
        # STAT? is answered after 0.5 s (its caller gave up at 0.3 s); the IDN? reply is 0.4 s late, so
        # the stale STAT reply arrives while IDN? is waiting
        emu.delay_replies(0.5)
        emu.delay_replies(0.4)
        with pytest.raises(DaqTimeoutError, match=r"no reply to 'STAT\?'"):
            daq.status()
        daq.reply_timeout_s = 1.0
        assert daq.identify() == "SINECAL,DAQ-BRIDGE-EMU,SN0001,1.0"
        assert daq.stale_replies == 1
        assert daq.status()["state"] == "idle"
    finally:
        daq.close()


def _frames(seqs: list[int], n: int = 8) -> bytes:
    out = []
    for s in seqs:
        d = (np.arange(s * n, (s + 1) * n) % 65536).astype(np.uint16).view(np.int16)
        out.append(encode_samples(s % SEQ_MODULUS, d, -d))
    return b"".join(out)


def _indices(events: list) -> tuple[list[int], list[tuple[int, int]], list[str]]:
    idx: list[int] = []
    for e in events:
        if isinstance(e, SampleBlock):
            expect = (np.arange(e.first_index, e.first_index + e.count) % 65536).astype(np.uint16)
            assert np.array_equal(e.displacement.view(np.uint16), expect)
            idx += list(range(e.first_index, e.first_index + e.count))
    gaps = [(e.first_index, e.count) for e in events if isinstance(e, SampleGap)]
    errors = [e.kind for e in events if isinstance(e, FrameError)]
    return idx, gaps, errors


def test_sequence_numbers_far_ahead_frame_and_wrap() -> None:
    """sequence numbers | one valid frame far ahead makes the decoder reject every later frame; a
    2³²−1 jump reports a gap of 1.1e12 samples"""
    # one valid frame (good CRC) far ahead: rejected, the stream goes on
    dec = StreamDecoder(8)
    idx, gaps, errors = _indices(dec.feed(_frames([0, 1, 2, 1_000_000, 3, 4, 5, 6])))
    assert idx == list(range(56)) and gaps == [] and errors == ["sequence"]
    # the wire sequence wraps 0xFFFFFFFF -> 0: continuity, sample indices keep counting
    dec = StreamDecoder(8)
    dec.next_seq = SEQ_MODULUS - 2  # as after 2^32 - 2 frames
    idx, gaps, errors = _indices(dec.feed(_frames([SEQ_MODULUS - 2, SEQ_MODULUS - 1, SEQ_MODULUS,
                                                   SEQ_MODULUS + 1])))
    assert gaps == [] and errors == []
    assert idx == list(range((SEQ_MODULUS - 2) * 8, (SEQ_MODULUS + 2) * 8))
    # a jump of 2^32 - 1 is one frame back (a duplicate), not a gap of (2^32 - 1) * 256 samples
    dec = StreamDecoder(256)
    d = np.zeros(256, np.int16)
    events = dec.feed(encode_samples(SEQ_MODULUS - 1, d, d) + encode_samples(0, d, d)
                      + encode_samples(SEQ_MODULUS - 1, d, d) + encode_samples(1, d, d))
    assert [type(e).__name__ for e in events] == ["FrameError", "SampleBlock", "FrameError", "SampleBlock"]
    assert dec.stats.samples_lost == 0 and dec.stats.gaps == 0 and dec.next_sample_index == 512
    assert "expected sequence 0, got 4294967295 (1 frame(s) behind" in events[0].detail
    assert "expected sequence 1, got 4294967295 (2 frame(s) behind" in events[2].detail
