"""The bridge firmware's core on an emulated Cortex-M3 (QEMU's mps2-an385, its UART on a pty), against
the station's DAQ driver: the same C core as on the host and the RP2040, cross-compiled with
arm-none-eabi-gcc and newlib.  Skips without the cross compiler or QEMU, except under CI, where
``.ci/run`` installs them."""

from __future__ import annotations

import re
import select
import subprocess
import time
from collections.abc import Iterator

import pytest

from drivers.daq import DaqBridge, DaqCommandError, SerialLink
from tests.firmware_support import build, check_counter_tiling, stream


@pytest.fixture
def qemu_bridge() -> Iterator[str]:
    """QEMU running build/mps2/bridge-mps2.elf; the pty of its UART0 (QEMU is bounded to 60 s)."""
    elf = build("mps2", "arm-none-eabi-gcc", "qemu-system-arm") / "mps2" / "bridge-mps2.elf"
    proc = subprocess.Popen(["timeout", "60", "qemu-system-arm", "-M", "mps2-an385", "-display", "none",
                             "-monitor", "none", "-serial", "pty", "-kernel", str(elf)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        assert proc.stdout is not None
        seen, deadline = "", time.monotonic() + 10
        while (found := re.search(r"/dev/pts/\d+", seen)) is None and time.monotonic() < deadline:
            if select.select([proc.stdout], [], [], 0.5)[0]:
                seen += proc.stdout.readline()
        assert found is not None, f"QEMU did not announce its UART's pty: {seen!r}"
        yield found[0]
    finally:
        proc.terminate()
        proc.wait(timeout=5)


@pytest.mark.slow
def test_the_core_on_an_emulated_cortex_m3_answers_and_streams_without_loss(qemu_bridge: str) -> None:
    daq = DaqBridge()
    daq.connect(SerialLink(qemu_bridge, kind="uart"))  # QEMU notices the open pty within a second
    try:
        assert daq.hardware is not None
        assert daq.hardware.identity == "SINECAL,DAQ-BRIDGE-MPS2,QEMU0001,1.0"
        assert (daq.hardware.link, daq.hardware.adc_clock_hz) == ("uart", 25e6)
        with pytest.raises(DaqCommandError, match=r"ERR 2 bad value for frame: expected integer 16\.\.4096, got '8'"):
            daq.command("CONF frame=8")
        assert daq.command("CONF rate=20000")[:37] == "OK CONF rate=20000 rate_exact=20000 f"  # 25 MHz / 1250
    finally:
        daq.close()
    events, status, summary = stream(qemu_bridge, "uart", 1.0)
    assert summary.frames_sent >= 70  # 1 s at 20 kHz is 78 frames of 256 samples
    assert check_counter_tiling(events, summary.samples_sent) == []  # no gap: every sample, in order
    assert status["overflows"] == "0" and summary.stats.crc_errors == 0
