"""Wall time of the test suite: the fast subset (``-m "not slow"``) and the full suite (JSON).

    python3 bench/suite.py                 # fast subset, then full suite, once each
    python3 bench/suite.py --fast-only --repeat 3

Each figure is the median wall time of ``--repeat`` runs of ``python3 -m pytest -q`` in a
subprocess (the same command as the README), with the pass/fail counts of the last run, the CPU
time (user + system) of pytest and everything it started, and the 1-minute load average before and
after (the machine is shared: a figure taken under load says so; the CPU time hardly depends on it).
Targets (docs/testing.md): fast subset <= 45 s, full suite <= 240 s on the 2-core station PC.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent


def _counts(tail: str) -> dict[str, int]:
    return {k: int(v) for v, k in re.findall(r"(\d+) (passed|failed|skipped|deselected|errors?|xfailed)", tail)}


def run_suite(marker: str | None, repeat: int, workers: int = 4) -> dict[str, Any]:
    spread = ["-n", str(workers), "--dist", "loadgroup"] if workers else []
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *spread]
    if marker:
        cmd += ["-m", marker]
    times, cpu, last, failed = [], [], "", []
    load_before = os.getloadavg()[0]
    for _ in range(repeat):
        r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
        times.append(time.perf_counter() - t0)
        r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu.append(r1.ru_utime - r0.ru_utime + r1.ru_stime - r0.ru_stime)
        last = res.stdout.strip().splitlines()[-1] if res.stdout.strip() else res.stderr[-500:]
        failed += [line.split(" - ")[0].split(" ", 1)[1] for line in res.stdout.splitlines()
                   if line.startswith(("FAILED ", "ERROR "))]
    return {"command": " ".join(["pytest", "-q", *(["-n", str(workers), "--dist", "loadgroup"] if workers else []),
                                 *(["-m", marker] if marker else [])]),
            "wall_s_median": round(statistics.median(times), 1), "wall_s_runs": [round(t, 1) for t in times],
            "cpu_s_median": round(statistics.median(cpu), 1),
            "counts": _counts(last), "summary": last, "failed_tests": failed,
            "load_avg_1min_before": round(load_before, 2), "load_avg_1min_after": round(os.getloadavg()[0], 2)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=1, help="runs per figure (median)")
    ap.add_argument("--fast-only", action="store_true", help="only the fast subset")
    ap.add_argument("--workers", type=int, default=4, help="pytest-xdist workers, as the README (0: one)")
    args = ap.parse_args()
    out: dict[str, Any] = {"cpus": os.cpu_count(), "fast": run_suite("not slow", args.repeat, args.workers)}
    if not args.fast_only:
        out["full"] = run_suite(None, args.repeat, args.workers)
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
