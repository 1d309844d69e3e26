"""The motor-controller emulator: a real pymodbus server (TCP on loopback, RTU over a pty).

Every request goes through pymodbus' own framing and PDU code; the device logic is the
:class:`MotorRegisterImage` hooked in as the ``SimDevice`` action.  Fault injection
(:class:`ModbusFaults`) drops replies (the client times out) or answers with exception codes.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
from dataclasses import dataclass, field

from pymodbus import FramerType
from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from drivers.motor.registers import RegisterMap
from drivers.sim.motor_image import MotorRegisterImage
from drivers.sim.pty import PtyBridge

log = logging.getLogger(__name__)

LOOPBACK = "127.0.0.1"


@dataclass
class ModbusFaults:
    """Fault-injection hooks, callable from any thread.

    ``drop_replies(n)``: the next n replies are not sent (the request *is* executed, as when a
    reply is lost on the line).  ``exception_replies(code, n, register)``: the next n requests that
    touch ``register`` (any register if None) are answered with Modbus exception ``code``.
    """

    _lock: threading.Lock = field(default_factory=threading.Lock)
    _drop: int = 0
    _exc: list[tuple[int, int | None]] = field(default_factory=list)  # (code, address or None)
    dropped: int = 0
    exceptions_sent: int = 0

    def drop_replies(self, n: int = 1) -> None:
        with self._lock:
            self._drop += n

    def exception_replies(self, code: int, n: int = 1, address: int | None = None) -> None:
        with self._lock:
            self._exc.extend([(code, address)] * n)

    def clear(self) -> None:
        with self._lock:
            self._drop = 0
            self._exc.clear()

    def take_exception(self, address: int, count: int) -> int | None:
        with self._lock:
            for i, (code, addr) in enumerate(self._exc):
                if addr is None or address <= addr < address + count:
                    del self._exc[i]
                    self.exceptions_sent += 1
                    return code
        return None

    def take_drop(self) -> bool:
        with self._lock:
            if self._drop > 0:
                self._drop -= 1
                self.dropped += 1
                return True
        return False


class MotorEmulator:
    """pymodbus servers around one :class:`MotorRegisterImage`; start/stop inside a running loop."""

    def __init__(self, image: MotorRegisterImage, *, tcp_port: int = 0, rtu: bool = True,
                 rtu_baudrate: int = 115200) -> None:
        self.image = image
        self.map: RegisterMap = image.map
        self.faults = ModbusFaults()
        self._tcp_port = tcp_port
        self._rtu = rtu
        self._baud = rtu_baudrate
        self._tcp: ModbusTcpServer | None = None
        self._serial: ModbusSerialServer | None = None
        self._bridge: PtyBridge | None = None
        self.tcp_address: tuple[str, int] | None = None
        self.rtu_path: str | None = None

    def _device(self) -> SimDevice:
        simdata = [
            SimData(reg.address, values=[0] * reg.words, datatype=DataType.REGISTERS,
                    readonly=not reg.writable)
            for reg in sorted(self.map.registers.values(), key=lambda r: r.address)
        ]
        return SimDevice(self.map.device.device_id, simdata=simdata, action=self._action)

    async def _action(self, function_code: int, start_address: int, address: int, count: int,
                      registers: list[int], set_values: list[int] | list[bool] | None) -> ExcCodes | None:
        injected = self.faults.take_exception(address, count)
        if injected is not None:
            log.info("motor emulator: injected exception %d for fc %d @%d", injected, function_code, address)
            return ExcCodes(injected)
        if set_values is None:  # read
            result = self.image.read(address, count)
            if isinstance(result, int):
                return ExcCodes(result)
            registers[address - start_address: address - start_address + count] = result
            return None
        code = self.image.write(address, [int(v) for v in set_values])
        return ExcCodes(code) if code is not None else None

    def _trace_packet(self, sending: bool, data: bytes) -> bytes:
        if sending and self.faults.take_drop():
            log.info("motor emulator: injected drop of reply %s", data.hex())
            return b""
        return data

    async def start(self) -> None:
        """Start listening: TCP on 127.0.0.1 (port 0 = any free port) and RTU on a pty."""
        self._tcp = ModbusTcpServer(self._device(), address=(LOOPBACK, self._tcp_port),
                                    trace_packet=self._trace_packet)
        await self._tcp.serve_forever(background=True)
        sock = self._tcp.transport.sockets[0]  # type: ignore[union-attr]
        self.tcp_address = sock.getsockname()[:2]
        if self._rtu:
            self._bridge = PtyBridge().start()
            self._serial = ModbusSerialServer(
                self._device(), framer=FramerType.RTU, port=self._bridge.a.path, baudrate=self._baud,
                trace_packet=self._trace_packet)
            await self._serial.serve_forever(background=True)
            self.rtu_path = self._bridge.b.path
        log.info("motor emulator: Modbus TCP on %s:%d, RTU on %s", *self.tcp_address, self.rtu_path)

    async def stop_tcp(self) -> None:
        """Close the TCP listener and its connections (fault injection: lost link)."""
        if self._tcp is not None:
            await self._tcp.shutdown()
            self._tcp = None

    async def restart_tcp(self) -> None:
        """Listen again on the same TCP port after :meth:`stop_tcp`."""
        if self._tcp is None and self.tcp_address is not None:
            self._tcp = ModbusTcpServer(self._device(), address=self.tcp_address,
                                        trace_packet=self._trace_packet)
            await self._tcp.serve_forever(background=True)

    async def stop(self) -> None:
        await self.stop_tcp()
        if self._serial is not None:
            with contextlib.suppress(Exception):
                await self._serial.shutdown()
            self._serial = None
        if self._bridge is not None:
            await asyncio.to_thread(self._bridge.close)
            self._bridge = None
