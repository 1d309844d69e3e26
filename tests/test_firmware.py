"""The reference bridge firmware (``firmware/``), built for the host with the system C compiler,
against the station's DAQ driver over a real pty: the protocol's second, independent implementation.

The C core's own checks (CRC-32 check value, SLIP, sequence wrap, ...) run as ``firmware/test/selftest.c``;
here the Python side checks what the firmware puts on the wire: every reply of
``docs/daq-protocol.md`` section 4, a lossless 20 kHz stream whose samples match the synthetic
source recomputed independently, and lost frames reported as gaps at their exact sample positions.
Without a C compiler the tests skip, except under CI (``CI`` set), where that is a failure.
"""

from __future__ import annotations

import os
import re
import select
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from drivers.daq import DaqBridge, SampleBlock, SampleGap, SerialLink, StreamStalled
from drivers.daq.protocol import (
    PKT_COMMAND,
    PKT_SAMPLES,
    Reply,
    StreamDecoder,
    crc32,
    encode_command,
    encode_packet,
)
from drivers.sim.daq_emulator import DaqEmulator
from drivers.sim.pty import open_pty
from tests.firmware_support import build, check_counter_tiling, stream

pytestmark = pytest.mark.waits  # the bridge firmware streaming in real time: about 6 s of wall time, under 1 s of CPU

CONFIG_KEYS = ("rate", "rate_exact", "frame", "range_disp", "range_force", "channels")


@pytest.fixture(scope="module")
def firmware_build() -> Path:
    return build("all", os.environ.get("CC", "cc"))


class Firmware:
    """``bridge-host --pty`` as a subprocess: ``path`` is the pty the driver opens."""

    def __init__(self, build: Path, *args: str) -> None:
        self.stderr = ""
        self.proc = subprocess.Popen([str(build / "bridge-host"), "--pty", *args], stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True)
        assert self.proc.stdout is not None
        ready, _, _ = select.select([self.proc.stdout], [], [], 5.0)
        line = self.proc.stdout.readline() if ready else ""
        if not line.startswith("PTY "):
            self.close()
            raise AssertionError(f"bridge-host did not announce its pty, got {line!r}: {self.stderr}")
        self.path = line.split()[1]

    def close(self) -> str:
        """Terminate; returns what the firmware logged on stderr."""
        if self.proc.poll() is None:
            self.proc.terminate()
        _, self.stderr = self.proc.communicate(timeout=5)
        return self.stderr


@pytest.fixture
def start_firmware(firmware_build: Path) -> Iterator:
    started: list[Firmware] = []

    def start(*args: str) -> Firmware:
        fw = Firmware(firmware_build, *args)
        started.append(fw)
        return fw

    yield start
    for fw in started:
        fw.close()


def test_core_selftest_and_crc_check_value(firmware_build: Path) -> None:
    done = subprocess.run([str(firmware_build / "selftest")], capture_output=True, text=True, timeout=30)
    assert done.returncode == 0, done.stderr
    assert 'crc32("123456789") = 0xCBF43926' in done.stdout  # CRC-32/ISO-HDLC's standard check value
    assert crc32(b"123456789") == 0xCBF43926


class RawPort:
    """The pty without the driver: byte-exact commands in, replies (and frames) decoded by the host's decoder."""

    def __init__(self, path: str) -> None:
        self.link = SerialLink(path, kind="usb-cdc")
        self.decoder = StreamDecoder(256)
        self.frames_seen = 0

    def ask(self, wire: bytes, timeout_s: float = 2.0) -> str:
        """Send raw bytes, return the text of the one reply they get (CRC checked by zlib)."""
        self.link.write(wire)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for ev in self.decoder.feed(self.link.read(65536, 0.005)):
                if isinstance(ev, Reply):
                    return ev.text
                self.frames_seen += 1
        raise AssertionError(f"no reply to {wire!r} within {timeout_s} s")

    def command(self, text: str, tag: str | None = None) -> str:
        return self.ask(encode_command(text, tag))


def kv(text: str) -> dict[str, str]:
    return dict(w.split("=", 1) for w in text.split() if "=" in w)


