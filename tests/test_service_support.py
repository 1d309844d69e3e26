"""Shared by the daemon tests: a real ``station serve --sim`` process on a free loopback port with a
short configuration (2-step runs, settle 0.2 s, record 0.5 s, 50 Hz/s ramps), and an HTTP client."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx
import yaml

from tests.conftest import make_fast_dict

TOKEN = "test-token-0123456789"
FINAL = ("completed", "aborted", "failed", "interrupted")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def daemon_config(data_dir: Path, **service: Any) -> dict[str, Any]:
    d = make_fast_dict()
    d["rig"]["acceleration_hz_per_s"] = 50.0
    d["plan"]["steps"] = [{"crank_frequency_hz": 10.0, "crank_radius_m": 0.001},
                          {"crank_frequency_hz": 20.0, "crank_radius_m": 0.001}]
    d["station"]["recordings_dir"] = str(data_dir)
    if service:
        d["service"] = service
    return d


def run_body(freqs: tuple[float, ...] = (10.0, 20.0), radius: float = 0.001, **step: Any) -> dict[str, Any]:
    return {"transducer_id": "TX5K-0001", "top_mass_kg": 25.717,
            "steps": [{"crank_frequency_hz": f, "crank_radius_m": radius, **step} for f in freqs]}


class Daemon:
    """``station serve --sim`` in a subprocess; ``client`` talks to it (with the token)."""

    def __init__(self, tmp: Path, *, workers: int = 1, data_dir: Path | None = None, name: str = "daemon",
                 **service: Any) -> None:
        self.tmp = tmp
        self.data_dir = data_dir or tmp / "recordings"
        self.cfg_path = tmp / f"{name}.yaml"
        self.cfg_path.write_text(yaml.safe_dump(daemon_config(self.data_dir, **service)))
        self.log_path = tmp / f"{name}.log"
        self.workers = workers
        self.port = 0
        self.proc: subprocess.Popen[bytes] | None = None
        self.client: httpx.Client | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def start(self, timeout_s: float = 40.0) -> Daemon:
        self.port = free_port()
        env = {**os.environ, "STATION_TOKEN": TOKEN, "PYTHONUNBUFFERED": "1"}
        log = self.log_path.open("ab")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "station.cli", "serve", "--sim", "--config", str(self.cfg_path),
             "--port", str(self.port), "--workers", str(self.workers)],
            stdout=log, stderr=subprocess.STDOUT, env=env, cwd=self.tmp)
        log.close()
        self.client = httpx.Client(base_url=self.url, headers={"Authorization": f"Bearer {TOKEN}"}, timeout=30.0)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"daemon exited with {self.proc.returncode}:\n{self.log()}")
            try:
                if self.client.get("/health").status_code == 200:
                    return self
            except httpx.TransportError:
                pass
            time.sleep(0.1)
        raise RuntimeError(f"daemon not ready in {timeout_s} s:\n{self.log()}")

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")[-6000:] if self.log_path.exists() else ""

    def stop(self, sig: int = signal.SIGTERM, timeout_s: float = 40.0) -> int:
        assert self.proc is not None
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
                raise
        if self.client is not None:
            self.client.close()
        return int(self.proc.returncode)

    def kill(self) -> None:
        self.stop(signal.SIGKILL)

    def __enter__(self) -> Daemon:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.stop()

    # ---- helpers
    def c(self) -> httpx.Client:
        assert self.client is not None
        return self.client

    def start_run(self, **kw: Any) -> str:
        r = self.c().post("/runs", json=run_body(**kw))
        assert r.status_code == 202, r.text
        return str(r.json()["id"])

    def wait_state(self, run_id: str, states: tuple[str, ...] = FINAL, timeout_s: float = 60.0,
                   step_state: str | None = None) -> dict[str, Any]:
        deadline = time.monotonic() + timeout_s
        st: dict[str, Any] = {}
        while time.monotonic() < deadline:
            st = self.c().get(f"/runs/{run_id}").json()
            if st["state"] in states and (step_state is None or st["step_state"] == step_state):
                return st
            time.sleep(0.1)
        raise AssertionError(f"run {run_id} not in {states} after {timeout_s} s: {st}\n{self.log()}")
