"""Throughput and CPU cost of the DAQ serial path: emulator -> pty -> driver -> decoded numpy blocks.

The DAQ-bridge emulator runs in a subprocess (its own core, rig physics at a steady 20 Hz crank) with
a 64 KiB device FIFO, so a driver that falls behind makes the FIFO overflow and frames get lost.
The driver (reader thread + a consumer that drains the decoded blocks) runs here.

Prints JSON:
  max_lossless_rate_factor  highest multiple of the 20 kHz two-channel rate for which every repeat
                            delivered every sample (no gap, no CRC error, emulator kept real time);
  cpu_share_at_1x           median share of one core used by the driver process at 20 kHz;
  plus the per-rate details.  Frames carry about 12.8 ms of data (256 samples at 20 kHz, more at
  higher rates, at most 4096).  The ladder stops at 50x, the emulator's 1 MHz rate limit.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

BASE_RATE_HZ = 20_000.0
FACTORS = (1, 2, 5, 10, 15, 20, 25, 30, 40, 50)


def run_emulator() -> int:
    """Subprocess mode: DAQ emulator on a pty; prints the pty path; runs until stdin closes."""
    from drivers.rig.presets import paper_5kN_physics
    from drivers.sim.daq_emulator import DaqEmulator
    from drivers.sim.daq_source import RigSource
    from drivers.sim.pty import open_pty

    pty = open_pty()
    src = RigSource(paper_5kN_physics(), seed=1, crank_radius_m=0.01)
    emu = DaqEmulator(pty.master, src, lambda: 20.0, fifo_bytes=64 * 1024, on_close=pty.forget_master).start()
    print(pty.path, flush=True)
    sys.stdin.read()
    emu.close()
    pty.close()
    return 0


def stream_once(port: str, factor: float, seconds: float) -> dict[str, float]:
    """Stream ``seconds`` at ``factor`` x 20 kHz; returns counts and the driver's CPU share."""
    from drivers.daq import DaqBridge, SampleBlock, SampleGap, SerialLink

    rate = BASE_RATE_HZ * factor
    frame = int(min(4096, 256 * max(1.0, factor)))  # about 12.8 ms of data per frame
    daq = DaqBridge(reply_timeout_s=3.0)
    daq.connect(SerialLink(port))
    daq.configure(rate_hz=rate, frame_samples=frame)
    got = gaps = 0
    c0, w0 = time.process_time(), time.monotonic()
    daq.start()
    while time.monotonic() - w0 < seconds:
        ev = daq.get_event(0.1)
        if isinstance(ev, SampleBlock):
            got += ev.count
        elif isinstance(ev, SampleGap):
            gaps += 1
    summary = daq.stop()
    for ev in daq.events(0.3):
        if isinstance(ev, SampleBlock):
            got += ev.count
        elif isinstance(ev, SampleGap):
            gaps += 1
    cpu, wall = time.process_time() - c0, time.monotonic() - w0
    overflows = int(daq.status().get("overflows", "-1"))
    daq.close()
    return {"sent": summary.samples_sent, "received": got, "gaps": gaps, "overflows": overflows,
            "crc_errors": summary.stats.crc_errors, "expected": rate * seconds, "cpu_share": cpu / wall}


def lossless(r: dict[str, float]) -> bool:
    return (r["gaps"] == 0 and r["overflows"] == 0 and r["crc_errors"] == 0 and r["received"] == r["sent"]
            and r["sent"] >= 0.9 * r["expected"])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--emulator", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--seconds", type=float, default=2.0, help="stream length per run")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    if args.emulator:
        return run_emulator()
    proc = subprocess.Popen([sys.executable, __file__, "--emulator"], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    assert proc.stdout is not None and proc.stdin is not None
    port = proc.stdout.readline().strip()
    try:
        cpu_runs = [stream_once(port, 1, 3.0)["cpu_share"] for _ in range(max(3, args.repeats))]
        details: dict[str, dict[str, object]] = {}
        best = 0.0
        for factor in FACTORS:
            runs = [stream_once(port, factor, args.seconds) for _ in range(args.repeats)]
            ok = all(lossless(r) for r in runs)
            details[str(factor)] = {"lossless": ok,
                                    "cpu_share_median": round(statistics.median(r["cpu_share"] for r in runs), 4),
                                    "samples_lost_max": max(int(r["sent"] - r["received"]) for r in runs)}
            if not ok:
                break
            best = factor
    finally:
        proc.stdin.close()
        proc.wait(timeout=10)
    print(json.dumps({
        "max_lossless_rate_factor": best,
        "cpu_share_at_1x": round(statistics.median(cpu_runs), 4),
        "factor_ceiling": FACTORS[-1],  # the emulator's 1 MHz limit: a result equal to it means ">="
        "base_rate_hz": BASE_RATE_HZ,
        "channels": 2,
        "cores": os.cpu_count(),
        "per_factor": details,
    }, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