def test_every_command_is_answered_per_the_spec(start_firmware) -> None:
    fw = start_firmware()
    port = RawPort(fw.path)
    try:
        # identity, hardware, status, configuration (section 4); every tagged reply echoes its tag
        assert port.command("IDN?", "#1") == "#1 OK SINECAL,DAQ-BRIDGE-HOST,HOST0001,1.0"
        hw = port.command("HW?", "#2")
        assert hw.startswith("#2 OK HW ")
        assert kv(hw) == {"adc": "SYNTHETIC", "bits": "24", "channels": "disp,force", "clock_hz": "16000000",
                          "rate_min": "100", "rate_max": "1000000", "link": "usb-cdc",
                          "link_bytes_per_s": "4000000"}
        stat = port.command("STAT?", "#3")
        assert stat.startswith("#3 OK STAT state=idle frames=0 overflows=0 ")
        assert tuple(kv(stat))[3:] == CONFIG_KEYS
        assert port.command("CONF", "#4") == ("#4 OK CONF rate=20000 rate_exact=20000 frame=256 range_disp=10 "
                                              "range_force=10 channels=disp,force")
        # the driver formats rates with %g (1e+06); the ADC divides a 16 MHz clock by whole numbers
        assert kv(port.command("CONF rate=1e+06"))["rate_exact"] == "1000000"
        conf = kv(port.command("CONF rate=12345.6 frame=64 range_disp=0.5 range_force=2.5"))
        assert float(conf["rate_exact"]) == pytest.approx(16e6 / round(16e6 / 12345.6), rel=1e-9)
        assert (conf["rate"], conf["frame"], conf["range_disp"], conf["range_force"]) == ("12345.6", "64", "0.5", "2.5")
        # refused values: ERR 2 saying what was expected and what came; nothing of the command applied
        for bad, expected in [("rate=99", "100..1000000 Hz"), ("rate=abc", "100..1000000 Hz"),
                              ("rate=nan", "100..1000000 Hz"), ("frame=4097", "integer 16..4096"),
                              ("frame=16.5", "integer 16..4096"), ("range_disp=11", "0.1..10 V"),
                              ("channels=force,disp", "disp,force"), ("foo=1", "key=value"),
                              ("rate", "key=value")]:
            reply = port.command(f"CONF frame=32 {bad}", "#5")
            assert reply.startswith("#5 ERR 2 bad ") and expected in reply and "got" in reply, reply
        # 16 MHz / 16 = 1 MHz and / 17 = 941 kHz: nothing within 1 % of 980 kHz (HW? rate_exact rule)
        assert port.command("CONF rate=980000", "#5") == ("#5 ERR 2 bad value for rate: expected a rate within 1 % "
                                                          "of one the ADC achieves (nearest: 1000000 Hz), got '980000'")
        assert kv(port.command("STAT?"))["frame"] == "64"
        assert port.command("STOP now", "#5") == "#5 ERR 2 bad argument: expected none after STOP, got 'now'"
        assert port.command("STOP", "#6") == "#6 OK STOP frames=0 samples=0 (was idle)"
        # errors 1 (unknown or empty) and 2 (bad tag: answered untagged)
        assert port.command("FLY", "#7") == ("#7 ERR 1 unknown command 'FLY': expected IDN?, HW?, CONF, START, "
                                             "STOP or STAT?")
        assert port.ask(encode_packet(PKT_COMMAND, b"#8")).startswith("#8 ERR 1 empty command")
        assert port.ask(encode_packet(PKT_COMMAND, b"#0123456789abcdef IDN?")).startswith("ERR 2 bad tag: expected")
        # error 4: a malformed packet (CRC, type, length, SLIP) is answered untagged
        good = encode_command("IDN?", "#9")
        malformed = {"expected CRC": good[:-2] + bytes([good[-2] ^ 1]) + good[-1:],
                     "expected type 0x10": encode_packet(PKT_SAMPLES, b"#9 IDN?"),
                     "expected at least 5 bytes": b"\xc0\x10\x00\xc0",
                     "expected at most": encode_packet(PKT_COMMAND, b"#9 " + b"X" * 300),
                     "expected 0xDC or 0xDD": b"\xc0\x10\xdb\x41\xc0"}
        for expected, wire in malformed.items():
            assert port.ask(wire).startswith(f"ERR 4 malformed command packet: {expected}")
        # streaming: START, busy (3), HW? and STAT? allowed, STOP after the last frame
        port.decoder.reset(64)
        start = port.command("START", "#10")
        assert start.startswith("#10 OK START seq=0 rate=12345.6 rate_exact=") and tuple(kv(start))[1:] == CONFIG_KEYS
        assert port.command("START", "#11").startswith("#11 ERR 3 busy")
        assert port.command("CONF rate=20000", "#12").startswith("#12 ERR 3 busy")
        assert port.command("HW?", "#13").startswith("#13 OK HW adc=SYNTHETIC")
        time.sleep(0.1)
        assert kv(port.command("STAT?"))["state"] == "streaming"
        stop = port.command("STOP", "#14")
        match = re.fullmatch(r"#14 OK STOP frames=(\d+) samples=(\d+)", stop)
        assert match is not None, stop
        assert int(match[1]) >= 15 and int(match[2]) == 64 * int(match[1])  # 0.1 s at 12.3 kHz in 64-sample frames
        assert port.decoder.stats.frames_ok == int(match[1])  # all before the reply, none lost
        assert kv(port.command("STAT?"))["state"] == "idle"
    finally:
        port.link.close()


