"""Benchmark of the nightly batch: throughput of ``run_batch`` with 1 and 2 local workers on 50
simulated recordings of the shipped plan (config/sim-5kN.yaml: 5 steps of 2 s at 20 kHz); prints JSON.

The fork server of the pool is started once per process; the first ``run_batch`` pays for it
(about 1 s: importing numpy, scipy, h5py and the identification).  A warm-up batch on 2 recordings
starts it, so the timings compare the pool sizes, not the start-up; the cold first call is reported
separately.  Wall times are medians of ``--repeat`` runs, alternating the pool sizes, and the speedup
is also given from the best runs (least disturbed by other processes); the 1-minute load average is
reported because other processes on the machine skew a 2-worker measurement most.

Usage: python bench/batch.py [--recordings N] [--repeat R] [--workers 1,2]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time
from pathlib import Path

from station.batch import run_batch
from station.config import default_config_path, load_config
from station.simulate import simulate_run


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recordings", type=int, default=50)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--workers", default="1,2")
    a = ap.parse_args()
    sizes = [int(w) for w in a.workers.split(",")]
    cfg = load_config(default_config_path())
    with tempfile.TemporaryDirectory() as tmp:
        paths = [simulate_run(cfg, Path(tmp), seed=s) for s in range(a.recordings)]
        t0 = time.perf_counter()
        run_batch(paths[:2], workers=max(sizes))
        cold = time.perf_counter() - t0
        walls: dict[int, list[float]] = {w: [] for w in sizes}
        job_s: dict[int, list[float]] = {w: [] for w in sizes}
        job_cpu: dict[int, list[float]] = {w: [] for w in sizes}
        for _ in range(a.repeat):
            for w in sizes:
                t0 = time.perf_counter()
                items = run_batch(paths, workers=w)
                walls[w].append(time.perf_counter() - t0)
                assert all(it.ok for it in items)
                job_s[w].append(statistics.median(it.wall_s for it in items))
                job_cpu[w].append(statistics.median(it.cpu_s for it in items))
    med = {w: statistics.median(v) for w, v in walls.items()}
    base = med[sizes[0]]
    print(json.dumps({
        "recordings": a.recordings, "repeat": a.repeat, "cpu_count": os.cpu_count(),
        "load_average_1min_after": os.getloadavg()[0],
        "cold_start_first_call_s": round(cold, 3),
        "wall_s_median": {str(w): round(v, 3) for w, v in med.items()},
        "wall_s_all": {str(w): [round(x, 3) for x in v] for w, v in walls.items()},
        "recordings_per_s": {str(w): round(a.recordings / v, 1) for w, v in med.items()},
        "job_s_median_in_worker": {str(w): round(statistics.median(v), 4) for w, v in job_s.items()},
        "job_cpu_s_median_in_worker": {str(w): round(statistics.median(v), 4) for w, v in job_cpu.items()},
        "speedup_vs_first": {str(w): round(base / v, 2) for w, v in med.items()},
        "speedup_vs_first_best_of": {str(w): round(min(walls[sizes[0]]) / min(v), 2) for w, v in walls.items()},
    }, indent=2))


if __name__ == "__main__":
    main()
