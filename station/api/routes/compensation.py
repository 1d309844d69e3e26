"""Dynamic compensation over HTTP: a filter designed from a run's stored identification for the
application's mounting (JSON, and its Bode plot), and a filter applied to a signal (JSON in, JSON
out; bounded by the body limit and ``MAX_API_SAMPLES``).  The method is ``station.compensate``
(docs/compensation.md); nothing here computes."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

from fastapi import Response
from pydantic import BaseModel, ConfigDict, Field, model_validator

from station.api.deps import ArtifactsDep, Reader, RunDep
from station.api.problems import Refusal
from station.api.routes import api_router
from station.api.routes.runs import BINARY, BODY_ERRORS, E401, E404, E422, E503
from station.errors import BadInputError

router = api_router(tags=["compensation"])
MAX_API_SAMPLES = 200_000
MAX_API_TAPS = 256


class DesignIn(BaseModel):
    """What the application states: its sample rate, the mass mounted on the transducer, the band
    (or the cut-off) and the filter's shape."""

    model_config = ConfigDict(extra="forbid")

    sample_rate_hz: float = Field(gt=0, le=10e6, description="the application's sample rate in Hz")
    mounted_mass_kg: float = Field(ge=0, le=1e4, description="mass mounted on the transducer in the application, kg")
    mounted_mass_std_kg: float = Field(default=0.0, ge=0, le=1e3, description="its standard uncertainty, kg")
    band_hz: tuple[float, float] | None = Field(default=None, description="band of interest (low, high) in Hz")
    cutoff_hz: float | None = Field(default=None, gt=0, description="cut-off of the regularising low-pass, Hz")
    taps: int = Field(default=64, ge=4, le=MAX_API_TAPS)
    lowpass_order: int = Field(default=4, ge=1, le=16)
    delay_samples: int | None = Field(default=None, ge=0, description="delay in samples (null: least error)")
    allow_extrapolation: bool = Field(default=False, description="accept a band beyond the calibrated range "
                                      "(the filter then carries the finding 'extrapolation')")

    @model_validator(mode="after")
    def _band_or_cutoff(self) -> DesignIn:
        if self.band_hz is None and self.cutoff_hz is None:
            raise ValueError("state band_hz or cutoff_hz")
        return self


class FilterOut(BaseModel):
    """The filter as ``station compensate design`` writes it (docs/compensation.md lists every field)."""

    model_config = ConfigDict(extra="allow")

    format: str
    format_version: int
    sample_rate_hz: float
    taps: int
    b: list[float] = Field(description="coefficients, unit_out/unit_in")
    b_cov: list[list[float]] = Field(description="their covariance")
    unit_in: str
    unit_out: str
    delay_samples: int
    delay_s: float
    band_hz: list[float]
    cutoff_hz: float
    fit_rms_band: float
    dynamic_error_bound: float
    noise_gain: float
    findings: list[dict[str, Any]]


class ApplyIn(BaseModel):
    model_config = ConfigDict(extra="forbid")

    filter: dict[str, Any] = Field(description="a filter document (POST /runs/{id}/compensation)")
    signal: list[float] = Field(min_length=1, max_length=MAX_API_SAMPLES,
                                description="the measured signal in the filter's unit_in, uniformly sampled")
    sample_rate_hz: float = Field(gt=0, description="the signal's sample rate in Hz (must be the filter's)")
    noise_std: float = Field(default=0.0, ge=0, description="standard deviation of white noise in the signal")
    keep_delay: bool = Field(default=False, description="keep the delay in the time axis")


class ApplyOut(BaseModel):
    time_s: list[float]
    estimate: list[float]
    u: list[float] = Field(description="standard uncertainty (k = 1) at every sample")
    unit: str
    delay_s: float
    delay_removed: bool


