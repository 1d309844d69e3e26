"""Byte-exact Modbus frames: the emulator (TCP and RTU) and the driver's own requests."""

from __future__ import annotations

import asyncio
import socket
from collections.abc import Iterator

import pytest
import serial

from drivers.motor import (
    LinkPolicy,
    ModbusTransport,
    MotorController,
    MotorExceptionReplyError,
    MotorValueError,
)
from drivers.sim import SimRig


def crc16_modbus(data: bytes) -> bytes:
    """Independent CRC-16/MODBUS (reflected 0xA001, init 0xFFFF), low byte first on the wire."""
    crc = 0xFFFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc.to_bytes(2, "little")


def test_crc16_reference_vector() -> None:
    assert crc16_modbus(bytes.fromhex("01030000000A")) == bytes.fromhex("C5CD")


@pytest.fixture(scope="module")
def rig() -> Iterator[SimRig]:
    with SimRig(seed=1) as r:
        yield r


def tcp_exchange(addr: tuple[str, int], request_hex: str) -> str:
    with socket.create_connection(addr, timeout=2.0) as s:
        s.sendall(bytes.fromhex(request_hex))
        data = b""
        while len(data) < 6 or len(data) < 6 + int.from_bytes(data[4:6], "big"):
            chunk = s.recv(256)
            assert chunk, f"connection closed after {data.hex()}"
            data += chunk
    return data.hex(" ").upper()


@pytest.mark.parametrize(("request_hex", "reply_hex"), [
    # read max_frequency (addr 106): 100.00 Hz = 10000 = 0x2710
    ("0001 0000 0006 01 03 006A 0001", "00 01 00 00 00 05 01 03 02 27 10"),
    # write frequency_setpoint 150.00 Hz (0x3A98) > max: exception 03 ILLEGAL DATA VALUE
    ("0002 0000 0006 01 06 0001 3A98", "00 02 00 00 00 03 01 86 03"),
    # read an address outside the map: exception 02 ILLEGAL DATA ADDRESS
    ("0003 0000 0006 01 03 0032 0001", "00 03 00 00 00 03 01 83 02"),
    # write the read-only actual_speed: exception 02
    ("0004 0000 0006 01 06 0064 0001", "00 04 00 00 00 03 01 86 02"),
    # FC16 ramp 5.00 Hz/s + watchdog counter 1: echo of address and count
    ("0005 0000 000B 01 10 0002 0002 04 01F4 0001", "00 05 00 00 00 06 01 10 00 02 00 02"),
    # FC06 setpoint 20.00 Hz: echo of the request
    ("0006 0000 0006 01 06 0001 07D0", "00 06 00 00 00 06 01 06 00 01 07 D0"),
])
def test_emulator_tcp_frames(rig: SimRig, request_hex: str, reply_hex: str) -> None:
    assert tcp_exchange(rig.addresses.modbus_tcp, request_hex.replace(" ", "")) == reply_hex


def test_emulator_tcp_injected_exception_frame(rig: SimRig) -> None:
    rig.modbus_faults.exception_replies(0x06, n=1, address=102)  # SERVER DEVICE BUSY on the status word
    assert tcp_exchange(rig.addresses.modbus_tcp, "000700000006010300640006") == "00 07 00 00 00 03 01 83 06"
    assert tcp_exchange(rig.addresses.modbus_tcp, "0008000000060103006A0001").endswith("01 03 02 27 10")


def rtu_exchange(port: str, pdu_hex: str, reply_len: int) -> bytes:
    frame = bytes.fromhex(pdu_hex)
    frame += crc16_modbus(frame)
    with serial.Serial(port, baudrate=115200, timeout=2.0) as ser:
        ser.reset_input_buffer()
        ser.write(frame)
        return ser.read(reply_len)


