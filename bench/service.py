"""Benchmark of the station daemon; prints JSON.

1. Status latency while a run acquires: a real ``station serve --sim`` process (20 kHz DAQ through
   the emulators, recording to HDF5), one run in its record window; 50 concurrent HTTP clients
   (one connection each) poll ``GET /runs/{id}`` for ``--seconds`` seconds, each at most every
   ``--interval`` s (the web page's polling rate; 0 = back to back).  Median and p99 of the
   request latency seen by the clients, and the run's lost samples (must be 0).
2. Batch throughput: ``station.batch.run_batch(paths, workers=N, executor="local")`` on 50
   simulated recordings with 1 and 2 workers (the nightly batch; another module).  If that module is
   not installed, ``batch_speedup_2_workers`` is null with a note.

Usage: python bench/service.py [--clients 50] [--seconds 8] [--interval 0.1] [--recordings 50]
"""

from __future__ import annotations

import argparse
import asyncio
import importlib
import json
import logging
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from bench._daemon import BenchDaemon, bench_config  # noqa: E402
from station.config import default_config_path, load_config  # noqa: E402
from station.simulate import simulate_run  # noqa: E402

log = logging.getLogger("bench.service")


def _pct(xs: list[float], q: float) -> float:
    s = sorted(xs)
    return s[min(len(s) - 1, max(0, round(q * (len(s) - 1))))]


class _Conn:
    """A minimal HTTP/1.1 keep-alive client (GET, Content-Length bodies): cheap enough that 50 of
    them on the same machine measure the daemon rather than the client library."""

    def __init__(self, host: str, port: int) -> None:
        self.host, self.port = host, port
        self.r: asyncio.StreamReader | None = None
        self.w: asyncio.StreamWriter | None = None

    async def get(self, path: str) -> tuple[int, bytes]:
        if self.w is None:
            self.r, self.w = await asyncio.open_connection(self.host, self.port)
        assert self.r is not None
        self.w.write(f"GET {path} HTTP/1.1\r\nHost: {self.host}:{self.port}\r\n\r\n".encode())
        await self.w.drain()
        head = await self.r.readuntil(b"\r\n\r\n")
        lines = head.decode("latin-1").split("\r\n")
        status = int(lines[0].split()[1])
        length = next(int(h.split(":", 1)[1]) for h in lines[1:] if h.lower().startswith("content-length:"))
        return status, await self.r.readexactly(length)

    def close(self) -> None:
        if self.w is not None:
            self.w.close()


async def _poll(port: int, run_id: str, clients: int, seconds: float, interval: float) -> tuple[list[float], int]:
    """Each client connects and makes one request first (not timed), then all poll together."""
    lat: list[float] = []
    errors = 0
    conns = [_Conn("127.0.0.1", port) for _ in range(clients)]
    path = f"/runs/{run_id}"
    await asyncio.gather(*(c.get(path) for c in conns))
    stop = time.monotonic() + seconds

    async def client(c: _Conn, k: int) -> None:
        nonlocal errors
        await asyncio.sleep(interval * k / clients)  # spread the clients over one interval
        while time.monotonic() < stop:
            t0 = time.perf_counter()
            try:
                code, body = await c.get(path)
                ok = code == 200 and json.loads(body)["state"] == "running"
            except (OSError, asyncio.IncompleteReadError, ValueError):
                ok = False
            dt = time.perf_counter() - t0
            if ok:
                lat.append(dt)
            else:
                errors += 1
            if interval > 0:
                await asyncio.sleep(max(0.0, interval - dt))
    try:
        await asyncio.gather(*(client(c, k) for k, c in enumerate(conns)))
    finally:
        for c in conns:
            c.close()
    return lat, errors


