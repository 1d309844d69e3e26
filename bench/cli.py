"""Start-up time of the ``station`` command: ``station --help`` and ``station identify`` on one recording.

Each command runs as a new process, end to end (interpreter start, imports, work, exit), as a user
types it.  Prints JSON: the median wall time over repeats of each, the targets, and side by side the
bare interpreter's start (``python -c pass``) and the machine's load average, since on a shared
machine every figure moves with the load; also the CPU time (user + system) of each, which moves much
less with the load than the wall time.

    PYTHONPATH=$PWD python3 bench/cli.py [--repeats 7]
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


def _station() -> list[str]:
    """The console script installed beside this interpreter (not a version manager's shim on PATH),
    else the same entry point through ``-m``."""
    exe = Path(sys.executable).parent / "station"
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "station.cli"]


def _median_s(cmd: list[str], repeats: int) -> tuple[float, float]:
    """Median wall time and median CPU time (user + system of the child) of ``cmd``, in s."""
    wall, cpu = [], []
    for _ in range(repeats):
        r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        wall.append(time.perf_counter() - t0)
        r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu.append(r1.ru_utime - r0.ru_utime + r1.ru_stime - r0.ru_stime)
    return statistics.median(wall), statistics.median(cpu)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()
    station = _station()
    with tempfile.TemporaryDirectory() as tmp:
        # one recording of the default configuration (5 steps, 20 kHz), made once, not timed
        res = subprocess.run([*station, "simulate", "--out", tmp, "--seed", "3"], check=True,
                             capture_output=True, text=True)
        rec = Path(res.stdout.strip().splitlines()[-1])
        load_before = os.getloadavg()[0]
        help_s, help_cpu = _median_s([*station, "--help"], args.repeats)
        ident_s, ident_cpu = _median_s([*station, "identify", str(rec)], args.repeats)
        start_s, start_cpu = _median_s([sys.executable, "-c", "pass"], args.repeats)
        out = {
            "help_s": round(help_s, 3),
            "identify_s": round(ident_s, 3),
            "python_start_s": round(start_s, 3),
            "help_cpu_s": round(help_cpu, 3),
            "identify_cpu_s": round(ident_cpu, 3),
            "python_start_cpu_s": round(start_cpu, 3),
            "target_help_s": 0.3,
            "target_identify_s": 1.0,
            "repeats": args.repeats,
            "recording_samples_per_channel": None,
            "load_average_1min": [round(load_before, 2), round(os.getloadavg()[0], 2)],
            "command": " ".join(Path(c).name if i == 0 else c for i, c in enumerate(station)),
        }
        import h5py

        with h5py.File(rec, "r") as f:
            out["recording_samples_per_channel"] = int(f["raw/force"].shape[0])
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
