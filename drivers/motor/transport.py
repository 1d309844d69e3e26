"""Register transports: the backend a :class:`~drivers.motor.controller.MotorController` talks through.

A transport moves 16-bit holding-register words; it knows nothing of names or scaling except
``what`` (the register name), which it puts into every error it raises.  The Modbus transport
(TCP or RTU, pymodbus 3.x async client) adds time-outs, retries (of reads and of the writes the
caller says are idempotent) and reconnect with back-off.
The in-process backend for fast unit tests lives in :mod:`drivers.sim.motor_inprocess`.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable
from urllib.parse import parse_qs, urlparse

from pymodbus import FramerType
from pymodbus.client import AsyncModbusSerialClient, AsyncModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException

from drivers.motor.errors import (
    MotorExceptionReplyError,
    MotorLinkError,
    MotorProtocolError,
    MotorTimeoutError,
)

log = logging.getLogger(__name__)

ModbusClient = AsyncModbusTcpClient | AsyncModbusSerialClient


class RegisterTransport(Protocol):
    """Word-level access to the controller's holding registers (0-based addresses)."""

    description: str

    async def open(self) -> None: ...

    async def read(self, address: int, count: int, what: str, function: int = 0x03) -> list[int]: ...

    async def write(self, address: int, words: Sequence[int], what: str, *, retry: bool = True) -> None:
        """``retry=False``: sent once, never again after a time-out (a write that is not idempotent)."""

    async def close(self) -> None: ...


@runtime_checkable
class PeerKeptWatchdog(Protocol):
    """A transport whose other end refreshes the drive's communication watchdog itself (a process
    that owns the drive's connection): the controller's keeper asks it whether the refreshes still
    go through instead of refreshing the drive a second time, and that question is the peer's sign
    that this side lives."""

    async def watchdog_status(self) -> None:
        """Return while the peer's refreshes go through; raise ``MotorError`` naming why not."""


@dataclass(frozen=True)
class LinkPolicy:
    """Time-out per request (s), retries after a time-out, reconnect back-off (s) and budget."""

    timeout_s: float = 0.5
    retries: int = 2
    backoff_initial_s: float = 0.05
    backoff_max_s: float = 2.0
    reconnect_attempts: int = 5


