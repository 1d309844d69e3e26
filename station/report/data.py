"""What the report and the plots need from a recording, loaded once per file version.

* the identification: the stored ``results/identify_<method>_<model>`` preferred in the order
  ``METHOD_PREFERENCE`` (the latest written of a method), else computed now with the station's
  default (``identify_recording``: fd, model auto) and not stored;
* H(f) at the steps: ``processed/steps`` (arrays ``frequency_hz``, ``H``, ``H_cov``) when the run was
  processed, else the identification's own sine fits of the raw record windows;
* the per-step time signals with the model's prediction (for the time-domain plots);
* the discrepancy workflow's ``results/discrepancy`` when present.

``load_run`` caches the last 4 recordings by (path, modification time, size), so the four plots
and the report of one run read and fit it once (the raw channels are dropped; the record windows kept).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from station.errors import RecordingFormatError, StationError
from station.ident.api import identify_recording, measured_response
from station.ident.frf import FrequencyResponse, whitened_jacobian
from station.ident.models import Model, SdofModel, make_model
from station.recording import Recording, read_recording
from station.recording.stored import read_processed, read_stored, results_version

FloatArray = NDArray[np.float64]
log = logging.getLogger(__name__)
METHOD_PREFERENCE = ("fd", "oe", "pso+", "pso", "rls")
PAPER_METHODS = ("pso", "pso+")


@dataclass(frozen=True)
class StoredResult:
    """One ``results/<name>`` document and when it was written (ISO 8601, UTC)."""

    name: str
    written: str
    payload: dict[str, Any]


@dataclass(frozen=True)
class Response:
    """Measured H = force signal / frame acceleration at the steps, V/(m/s^2): f_hz (n,),
    H (n,) complex, cov (n, 2, 2) of (Re H, Im H), step index per point, and where it came from."""

    f_hz: FloatArray
    H: NDArray[np.complex128]
    cov: FloatArray
    step_index: tuple[int, ...]
    source: str


@dataclass(frozen=True)
class ModelCurve:
    """The identified model ready to evaluate: theta in model units, cov (or None when the result
    stores no correlation matrix), and a note (e.g. drawn in the stiff-coupling limit)."""

    model: Model
    theta: FloatArray
    cov: FloatArray | None
    note: str = ""


@dataclass(frozen=True)
class StepTrace:
    """One usable step in the time domain: t (s, from the window's centre), force signal u (V) and
    the model's prediction (V, None without a model); f_hz the fitted crank frequency."""

    index: int
    f_hz: float
    t_s: FloatArray
    u_V: FloatArray
    model_V: FloatArray | None


@dataclass(frozen=True)
class RunData:
    """Everything a report of one recording shows."""

    rec: Recording
    ident: dict[str, Any]
    ident_source: str
    results: dict[str, StoredResult]
    response: Response
    curve: ModelCurve | None
    curve_note: str
    traces: tuple[StepTrace, ...]
    discrepancy: dict[str, Any] | None

    @property
    def mass_kg(self) -> float:
        """M = m_e + m_l of the model (m_e taken as 0 when unknown)."""
        extra = self.ident.get("extra") or {}
        return float(extra.get("m_e_kg", self.rec.end_mass_kg or 0.0)) + float(
            extra.get("m_l_kg", self.rec.load_mass_kg))


def read_groups(path: Path) -> tuple[dict[str, StoredResult], dict[str, Any] | None]:
    """All ``results`` documents, and ``processed/steps`` (its JSON plus arrays) or None."""
    results = {n: StoredResult(n, s.written, s.doc) for n, s in read_stored(path).items()}
    stored = read_processed(path)
    proc = None
    if stored is not None and all(k in stored.arrays for k in ("frequency_hz", "H", "H_cov")):
        proc = {"json": stored.doc, **{k: stored.arrays[k] for k in ("frequency_hz", "H", "H_cov")}}
    return results, proc


def choose_identification(results: dict[str, StoredResult]) -> StoredResult | None:
    """The stored identification the report shows: first method of METHOD_PREFERENCE, latest written."""
    for method in METHOD_PREFERENCE:
        found = [r for r in results.values() if r.name.startswith("identify_")
                 and r.payload.get("method") == method and "parameters" in r.payload]
        if found:
            return max(found, key=lambda r: r.written)
    return None


def _covariance(model: Model, theta: FloatArray, std: FloatArray, resp: Response) -> FloatArray | None:
    """Covariance with the identification's standard uncertainties and the correlation of the
    weighted frequency-domain problem at the estimate (results store no covariance matrix; the
    ``identifiability.correlations`` describe the design against the noise floor, not the estimate)."""
    if 2 * resp.f_hz.size < theta.size:
        return None
    frf = FrequencyResponse(resp.f_hz, resp.H, resp.cov, np.zeros(resp.f_hz.size), np.zeros(resp.f_hz.size))
    try:
        J = whitened_jacobian(model, theta, frf, scale=np.where(theta != 0, np.abs(theta), 1.0))
        C = np.linalg.pinv(J.T @ J)
    except np.linalg.LinAlgError:
        return None
    d = np.sqrt(np.clip(np.diag(C), 0, None))
    if not np.all(d > 0) or not np.all(np.isfinite(C)):
        return None
    return np.clip(C / np.outer(d, d), -1, 1) * np.outer(std, std)


def model_curve(ident: dict[str, Any], rec: Recording, resp: Response) -> tuple[ModelCurve | None, str]:
    """The identified model with its parameters, or None and why it cannot be drawn."""
    params: dict[str, Any] = ident.get("parameters") or {}
    extra = ident.get("extra") or {}
    m_e = float(extra.get("m_e_kg", rec.end_mass_kg or 0.0))
    m_l = float(extra.get("m_l_kg", rec.load_mass_kg))
    try:
        model: Model = make_model(str(ident.get("model")), m_e, m_l)
    except ValueError as exc:
        return None, f"model curve not drawn: {exc}"
    note = ""
    names = model.names
    if model.key == "coupled" and not all((params.get(n) or {}).get("identifiable") for n in ("k_c", "b_c")):
        model, names = SdofModel(m_e, m_l), model.names[:3]
        note = "k_c, b_c not identifiable: drawn in the stiff-coupling limit (Eq. 9)"
    bad = [n for n in names if not (params.get(n) or {}).get("identifiable")
           or (params.get(n) or {}).get("value") is None]
    if bad:
        why = "; ".join(f"{n} not identifiable: {(params.get(n) or {}).get('reason') or 'no value'}" for n in bad)
        return None, f"model curve not drawn ({why})"
    theta = np.array([float(params[n]["value"]) for n in names])
    std = np.array([float(params[n]["std"]) if params[n].get("std") is not None else np.nan for n in names])
    cov = _covariance(model, theta, std, resp) if np.all(np.isfinite(std)) else None
    if cov is None:
        note = "; ".join(filter(None, [note, "no parameter covariance: model uncertainty band not drawn"]))
    return ModelCurve(model, theta, cov, note), ""


def _response(proc: dict[str, Any] | None, frf: Any, usable: list[int]) -> Response:
    if proc is not None and len(proc["frequency_hz"]):
        steps = proc["json"].get("steps") or []
        idx = tuple(int(s.get("index", i)) for i, s in enumerate(steps))
        if len(idx) != len(proc["frequency_hz"]):
            idx = tuple(range(len(proc["frequency_hz"])))
        return Response(np.asarray(proc["frequency_hz"], float), np.asarray(proc["H"], complex),
                        np.asarray(proc["H_cov"], float).reshape(-1, 2, 2), idx, "processed/steps")
    return Response(frf.f_hz, frf.H, frf.cov, tuple(usable), "sine fits of the raw record windows")


def _traces(frf: Any, sigs: list[Any], usable: list[int], curve: ModelCurve | None) -> tuple[StepTrace, ...]:
    out = []
    for i, s in enumerate(sigs):
        f = s.fit_x.frequency_hz
        tt = s.t - s.fit_x.t_center_s
        pred = None
        if curve is not None:
            h = np.arange(1, s.X_h.size + 1)
            A = -((2 * np.pi * f * h) ** 2) * s.X_h
            E = np.exp(1j * np.outer(tt, 2 * np.pi * f * h))
            pred = float(frf.force_offset_V[i]) + (E @ (curve.model.response(curve.theta, h * f) * A)).real
        out.append(StepTrace(usable[i], float(f), tt, np.asarray(s.u, float), pred))
    return tuple(out)


@lru_cache(maxsize=4)
def _load(path_str: str, _mtime_ns: int, _size: int, _results: tuple[tuple[str, int], ...]) -> RunData:
    path = Path(path_str)
    results, proc = read_groups(path)
    rec = read_recording(path)
    stored = choose_identification(results)
    if stored is not None:
        ident, source = stored.payload, f"results/{stored.name} (stored beside the recording, written {stored.written})"
    else:
        try:
            ident = identify_recording(rec).to_dict()
        except StationError as exc:
            raise RecordingFormatError(f"{path}: no identification results stored (results/identify_*) "
                                       f"and none could be computed: {exc}") from None
        source = "computed for this report with the default method (not stored in the recording)"
    try:
        frf, sigs, _notes = measured_response(rec)
    except StationError as exc:
        raise RecordingFormatError(f"{path}: no results can be shown: {exc}") from None
    usable = [st.index for st in rec.steps if st.usable]
    response = _response(proc, frf, usable)
    curve, why = model_curve(ident, rec, response)
    disc = results.get("discrepancy")
    traces = _traces(frf, sigs, usable, curve)
    empty = np.zeros(0)  # the cache keeps the record windows (traces), not the whole raw channels
    return RunData(replace(rec, displacement_m=empty, force_V=empty), ident, source, results, response, curve, why,
                   traces, disc.payload if disc else None)


def load_run(path: str | Path) -> RunData:
    """RunData of a recording (cached while the file is unchanged); RecordingFormatError when the
    recording cannot be read or has no results and none can be computed."""
    p = Path(path).resolve()
    try:
        st = p.stat()
    except OSError:
        raise RecordingFormatError(f"{path}: no such recording") from None
    return _load(str(p), st.st_mtime_ns, st.st_size, results_version(p))
