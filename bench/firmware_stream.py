"""The reference bridge firmware's host build (``firmware/``) streaming to the station's driver over a pty.

Builds ``firmware/build/bridge-host`` (``make``), then for each rate of the ladder starts it on a pty
with the counter source (every sample checkable) and a 64 KiB FIFO, connects :class:`DaqBridge`,
streams ``--seconds`` of frames of 256 samples and stops.  A step is lossless when every repeat
delivered every sample (no gap, no CRC or framing error, ``STAT? overflows=0``) and every delivered
sample holds its own index.  A pty ignores the baud rate: this measures the firmware and the
driver on this host, not a link (``bench/daq_stream.py`` paces a UART).

Prints JSON: per step the rate, samples sent and lost, bytes per second received, the firmware's
CPU time per second of stream (``/proc/<pid>/stat``), and ``max_lossless_rate_hz``.
"""

from __future__ import annotations

import argparse
import json
import os
import select
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from drivers.daq import DaqBridge, SampleBlock, SampleGap, SerialLink  # noqa: E402

FRAME = 256


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process (Linux /proc), s."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def one_run(binary: Path, rate_hz: float, seconds: float) -> dict[str, float | int | bool]:
    proc = subprocess.Popen([str(binary), "--pty", "--source", "counter", "--fifo-bytes", "65536"],
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        assert proc.stdout is not None
        ready, _, _ = select.select([proc.stdout], [], [], 5.0)
        path = proc.stdout.readline().split()[1] if ready else ""
        daq = DaqBridge(stall_timeout_s=2.0)
        daq.connect(SerialLink(path, kind="usb-cdc"))
        try:
            daq.configure(rate_hz=rate_hz, frame_samples=FRAME, check_link_budget=False)
            cpu0, t0 = cpu_seconds(proc.pid), time.monotonic()
            daq.start()
            events: list = []
            while time.monotonic() - t0 < seconds:
                if (ev := daq.get_event(0.2)) is not None:
                    events.append(ev)
            status = daq.status()
            summary = daq.stop()
            events += list(daq.events(timeout_s=0.05))
            cpu = cpu_seconds(proc.pid) - cpu0
            wall = time.monotonic() - t0
        finally:
            daq.close()
    finally:
        proc.terminate()
        proc.wait(timeout=5)
    intact = all(np.array_equal(e.displacement, (np.arange(e.first_index, e.first_index + e.count) % 65536)
                                .astype(np.uint16).view(np.int16)) for e in events if isinstance(e, SampleBlock))
    lost = sum(e.count for e in events if isinstance(e, SampleGap))
    stats = summary.stats
    lossless = (intact and lost == 0 and stats.crc_errors == 0 and stats.framing_errors == 0
                and status.get("overflows") == "0")
    return {"samples_sent": summary.samples_sent, "samples_lost": lost, "overflows": int(status["overflows"]),
            "intact": intact, "lossless": lossless, "bytes_per_s": round(stats.bytes / wall),
            "firmware_cpu_s_per_s": round(cpu / wall, 4)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rates", default="20000,50000,100000,200000,400000,1000000",
                        help="sample rates per channel, Hz (comma-separated, ascending)")
    parser.add_argument("--seconds", type=float, default=3.0)
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    build = subprocess.run(["make", "-s", "-C", str(ROOT / "firmware"), "all"], capture_output=True, text=True)
    if build.returncode != 0:
        sys.exit(f"firmware build failed: {build.stderr}")
    binary = ROOT / "firmware" / "build" / "bridge-host"
    steps, best = [], None
    for rate in (float(r) for r in args.rates.split(",")):
        runs = [one_run(binary, rate, args.seconds) for _ in range(args.repeats)]
        ok = all(r["lossless"] for r in runs)
        steps.append({"rate_hz": rate, "lossless": ok, "runs": runs})
        if not ok:
            break
        best = rate
    print(json.dumps({"benchmark": "firmware_stream", "frame_samples": FRAME, "seconds": args.seconds,
                      "repeats": args.repeats, "load_average": os.getloadavg()[0],
                      "max_lossless_rate_hz": best, "steps": steps}, indent=1))


if __name__ == "__main__":
    main()
