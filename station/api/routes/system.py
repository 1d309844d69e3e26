"""/stop, /health, /station: the emergency stop, the state of the device links, the limits."""

from __future__ import annotations

import asyncio
import concurrent.futures
from collections.abc import Callable, Mapping
from datetime import UTC, datetime
from typing import Annotated, Any

from fastapi import Body, Depends, FastAPI, Request, status

from station.api.deps import ManagerDep, Operator, Reader, RunsDep, SettingsDep, credentials_of, token_lookup
from station.api.problems import Refusal
from station.api.routes import api_router
from station.api.routes.runs import BODY_ERRORS
from station.api.schemas import (
    AcknowledgeIn,
    AcknowledgeOut,
    DriveLimitsOut,
    DriveOut,
    EnvironmentFormOut,
    ErrorOut,
    HealthOut,
    LimitsOut,
    RangeOut,
    StationOut,
    StopOut,
)
from station.config import MAX_STEPS, MAX_TOP_MASS_KG, EnvironmentConfig, StationConfig
from station.lab import users
from station.lab.store import Store
from station.lab.users import AuthError
from station.limits import drive_profile, force_limit_N
from station.rigproc.stopport import cross_site_refusal
from station.service.runs import StopReport
from station.service.settings import ServiceSettings

router = api_router(tags=["station"])


async def not_cross_site(request: Request) -> None:
    """A request another web site's page makes the browser send is refused (:func:`cross_site_refusal`).
    The station's own page (same origin), API clients and curl (neither header) pass."""
    why = cross_site_refusal(request.headers.get("sec-fetch-site"), request.headers.get("origin"),
                             request.headers.get("host", ""))
    if why is not None:
        raise Refusal(status.HTTP_403_FORBIDDEN, "cross-site", why)


SameSite = Depends(not_cross_site)


@router.post("/stop", response_model=StopOut, dependencies=[SameSite],
             responses={403: {"model": ErrorOut, "description": "sent by another web site's page"}},
             summary="Emergency stop (always accepted, except from another web site)")
async def emergency_stop(runs: RunsDep, settings: SettingsDep, request: Request) -> StopOut:
    """Aborts every run on the rig and commands an emergency stop on the motor controller at once.
    Accepted with or without a token or a run: stopping is never unsafe (only a request another web
    site's page makes the browser send is refused).  Nothing on the way waits for the database.
    The answer comes once the drive, read back, reports standstill (at most the time a healthy drive
    needs to stop): `motor_stopped` is what the drive reports, `stop_commanded` whether the
    controller took the command, `drive` its last state.  The stop latches: no run starts until an
    operator acknowledges it (`POST /stop/acknowledge`); a drive still turning latches too (source
    `drive`) and shows in `/health`."""
    arrived: asyncio.Future[StopReport] | None = getattr(request.state, STOP_ON_ARRIVAL, None)
    if arrived is not None:  # handed to the rig as the request head arrived (stop_on_arrival)
        return stop_answer(await asyncio.shield(arrived))
    source = "page" if request.headers.get("x-station-client") == "page" else "api"
    return stop_answer(await runs.emergency_stop(source, who_stopped(request.headers, settings)))


STOP_ON_ARRIVAL = "station_stop"  # the request's state: the stop begun on its head's arrival
LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "::1", "[::1]")  # what the daemon on loopback takes as Host


def stop_on_arrival(app: FastAPI) -> StopOnArrival:
    """For the server's connections (``ConnectionBounds.on_head``): :class:`StopOnArrival`."""
    return StopOnArrival(app)


