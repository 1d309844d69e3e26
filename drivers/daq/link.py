"""Byte links under the DAQ driver: a serial port (pyserial; also a pty) or an in-process socket."""

from __future__ import annotations

import contextlib
import socket
from typing import Protocol

import serial

from drivers.daq.protocol import LINK_KINDS


class DaqLinkError(ConnectionError):
    """The link to the bridge is lost (port closed, device unplugged, read/write failure)."""


class ByteLink(Protocol):
    """A bidirectional byte stream.  ``read`` returns what arrived within ``timeout_s`` (may be b"")."""

    description: str

    def read(self, max_bytes: int, timeout_s: float) -> bytes: ...

    def write(self, data: bytes) -> None: ...

    def close(self) -> None: ...


class SerialLink:
    """pyserial port; ``read`` drains continuously for up to ``timeout_s`` (batched reads).

    ``kind``: ``"uart"`` (a UART, also behind a USB-serial adapter: ``baudrate`` is the line's rate and
    bounds the stream) or ``"usb-cdc"`` (the bridge's own USB port: the baud rate is ignored by the
    device and the stream is bounded by the throughput the bridge reports)."""

    def __init__(self, port: str, *, baudrate: int = 3_000_000, kind: str = "uart") -> None:
        if kind not in LINK_KINDS:
            raise ValueError(f"DAQ link kind: expected one of {', '.join(LINK_KINDS)}, got {kind!r}")
        self.kind = kind
        try:  # exclusive: a second program on the port is refused, never sharing the stream with us
            self._ser = serial.Serial(port, baudrate=baudrate, timeout=0.02, write_timeout=1.0, exclusive=True)
        except (serial.SerialException, OSError) as exc:
            busy = "lock" in str(exc).lower()
            raise DaqLinkError(f"cannot open DAQ bridge port {port}: "
                               + ("another program has it open" if busy else str(exc))) from exc
        self.description = f"serial {port} @ {baudrate} Bd" if kind == "uart" else f"usb-cdc {port}"
        self.baudrate = baudrate

    def read(self, max_bytes: int, timeout_s: float) -> bytes:
        try:
            if self._ser.timeout != timeout_s:
                self._ser.timeout = timeout_s
            data: bytes = self._ser.read(max_bytes)
            return data
        except (serial.SerialException, OSError, TypeError) as exc:
            raise DaqLinkError(f"{self.description}: read failed: {exc}") from exc

    def read_first(self, max_bytes: int, timeout_s: float) -> bytes:
        """What arrived, returned as soon as anything did (b"" after ``timeout_s``): the bridge's
        reader while no stream runs wakes at once for a reply and otherwise seldom."""
        try:
            if self._ser.timeout != timeout_s:
                self._ser.timeout = timeout_s
            first: bytes = self._ser.read(1)
            waiting = self._ser.in_waiting if first else 0
            return first + self._ser.read(min(waiting, max_bytes - 1)) if waiting else first
        except (serial.SerialException, OSError, TypeError) as exc:
            raise DaqLinkError(f"{self.description}: read failed: {exc}") from exc

    def write(self, data: bytes) -> None:
        try:
            self._ser.write(data)
        except (serial.SerialException, OSError) as exc:
            raise DaqLinkError(f"{self.description}: write failed: {exc}") from exc

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self._ser.close()


class SocketLink:
    """One end of ``socket.socketpair()`` (in-process backend for fast unit tests)."""

    def __init__(self, sock: socket.socket) -> None:
        self._sock = sock
        self.description = "in-process socket"

    def read(self, max_bytes: int, timeout_s: float) -> bytes:
        self._sock.settimeout(timeout_s)
        try:
            data = self._sock.recv(max_bytes)
        except TimeoutError:
            return b""
        except OSError as exc:
            raise DaqLinkError(f"{self.description}: read failed: {exc}") from exc
        if not data:
            raise DaqLinkError(f"{self.description}: closed by the bridge")
        return data

    def write(self, data: bytes) -> None:
        try:
            self._sock.sendall(data)
        except OSError as exc:
            raise DaqLinkError(f"{self.description}: write failed: {exc}") from exc

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self._sock.close()