class _SilentSource:
    """The emulator's sample source for reply comparisons (samples do not matter here)."""

    def configure(self, rate_hz: float, range_disp_V: float, range_force_V: float) -> None:
        return None

    def advance(self, n: int, f_end_hz: float) -> tuple[np.ndarray, np.ndarray]:
        return np.zeros(n, np.int16), np.zeros(n, np.int16)


def reply_kind(reply: str) -> tuple[str | None, str, str]:
    """``"#1 OK CONF rate=..."`` -> ``("#1", "OK", "CONF")``; ``"ERR 2 ..."`` -> ``(None, "ERR", "2")``;
    the identity of ``IDN?`` -> ``"IDN?"``."""
    words = reply.split()
    tag = words.pop(0) if words[0].startswith("#") else None
    second = words[1] if words[0] == "ERR" or words[1] in ("HW", "CONF", "START", "STOP", "STAT") else "IDN?"
    return tag, words[0], second


def test_firmware_and_python_emulator_give_the_same_reply_kinds(start_firmware) -> None:
    """Where the spec fixes the reply (section 4), both implementations answer alike: the first two words
    (``OK CONF``, ``ERR 2``, ...) and the tagging.  (Where the spec is silent they may differ:
    firmware/README.md lists the firmware's choices.)"""
    good = encode_command("IDN?", "#1")
    script = [encode_command(text, "#1") for text in (
        "IDN?", "HW?", "STAT?", "CONF", "CONF rate=20000 frame=256", "CONF rate=99", "CONF frame=4097",
        "CONF range_disp=11", "CONF channels=force,disp", "CONF foo=1", "STOP", "FLY", "", "START", "START",
        "CONF frame=64", "HW?", "STOP")]
    script[12:12] = [encode_packet(PKT_COMMAND, b"#0123456789abcdef IDN?"),      # bad tag: ERR 2 untagged
                     good[:-2] + bytes([good[-2] ^ 1]) + good[-1:],             # CRC: ERR 4 untagged
                     encode_packet(PKT_SAMPLES, b"#1 IDN?"), b"\xc0\x10\x00\xc0",  # type, length: ERR 4
                     encode_packet(PKT_COMMAND, b"#1 IDN\xff"), b"\xc0\x10\xdb\x41\xc0"]  # non-ASCII, SLIP: ERR 4
    pty = open_pty()
    emulator = DaqEmulator(pty.master, _SilentSource(), lambda t: 20.0, on_close=pty.forget_master).start()
    answers = []
    try:
        for path in (start_firmware().path, pty.path):
            port = RawPort(path)
            try:
                answers.append([reply_kind(port.ask(wire)) for wire in script])
            finally:
                port.link.close()
    finally:
        emulator.close()
        pty.close()
    assert answers[0] == answers[1]
    assert answers[0][12:18] == [(None, "ERR", "2")] + [(None, "ERR", "4")] * 5
    assert answers[0][:2] == [("#1", "OK", "IDN?"), ("#1", "OK", "HW")]


