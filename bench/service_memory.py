"""Daemon memory over many runs; prints JSON.

A real ``station serve --sim`` process; ``--runs`` short runs one after the other (one step at
10 Hz, settle 0.2 s, record ``--record-s``), each followed live over server-sent events (as the page
does) and through its status; after each run has left the rig, the daemon's resident set size
(VmRSS of the daemon process only; identification workers are separate processes).  Printed: the
RSS after each run, the mean of the first and last ten, and the least-squares slope over the runs
after the first ten (warm-up: imports, caches, allocator pools).  Flat means a slope of a few
kB per run at most.

Usage: python bench/service_memory.py [--runs 50] [--record-s 0.3] [--workers 0]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from bench._daemon import BenchDaemon, bench_config  # noqa: E402


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def _slope(ys: list[float]) -> float:
    xs = list(range(len(ys)))
    mx, my = statistics.fmean(xs), statistics.fmean(ys)
    return sum((x - mx) * (y - my) for x, y in zip(xs, ys, strict=True)) / sum((x - mx) ** 2 for x in xs)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=50)
    ap.add_argument("--record-s", type=float, default=0.3)
    ap.add_argument("--workers", type=int, default=0)
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench-memory-"))
    d = bench_config(tmp / "rec", record_s=args.record_s)
    body = {"transducer_id": d["transducer"]["id"], "top_mass_kg": d["rig"]["top_mass_kg"],
            "steps": [{"crank_frequency_hz": 10.0, "crank_radius_m": 0.001}]}
    rss: list[float] = []
    states: dict[str, int] = {}
    with BenchDaemon(tmp, d, args=["--workers", str(args.workers)], stop_timeout_s=60) as daemon:
        c, proc = daemon.client, daemon.proc
        assert proc is not None
        t0 = time.monotonic()
        for _ in range(args.runs):
            r = c.post("/runs", json=body)
            r.raise_for_status()
            rid = r.json()["id"]
            with c.stream("GET", f"/runs/{rid}/events") as ev:  # follow it live until its end event
                for line in ev.iter_lines():
                    if line.startswith("event: end"):
                        break
                    if line.startswith("event:") and c.get(f"/runs/{rid}").json()["state"] not in (
                            "queued", "running"):
                        break
            while (st := c.get(f"/runs/{rid}").json())["state"] in ("queued", "running"):
                time.sleep(0.05)
            states[st["state"]] = states.get(st["state"], 0) + 1
            c.get("/runs", params={"limit": 100})
            rss.append(round(_rss_mb(proc.pid), 2))
        wall = time.monotonic() - t0
    tail = rss[10:] if len(rss) > 12 else rss
    out: dict[str, Any] = {
        "runs": args.runs, "states": states, "wall_s": round(wall, 1),
        "rss_MB_after_each_run": rss,
        "rss_MB_first10_mean": round(statistics.fmean(rss[:10]), 2),
        "rss_MB_last10_mean": round(statistics.fmean(rss[-10:]), 2),
        "slope_kB_per_run_after_10": round(1024 * _slope(tail), 1),
    }
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
