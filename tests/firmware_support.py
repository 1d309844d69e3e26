"""Shared by the bridge firmware's tests: building ``firmware/`` with make (or skipping: no toolchain),
streaming the counter source through the driver and checking that blocks and gaps tile the stream."""

from __future__ import annotations

import fcntl
import os
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from drivers.daq import DaqBridge, SampleBlock, SampleGap, SerialLink, StreamSummary

FIRMWARE = Path(__file__).resolve().parent.parent / "firmware"


def build(target: str, *tools: str) -> Path:
    """``make target`` in firmware/ (warnings are errors; incremental: nothing to do after ``.ci/run``
    built it); the build folder.  Skips when a tool is missing, except under CI (``CI`` set), where
    ``.ci/run`` installs them and a missing one is a failure."""
    missing = [tool for tool in (*tools, "make") if shutil.which(tool) is None]
    if missing:
        reason = f"no {' or '.join(missing)} on PATH: the bridge firmware's {target} build cannot be tested"
        if os.environ.get("CI"):
            pytest.fail(f"{reason} (under CI it is required: .ci/run installs it)")
        pytest.skip(reason)
    # one make at a time: test workers building into the same folder at once link half-written objects
    with open(FIRMWARE / ".build.lock", "a+b") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        done = subprocess.run(["make", "-s", "-j2", "-C", str(FIRMWARE), f"CC={os.environ.get('CC', 'cc')}",
                               target], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, f"firmware build ({target}) failed:\n{done.stdout}\n{done.stderr}"
    return FIRMWARE / "build"


def stream(path: str, kind: str, seconds: float) -> tuple[list, dict[str, str], StreamSummary]:
    """Connect the driver to the bridge on ``path``, stream 20 kHz in frames of 256 for ``seconds``,
    stop: the sample events (blocks and gaps), ``STAT?`` once stopped (its counts are those of the
    whole stream: a starved host may still be dropping frames just before STOP) and the STOP summary."""
    daq = DaqBridge(stall_timeout_s=1.0)
    daq.connect(SerialLink(path, kind=kind))
    try:
        daq.configure(rate_hz=20_000, frame_samples=256)
        daq.start()
        time.sleep(seconds)
        summary = daq.stop()  # the trailing events are queued when it returns
        events = [e for e in daq.events(timeout_s=0.05) if isinstance(e, SampleBlock | SampleGap)]
        status = daq.status()
        assert status["state"] == "idle", status
    finally:
        daq.close()
    return events, status, summary


def check_counter_tiling(events: list, samples_sent: int) -> list[tuple[int, int]]:
    """Blocks and gaps tile 0..samples_sent-1; every block holds the counter source of its own indices
    (disp = index mod 2^16 as int16, force = -1 - disp); returns the gaps (first, count)."""
    index, gaps = 0, []
    for ev in events:
        assert ev.first_index == index
        if isinstance(ev, SampleGap):
            gaps.append((ev.first_index, ev.count))
            index += ev.count
            continue
        want = (np.arange(index, index + ev.count) % 65536).astype(np.uint16).view(np.int16)
        assert np.array_equal(ev.displacement, want) and np.array_equal(ev.force, -1 - want.astype(np.int32))
        index += ev.count
    assert index == samples_sent
    return gaps
