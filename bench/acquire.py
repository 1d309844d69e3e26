"""The whole acquisition path: DAQ emulator -> pty -> driver -> acquisition loop -> HDF5 on disk.

The DAQ-bridge emulator runs in a subprocess (``bench/daq_stream.py --emulator``: rig physics at a
steady 20 Hz crank, 64 KiB device FIFO, so a station that falls behind loses frames).  This process
runs the station side: the DAQ driver's reader thread, the acquisition thread (ring buffer) and the
disk thread (crash-safe HDF5 writer, flushed twice a second).

Prints JSON:
  realtime_factor   highest multiple of the 20 kHz two-channel rate at which every repeat stored
                    every sample on disk (no gap, no CRC error; emulator kept real time);
  cpu_share_at_1x   median share of one core used by the station side at 20 kHz;
  lost_samples      samples lost in the runs counted for realtime_factor (0 by definition there);
  peak_rss_mb_1min, peak_rss_mb_10min
                    peak resident memory of a fresh process recording 1 and 10 minutes of 20 kHz
                    data (streamed at ``--memory-factor`` x real time to keep the bench short).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

BASE_RATE_HZ = 20_000.0
FACTORS = (1, 2, 5, 10, 15, 20, 30, 40, 50)
HERE = Path(__file__).resolve().parent


def record_once(port: str, factor: float, seconds: float, out_dir: str) -> dict[str, float]:
    """Record ``seconds`` of wall time at factor x 20 kHz through the station's acquisition path."""
    import h5py

    from drivers.daq import DaqBridge, SerialLink
    from station.recording import ChannelSpec, RecordingWriter, RunMetadata, new_run_id
    from station.run.acquisition import Acquisition

    rate = BASE_RATE_HZ * factor
    frame = int(min(4096, 256 * max(1.0, factor)))
    daq = DaqBridge(reply_timeout_s=3.0)
    daq.connect(SerialLink(port))
    daq.configure(rate_hz=rate, frame_samples=frame, check_link_budget=False)  # an unpaced pty
    meta = RunMetadata(run_id=new_run_id("BENCH"), transducer_id="BENCH", source="calibrate",
                       sample_rate_hz=rate, load_mass_kg=26.2, end_mass_kg=0.12, sensitivity_V_per_N=2e-3,
                       capacity_N=5000.0, config_yaml="bench: true\n")
    lsb = 20.0 / 2**16
    writer = RecordingWriter(out_dir, meta, (ChannelSpec("displacement", "i2", "count", "m", lsb / 500),
                                             ChannelSpec("force", "i2", "count", "V", lsb)), min_free_bytes=0)
    acq = Acquisition(daq.get_event, writer, sample_rate_hz=rate,
                      rejected_frames=lambda: daq.decoder.stats.crc_errors + daq.decoder.stats.framing_errors)
    c0, w0 = time.process_time(), time.monotonic()
    daq.start()
    acq.start()
    while time.monotonic() - w0 < seconds and acq.error is None:
        time.sleep(0.05)
    summary = daq.stop()
    time.sleep(0.3)
    acq.stop()
    cpu, wall = time.process_time() - c0, time.monotonic() - w0
    overflows = int(daq.status().get("overflows", "-1"))
    daq.close()
    path = writer.finish("completed")
    with h5py.File(path, "r") as f:  # count without loading: the bench measures the station, not itself
        stored = min(f["raw/displacement"].shape[0], f["raw/force"].shape[0])
    path.unlink()
    lost = sum(n for _, n in acq.lost)
    return {"sent": summary.samples_sent, "stored": stored, "lost": lost, "overflows": overflows,
            "crc_errors": summary.stats.crc_errors, "expected": rate * seconds, "cpu_share": cpu / wall,
            "error": str(acq.error or "")}


def lossless(r: dict[str, float]) -> bool:
    return (r["lost"] == 0 and r["overflows"] == 0 and r["crc_errors"] == 0 and not r["error"]
            and r["stored"] >= r["sent"] >= 0.9 * r["expected"])


def _emulator() -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, str(HERE / "daq_stream.py"), "--emulator"], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})


def _vm_hwm_mb() -> float:
    """Peak resident memory of this process in MB: VmHWM, which starts afresh at exec (ru_maxrss does
    not: Linux carries it over from the parent that forked us, which would report the bench's own
    peak instead of the recording process's)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024.0
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def memory_run(minutes: float, factor: float) -> int:
    """Subprocess mode: record ``minutes`` of 20 kHz data (at factor x real time); print peak RSS."""
    proc = _emulator()
    assert proc.stdout is not None and proc.stdin is not None
    port = proc.stdout.readline().strip()
    try:
        with tempfile.TemporaryDirectory() as d:
            r = record_once(port, factor, minutes * 60.0 / factor, d)
    finally:
        proc.stdin.close()
        proc.wait(timeout=10)
    peak_mb = _vm_hwm_mb()
    print(json.dumps({"peak_rss_mb": round(peak_mb, 1), "stored": r["stored"], "lost": r["lost"]}))
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=3.0, help="wall time per run")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--memory-factor", type=float, default=10.0)
    ap.add_argument("--memory-run", type=float, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.memory_run is not None:
        return memory_run(args.memory_run, args.memory_factor)
    proc = _emulator()
    assert proc.stdout is not None and proc.stdin is not None
    port = proc.stdout.readline().strip()
    details: dict[str, object] = {}
    best, lost_at_best = 0.0, 0
    try:
        with tempfile.TemporaryDirectory() as d:
            cpu = [record_once(port, 1, args.seconds, d)["cpu_share"] for _ in range(args.repeats)]
            for factor in FACTORS:
                runs = [record_once(port, factor, args.seconds, d) for _ in range(args.repeats)]
                ok = all(lossless(r) for r in runs)
                details[str(factor)] = {"lossless": ok, "lost_max": max(int(r["lost"]) for r in runs),
                                        "cpu_share_median": round(statistics.median(r["cpu_share"] for r in runs), 3)}
                if not ok:
                    break
                best, lost_at_best = factor, sum(int(r["lost"]) for r in runs)
    finally:
        proc.stdin.close()
        proc.wait(timeout=10)
    mem = {}
    for minutes in (1, 10):
        out = subprocess.run([sys.executable, __file__, "--memory-run", str(minutes), "--memory-factor",
                              str(args.memory_factor)], capture_output=True, text=True, check=True)
        mem[minutes] = json.loads(out.stdout.strip().splitlines()[-1])
    print(json.dumps({
        "realtime_factor": best,
        "cpu_share_at_1x": round(statistics.median(cpu), 4),
        "lost_samples": lost_at_best,
        "peak_rss_mb_1min": mem[1]["peak_rss_mb"],
        "peak_rss_mb_10min": mem[10]["peak_rss_mb"],
        "memory_runs": mem,
        "factor_ceiling": FACTORS[-1],
        "per_factor": details,
    }, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
