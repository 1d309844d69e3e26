"""The technician's rough edges, in process: /docs works without a network, the command line says
what is wrong and what to do in one line, /health names the device that cannot be reached."""

from __future__ import annotations

import asyncio
import re
from pathlib import Path

import pytest

from station.cli import main
from tests.station_support import CAPPED, app_in_process


@pytest.mark.slow
def test_api_docs_load_nothing_from_another_host(tmp_path: Path) -> None:
    async def go() -> None:
        async with app_in_process(tmp_path / "rec", **CAPPED) as (_, c):
            for page in ("/docs", "/redoc"):
                html = (await c.get(page)).text
                urls = re.findall(r"""(?:src|href)=["']([^"']+)["']|url:\\s*["']([^"']+)["']""", html)
                found = [u for pair in urls for u in pair if u]
                assert found and all(u.startswith("/") for u in found), (page, found)
                for u in found:
                    r = await c.get(u)
                    assert r.status_code == 200 and len(r.content) > 100, (page, u, r.status_code)
            assert (await c.get("/openapi.json")).json()["openapi"].startswith("3.1")
    asyncio.run(go())


@pytest.mark.parametrize(("argv", "says"), [
    (["identify"], "name the recording to identify, e.g. `station identify recordings/"),
    (["calibrate", "--sim", "--steps", "3,5,200"], "200 Hz: outside the rig's crank frequency range [1, 100] Hz"),
])
def test_cli_errors_are_one_line_with_the_fix(argv: list[str], says: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and says in err[0] and "Traceback" not in err[0], err


def test_a_connection_failure_is_named_under_its_device() -> None:
    from drivers.daq.link import DaqLinkError
    from drivers.motor.errors import MotorLinkError
    from station.service.riglink import device_of

    assert device_of(MotorLinkError("<connect>", "link to modbus-tcp://127.0.0.1:502 lost")) == "motor"
    assert device_of(DaqLinkError("/dev/ttyACM0: no such device")) == "daq"
    assert device_of(RuntimeError("?")) is None