class StopOnArrival:
    """As soon as the head of a ``POST /stop`` is read, before its connection does any other work
    (middleware, routing, dependencies, the body), the emergency stop is handed to the rig thread
    and carried on as a task of its own; the route answers with that task's report.  The main
    port's accept gate (``commands/gate.py``) hands it over earlier still, from its own thread, when
    a connection's first bytes are such a head (:meth:`early`).  A request the route would refuse
    (another site's page, a Host the daemon does not take) is left to it."""

    def __init__(self, app: FastAPI) -> None:
        self.app = app
        self.settings: ServiceSettings = app.state.settings

    def _manager(self, method: str, path: str, headers: Mapping[str, str]) -> Any:
        """The run manager when this is a stop the route takes, else None."""
        manager = getattr(self.app.state, "manager", None)
        if method != "POST" or path != "/stop" or manager is None:
            return None
        host = headers.get("host", "")
        if self.settings.loopback_only and host.split(":")[0] not in LOOPBACK_HOSTS:
            return None  # as TrustedHostMiddleware: refused by the app
        if cross_site_refusal(headers.get("sec-fetch-site"), headers.get("origin"), host) is not None:
            return None
        return manager

    def early(self, method: str, path: str, headers: dict[str, str],
              loop: asyncio.AbstractEventLoop) -> concurrent.futures.Future[StopReport] | None:
        """From any thread but the rig thread's (the accept gate's): the runs aborted and the stop
        handed to the rig thread now, and the rest of the stop (latch, record, read-back) begun on
        the server's ``loop``, whatever becomes of the connection; its future (None if this is not a
        stop the route takes)."""
        manager = self._manager(method, path, headers)
        if manager is None:
            return None
        runs = manager.runs
        aborted = runs.abort_all()  # first: a procedure reading the drive's fault ends as aborted, not failed
        commanded = runs.link.command_emergency_stop()
        return asyncio.run_coroutine_threadsafe(
            runs.emergency_stop(self._source(headers), who_stopped(headers, self.settings), commanded, aborted), loop)

    def __call__(self, scope: dict[str, Any], given: object = None) -> None:
        """On the server's loop; ``given``: :meth:`early`'s stop for this request, if any."""
        task: asyncio.Future[StopReport]
        if isinstance(given, concurrent.futures.Future):
            task = asyncio.wrap_future(given)
        else:
            headers = {k.decode("latin-1"): v.decode("latin-1") for k, v in scope.get("headers", [])}
            manager = self._manager(str(scope.get("method")), str(scope.get("path")), headers)
            if manager is None:
                return
            runs = manager.runs
            aborted = runs.abort_all()  # first, as in early()
            commanded = runs.link.command_emergency_stop()
            task = asyncio.get_running_loop().create_task(
                runs.emergency_stop(self._source(headers), who_stopped(headers, self.settings), commanded, aborted))
        scope.setdefault("state", {})[STOP_ON_ARRIVAL] = task

    @staticmethod
    def _source(headers: Mapping[str, str]) -> str:
        return "page" if headers.get("x-station-client") == "page" else "api"


def stop_answer(rep: StopReport) -> StopOut:
    """The answer to a stop (the main port's and the stop port's alike)."""
    drive = DriveOut.model_validate(rep.drive.to_dict()) if rep.drive is not None else None
    return StopOut(motor_stopped=rep.motor_stopped, stop_commanded=rep.commanded, drive=drive,
                   aborted_runs=rep.aborted_runs, detail=rep.detail)


def who_stopped(headers: Mapping[str, str], settings: ServiceSettings) -> Callable[[Store], str]:
    """Who asked for the stop (``headers``: the request's, lower-case names), looked up when the
    stop's record is written (after the stop, by the database's writer): a user's name, or
    ``anonymous`` without valid credentials."""
    token, session = credentials_of({k: headers.get(k, "") for k in ("authorization", "cookie")})

    def find(store: Store) -> str:
        try:
            if token is not None:
                who = token_lookup(token, settings)(store)
                return who.name if who is not None else "anonymous (wrong token)"
            if session is not None:
                return users.session_user(store, session).name
        except AuthError:
            return "anonymous (session ended)"
        return "anonymous"
    return find


