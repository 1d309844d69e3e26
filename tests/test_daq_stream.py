"""Integration: the real DAQ driver against the DAQ-bridge emulator through a pseudo-terminal."""

from __future__ import annotations

import os
import time
from collections.abc import Iterator

import numpy as np
import pytest

from drivers.daq import (
    DaqBridge,
    DaqCommandError,
    DaqLinkError,
    SampleBlock,
    SampleGap,
    SerialLink,
    StreamStalled,
)
from drivers.rig.presets import paper_5kN_physics
from drivers.sim.daq_emulator import DaqEmulator
from drivers.sim.daq_source import RigSource
from drivers.sim.pty import open_pty
from tests.daq_support import emulator_on_pty

pytestmark = pytest.mark.waits  # 20 kHz streamed in real time through a pty: about 9 s of wall time, under 1 s of CPU


@pytest.fixture
def rig_pty(request: pytest.FixtureRequest) -> Iterator[tuple[DaqEmulator, DaqBridge]]:
    with emulator_on_pty(getattr(request, "param", None), seed=3) as (emu, path):
        daq = DaqBridge(stall_timeout_s=0.3)
        daq.connect(SerialLink(path))
        yield emu, daq
        daq.close()


def collect(daq: DaqBridge, seconds: float) -> list:
    events: list = []
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        ev = daq.get_event(0.2)
        if ev is not None:
            events.append(ev)
    return events


def drain(daq: DaqBridge) -> list:
    return list(daq.events(timeout_s=0.3))


def merged(intervals: list[tuple[int, int]]) -> list[tuple[int, int]]:
    out: list[tuple[int, int]] = []
    for first, n in sorted(intervals):
        if out and out[-1][0] + out[-1][1] == first:
            out[-1] = (out[-1][0], out[-1][1] + n)
        else:
            out.append((first, n))
    return out


@pytest.mark.slow
@pytest.mark.parametrize("rig_pty", [RigSource(paper_5kN_physics(), seed=7, crank_radius_m=0.01)],
                         indirect=True)
def test_four_seconds_of_20khz_rig_data_through_a_pty_without_loss(rig_pty) -> None:
    _, daq = rig_pty
    assert daq.identify().startswith("SINECAL,DAQ-BRIDGE-EMU")
    cfg = daq.configure(rate_hz=20_000, frame_samples=256)
    assert (cfg.rate_hz, cfg.frame_samples) == (20_000.0, 256)
    daq.start()
    events = collect(daq, 4.0)  # longer streams: bench/daq_stream.py, tests/test_clock.py (virtual clock, 10 s)
    summary = daq.stop()
    events += drain(daq)
    blocks = [e for e in events if isinstance(e, SampleBlock)]
    assert [e for e in events if not isinstance(e, SampleBlock)] == []
    assert summary.samples_sent >= 4 * 20_000 * 0.98
    starts = np.array([b.first_index for b in blocks])
    ends = starts + np.array([b.count for b in blocks])
    assert starts[0] == 0 and np.array_equal(starts[1:], ends[:-1])  # contiguous, in order
    assert ends[-1] == summary.samples_sent
    st = summary.stats
    assert (st.samples_ok, st.samples_lost) == (summary.samples_sent, 0)
    assert (st.crc_errors, st.framing_errors) == (0, 0)
    disp = np.concatenate([b.displacement for b in blocks]).astype(float)
    # 10 mm crank at 500 V/m on a +-10 V 16-bit ADC: about +-16384 codes
    assert 15_000 < np.percentile(np.abs(disp), 99.9) < 17_500


@pytest.mark.slow
def test_injected_faults_are_reported_exactly(rig_pty) -> None:
    emu, daq = rig_pty
    daq.configure(rate_hz=20_000, frame_samples=256)
    emu.drop_frames([5, 6, 40])
    emu.corrupt_frames([20, 41])
    daq.start()
    events = collect(daq, 0.8)
    emu.inject_garbage(300)
    emu.inject_garbage(50)
    events += collect(daq, 0.4)
    emu.stall(0.7)  # stalled stream: the samples of 0.7 s are lost
    events += collect(daq, 1.5)
    emu.stall(5.0)  # stalled until after STOP: a trailing gap, reported by stop()
    events += collect(daq, 0.5)
    summary = daq.stop()
    events += drain(daq)

    gaps = [(e.first_index, e.count) for e in events if isinstance(e, SampleGap)]
    assert merged(gaps) == merged(emu.lost)
    assert merged(gaps)[:3] == [(5 * 256, 512), (20 * 256, 256), (40 * 256, 512)]
    assert len(merged(gaps)) == 5  # + the stall and the trailing stall
    stalls = [e for e in events if isinstance(e, StreamStalled)]
    assert len(stalls) >= 2 and all(s.seconds >= 0.3 for s in stalls)
    st = summary.stats
    assert st.crc_errors >= 2 and st.samples_lost == sum(n for _, n in emu.lost)
    assert st.samples_ok + st.samples_lost == summary.samples_sent

    # never a corrupted sample: every delivered sample is the emulator's counter at its index
    blocks = [e for e in events if isinstance(e, SampleBlock)]
    first = blocks[0]
    offset = int(first.displacement[0].astype(np.uint16)) - first.first_index
    for b in blocks:
        expect = ((offset + np.arange(b.first_index, b.first_index + b.count)) % 65536).astype(np.uint16)
        assert np.array_equal(b.displacement.view(np.uint16), expect)
        assert np.array_equal(b.force, (-b.displacement.astype(np.int32)).astype(np.int16))


def test_closed_port_ends_the_stream_with_a_link_error(rig_pty) -> None:
    emu, daq = rig_pty
    daq.configure()
    daq.start()
    assert isinstance(daq.get_event(1.0), SampleBlock)
    emu.close_port()
    with pytest.raises(DaqLinkError):
        for _ in range(100):
            daq.get_event(0.2)
    with pytest.raises(DaqLinkError):
        daq.status()


def test_bad_configuration_is_refused_with_expected_and_received(rig_pty) -> None:
    _, daq = rig_pty
    with pytest.raises(DaqCommandError, match=r"bad value for rate: expected 100\.\.1e\+06 Hz, got '5e\+06'"):
        daq.configure(rate_hz=5e6, check_link_budget=False)  # the bridge refuses it too
    with pytest.raises(DaqCommandError, match="unknown command 'FOO'"):
        daq.command("FOO")
    assert daq.status()["state"] == "idle"


def test_connect_to_a_silent_port_fails_cleanly() -> None:
    """No bridge answers the STOP of connect(): DaqTimeoutError, and no reader thread or port is left."""
    from drivers.daq import DaqTimeoutError

    pty = open_pty()
    try:
        daq = DaqBridge(reply_timeout_s=0.2)
        with pytest.raises(DaqTimeoutError, match=r"no reply to 'STOP'"):
            daq.connect(SerialLink(pty.path), reset_timeout_s=0.3)
        assert daq._thread is not None and not daq._thread.is_alive() and daq._link is None
        assert os.read(pty.master, 4096).startswith(b"\xc0\x10#1 STOP")  # what the bridge would have got
    finally:
        pty.close()
