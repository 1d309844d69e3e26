"""The stop port: a listener of its own for ``POST /stop`` (its socket, its thread and loop).

The app runs in process on the simulated rig's virtual clock; the stop port is the real listener
on loopback, spoken to with raw HTTP/1.1 over TCP.  Times are not asserted (bench/stop_latency.py
measures them)."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import socket
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

from station.commands import stop as stop_command
from station.commands.connections import ConnectionBounds
from station.commands.stopport import daemon_stop_port
from station.rigproc.stopport import MAX_HEAD_BYTES, StopPort, host_refusal, parse_head, station_names
from tests.station_support import (
    CAPPED,
    app_in_process,
    run_body,
    served_on_a_socket,
    start,
    wait_state,
)

PAGE_PORT = 8080  # the main port the stop port names as the station's page (not listened on in these tests)


@contextlib.asynccontextmanager
async def stop_port(m: Any, **kw: Any) -> AsyncIterator[StopPort]:
    port = await asyncio.to_thread(daemon_stop_port(m, m.settings, "127.0.0.1", 0, page_port=PAGE_PORT, **kw).start)
    try:
        yield port
    finally:
        await asyncio.to_thread(port.close)


async def raw(port: int, request: bytes) -> tuple[int, dict[str, str], dict[str, Any]]:
    """Send ``request`` as it is; (status, headers, JSON body) of the answer (the port closes it)."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        writer.write(request)
        await writer.drain()
        data = await asyncio.wait_for(reader.read(), 30.0)
    finally:
        writer.close()
    head, _, body = data.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    headers = {k.lower(): v.strip() for k, _, v in (line.partition(":") for line in lines[1:])}
    return int(lines[0].split(" ")[1]), headers, json.loads(body)


def req(method: str, port: int, *headers: str, path: str = "/stop") -> bytes:
    return "\r\n".join([f"{method} {path} HTTP/1.1", f"Host: 127.0.0.1:{port}", *headers, "", ""]).encode()


def test_the_head_parser_takes_http1_and_refuses_the_rest() -> None:
    method, target, headers = parse_head(b"POST /stop?client=page HTTP/1.1\r\nHost: a:1\r\nOrigin:  x \r\n\r\n")
    assert (method, target, headers) == ("POST", "/stop?client=page", {"host": "a:1", "origin": "x"})
    for bad in (b"POST /stop\r\n\r\n", b"\x16\x03\x01 TLS HTTP/1.1\r\n\r\n", b"POST /stop HTTP/2\r\n\r\n",
                b"POST /stop HTTP/1.1\r\nno colon\r\n\r\n", b"POST /stop HTTP/1.1\r\nHost: a\r\nHost: b\r\n\r\n",
                b"POST /stop HTTP/1.1\r\nContent-Length: -1\r\n\r\n",
                b"POST /stop HTTP/1.1\r\nTransfer-Encoding: chunked\r\n\r\n"):
        with pytest.raises(Exception, match=r"request line|header|Content-Length|no body"):
            parse_head(bad)


def test_the_host_header_must_name_this_station() -> None:
    names = frozenset({"rig-3.lab.example"})
    for ok in ("127.0.0.1:8081", "localhost:8081", "LOCALHOST", "localhost.", "[::1]:8081", "[::1]",
               "192.168.1.20:8081", "10.0.0.7", "[fe80::1]:8081", "rig-3.lab.example:8081", "RIG-3.lab.example"):
        assert host_refusal(ok, names) is None, ok
    for bad in ("rebind.test:8081", "evil.example", "localhost.evil.example:8081", "127.0.0.1.evil.example",
                "rig-3.lab.example.evil.example", "2130706433:8081", "[::1", "[::1]x", "[rebind.test]:8081"):
        assert host_refusal(bad, names) is not None, bad
    assert "no Host" in (host_refusal("", names) or "")


def test_the_station_names_are_the_configured_ones_and_a_named_listen_address(tmp_path: Path) -> None:
    from station.config import parse_config
    from station.service.settings import build_settings
    from tests.station_support import TOKEN, daemon_config

    def names(host: str, configured: list[str]) -> frozenset[str]:
        d = daemon_config(tmp_path / "rec")
        d["service"]["host_names"] = configured
        return station_names(build_settings(parse_config(d), sim=True, host=host, env={"STATION_TOKEN": TOKEN}))
    assert names("0.0.0.0", ["Rig-3.lab.example."]) == {"rig-3.lab.example"}
    assert names("::", []) == frozenset()
    assert names("rig-3", []) == {"rig-3"}


