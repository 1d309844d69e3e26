"""The transducer as the application sees it: force in (N), signal out (V), with its parameters'
covariance, built from a calibration.

Three origins, one type (``Sensor``):

* an identified result of a recording (``from_result``): Eq. 9 (``sdof``) or Eq. 8 (``coupled``)
  with the *application's* mounted mass m_l in place of the calibration's top mass.  With the base
  at rest and a force F on the mounted mass, Eq. 3 gives

  - stiff coupling:  G(s) = S k_f / (M s^2 + b_f s + k_f),  M = m_e + m_l;
  - finite coupling: G(s) = S k_f C / ((m_l s^2 + C)(m_e s^2 + C + K) - C^2),
    C = b_c s + k_c, K = b_f s + k_f;

  static limit S in both.  Parameters (S, k_f, b_f[, k_c, b_c], m_e, m_l).  The calibration
  determines S M_cal, k_f / M_cal and b_f / M_cal (M_cal = m_e + m_l,cal); S, k_f, b_f move with the
  end mass, so the end mass's uncertainty enters their covariance *and* their correlation with m_e:
  cov(theta, m_e) = (d theta / d m_e) u(m_e)^2 with d theta / d m_e = (-S, k_f, b_f) / M_cal
  (stiff coupling; for Eq. 8 the end mass is taken as fixed and that is stated).
* a table of sinusoidal calibration values (``from_table``): a second-order system
  G(f) = S0 / (1 - (f/f0)^2 + 2 j delta f/f0) fitted to it (weighted least squares), parameters
  (S0, f0, delta) with their covariance; the table carries no mass, so no other mounting.

Units: ``response`` in the table's or V/N; frequencies in Hz.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from station.errors import BadInputError
from station.ident.models import numeric_jacobian
from station.ident.result import Check, IdentificationResult, json_float, json_floats
from station.vocabulary import Severity

FloatArray = NDArray[np.float64]
ComplexArray = NDArray[np.complex128]

MAX_TABLE_ROWS = 10_000


def _sdof(theta: ArrayLike, f_hz: ArrayLike) -> ComplexArray:
    S, k, b, me, ml = np.asarray(theta, dtype=float)
    s = 2j * np.pi * np.asarray(f_hz, dtype=float)
    return S * k / ((me + ml) * s**2 + b * s + k)


def _coupled(theta: ArrayLike, f_hz: ArrayLike) -> ComplexArray:
    S, kf, bf, kc, bc, me, ml = np.asarray(theta, dtype=float)
    s = 2j * np.pi * np.asarray(f_hz, dtype=float)
    C, K = bc * s + kc, bf * s + kf
    return S * kf * C / ((ml * s**2 + C) * (me * s**2 + C + K) - C**2)


def _second_order(theta: ArrayLike, f_hz: ArrayLike) -> ComplexArray:
    S0, f0, d = np.asarray(theta, dtype=float)
    r = np.asarray(f_hz, dtype=float) / f0
    return S0 / (1 - r**2 + 2j * d * r)


RESPONSES: dict[str, Callable[[ArrayLike, ArrayLike], ComplexArray]] = {
    "sdof": _sdof, "coupled": _coupled, "second_order": _second_order}


@dataclass(frozen=True)
class Sensor:
    """A transducer model for compensation: ``kind`` (a key of ``RESPONSES``), parameter ``names``,
    ``units``, values ``theta`` (n,) and covariance ``cov`` (n, n) in the units' products;
    ``calibrated_range_hz`` (lowest, highest calibrated frequency); ``unit_in``/``unit_out`` of the
    response (e.g. N -> V); ``origin`` (what it was built from); ``assumptions`` stated with every
    filter built on it; ``findings`` (``Check``); ``fit`` (a fitted table's points and residuals)."""

    kind: str
    names: tuple[str, ...]
    units: tuple[str, ...]
    theta: tuple[float, ...]
    cov: tuple[tuple[float, ...], ...]
    calibrated_range_hz: tuple[float, float]
    unit_in: str = "N"
    unit_out: str = "V"
    origin: str = ""
    assumptions: dict[str, Any] = field(default_factory=dict)
    findings: tuple[Check, ...] = ()
    fit: dict[str, Any] = field(default_factory=dict)

    @property
    def theta_array(self) -> FloatArray:
        return np.asarray(self.theta, dtype=float)

    @property
    def cov_array(self) -> FloatArray:
        return np.asarray(self.cov, dtype=float).reshape(len(self.theta), len(self.theta))

    def response(self, f_hz: ArrayLike, theta: ArrayLike | None = None) -> ComplexArray:
        """G(j 2 pi f) in unit_out/unit_in, shape of f_hz."""
        return RESPONSES[self.kind](self.theta_array if theta is None else theta, f_hz)

    def jacobian(self, f_hz: ArrayLike) -> ComplexArray:
        """dG/dtheta at theta, shape (n_f, n_theta), central differences."""
        th = self.theta_array
        return numeric_jacobian(RESPONSES[self.kind], th, f_hz, typical=np.abs(th) + 1e-12)

    def response_std(self, f_hz: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Standard uncertainties of |G| (relative) and of its phase (rad) at f_hz, linear propagation."""
        G = self.response(f_hz)
        J = self.jacobian(f_hz)
        dlog = J / G[:, None]  # d ln G / d theta: real part -> relative magnitude, imaginary -> phase
        C = self.cov_array
        u_rel = np.sqrt(np.clip(np.einsum("ij,jk,ik->i", dlog.real, C, dlog.real), 0, None))
        u_ph = np.sqrt(np.clip(np.einsum("ij,jk,ik->i", dlog.imag, C, dlog.imag), 0, None))
        return u_rel, u_ph

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "names": list(self.names), "units": list(self.units),
                "theta": list(self.theta), "cov": [list(r) for r in self.cov],
                "calibrated_range_hz": list(self.calibrated_range_hz), "unit_in": self.unit_in,
                "unit_out": self.unit_out, "origin": self.origin, "assumptions": self.assumptions,
                "findings": [c.to_dict() for c in self.findings], "fit": self.fit}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Sensor:
        kind = str(d["kind"])
        if kind not in RESPONSES:
            raise BadInputError(f"unknown transducer model {kind!r} (known: {', '.join(RESPONSES)})")
        theta = tuple(float(v) for v in d["theta"])
        cov = tuple(tuple(float(v) for v in r) for r in d["cov"])
        if len(cov) != len(theta) or any(len(r) != len(theta) for r in cov):
            raise BadInputError("the transducer's covariance does not match its parameters")
        lo, hi = (math.nan if v is None else float(v) for v in d["calibrated_range_hz"])  # JSON null: unknown
        return cls(kind, tuple(d["names"]), tuple(d["units"]), theta, cov, (lo, hi), str(d.get("unit_in", "N")),
                   str(d.get("unit_out", "V")), str(d.get("origin", "")), dict(d.get("assumptions") or {}),
                   tuple(Check.from_dict(c) for c in d.get("findings") or ()), dict(d.get("fit") or {}))


def from_result(res: IdentificationResult, mounted_mass_kg: float, mounted_mass_std_kg: float = 0.0,
                origin: str = "") -> Sensor:
    """The transducer of an identified result carrying ``mounted_mass_kg`` (kg, with its standard
    uncertainty) in the application.  Refused: a model the compensation does not know (the paper's
    digital h1/h2 carry no masses: identify with fd or oe), parameters without a value, no covariance."""
    if not (math.isfinite(mounted_mass_kg) and mounted_mass_kg >= 0):
        raise BadInputError(f"mounted mass {mounted_mass_kg!r} kg: state a mass >= 0 kg")
    if not (math.isfinite(mounted_mass_std_kg) and mounted_mass_std_kg >= 0):
        raise BadInputError(f"mounted mass std {mounted_mass_std_kg!r} kg: state a value >= 0 kg")
    if res.model not in ("sdof", "coupled"):
        raise BadInputError(f"the result of model {res.model!r} carries no masses: a filter for another mounting "
                            "needs Eq. 9 or Eq. 8 (identify with --method fd or oe)")
    if res.covariance is None:
        raise BadInputError(f"the result {res.result_name} has no covariance: no uncertainty could be propagated")
    core = ("S", "k_f", "b_f") if res.model == "sdof" else ("S", "k_f", "b_f", "k_c", "b_c")
    findings: list[Check] = [Check(f.name, f.severity, f.step, f.message, f.values) for f in res.checks
                             if f.severity in ("warning", "refused")]
    fixed: dict[str, float] = {}
    bc = res.parameters.get("b_c")
    if res.model == "coupled" and (bc is None or bc.value is None or "b_c" not in res.covariance.names):
        # the coupling's damping hardly shows below the coupling's resonance: a calibration up to a few
        # hundred hertz leaves it undetermined; the filter then assumes none, and says so
        fixed["b_c"] = 0.0
        findings.append(Check("coupling_damping_conditional", Severity.WARNING, None,
                              "the calibration does not determine the coupling's damping b_c"
                              f"{' (' + bc.reason + ')' if bc is not None and bc.reason else ''}: the filter "
                              "takes b_c = 0 N*s/m as exact and is conditional on it", {"b_c_N_s_per_m": 0.0}))
    missing = [n for n in core if n not in fixed and (res.parameters.get(n) is None or res.parameters[n].value is None)]
    if missing or any(n not in res.covariance.names for n in core if n not in fixed):
        raise BadInputError(f"the result {res.result_name} does not determine {', '.join(missing or core)}: "
                            "no filter can be built on it")
    idx = [res.covariance.names.index(n) if n not in fixed else -1 for n in core]
    cov_core = np.zeros((len(core), len(core)))
    known = [i for i, j in enumerate(idx) if j >= 0]
    cov_core[np.ix_(known, known)] = res.covariance.array[np.ix_([idx[i] for i in known], [idx[i] for i in known])]
    theta_core = np.array([fixed[n] if n in fixed else float(res.parameters[n].value)  # type: ignore[arg-type]
                           for n in core])
    em, lm = res.assumptions.end_mass, res.assumptions.load_mass
    m_e = json_float(res.extra, "m_e_kg", 0.0 if em is None else em.value or 0.0)
    m_l_cal = json_float(res.extra, "m_l_kg", 0.0 if lm is None else lm.value or 0.0)
    u_me = None if em is None else em.std
    em_source = em.source if em is not None and em.source else ""
    n = len(core)
    cov = np.zeros((n + 2, n + 2))
    cov[:n, :n] = cov_core
    if u_me is not None and res.model == "sdof":
        u_me = float(u_me)
        g = np.array([-theta_core[0], theta_core[1], theta_core[2]]) / (m_e + m_l_cal)
        cov[:n, n] = cov[n, :n] = g * u_me**2
        cov[n, n] = u_me**2
        me_note = (f"end mass m_e = {m_e:g} kg (std {u_me:.2g} kg, {em_source or 'stated'}), correlated "
                   "with S, k_f, b_f as the calibration's S M, k_f/M, b_f/M fix them")
    else:
        me_note = (f"end mass m_e = {m_e:g} kg taken as exact ({em_source or 'assumed'}): the filter is "
                   "conditional on it")
        findings.append(Check("end_mass_conditional", Severity.WARNING, None, me_note, {"m_e_kg": m_e}))
    cov[n + 1, n + 1] = mounted_mass_std_kg**2
    cov = 0.5 * (cov + cov.T)
    f_cal = json_floats(res.extra, "f_hz") if "f_hz" in res.extra else []
    rng = (min(f_cal), max(f_cal)) if f_cal else (math.nan, math.nan)
    units = (*tuple(res.parameters[n].unit if n in res.parameters else "N*s/m" for n in core), "kg", "kg")
    assumptions = {
        "model": f"{'Eq. 9 (stiff coupling)' if res.model == 'sdof' else 'Eq. 8 (finite coupling)'} of the "
                 f"{res.method} result, base at rest, the force acting on the mounted mass",
        "end_mass": me_note,
        "mounted_mass": f"m_l = {mounted_mass_kg:g} kg (std {mounted_mass_std_kg:.2g} kg), stated by the user",
        "calibration_load_mass_kg": m_l_cal,
        "chain": "the measurement chain of the application (conditioner, DAQ) is the calibration's: its gain "
                 "is in S; its own dynamics are not compensated",
    }
    return Sensor(res.model, (*core, "m_e", "m_l"), units, (*tuple(theta_core), m_e, mounted_mass_kg),
                  tuple(tuple(float(v) for v in r) for r in cov), rng, "N", "V",
                  origin or f"identified result {res.result_name}", assumptions, tuple(findings))


# ---------------------------------------------------------------------------------------------------------------
# A table of sinusoidal calibration values


@dataclass(frozen=True)
class Table:
    """Rows of a calibration table: frequency_hz (n,), complex response H (n,), standard
    uncertainties of |H| (absolute, or NaN) and of its phase (rad, or NaN)."""

    frequency_hz: FloatArray
    H: ComplexArray
    u_magnitude: FloatArray
    u_phase_rad: FloatArray


def read_table(text: str) -> Table:
    """Parse a CSV whose header names frequency_hz, magnitude, phase_deg or phase_rad and optionally
    u_magnitude, u_phase_deg or u_phase_rad (comment lines start with '#').  Refused with the
    offending line: a missing column, a value that is not a finite number, a frequency <= 0 or
    repeated, fewer than 4 rows or more than MAX_TABLE_ROWS."""
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise BadInputError("the calibration table is empty")
    reader = csv.reader(io.StringIO("\n".join(lines)))
    header = [h.strip().lower() for h in next(reader)]
    if "frequency_hz" not in header or "magnitude" not in header:
        raise BadInputError(f"the calibration table's header {header} must name frequency_hz and magnitude")
    phase_col = "phase_deg" if "phase_deg" in header else "phase_rad" if "phase_rad" in header else None
    if phase_col is None:
        raise BadInputError("the calibration table's header must name phase_deg or phase_rad")
    u_ph_col = "u_phase_deg" if "u_phase_deg" in header else "u_phase_rad" if "u_phase_rad" in header else None
    rows: list[list[float]] = []
    for i, row in enumerate(reader, start=2):
        if len(rows) >= MAX_TABLE_ROWS:
            raise BadInputError(f"the calibration table has more than {MAX_TABLE_ROWS} rows")
        if len(row) != len(header):
            raise BadInputError(f"calibration table line {i}: {len(row)} fields, the header has {len(header)}")
        try:
            vals = [float(v) for v in row]
        except ValueError:
            raise BadInputError(f"calibration table line {i}: not a number: {row}") from None
        if not all(math.isfinite(v) for v in vals):
            raise BadInputError(f"calibration table line {i}: a value is not finite: {row}")
        rows.append(vals)
    a = np.array(rows, dtype=float).reshape(-1, len(header))
    col = {h: a[:, j] for j, h in enumerate(header)}
    f = col["frequency_hz"]
    if len(f) < 4:
        raise BadInputError(f"the calibration table has {len(f)} rows: at least 4 are needed to fit a model")
    if np.any(f <= 0) or len(np.unique(f)) != len(f):
        raise BadInputError("the calibration table's frequencies must be > 0 Hz and distinct")
    ph = col[phase_col] * (np.pi / 180 if phase_col == "phase_deg" else 1.0)
    mag = col["magnitude"]
    if np.any(mag <= 0):
        raise BadInputError("the calibration table's magnitudes must be > 0")
    u_mag = col.get("u_magnitude", np.full(len(f), np.nan))
    u_ph = np.full(len(f), np.nan)
    if u_ph_col:
        u_ph = col[u_ph_col] * (np.pi / 180 if u_ph_col == "u_phase_deg" else 1.0)
    order = np.argsort(f)
    return Table(f[order], (mag * np.exp(1j * ph))[order], u_mag[order], u_ph[order])


def fit_table(table: Table, unit_in: str = "N", unit_out: str = "V", origin: str = "calibration table") -> Sensor:
    """Fit G(f) = S0 / (1 - (f/f0)^2 + 2 j delta f/f0) to a table (weighted least squares in Re, Im).

    Weights: per row the isotropic standard uncertainty sqrt((u_|H|^2 + (|H| u_phase)^2)/2) of Re H and
    Im H; the covariance is (J^T W J)^-1, scaled by chi^2/dof when that exceeds 1 (the scatter says the
    stated uncertainties are too small; a finding says so).  Without uncertainties the rows weigh alike
    and the covariance comes from the scatter (a finding says so)."""
    from scipy.optimize import least_squares

    f, H = table.frequency_hz, table.H
    has_u = bool(np.all(np.isfinite(table.u_magnitude)) and np.all(np.isfinite(table.u_phase_rad)))
    findings: list[Check] = []
    if has_u:
        sig = np.sqrt((table.u_magnitude**2 + (np.abs(H) * table.u_phase_rad) ** 2) / 2)
        if np.any(sig <= 0):
            raise BadInputError("the calibration table states a zero uncertainty: give u > 0 or none")
    else:
        sig = np.ones(len(f))
    mag = np.abs(H)
    S0 = float(mag[0])
    f0 = float(f[np.argmax(mag)]) if np.argmax(mag) > 0 else float(f[-1]) * 2
    x0 = np.array([S0, f0, 0.05])

    def resid(x: FloatArray) -> FloatArray:
        r = (_second_order(x, f) - H) / sig
        return np.concatenate([r.real, r.imag])

    sol = least_squares(resid, x0, x_scale=np.abs(x0), method="lm", xtol=1e-14, ftol=1e-14, max_nfev=20000)
    if not sol.success or not np.all(np.isfinite(sol.x)) or sol.x[1] <= 0:
        raise BadInputError(f"the second-order model does not fit the table ({sol.message})")
    x = sol.x
    J = sol.jac
    dof = max(2 * len(f) - 3, 1)
    chi2 = float(np.sum(sol.fun**2))
    try:
        cov = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        raise BadInputError("the table does not determine S0, f0 and delta (singular fit)") from None
    if not has_u:
        cov *= chi2 / dof
        findings.append(Check("table_without_uncertainty", Severity.WARNING, None,
                              "the table states no uncertainties: the model's covariance is taken from the fit's "
                              "scatter alone", {"residual_rms": math.sqrt(chi2 / (2 * len(f)))}))
    elif chi2 / dof > 1:
        cov *= chi2 / dof
        findings.append(Check("table_misfit", Severity.WARNING, None,
                              f"the model misfits the table beyond its stated uncertainties (chi^2/dof "
                              f"{chi2 / dof:.3g}): the covariance is scaled by it", {"chi2_per_dof": chi2 / dof}))
    x[2] = abs(x[2])
    res = _second_order(x, f) - H
    fit = {"frequency_hz": f.tolist(), "magnitude": mag.tolist(), "phase_rad": np.angle(H).tolist(),
           "residual_rel": (np.abs(res) / mag).tolist(), "chi2_per_dof": chi2 / dof if has_u else None,
           "weighted": has_u}
    names = ("S0", "f0", "delta")
    units = (f"{unit_out}/{unit_in}", "Hz", "1")
    assumptions = {"model": "second-order system G(f) = S0 / (1 - (f/f0)^2 + 2 j delta f/f0) fitted to the table",
                   "mounting": "the table's: a table carries no masses, so the filter is for the mounting it "
                               "was calibrated in"}
    return Sensor("second_order", names, units, tuple(float(v) for v in x),
                  tuple(tuple(float(v) for v in r) for r in 0.5 * (cov + cov.T)),
                  (float(f[0]), float(f[-1])), unit_in, unit_out, origin, assumptions, tuple(findings), fit)


def sensor_from_recording(path: str, mounted_mass_kg: float, mounted_mass_std_kg: float = 0.0,
                          result_name: str | None = None) -> Sensor:
    """The transducer of a recording's stored identification (``identify_fd_sdof`` etc.; the first
    of fd/oe with Eq. 9 or Eq. 8 unless ``result_name`` names one)."""
    from station.recording.stored import read_stored

    try:
        stored = read_stored(path)
    except (OSError, ValueError) as exc:
        raise BadInputError(f"{path}: not a readable recording ({exc})") from None
    names: Sequence[str] = [result_name] if result_name else [
        n for pref in ("identify_fd_", "identify_oe_") for n in sorted(stored) if n.startswith(pref)]
    for name in names:
        s = stored.get(name)
        if s is not None:
            res = IdentificationResult.from_dict(s.doc)
            if res.model in ("sdof", "coupled"):
                return from_result(res, mounted_mass_kg, mounted_mass_std_kg, f"{path}: {name}")
    raise BadInputError(f"{path}: no stored identification with Eq. 9 or Eq. 8 "
                        f"({'not found: ' + result_name if result_name else 'run station identify first'})")
