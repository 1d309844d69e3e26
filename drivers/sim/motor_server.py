"""The motor-controller emulator: a real pymodbus server (TCP on loopback, RTU over a pty).

Every request goes through pymodbus' own framing and PDU code; the device logic is the
:class:`MotorRegisterImage` hooked in as the ``SimDevice`` action.  Before pymodbus sees a request,
:func:`screen_request` applies the controller's documented behaviour: no reply to another unit id,
exception 01 ILLEGAL FUNCTION for every function but 03/06/16, exception 03 ILLEGAL DATA VALUE for a
bad quantity or byte count.  Fault injection (:class:`ModbusFaults`) drops replies (the client times
out) or answers with exception codes.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
from dataclasses import dataclass, field
from typing import Any, TypeVar

from pymodbus import FramerType
from pymodbus.constants import ExcCodes
from pymodbus.pdu import ExceptionResponse
from pymodbus.server import ModbusBaseServer, ModbusSerialServer, ModbusTcpServer
from pymodbus.server.requesthandler import ServerRequestHandler
from pymodbus.simulator import DataType, SimData, SimDevice

from drivers.motor.profile import DriveProfile
from drivers.sim.motor_image import NO_REPLY, MotorRegisterImage
from drivers.sim.pty import PtyBridge

log = logging.getLogger(__name__)

LOOPBACK = "127.0.0.1"
DOCUMENTED_FUNCTIONS = (0x03, 0x06, 0x10)
SILENT = -1  # screen_request verdict: no reply at all
# RTU character format of the emulator's pty: a pty carries bytes, not characters, so parity is not
# emulated; and Linux refuses even parity (PARENB without PARODD) on a pty with EINVAL.  The emulator
# therefore opens its pty 8N2 (the spec's format without parity); a client on the pty must use
# parity="N" (8N2), see SimRigAddresses.modbus_rtu_url.  Real controllers: 8E1 (the driver's default).
RTU_PARITY = "N"
RTU_STOPBITS = 2


def screen_request(device_id: int, unit: int, pdu: bytes,
                   functions: tuple[int, ...] = DOCUMENTED_FUNCTIONS, max_read: int = 125) -> int | None:
    """The drive's answer before any register is touched: ``SILENT`` (another unit id, including
    broadcast 0: not supported), an exception code (01 a function the drive does not answer, by its
    profile; 03 quantity, byte count or length wrong for 03/04/06/16), or None (a well-formed request
    of a function it answers).  A read longer than ``max_read`` (the drive's longest read) is 03."""
    if unit != device_id:
        return SILENT
    fc = pdu[0]
    if fc not in functions:
        return int(ExcCodes.ILLEGAL_FUNCTION)
    if fc in (0x03, 0x04):
        ok = len(pdu) == 5 and 1 <= int.from_bytes(pdu[3:5], "big") <= max_read
    elif fc == 0x06:
        ok = len(pdu) == 5
    else:
        qty = int.from_bytes(pdu[3:5], "big") if len(pdu) >= 6 else 0
        ok = 1 <= qty <= 123 and pdu[5] == 2 * qty and len(pdu) == 6 + 2 * qty
    return None if ok else int(ExcCodes.ILLEGAL_VALUE)


class _ScreeningHandler(ServerRequestHandler):
    """pymodbus' request handler with :func:`screen_request` in front."""

    device_id = 1
    functions: tuple[int, ...] = DOCUMENTED_FUNCTIONS
    max_read = 125

    def callback_data(self, data: bytes, addr: tuple[Any, ...] | None = None) -> int:
        used, unit, tid, pdu = self.framer.decode(data)
        if used and pdu:
            verdict = screen_request(self.device_id, unit, pdu, self.functions, self.max_read)
            if verdict == SILENT:
                log.info("motor emulator: request for unit %d ignored (this is unit %d)", unit, self.device_id)
                return used
            if verdict is not None:
                log.info("motor emulator: function 0x%02X answered with exception %d", pdu[0], verdict)
                # pymodbus leaves server_send (and the servers' shutdown) without annotations
                self.server_send(ExceptionResponse(pdu[0], verdict, device_id=unit, transaction=tid), addr)  # type: ignore[no-untyped-call]
                return used
        return int(super().callback_data(data, addr))


_Server = TypeVar("_Server", bound=ModbusBaseServer)


def _screening(server_cls: type[_Server], device_id: int, functions: tuple[int, ...], max_read: int) -> type[_Server]:
    """``server_cls`` whose connections are handled by a :class:`_ScreeningHandler` for this drive."""
    handler: type[_ScreeningHandler] = type("ScreeningHandler", (_ScreeningHandler,),
                                            {"device_id": device_id, "functions": functions, "max_read": max_read})

    def callback_new_connection(self: ModbusBaseServer) -> ServerRequestHandler:
        return handler(self, self.trace_packet, self.trace_pdu, self.trace_connect)

    screened: type[_Server] = type(f"Screened{server_cls.__name__}", (server_cls,),
                                   {"callback_new_connection": callback_new_connection})
    return screened


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

    def pending_drops(self) -> int:
        with self._lock:
            return self._drop

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
                 rtu_baudrate: int = 115200, rtu_local_echo: bool = False) -> None:
        """``rtu_local_echo``: the RTU line echoes every byte the client sends back to it, as an
        RS-485 adapter without echo suppression does."""
        self.image = image
        self.map: DriveProfile = image.profile
        self.faults = ModbusFaults()
        self._tcp_port = tcp_port
        self._rtu = rtu
        self._baud = rtu_baudrate
        self._echo = rtu_local_echo
        t = self.map.transport
        self._tcp_cls = _screening(ModbusTcpServer, t.unit_id, t.functions, t.max_registers_per_read)
        self._serial_cls = _screening(ModbusSerialServer, t.unit_id, t.functions, t.max_registers_per_read)
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
        return SimDevice(self.map.transport.unit_id, simdata=simdata, action=self._action)

    async def _action(self, function_code: int, start_address: int, address: int, count: int,
                      registers: list[int], set_values: list[int] | list[bool] | None) -> ExcCodes | None:
        injected = self.faults.take_exception(address, count)
        if injected is not None:
            log.info("motor emulator: injected exception %d for fc %d @%d", injected, function_code, address)
            return ExcCodes(injected)
        if set_values is None:  # read
            # pymodbus also reads through the action before a write (FC 06/16): that is a holding read
            result = self.image.read(address, count, 0x04 if function_code == 0x04 else 0x03)
            if result == NO_REPLY:
                self._no_reply()
                return None
            if isinstance(result, int):
                return ExcCodes(result)
            registers[address - start_address: address - start_address + count] = result
            return None
        code = self.image.write(address, [int(v) for v in set_values])
        if code == NO_REPLY:
            self._no_reply()
            return None
        return ExcCodes(code) if code is not None else None

    def _no_reply(self) -> None:
        """The drive reboots: this request's reply is not sent (once per request: pymodbus also
        reads through the action before a write)."""
        if not self.faults.pending_drops():
            self.faults.drop_replies(1)

    def _trace_packet(self, sending: bool, data: bytes) -> bytes:
        if sending and self.faults.take_drop():
            log.info("motor emulator: injected drop of reply %s", data.hex())
            return b""
        return data

    async def start(self) -> None:
        """Start listening: TCP on 127.0.0.1 (port 0 = any free port) and RTU on a pty."""
        self._tcp = self._tcp_cls(self._device(), address=(LOOPBACK, self._tcp_port),
                                  trace_packet=self._trace_packet)
        await self._tcp.serve_forever(background=True)
        sockets = getattr(self._tcp.transport, "sockets", None)  # an asyncio Server
        if not sockets:
            raise RuntimeError("the Modbus TCP server did not open its socket")
        sock = sockets[0]
        self.tcp_address = sock.getsockname()[:2]
        if self._rtu:
            self._bridge = PtyBridge(echo_b=self._echo).start()
            self._serial = self._serial_cls(
                self._device(), framer=FramerType.RTU, port=self._bridge.a.path, baudrate=self._baud,
                parity=RTU_PARITY, stopbits=RTU_STOPBITS, bytesize=8, trace_packet=self._trace_packet)
            await self._serial.serve_forever(background=True)
            self.rtu_path = self._bridge.b.path
        log.info("motor emulator: Modbus TCP on %s:%d, RTU on %s", *self.tcp_address, self.rtu_path)

    async def stop_tcp(self) -> None:
        """Close the TCP listener and its connections (fault injection: lost link)."""
        if self._tcp is not None:
            await self._tcp.shutdown()  # type: ignore[no-untyped-call]  # unannotated in pymodbus
            self._tcp = None

    async def restart_tcp(self) -> None:
        """Listen again on the same TCP port after :meth:`stop_tcp`."""
        if self._tcp is None and self.tcp_address is not None:
            self._tcp = self._tcp_cls(self._device(), address=self.tcp_address,
                                      trace_packet=self._trace_packet)
            await self._tcp.serve_forever(background=True)

    async def stop(self) -> None:
        await self.stop_tcp()
        if self._serial is not None:
            with contextlib.suppress(Exception):
                await self._serial.shutdown()  # type: ignore[no-untyped-call]  # unannotated in pymodbus
            self._serial = None
        if self._bridge is not None:
            await asyncio.to_thread(self._bridge.close)
            self._bridge = None
