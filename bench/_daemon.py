"""A simulated station's daemon for the bench scripts and ``docs/screenshots.py``: the shipped
configuration (shortened for a bench, or as shipped), ``station serve --sim`` in a subprocess on a
free loopback port with its log in a file, waited for until ``/health`` answers, stopped with SIGTERM
(killed if it does not end).

    with BenchDaemon(tmp, bench_config(tmp / "recordings", record_s=0.5)) as d:
        d.client.get("/runs")          # the administrator's client (STATION_TOKEN)

or, step by step, ``d.start()``, ``d.wait_ready()``, ``d.stop()``.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import httpx
import yaml

ROOT = Path(__file__).resolve().parent.parent
TOKEN = "bench-token-0123456789"  # the administrator's script token of a bench's daemon
SHIPPED = ROOT / "config" / "sim-5kN.yaml"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def bench_config(data_dir: Path, *, short: bool = True, settle_s: float = 0.2, record_s: float = 1.0,
                 acceleration_hz_per_s: float = 50.0, pre_roll_s: float | None = 0.2) -> dict[str, Any]:
    """The shipped simulated station's configuration (config/sim-5kN.yaml) recording into
    ``data_dir``; ``short``: its plan settled ``settle_s`` and recorded ``record_s`` per step (s), the
    crank ramped at ``acceleration_hz_per_s`` (Hz/s), the simulated rig's pre-roll ``pre_roll_s``
    (s; None: as shipped), so that a run takes seconds."""
    d: dict[str, Any] = yaml.safe_load(SHIPPED.read_text(encoding="utf-8"))
    d["station"]["recordings_dir"] = str(data_dir)
    if short:
        d["rig"]["acceleration_hz_per_s"] = acceleration_hz_per_s
        d["plan"].update({"settle_s": settle_s, "record_s": record_s})
        if pre_roll_s is not None:
            d["simulation"]["pre_roll_s"] = pre_roll_s
    return d


class BenchDaemon:
    """``station serve --sim`` with ``config`` (written to ``tmp/station.yaml``), run in ``tmp``.
    ``args``: more arguments of ``station serve``; ``env``: more environment; ``token``: the
    administrator's token (``STATION_TOKEN``; None: none, and ``client`` sends none)."""

    def __init__(self, tmp: Path, config: dict[str, Any], *, args: Sequence[str] = (),
                 env: dict[str, str] | None = None, token: str | None = TOKEN, start_timeout_s: float = 240.0,
                 stop_timeout_s: float = 30.0) -> None:
        self.tmp = tmp
        self.config_path = tmp / "station.yaml"
        self.log_path = tmp / "daemon.log"
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.args = list(args)
        path = os.pathsep.join(filter(None, (str(ROOT), os.environ.get("PYTHONPATH"))))
        self.env = {**os.environ, "PYTHONPATH": path, "PYTHONUNBUFFERED": "1", **(env or {})}
        if token is not None:
            self.env["STATION_TOKEN"] = token
        self.start_timeout_s = start_timeout_s
        self.stop_timeout_s = stop_timeout_s
        self.client = httpx.Client(base_url=self.url, timeout=60,
                                   headers={"Authorization": f"Bearer {token}"} if token is not None else {})
        self.proc: subprocess.Popen[bytes] | None = None
        tmp.mkdir(parents=True, exist_ok=True)
        self.config_path.write_text(yaml.safe_dump(config), encoding="utf-8")

    def start(self) -> BenchDaemon:
        with self.log_path.open("wb") as log:  # the child keeps its own descriptor
            self.proc = subprocess.Popen([sys.executable, "-m", "station.cli", "serve", "--sim", "--config",
                                          str(self.config_path), "--port", str(self.port), *self.args],
                                         stdout=log, stderr=subprocess.STDOUT, env=self.env, cwd=self.tmp)
        return self

    def log(self) -> str:
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""

    def wait_ready(self) -> httpx.Client:
        """Until ``/health`` answers 200 (a loaded machine starts it slowly); RuntimeError with the
        log's end if it exits or takes longer than ``start_timeout_s``."""
        assert self.proc is not None, "start() first"
        deadline = time.monotonic() + self.start_timeout_s
        while True:
            with contextlib.suppress(httpx.TransportError):
                if self.client.get("/health").status_code == 200:
                    return self.client
            if time.monotonic() > deadline or self.proc.poll() is not None:
                raise RuntimeError(f"the daemon did not start (exit code {self.proc.poll()}): {self.log()[-3000:]}")
            time.sleep(0.1)

    def stop(self) -> None:
        self.client.close()
        if self.proc is None or self.proc.poll() is not None:
            return
        self.proc.send_signal(signal.SIGTERM)
        try:
            self.proc.wait(self.stop_timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()

    def __enter__(self) -> BenchDaemon:
        self.start()
        try:
            self.wait_ready()
        except BaseException:
            self.stop()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
