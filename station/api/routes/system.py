"""/stop, /health, /station: the emergency stop, the state of the device links, the limits."""

from __future__ import annotations

from fastapi import APIRouter

from station.api.deps import ManagerDep, Reader, SettingsDep
from station.api.schemas import ErrorOut, HealthOut, LimitsOut, RangeOut, StationOut, StopOut
from station.config import MAX_STEPS, MAX_TOP_MASS_KG
from station.limits import force_limit_N

router = APIRouter(tags=["station"])


@router.post("/stop", response_model=StopOut, summary="Emergency stop (always accepted)")
async def emergency_stop(manager: ManagerDep) -> StopOut:
    """Aborts every run on the rig and commands an emergency stop on the motor controller at once.
    Always accepted, with or without a token or a run: stopping is never unsafe.  `motor_stopped`
    says whether the controller took the command."""
    rep = await manager.emergency_stop()
    return StopOut(motor_stopped=rep.motor_stopped, aborted_runs=rep.aborted_runs, detail=rep.detail)


@router.get("/health", response_model=HealthOut, dependencies=[Reader],
            responses={401: {"model": ErrorOut}}, summary="State of each device link, database, workers")
async def health(manager: ManagerDep) -> HealthOut:
    return HealthOut.model_validate(manager.health())


@router.get("/station", response_model=StationOut, dependencies=[Reader],
            responses={401: {"model": ErrorOut}}, summary="The mounted transducer and the rig's limits")
async def station_info(settings: SettingsDep) -> StationOut:
    cfg = settings.config
    rig = cfg.rig
    return StationOut(
        name=cfg.station.name, transducer_id=cfg.transducer.id, capacity_N=cfg.transducer.capacity_N,
        default_top_mass_kg=rig.top_mass_kg, simulated=settings.sim,
        limits=LimitsOut(crank_frequency_hz=RangeOut(**rig.crank_frequency_hz.model_dump()),
                         crank_radius_m=RangeOut(**rig.crank_radius_m.model_dump()),
                         peak_force_limit_N=force_limit_N(cfg),
                         moving_mass_without_top_kg=rig.adaption_mass_kg + (cfg.transducer.end_mass_kg or 0.0),
                         top_mass_kg=RangeOut(min=0.0, max=MAX_TOP_MASS_KG), steps=RangeOut(min=1, max=MAX_STEPS),
                         acceleration_hz_per_s=rig.acceleration_hz_per_s),
        default_settle_s=cfg.plan.settle_s, default_record_s=cfg.plan.record_s,
        default_steps=[{"crank_frequency_hz": s.crank_frequency_hz, "crank_radius_m": s.crank_radius_m}
                       for s in cfg.plan.steps],
        token_required=["POST /runs", "POST /runs/{id}/abort"])
