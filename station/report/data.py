"""What the report and the plots need from a recording, read from what is stored beside it.

* the identification: the stored ``results/identify_<method>_<model>`` (an ``IdentificationResult``
  with its covariance, read back by ``from_dict``) preferred in the order ``ident.names.METHOD_PREFERENCE`` (the
  latest written of a method); only when none is stored, computed now with the station's default
  (``identify_recording``: fd, model auto) and labelled as not stored;
* H(f) at the steps and the displacement's harmonic phasors: ``processed/steps`` (arrays
  ``frequency_hz``, ``H``, ``H_cov``, ``t_center_s``, ``X_h``, per step of the plausibility gate's
  kept steps); only for a recording processed before those arrays were stored (or not processed),
  the sine fits of the raw record windows, computed once;
* the per-step time signals (the raw record windows) with the model's prediction, each labelled with
  its recording step index;
* the model curve with the covariance the identification stored (never rebuilt here);
* the model-gap analysis ``results/discrepancy`` when present.

``load_run`` caches the last 4 recordings by (path, modification time, size, the results' files), so
the four plots and the report of one run read it once (the raw channels are dropped; the record
windows kept).
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
from station.ident.identify import identify_recording
from station.ident.models import Model, SdofModel, make_model
from station.ident.names import METHOD_PREFERENCE
from station.ident.response.checked import CheckedResponse, checked_response
from station.ident.result import IdentificationResult, json_float
from station.recording import Recording, read_recording
from station.recording.stored import read_processed, read_stored, results_version
from station.run.methods import METHODS_RESULT

FloatArray = NDArray[np.float64]
log = logging.getLogger(__name__)
PROCESSED_ARRAYS = ("frequency_hz", "H", "H_cov")
TRACE_ARRAYS = ("t_center_s", "X_h")


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
    ident: IdentificationResult
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
        extra = self.ident.extra
        return (json_float(extra, "m_e_kg", self.rec.end_mass_kg or 0.0)
                + json_float(extra, "m_l_kg", self.rec.load_mass_kg))


def read_groups(path: Path) -> tuple[dict[str, StoredResult], dict[str, Any] | None]:
    """All stored ``results`` documents, and ``processed/steps`` (its JSON plus arrays) or None."""
    results = {n: StoredResult(n, s.written, s.doc) for n, s in read_stored(path).items()}
    stored = read_processed(path)
    proc = None
    if stored is not None and all(k in stored.arrays for k in PROCESSED_ARRAYS):
        proc = {"json": stored.doc, **stored.arrays}
    return results, proc


def choose_identification(results: dict[str, StoredResult]) -> StoredResult | None:
    """The stored identification the report shows: the primary of the listed methods (``results/methods``)
    when it is stored, else the first method of METHOD_PREFERENCE, latest written."""
    listed = results.get(METHODS_RESULT)
    for o in (listed.payload.get("methods", []) if listed else []):
        primary = results.get(str(o.get("result_name")))
        if o.get("primary") and o.get("status") == "done" and primary is not None and "parameters" in primary.payload:
            return primary
    for method in METHOD_PREFERENCE:
        found = [r for r in results.values() if r.name.startswith("identify_")
                 and r.payload.get("method") == method and "parameters" in r.payload]
        if found:
            return max(found, key=lambda r: r.written)
    return None


def model_curve(ident: IdentificationResult, rec: Recording) -> tuple[ModelCurve | None, str]:
    """The identified model with its parameters and stored covariance, or None and why it cannot
    be drawn."""
    params = ident.parameters
    m_e = json_float(ident.extra, "m_e_kg", rec.end_mass_kg or 0.0)
    m_l = json_float(ident.extra, "m_l_kg", rec.load_mass_kg)
    try:
        model: Model = make_model(ident.model, m_e, m_l)
    except ValueError as exc:
        return None, f"model curve not drawn: {exc}"
    note = ""
    names = model.names
    if model.key == "coupled" and not all(n in params and params[n].identifiable for n in ("k_c", "b_c")):
        model, names = SdofModel(m_e, m_l), model.names[:3]
        note = "k_c, b_c not identifiable: drawn in the stiff-coupling limit (Eq. 9)"
    bad = [n for n in names if n not in params or not params[n].identifiable or params[n].value is None]
    if bad:
        why = "; ".join(f"{n} not identifiable: {params[n].reason if n in params else 'not in the result'}"
                        for n in bad)
        return None, f"model curve not drawn ({why})"
    theta = np.array([float(params[n].value or 0.0) for n in names])
    cov = None
    c = ident.covariance
    if c is not None and all(n in c.names for n in names):
        i = [c.names.index(n) for n in names]
        cov = c.array[np.ix_(i, i)]
    else:
        note = "; ".join(filter(None, [note, "the stored result has no covariance of these parameters (stored "
                                             "by an older version): model uncertainty band not drawn"]))
    return ModelCurve(model, theta, cov, note), ""


def _from_processed(proc: dict[str, Any]) -> Response:
    steps = proc["json"].get("steps") or []
    n = len(proc["frequency_hz"])
    idx = tuple(int(s.get("index", i)) for i, s in enumerate(steps))
    if len(idx) != n:
        idx = tuple(range(n))
    return Response(np.asarray(proc["frequency_hz"], float), np.asarray(proc["H"], complex),
                    np.asarray(proc["H_cov"], float).reshape(-1, 2, 2), idx, "processed/steps")


def _predict(curve: ModelCurve | None, f: float, tt: FloatArray, X_h: NDArray[np.complex128],
             offset: float) -> FloatArray | None:
    """The model's force signal (V) at times tt (s, from the window's centre) for a frame moving
    with displacement harmonics X_h (m) at the fundamental f (Hz)."""
    if curve is None:
        return None
    h = np.arange(1, X_h.size + 1)
    A = -((2 * np.pi * f * h) ** 2) * X_h
    E = np.exp(1j * np.outer(tt, 2 * np.pi * f * h))
    return offset + (E @ (curve.model.response(curve.theta, h * f) * A)).real


def _stored_traces(rec: Recording, proc: dict[str, Any], resp: Response,
                   curve: ModelCurve | None) -> tuple[StepTrace, ...]:
    """Traces of the processed steps: the raw record windows, the model driven by the stored phasors."""
    steps = {st.index: st for st in rec.steps}
    offsets = [float(s.get("force_offset_V", 0.0)) for s in proc["json"].get("steps") or []]
    out = []
    for k, index in enumerate(resp.step_index):
        st = steps[index]
        t = np.arange(st.start_sample, st.end_sample) / rec.sample_rate_hz
        tt = t - float(proc["t_center_s"][k])
        f = float(resp.f_hz[k])
        X_h = np.asarray(proc["X_h"][k], complex)
        u = np.asarray(rec.force_V[st.start_sample:st.end_sample], float)
        out.append(StepTrace(index, f, tt, u, _predict(curve, f, tt, X_h, offsets[k] if k < len(offsets) else 0.0)))
    return tuple(out)


def _fitted_traces(cr: CheckedResponse, curve: ModelCurve | None) -> tuple[StepTrace, ...]:
    """Traces from sine fits of the raw windows, labelled with the steps the gate kept (``cr.used``)."""
    out = []
    for i, (index, s) in enumerate(zip(cr.used, cr.sigs, strict=True)):
        f = s.fit_x.frequency_hz
        tt = s.t - s.fit_x.t_center_s
        out.append(StepTrace(index, float(f), tt, np.asarray(s.u, float),
                             _predict(curve, f, tt, s.X_h, float(cr.frf.force_offset_V[i]))))
    return tuple(out)


@lru_cache(maxsize=4)
def cached_run_data(path_str: str, mtime_ns: int, size_bytes: int,
                    results_versions: tuple[tuple[str, int], ...]) -> RunData:
    """The cache behind :func:`load_run`: RunData of the recording at the resolved ``path_str``, keyed
    by the file's modification time (ns), size (bytes) and stored results' versions
    (:func:`~station.recording.stored.results_version`), so that a changed file is read again.  Call
    :func:`load_run`; ``cached_run_data.cache_clear()`` drops the (up to 4) cached runs and
    ``cached_run_data.cache_info()`` counts hits and misses."""
    path = Path(path_str)
    results, proc = read_groups(path)
    rec = read_recording(path)
    stored = choose_identification(results)
    cr: CheckedResponse | None = None
    try:
        if stored is not None:
            ident = IdentificationResult.from_dict(stored.payload)
            source = f"results/{stored.name} (stored beside the recording, written {stored.written})"
        else:
            try:
                cr = checked_response(rec)
                ident = identify_recording(rec, response=cr)
            except StationError as exc:
                raise RecordingFormatError(f"{path}: no identification results stored (results/identify_*) "
                                           f"and none could be computed: {exc}") from None
            source = "computed for this report with the default method (not stored with the recording)"
        curve, why = model_curve(ident, rec)
        if proc is not None and all(k in proc for k in TRACE_ARRAYS):
            response = _from_processed(proc)
            traces = _stored_traces(rec, proc, response, curve)
        else:  # nothing processed stored with the phasors: the sine fits of the raw windows, once
            cr = cr or checked_response(rec)
            response = _from_processed(proc) if proc is not None else Response(
                cr.frf.f_hz, cr.frf.H, cr.frf.cov, tuple(cr.used), "sine fits of the raw record windows")
            traces = _fitted_traces(cr, curve)
    except RecordingFormatError:
        raise
    except StationError as exc:
        raise RecordingFormatError(f"{path}: no results can be shown: {exc}") from None
    disc = results.get("discrepancy")
    empty = np.zeros(0)  # the cache keeps the record windows (traces), not the whole raw channels
    return RunData(replace(rec, displacement_m=empty, force_V=empty), ident, source, results, response, curve, why,
                   traces, disc.payload if disc else None)


RunKey = tuple[str, int, int, tuple[tuple[str, int], ...]]


def run_key(path: str | Path) -> RunKey:
    """What a recording's derived pages and plots are a function of: its resolved path, modification
    time (ns), size (bytes) and stored results' versions (the arguments of :func:`cached_run_data`);
    RecordingFormatError when there is no such file."""
    p = Path(path).resolve()
    try:
        st = p.stat()
    except OSError:
        raise RecordingFormatError(f"{path}: no such recording") from None
    return str(p), st.st_mtime_ns, st.st_size, results_version(p)


def load_run(path: str | Path) -> RunData:
    """RunData of a recording (cached while the file is unchanged); RecordingFormatError when the
    recording cannot be read or has no results and none can be computed."""
    return cached_run_data(*run_key(path))
