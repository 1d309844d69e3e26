"""What a completed run's recording holds after identification, as plain JSON-able data
(read in a thread by the daemon; ``station.api.schemas.RunResults`` types it)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any, cast

import numpy as np
from typing_extensions import TypedDict  # pydantic reads it (the API's schema) on Python < 3.12

from station.ident.result import IdentificationResult, JsonValue
from station.recording import read_documents, read_result, start_metadata
from station.recording.stored import read_processed
from station.run.methods import agreement, read_outcomes


def finite(obj: Any) -> Any:
    """``obj`` with every non-finite float replaced by None (JSON has no NaN or inf)."""
    if isinstance(obj, float | np.floating):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [finite(v) for v in obj]
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.ndarray):
        return finite(obj.tolist())
    return obj


class StepResponse(TypedDict):
    """H(f) = force signal / frame acceleration of one step, V/(m/s^2): its magnitude and phase (deg)
    with standard uncertainties, the amplitudes (m, V) and the samples it rests on (the API's
    schema of a step's response is this type)."""

    index: int
    frequency_hz: float | None
    frequency_std_hz: float | None
    H_real: float | None
    H_imag: float | None
    H_magnitude: float | None
    H_magnitude_std: float | None
    H_phase_deg: float | None
    H_phase_std_deg: float | None
    displacement_amplitude_m: float | None
    force_amplitude_V: float | None
    n_samples: int | None


class ResultFields(TypedDict, total=False):
    """A stored identification's parameters (a list in the model's order), fit, identifiability,
    notes, checks and budget, in their JSON form."""

    parameters: list[JsonValue]
    fit: JsonValue
    identifiability: JsonValue
    notes: list[JsonValue]
    checks: list[JsonValue]
    budget: JsonValue


class StoredMethod(ResultFields, total=False):
    """A listed identification (``station.run.methods.MethodOutcome``'s fields) with its stored
    result's fields and its agreement with the primary result, per parameter
    (``station.api.schemas.MethodResultOut``)."""

    agreement: Mapping[str, JsonValue]


class StoredResults(ResultFields):
    """What ``load_results`` gives (``station.api.schemas.RunResults`` without the run's own fields):
    the stored identification (its method, model, result fields, assumptions, determined quantities
    and covariance), the processed H(f), the skipped steps, the units, every listed method and the
    room conditions."""

    method: str | None
    model: str | None
    assumptions: JsonValue
    determined: JsonValue
    covariance: JsonValue
    frequency_response: list[StepResponse]
    skipped_steps: list[JsonValue]
    units: dict[str, str]
    methods: list[StoredMethod]
    environment: JsonValue


def frequency_response(path: Path) -> tuple[list[StepResponse], list[JsonValue], dict[str, str]]:
    """(per-step H(f) with standard uncertainties of magnitude and phase, skipped steps, units)."""
    stored = read_processed(path)
    if stored is None:
        return [], [], {}
    doc, cov = stored.doc, stored.arrays.get("H_cov")
    out: list[StepResponse] = []
    for k, st in enumerate(doc.get("steps", [])):
        re, im = (float(v) for v in st["H"])
        mag = math.hypot(re, im)
        mag_std = phase_std = None
        if cov is not None and k < len(cov) and mag > 0:
            C = np.asarray(cov[k], dtype=float)
            g_mag = np.array([re, im]) / mag
            g_ph = np.array([-im, re]) / mag**2
            mag_std = float(np.sqrt(max(g_mag @ C @ g_mag, 0.0)))
            phase_std = float(np.degrees(np.sqrt(max(g_ph @ C @ g_ph, 0.0))))
        out.append({"index": int(st["index"]), "frequency_hz": st["frequency_hz"],
                    "frequency_std_hz": st.get("frequency_std_hz"), "H_real": re, "H_imag": im,
                    "H_magnitude": mag, "H_magnitude_std": mag_std,
                    "H_phase_deg": math.degrees(math.atan2(im, re)), "H_phase_std_deg": phase_std,
                    "displacement_amplitude_m": st.get("displacement_amplitude_m"),
                    "force_amplitude_V": st.get("force_amplitude_V"), "n_samples": st.get("n_samples")})
    units = {"frequency_hz": "Hz", "H": "V/(m/s^2)", "H_phase_deg": "deg", "displacement_amplitude_m": "m",
             "force_amplitude_V": "V"}
    return cast(list[StepResponse], finite(out)), cast(list[JsonValue], finite(doc.get("skipped", []))), units


def load_results(path: Path, result_name: str) -> StoredResults:
    """The identification stored as result ``result_name`` (an ``IdentificationResult``, with its
    covariance) and the processed H(f), as stored beside the recording; nothing is re-fitted."""
    doc = read_result(path, result_name)
    steps, skipped, units = frequency_response(path)
    out: dict[str, JsonValue] = {"method": None, "model": None, "parameters": [], "fit": None, "identifiability": None,
                           "notes": [], "checks": [], "budget": {}, "assumptions": {}, "determined": {},
                           "covariance": None}
    primary = None if doc is None else IdentificationResult.from_dict(doc)
    if primary is not None:
        out.update(_result_fields(primary, tuple(out)))
    methods = method_results(path, primary)
    env = start_metadata(read_documents(path)).get("environment")
    return cast(StoredResults, finite({**out, "frequency_response": steps, "skipped_steps": skipped, "units": units,
                                       "methods": methods, "environment": env if isinstance(env, dict) else None}))


def _result_fields(res: IdentificationResult, keys: tuple[str, ...]) -> dict[str, JsonValue]:
    """``keys`` of the result's JSON form, ``parameters`` as a list in the model's order (the API's)."""
    d = res.to_dict()
    return {k: [{"name": n, **p.to_dict()} for n, p in res.parameters.items()] if k == "parameters" else d[k]
            for k in keys if k in d}


METHOD_KEYS = ("parameters", "fit", "identifiability", "notes", "checks", "budget")


def method_results(path: Path, primary: IdentificationResult | None) -> list[StoredMethod]:
    """Every listed identification's outcome with its stored result and its agreement with the
    primary (``station.run.methods``), in the listed order; [] when none were listed."""
    out: list[StoredMethod] = []
    for o in read_outcomes(path):
        entry = cast(StoredMethod, {**o.to_dict(), "agreement": {}})
        doc = read_result(path, o.result_name) if o.status == "done" and o.result_name else None
        if doc is not None:
            res = IdentificationResult.from_dict(doc)
            entry.update(cast(StoredMethod, _result_fields(res, METHOD_KEYS)))
            if primary is not None and not o.primary:
                entry["agreement"] = agreement(primary, res)
        out.append(entry)
    return out
