"""The nightly check run: a short calibration of the register's check transducer, asked of the station
daemon before the batch re-identifies (docs/batch.md, "The check run").

The batch does not drive the rig itself: the daemon holds it (one station per recordings folder), so
the check run is an ordinary run started through the daemon's API (``POST /runs``), with the limits,
the stop, the recording, the identification, the audit trail and the history a technician's run has.
The batch waits until the run is identified (``completed``) or ends otherwise, and whatever happens
it comes back with a :class:`CheckRun` finding: "completed", or "not run" / "failed" / "unfinished"
with the reason (the daemon unreachable, the rig busy or unavailable, the run refused or failed).
"""

from __future__ import annotations

import asyncio
import time
from dataclasses import asdict, dataclass
from typing import Any

import httpx

from station.config import StationConfig

FINAL = ("completed", "failed", "aborted", "interrupted")


@dataclass(frozen=True)
class CheckRun:
    """What became of a night's check run: ``status`` "completed" (identified: it is in the
    transducer's history), "not run" (refused or not reachable: nothing moved), "failed" (the run
    ended failed, aborted or interrupted), "unfinished" (not identified within the timeout); ``at``
    UNIX s when asked; ``detail`` the reason for people."""

    transducer_id: str
    status: str
    detail: str
    at: float
    run_id: str | None = None
    state: str | None = None

    @property
    def ok(self) -> bool:
        return self.status == "completed"

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def check_body(cfg: StationConfig, transducer_id: str) -> dict[str, Any]:
    """The check run's request (``POST /runs`` body): ``batch.check_steps``, or three of the plan's
    steps (first, middle, last); ``batch.check_top_mass_kg`` or ``rig.top_mass_kg``."""
    steps = list(cfg.batch.check_steps)
    if not steps:
        plan = cfg.plan.steps
        steps = [plan[i] for i in sorted({0, (len(plan) - 1) // 2, len(plan) - 1})]
    return {"transducer_id": transducer_id,
            "top_mass_kg": cfg.batch.check_top_mass_kg or cfg.rig.top_mass_kg,
            "steps": [s.model_dump(exclude_none=True) for s in steps]}


def station_url(cfg: StationConfig) -> str:
    """The daemon's address: ``batch.station_url``, else http://service.host:service.port."""
    if cfg.batch.station_url:
        return cfg.batch.station_url.rstrip("/")
    host = cfg.service.host
    host = "127.0.0.1" if host in ("0.0.0.0", "") else "[::1]" if host == "::" else host
    return f"http://{host}:{cfg.service.port}"


def _problem(r: httpx.Response) -> str:
    """A refusal's reason from its problem details (or its text)."""
    try:
        doc = r.json()
    except ValueError:
        return f"HTTP {r.status_code}: {r.text[:200]}"
    if isinstance(doc, dict):
        return f"HTTP {r.status_code}: {doc.get('detail') or doc.get('title') or doc}"
    return f"HTTP {r.status_code}: {doc}"


async def run_check(client: httpx.AsyncClient, body: dict[str, Any], *, timeout_s: float = 1800.0,
                    poll_s: float = 1.0) -> CheckRun:
    """Start the check run ``body`` on the daemon ``client`` talks to (base URL and token set) and
    wait until it is identified or ends (asked after 0.05 s, then at doubling intervals up to
    ``poll_s``); never raises for what the daemon or the network does."""
    tx, at = str(body.get("transducer_id")), time.time()
    try:
        r = await client.post("/runs", json=body)
    except httpx.HTTPError as exc:
        return CheckRun(tx, "not run", f"no station daemon reached at {client.base_url}: "
                        f"{type(exc).__name__}: {exc}", at)
    if r.status_code != 202:
        why = {409: "the rig is busy or stopped", 503: "the rig is unavailable", 401: "the API token was refused",
               403: "the API token may not start runs", 422: "the check plan was refused"}.get(r.status_code,
                                                                                              "refused")
        return CheckRun(tx, "not run", f"{why}: {_problem(r)}", at)
    run_id = str(r.json()["id"])
    deadline = time.monotonic() + timeout_s
    state, wait = "queued", min(0.05, poll_s)
    while True:
        try:
            st = await client.get(f"/runs/{run_id}")
            if st.status_code == 200:
                doc = st.json()
                state = doc["state"]
                if state == "completed":
                    return CheckRun(tx, "completed", f"run {run_id} identified", at, run_id, state)
                if state in FINAL:
                    return CheckRun(tx, "failed", f"run {run_id} ended {state}: {doc.get('reason') or ''}".rstrip(": "),
                                    at, run_id, state)
        except httpx.HTTPError:
            pass  # the daemon may be restarting: asked again until the deadline
        if time.monotonic() >= deadline:
            return CheckRun(tx, "unfinished", f"run {run_id} was still {state} after {timeout_s:g} s (the daemon "
                            "goes on with it; tomorrow's charts will have it)", at, run_id, state)
        await asyncio.sleep(wait)
        wait = min(2 * wait, poll_s)  # asked often at first (a short check run), then every poll_s


async def check_runs(cfg: StationConfig, transducers: list[str], token: str | None, *,
                     transport: httpx.AsyncBaseTransport | None = None, poll_s: float = 1.0) -> list[CheckRun]:
    """One check run per check transducer of the register, one after the other, on the daemon of
    ``cfg`` (``transport``: another way to reach it, e.g. in process)."""
    url = station_url(cfg)
    if not token:
        return [CheckRun(tx, "not run", "no API token for the station daemon: set STATION_TOKEN or service.token",
                         time.time()) for tx in transducers]
    out = []
    async with httpx.AsyncClient(base_url=url, transport=transport, timeout=30.0,
                                 headers={"Authorization": f"Bearer {token}"}) as client:
        for tx in transducers:
            out.append(await run_check(client, check_body(cfg, tx), timeout_s=cfg.batch.check_timeout_s,
                                       poll_s=poll_s))
    return out