class ModbusTransport:
    """pymodbus async client with our own retry/reconnect policy (pymodbus' auto-reconnect is off)."""

    def __init__(self, make_client: Callable[[], ModbusClient], description: str, *, device_id: int = 1,
                 policy: LinkPolicy | None = None, inter_frame_delay_s: float = 0.0) -> None:
        """``inter_frame_delay_s``: the pause the drive needs between the end of one exchange and the
        next request (s)."""
        self._make_client = make_client
        self.description = description
        self.device_id = device_id
        self.policy = policy or LinkPolicy()
        self.inter_frame_delay_s = inter_frame_delay_s
        self._client: ModbusClient | None = None
        self._last_exchange = -math.inf
        self.reconnects = 0

    @classmethod
    def tcp(cls, host: str, port: int, *, device_id: int = 1,
            policy: LinkPolicy | None = None) -> ModbusTransport:
        """Modbus TCP (MBAP framing) to ``host:port``."""
        pol = policy or LinkPolicy()

        def make() -> ModbusClient:
            return AsyncModbusTcpClient(host, port=port, framer=FramerType.SOCKET, timeout=pol.timeout_s,
                                        retries=0, reconnect_delay=0)

        return cls(make, f"modbus-tcp://{host}:{port}", device_id=device_id, policy=pol)

    @classmethod
    def rtu(cls, port: str, *, baudrate: int = 115200, parity: str = "E", stopbits: int | None = None,
            local_echo: bool = False, device_id: int = 1, policy: LinkPolicy | None = None) -> ModbusTransport:
        """Modbus RTU (CRC-16 framing) on serial device ``port``.

        Character format as the Modbus serial-line spec asks: 8 data bits, ``parity`` "E" (default),
        "O" or "N"; ``stopbits`` defaults to 1 with parity and 2 without (8E1, 8O1, 8N2).
        ``local_echo``: the adapter (RS-485 half duplex) echoes what we send; read it back and discard it.
        """
        parity, stopbits = rtu_line_settings(parity, stopbits)
        if not isinstance(baudrate, int) or isinstance(baudrate, bool) or baudrate <= 0:
            raise ValueError(f"Modbus RTU baudrate: expected a positive integer, got {baudrate!r}")
        pol = policy or LinkPolicy()

        def make() -> ModbusClient:
            return AsyncModbusSerialClient(port, framer=FramerType.RTU, baudrate=baudrate, parity=parity,
                                           stopbits=stopbits, bytesize=8, timeout=pol.timeout_s, retries=0,
                                           reconnect_delay=0, handle_local_echo=local_echo)

        desc = f"modbus-rtu://{port}?baudrate={baudrate}&parity={parity}&stopbits={stopbits}" + (
            "&echo=1" if local_echo else "")
        return cls(make, desc, device_id=device_id, policy=pol)

    @property
    def connected(self) -> bool:
        return self._client is not None and self._client.connected

    async def open(self) -> None:
        await self._ensure_connected("<connect>")

    async def _ensure_connected(self, what: str) -> ModbusClient:
        if self._client is not None and self._client.connected:
            return self._client
        delay = self.policy.backoff_initial_s
        for attempt in range(1, self.policy.reconnect_attempts + 1):
            if self._client is not None:
                self._client.close()
            self._client = self._make_client()
            try:
                ok = await self._client.connect()
            except (OSError, ModbusException) as exc:
                log.debug("connect to %s failed: %s", self.description, exc)
                ok = False
            if ok:
                if attempt > 1 or self.reconnects:
                    log.info("reconnected to %s (attempt %d)", self.description, attempt)
                self.reconnects += 1
                return self._client
            if attempt == self.policy.reconnect_attempts:
                break
            log.warning("cannot connect to %s (attempt %d/%d), retrying in %.2f s",
                        self.description, attempt, self.policy.reconnect_attempts, delay)
            await asyncio.sleep(delay)
            delay = min(2 * delay, self.policy.backoff_max_s)
        raise MotorLinkError(what, f"link to {self.description} lost; "
                                   f"{self.policy.reconnect_attempts} reconnect attempts failed")

    async def _call(self, what: str, fc: int, request: Callable[[ModbusClient], Awaitable[Any]],
                    retry: bool = True) -> Any:
        last = "no attempt"
        lost = False
        attempts = self.policy.retries + 1 if retry else 1
        for _ in range(attempts):
            client = await self._ensure_connected(what)
            pause = self._last_exchange + self.inter_frame_delay_s - time.monotonic()
            if pause > 0:
                await asyncio.sleep(pause)
            try:
                reply = await request(client)
            except ConnectionException as exc:
                last, lost = f"connection lost ({exc})", True
                client.close()
                continue
            except ModbusException as exc:  # pymodbus raises ModbusIOException on time-out
                last, lost = f"no reply within {self.policy.timeout_s} s ({exc})", False
                if not client.connected:
                    lost = True
                continue
            finally:
                self._last_exchange = time.monotonic()
            if reply.isError():
                code = getattr(reply, "exception_code", 0)
                raise MotorExceptionReplyError(what, fc, code)
            return reply
        once = "" if retry else " (sent once, not repeated: the drive may or may not have taken it)"
        if lost:
            raise MotorLinkError(what, f"{self.description}: {last}{once}")
        raise MotorTimeoutError(what, f"{self.description}: {last} after {attempts} attempt(s){once}")

    async def read(self, address: int, count: int, what: str, function: int = 0x03) -> list[int]:
        """FC 03 (holding) or FC 04 (``function=4``, input registers) read of ``count`` words at ``address``."""
        if function == 0x04:
            reply = await self._call(what, 0x04, lambda c: c.read_input_registers(
                address, count=count, device_id=self.device_id))
        else:
            reply = await self._call(what, 0x03, lambda c: c.read_holding_registers(
                address, count=count, device_id=self.device_id))
        regs = list(getattr(reply, "registers", []))
        if len(regs) != count:
            raise MotorProtocolError(what, f"expected {count} register(s) in the reply, got {len(regs)}")
        return regs

    async def write(self, address: int, words: Sequence[int], what: str, *, retry: bool = True) -> None:
        """FC 06 for one word, FC 16 for several.  ``retry=False``: a write that is not idempotent (a
        command word) is sent once and never again after a time-out (:class:`MotorTimeoutError`)."""
        if len(words) == 1:
            await self._call(what, 0x06, lambda c: c.write_register(address, int(words[0]),
                                                                    device_id=self.device_id), retry)
        else:
            await self._call(what, 0x10, lambda c: c.write_registers(address, [int(w) for w in words],
                                                                     device_id=self.device_id), retry)

    async def close(self) -> None:
        if self._client is not None:
            self._client.close()
            self._client = None