def synthetic_sine(seed: int, rate_hz: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """firmware/port/host/synth.h's sine source, rewritten from its description, as the core converts it
    (24-bit codes rounded to 16 bits)."""

    def xorshift32(x: int) -> int:
        x ^= (x << 13) & 0xFFFFFFFF
        x ^= x >> 17
        x ^= (x << 5) & 0xFFFFFFFF
        return x

    x1 = xorshift32(seed or 0x9E3779B9)
    x2 = xorshift32(x1)
    f_hz, phase = 5 + (x1 % 2000) * 0.01, -(0.1 + (x2 % 1000) * 0.001)
    w = 2 * np.pi * f_hz * np.arange(n, dtype=np.float64) / rate_hz
    codes24 = [np.round(a * 2.0**23 * np.sin(w + p)) for a, p in ((0.6, 0.0), (0.4, phase))]
    return tuple(np.floor((c + 128) / 256).astype(np.int64) for c in codes24)  # type: ignore[return-value]


@pytest.mark.slow
def test_streams_20khz_to_the_driver_without_loss(start_firmware) -> None:
    fw = start_firmware("--seed", "5")
    daq = DaqBridge(stall_timeout_s=0.5)
    daq.connect(SerialLink(fw.path, kind="usb-cdc"))
    try:
        assert daq.hardware is not None and (daq.hardware.adc, daq.hardware.adc_bits) == ("SYNTHETIC", 24)
        config = daq.configure(rate_hz=20_000, frame_samples=256)
        assert (config.rate_hz, config.rate_requested_hz) == (20_000.0, 20_000.0)
        daq.start()
        events: list[SampleBlock] = []
        t_end = time.monotonic() + 3.0
        while time.monotonic() < t_end:
            ev = daq.get_event(0.2)
            assert not isinstance(ev, SampleGap | StreamStalled), ev  # no gap, no stall
            if ev is not None:
                events.append(ev)
        summary = daq.stop()  # the trailing events are queued when it returns
        for ev in daq.events(timeout_s=0.05):
            assert isinstance(ev, SampleBlock), ev  # no trailing gap
            events.append(ev)
        status = daq.status()
    finally:
        daq.close()
    assert summary.frames_sent >= 200  # 3 s at 20 kHz is 234 frames of 256 samples
    assert summary.stats.crc_errors == summary.stats.framing_errors == summary.stats.samples_lost == 0
    assert status["overflows"] == "0"
    disp = np.concatenate([e.displacement for e in events])
    force = np.concatenate([e.force for e in events])
    assert [e.first_index for e in events] == [sum(e.count for e in events[:k]) for k in range(len(events))]
    assert len(disp) == summary.samples_sent
    want_disp, want_force = synthetic_sine(5, 20_000.0, len(disp))
    assert np.abs(disp - want_disp).max() <= 1 and np.abs(force - want_force).max() <= 1  # libm vs numpy sin
    assert np.abs(disp).max() > 0.59 * 32768  # the sine's amplitude, not a flat line


def test_samples_lost_before_the_core_are_a_gap_of_whole_frames_at_their_position(start_firmware) -> None:
    # samples 1000..1009 fall in frame 3 (768..1023); 3000..3599 in frames 11..14 (2816..3839)
    fw = start_firmware("--source", "counter", "--adc-skip", "1000:10", "--adc-skip", "3000:600")
    events, status, summary = stream(fw.path, "usb-cdc", 0.25)
    assert check_counter_tiling(events, summary.samples_sent) == [(768, 256), (2816, 1024)]
    assert status["overflows"] == "5"
    assert re.findall(r"drop first=(\d+) count=(\d+) reason=adc", fw.close()) == [
        ("3", "1"), ("11", "1"), ("12", "2"), ("14", "1")]


@pytest.mark.slow
def test_fifo_overflow_is_reported_as_a_gap_at_the_dropped_frames(start_firmware) -> None:
    # the link stops taking bytes at frame 5 for 0.4 s: a 16 KiB FIFO holds ~14 frames of the ~31 produced
    fw = start_firmware("--source", "counter", "--fifo-bytes", "16384", "--tx-block-at", "5", "--tx-block-ms", "400")
    events, status, summary = stream(fw.path, "usb-cdc", 0.8)
    gaps = check_counter_tiling(events, summary.samples_sent)
    logged = re.findall(r"drop first=(\d+) count=(\d+) reason=fifo", fw.close())
    drops = [(int(a) * 256, int(n) * 256) for a, n in logged]
    merged: list[tuple[int, int]] = []
    for first, n in drops:
        if merged and sum(merged[-1]) == first:
            merged[-1] = (merged[-1][0], merged[-1][1] + n)
        else:
            merged.append((first, n))
    assert gaps and gaps == merged  # where the driver sees the gap is where the firmware dropped frames
    assert int(status["overflows"]) == sum(n for _, n in drops) // 256 == summary.stats.frames_lost
