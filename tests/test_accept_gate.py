"""The main port's accept gate (``station/commands/gate.py``): a thread of its own accepts and holds
silent connections, hands a connection to uvicorn's loop once its first bytes come, and hands a
``POST /stop`` to the rig as soon as its head is there, even while the web server's loop is busy.

A real uvicorn server behind the gate on loopback, in this process; the app with the simulated rig
on its virtual clock (``app_in_process``) where a stop is given.  No time is asserted."""

from __future__ import annotations

import asyncio
import contextlib
import errno
import socket
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from station.api.routes.system import stop_on_arrival
from station.commands.connections import ConnectionBounds
from station.commands.gate import bind, stop_head
from tests.station_support import CAPPED_SPEEDUP, app_in_process, served_on_a_socket, start, wait_state

BOUND_S = 10.0  # every wait below ends by this (never reached when the code is right)
FLOOD = 1000


async def ok_app(scope: Any, receive: Any, send: Any) -> None:
    await send({"type": "http.response.start", "status": 200, "headers": [(b"content-length", b"2")]})
    await send({"type": "http.response.body", "body": b"ok"})


@contextlib.contextmanager
def silent(port: int, n: int) -> Iterator[list[socket.socket]]:
    """``n`` connections to ``port`` that send nothing (non-blocking connects), closed on leaving."""
    socks = []
    try:
        for _ in range(n):
            s = socket.socket()
            s.setblocking(False)
            assert s.connect_ex(("127.0.0.1", port)) in (0, errno.EINPROGRESS)
            socks.append(s)
        yield socks
    finally:
        for s in socks:
            s.close()


def whole_answer(sock: socket.socket) -> bytes:
    """One whole answer of :func:`ok_app` (its head and its 2-byte body), or what came before a close."""
    got = b""
    while not (b"\r\n\r\n" in got and got.endswith(b"ok")) and (part := sock.recv(4096)):
        got += part
    return got


def until_closed(sock: socket.socket) -> bytes:
    got = b""
    while part := sock.recv(65536):
        got += part
    return got


async def settle(cond: Any, what: str) -> None:
    """Wait (letting this loop run) until ``cond()``; fails after :data:`BOUND_S`."""
    deadline = time.monotonic() + BOUND_S
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"not within {BOUND_S:g} s: {what}")
        await asyncio.sleep(0.01)


def until(cond: Any, what: str) -> None:
    """Wait (blocking this thread) until ``cond()``; fails after :data:`BOUND_S`."""
    deadline = time.monotonic() + BOUND_S
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"not within {BOUND_S:g} s: {what}")
        time.sleep(0.01)


def test_a_stop_head_is_recognised_only_whole_and_at_the_stop_path() -> None:
    host = b"Host: 127.0.0.1:8080\r\n"
    assert stop_head(b"POST /stop HTTP/1.1\r\n" + host + b"Origin: http://a\r\n\r\n") == (
        "POST", "/stop", {"host": "127.0.0.1:8080", "origin": "http://a"})
    assert stop_head(b"POST /stop?client=page HTTP/1.1\r\n" + host + b"\r\n")[1] == "/stop"  # type: ignore[index]
    assert stop_head(b"POST /st%6fp HTTP/1.1\r\n" + host + b"\r\n")[1] == "/stop"  # type: ignore[index]
    assert stop_head(b"POST /stop HTTP/1.1\r\n" + host) is None  # the head is not complete
    assert stop_head(b"POST /stop/acknowledge HTTP/1.1\r\n" + host + b"\r\n") is None
    assert stop_head(b"GET /stop HTTP/1.1\r\n" + host + b"\r\n") is None
    assert stop_head(b"POST /stop HTTP/1.1\r\nbroken\r\n\r\n") is None  # the loop answers it (400)


def test_the_gate_listens_on_every_address_of_a_name_on_one_port() -> None:
    socks = bind("localhost", 0, 16)
    try:
        assert socks and len({s.getsockname()[1] for s in socks}) == 1
        with socket.create_connection(("localhost", socks[0].getsockname()[1]), timeout=BOUND_S):
            pass  # the kernel completed the handshake: it listens
    finally:
        for s in socks:
            s.close()


