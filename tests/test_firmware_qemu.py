"""The bridge firmware's core on an emulated Cortex-M3 (QEMU's mps2-an385, its UART on a pty), against
the station's DAQ driver: the same C core as on the host and the RP2040, cross-compiled with
arm-none-eabi-gcc and newlib.  Skips without the cross compiler or QEMU, except under CI, where
``.ci/run`` installs them.

The emulated core runs in instruction-counted time (``-icount``): its timers, and so its 20 kHz sample
clock, advance with the instructions it executes, not with the host's wall clock, so a host starved of
CPU (the full suite on both cores) slows the core down instead of making it lose samples; the stream
lasts one second of the core's time, counted in the frames it reports.  A reply is awaited 1 s where
the host is not starved; on a starved host the budget grows with the CPU share it measures."""

from __future__ import annotations

import re
import select
import subprocess
import time
from collections.abc import Iterator

import pytest

from drivers.daq import DaqBridge, DaqCommandError, SampleBlock, SampleGap, SerialLink
from tests.firmware_support import build, check_counter_tiling

NOMINAL_REPLY_S = 1.0  # the bridge's reply budget on a host that is not starved


def reply_budget_s(probe_s: float = 0.2) -> float:
    """The reply budget: 1 s when this process gets (nearly) a whole core for ``probe_s``, else
    scaled by the share it got (a starved host runs the emulated core slower), at most 15 s."""
    wall0, cpu0 = time.perf_counter(), time.process_time()
    while time.perf_counter() - wall0 < probe_s:
        pass
    share = (time.process_time() - cpu0) / (time.perf_counter() - wall0)
    return NOMINAL_REPLY_S if share >= 0.9 else min(15.0, 3.0 * NOMINAL_REPLY_S / max(share, 0.2))


@pytest.fixture
def qemu_bridge() -> Iterator[str]:
    """QEMU running build/mps2/bridge-mps2.elf in instruction-counted time (a 62.5 MHz core: 16 ns per
    instruction); the pty of its UART0 (QEMU is bounded to 120 s)."""
    elf = build("mps2", "arm-none-eabi-gcc", "qemu-system-arm") / "mps2" / "bridge-mps2.elf"
    proc = subprocess.Popen(["timeout", "120", "qemu-system-arm", "-M", "mps2-an385", "-display", "none",
                             "-monitor", "none", "-serial", "pty",
                             "-icount", "shift=4,align=off,sleep=on", "-kernel", str(elf)],
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
    budget = reply_budget_s()
    daq = DaqBridge(reply_timeout_s=budget, stall_timeout_s=max(1.0, budget))
    daq.connect(SerialLink(qemu_bridge, kind="uart"))  # QEMU notices the open pty within a second
    try:
        assert daq.hardware is not None
        assert daq.hardware.identity == "SINECAL,DAQ-BRIDGE-MPS2,QEMU0001,1.0"
        assert (daq.hardware.link, daq.hardware.adc_clock_hz) == ("uart", 25e6)
        with pytest.raises(DaqCommandError, match=r"ERR 2 bad value for frame: expected integer 16\.\.4096, got '8'"):
            daq.command("CONF frame=8")
        assert daq.command("CONF rate=20000")[:37] == "OK CONF rate=20000 rate_exact=20000 f"  # 25 MHz / 1250
        # one second of the core's time: 78 frames of 256 samples at 20 kHz (bounded by the wall clock)
        daq.configure(rate_hz=20_000, frame_samples=256)
        daq.start()
        deadline = time.monotonic() + 60.0
        while int((status := daq.status())["frames"]) < 78 and time.monotonic() < deadline:
            time.sleep(0.2)
        summary = daq.stop()  # the trailing events are queued when it returns
        events = [e for e in daq.events(timeout_s=0.05) if isinstance(e, SampleBlock | SampleGap)]
    finally:
        daq.close()
    assert summary.frames_sent >= 78
    assert check_counter_tiling(events, summary.samples_sent) == []  # no gap: every sample, in order
    assert status["overflows"] == "0" and summary.stats.crc_errors == 0