def rtu_line_settings(parity: str = "E", stopbits: int | None = None) -> tuple[str, int]:
    """(parity, stop bits) of an RTU line, defaults as the Modbus serial-line spec asks: 8E1, or 8N2
    without parity.  ValueError naming what was expected and what was received."""
    if parity not in ("E", "O", "N"):
        raise ValueError(f"Modbus RTU parity: expected 'E' (even, the default), 'O' or 'N', got {parity!r}")
    if stopbits is None:
        stopbits = 2 if parity == "N" else 1
    if stopbits not in (1, 2):
        raise ValueError(f"Modbus RTU stop bits: expected 1 or 2, got {stopbits!r}")
    return parity, stopbits


_RTU_QUERY_KEYS = ("baudrate", "parity", "stopbits", "echo")


def transport_from_url(url: str, *, device_id: int = 1, policy: LinkPolicy | None = None,
                       baudrate: int = 115200, parity: str = "E", stopbits: int | None = None,
                       inter_frame_delay_s: float = 0.0) -> ModbusTransport:
    """``modbus-tcp://HOST:PORT`` or ``modbus-rtu:///dev/ttyX?baudrate=115200&parity=E&stopbits=1&echo=0``
    (RTU defaults: ``baudrate``, ``parity`` and ``stopbits`` as given, e.g. a drive profile's; else
    115200 Bd, 8E1; 8N2 with ``parity=N``; ``echo=1`` discards the adapter's local echo)."""
    u = urlparse(url)
    if u.scheme == "modbus-tcp":
        if u.hostname is None or u.port is None:
            raise ValueError(f"expected modbus-tcp://HOST:PORT, got {url!r}")
        t = ModbusTransport.tcp(u.hostname, u.port, device_id=device_id, policy=policy)
        t.inter_frame_delay_s = inter_frame_delay_s
        return t
    if u.scheme == "modbus-rtu":
        q = {k: v[-1] for k, v in parse_qs(u.query, keep_blank_values=True).items()}
        unknown = sorted(set(q) - set(_RTU_QUERY_KEYS))
        if unknown:
            raise ValueError(f"modbus-rtu URL: expected query keys among {list(_RTU_QUERY_KEYS)}, got {unknown}")
        try:
            baud = int(q.get("baudrate", str(baudrate)))
            stop = int(q["stopbits"]) if "stopbits" in q else (stopbits if "parity" not in q else None)
        except ValueError:
            raise ValueError(f"modbus-rtu URL: expected integer baudrate and stopbits, got {u.query!r}") from None
        echo = q.get("echo", "0")
        if echo not in ("0", "1"):
            raise ValueError(f"modbus-rtu URL: expected echo=0 or echo=1, got echo={echo!r}")
        t = ModbusTransport.rtu(u.path, baudrate=baud, parity=q.get("parity", parity).upper(), stopbits=stop,
                                local_echo=echo == "1", device_id=device_id, policy=policy)
        t.inter_frame_delay_s = inter_frame_delay_s
        return t
    raise ValueError(f"expected a modbus-tcp:// or modbus-rtu:// URL, got {url!r}")