@pytest.mark.slow  # ~3 s: a run on the simulated rig, a thousand connections
def test_a_stop_reaches_the_drive_past_a_thousand_silent_connections_while_the_web_loop_is_held(
        tmp_path: Path) -> None:
    """The web server's loop does not run while a thousand silent connections arrive and a stop is
    sent on a new one (as a loop busy with other work, or a flood, would): the gate accepts them all,
    sees the stop's head and hands the stop to the rig; once the loop runs, the route answers with
    that very stop.  The silent connections never cost the loop a protocol object."""
    async def go() -> None:
        async with app_in_process(tmp_path / "rec", max_speedup=CAPPED_SPEEDUP) as (m, c):
            app = c._transport.app  # type: ignore[attr-defined]
            bounds = ConnectionBounds(max_connections=2 * FLOOD, header_timeout_s=30.0)
            bounds.on_head = stop_on_arrival(app)
            rid = await start(c, freqs=(10.0,), record_s=120.0)
            await wait_state(c, rid, ("running",), "recording")
            async with served_on_a_socket(app, bounds, gated=True) as port:
                motor = m.link.rig.motor

                def fault() -> int:  # read through the rig thread: this loop is held
                    return int(m.link.thread.submit(asyncio.wait_for(motor.read_state(), 2.0)).result(5).fault_code)

                with silent(port, FLOOD):
                    until(lambda: bounds.held == FLOOD, "the flood accepted")  # (this loop held all along)
                    stop = socket.create_connection(("127.0.0.1", port), timeout=BOUND_S)
                    stop.sendall(f"POST /stop HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nConnection: close\r\n\r\n".encode())
                    until(lambda: fault() != 0, "the stop reached the drive while the web loop was held")
                    assert bounds.open == 0  # no connection reached the loop yet
                    with stop:
                        answer = await asyncio.to_thread(until_closed, stop)  # the loop runs again
                    assert answer.startswith(b"HTTP/1.1 200") and b'"stop_commanded":true' in answer, answer[:300]
                    assert bounds.open <= 1 and bounds.held == FLOOD  # the silent ones are still the gate's
            assert await m.link.motor_fault() == (2, "emergency_stop")
            assert m.latch.state()["count"] == 1  # one stop: the gate's, answered by the route
            assert (await wait_state(c, rid))["state"] == "aborted"
    asyncio.run(go())


def test_the_gate_keeps_the_cap_silent_connections_past_their_grace_after_idle_ones() -> None:
    """Silent connections are held off the loop and count against the cap: beyond it the oldest
    silent ones past their grace make room (closed with a FIN), but an idle connection of the loop
    (read and answered) goes first."""
    async def go() -> None:
        bounds = ConnectionBounds(max_connections=4, header_timeout_s=30.0, grace_s=0.1)
        async with served_on_a_socket(ok_app, bounds, gated=True) as port:
            with silent(port, 6) as socks:
                await settle(lambda: bounds.evicted == 2, "the two oldest made room")
                assert bounds.held == 4 and bounds.open == 0
                first, second, asker, *_ = socks
                for s in (first, second, asker):
                    s.setblocking(True)
                    s.settimeout(BOUND_S)
                for s in (first, second):
                    assert s.recv(1) == b""  # closed with a FIN, not reset
                asker.sendall(f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n".encode())
                got = await asyncio.to_thread(whole_answer, asker)
                assert got.startswith(b"HTTP/1.1 200") and got.endswith(b"ok")  # served by the loop, kept alive
                assert bounds.open == 1 and bounds.held == 3
                with silent(port, 1):  # one more: the idle one makes room, not a silent one
                    assert await asyncio.to_thread(asker.recv, 1) == b""
                    await settle(lambda: bounds.open == 0, "the idle one closed")
                    assert bounds.held == 4 and bounds.evicted == 3
    asyncio.run(go())


def test_silent_connections_are_closed_cleanly_at_the_header_timeout_and_a_silent_close_never_reaches_the_loop(
        ) -> None:
    async def go() -> None:
        bounds = ConnectionBounds(max_connections=64, header_timeout_s=0.5)
        async with served_on_a_socket(ok_app, bounds, gated=True) as port:
            with silent(port, 3) as socks:
                for s in socks:
                    s.setblocking(True)
                    s.settimeout(BOUND_S)
                    assert await asyncio.to_thread(s.recv, 1) == b""  # our FIN: a clean close
                assert bounds.held == 0 and bounds.timed_out == 3 and bounds.open == 0
            # a head that trickles in after a silent start is closed by the header timeout
            with socket.create_connection(("127.0.0.1", port)) as late:
                late.settimeout(BOUND_S)
                time.sleep(0.2)
                late.sendall(b"GET / HTTP/1.1\r\n")  # never completed
                with contextlib.suppress(ConnectionResetError):  # closed with its unread head
                    assert await asyncio.to_thread(late.recv, 1) == b""
                assert bounds.timed_out == 4
            # a client that closes without a word never reaches the loop
            socket.create_connection(("127.0.0.1", port)).close()
            await settle(lambda: bounds.held == 0, "the silent close seen")
            assert bounds.open == 0 and bounds.timed_out == 4
    asyncio.run(go())