def test_emulator_rtu_frames(rig: SimRig) -> None:
    assert rig.addresses.modbus_rtu is not None
    reply = rtu_exchange(rig.addresses.modbus_rtu, "0103006A0001", 7)
    assert reply == bytes.fromhex("0103022710") + crc16_modbus(bytes.fromhex("0103022710"))
    reply = rtu_exchange(rig.addresses.modbus_rtu, "010600013A98", 5)
    assert reply == bytes.fromhex("018603") + crc16_modbus(bytes.fromhex("018603"))
    assert reply.hex() == "0186030261"  # the exception frame on the wire, CRC included


class FakeModbusServer:
    """A loopback TCP peer that records each request and answers with canned bytes."""

    def __init__(self, replies: list[bytes]) -> None:
        self.replies = replies
        self.requests: list[bytes] = []

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        while self.replies:
            head = await reader.readexactly(6)
            body = await reader.readexactly(int.from_bytes(head[4:6], "big"))
            self.requests.append(head + body)
            writer.write(self.replies.pop(0))
            await writer.drain()
        await reader.read()

    async def __aenter__(self) -> tuple[str, int]:
        self.server = await asyncio.start_server(self._handle, "127.0.0.1", 0)
        return self.server.sockets[0].getsockname()[:2]

    async def __aexit__(self, *exc: object) -> None:
        self.server.close()


def test_driver_requests_and_reply_decoding_are_byte_exact() -> None:
    replies = [
        bytes.fromhex("0001 0000 0006 01 06 0001 07D0".replace(" ", "")),
        # status block 100..105: speed 12.34 Hz, angle 90.00 deg, status 0x0007, fault 0, revs 65538
        bytes.fromhex("0002 0000 000F 01 03 0C 04D2 2328 0007 0000 0001 0002".replace(" ", "")),
        bytes.fromhex("0003 0000 0003 01 86 03".replace(" ", "")),
    ]
    fake = FakeModbusServer(list(replies))

    async def run() -> None:
        async with fake as (host, port):
            motor = MotorController()
            await motor.connect(ModbusTransport.tcp(host, port, policy=LinkPolicy(timeout_s=1.0)))
            await motor.set_frequency(20.0)
            st = await motor.read_status()
            assert st.actual_speed_hz == pytest.approx(12.34)
            assert st.crank_angle_deg == pytest.approx(90.0)
            assert st.flags["enabled"] and st.flags["at_setpoint"] and not st.flags["fault"]
            assert (st.fault_code, st.fault_name, st.revolution_count) == (0, "none", 65538)
            with pytest.raises(MotorExceptionReplyError) as info:
                await motor.write("acceleration_ramp", 5.0)
            assert info.value.register == "acceleration_ramp"
            assert (info.value.function_code, info.value.exception_code) == (0x06, 0x03)
            assert "ILLEGAL DATA VALUE" in str(info.value)
            await motor.close()

    asyncio.run(run())
    assert [r.hex(" ").upper() for r in fake.requests] == [
        "00 01 00 00 00 06 01 06 00 01 07 D0",  # FC06 frequency_setpoint = 2000 (20.00 Hz)
        "00 02 00 00 00 06 01 03 00 64 00 06",  # FC03 status block, 6 words from 100
        "00 03 00 00 00 06 01 06 00 02 01 F4",  # FC06 acceleration_ramp = 500 (5.00 Hz/s)
    ]


def test_driver_refuses_out_of_range_values_before_sending() -> None:
    fake = FakeModbusServer([bytes.fromhex("0001 0000 0006 01 06 0002 01F4".replace(" ", ""))])

    async def run() -> None:
        async with fake as (host, port):
            motor = MotorController()
            await motor.connect(ModbusTransport.tcp(host, port, policy=LinkPolicy(timeout_s=1.0)))
            for name, value in (("acceleration_ramp", 0.0), ("acceleration_ramp", 100.5), ("enable", 2),
                                ("frequency_setpoint", -1.0), ("watchdog_timeout", 61.0)):
                with pytest.raises(MotorValueError, match=f"register '{name}': expected"):
                    await motor.write(name, value)
            await motor.set_ramp(5.0)  # in range: sent
            await motor.close()

    asyncio.run(run())
    assert [r.hex(" ").upper() for r in fake.requests] == ["00 01 00 00 00 06 01 06 00 02 01 F4"]