@router.post("/stop/acknowledge", response_model=AcknowledgeOut, dependencies=[SameSite],
             responses={**BODY_ERRORS, 401: {"model": ErrorOut}, 403: {"model": ErrorOut},
                        409: {"model": ErrorOut, "description": "the motor controller still reports a fault"}},
             summary="Acknowledge the emergency stop (runs may start again)")
async def acknowledge_stop(manager: ManagerDep, body: Annotated[AcknowledgeIn, Body()],
                           who: Operator) -> AcknowledgeOut:
    """An operator confirms the rig is safe: the motor controller's latched fault is reset and read
    back, and the acknowledgement (who, when, note) is recorded in the database and the log.
    Refused (409) while the controller still reports a fault, e.g. the crank still turning."""
    note = body.note if body.operator in ("", who.name) else f"operator at the rig: {body.operator}; {body.note}"
    rep = await manager.runs.acknowledge(who.name, note.strip("; "))
    return AcknowledgeOut(acknowledged=rep.acknowledged, by=rep.by, at=datetime.now(UTC), detail=rep.detail,
                          latched=manager.latch.latched)


@router.get("/health", response_model=HealthOut, dependencies=[Reader],
            responses={401: {"model": ErrorOut}}, summary="State of each device link, database, workers")
async def health(manager: ManagerDep) -> HealthOut:
    return HealthOut.model_validate(await manager.health())


@router.get("/station", response_model=StationOut, dependencies=[Reader],
            responses={401: {"model": ErrorOut}}, summary="The mounted transducer and the rig's limits")
async def station_info(settings: SettingsDep) -> StationOut:
    cfg = settings.config
    rig = cfg.rig
    drive = drive_profile(rig.motor.profile)
    return StationOut(
        name=cfg.station.name, transducer_id=cfg.transducer.id, capacity_N=cfg.transducer.capacity_N,
        default_top_mass_kg=rig.top_mass_kg, simulated=settings.sim,
        limits=LimitsOut(crank_frequency_hz=RangeOut(**rig.crank_frequency_hz.model_dump()),
                         crank_radius_m=RangeOut(**rig.crank_radius_m.model_dump()),
                         peak_force_limit_N=force_limit_N(cfg),
                         moving_mass_without_top_kg=rig.adaption_mass_kg + (cfg.transducer.end_mass_kg or 0.0),
                         top_mass_kg=RangeOut(min=0.0, max=MAX_TOP_MASS_KG), steps=RangeOut(min=1, max=MAX_STEPS),
                         acceleration_hz_per_s=rig.acceleration_hz_per_s,
                         drive=DriveLimitsOut(
                             profile=drive.name,
                             crank_frequency_hz=RangeOut(min=drive.device.min_frequency_hz,
                                                         max=drive.device.max_frequency_hz),
                             acceleration_hz_per_s=RangeOut(min=drive.device.min_ramp_hz_per_s,
                                                            max=drive.device.max_ramp_hz_per_s))),
        default_settle_s=cfg.plan.settle_s, default_record_s=cfg.plan.record_s,
        default_steps=[{"crank_frequency_hz": s.crank_frequency_hz, "crank_radius_m": s.crank_radius_m}
                       for s in cfg.plan.steps],
        token_required=["POST /runs", "POST /runs/{id}/abort", "POST /stop/acknowledge", "POST /campaigns"],
        stop_port=settings.stop_port, environment=environment_form(cfg))


def environment_form(cfg: StationConfig) -> EnvironmentFormOut:
    """The run form's room conditions: the accepted ranges and the configuration's defaults."""
    env = cfg.environment

    def accepted(name: str) -> RangeOut:
        lo, hi = EnvironmentConfig.accepted_range(name)
        return RangeOut(min=lo, max=hi)

    return EnvironmentFormOut(
        temperature_c=accepted("temperature_c"), relative_humidity_pct=accepted("relative_humidity_pct"),
        default_temperature_c=env.temperature_c, default_relative_humidity_pct=env.relative_humidity_pct,
        otherwise="simulated room sensor" if cfg.simulation is not None else "not recorded")