def status_latency(clients: int, seconds: float, interval: float) -> dict[str, Any]:
    tmp = Path(tempfile.mkdtemp(prefix="bench-service-"))
    try:
        with BenchDaemon(tmp, bench_config(tmp / "recordings")) as d:
            return _status_latency(d.client, d.port, clients, seconds, interval)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _status_latency(c: httpx.Client, port: int, clients: int, seconds: float, interval: float) -> dict[str, Any]:
    record_s = seconds + 4.0
    r = c.post("/runs", json={"transducer_id": "TX5K-0001", "top_mass_kg": 25.717,
                              "steps": [{"crank_frequency_hz": 20.0, "crank_radius_m": 0.001,
                                         "record_s": record_s}]})
    r.raise_for_status()
    run_id = r.json()["id"]
    while (st := c.get(f"/runs/{run_id}").json())["step_state"] != "recording":
        if st["state"] not in ("queued", "running"):
            raise RuntimeError(f"run ended early: {st}")
        time.sleep(0.05)
    lat, errors = asyncio.run(_poll(port, run_id, clients, seconds, interval))
    while (st := c.get(f"/runs/{run_id}").json())["state"] in ("queued", "running", "identifying"):
        time.sleep(0.2)
    ms = [x * 1000 for x in lat]
    return {"status_p50_ms": round(statistics.median(ms), 2), "status_p99_ms": round(_pct(ms, 0.99), 2),
            "status_max_ms": round(max(ms), 2), "status_requests": len(ms), "status_errors": errors,
            "status_rate_hz": round(len(ms) / seconds, 1), "clients": clients, "client_interval_s": interval,
            "lost_samples": st["lost_samples"], "run_state": st["state"], "run_samples": st["samples"]}


def batch_speedup(n: int, repeat: int = 2) -> dict[str, Any]:
    """run_batch on ``n`` simulated recordings of the shipped plan (5 steps of 2 s at 20 kHz), after a
    warm-up batch (the pool's start-up is paid once per process); best of ``repeat`` alternating runs."""
    try:
        run_batch = importlib.import_module("station.batch").run_batch
    except (ImportError, AttributeError) as exc:
        return {"batch_speedup_2_workers": None,
                "batch_note": f"station.batch.run_batch is not available yet ({exc}); not measured"}
    tmp = Path(tempfile.mkdtemp(prefix="bench-batch-"))
    try:
        cfg = load_config(default_config_path())
        paths = [simulate_run(cfg, tmp, seed=i) for i in range(n)]
        run_batch(paths[:2], workers=2, executor="local")  # warm-up
        times: dict[int, list[float]] = {1: [], 2: []}
        for _ in range(repeat):
            for workers in (1, 2):
                t0 = time.perf_counter()
                items = run_batch(paths, workers=workers, executor="local")
                times[workers].append(time.perf_counter() - t0)
                failed = [i for i in items if i.status != "ok"]
                if failed:
                    raise RuntimeError(f"{len(failed)} batch items failed: {failed[:2]}")
        t1, t2 = min(times[1]), min(times[2])
        return {"batch_recordings": n, "batch_seconds_1_worker": round(t1, 2),
                "batch_seconds_2_workers": round(t2, 2), "batch_speedup_2_workers": round(t1 / t2, 2),
                "batch_runs": {k: [round(x, 2) for x in v] for k, v in times.items()},
                "cpu_count": os.cpu_count(), "load_average_1min": round(os.getloadavg()[0], 2)}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clients", type=int, default=50)
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--interval", type=float, default=0.1, help="s between one client's requests (0: none)")
    ap.add_argument("--recordings", type=int, default=50)
    ap.add_argument("--skip-batch", action="store_true")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    out: dict[str, Any] = status_latency(args.clients, args.seconds, args.interval)
    out["targets"] = {"status_p99_ms": "<= 50", "lost_samples": "0", "batch_speedup_2_workers": ">= 1.8"}
    if args.skip_batch:
        out["batch_speedup_2_workers"] = None
        out["batch_note"] = "skipped (--skip-batch)"
    else:
        out.update(batch_speedup(args.recordings))
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