def _design(path: Path, body: dict[str, Any]) -> dict[str, Any]:
    from station.compensate.design import DesignSpec, default_cutoff, design_filter
    from station.compensate.sensor import sensor_from_recording

    d = DesignIn.model_validate(body)
    sensor = sensor_from_recording(str(path), d.mounted_mass_kg, d.mounted_mass_std_kg)
    band = d.band_hz if d.band_hz is not None else (0.0, float(d.cutoff_hz or 0.0) / 1.5)
    cutoff = d.cutoff_hz if d.cutoff_hz is not None else default_cutoff(band[1], d.sample_rate_hz)
    filt = design_filter(sensor, DesignSpec(d.sample_rate_hz, (float(band[0]), float(band[1])), float(cutoff),
                                            d.taps, d.lowpass_order, d.delay_samples, d.allow_extrapolation))
    doc = filt.to_dict()
    doc["transducer"]["origin"] = Path(doc["transducer"]["origin"].split(":")[0]).name  # no server paths
    return doc


def _plot(path: Path, body: dict[str, Any]) -> bytes:
    import tempfile

    from station.compensate.design import CompensationFilter
    from station.compensate.plots import bode_plot

    doc = _design(path, body)
    with tempfile.TemporaryDirectory() as tmp:
        return bode_plot(CompensationFilter.from_dict(doc), Path(tmp) / "bode.png").read_bytes()


def _refused(exc: BadInputError) -> Refusal:
    return Refusal(422, "compensation-refused", str(exc),
                   errors=[{"type": "compensation_refused", "loc": ["body"], "msg": str(exc)}])


@router.post("/runs/{run_id}/compensation", response_model=FilterOut, dependencies=[Reader],
             responses={**E401, **E404, **E422, **E503, **BODY_ERRORS},
             summary="A compensation filter for the application's mounting, from the run's identification")
async def run_compensation(run: RunDep, artifacts: ArtifactsDep, body: DesignIn) -> dict[str, Any]:
    """Least-squares FIR inverse of the run's identified transducer carrying ``mounted_mass_kg``,
    with its coefficients' covariance (422 with the reason when refused: a band beyond the
    calibrated range without ``allow_extrapolation``, no stored identification, ...)."""
    try:
        doc = await artifacts.read_file(run.id, lambda p: _design(p, body.model_dump()))
    except BadInputError as exc:
        raise _refused(exc) from None
    from station.service.results import finite

    return finite(doc)  # e.g. an older result without its frequencies has a NaN calibrated range: null


@router.post("/runs/{run_id}/compensation/plot", response_class=Response, dependencies=[Reader],
             responses={200: {"content": {"image/png": {"schema": BINARY}}, "description": "Bode plot"},
                        **E401, **E404, **E422, **BODY_ERRORS},
             summary="The Bode plot of that filter: transducer, filter, compensated system with bands")
async def run_compensation_plot(run: RunDep, artifacts: ArtifactsDep, body: DesignIn) -> Response:
    try:
        png = await artifacts.read_file(run.id, lambda p: _plot(p, body.model_dump()))
    except BadInputError as exc:
        raise _refused(exc) from None
    return Response(png, media_type="image/png")


def _apply(body: ApplyIn) -> dict[str, Any]:
    import numpy as np

    from station.compensate.apply import Noise, compensate
    from station.compensate.design import CompensationFilter
    from station.compensate.signals import check_rate

    filt = CompensationFilter.from_dict(body.filter)
    if len(filt.b) > MAX_API_TAPS:
        raise BadInputError(f"a filter of {len(filt.b)} taps: the API applies at most {MAX_API_TAPS}")
    check_rate(body.sample_rate_hz, filt.sample_rate_hz)
    x = np.asarray(body.signal, dtype=float)
    y, u = compensate(filt, x, Noise.white(body.noise_std))
    t = np.arange(x.size) / body.sample_rate_hz - (0.0 if body.keep_delay else filt.delay_s)
    return {"time_s": t.tolist(), "estimate": y.tolist(), "u": u.tolist(), "unit": filt.unit_out,
            "delay_s": filt.delay_s, "delay_removed": not body.keep_delay}


@router.post("/compensation/apply", response_model=ApplyOut, dependencies=[Reader],
             responses={**E401, **E422, **BODY_ERRORS},
             summary="Apply a compensation filter to a signal, with u at every sample")
async def apply_compensation(body: ApplyIn) -> dict[str, Any]:
    """The estimate and its standard uncertainty (GUM: the coefficients' covariance and the white
    noise stated) at every sample; at most ``MAX_API_SAMPLES`` samples (the command line takes more)."""
    try:
        return await asyncio.to_thread(_apply, body)
    except BadInputError as exc:
        raise _refused(exc) from None
