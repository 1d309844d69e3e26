"""The emulator checked by an off-the-shelf Modbus master we did not write: mbpoll (libmodbus).

Skips only when mbpoll is absent and ``CI`` is unset; under CI it must run (``.ci/run`` installs it).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from collections.abc import Iterator

import pytest

from drivers.sim import SimRig

MBPOLL = shutil.which("mbpoll")
if MBPOLL is None:
    if os.environ.get("CI"):
        raise RuntimeError("CI is set but mbpoll is not installed (apt-get install mbpoll)")
    pytest.skip("mbpoll not installed (apt-get install mbpoll); required under CI", allow_module_level=True)


@pytest.fixture(scope="module")
def rig() -> Iterator[SimRig]:
    with SimRig(seed=4) as r:
        yield r


def mbpoll(*args: str) -> subprocess.CompletedProcess[str]:
    assert MBPOLL is not None
    return subprocess.run([MBPOLL, "-a", "1", "-0", "-1", "-o", "1", *args], capture_output=True, text=True,
                          timeout=20)


def values(out: str) -> dict[int, int]:
    """``[ref]: value`` lines of mbpoll's output."""
    return {int(r): int(v) for r, v in re.findall(r"^\[(\d+)\]:\s+(-?\d+)", out, re.MULTILINE)}


def tcp(rig: SimRig, *args: str, write: tuple[str, ...] = ()) -> subprocess.CompletedProcess[str]:
    host, port = rig.addresses.modbus_tcp
    return mbpoll("-m", "tcp", "-p", str(port), *args, host, *write)


def test_mbpoll_reads_the_status_block_over_tcp(rig: SimRig) -> None:
    m = rig.motor
    m.set_watchdog_timeout(60.0)  # 0 (off) is refused with the drive enabled
    m.set_ramp(100.0)
    m.set_setpoint(12.5)
    m.set_enable(True)
    while m.speed_hz() < 12.5:
        pass
    r = tcp(rig, "-r", "100", "-c", "7")
    assert r.returncode == 0, r.stderr
    v = values(r.stdout)
    assert v[100] == 1250  # actual_speed 12.50 Hz
    assert 0 <= v[101] < 36000  # crank_angle in 0.01 deg
    assert v[102] & 0b111 == 0b111  # enabled, running, at_setpoint
    assert v[103] == 0 and v[106] == 10000
    m.set_enable(False)
    while m.speed_hz() > 0.0:
        pass
    m.preset_angle(2 * 3.141592653589793 * 70000.25)  # 70000 = 0x0001_1170 revolutions
    r16 = tcp(rig, "-r", "104", "-c", "2")
    r32 = tcp(rig, "-t", "4:int", "-B", "-r", "104")  # uint32, high word first
    assert r16.returncode == 0 and r32.returncode == 0, r32.stderr
    hi, lo = values(r16.stdout)[104], values(r16.stdout)[105]
    revs = int(m.snapshot().angle_rad / (2 * 3.141592653589793))
    assert (hi, lo) == (0x0001, 0x1170)
    assert values(r32.stdout)[104] == hi << 16 | lo == revs == 70000


def test_mbpoll_writes_and_gets_the_exception_reply(rig: SimRig) -> None:
    r = tcp(rig, "-r", "1", write=("2000",))
    assert r.returncode == 0, r.stderr
    assert rig.motor.snapshot().setpoint_hz == pytest.approx(20.0)
    r = tcp(rig, "-r", "1", write=("15000",))  # 150 Hz beyond the configured maximum
    assert r.returncode != 0
    assert "Illegal data value" in r.stderr
    assert rig.motor.snapshot().setpoint_hz == pytest.approx(20.0)
    r = tcp(rig, "-r", "100", write=("1",))  # read-only register
    assert r.returncode != 0 and "Illegal data address" in r.stderr


def test_mbpoll_reads_over_rtu_on_the_pty(rig: SimRig) -> None:
    assert rig.addresses.modbus_rtu is not None
    r = mbpoll("-m", "rtu", "-b", "115200", "-P", "none", "-r", "106", rig.addresses.modbus_rtu)
    assert r.returncode == 0, r.stderr
    assert values(r.stdout) == {106: 10000}
