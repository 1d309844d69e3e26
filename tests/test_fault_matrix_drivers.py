"""Fault matrix of the rig boundary, driver side: one test per row of the review table.

Each docstring quotes the row ("case | what happened before"); the test shows what happens now on
the simulated rig (real ptys, a real pymodbus server, the DAQ-bridge emulator).
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator

import numpy as np
import pytest

from drivers.daq import DaqBridge, DaqTimeoutError, FrameError, SampleBlock, SampleGap, SerialLink
from drivers.daq.protocol import SEQ_MODULUS, StreamDecoder, encode_samples
from drivers.motor import (
    LinkPolicy,
    ModbusTransport,
    MotorCommunicationError,
    MotorController,
    MotorStateError,
    MotorValueError,
    load_profile,
    shipped_profiles,
    transport_from_url,
)
from drivers.sim import SimRig
from drivers.sim.daq_emulator import DaqEmulator
from tests.daq_support import emulator_on_pty

pytestmark = pytest.mark.waits  # protocol time-outs in real time: about 6 s of wall time, under 1 s of CPU

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture
def bridge_pty() -> Iterator[tuple[DaqEmulator, str]]:
    with emulator_on_pty(seed=3) as bridge:
        yield bridge


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


@pytest.mark.slow
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


@pytest.mark.slow
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


# ---------------------------------------------------------------------------------------------- Modbus
@pytest.fixture(scope="module")
def modbus_rig() -> Iterator[SimRig]:
    with SimRig(seed=5, rtu_local_echo=True) as rig:
        yield rig


def tcp_exchange(addr: tuple[str, int], request_hex: str, timeout_s: float = 1.0) -> str | None:
    """One raw Modbus TCP request; the reply as spaced upper-case hex, or None if none came."""
    with socket.create_connection(addr, timeout=timeout_s) as s:
        s.sendall(bytes.fromhex(request_hex.replace(" ", "")))
        data = b""
        try:
            while len(data) < 6 or len(data) < 6 + int.from_bytes(data[4:6], "big"):
                chunk = s.recv(256)
                if not chunk:
                    break
                data += chunk
        except TimeoutError:
            return None
    return data.hex(" ").upper()


def test_modbus_rtu_character_format_defaults_to_8e1() -> None:
    """Modbus RTU | 8N1 default where the Modbus serial spec asks 8E1 (or 8N2); no RS-485 local-echo
    option (4 time-outs in 20 reads with an echoing adapter); the emulator applies half of a refused
    FC16 write, answers other unit ids and undocumented function codes; `watchdog_timeout = 0`
    disables the watchdog

    Part: the character format.
    """
    def line(t: ModbusTransport) -> tuple[str, int, int]:
        async def make() -> tuple[str, int, int]:
            p = t._make_client().comm_params  # the pymodbus client the transport would open
            return p.parity, p.stopbits, p.bytesize
        return asyncio.run(make())

    assert line(ModbusTransport.rtu("/dev/ttyUSB0")) == ("E", 1, 8)
    assert line(ModbusTransport.rtu("/dev/ttyUSB0", parity="N")) == ("N", 2, 8)
    assert line(ModbusTransport.rtu("/dev/ttyUSB0", parity="O")) == ("O", 1, 8)
    assert line(transport_from_url("modbus-rtu:///dev/ttyUSB0")) == ("E", 1, 8)
    assert line(transport_from_url("modbus-rtu:///dev/ttyUSB0?parity=N&stopbits=1")) == ("N", 1, 8)
    with pytest.raises(ValueError, match=r"parity: expected 'E' .*, 'O' or 'N', got 'X'"):
        ModbusTransport.rtu("/dev/ttyUSB0", parity="X")
    with pytest.raises(ValueError, match="stop bits: expected 1 or 2, got 3"):
        transport_from_url("modbus-rtu:///dev/ttyUSB0?stopbits=3")
    with pytest.raises(ValueError, match=r"expected query keys among .* got \['bauds'\]"):
        transport_from_url("modbus-rtu:///dev/ttyUSB0?bauds=9600")


def test_modbus_rtu_local_echo_is_read_back_and_discarded(modbus_rig: SimRig) -> None:
    """Modbus RTU | 8N1 default where the Modbus serial spec asks 8E1 (or 8N2); no RS-485 local-echo
    option (4 time-outs in 20 reads with an echoing adapter); the emulator applies half of a refused
    FC16 write, answers other unit ids and undocumented function codes; `watchdog_timeout = 0`
    disables the watchdog

    Part: RS-485 local echo (the rig's RTU line echoes every byte we send).
    """
    url = modbus_rig.addresses.modbus_rtu_url
    assert url is not None
    # no retries, so every read counts; a reply that comes is quick, so the time-out only bounds the
    # reads expected to fail (a loaded machine can delay a good reply past 0.3 s: 2 s for those)
    ok_policy = LinkPolicy(timeout_s=2.0, retries=0, reconnect_attempts=2)
    failing_policy = LinkPolicy(timeout_s=0.3, retries=0, reconnect_attempts=2)

    async def reads(echo: bool, n: int) -> int:
        motor = MotorController()
        policy = ok_policy if echo else failing_policy
        await motor.connect(transport_from_url(url + ("&echo=1" if echo else ""), policy=policy))
        ok = 0
        for _ in range(n):
            with contextlib.suppress(MotorCommunicationError):
                ok += await motor.read("max_frequency") == pytest.approx(100.0)
        await motor.close()
        return ok

    assert asyncio.run(reads(True, 20)) == 20
    assert asyncio.run(reads(False, 2)) == 0  # without echo handling the own request is taken as reply


def test_modbus_emulator_fc16_is_all_or_nothing(modbus_rig: SimRig) -> None:
    """Modbus RTU | 8N1 default where the Modbus serial spec asks 8E1 (or 8N2); no RS-485 local-echo
    option (4 time-outs in 20 reads with an echoing adapter); the emulator applies half of a refused
    FC16 write, answers other unit ids and undocumented function codes; `watchdog_timeout = 0`
    disables the watchdog

    Part: a refused FC16 write changes nothing.
    """
    addr = modbus_rig.addresses.modbus_tcp
    img = modbus_rig.image
    before = img.read(0, 5)
    # setpoint 20.00 Hz (valid) + ramp 0 (outside 0.01..100 Hz/s): exception 03, setpoint unchanged
    assert tcp_exchange(addr, "0001 0000 000B 01 10 0001 0002 04 07D0 0000") == "00 01 00 00 00 03 01 90 03"
    assert img.read(0, 5) == before
    # enabled: setpoint 30 Hz, ramp 50 Hz/s, watchdog, timeout 0 -> the last is refused (04): none applied
    modbus_rig.motor.set_watchdog_timeout(60.0)
    modbus_rig.motor.set_enable(True)
    try:
        before = img.read(0, 5)
        assert tcp_exchange(addr, "0002 0000 000F 01 10 0001 0004 08 0BB8 1388 0001 0000") == \
            "00 02 00 00 00 03 01 90 04"
        assert img.read(0, 5) == before
    finally:
        modbus_rig.motor.set_enable(False)


@pytest.mark.parametrize(("request_hex", "reply_hex"), [
    ("0003 0000 0006 01 04 006A 0001", "00 03 00 00 00 03 01 84 01"),  # FC04 input registers: 01
    ("0004 0000 0006 01 05 0000 FF00", "00 04 00 00 00 03 01 85 01"),  # FC05 write coil: 01
    ("0005 0000 0006 01 01 0000 0001", "00 05 00 00 00 03 01 81 01"),  # FC01 read coils: 01
    ("0006 0000 0002 01 41", "00 06 00 00 00 03 01 C1 01"),            # a code pymodbus does not know
    ("0007 0000 0006 01 03 0064 0000", "00 07 00 00 00 03 01 83 03"),  # FC03 quantity 0: 03
    ("0008 0000 0006 01 03 0064 007E", "00 08 00 00 00 03 01 83 03"),  # FC03 quantity 126 > 125: 03
    ("0009 0000 000B 01 10 0002 0002 03 01F4 0001", "00 09 00 00 00 03 01 90 03"),  # byte count 3 != 4
    ("000A 0000 0006 02 03 006A 0001", None),                          # unit 2: silent
    ("000B 0000 0006 00 06 0001 07D0", None),                          # broadcast 0: silent, not applied
    ("000C 0000 0006 01 03 006A 0001", "00 0C 00 00 00 05 01 03 02 27 10"),  # unit 1 still answers
])
def test_modbus_emulator_unit_ids_and_exception_codes(modbus_rig: SimRig, request_hex: str,
                                                      reply_hex: str | None) -> None:
    """Modbus RTU | 8N1 default where the Modbus serial spec asks 8E1 (or 8N2); no RS-485 local-echo
    option (4 time-outs in 20 reads with an echoing adapter); the emulator applies half of a refused
    FC16 write, answers other unit ids and undocumented function codes; `watchdog_timeout = 0`
    disables the watchdog

    Part: other unit ids, undocumented function codes, bad quantities.
    """
    setpoint = modbus_rig.image.read(1, 1)
    # a reply that comes is quick: the time-out only bounds the silent cases (a loaded machine can delay
    # a reply past a short one)
    timeout_s = 0.4 if reply_hex is None else 2.0
    assert tcp_exchange(modbus_rig.addresses.modbus_tcp, request_hex, timeout_s=timeout_s) == reply_hex
    assert modbus_rig.image.read(1, 1) == setpoint


def test_modbus_watchdog_cannot_be_switched_off_while_enabled(modbus_rig: SimRig) -> None:
    """Modbus RTU | 8N1 default where the Modbus serial spec asks 8E1 (or 8N2); no RS-485 local-echo
    option (4 time-outs in 20 reads with an echoing adapter); the emulator applies half of a refused
    FC16 write, answers other unit ids and undocumented function codes; `watchdog_timeout = 0`
    disables the watchdog

    Part: `watchdog_timeout = 0` while the drive is enabled.
    """
    addr = modbus_rig.addresses.modbus_tcp

    async def run() -> None:
        motor = MotorController()
        await motor.connect(ModbusTransport.tcp(*addr, policy=LinkPolicy(timeout_s=2.0, retries=0)))
        await motor.set_watchdog_timeout(1.0)
        await motor.enable()
        try:
            with pytest.raises(MotorStateError, match="expected a timeout > 0 s while the drive is enabled"):
                await motor.set_watchdog_timeout(0)
            with pytest.raises(MotorValueError, match=r"expected 0..60 s, got 120"):
                await motor.set_watchdog_timeout(120)  # refused before sending: outside the map's range
            # the controller refuses it as well (a master that bypasses the driver's check): 04
            assert tcp_exchange(addr, "0010 0000 0006 01 06 0004 0000") == "00 10 00 00 00 03 01 86 04"
            assert await motor.read("watchdog_timeout") == pytest.approx(1.0)
        finally:
            await motor.disable()
        await motor.set_watchdog_timeout(0)  # allowed while disabled ...
        assert tcp_exchange(addr, "0011 0000 0006 01 06 0000 0001") == "00 11 00 00 00 03 01 86 04"
        assert not modbus_rig.motor.snapshot().enabled  # ... but then the drive cannot be enabled
        await motor.set_watchdog_timeout(1.0)
        await motor.close()

    asyncio.run(run())


@pytest.mark.slow
@pytest.mark.parametrize("name", shipped_profiles())
def test_modbus_emulator_answers_as_each_profiled_drive(name: str) -> None:
    """Modbus RTU | ... the emulator answers other unit ids and undocumented function codes -- part:
    every shipped drive profile over a real Modbus TCP server: silent for another unit id, 01 for a
    function the drive does not answer, 03 for a read longer than the drive takes or a set point out
    of its range, a normal reply otherwise (the in-process matrix per profile: test_drive_profiles.py)."""
    p = load_profile(name)
    unit, speed, sp = p.transport.unit_id, p[p.speed], p[p.setpoint]

    def req(tid: int, pdu: str) -> str:
        body = f"{unit:02X}" + pdu
        return f"{tid:04X} 0000 {len(bytes.fromhex(body)):04X} " + body

    with SimRig(seed=5, rtu=False, profile=p) as rig:
        addr = rig.addresses.modbus_tcp
        read_speed = f"03 {speed.address:04X} {speed.words:04X}"
        assert tcp_exchange(addr, req(1, read_speed).replace(f" {unit:02X}", f" {unit % 247 + 1:02X}", 1),
                            timeout_s=0.4) is None
        assert tcp_exchange(addr, req(2, f"05 {sp.address:04X} FF00")) == f"00 02 00 00 00 03 {unit:02X} 85 01"
        if 0x10 not in p.transport.functions:
            assert tcp_exchange(addr, req(3, f"10 {sp.address:04X} 0001 02 0000")) == \
                f"00 03 00 00 00 03 {unit:02X} 90 01"
        limit = p.transport.max_registers_per_read
        if limit < 125:
            assert tcp_exchange(addr, req(4, f"03 {speed.address:04X} {limit + 1:04X}")) == \
                f"00 04 00 00 00 03 {unit:02X} 83 03"
        too_fast = sp.words_of_raw(sp.raw_of(p.device.max_frequency_hz) + 1)
        if sp.words == 1:
            assert tcp_exchange(addr, req(5, f"06 {sp.address:04X} {too_fast[0]:04X}")) == \
                f"00 05 00 00 00 03 {unit:02X} 86 03"
        reply = tcp_exchange(addr, req(6, read_speed))
        assert reply is not None and reply.split()[6:9] == [f"{unit:02X}", "03", f"{2 * speed.words:02X}"]


# ---------------------------------------------------------------------------------------------- link budget
def test_link_budget_is_checked() -> None:
    """default 3 Mbaud link | carries 3.6× the 20 kHz stream at most; measured lossless to 3×. The ≥ 10×
    in `bench/daq_stream.py` is measured on a pty, which ignores baud rate. Nothing checks that a
    configured baud rate can carry the configured rate (9600 Bd is accepted)"""

    from drivers.daq import link_budget
    from station.errors import ConfigError
    from tests.conftest import station_config

    # the worst case is an upper bound of what the encoder really sends for the nastiest samples
    nasty = np.full(256, np.frombuffer(b"\xc0\xdb", "<i2")[0])
    wire = encode_samples(SEQ_MODULUS - 1, nasty, nasty)
    b = link_budget(20_000, 3_000_000)
    assert b.frame_bytes == 1035 and len(wire) <= b.worst_wire_bytes == 2072
    assert len(wire) > 2 * 1024  # (every sample byte is escaped: the bound is nearly reached)
    assert b.required_baud == pytest.approx(20_000 / 256 * 2072 * 10)  # 1,618,750 Bd
    assert b.margin == pytest.approx(3_000_000 / 1_618_750)

    def cfg(baud: int, rate: float) -> object:
        return station_config(devices={"daq_baudrate": baud}, daq={"sample_rate_hz": rate})

    cfg(3_000_000, 20_000)  # the shipped default is carried, with margin 1.85
    cfg(921_600, 10_000)
    with pytest.raises(ConfigError, match=r"a DAQ link of 9600 Bd cannot carry 20000 Hz x 2 channels: expected "
                                          r"at least 1,618,750 Bd .* received 9600 Bd"):
        cfg(9600, 20_000)
    with pytest.raises(ConfigError, match=r"921600 Bd cannot carry 20000 Hz"):
        cfg(921_600, 20_000)
    with pytest.raises(ConfigError, match=r"3000000 Bd cannot carry 50000 Hz .*largest rate at 3000000 Bd: "
                                          r"37,066 Hz"):
        cfg(3_000_000, 50_000)


def test_driver_refuses_a_rate_its_serial_link_cannot_carry(bridge_pty: tuple[DaqEmulator, str]) -> None:
    """default 3 Mbaud link | ... Nothing checks that a configured baud rate can carry the configured
    rate (9600 Bd is accepted) -- part: the driver, before anything is sent."""
    from drivers.daq import DaqLinkBudgetError

    emu, path = bridge_pty
    daq = DaqBridge()
    daq.connect(SerialLink(path, baudrate=9600))
    try:
        with pytest.raises(DaqLinkBudgetError, match="9600 Bd cannot carry 20000 Hz"):
            daq.configure(rate_hz=20_000)
        assert emu.config["rate"] == "20000" and daq.config is None
        assert daq.configure(rate_hz=100, frame_samples=16).rate_hz == 100  # 100 Hz fits in 9600 Bd
        assert daq.configure(rate_hz=20_000, check_link_budget=False).rate_hz == 20_000  # benches only
    finally:
        daq.close()