@pytest.mark.slow
def test_stop_port_stops_the_drive_and_refuses_bad_and_cross_site_requests_without_effect(tmp_path: Path) -> None:
    async def go() -> None:
        async with app_in_process(tmp_path / "rec", **CAPPED) as (m, c), stop_port(m) as sp:
            p = sp.port
            refused = [
                (b"GARBAGE\r\n\r\n", 400),
                (req("POST", p, "X-Big: " + "a" * (MAX_HEAD_BYTES + 10)), 431),
                (req("POST", p, "Transfer-Encoding: chunked"), 400),
                (req("POST", p, "Origin: http://evil.example", "Sec-Fetch-Site: cross-site"), 403),
                (req("POST", p, "Origin: http://127.0.0.1:9999", "Sec-Fetch-Site: same-site"), 403),
                (req("POST", p, "Sec-Fetch-Site: cross-site"), 403),
                (b"POST /stop HTTP/1.1\r\nHost: rebind.test:%d\r\n\r\n" % p, 403),  # DNS rebinding
                (b"GET /stop HTTP/1.1\r\nHost: rebind.test:%d\r\n\r\n" % p, 403),
                (b"POST /stop HTTP/1.1\r\n\r\n", 400),  # no Host
                (req("POST", p, path="/runs"), 404),
                (req("PUT", p), 405),
            ]
            for request, want in refused:
                status, headers, body = await raw(p, request)
                assert status == want, (request[:60], body)
                # a refusal as problem details, as the main port answers
                assert headers["content-type"] == "application/problem+json" and body["status"] == want
                assert body["type"].startswith("urn:sinecal:problem:") and body["detail"]
            assert not m.latch.latched and await m.link.motor_fault() is None  # no effect
            status, _, body = await raw(p, req("GET", p))
            assert status == 200 and body["estop"]["latched"] is False

            rid = await start(c, freqs=(10.0,), record_s=120.0)
            await wait_state(c, rid, ("running",), "recording")
            # the station's own page (the main port's origin: same site, another port)
            status, headers, body = await raw(p, req("POST", p, f"Origin: http://127.0.0.1:{PAGE_PORT}",
                                                     "Sec-Fetch-Site: same-site", path="/stop?client=page"))
            assert status == 200, body
            assert headers["access-control-allow-origin"] == f"http://127.0.0.1:{PAGE_PORT}"
            assert body["stop_commanded"] and body["motor_stopped"] and body["aborted_runs"] == [rid], body
            assert body["drive"]["standstill"] and body["drive"]["speed_hz"] == 0.0
            assert await m.link.motor_fault() == (2, "emergency_stop")  # the drive has it
            st = await wait_state(c, rid, ("aborted",))
            assert "emergency stop" in st["message"]
            # the same latch as the main port's stop: shown there and here, refusing runs
            h = (await c.get("/health")).json()
            assert h["estop"]["latched"] and h["estop"]["source"] == "page"
            assert (await c.post("/runs", json=run_body(freqs=(10.0,)))).status_code == 409
            status, _, body = await raw(p, req("GET", p))
            assert body["estop"]["latched"] and body["drive"]["standstill"] is True
            # `station stop` goes to the stop port (the main port here listens nowhere)
            args = argparse.Namespace(url="http://127.0.0.1:9", stop_port=p)
            assert await asyncio.to_thread(stop_command.run, args) == 0
            assert m.latch.state()["count"] == 2
    asyncio.run(go())


@pytest.mark.slow  # ~3 s: a real uvicorn main port, a few hundred idle connections on it and a flood on the stop port
def test_stop_port_stops_past_idle_connections_on_the_main_port_and_its_own(tmp_path: Path) -> None:
    async def go() -> None:
        bounds = ConnectionBounds(max_connections=64, header_timeout_s=10.0)
        async with app_in_process(tmp_path / "rec", **CAPPED) as (m, c), stop_port(m, max_connections=16) as sp, \
                served_on_a_socket(c._transport.app, bounds) as main_port:  # type: ignore[attr-defined]
            idle: list[socket.socket] = []
            try:
                rid = await start(c, freqs=(10.0,), record_s=120.0)
                await wait_state(c, rid, ("running",), "recording")
                for _ in range(300):
                    idle.append(socket.create_connection(("127.0.0.1", main_port)))
                for _ in range(40):  # more idle ones than the stop port's own cap
                    idle.append(socket.create_connection(("127.0.0.1", sp.port)))
                await asyncio.sleep(0.2)
                status, _, body = await raw(sp.port, req("POST", sp.port))
                assert status == 200 and body["stop_commanded"] and body["aborted_runs"] == [rid], body
                assert await m.link.motor_fault() == (2, "emergency_stop")
                assert sp.evicted >= 40 - 16
                assert (await wait_state(c, rid, ("aborted",)))["state"] == "aborted"
            finally:
                for s in idle:
                    s.close()
    asyncio.run(go())


def test_station_stop_tries_the_main_port_when_the_stop_port_refuses(monkeypatch: pytest.MonkeyPatch,
                                                                     capsys: pytest.CaptureFixture[str]) -> None:
    import io
    import urllib.error

    asked: list[str] = []

    def post(url: str) -> dict[str, Any]:
        asked.append(url)
        if ":8081/" in url:  # the stop port does not take the name the station was reached by
            raise urllib.error.HTTPError(url, 403, "Forbidden", {}, io.BytesIO(b'{"detail": "Host"}'))  # type: ignore[arg-type]
        return {"detail": "stopped", "motor_stopped": True, "aborted_runs": []}

    monkeypatch.setattr(stop_command, "_post", post)
    assert stop_command.run(argparse.Namespace(url="http://rig-3:8080", stop_port=None)) == 0
    assert asked == ["http://rig-3:8081/stop", "http://rig-3:8080/stop"]
    assert "refused the stop (403" in capsys.readouterr().err
